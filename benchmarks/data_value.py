"""What data buys a model: the paper's dataset-scale and curation claims, measured on a CPU budget.

    python -m benchmarks.data_value --out /work/data-value   # about a working day on 2 cores; resumes
    python -m benchmarks.data_value --out DIR --arms scale-48 scale-3000   # some arms (their data first)
    python -m benchmarks.data_value --out DIR --report-only  # the report from what is finished in DIR

Every arm trains `tiny` for the same number of steps with the same batch (equal compute whatever the
machine's load), with the README's commands run as a user runs them (subprocesses), and is scored by
`panolam eval` on one held-out set drawn here from a seed nothing was tuned on (clean: no injected
defects), front view in, front/left/back/right out; *novel* is left, back and right.

Arms:
  scale-N        the first N subjects of one clean dataset (seed POOL_SEED); N in ``--scale``. The
                 smallest arm has a dataset of its own, generated with the same seed, so it holds the
                 same people as the first subjects of the largest: a larger arm adds people.
                 Beside held-out, each arm is scored the same way on its first 48 training subjects
                 (the memorization gap) and its train-batch PSNR (the log's last 100 steps) is given.
  curation-*     one dataset with ``--defect-rate`` injected defects (seed ``--defect-seed``):
                 ``as-is`` all of it; ``auto`` without what `label-tool auto` flags (no person);
                 ``truth`` without the injected truth; ``random`` without a random set of the size
                 ``auto`` removed, which separates "fewer subjects" from "cleaner subjects".

Resuming: datasets are written with `datagen sample --resume`, training with `panolam train
--resume`, and a finished stage is not redone (its output is its marker), so the study can be run
in pieces and killed at any moment. An arm finished earlier whose folder is gone (moved, deleted,
another machine) keeps its figures from the last report written with the same settings and seeds,
and the report says so; each arm names the hosts and code it trained on. Writes
``benchmarks/reports/data_value.{md,json}``, the plot ``data_value_scale.png`` and one gallery per
arm (``data_value_<arm>.png``).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import REPORTS, injected_defects, machine_info, pyplot, table, write_report
from datagen.files import atomic_write

HELD_OUT_SEED, POOL_SEED, DEFECT_SEED = 7411, 5303, 6197
# DEFECT_SEED's dataset later chose washed_out's feature (benchmarks.preflags_quality.TUNING_SEEDS): the
# curation arms reported were cut by label-tool auto as it was before (137 flagged, 132 of them defective);
# today's detectors flag 146 there (140 defective), so a fresh auto arm on this seed would be tuned on it.
RESOLUTION = 128  # the encoder's input size (tiny): training resizes targets to 64 px, eval compares at 128
COLOUR_SUBJECTS = 16  # held-out dataset subjects not scored: they give the mean-colour template its colour
TRAIN_EVAL_SUBJECTS = 48  # training subjects scored like the held-out ones (the memorization gap)
LOG_TAIL = 100  # train-batch PSNR: mean of the log's last steps
CURATION_ARMS = ("as-is", "auto", "truth", "random")
GOAL_SCALE_DB = 1.5  # the largest scale arm over 48 subjects, held-out novel foreground PSNR


def console(command: str, *argv: str, cwd: Path, log: Path | None = None) -> float:
    """Run one of the project's console scripts (datagen, label-tool, panolam) from this Python's
    environment, its output appended to ``log`` when given; returns its peak resident memory (MiB)."""
    print("$", command, " ".join(argv), flush=True)
    with open(log, "a") if log is not None else open(os.devnull, "w") as f:
        out = None if log is None else f
        proc = subprocess.Popen([str(Path(sys.executable).parent / command), *argv], cwd=cwd, stdout=out,
                                stderr=None if log is None else subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, [command, *argv])
    return usage.ru_maxrss / 1024


class Study:
    """The study's folder: datasets, manifests and runs, each stage done once."""

    held_out_seed, pool_seed = HELD_OUT_SEED, POOL_SEED

    def __init__(self, args):
        self.args, self.out = args, args.out.resolve()
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "labels").mkdir(exist_ok=True)  # no reviewer: every verdict comes from the study

    # -- data --------------------------------------------------------------------------------------
    def dataset(self, name: str, subjects: int, seed: int, defect_rate: float = 0.0) -> Path:
        root = self.out / name
        if not _complete(root):
            console("datagen", "sample", "--out", name, "--subjects", str(subjects), "--resolution", str(RESOLUTION),
                    "--defect-rate", str(defect_rate), "--seed", str(seed), "--workers", "auto", "--quiet",
                    *(["--resume"] if (root / "index.json").exists() else []), cwd=self.out)
        return root

    def held_out(self) -> tuple[Path, Path]:
        root = self.dataset("held-out", self.args.held_out + COLOUR_SUBJECTS, self.held_out_seed)
        manifest = self.out / "manifests" / "held-out.json"
        if not manifest.exists():
            console("label-tool", "compile", "held-out", "--labels", "labels", "--test-count",
                    str(self.args.held_out), "--out", str(manifest), cwd=self.out)
        return root, manifest

    def arm_data(self, arm: str) -> tuple[Path, list[str]]:
        """The dataset of ``arm`` and the subjects it trains on (in dataset order)."""
        kind, _, what = arm.partition("-")
        if kind == "scale":
            n, largest = int(what), max(self.args.scale)
            smallest = n == min(self.args.scale)  # its own small dataset, so it need not wait for the largest
            root = self.dataset(f"pool-{n if smallest else largest}", n if smallest else largest, self.pool_seed)
            return root, _subjects(root)[:n]
        root = self.dataset("defects", self.args.curation_subjects, DEFECT_SEED, self.args.defect_rate)
        everyone = _subjects(root)
        if what == "as-is":
            return root, everyone
        if what == "truth":
            truth = injected_defects(root)
            return root, [s for s in everyone if not truth[s]]
        flagged = self.flagged(root)
        if what == "auto":
            return root, [s for s in everyone if s not in flagged]
        rng = np.random.default_rng([DEFECT_SEED, len(flagged)])
        dropped = {everyone[i] for i in rng.choice(len(everyone), len(flagged), replace=False)}
        return root, [s for s in everyone if s not in dropped]

    def detect(self, root: Path) -> dict[str, list[str]]:
        """subject -> the detectors that flag it, each at its own threshold (no per-dataset calibration, which
        would flag the same share of any dataset), so that datasets can be compared."""
        report = root / "preflags.json"
        if not report.exists():
            console("label-tool", "auto", str(root), "--quiet", "--false-alarm-rate", "0", cwd=self.out)
        return {r["subject"]: r["flags"] for r in json.loads(report.read_text())["subjects"]}

    def flagged(self, root: Path) -> set[str]:
        """Subjects `label-tool auto` flags (run once; its report is the dataset's preflags.json)."""
        report = root / "preflags.json"
        if not report.exists():
            console("label-tool", "auto", root.name, "--quiet", "--workers", str(os.cpu_count() or 1), cwd=self.out)
        return {r["subject"] for r in json.loads(report.read_text())["subjects"] if r["flags"]}

    def manifest(self, name: str, root: Path, train: list[str], test: list[str] = ()) -> Path:
        """A manifest of ``root`` accepting ``train`` (split train) and ``test`` (split test); the rest rejected."""
        from labeling_tool.compiler import compile_manifest, write_manifest
        path = self.out / "manifests" / f"{name}.json"
        if not path.exists():
            m = compile_manifest(root, self.out / "labels", unreviewed="accept", test_count=0)
            train, test = set(train), set(test)
            for row in m["subjects"]:
                s = row["subject"]
                row["verdict"] = "accepted" if s in train or s in test else "rejected"
                row["split"] = "test" if s in test else "train" if s in train else None
                row["reasons"] = [] if row["verdict"] == "accepted" else ["not in this arm"]
            write_manifest(m, path)
        return path

    # -- training and evaluation -------------------------------------------------------------------------
    def training(self, arm: str) -> tuple[int, list[str]]:
        """The steps of ``arm`` and the `panolam train` options a new run of it starts with: here the study's
        steps and `tiny` for every arm."""
        return self.args.steps, ["--config", "tiny"]

    def run_arm(self, arm: str) -> None:
        """Train ``arm`` on its data (:meth:`arm_data`) as :meth:`training` says, with the study's batch, then
        score it."""
        root, train = self.arm_data(arm)
        held_out, held_out_manifest = self.held_out()
        manifest = self.manifest(arm, root, train)
        run = self.out / "runs" / arm
        steps, options = self.training(arm)
        if _steps_done(run) < steps:
            resume = ["--resume", str(run)] if (run / "checkpoint.pt").exists() else ["--out", str(run), *options]
            record_host(run)
            peak = console("panolam", "train", "--data", str(root), "--manifest", str(manifest), "--steps", str(steps),
                           "--batch-size", str(self.args.batch_size), "--no-progress", "--checkpoint-every", "50",
                           *resume, cwd=self.out, log=self.out / f"{arm}.log")
            memory = run / "peak-rss-mib.json"  # the largest of the training processes (one per resume)
            earlier = json.loads(memory.read_text()) if memory.exists() else 0.0
            memory.write_text(json.dumps(max(earlier, peak)))
        if not (run / "eval-held-out" / "eval.json").exists():
            console("panolam", "eval", "--data", str(held_out), "--manifest", str(held_out_manifest), "--ckpt", str(run),
                    "--out", str(run / "eval-held-out"), cwd=self.out, log=self.out / f"{arm}.log")
        renders = run / "renders-held-out"
        if not (renders / "preflags.json").exists():
            shutil.rmtree(renders, ignore_errors=True)  # a partial one from an interrupted eval
            console("panolam", "eval", "--data", str(held_out), "--manifest", str(held_out_manifest), "--ckpt", str(run),
                    "--out", str(run / "eval-renders"), "--no-baselines", "--no-faces", "--gallery", "0",
                    "--renders", str(renders), cwd=self.out, log=self.out / f"{arm}.log")
            self.detect(renders)
        if not (run / "eval-train" / "eval.json").exists():
            seen = self.manifest(f"{arm}-train-eval", root, [], train[:TRAIN_EVAL_SUBJECTS])
            console("panolam", "eval", "--data", str(root), "--manifest", str(seen), "--ckpt", str(run),
                    "--out", str(run / "eval-train"), "--no-baselines", "--no-faces", "--gallery", "0",
                    cwd=self.out, log=self.out / f"{arm}.log")


