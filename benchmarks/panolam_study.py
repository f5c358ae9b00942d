"""PanoLAM on procedural heads, on a CPU: does it learn, does the paper's ablation ordering hold, and
what do speed and accuracy trade?

    python -m benchmarks.panolam_study                          # everything, one process (hours on 2 cores)
    python -m benchmarks.panolam_study --phase train --threads 1 --variants main quarter_subjects &
    python -m benchmarks.panolam_study --phase train --threads 1 --variants no_c2f tiny single_point rays_k8
    python -m benchmarks.panolam_study --phase baselines final speed report   # then, on a quiet machine
    python -m benchmarks.panolam_study --device cuda --subjects 2000 --steps 20000 --ablation-steps 20000  # a GPU

The learning goal of the current recipe (novel-view foreground PSNR 5 dB over the mean-colour
template within 2 hours of training on 2 cores) is measured by the recipe itself run for two hours,
``python -m benchmarks.panolam_recipe --time-limit 7200 --steps 100000 --report panolam_recipe_2h``;
this study compares the paper's ablations and the speed-accuracy trade-offs.

Phases (each skips what is already on disk, so an interrupted study resumes; training processes can
run side by side, each variant writing only under ``runs/<name>/``):
1. data: ``datagen sample`` of procedural heads (360 protocol, 32 views, 128 px) and a manifest
   (``label-tool compile``, unreviewed subjects accepted, ``--test-count`` held out).
2. baselines: the untrained model and the template rendered opaque in the mean foreground colour
   of the training images, on the held-out subjects.
3. train: the main ``tiny`` run (``--steps``, evaluated on held-out subjects every ``--eval-every``
   steps; training stops there and resumes exactly) and the paper's ablations with their own
   ``--ablation-steps`` schedule: ``tiny``, no coarse-to-fine (``tiny+no_c2f``), single-point
   tri-plane query (``tiny+single_point``), ray aggregation with K_m = 8 (the `tiny` of before, now 2) and ``tiny`` on a quarter
   of the training subjects.
4. final: every run's last checkpoint on the held-out subjects (front view in; front, left, back
   and right out; 64 px), each in a fresh process for clean time and memory readings.
5. speed: the main run against the dense Gaussian count (re-densified at inference: the barycentric
   weights exist for any count) and the render resolution.
6. report: ``benchmarks/reports/panolam_training.{md,json,png}`` and ``speed_vs_error.{md,json,png}``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from benchmarks.common import (HERE, REPORTS, machine_info, peak_rss_since_reset_mb, pyplot,
                               reset_peak_rss, run_child, table, write_report)
from datagen.dataset.manifests import read_manifest
from panolam.evaluate import EVAL_VIEWS, MeanColourTemplate, evaluate, mean_foreground_colour
from panolam.evaluate import paired_difference as per_subject_difference
from panolam.model import PanoLAM
from panolam.checkpoints import load_model, read_checkpoint
from panolam.config import TrainConfig, preset
from panolam.train import train

OUT = HERE / "out" / "study"
MAIN = "main"  # the long `tiny` run: learning curve, speed against error
VARIANTS = {  # name: (config, fraction of training subjects, model overrides); all but MAIN train --ablation-steps
    MAIN: ("tiny", 1.0, {}),
    "tiny": ("tiny", 1.0, {}),
    "no_c2f": ("tiny+no_c2f", 1.0, {}),
    "single_point": ("tiny+single_point", 1.0, {}),
    "rays_k8": ("tiny", 1.0, {"ray_samples": 8}),
    "quarter_subjects": ("tiny", 0.25, {}),
}
RESOLUTION = 64
PHASES = ("data", "baselines", "train", "final", "speed", "report")
# The paper's module ablations (Table 4: PSNR, SSIM on its 360-degree test set; "2K subj." trains on 2,000 subjects).
PAPER_ABLATION = {"tiny": ("Full", 23.494, 0.793), "no_c2f": ("w/o C2F", 22.312, 0.731),
                  "single_point": ("w/o ST ray agg.", 22.156, 0.715), "quarter_subjects": ("2K subj.", 19.391, 0.699)}


def data_phase(args) -> tuple[Path, Path]:
    data, manifest = args.out / "heads", args.out / "heads-v1.json"
    if not (data / "index.json").exists() or args.resume_data:
        subprocess.run(["datagen", "sample", "--protocol", "360", "--subjects", str(args.subjects), "--resolution", "128",
                        "--views", "32", "--seed", "11", "--shard-size", "32", "--out", str(data), "--quiet",
                        *(["--resume"] if data.exists() else [])], check=True)
    if not manifest.exists():
        (args.out / "labels").mkdir(parents=True, exist_ok=True)
        subprocess.run(["label-tool", "compile", str(data), "--labels", str(args.out / "labels"), "--out", str(manifest),
                        "--test-count", str(args.test_count)], check=True)
    return data, manifest


def subset_manifest(manifest: Path, fraction: float, out: Path) -> Path:
    """A copy of the manifest accepting only the first ``fraction`` of its training subjects."""
    if fraction >= 1.0:
        return manifest
    m = read_manifest(manifest)
    train_rows = [s for s in m["subjects"] if s["verdict"] == "accepted" and s["split"] == "train"]
    keep = {s["subject"] for s in train_rows[:max(1, int(len(train_rows) * fraction))]}
    for s in m["subjects"]:
        if s["split"] == "train" and s["subject"] not in keep:
            s["split"] = None
    path = out / f"manifest-{fraction:g}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(m))
    return path


def train_config(steps: int) -> TrainConfig:
    return TrainConfig(steps=steps, batch_size=2, views_per_sample=6, render_resolution=RESOLUTION,
                       warmup_steps=max(1, steps // 20), checkpoint_every=100, log_every=10,
                       image_every=max(1, steps // 5))


def evaluate_run(model, data, manifest, args, resolution: int = RESOLUTION) -> dict:
    """Held-out metrics (means per view, medians of the times) and per-subject PSNR/SSIM for paired comparisons."""
    r = evaluate(model, data, read_manifest(manifest), "test", resolution=resolution, limit=args.eval_subjects)
    return {**{k: r[k] for k in ("subjects", "per_view", "reconstruct_s_median", "render_ms_per_view_median")},
            "rows": [{k: row[k] for k in ("subject", "view", "psnr", "psnr_fg", "ssim", "ssim_fg")} for row in r["rows"]]}


def train_phase(args, data, manifest) -> None:
    """Train the chosen variants; each keeps its curve in ``runs/<name>/curve.json`` (so processes can share a study)."""
    for name in args.variants:
        config, fraction, overrides = VARIANTS[name]
        steps = args.steps if name == MAIN else args.ablation_steps
        cfg = train_config(steps)
        run = args.out / "runs" / name
        curve_path = run / "curve.json"
        curve = json.loads(curve_path.read_text()) if curve_path.exists() else {
            "rows": [], "command": args.command, "machine": machine_info(), "train_config": cfg.to_dict(),
            "model_config": preset(config, **overrides).to_dict(), "training_fraction": fraction}
        model_cfg = preset(config, **overrides)
        used = subset_manifest(manifest, fraction, run.parent / name)
        stops = sorted({*range(args.eval_every, steps + 1, args.eval_every), steps}) if name == MAIN else [steps]
        for stop in stops:
            if any(r["step"] == stop for r in curve["rows"]):
                continue
            done = read_checkpoint(run)["step"] if (run / "checkpoint.pt").exists() else 0
            t0 = time.perf_counter()
            if done < stop:
                train(data, used, model_cfg, cfg, run, resume=done > 0, device=args.device, progress=False, until=stop)
            row = {"step": stop, "train_s": time.perf_counter() - t0,
                   **evaluate_run(load_model(run, args.device), data, manifest, args)}
            curve["rows"].append(row)
            print(f"{name} step {stop}: held-out PSNR {_psnr(row):.2f} dB ({row['train_s']:.0f} s)", flush=True)
            curve["history"] = [{k: h[k] for k in ("step", "loss", "psnr_dense", "seconds")}
                                for h in read_checkpoint(run)["history"]]
            _write_json(curve_path, curve)


def baseline_phase(args, data, manifest) -> None:
    torch.manual_seed(0)
    untrained = PanoLAM(preset("tiny")).to(args.device).eval()
    colour = mean_foreground_colour(data, read_manifest(manifest), RESOLUTION)
    _write_json(args.out / "baselines.json", {
        "untrained": evaluate_run(untrained, data, manifest, args),
        "mean_colour_template": {**evaluate_run(MeanColourTemplate(untrained, colour.to(args.device)), data, manifest,
                                                 args),
                                 "colour": colour.tolist()},
    })


def measure_child(config: dict) -> dict:
    """One held-out evaluation in this fresh process (clean time and peak-memory readings)."""
    overrides = {"dense_points": config["dense_points"]} if config.get("dense_points") else {}
    model = load_model(config["run"], config.get("device", "cpu"), **overrides)
    base = reset_peak_rss()
    r = evaluate_run(model, config["data"], config["manifest"], SimpleNamespace(eval_subjects=config["eval_subjects"]),
                     config.get("resolution", RESOLUTION))
    return {**r, "dense_count": model.dense_count, "peak_mb": peak_rss_since_reset_mb() - base}


def _measure(args, data, manifest, run: Path, **options) -> dict:
    return run_child(Path(__file__), {"run": str(run), "data": str(data), "manifest": str(manifest),
                                      "eval_subjects": args.eval_subjects, "device": args.device, **options})


def final_phase(args, data, manifest) -> None:
    """Each trained run's last checkpoint on the held-out subjects, one run at a time (clean times and memory)."""
    for name in VARIANTS:
        run = args.out / "runs" / name
        if not (run / "curve.json").exists():
            continue
        r = _measure(args, data, manifest, run)
        history = json.loads((run / "curve.json").read_text()).get("history", [])
        _write_json(run / "final.json", {
            "step": read_checkpoint(run)["step"], "machine": machine_info(),
            "train_s_per_step_median": float(np.median([h["seconds"] for h in history])) if history else None, **r})
        print(f"{name}: held-out PSNR {_psnr(r):.2f} dB", flush=True)


