"""The training recipe as a new user meets it: 20 minutes (or 2 hours) of `tiny` on a CPU, then `panolam eval`.

    python -m benchmarks.panolam_recipe                       # ~40 min on 2 cores: data, train, eval, report
    python -m benchmarks.panolam_recipe --time-limit 7200 --steps 100000 --report panolam_recipe_2h \
        --out benchmarks/out/recipe-2h                        # the two-hour run
    python -m benchmarks.panolam_recipe --report-only --out DIR   # the report from a finished run in DIR

The commands are the README's recipe, run as a user runs them (subprocesses): a fresh procedural
dataset (360 protocol, 32 views of 128 px, no injected defects; by default 548 subjects of seed
61043, which nothing was tuned on), a manifest holding out ``--test-count`` subjects (48), ``panolam
train --config tiny --time-limit`` with ``--train-options`` (``--lr-floor 0.9``) and ``panolam eval --split
test`` (front view in; front, left, back and right out; the untrained model and the mean-colour
template as baselines; the gallery). The report gives the gains over both baselines on the full
frame and on the foreground, the steps the time bought, and the load average around training, the
one figure the machine's other work changes. Writes ``benchmarks/reports/panolam_recipe.{md,json}``
and ``panolam_recipe_gallery.png`` (``--report`` names them).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from benchmarks.common import HERE, REPORTS, machine_info, table, write_report
from datagen.files import atomic_write

OUT = HERE / "out" / "recipe"
GOAL_DB = 6.0  # full-frame PSNR gain over the untrained model the recipe should reach in 20 minutes
GOAL_NOVEL_FG_DB = 5.0  # novel-view foreground PSNR gain over the mean-colour template within 2 hours


def run(command: str, *argv: str, cwd: Path) -> None:
    """One of the project's console scripts (datagen, label-tool, panolam), from this Python's environment."""
    print("$", command, " ".join(argv), flush=True)
    subprocess.run([str(Path(sys.executable).parent / command), *argv], cwd=cwd, check=True)


SETTINGS = ("seed", "subjects", "test_count", "time_limit", "steps", "train_options")


def measure(args) -> dict:
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    # what this run is, so that --report-only reports it whatever the defaults are then
    atomic_write(out / "settings.json", json.dumps({k: getattr(args, k) for k in SETTINGS}).encode())
    # a dataset begun earlier is resumed (complete shards are skipped), so an interrupted generation is finished
    run("datagen", "sample", "--out", "data", "--subjects", str(args.subjects), "--resolution", "128",
        "--defect-rate", "0", "--seed", str(args.seed), "--workers", "2", "--quiet",
        *(["--resume"] if (out / "data" / "index.json").exists() else []), cwd=out)
    (out / "labels").mkdir(exist_ok=True)
    run("label-tool", "compile", "data", "--labels", "labels", "--test-count", str(args.test_count),
        "--out", "manifest.json", cwd=out)
    if (out / "runs").exists():
        shutil.rmtree(out / "runs")
    load = {"before_training": list(os.getloadavg())}
    run("panolam", "train", "--data", "data", "--manifest", "manifest.json", "--config", "tiny", "--out", "runs/r1",
        "--time-limit", str(args.time_limit), *(["--steps", str(args.steps)] if args.steps else []),
        *shlex.split(args.train_options), cwd=out)
    load["after_training"] = list(os.getloadavg())
    run("panolam", "eval", "--data", "data", "--manifest", "manifest.json", "--split", "test", "--ckpt", "runs/r1",
        cwd=out)
    (out / "load.json").write_text(json.dumps(load))
    return collect(out, args)


def collect(out: Path, args) -> dict:
    """The figures of a finished run in ``out`` (its eval.json, train.log, load.json and settings.json;
    a run from before settings.json is taken to have the settings in ``args``)."""
    if (out / "settings.json").exists():
        args = argparse.Namespace(**json.loads((out / "settings.json").read_text()))
    ev = json.loads((out / "runs" / "r1" / "eval-test" / "eval.json").read_text())
    steps = [line for line in (out / "runs" / "r1" / "train.log").read_text().splitlines() if line.startswith("step ")]
    load = json.loads((out / "load.json").read_text()) if (out / "load.json").exists() else {}
    models = {"this model": ev, **{f"baseline: {k.replace('_', ' ')}": v for k, v in ev["baselines"].items()}}
    figures = {name: {view: {m: r["per_view"][view][m] for m in ("psnr", "psnr_fg", "ssim", "ssim_fg")}
                      for view in ("all", "novel")} for name, r in models.items()}
    return {"machine": machine_info(), "seed": args.seed, "subjects": args.subjects, "test_count": args.test_count,
            "time_limit_s": args.time_limit, "steps": args.steps, "train_options": args.train_options,
            "steps_done": len(steps), "train_psnr_last_200": _mean_batch_psnr(steps[-200:]),
            "last_step": steps[-1] if steps else None,
            "load_average": load, "figures": figures, "eval_subjects": ev["subjects"],
            "reconstruct_s_median": ev["reconstruct_s_median"]}


def _mean_batch_psnr(step_lines: list[str]) -> float | None:
    """The mean training-batch PSNR (dB, the renders at the training resolution) of train.log's step lines."""
    values = [float(m.group(1)) for line in step_lines if (m := re.search(r"PSNR ([-\d.]+) dB", line))]
    return sum(values) / len(values) if values else None