def host_label(m: dict) -> str:
    """The host and code of a :func:`machine_info`: 'AMD EPYC (family 26 model 2, AVX512), revision 5df2a21'."""
    cpu = ", ".join(v for v in (m.get("cpu_family_model"), m.get("cpu_capability")) if v)
    return f"{m['cpu_model']}{f' ({cpu})' if cpu else ''}, revision {m['git_revision'].split()[0][:7]}"


def record_host(run: Path) -> None:
    """Add the host and code of a training process about to start to ``run/hosts.json`` (one line per process
    that trained, a resume included): arms trained on different hosts or code say so in the report."""
    path = run / "hosts.json"
    hosts = json.loads(path.read_text()) if path.exists() else []
    run.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps([*hosts, {"host": host_label(machine_info()), "from_step": _steps_done(run)}],
                                  indent=1).encode())


def previous_report(report: Path, settings: dict, seeds: dict) -> dict | None:
    """The study's last report (``report``) when it was written with the same ``seeds`` and the same values of
    ``settings`` (a subset of the study's settings), else None."""
    old = json.loads(report.read_text()) if report.exists() else None
    if old is None or old["seeds"] != seeds or any(old["settings"].get(k) != v for k, v in settings.items()):
        return None
    return old


def carry(found: dict, wanted: list[str], old: dict | None) -> dict:
    """``found`` (figures of the arms finished in the study's folder) and, for each arm of ``wanted`` that is not
    there, its figures from ``old`` (:func:`previous_report`), in ``wanted`` order: a folder lost or moved keeps
    the arms it finished. A carried arm says when that report was written (``carried_from``)."""
    arms = dict(found)
    for a in wanted:
        if a not in arms and old and a in old["arms"]:
            arms[a] = dict(old["arms"][a], carried_from=old["machine"]["date"])
    return {a: arms[a] for a in wanted if a in arms}


