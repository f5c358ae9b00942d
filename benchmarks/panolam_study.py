"""PanoLAM on procedural heads, on a CPU: does it learn, does the paper's ablation ordering hold, and
what do speed and accuracy trade?

    python benchmarks/panolam_study.py                 # dataset + 4 trainings + evaluations (about 1.5 h on 2 cores)
    python benchmarks/panolam_study.py --steps 300     # shorter
    python benchmarks/panolam_study.py --phase report  # rewrite the reports from the JSON

Steps (each skips what is already on disk, so an interrupted study resumes):
1. data: ``datagen sample`` of procedural heads (360 protocol, 32 views, 128 px) and a manifest
   (``label-tool compile``, unreviewed subjects accepted, ``--test-count`` held out).
2. train: the ``tiny`` preset and the paper's ablations with the same steps, batch and schedule:
   no coarse-to-fine (``tiny+no_c2f``), single-point tri-plane query (``tiny+single_point``) and
   ``tiny`` on a quarter of the training subjects. The ``tiny`` run is evaluated on the held-out
   subjects every ``--eval-every`` steps (training stops there and resumes exactly).
3. evaluate on the held-out subjects (front view in; front/left/back/right out; 64 px):
   every run, and two baselines: the untrained model and the head template rendered with the mean
   foreground colour of the training images.
4. speed against error with the trained ``tiny`` run: PSNR/SSIM, reconstruction time, render time
   and peak memory against the dense Gaussian count (re-densified at inference: the barycentric
   weights hold for any count) and against render resolution; K_m from the ablation.

Reports: ``benchmarks/reports/panolam_training.{md,json,png}`` and ``speed_vs_error.{md,json,png}``.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.common import HERE, REPORTS, machine_info, pyplot, rss_mb, write_report  # noqa: E402
from labeling_tool.manifest import read_manifest  # noqa: E402
from panolam.config import preset  # noqa: E402
from panolam.data import accepted_subjects, load_views  # noqa: E402
from panolam.evaluate import evaluate  # noqa: E402
from panolam.gaussians import Gaussians  # noqa: E402
from panolam.model import PanoLAM  # noqa: E402
from panolam.train import TrainConfig, load_model, read_checkpoint, train  # noqa: E402

OUT = HERE / "out" / "study"
VARIANTS = {  # name: (config, fraction of training subjects, model overrides)
    "tiny": ("tiny", 1.0, {}),
    "no_c2f": ("tiny+no_c2f", 1.0, {}),
    "single_point": ("tiny+single_point", 1.0, {}),
    "rays_k2": ("tiny", 1.0, {"ray_samples": 2}),
    "quarter_subjects": ("tiny", 0.25, {}),
}
RESOLUTION = 64


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


def train_config(args) -> TrainConfig:
    return TrainConfig(steps=args.steps, batch_size=2, views_per_sample=6, render_resolution=RESOLUTION,
                       warmup_steps=max(1, args.steps // 20), checkpoint_every=100, log_every=10,
                       image_every=max(1, args.steps // 5))


def evaluate_run(model, data, manifest, args, resolution: int = RESOLUTION) -> dict:
    r = evaluate(model, data, read_manifest(manifest), "test", resolution=resolution, limit=args.eval_subjects)
    return {k: r[k] for k in ("subjects", "per_view", "reconstruct_s_median", "render_ms_per_view_median")}


def train_phase(args, data, manifest) -> None:
    """Train the chosen variants; each keeps its curve in ``runs/<name>/curve.json`` (so processes can share a study)."""
    cfg = train_config(args)
    for name in args.variants:
        config, fraction, overrides = VARIANTS[name]
        run = args.out / "runs" / name
        curve_path = run / "curve.json"
        curve = json.loads(curve_path.read_text()) if curve_path.exists() else {
            "rows": [], "command": args.command, "machine": machine_info(), "train_config": cfg.to_dict(),
            "model_config": preset(config, **overrides).to_dict(), "training_fraction": fraction}
        model_cfg = preset(config, **overrides)
        used = subset_manifest(manifest, fraction, run.parent / name)
        stops = range(args.eval_every, args.steps + 1, args.eval_every) if name == "tiny" else [args.steps]
        for stop in stops:
            if any(r["step"] == stop for r in curve["rows"]):
                continue
            done = read_checkpoint(run)["step"] if (run / "checkpoint.pt").exists() else 0
            t0 = time.perf_counter()
            if done < stop:
                train(data, used, model_cfg, cfg, run, resume=done > 0, progress=False, until=stop)
            row = {"step": stop, "train_s": time.perf_counter() - t0,
                   **evaluate_run(load_model(run), data, manifest, args)}
            curve["rows"].append(row)
            print(f"{name} step {stop}: held-out PSNR {_psnr(row):.2f} dB ({row['train_s']:.0f} s)", flush=True)
            curve["history"] = [{k: h[k] for k in ("step", "loss", "psnr_dense", "seconds")}
                                for h in read_checkpoint(run)["history"]]
            _write_json(curve_path, curve)


class MeanColourTemplate(torch.nn.Module):
    """Baseline: the untrained model's dense template Gaussians, opaque, in one colour."""

    def __init__(self, model: PanoLAM, colour: torch.Tensor):
        super().__init__()
        self.model, self.colour, self.cfg = model, colour, model.cfg

    def forward(self, x):
        d = self.model(x).dense
        return SimpleNamespace(dense=Gaussians(d.means, d.quats, d.scales, torch.full_like(d.opacities, 0.99),
                                               self.colour.expand_as(d.colors)))


