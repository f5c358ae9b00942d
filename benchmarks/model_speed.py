"""Forward time and peak memory of the PanoLAM network; coarse-to-fine against direct dense regression.

    python benchmarks/model_speed.py            # a few minutes on 2 cores
    python benchmarks/model_speed.py --quick    # tiny rows only

Writes ``benchmarks/reports/model_speed.{json,md,png}``. Each row runs in a fresh process: one
warm-up, then ``repeats`` timed passes on one 512 x 512 image (batch 1), medians of
``time.perf_counter``. Memory is the peak resident set size during the timed passes minus the
resident size before them (CPU), or ``torch.cuda.max_memory_allocated`` (GPU). "forward" is the
reconstruction alone (no_grad); "fwd+bwd" adds the backward pass of a loss on every dense Gaussian
attribute (no rendering, so the network is what is measured).

``full`` rows use the paper's sizes with the DINOv2 ViT-L/14 encoder replaced by a stub that
returns 37 x 37 tokens of 512 channels: no DINOv2 weights exist on this machine, and the frozen
encoder costs the same in both variants. Its own cost is measured separately with random weights
(a ViT-L/14 of the official shape built from its config; the time does not depend on the weights).
The coarse-to-fine comparison holds everything else equal: the same blocks, heads and tri-plane
branch; "direct" runs the attention stack on all M_D points instead of the template's vertices.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn as nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.common import REPORTS, machine_info, peak_rss_mb, pyplot, rss_mb, run_child, write_report  # noqa: E402

NAME = "model_speed"
PAPER = "paper (A100): reconstruction 0.11 s; coarse-to-fine ~6x faster and ~2.4x less memory than direct"


class TokenStub(nn.Module):
    """DINOv2 ViT-L/14 at 518 px stand-in: 37 x 37 tokens of ``out_dim`` channels from the image."""

    def __init__(self, out_dim):
        super().__init__()
        self.out_dim, self.num_tokens, self.image_size = out_dim, 37 * 37, 518
        self.proj = nn.Linear(3, out_dim)

    def forward(self, x):
        return self.proj(nn.functional.interpolate(x, size=(37, 37), mode="area").flatten(2).transpose(1, 2))


def child(config: dict) -> dict:
    from panolam import model as model_module
    from panolam.config import preset
    torch.set_num_threads(config["threads"])
    if config["encoder"] == "vit_l":
        return vit_l_child(config)
    if config["stub_encoder"]:
        model_module.build_encoder = lambda kind, weights, out_dim, **kw: TokenStub(out_dim)
    torch.manual_seed(0)
    m = model_module.PanoLAM(preset(config["config"], dense_points=config["dense_points"]))
    x = torch.rand(1, 3, 512, 512)

    def forward():
        with torch.no_grad():
            m(x)

    def forward_backward():
        rec = m(x)
        d = rec.dense
        (d.means.sum() + d.scales.sum() + d.colors.sum() + d.opacities.sum() + d.quats.sum()).backward()
        m.zero_grad(set_to_none=True)

    out = {"dense_count": m.dense_count, "parameters": sum(p.numel() for p in m.parameters() if p.requires_grad)}
    for name, fn in (("forward", forward), ("fwd_bwd", forward_backward)):
        if name == "fwd_bwd" and not config["backward"]:
            continue
        fn()
        base = rss_mb()
        Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS to the current RSS
        times = []
        for _ in range(config["repeats"]):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[f"{name}_s"] = statistics.median(times)
        out[f"{name}_peak_mb"] = _hwm_mb() - base
    return out


def _hwm_mb() -> float:
    """Peak RSS since the last clear_refs reset (VmHWM), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return peak_rss_mb()


def vit_l_child(config: dict) -> dict:
    from transformers import Dinov2Config, Dinov2Model
    model = Dinov2Model(Dinov2Config(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16,
                                     intermediate_size=4096, patch_size=14, image_size=518)).eval()
    x = torch.rand(1, 3, 518, 518)
    with torch.no_grad():
        model(x, output_hidden_states=True)
        base = rss_mb()
        Path("/proc/self/clear_refs").write_text("5")
        t0 = time.perf_counter()
        model(x, output_hidden_states=True)
        seconds = time.perf_counter() - t0
    return {"forward_s": seconds, "forward_peak_mb": _hwm_mb() - base,
            "parameters": sum(p.numel() for p in model.parameters())}


def plan(quick: bool) -> list[dict]:
    rows = []
    counts = (5000, 10000) if quick else (5000, 10000, 20000)
    for n in counts:
        for cfg in ("tiny", "tiny+no_c2f"):
            rows.append(dict(config=cfg, dense_points=n, stub_encoder=False, encoder="model", backward=True,
                             repeats=3, threads=2))
    if not quick:
        for cfg in ("full", "full+no_c2f"):
            rows.append(dict(config=cfg, dense_points=10000, stub_encoder=True, encoder="model", backward=False,
                             repeats=1, threads=2))
        rows.append(dict(config="vit_l", dense_points=0, stub_encoder=False, encoder="vit_l", backward=False,
                         repeats=1, threads=2))
    return rows