def _complete(root: Path) -> bool:
    """Every shard of the dataset at ``root`` has its sidecar (written last)."""
    try:
        index = json.loads((root / "index.json").read_text())
    except OSError:
        return False
    return all((root / f"{s['name']}.json").exists() for s in index["shards"])


def _subjects(root: Path) -> list[str]:
    return [s for shard in json.loads((root / "index.json").read_text())["shards"] for s in shard["subjects"]]


STEP_LINE = re.compile(r"step (\d+): .*PSNR ([-\d.]+) dB, .*, ([\d.]+) s/step(?:, ([\d.]+) s data)?")


def _log_steps(run: Path) -> list[dict]:
    """The step lines of a run's train.log as {step, psnr (train batch, dB), seconds, data_s}."""
    log = run / "train.log"
    found = (STEP_LINE.match(line) for line in (log.read_text().splitlines() if log.exists() else []))
    return [{"step": int(m[1]), "psnr": float(m[2]), "seconds": float(m[3]),
             "data_s": float(m[4]) if m[4] else math.nan} for m in found if m]


def _steps_done(run: Path) -> int:
    rows = _log_steps(run)
    return rows[-1]["step"] if rows else 0


# -- figures ---------------------------------------------------------------------------------------------
def per_subject(ev: dict, metric: str = "psnr_fg") -> dict[str, float]:
    """subject -> mean ``metric`` over the novel views (left, back, right) of an eval.json."""
    values = {}
    for row in ev["rows"]:
        if row["view"] != "front" and row.get(metric) is not None and not math.isnan(row[metric]):
            values.setdefault(row["subject"], []).append(row[metric])
    return {k: float(np.mean(v)) for k, v in values.items()}