def _duration(seconds: float) -> str:
    return f"{seconds / 3600:g} hours" if seconds >= 3600 else f"{seconds / 60:g} minutes"


def _verdict(gain: float, goal: float, time_limit_s: float, budget_s: float) -> str:
    if time_limit_s > budget_s:
        return "not comparable: this run trained longer"
    return "met" if gain >= goal else "missed"


def markdown(res: dict) -> str:
    f = res["figures"]
    ours, untrained, template = f["this model"], f["baseline: untrained"], f["baseline: mean colour template"]
    gain = ours["all"]["psnr"] - untrained["all"]["psnr"]
    novel = ours["novel"]["psnr_fg"] - template["novel"]["psnr_fg"]
    rows = [[name, *(f"{v[view][m]:.2f}" if "psnr" in m else f"{v[view][m]:.3f}"
                     for view, m in (("all", "psnr"), ("all", "psnr_fg"), ("novel", "psnr"), ("novel", "psnr_fg"),
                                     ("novel", "ssim_fg")))] for name, v in f.items()]
    load = res["load_average"]
    lines = [
        f"# The training recipe in {_duration(res['time_limit_s'])} on a CPU", "",
        f"Machine: {res['machine']['cpu_model']}, {res['machine']['usable_cpus']} usable CPUs, torch "
        f"{res['machine']['torch']}; report written {res['machine']['date']}. 1-minute load average "
        f"{load.get('before_training', ['?'])[0]} before training and {load.get('after_training', ['?'])[0]} after "
        "(the run itself keeps about 2 busy).", "",
        "```",
        f"datagen sample --out data --subjects {res['subjects']} --resolution 128 --defect-rate 0 --seed {res['seed']} "
        "--workers 2",
        f"label-tool compile data --labels labels --test-count {res['test_count']} --out manifest.json",
        f"panolam train --data data --manifest manifest.json --config tiny --out runs/r1 --time-limit {res['time_limit_s']}"
        + (f" --steps {res['steps']}" if res.get("steps") else "")
        + (f" {res['train_options']}" if res.get("train_options") else ""),
        "panolam eval --data data --manifest manifest.json --split test --ckpt runs/r1",
        "```", "",
        f"Training did {res['steps_done']} steps in the time limit (at most {res.get('steps') or 2000:,}; the "
        f"learning rate's decay is fitted to the time limit; `{res['last_step']}`)"
        + (f"; its training batches scored {res['train_psnr_last_200']:.2f} dB over the last 200 steps (full "
           "frame at the training resolution)" if res.get("train_psnr_last_200") is not None else "")
        + ". Evaluated on "
        f"{res['eval_subjects']} held-out subjects: the front view in, the front, left, back and right views out at "
        "128 px; *novel* is left, back and right; fg is the foreground "
        "(target or render alpha >= 0.5).", "",
        *table(["model", "all PSNR dB", "all PSNR fg dB", "novel PSNR dB", "novel PSNR fg dB", "novel SSIM fg"], rows),
        "",
        f"Full-frame PSNR over the untrained model: **{gain:+.2f} dB** (goal {GOAL_DB:+.1f} dB in 20 minutes: "
        f"{_verdict(gain, GOAL_DB, res['time_limit_s'], 1200)}). Novel-view foreground PSNR over the mean-colour "
        f"template: **{novel:+.2f} dB** (goal {GOAL_NOVEL_FG_DB:+.1f} dB within 2 hours: "
        f"{_verdict(novel, GOAL_NOVEL_FG_DB, res['time_limit_s'], 7200)}). Paired per-subject gains with their "
        "standard errors are in the run's eval.md.", "",
        "![held-out subjects: the input, the reconstruction and the truth from the front, left, back and right]"
        "(panolam_recipe_gallery.png)", "",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=OUT, help="work folder (dataset, run)")
    parser.add_argument("--subjects", type=int, default=548)
    parser.add_argument("--test-count", type=int, default=48)
    parser.add_argument("--seed", type=int, default=61043)
    parser.add_argument("--time-limit", type=int, default=1200, help="seconds of training")
    parser.add_argument("--steps", type=int, help="panolam train --steps (default: not passed, so 2,000)")
    parser.add_argument("--train-options", default="--lr-floor 0.9",
                        help="more panolam train options, as one string ('' for none)")
    parser.add_argument("--report", default="panolam_recipe", help="report name under benchmarks/reports")
    parser.add_argument("--report-only", action="store_true", help="the report from the run already in --out")
    args = parser.parse_args(argv)
    res = collect(args.out, args) if args.report_only else measure(args)
    write_report(REPORTS / args.report, res, markdown(res).replace("panolam_recipe_gallery", f"{args.report}_gallery"))
    shutil.copyfile(args.out / "runs" / "r1" / "eval-test" / "gallery.png", REPORTS / f"{args.report}_gallery.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