def mean_foreground_colour(data, manifest) -> torch.Tensor:
    total, weight = torch.zeros(3), 0.0
    for key, shard in accepted_subjects(read_manifest(manifest), "train")[:32]:
        v = load_views(data, key, shard, resolution=RESOLUTION)
        total += (v.images * v.masks).sum(dim=(0, 2, 3))
        weight += float(v.masks.sum())
    return total / max(weight, 1.0)


def baseline_phase(args, data, manifest) -> None:
    torch.manual_seed(0)
    untrained = PanoLAM(preset("tiny")).eval()
    colour = mean_foreground_colour(data, manifest)
    _write_json(args.out / "baselines.json", {
        "untrained": evaluate_run(untrained, data, manifest, args),
        "mean_colour_template": {**evaluate_run(MeanColourTemplate(untrained, colour), data, manifest, args),
                                 "colour": colour.tolist()},
    })


def _peak_reset() -> float:
    Path("/proc/self/clear_refs").write_text("5")
    return rss_mb()


def _peak_since(base: float) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024 - base
    return float("nan")


def speed_phase(args, data, manifest) -> None:
    run = args.out / "runs" / "tiny"
    rows = []
    for n in args.dense_counts:
        model = load_model(run, dense_points=n)
        base = _peak_reset()
        r = evaluate_run(model, data, manifest, args)
        rows.append({"axis": "dense_points", "value": model.dense_count, "peak_mb": _peak_since(base), **r})
        print(f"M_D={model.dense_count}: PSNR {r['per_view']['all']['psnr']:.2f}", flush=True)
    model = load_model(run)
    for res in args.resolutions:
        base = _peak_reset()
        r = evaluate_run(model, data, manifest, args, resolution=res)
        rows.append({"axis": "render_resolution", "value": res, "peak_mb": _peak_since(base), **r})
        print(f"{res} px: PSNR {r['per_view']['all']['psnr']:.2f}", flush=True)
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
    speed = read(args.out / "speed.json") or {}
    return {"machine": machine_info(), "command": args.command, "args": args.recorded,
            "baselines": read(args.out / "baselines.json") or {},
            "curves": {k: v["rows"] for k, v in curves.items()},
            "history": {k: v.get("history", []) for k, v in curves.items()},
            "speed_vs_error": speed.get("rows", []), "speed_machine": speed.get("machine")}


# -- reports --------------------------------------------------------------------------------------------------
def _psnr(r):
    return r["per_view"]["all"]["psnr"]


def _views(r):
    return " | ".join(f"{r['per_view'][v]['psnr']:.2f}" for v in ("front", "left", "back", "right"))