def paired(a: dict[str, float], b: dict[str, float]) -> dict:
    """Mean of a - b over the subjects both have, with its 95 % interval (Student's t)."""
    from scipy.stats import t
    d = np.array([a[k] - b[k] for k in a if k in b])
    if len(d) < 2:
        return {"mean": float(d.mean()) if len(d) else math.nan, "ci95": [math.nan, math.nan], "n": len(d)}
    half = float(t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d)))
    return {"mean": float(d.mean()), "ci95": [float(d.mean()) - half, float(d.mean()) + half], "n": len(d)}


def _report_order(arm: str) -> tuple[int, int]:
    """Scale arms by their number of subjects, then the curation arms in CURATION_ARMS order."""
    kind, _, what = arm.partition("-")
    return (0, int(what)) if kind == "scale" else (1, CURATION_ARMS.index(what))


def arm_figures(study: Study, arm: str) -> dict | None:
    """The figures of one arm whose held-out evaluation is done (None before)."""
    run = study.out / "runs" / arm
    ev_path = run / "eval-held-out" / "eval.json"
    if not ev_path.exists():
        return None
    ev = json.loads(ev_path.read_text())
    train_ev = json.loads((run / "eval-train" / "eval.json").read_text()) \
        if (run / "eval-train" / "eval.json").exists() else None
    steps = _log_steps(run)
    tail = steps[-LOG_TAIL:]
    manifest = json.loads((study.out / "manifests" / f"{arm}.json").read_text())
    return {
        "train_subjects": sum(1 for r in manifest["subjects"] if r["split"] == "train"),
        "steps": steps[-1]["step"] if steps else 0,
        "step_s_median": float(np.median([r["seconds"] for r in steps])) if steps else None,
        "data_s_median": float(np.nanmedian([r["data_s"] for r in steps])) if steps else None,
        "train_batch_psnr": float(np.mean([r["psnr"] for r in tail])) if tail else None,
        "train_peak_rss_mib": json.loads((run / "peak-rss-mib.json").read_text())
        if (run / "peak-rss-mib.json").exists() else None,
        "held_out": {v: {m: ev["per_view"][v][m] for m in ("psnr", "psnr_fg", "ssim", "ssim_fg", "lpips")}
                     for v in ("all", "novel")},
        "train_subjects_eval": None if train_ev is None else
        {v: {m: train_ev["per_view"][v][m] for m in ("psnr", "psnr_fg", "ssim_fg")} for v in ("all", "novel")},
        "per_subject_novel_psnr_fg": per_subject(ev),
        "per_subject_novel_ssim_fg": per_subject(ev, "ssim_fg"),
        "template_per_subject_novel_psnr_fg": per_subject(ev["baselines"]["mean_colour_template"])
        if "baselines" in ev else None,
        "csim": ev["per_view"]["front"].get("csim"),
        "defects": _defect_rates(run / "renders-held-out" / "preflags.json", set(per_subject(ev))),
        "hosts": json.loads((run / "hosts.json").read_text()) if (run / "hosts.json").exists() else None,
    }