def speed_phase(args, data, manifest) -> None:
    run = args.out / "runs" / MAIN
    rows = []
    for n in args.dense_counts:
        r = _measure(args, data, manifest, run, dense_points=n)
        rows.append({"axis": "dense_points", "value": r["dense_count"], **r})
        print(f"M_D={r['dense_count']}: PSNR {_psnr(r):.2f}", flush=True)
    for res in args.resolutions:
        r = _measure(args, data, manifest, run, resolution=res)
        rows.append({"axis": "render_resolution", "value": res, **r})
        print(f"{res} px: PSNR {_psnr(r):.2f}", flush=True)
    _write_json(args.out / "speed.json", {"machine": machine_info(), "rows": rows})


def _write_json(path: Path, value) -> None:
    """Write JSON under a temporary name, then rename (an interrupted study never leaves half a file)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(value, indent=1))
    tmp.replace(path)


def load_results(args) -> dict:
    """Everything the phases wrote under ``args.out``, as one dict for the reports."""
    read = lambda p: json.loads(p.read_text()) if p.exists() else None  # noqa: E731
    curves = {name: read(args.out / "runs" / name / "curve.json") for name in VARIANTS}
    curves = {k: v for k, v in curves.items() if v}
    finals = {name: read(args.out / "runs" / name / "final.json") for name in curves}
    speed = read(args.out / "speed.json") or {}
    return {"machine": machine_info(), "command": args.command, "args": args.recorded,
            "baselines": read(args.out / "baselines.json") or {},
            "curves": {k: v["rows"] for k, v in curves.items()},
            "runs": {k: {key: v.get(key) for key in ("command", "train_config", "model_config", "training_fraction",
                                                     "machine")} for k, v in curves.items()},
            "history": {k: v.get("history", []) for k, v in curves.items()},
            "final": {k: v for k, v in finals.items() if v},
            "speed_vs_error": speed.get("rows", []), "speed_machine": speed.get("machine")}


# -- reports --------------------------------------------------------------------------------------------------
def _psnr(r):
    return r["per_view"]["all"]["psnr"]


def _ssim(r):
    return r["per_view"]["all"]["ssim"]


def _views(r):
    return " | ".join(f"{r['per_view'][v]['psnr']:.2f}" for v in ("front", "left", "back", "right"))


def paired_difference(a: dict, b: dict) -> tuple[float, float]:
    """Mean and standard error of the per-subject PSNR difference a - b (each subject's four views averaged)."""
    return per_subject_difference(a, b, "psnr", views=tuple(EVAL_VIEWS))[:2]


def _machine_line(m: dict) -> str:
    return (f"{m['cpu_model']} ({m['cpu_count']} cores), torch {m['torch']}, revision {m['git_revision']}, "
            f"{m['date']}")


def _setup(results: dict) -> list[str]:
    a, runs = results["args"], results["runs"]
    main = runs.get(MAIN) or next(iter(runs.values()), {})
    tc = main.get("train_config") or {}
    commands = sorted({r["command"] for r in runs.values() if r.get("command")})
    return [f"Machine: {_machine_line(main.get('machine') or results['machine'])}. Dataset: {a['subjects']} "
            f"procedural subjects (360 protocol, 32 views of 128 px; 4 % carry an injected defect and, unreviewed, "
            f"stay accepted), {a['test_count']} held out by the manifest, {a['eval_subjects']} of them evaluated: the "
            f"front view in at the encoder's 128 px, front/left/back/right out at {RESOLUTION} px over white. "
            f"Training: {tc.get('batch_size')} subjects x {tc.get('views_per_sample')} views per step (1 input, the "
            f"rest targets) at {tc.get('render_resolution')} px, Adam, linear warm-up then cosine decay; D-SSIM stands "
            "in for LPIPS (no LPIPS weights here); procedural data has no GAN planes, so lambda_6 has nothing to "
            "supervise. Training processes ran two at a time, one thread each, so their seconds per step are "
            "comparable with each other, not with a quiet 2-thread run.", "", "```", *commands,
            "python -m benchmarks.panolam_study --phase baselines final speed report", "```"]


def training_markdown(results: dict, plot_note: str) -> str:
    curves, finals, base = results["curves"], results["final"], results["baselines"]
    lines = ["# PanoLAM `tiny` trained on procedural heads (CPU)", "", *_setup(results), "",
             "## Held-out subjects: does it learn?", "",
             "| model | PSNR dB (all views) | front | left | back | right | SSIM |", "|---|---|---|---|---|---|---|"]
    for name, r in base.items():
        lines.append(f"| baseline: {name.replace('_', ' ')} | {_psnr(r):.2f} | {_views(r)} | {_ssim(r):.4f} |")
    if MAIN in finals:
        r = finals[MAIN]
        lines.append(f"| `tiny`, {r['step']} steps | {_psnr(r):.2f} | {_views(r)} | {_ssim(r):.4f} |")
        for name, b in base.items():
            d, se = paired_difference(r, b)
            lines.append(f"\n`tiny` against the {name.replace('_', ' ')} baseline: {d:+.2f} +- {se:.2f} dB "
                         f"(mean +- standard error of the per-subject difference, {r['subjects']} subjects).")
    if curves.get(MAIN):
        elapsed = np.cumsum([x["train_s"] for x in curves[MAIN]]) / 60
        lines += ["", "Held-out PSNR of the main run during training (its schedule ends at the last step):", "",
                  "| step | PSNR dB | SSIM | training min |", "|---|---|---|---|"]
        lines += [f"| {r['step']} | {_psnr(r):.2f} | {_ssim(r):.4f} | {t:.0f} |" for r, t in zip(curves[MAIN], elapsed)]
    ablations = [n for n in ("tiny", "no_c2f", "single_point", "rays_k8", "quarter_subjects") if n in finals]
    if "tiny" in finals and len(ablations) > 1:
        steps = finals["tiny"]["step"]
        what = {"tiny": "the `tiny` preset", "no_c2f": "no coarse-to-fine: the attention stack runs on all M_D points",
                "single_point": "tri-plane queried at the point only (no ray aggregation)",
                "rays_k8": "ray aggregation with K_m = 8 instead of 2",
                "quarter_subjects": "a quarter of the training subjects"}
        lines += ["", f"## The paper's ablations at small scale ({steps} steps each, each with its own schedule)", "",
                  "| variant | what changes | PSNR dB | SSIM | `tiny` minus it, dB | train s/step | paper: PSNR / SSIM |",
                  "|---|---|---|---|---|---|---|"]
        for n in ablations:
            r = finals[n]
            d = "-" if n == "tiny" else "{:+.2f} +- {:.2f}".format(*paired_difference(finals["tiny"], r))
            paper = PAPER_ABLATION.get(n)
            paper = f"{paper[0]}: {paper[1]:.2f} / {paper[2]:.3f}" if paper else "-"
            lines.append(f"| {n} | {what[n]} | {_psnr(r):.2f} | {_ssim(r):.4f} | {d} | "
                         f"{r['train_s_per_step_median']:.1f} | {paper} |")
        verdicts = []
        for n in ("no_c2f", "single_point", "quarter_subjects"):
            if n in finals:
                d, se = paired_difference(finals["tiny"], finals[n])
                verdicts.append(f"{n}: " + ("tiny better" if d > 2 * se else "ablation better" if d < -2 * se
                                            else "no clear difference") + f" ({d:+.2f} +- {se:.2f} dB)")
        lines += ["", "Paper's ordering (the full model beats each ablation), judged by the paired difference against "
                  "twice its standard error: " + "; ".join(verdicts) + "."]
    lines += ["", plot_note, ""]
    return "\n".join(lines)


def speed_markdown(results: dict, plot_note: str) -> str:
    rows, finals = results["speed_vs_error"], results["final"]
    m = results.get("speed_machine") or results["machine"]
    lines = ["# Speed against error: PanoLAM `tiny` (CPU)", "",
             f"Machine: {_machine_line(m)}; measured alone, {m['torch_threads']} threads. Held-out subjects of the "
             f"study (panolam_training.md): front view in, front/left/back/right out at {RESOLUTION} px unless a row "
             "varies the resolution. Times are medians per subject (reconstruction: one forward pass, batch 1; "
             "render: per view); memory is the peak resident-set increase while evaluating (model, images, renders).", ""]
    axis = lambda a: [r for r in rows if r["axis"] == a]  # noqa: E731
    quality = lambda r: [f"{_psnr(r):.2f}", f"{_ssim(r):.4f}"]  # noqa: E731
    if axis("dense_points"):
        lines += ["## Dense Gaussians M_D (the main run, trained at 5,000, re-densified at inference)", "",
                  *table(["M_D", "PSNR dB", "SSIM", "reconstruct ms", "render ms/view", "peak MiB"],
                         [[r["value"], *quality(r), f"{r['reconstruct_s_median'] * 1000:.0f}",
                           f"{r['render_ms_per_view_median']:.1f}", f"{r['peak_mb']:.0f}"] for r in axis("dense_points")]),
                  ""]
    if axis("render_resolution"):
        lines += ["## Render resolution (the main run)", "",
                  *table(["px", "PSNR dB", "SSIM", "render ms/view", "peak MiB"],
                         [[r["value"], *quality(r), f"{r['render_ms_per_view_median']:.1f}", f"{r['peak_mb']:.0f}"]
                          for r in axis("render_resolution")]), ""]
    k_runs = [(n, k) for n, k in (("single_point", 1), ("rays_k8", 4 * 8), ("tiny", 4 * preset("tiny").ray_samples))
              if n in finals]
    if k_runs:
        lines += [f"## Tri-plane samples per dense point (separate trainings, {finals[k_runs[0][0]]['step']} steps)", "",
                  "| run | samples per point | PSNR dB | SSIM | minus `tiny`, dB | reconstruct ms | train s/step | "
                  "peak MiB |", "|---|---|---|---|---|---|---|---|"]
        for n, k in k_runs:
            r = finals[n]
            label = "1 (the point alone)" if n == "single_point" else f"{k} (4 cameras x K_m = {k // 4})"
            d = "-" if n == "tiny" or "tiny" not in finals else "{:+.2f} +- {:.2f}".format(
                *paired_difference(r, finals["tiny"]))
            lines.append(f"| {n} | {label} | {_psnr(r):.2f} | {_ssim(r):.4f} | {d} | "
                         f"{r['reconstruct_s_median'] * 1000:.0f} | {r['train_s_per_step_median']:.1f} | "
                         f"{r['peak_mb']:.0f} |")
        lines += ["", "Differences are paired per held-out subject (mean +- standard error); within about two "
                  "standard errors they are noise.", ""]
    if "tiny" in finals and "no_c2f" in finals:
        a, b = finals["tiny"], finals["no_c2f"]
        d, se = paired_difference(a, b)
        lines += ["## Coarse-to-fine against direct dense regression (same M_D, same steps)", "",
                  "| run | PSNR dB | SSIM | reconstruct ms | train s/step | peak MiB |", "|---|---|---|---|---|---|"]
        lines += [f"| {n} | {_psnr(r):.2f} | {_ssim(r):.4f} | {r['reconstruct_s_median'] * 1000:.0f} | "
                  f"{r['train_s_per_step_median']:.1f} | {r['peak_mb']:.0f} |" for n, r in (("tiny", a), ("no_c2f", b))]
        lines += ["", f"Direct regression relative to coarse-to-fine: reconstruction "
                  f"{b['reconstruct_s_median'] / a['reconstruct_s_median']:.1f}x the time, training "
                  f"{b['train_s_per_step_median'] / a['train_s_per_step_median']:.1f}x the time per step, PSNR "
                  f"{-d:+.2f} +- {se:.2f} dB. The network alone, forward and backward, with peak memory: "
                  "model_speed.md.", ""]
    lines += [plot_note, ""]
    return "\n".join(lines)


def training_plot(results: dict, path: Path) -> str:
    plt = pyplot()
    if plt is None:
        return "Plot skipped: matplotlib is not installed."
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, hist in results["history"].items():
        if not hist:
            continue
        steps, p = np.array([h["step"] for h in hist]), np.array([h["psnr_dense"] for h in hist])
        k = max(1, min(25, len(p) // 4))
        ax.plot(steps[k - 1:], np.convolve(p, np.ones(k) / k, mode="valid"), alpha=0.6, lw=1,
                label=f"{name}: training batches (running mean of {k})")
    rows = results["curves"].get(MAIN, [])
    if rows:
        ax.plot([r["step"] for r in rows], [_psnr(r) for r in rows], "ko-", label=f"{MAIN}: held-out subjects")
    for (name, r), colour in zip(results["baselines"].items(), ("gray", "tab:red")):
        ax.axhline(_psnr(r), ls="--", color=colour, label=f"baseline, held out: {name.replace('_', ' ')}")
    ax.set(xlabel="step", ylabel="PSNR dB", title="PanoLAM tiny on procedural heads (CPU)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"![learning curves]({path.name})"


def speed_plot(results: dict, path: Path) -> str:
    plt = pyplot()
    if plt is None:
        return "Plot skipped: matplotlib is not installed."
    rows, finals = results["speed_vs_error"], results["final"]
    k_runs = [(k, finals[n]) for n, k in (("single_point", 1), ("rays_k8", 32), ("tiny", 4 * preset("tiny").ray_samples))
              if n in finals]
    panels = [("dense Gaussians M_D", [(r["value"], r) for r in rows if r["axis"] == "dense_points"],
               "reconstruct ms", lambda r: r["reconstruct_s_median"] * 1000),
              ("tri-plane samples per point", k_runs, "train s/step", lambda r: r["train_s_per_step_median"]),
              ("render px", [(r["value"], r) for r in rows if r["axis"] == "render_resolution"],
               "render ms / view", lambda r: r["render_ms_per_view_median"])]
    panels = [p for p in panels if p[1]]
    if not panels:
        return ""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4), squeeze=False)
    for ax, (label, points, cost_label, cost) in zip(axes[0], panels):
        x = [v for v, _ in points]
        ax.plot(x, [_psnr(r) for _, r in points], "o-", color="tab:blue")
        ax.set(xlabel=label, ylabel="held-out PSNR dB")
        if label != "render px":
            ax.set_xscale("log")
            ax.minorticks_off()
        ax.set_xticks(x, [str(v) for v in x])
        twin = ax.twinx()
        twin.plot(x, [cost(r) for _, r in points], "s--", color="tab:orange")
        twin.set_ylabel(cost_label, color="tab:orange")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"![speed against error]({path.name})"


def reports(results: dict) -> None:
    stem = REPORTS / "panolam_training"
    stem.parent.mkdir(parents=True, exist_ok=True)
    write_report(stem, {k: results[k] for k in ("args", "runs", "baselines", "curves", "final", "history")},
                 training_markdown(results, training_plot(results, stem.with_suffix(".png"))))
    stem = REPORTS / "speed_vs_error"
    write_report(stem, {k: results[k] for k in ("speed_machine", "speed_vs_error", "final")},
                 speed_markdown(results, speed_plot(results, stem.with_suffix(".png"))))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--subjects", type=int, default=160)
    parser.add_argument("--test-count", type=int, default=16)
    parser.add_argument("--steps", type=int, default=800, help="steps of the main run")
    parser.add_argument("--ablation-steps", type=int, default=200, help="steps of each ablation run")
    parser.add_argument("--eval-every", type=int, default=100, help="held-out evaluation interval of the main run")
    parser.add_argument("--eval-subjects", type=int, default=16)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--dense-counts", type=int, nargs="+", default=[1280, 2500, 5000, 10000, 20000])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128])
    parser.add_argument("--phase", nargs="+", default=list(PHASES), choices=list(PHASES))
    parser.add_argument("--resume-data", action="store_true", help="finish an interrupted dataset")
    parser.add_argument("--threads", type=int, help="torch threads (two studies of 1 thread each share 2 cores well)")
    parser.add_argument("--device", default="cpu", help="torch device of training and evaluation (cpu, cuda, cuda:1)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(measure_child(json.loads(args.child))))
        return
    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    args.command = "python -m benchmarks.panolam_study " + " ".join(argv or sys.argv[1:])
    args.recorded = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    data, manifest = data_phase(args) if "data" in args.phase else (args.out / "heads", args.out / "heads-v1.json")
    if "baselines" in args.phase:
        baseline_phase(args, data, manifest)
    if "train" in args.phase:
        train_phase(args, data, manifest)
    if "final" in args.phase:
        final_phase(args, data, manifest)
    if "speed" in args.phase:
        speed_phase(args, data, manifest)
    if "report" in args.phase:
        reports(load_results(args))


if __name__ == "__main__":
    main()
