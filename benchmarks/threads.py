"""Thread settings on an idle and on a busy machine: each command with its default threads
(:mod:`datagen.threads`), with one thread, and with every usable CPU (torch's own default, which every
command used before), timed as a user runs it (a subprocess, start-up included).

    python -m benchmarks.threads            # about 15 minutes on 2 cores
    python -m benchmarks.threads --report-only

Busy means one spinning process per usable CPU, started before the command and kept running: the
cores are held by other work, as on a shared machine or a laptop running a build. The goal: the
default never more than 1.3x slower than the best setting, idle or busy. Writes
``benchmarks/reports/threads.{md,json}``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import HERE, REPORTS, machine_info, table, write_report
from datagen.threads import usable_cpus

OUT = HERE / "out" / "threads"
GOAL = 1.3
SPIN = "import time\nend = time.time() + {s}\nwhile time.time() < end: pass"


def _exe(command: str) -> str:
    return str(Path(sys.executable).parent / command)


def prepare(out: Path) -> None:
    """A small dataset, a manifest, a 2-step run and a photo for the timed commands (made once)."""
    out.mkdir(parents=True, exist_ok=True)
    steps = [
        ("data", [_exe("datagen"), "sample", "--out", "data", "--subjects", "16", "--resolution", "128",
                  "--defect-rate", "0", "--seed", "3", "--quiet"]),
        ("manifest.json", [_exe("label-tool"), "compile", "data", "--labels", "labels", "--test-count", "4",
                           "--out", "manifest.json"]),
        ("run", [_exe("panolam"), "train", "--data", "data", "--manifest", "manifest.json", "--config", "tiny",
                 "--steps", "2", "--out", "run", "--no-progress"]),
    ]
    (out / "labels").mkdir(exist_ok=True)
    for made, argv in steps:
        if not (out / made).exists():
            subprocess.run(argv, cwd=out, check=True, stdout=subprocess.DEVNULL)
    if not (out / "photo.png").exists():
        from datagen.dataset.shards import decode_sample, read_fields
        from PIL import Image
        key = json.loads((out / "data" / "index.json").read_text())["shards"][0]["subjects"][0]
        sample = decode_sample(key, read_fields(out / "data", 0, key), views=[0], depth=False)
        Image.fromarray(sample.rgb[0]).resize((512, 512)).save(out / "photo.png")


def commands(out: Path) -> dict[str, list[str]]:
    """What is timed: each command a user runs on a CPU, sized to a few seconds to a minute."""
    return {
        "datagen sample (8 subjects, 128 px)": [_exe("datagen"), "sample", "--out", "timed-sample", "--subjects", "8",
                                                "--resolution", "128", "--seed", "5", "--quiet"],
        "datagen shape (1 subject, 96^3)": [_exe("datagen"), "shape", "data", "--subject", "0", "--out",
                                            "timed-shape.ply", "--res", "96"],
        "label-tool auto (16 subjects)": [_exe("label-tool"), "auto", "data", "--quiet"],
        "panolam train (8 steps)": [_exe("panolam"), "train", "--data", "data", "--manifest", "manifest.json",
                                    "--config", "tiny", "--steps", "8", "--out", "timed-run", "--no-progress"],
        "panolam infer (1 photo, no crop)": [_exe("panolam"), "infer", "photo.png", "--ckpt", "run", "--no-crop",
                                             "--out", "timed-head.ply", "--views", "timed-views"],
        "panolam eval (4 subjects)": [_exe("panolam"), "eval", "--data", "data", "--manifest", "manifest.json",
                                      "--ckpt", "run", "--out", "timed-eval", "--no-baselines"],
    }


def timed(argv: list[str], out: Path, threads: int | None) -> float:
    """Seconds one command takes; ``threads``: OMP_NUM_THREADS for it (None: not set, the default)."""
    for leftover in ("timed-sample", "timed-run", "timed-eval", "timed-views", "timed-head.ply", "timed-shape.ply",
                     "data/preflags.json"):
        path = out / leftover
        shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    if threads is not None:
        env["OMP_NUM_THREADS"] = str(threads)
    t0 = time.perf_counter()
    subprocess.run(argv, cwd=out, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def measure(out: Path, repeats: int, conditions=("idle", "busy"), only=(), results: dict | None = None) -> dict:
    """Time the commands (those whose name contains one of ``only``, default all) under ``conditions``,
    the settings interleaved run by run (the median of ``repeats``), into ``results`` (a new report
    when None; the entries measured replace theirs)."""
    prepare(out)
    cpus = usable_cpus()
    settings = {"default": None, "1 thread": 1, f"{cpus} threads (torch's default)": cpus}
    results = results or {"usable_cpus": cpus, "load": {}, "seconds": {}}
    results.update(machine=machine_info())
    chosen = {k: v for k, v in commands(out).items() if not only or any(o in k for o in only)}
    for condition in conditions:
        spinners = [subprocess.Popen([sys.executable, "-c", SPIN.format(s=3600)]) for _ in range(cpus)] \
            if condition == "busy" else []
        try:
            time.sleep(2 if spinners else 0)
            results["load"][f"{condition} before"] = os.getloadavg()[0]
            for name, argv in chosen.items():
                runs = {label: [] for label in settings}
                for _ in range(repeats):  # interleaved, so a slow moment of the machine hits every setting
                    for label, threads in settings.items():
                        runs[label].append(timed(argv, out, threads))
                medians = {label: float(np.median(r)) for label, r in runs.items()}
                results["seconds"].setdefault(condition, {})[name] = medians
                results.setdefault("repeats", {}).setdefault(condition, {})[name] = repeats
                print(f"{condition:4s} {name:40s} " + ", ".join(f"{k} {v:.1f} s" for k, v in medians.items()),
                      flush=True)
            results["load"][f"{condition} after"] = os.getloadavg()[0]
        finally:
            for s in spinners:
                s.kill()
                s.wait()
    return results


def markdown(res: dict) -> str:
    m = res["machine"]
    lines = ["# Threads on an idle and a busy machine", "",
             f"{m['cpu_model']}, {res['usable_cpus']} usable CPUs, torch {m['torch']}, revision {m['git_revision']}, "
             f"{m['date']}. Each command as a subprocess (start-up included), the median of the runs given in the "
             "table, the settings interleaved. "
             f"Busy: {res['usable_cpus']} spinning processes held every CPU. 1-minute load average: "
             + ", ".join(f"{k} {v:.2f}" for k, v in res["load"].items()) + ".", ""]
    worst = 0.0
    for condition, by_command in res["seconds"].items():
        labels = list(next(iter(by_command.values())))
        rows = []
        for name, secs in by_command.items():
            best = min(secs.values())
            ratio = secs["default"] / best
            worst = max(worst, ratio)
            rows.append([name, *(f"{secs[k]:.1f}" for k in labels), f"{ratio:.2f}x",
                         res["repeats"][condition][name]])
        lines += [f"## {condition.capitalize()}", ""] + table(
            ["command", *(f"{k}, s" for k in labels), "default / best", "runs"], rows) + [""]
    lines += [f"Worst default against the best setting: **{worst:.2f}x** (goal at most {GOAL}x: "
              f"{'met' if worst <= GOAL else 'missed'})."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=OUT, help="work folder")
    parser.add_argument("--repeats", type=int, default=1, help="runs of each command and setting (the median)")
    parser.add_argument("--conditions", nargs="+", default=["idle", "busy"], choices=["idle", "busy"])
    parser.add_argument("--only", nargs="+", default=[], metavar="TEXT",
                        help="time only the commands whose name contains TEXT, replacing their entries in the "
                             "existing report")
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args(argv)
    stem = REPORTS / "threads"
    earlier = json.loads(stem.with_suffix(".json").read_text()) if stem.with_suffix(".json").exists() else None
    if args.report_only:
        res = earlier
    else:
        res = measure(args.out, args.repeats, args.conditions, args.only, earlier if args.only else None)
    write_report(stem, res, markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