STUDY_SETTINGS = ("steps", "batch_size", "held_out", "curation_subjects", "defect_rate")  # what arms must share


def collect(study: Study) -> dict:
    """The figures of every finished arm: in the study's folder, or carried from the last report."""
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(study.args).items()}
    seeds = {"held_out": study.held_out_seed, "pool": study.pool_seed, "defects": DEFECT_SEED}
    old = previous_report(REPORTS / f"{study.args.report}.json", {k: settings[k] for k in STUDY_SETTINGS}, seeds)
    wanted = sorted(study.args.arms, key=_report_order)
    arms = carry({a: f for a in wanted if (f := arm_figures(study, a))}, wanted, old)
    comparisons = {}
    scale = [a for a in arms if a.startswith("scale-")]  # by size: arms are in _report_order
    for a in scale[1:]:
        comparisons[f"{a} - {scale[0]}"] = compare(arms[a], arms[scale[0]])
    for smaller, larger in zip(scale[1:], scale[2:]):  # each size against the one below it
        comparisons[f"{larger} - {smaller}"] = compare(arms[larger], arms[smaller])
    for a, b in (("auto", "as-is"), ("auto", "random"), ("truth", "as-is"), ("truth", "random"), ("random", "as-is")):
        if f"curation-{a}" in arms and f"curation-{b}" in arms:
            comparisons[f"curation-{a} - curation-{b}"] = compare(arms[f"curation-{a}"], arms[f"curation-{b}"])
    for name, r in arms.items():
        if r["template_per_subject_novel_psnr_fg"]:
            comparisons[f"{name} - mean-colour template"] = {
                "novel_psnr_fg": paired(r["per_subject_novel_psnr_fg"], r["template_per_subject_novel_psnr_fg"])}
    truth_flags = study.out / "held-out" / "preflags.json"
    if arms and not truth_flags.exists() and _complete(study.out / "held-out"):
        study.detect(study.out / "held-out")
    held_out = set(next(iter(arms.values()))["per_subject_novel_psnr_fg"]) if arms else set()
    return {"machine": machine_info(),
            "held_out_defects": _defect_rates(truth_flags, held_out) or (old and old["held_out_defects"]),
            "settings": settings, "seeds": seeds, "arms": arms, "comparisons": comparisons,
            "curation": curation_counts(study, old and old["curation"])}