def measure(quick: bool) -> dict:
    rows = []
    for config in plan(quick):
        print(f"measuring {config['config']} M_D={config['dense_points']} ...", flush=True)
        try:
            rows.append({**config, **run_child(Path(__file__).resolve(), config)})
        except RuntimeError as e:
            rows.append({**config, "error": str(e).splitlines()[-1]})
    return {"mode": "quick" if quick else "full", "machine": machine_info(), "rows": rows,
            "command": "python benchmarks/model_speed.py" + (" --quick" if quick else "")}


def _ratio(rows, config_a, config_b, n, key):
    a = next((r for r in rows if r["config"] == config_a and r["dense_points"] == n and key in r), None)
    b = next((r for r in rows if r["config"] == config_b and r["dense_points"] == n and key in r), None)
    return None if a is None or b is None else b[key] / a[key]


def markdown(results: dict, plot_note: str) -> str:
    m = results["machine"]
    lines = [f"# PanoLAM network: speed and memory ({results['mode']})", "",
             f"`{results['command']}` on {m['cpu_model']} ({m['cpu_count']} cores, torch {m['torch']}, "
             f"{m['torch_threads']} threads, load average {m['load_average'][0]:.2f}), revision {m['git_revision']}, "
             f"{m['date']}. No GPU here: every row is CPU. {PAPER}.", "",
             "| config | M_D (asked / got) | trainable params | forward s | forward peak MiB | fwd+bwd s | "
             "fwd+bwd peak MiB |", "|---|---|---|---|---|---|---|"]
    f = lambda r, k, fmt: (fmt.format(r[k]) if k in r else "-")  # noqa: E731
    for r in results["rows"]:
        if "error" in r:
            lines.append(f"| {r['config']} | {r['dense_points']} | failed: {r['error']} | | | | |")
            continue
        lines.append(f"| {r['config']} | {r['dense_points']} / {r.get('dense_count', '-')} | "
                     f"{r['parameters'] / 1e6:.1f} M | {f(r, 'forward_s', '{:.3f}')} | {f(r, 'forward_peak_mb', '{:.0f}')} "
                     f"| {f(r, 'fwd_bwd_s', '{:.3f}')} | {f(r, 'fwd_bwd_peak_mb', '{:.0f}')} |")
    lines += ["", "Direct dense regression relative to coarse-to-fine (ratio > 1: coarse-to-fine is better):", "",
              "| preset | M_D | forward time | forward memory | fwd+bwd time | fwd+bwd memory |", "|---|---|---|---|---|---|"]
    rows = results["rows"]
    for base in ("tiny", "full"):
        for n in sorted({r["dense_points"] for r in rows if r["config"] == base}):
            vals = [_ratio(rows, base, f"{base}+no_c2f", n, k) for k in ("forward_s", "forward_peak_mb", "fwd_bwd_s",
                                                                          "fwd_bwd_peak_mb")]
            lines.append(f"| {base} | {n} | " + " | ".join("-" if v is None else f"{v:.2f}x" for v in vals) + " |")
    lines += ["", "`full` rows: encoder replaced by a 37 x 37-token stub (see the script's docstring); "
              "`vit_l` is the DINOv2 ViT-L/14 encoder alone at 518 px with random weights, so a CPU "
              "reconstruction with `full` costs about the sum of the two.", "", plot_note, ""]
    return "\n".join(lines)


def plot(results: dict, path: Path) -> str:
    plt = pyplot()
    if plt is None:
        return "Plot skipped: matplotlib is not installed (`pip install matplotlib`)."
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for cfg, style in (("tiny", "o-"), ("tiny+no_c2f", "s--")):
        rows = [r for r in results["rows"] if r["config"] == cfg and "fwd_bwd_s" in r]
        n = [r["dense_count"] for r in rows]
        axes[0].plot(n, [r["fwd_bwd_s"] for r in rows], style, label=cfg)
        axes[1].plot(n, [r["fwd_bwd_peak_mb"] for r in rows], style, label=cfg)
    axes[0].set(xlabel="dense Gaussians M_D", ylabel="forward + backward, s", title="time (CPU, batch 1)")
    axes[1].set(xlabel="dense Gaussians M_D", ylabel="peak memory, MiB", title="memory")
    for ax in axes:
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"![time and memory]({path.name})"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        import json
        print(json.dumps(child(json.loads(args.child))))
        return
    results = measure(args.quick)
    stem = REPORTS / (NAME if not args.quick else f"{NAME}_quick")
    stem.parent.mkdir(parents=True, exist_ok=True)
    write_report(stem, results, markdown(results, plot(results, stem.with_suffix(".png"))))


if __name__ == "__main__":
    main()
