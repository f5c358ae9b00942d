"""Which training recipe the README gives: candidate recipes trained for what a time budget buys, on tuning seeds.

    python -m benchmarks.recipe_tuning --out DIR                # 7 candidates, 300 steps of tiny each; resumes
    python -m benchmarks.recipe_tuning --out DIR --prepare      # data and step costs only; then, side by side:
    python -m benchmarks.recipe_tuning --out DIR --candidates readme subjects-500 floor-0.9
    python -m benchmarks.recipe_tuning --out DIR --candidates warmup-30 lr-8e-4 cross-only
    python -m benchmarks.recipe_tuning --out DIR --report-only  # the report from what is finished

Each candidate trains for the same CPU time: ``--steps`` steps of batch 2 of `tiny` (300 is what
20 minutes buy on 2 idle cores of a host at 4.2 s a step; a faster one did 600), or the steps of
its config that cost as much, from CPU seconds per step measured side by side before training.
Counting steps rather than seconds lets candidates run side by side on a busy machine. They are
scored like the data study's arms (:mod:`benchmarks.data_value`, whose stages this reuses): 48
clean held-out subjects, novel views, foreground PSNR, paired differences with 95 % intervals, the
full-frame PSNR beside. The seeds here are tuning seeds: the recipe is chosen on them, and the
figures the README quotes for it come from :mod:`benchmarks.panolam_recipe` on a seed of its own.
Writes ``benchmarks/reports/recipe_tuning.{md,json}`` and a gallery per candidate.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
from pathlib import Path

from benchmarks import data_value
from benchmarks.common import REPORTS, machine_info, table, write_report
from datagen.files import atomic_write

TUNING_HELD_OUT_SEED, TUNING_POOL_SEED = 8807, 8808  # the recipe is chosen on these; never reported as its figure
BASE_CONFIG = "tiny"
# Each candidate adds one change to the one before it (the last: one change to floor-0.9).
# name: (the change, training subjects, --config, more `panolam train` options)
CANDIDATES = {
    "readme": ("the README's recipe until now: 48 subjects; peak rate 4e-4 after 100 warm-up steps, cosine decay "
               "to 10 % of it", 48, BASE_CONFIG, ()),
    "subjects-500": ("500 subjects", 500, BASE_CONFIG, ()),
    "floor-0.9": ("+ the decay ends at 90 % of the peak rate", 500, BASE_CONFIG, ("--lr-floor", "0.9")),
    "warmup-30": ("+ 30 warm-up steps", 500, BASE_CONFIG, ("--lr-floor", "0.9", "--warmup-steps", "30")),
    "lr-8e-4": ("+ twice the peak rate (8e-4)", 500, BASE_CONFIG,
                ("--lr-floor", "0.9", "--warmup-steps", "30", "--lr", "8e-4")),
    "cross-only": ("+ point tokens attend to the image only (the paper's blocks), more steps in the same time", 500,
                   f"{BASE_CONFIG}+cross_only", ("--lr-floor", "0.9", "--warmup-steps", "30", "--lr", "8e-4")),
    # warmup-30 cost more than lr-8e-4 and cross-only gained back: the last change on floor-0.9 alone
    "floor-0.9-cross-only": ("floor-0.9 with point tokens attending to the image only (100 warm-up steps, peak 4e-4)",
                             500, f"{BASE_CONFIG}+cross_only", ("--lr-floor", "0.9")),
}
BASELINE = "readme"
# each change against the candidate it adds to, then each candidate against the README's recipe
COMPARISONS = (*zip(list(CANDIDATES)[1:-1], CANDIDATES), ("floor-0.9-cross-only", "floor-0.9"),
               ("floor-0.9-cross-only", "cross-only"), *((a, BASELINE) for a in list(CANDIDATES)[2:]))


class TuningStudy(data_value.Study):
    """The data study's stages on the tuning seeds; a candidate's data is the first N subjects of one pool, its
    steps those that cost what ``--steps`` steps of the base config cost (:meth:`step_costs`)."""

    held_out_seed, pool_seed = TUNING_HELD_OUT_SEED, TUNING_POOL_SEED

    def arm_data(self, arm: str) -> tuple[Path, list[str]]:
        return super().arm_data(f"scale-{CANDIDATES[arm][1]}")

    def training(self, arm: str) -> tuple[int, list[str]]:
        _, _, config, options = CANDIDATES[arm]
        steps = self.args.steps
        if config != BASE_CONFIG:
            costs = self.step_costs()
            steps = round(steps * costs[BASE_CONFIG] / costs[config])
        return steps, ["--config", config, *options]

    def step_costs(self) -> dict[str, float]:
        """CPU seconds of a training step of each config the candidates use, measured once, side by side
        (:class:`benchmarks.train_step.Stepper`'s batch of the candidates' shape, one thread, interleaved
        rounds after a warm-up step; medians), and kept in ``DIR/step-costs.json``. CPU time counts the
        work done, so a busy machine changes the ratios little."""
        path = self.out / "step-costs.json"
        configs = {BASE_CONFIG} | {CANDIDATES[a][2] for a in self.args.arms}
        costs = json.loads(path.read_text()) if path.exists() else {}
        if len(configs) > 1 and configs - set(costs):
            costs = measure_step_costs(sorted(configs))
            atomic_write(path, json.dumps(costs, indent=1).encode())
        return costs


def measure_step_costs(configs: list[str], rounds: int = 3) -> dict[str, float]:
    import torch

    from benchmarks.train_step import Stepper, interleaved
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        runs = interleaved({c: Stepper({}, {}, config=c) for c in configs}, rounds)
    finally:
        torch.set_num_threads(threads)
    return {c: statistics.median(stages["cpu"] for _, stages in rows) for c, rows in runs.items()}


def collect(study: TuningStudy) -> dict:
    settings = {"steps": study.args.steps, "batch_size": study.args.batch_size, "held_out": study.args.held_out}
    seeds = {"held_out": study.held_out_seed, "pool": study.pool_seed}
    found = {}
    for a in study.args.arms:
        figures = data_value.arm_figures(study, a)
        if figures:
            steps, options = study.training(a)
            found[a] = dict(figures, planned_steps=steps, options=options)
    old = data_value.previous_report(REPORTS / "recipe_tuning.json", settings, seeds)
    arms = data_value.carry(found, study.args.arms, old)
    comparisons = {f"{a} - {b}": data_value.compare(arms[a], arms[b]) for a, b in COMPARISONS if a in arms and b in arms}
    best = max(arms, key=lambda a: arms[a]["held_out"]["novel"]["psnr_fg"]) if arms else None
    return {"machine": machine_info(), "seeds": seeds, "settings": dict(settings, candidates=study.args.arms),
            "step_cpu_s": study.step_costs() or (old or {}).get("step_cpu_s", {}), "arms": arms, "comparisons": comparisons, "best": best}


def markdown(res: dict) -> str:
    m, s, arms = res["machine"], res["settings"], res["arms"]
    lines = ["# Choosing the training recipe (tuning seeds)", "",
             f"Machine: {m['cpu_model']} ({m.get('cpu_family_model')}, {m.get('cpu_capability')}), "
             f"{m['usable_cpus']} usable CPUs, torch {m['torch']}, revision "
             f"{m['git_revision']}; report written {m['date']}, 1-minute load average {m['load_average'][0]:.2f} "
             f"then. Tuning seeds: held-out {res['seeds']['held_out']} ({s['held_out']} clean subjects), pool "
             f"{res['seeds']['pool']}. Every candidate: batch {s['batch_size']}, the steps that cost what {s['steps']} "
             f"steps of `{BASE_CONFIG}` cost"
             + (" (CPU seconds of a step, measured side by side: "
                + ", ".join(f"`{c}` {v:.2f}" for c, v in res["step_cpu_s"].items()) + ")" if res["step_cpu_s"] else "")
             + "; held-out scores: novel views "
             "(left, back, right), foreground PSNR/SSIM, and the full frame of all four views, 128 px; intervals are "
             "95 % (Student's t over paired subjects).", "",
             f"Candidates finished: {len(arms)} of {len(s['candidates'])}.", "", *data_value.trained_on(arms)]
    lines += table(["candidate", "what", "training subjects", "steps", "train-batch PSNR dB (64 px)",
                    "held-out novel PSNR fg dB", "held-out novel SSIM fg", "held-out all PSNR dB",
                    "reconstructions flagged", "s/step (median)"],
                   [[a, CANDIDATES[a][0], r["train_subjects"], r["steps"], f"{r['train_batch_psnr']:.2f}",
                     f"{r['held_out']['novel']['psnr_fg']:.2f}", f"{r['held_out']['novel']['ssim_fg']:.3f}",
                     f"{r['held_out']['all']['psnr']:.2f}",
                     f"{r['defects']['flagged']} of {r['defects']['subjects']}" if r["defects"] else "-",
                     f"{r['step_s_median']:.2f}"] for a, r in arms.items()])
    if res["comparisons"]:
        lines += ["", "## Paired differences on the held-out subjects (novel-view foreground PSNR)", ""]
        lines += table(["comparison", "difference"],
                       [[k, data_value.ci_text(v["novel_psnr_fg"])] for k, v in res["comparisons"].items()])
    if res["best"]:
        lines += ["", f"Highest held-out novel-view foreground PSNR: **{res['best']}**."]
    return "\n".join(lines + data_value.galleries(arms, "recipe_tuning")) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    data_value.study_options(parser, "benchmarks/out/recipe-tuning", 300)
    parser.add_argument("--held-out", type=int, default=48, help="held-out subjects (clean)")
    parser.add_argument("--candidates", nargs="+", choices=list(CANDIDATES), default=list(CANDIDATES),
                        help="candidates to run, in this order")
    parser.add_argument("--prepare", action="store_true",
                        help="only generate the candidates' datasets and measure the step costs, so that processes "
                             "given different --candidates can then train side by side")
    parser.add_argument("--report-only", action="store_true", help="write the report from what is finished")
    args = parser.parse_args(argv)
    args.arms = args.candidates
    args.scale = sorted({CANDIDATES[a][1] for a in CANDIDATES})
    study = TuningStudy(args)
    if args.prepare:
        study.held_out()
        for arm in args.arms:
            study.arm_data(arm)
            study.training(arm)
        return 0
    if not args.report_only:
        for arm in args.arms:
            study.run_arm(arm)
    res = collect(study)
    for arm in res["arms"]:
        gallery = study.out / "runs" / arm / "eval-held-out" / "gallery.png"
        if gallery.exists():  # a carried candidate's is in the reports already
            shutil.copyfile(gallery, REPORTS / f"recipe_tuning_{arm}.png")
    write_report(REPORTS / "recipe_tuning", res, markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