def _defect_rates(report: Path, subjects: set[str]) -> dict | None:
    """Share of ``subjects`` that any detector flags in a pre-flags report, and the count per detector."""
    if not report.exists():
        return None
    rows = [r for r in json.loads(report.read_text())["subjects"] if r["subject"] in subjects]
    per = {}
    for r in rows:
        for f in r["flags"]:
            per[f] = per.get(f, 0) + 1
    return {"subjects": len(rows), "flagged": sum(1 for r in rows if r["flags"]), "per_detector": per}


def compare(a: dict, b: dict) -> dict:
    """Paired differences a - b of two arms' figures: novel-view foreground PSNR and SSIM."""
    return {"novel_psnr_fg": paired(a["per_subject_novel_psnr_fg"], b["per_subject_novel_psnr_fg"]),
            "novel_ssim_fg": paired(a["per_subject_novel_ssim_fg"], b["per_subject_novel_ssim_fg"])}


def _kinds(defects) -> dict[str, int]:
    """{defect class: subjects carrying it} of an iterable of per-subject defect lists."""
    kinds = {}
    for d in defects:
        for k in d:
            kinds[k] = kinds.get(k, 0) + 1
    return dict(sorted(kinds.items()))


def curation_counts(study: Study, old: dict | None = None) -> dict | None:
    """How many subjects the curation dataset has, how many carry injected defects, what auto flagged, and
    what each curation arm whose manifest is written trains on (subjects, defective ones, by class); arms
    with no manifest here keep what ``old`` (the last report's counts) says when the dataset counts agree."""
    root = study.out / "defects"
    if not (root / "preflags.json").exists():
        return old
    truth = injected_defects(root)
    flagged = {r["subject"] for r in json.loads((root / "preflags.json").read_text())["subjects"] if r["flags"]}
    bad = {s for s, d in truth.items() if d}
    training = {}
    for arm in CURATION_ARMS:
        manifest = study.out / "manifests" / f"curation-{arm}.json"
        if manifest.exists():
            train = [r["subject"] for r in json.loads(manifest.read_text())["subjects"] if r["split"] == "train"]
            training[f"curation-{arm}"] = {"subjects": len(train), "defective": sum(1 for s in train if truth[s]),
                                           "defect_types": _kinds(truth[s] for s in train)}
    counts = {"subjects": len(truth), "defective": len(bad), "flagged": len(flagged),
              "flagged_defective": len(flagged & bad), "defect_types": _kinds(truth.values())}
    if old and all(old[k] == v for k, v in counts.items()):
        training = {f"curation-{a}": training.get(f"curation-{a}") or old["training"][f"curation-{a}"]
                    for a in CURATION_ARMS if f"curation-{a}" in training or f"curation-{a}" in old["training"]}
    return dict(counts, training=training)


# -- the report ---------------------------------------------------------------------------------------------
def ci_text(c: dict) -> str:
    """A paired difference as '+0.80 dB [+0.39, +1.22] (n=48)'."""
    return f"{c['mean']:+.2f} dB [{c['ci95'][0]:+.2f}, {c['ci95'][1]:+.2f}] (n={c['n']})"