def training_markdown(results: dict, plot_note: str) -> str:
    m, a = results["machine"], results["args"]
    lines = ["# PanoLAM `tiny` trained on procedural heads (CPU)", "",
             f"`{results['command']}` on {m['cpu_model']} ({m['cpu_count']} cores, torch {m['torch']}), revision "
             f"{m['git_revision']}, {m['date']}. Dataset: {a['subjects']} procedural subjects (360 protocol, 32 views, "
             f"128 px), {a['test_count']} held out; training {a['steps']} steps of 2 subjects x 6 views at "
             f"{RESOLUTION} px; D-SSIM stands in for LPIPS (no LPIPS weights here). Held-out evaluation: "
             f"{a['eval_subjects']} test subjects, front view in, front/left/back/right out, {RESOLUTION} px.", "",
             "| model | held-out PSNR dB (all views) | front | left | back | right | SSIM | training time |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in results.get("baselines", {}).items():
        lines.append(f"| baseline: {name.replace('_', ' ')} | {_psnr(r):.2f} | {_views(r)} | "
                     f"{r['per_view']['all']['ssim']:.4f} | - |")
    for name, rows in results.get("curves", {}).items():
        if rows:
            r = rows[-1]
            total = sum(x["train_s"] for x in rows)
            lines.append(f"| {name} (step {r['step']}) | {_psnr(r):.2f} | {_views(r)} | {r['per_view']['all']['ssim']:.4f} "
                         f"| {total / 60:.1f} min |")
    curves = results.get("curves", {})
    if "tiny" in curves:
        lines += ["", "Held-out PSNR of `tiny` during training:", "", "| step | PSNR dB | SSIM |", "|---|---|---|"]
        lines += [f"| {r['step']} | {_psnr(r):.2f} | {r['per_view']['all']['ssim']:.4f} |" for r in curves["tiny"]]
    order = [n for n in ("tiny", "no_c2f", "single_point", "quarter_subjects") if curves.get(n)]
    if len(order) == 4:
        psnrs = {n: _psnr(curves[n][-1]) for n in order}
        holds = psnrs["tiny"] > max(psnrs["no_c2f"], psnrs["single_point"], psnrs["quarter_subjects"])
        lines += ["", f"Paper's ablation ordering (full model best): {'holds' if holds else 'does not hold'} here "
                  f"(" + ", ".join(f"{n} {v:.2f} dB" for n, v in psnrs.items()) + ")."]
    lines += ["", plot_note, ""]
    return "\n".join(lines)


def speed_markdown(results: dict, plot_note: str) -> str:
    rows = results.get("speed_vs_error", [])
    lines = ["# Speed against error: PanoLAM `tiny` (CPU)", "",
             f"Trained `tiny` run of the study (`{results['command']}`); held-out subjects at "
             f"{RESOLUTION} px unless the row varies the resolution. Times are medians per subject on "
             f"{results['machine']['cpu_count']} CPU cores; memory is the peak resident-set increase during the "
             "evaluation (model, images and renders).", "",
             "| varied | value | PSNR dB | SSIM | reconstruct ms | render ms/view | peak MiB |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['axis']} | {r['value']} | {_psnr(r):.2f} | {r['per_view']['all']['ssim']:.4f} | "
                     f"{r['reconstruct_s_median'] * 1000:.0f} | {r['render_ms_per_view_median']:.1f} | {r['peak_mb']:.0f} |")
    curves = results.get("curves", {})
    if curves.get("tiny") and curves.get("single_point"):
        a, b = curves["tiny"][-1], curves["single_point"][-1]
        lines += ["", "K_m (tri-plane samples per virtual-camera ray), from the ablation runs (same steps):", "",
                  "| K_m | PSNR dB | SSIM | reconstruct ms |", "|---|---|---|---|",
                  f"| 1 (the point only) | {_psnr(b):.2f} | {b['per_view']['all']['ssim']:.4f} | "
                  f"{b['reconstruct_s_median'] * 1000:.0f} |",
                  f"| {preset('tiny').ray_samples} per camera x 4 cameras | {_psnr(a):.2f} | "
                  f"{a['per_view']['all']['ssim']:.4f} | {a['reconstruct_s_median'] * 1000:.0f} |"]
    if curves.get("tiny") and curves.get("no_c2f"):
        a, b = curves["tiny"][-1], curves["no_c2f"][-1]
        lines += ["", f"Coarse-to-fine vs direct dense regression (same M_D): PSNR {_psnr(a):.2f} vs {_psnr(b):.2f} dB; "
                  f"reconstruction {a['reconstruct_s_median'] * 1000:.0f} vs {b['reconstruct_s_median'] * 1000:.0f} ms; "
                  f"training {sum(x['train_s'] for x in curves['tiny']) / 60:.1f} vs "
                  f"{sum(x['train_s'] for x in curves['no_c2f']) / 60:.1f} min. "
                  "Network time and memory alone: model_speed.md."]
    lines += ["", plot_note, ""]
    return "\n".join(lines)


def training_plot(results: dict, path: Path) -> str:
    plt = pyplot()
    if plt is None:
        return "Plot skipped: matplotlib is not installed."
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, hist in results.get("history", {}).items():
        steps = np.array([h["step"] for h in hist])
        p = np.array([h["psnr_dense"] for h in hist])
        k = max(1, len(p) // 30)
        smooth = np.convolve(p, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, label=f"{name}: training views", alpha=0.7)
    rows = results.get("curves", {}).get("tiny", [])
    if rows:
        ax.plot([r["step"] for r in rows], [_psnr(r) for r in rows], "ko-", label="tiny: held-out subjects")
    for name, r in results.get("baselines", {}).items():
        ax.axhline(_psnr(r), ls="--", color="gray" if name == "untrained" else "tab:red", label=f"baseline: {name}")
    ax.set(xlabel="step", ylabel="PSNR dB", title="PanoLAM tiny on procedural heads (CPU)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"![learning curve]({path.name})"


def speed_plot(results: dict, path: Path) -> str:
    plt = pyplot()
    rows = results.get("speed_vs_error", [])
    if plt is None or not rows:
        return "Plot skipped: matplotlib is not installed." if plt is None else ""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, axis, label in ((axes[0], "dense_points", "dense Gaussians M_D"), (axes[1], "render_resolution", "render px")):
        sel = [r for r in rows if r["axis"] == axis]
        x = [r["value"] for r in sel]
        ax.plot(x, [_psnr(r) for r in sel], "o-", color="tab:blue")
        ax.set(xlabel=label, ylabel="held-out PSNR dB")
        twin = ax.twinx()
        key = "reconstruct_s_median" if axis == "dense_points" else "render_ms_per_view_median"
        scale = 1000 if axis == "dense_points" else 1
        twin.plot(x, [r[key] * scale for r in sel], "s--", color="tab:orange")
        twin.set_ylabel("reconstruct ms" if axis == "dense_points" else "render ms / view", color="tab:orange")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"![speed against error]({path.name})"


def reports(results: dict) -> None:
    stem = REPORTS / "panolam_training"
    stem.parent.mkdir(parents=True, exist_ok=True)
    write_report(stem, results, training_markdown(results, training_plot(results, stem.with_suffix(".png"))))
    stem = REPORTS / "speed_vs_error"
    write_report(stem, {k: results.get(k) for k in ("machine", "command", "speed_vs_error")},
                 speed_markdown(results, speed_plot(results, stem.with_suffix(".png"))))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--subjects", type=int, default=160)
    parser.add_argument("--test-count", type=int, default=16)
    parser.add_argument("--steps", type=int, default=1200)
    parser.add_argument("--eval-every", type=int, default=200)
    parser.add_argument("--eval-subjects", type=int, default=16)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--dense-counts", type=int, nargs="+", default=[1280, 2500, 5000, 10000, 20000])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128])
    parser.add_argument("--phase", nargs="+", default=["data", "baselines", "train", "speed", "report"],
                        choices=["data", "baselines", "train", "speed", "report"])
    parser.add_argument("--resume-data", action="store_true", help="finish an interrupted dataset")
    parser.add_argument("--threads", type=int, help="torch threads (two studies of 1 thread each share 2 cores well)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    args.command = "python benchmarks/panolam_study.py " + " ".join(argv or sys.argv[1:])
    args.recorded = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    data, manifest = data_phase(args) if "data" in args.phase else (args.out / "heads", args.out / "heads-v1.json")
    if "baselines" in args.phase:
        baseline_phase(args, data, manifest)
    if "train" in args.phase:
        train_phase(args, data, manifest)
    if "speed" in args.phase:
        speed_phase(args, data, manifest)
    if "report" in args.phase:
        reports(load_results(args))


if __name__ == "__main__":
    main()