def plot(res: dict, path: Path) -> bool:
    plt = pyplot()
    scale = sorted(((int(a.split("-")[1]), r) for a, r in res["arms"].items() if a.startswith("scale-")))
    if plt is None or not scale:
        return False
    n = [s for s, _ in scale]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(n, [r["held_out"]["novel"]["psnr_fg"] for _, r in scale], "o-", label="held-out subjects")
    if all(r["train_subjects_eval"] for _, r in scale):
        ax.plot(n, [r["train_subjects_eval"]["novel"]["psnr_fg"] for _, r in scale], "s--",
                label=f"its first {TRAIN_EVAL_SUBJECTS} training subjects")
    ax.set_xscale("log")
    ax.set_xlabel("training subjects")
    ax.set_ylabel("novel-view foreground PSNR (dB)")
    ax.set_title(f"tiny, {res['settings']['steps']} steps of batch {res['settings']['batch_size']}")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def markdown(res: dict, plotted: bool) -> str:
    s, arms = res["settings"], res["arms"]
    m = res["machine"]
    lines = ["# What data buys: dataset scale and curation", "",
             f"Machine: {m['cpu_model']}, {m['usable_cpus']} usable CPUs, torch {m['torch']}, revision "
             f"{m['git_revision']}; report written {m['date']}, 1-minute load average "
             f"{m['load_average'][0]:.2f} then. Seeds: held-out {res['seeds']['held_out']} ({s['held_out']} clean "
             f"subjects), pool {res['seeds']['pool']}, curation {res['seeds']['defects']} "
             f"({s['curation_subjects']} subjects, defect rate {s['defect_rate']}). Every arm: `tiny`, "
             f"{s['steps']} steps of batch {s['batch_size']}; held-out scores: novel views (left, back, right), "
             "foreground PSNR/SSIM, 128 px; intervals are 95 % (Student's t over paired subjects).", "",
             f"Arms finished: {len(arms)} of {len(s['arms'])} ({', '.join(arms) or 'none'}).", "",
             *trained_on(arms)]
    rows = []
    for name, r in arms.items():
        tr = r["train_subjects_eval"]
        rows.append([name, r["train_subjects"], r["steps"], f"{r['train_batch_psnr']:.2f}",
                     f"{tr['novel']['psnr_fg']:.2f}" if tr else "-", f"{r['held_out']['novel']['psnr_fg']:.2f}",
                     f"{r['held_out']['novel']['ssim_fg']:.3f}", f"{r['held_out']['all']['psnr']:.2f}",
                     f"{r['step_s_median']:.2f}", f"{r['data_s_median']:.3f}",
                     f"{r['train_peak_rss_mib']:.0f}" if r["train_peak_rss_mib"] else "-"])
    lines += table(["arm", "training subjects", "steps", "train-batch PSNR dB (64 px)",
                    f"first {TRAIN_EVAL_SUBJECTS} training subjects, novel PSNR fg dB", "held-out novel PSNR fg dB",
                    "held-out novel SSIM fg", "held-out all PSNR dB", "s/step (median)", "data s/step (median)",
                    "training peak RSS MiB"], rows)
    lines += ["", "## Paired differences on the held-out subjects", ""]
    lines += table(["comparison", "novel PSNR fg", "novel SSIM fg"],
                   [[k, ci_text(v["novel_psnr_fg"]), f"{v['novel_ssim_fg']['mean']:+.3f}" if "novel_ssim_fg" in v else "-"]
                    for k, v in res["comparisons"].items()])
    if res["curation"]:
        c = res["curation"]
        lines += ["", f"Curation dataset: {c['subjects']} subjects, {c['defective']} with injected defects "
                      f"({', '.join(f'{k} {v}' for k, v in c['defect_types'].items())}); `label-tool auto` "
                      f"flagged {c['flagged']}, {c['flagged_defective']} of them defective."]
        if c["training"]:
            lines += ["", "What each curation arm trains on:", ""]
            lines += table(["arm", "training subjects", "with an injected defect", "by class"],
                           [[a, t["subjects"], t["defective"],
                             ", ".join(f"{k} {v}" for k, v in t["defect_types"].items()) or "-"]
                            for a, t in c["training"].items()])
    lines += ["", "## Defects the models draw", "",
              "`label-tool auto --false-alarm-rate 0` (every detector at its own threshold) on each arm's "
              "reconstructions of the held-out subjects, rendered from all 32 of their cameras "
              "(`panolam eval --renders`), and on the held-out subjects themselves:", ""]
    rated = [("held-out subjects (truth)", res["held_out_defects"])] + [(a, r["defects"]) for a, r in arms.items()]
    lines += table(["renders of", "flagged", "per detector"],
                   [[name, f"{d['flagged']} of {d['subjects']}",
                     ", ".join(f"{k} {v}" for k, v in sorted(d["per_detector"].items())) or "-"]
                    for name, d in rated if d])
    if plotted:
        lines += ["", "![novel-view foreground PSNR against training subjects](data_value_scale.png)"]
    return "\n".join(lines + galleries(arms, "data_value")) + "\n"


def trained_on(arms: dict) -> list[str]:
    """Markdown lines: the hosts and code each arm trained on, and which arms came from an earlier report."""
    hosts = {}
    for name, r in arms.items():
        for host in dict.fromkeys(h["host"] for h in r.get("hosts") or [{"host": "hosts not recorded"}]):
            hosts.setdefault(host, []).append(name)
    lines = ["Trained on " + "; ".join(f"{h}: {', '.join(names)}" for h, names in hosts.items()) + "."] if hosts else []
    carried = {}
    for name, r in arms.items():
        if r.get("carried_from"):
            carried.setdefault(r["carried_from"], []).append(name)
    lines += [f"From the report of {date} (their work folder is gone; figures as reported then): {', '.join(names)}."
              for date, names in carried.items()]
    return [*lines, ""] if lines else []


def galleries(arms, report: str) -> list[str]:
    """Markdown lines: a section per arm with its gallery ``<report>_<arm>.png``."""
    return [line for name in arms for line in
            ("", f"### {name}", "", f"![{name}: input, reconstruction and truth from the front, left, back and "
                                    f"right]({report}_{name}.png)")]


def study_options(parser: argparse.ArgumentParser, out: str, steps: int) -> None:
    """The options every study of arms has: its work folder, and the steps and batch of every arm."""
    parser.add_argument("--out", type=Path, default=Path(out), help="work folder")
    parser.add_argument("--steps", type=int, default=steps, help="training steps of every arm")
    parser.add_argument("--batch-size", type=int, default=2, help="subjects per step of every arm")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    study_options(parser, "benchmarks/out/data-value", 1500)
    parser.add_argument("--scale", type=int, nargs="+", default=[48, 500, 3000], help="subjects of the scale arms")
    parser.add_argument("--held-out", type=int, default=48, help="held-out subjects (clean, fresh seed)")
    parser.add_argument("--curation-subjects", type=int, default=500)
    parser.add_argument("--defect-rate", type=float, default=0.3)
    parser.add_argument("--arms", nargs="+", help="arms to run, in this order (default: all, most telling first)")
    parser.add_argument("--report", default="data_value", help="report name under benchmarks/reports")
    parser.add_argument("--report-only", action="store_true", help="write the report from what is finished")
    args = parser.parse_args(argv)
    every = [f"scale-{min(args.scale)}", f"scale-{max(args.scale)}", *(f"curation-{c}" for c in CURATION_ARMS),
             *(f"scale-{n}" for n in sorted(args.scale)[1:-1])]
    args.arms = args.arms or every
    unknown = sorted(set(args.arms) - set(every))
    if unknown:
        parser.error(f"unknown arms {', '.join(unknown)}; choose from {', '.join(every)}")
    study = Study(args)
    if not args.report_only:
        for arm in args.arms:
            study.run_arm(arm)
    res = collect(study)
    plotted = plot(res, REPORTS / f"{args.report}_scale.png")
    for arm in res["arms"]:
        gallery = study.out / "runs" / arm / "eval-held-out" / "gallery.png"
        if gallery.exists():
            shutil.copyfile(gallery, REPORTS / f"{args.report}_{arm}.png")
    write_report(REPORTS / args.report, res, markdown(res, plotted).replace("data_value_", f"{args.report}_"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
