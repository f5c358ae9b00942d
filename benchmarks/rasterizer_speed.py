"""Speed and memory of the pure-PyTorch Gaussian rasterizer (``panolam.rasterizer``) on a CPU.

Writes ``benchmarks/reports/rasterizer_speed.{json,md}`` (``rasterizer_speed_quick.*`` with
``--quick``) and, when matplotlib is importable, a PNG plot beside them (otherwise the markdown
says it was skipped).

    python -m benchmarks.rasterizer_speed            # full run, a few minutes on 2 cores
    python -m benchmarks.rasterizer_speed --quick    # smoke run, under 2 minutes
    python -m benchmarks.rasterizer_speed --report-only [--quick]   # rewrite markdown and plot from the JSON
    python -m benchmarks.rasterizer_speed --constants [--report-only]   # the constants' PSNR, under a minute

Scenes look like a head avatar: Gaussians on a noisy ellipsoid (semi-axes 0.20, 0.25, 0.22) around
the origin, scales log-uniform in [0.003, 0.01], random rotations, opacities uniform in [0.2, 1],
seen from 2.7 units (yaw 20, pitch 10 degrees) with EG3D's 18.837 degree FOV. Each configuration
runs in a fresh subprocess: a warm-up forward+backward, then ``repeats`` timed forward passes
(``rasterize``) and backward passes (``loss.backward()`` of a sum over all outputs), wall clock
``time.perf_counter``, medians reported. Peak memory is the peak resident set size
(``getrusage(RUSAGE_SELF).ru_maxrss``) at the end minus the resident size just before the first
render, so it counts everything rendering added (tensors, allocator caches, autograd state); a
fresh process per configuration keeps earlier configurations out of the peak. The baseline
"dense tiles" is the straightforward approach: 16 px tiles, a Python loop over tiles, dense
(pixels x Gaussians) tensors per tile and autograd through everything.

``--constants`` measures what aligning the rasterizer's constants with gsplat's changed (alpha
clamp 0.99 -> 0.999, tile box 3 sigma of the major axis -> gsplat's opacity-aware 3.33 sigma per
axis): PSNR of the images rendered with the former constants, and with each change alone, against
today's (gsplat's), on four heads at 256 px (writes ``benchmarks/reports/rasterizer_constants.*``).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

import panolam.rasterizer as rasterizer
from benchmarks.common import (REPORTS, benchmark_parser, command_line, load_or_measure, machine_info,
                               peak_rss_mb, psnr_db, pyplot, report_name, reproduce, rss_mb, run_child)
from datagen.cameras import camera_position, fov_to_focal, intrinsics, look_at, pixel_intrinsics
from panolam.rasterizer import (ALPHA_MAX, ALPHA_MIN, BLOCK, T_MIN, bin_gaussians, project, rasterize,
                                tile_ranges)

NAME = "rasterizer_speed"
GOAL_SECONDS = 0.5           # the goal: forward + backward, 20K Gaussians, 256 x 256
GOAL_CONFIG = (20_000, 256)
# Every configuration of the rasterizer runs once per round (rounds interleave, so a burst of load
# from other processes spreads over all rows); medians are over all rounds' repeats.
FULL = {"counts": (5_000, 10_000, 20_000, 50_000, 100_000), "resolutions": (128, 256, 512), "rounds": 3,
        "repeats": 5, "repeats_large": 2, "dense_counts": (5_000, 20_000), "dense_repeats": 2}
QUICK = {"counts": (5_000, 20_000), "resolutions": (128, 256), "rounds": 1, "repeats": 3, "repeats_large": 2,
         "dense_counts": (), "dense_repeats": 1}


# ------------------------------------------------------------------------------------------------
# Scene and the dense baseline


def head_scene(n: int, seed: int = 0, opacity=(0.2, 1.0), scale=(0.003, 0.01)) -> dict:
    """n head-avatar-like Gaussians (see the module docstring; opacities uniform in ``opacity``, scales
    log-uniform in ``scale``), float32."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    means = direction * torch.tensor([0.20, 0.25, 0.22]) * (1 + 0.03 * torch.randn(n, 1, generator=g))
    log_scale = math.log(scale[0]) + (math.log(scale[1]) - math.log(scale[0])) * torch.rand(n, 3, generator=g)
    return dict(means=means, quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
                scales=log_scale.exp(), opacities=opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g),
                colors=torch.rand(n, 3, generator=g))


def head_camera(resolution: int):
    """(world-to-camera 4x4, pixel K), float32."""
    c2w = torch.from_numpy(look_at(camera_position(20.0, 10.0, 2.7)))
    K = pixel_intrinsics(torch.from_numpy(intrinsics(fov_to_focal(18.837))), resolution, resolution)
    return torch.linalg.inv(c2w).float(), K.float()


def dense_tiles_rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, tile_size=16):
    """Baseline: per 16 px tile, dense (pixels x Gaussians) alpha, cumprod transmittance, autograd.

    Same projection, tile rule and constants as ``rasterize``; returns (rgb, alpha, expected depth).
    """
    proj = project(means, quats, scales, opacities, viewmat, K, width, height)
    x0, x1, y0, y1 = tile_ranges(proj.means2d, proj.radii, width, height, tile_size)
    order = torch.argsort(proj.depths.detach(), stable=True)
    features = torch.cat([colors, proj.depths[:, None], torch.ones_like(proj.depths)[:, None]], -1)
    rows = []
    for ty in range(-(-height // tile_size)):
        row = []
        for tx in range(-(-width // tile_size)):
            ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, height)) + 0.5
            xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, width)) + 0.5
            pix = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1], -1).reshape(-1, 2)
            ids = order[(proj.valid & (x0 <= tx) & (tx < x1) & (y0 <= ty) & (ty < y1))[order]]
            d = pix[:, None, :] - proj.means2d[ids][None]
            a, b, c = proj.conics[ids].unbind(-1)
            power = -0.5 * (a * d[..., 0] ** 2 + 2 * b * d[..., 0] * d[..., 1] + c * d[..., 1] ** 2)
            alpha = (proj.log_opacities[ids] + power).exp().clamp(max=ALPHA_MAX)
            alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
            trans_after = torch.cumprod(1 - alpha, dim=1)
            trans = torch.cat([torch.ones_like(alpha[:, :1]), trans_after[:, :-1]], 1)
            weight = torch.where(trans_after >= T_MIN, alpha * trans, torch.zeros_like(alpha))
            row.append((weight @ features[ids]).reshape(len(ys), len(xs), -1))
        rows.append(torch.cat(row, 1))
    acc = torch.cat(rows, 0)
    alpha = acc[..., -1:]
    return acc[..., :-2], alpha, acc[..., -2:-1] / alpha.clamp_min(1e-10)


# ------------------------------------------------------------------------------------------------
# One configuration, in a fresh process


def child(config: dict) -> dict:
    """Time forward and backward passes of one configuration and measure its peak memory."""
    if config["variant"] == "phases":
        return phase_breakdown(config["repeats"])
    if config.get("threads"):
        torch.set_num_threads(config["threads"])
    scene = head_scene(config["n"])
    view, K = head_camera(config["resolution"])
    fn = dense_tiles_rasterize if config["variant"] == "dense_tiles" else rasterize
    r = config["resolution"]
    leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
    base_mb = rss_mb()

    def forward():
        return fn(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"], view, K,
                  r, r)

    forward_s, backward_s, cpu_s = [], [], []
    for i in range(config["repeats"] + 1):  # the first pass is a warm-up
        c0, t0 = time.process_time(), time.perf_counter()
        rgb, alpha, depth = forward()
        t1 = time.perf_counter()
        (rgb.sum() + alpha.sum() + depth.sum()).backward()
        t2, c2 = time.perf_counter(), time.process_time()
        if i:
            forward_s.append(t1 - t0)
            backward_s.append(t2 - t1)
            cpu_s.append(c2 - c0)
        for leaf in leaves.values():
            leaf.grad = None
    out = {"forward_s": forward_s, "backward_s": backward_s, "process_cpu_s": cpu_s, "peak_mb": peak_rss_mb() - base_mb,
           "alpha_mean": float(alpha.detach().mean()), "torch_threads": torch.get_num_threads()}
    if config["variant"] == "torch":
        with torch.no_grad():
            proj = project(*(scene[k] for k in ("means", "quats", "scales", "opacities")), view, K, r, r)
            bins = bin_gaussians(proj, r, r)
        out["block_pairs"] = int(bins.gaussian_ids.numel())
    return out


def phase_breakdown(repeats: int) -> dict:
    """Seconds of each stage at the goal configuration (repeats after a warm-up)."""
    from panolam.rasterizer import _Composite, finish

    n, r = GOAL_CONFIG
    scene = head_scene(n)
    view, K = head_camera(r)
    times = {k: [] for k in ("project", "bin", "composite_forward", "composite_backward_and_projection_backward")}
    for i in range(repeats + 1):
        leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
        t0 = time.perf_counter()
        proj = project(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], view, K, r, r)
        t1 = time.perf_counter()
        bins = bin_gaussians(proj, r, r)
        t2 = time.perf_counter()
        acc = _Composite.apply(proj.means2d, proj.conics, proj.log_opacities, leaves["colors"], proj.depths, bins)
        t3 = time.perf_counter()
        sum(o.sum() for o in finish(acc, None)).backward()
        t4 = time.perf_counter()
        if i:
            for key, seconds in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                times[key].append(seconds)
    return times


# ------------------------------------------------------------------------------------------------
# Running it all


def configurations(plan: dict) -> list[dict]:
    """The rasterizer's configurations (run every round); see dense_configurations for the baseline."""
    configs = []
    for n in plan["counts"]:
        configs.append({"variant": "torch", "n": n, "resolution": 256,
                        "repeats": plan["repeats"] if n <= 20_000 else plan["repeats_large"]})
    for r in plan["resolutions"]:
        if r != 256:
            configs.append({"variant": "torch", "n": 20_000, "resolution": r,
                            "repeats": plan["repeats"] if r <= 256 else plan["repeats_large"]})
    configs.append({"variant": "torch", "n": 20_000, "resolution": 256, "repeats": plan["repeats"], "threads": 1})
    configs.append({"variant": "torch", "n": 20_000, "resolution": 256, "repeats": plan["repeats"],
                    "omp_wait_policy": "PASSIVE"})
    configs.append({"variant": "phases", "repeats": plan["repeats"]})
    return configs


def dense_configurations(plan: dict) -> list[dict]:
    return [{"variant": "dense_tiles", "n": n, "resolution": 256, "repeats": plan["dense_repeats"]}
            for n in plan["dense_counts"]]


def measure(plan: dict, mode: str, command: str) -> dict:
    results = {"mode": mode, "command": command, "machine": machine_info(), "plan": plan,
               "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "load_average_before": os.getloadavg(), "rows": []}
    start = time.perf_counter()
    runs = {}
    jobs = [c for _ in range(plan["rounds"]) for c in configurations(plan)] + dense_configurations(plan)
    for config in jobs:
        print(f"[{time.perf_counter() - start:5.0f} s] {config}", flush=True)
        policy = config.get("omp_wait_policy")
        out = run_child(Path(__file__).resolve(), config, {"OMP_WAIT_POLICY": policy} if policy else None)
        runs.setdefault(json.dumps(config), []).append({**out, "load_average": os.getloadavg()[0]})
    for key, outs in runs.items():
        config = json.loads(key)
        if config["variant"] == "phases":
            results["phases"] = {k: statistics.median(sum((o[k] for o in outs), [])) for k in outs[0]
                                 if k != "load_average"}
        else:
            results["rows"].append(aggregate(config, outs))
    results["load_average_after"] = os.getloadavg()
    results["benchmark_seconds"] = time.perf_counter() - start
    return results


def aggregate(config: dict, outs: list[dict]) -> dict:
    """One table row from a configuration's runs: all rounds' samples pooled, medians, worst peak."""
    pooled = {k: sum((o[k] for o in outs), []) for k in ("forward_s", "backward_s", "process_cpu_s")}
    return {**config, **outs[0], **pooled, "rounds": len(outs), "peak_mb": max(o["peak_mb"] for o in outs),
            "load_average": statistics.mean(o["load_average"] for o in outs),
            "forward_median_s": statistics.median(pooled["forward_s"]),
            "backward_median_s": statistics.median(pooled["backward_s"]),
            "cpu_median_s": statistics.median(pooled["process_cpu_s"])}


# ------------------------------------------------------------------------------------------------
# Report


def is_default(row: dict) -> bool:
    """Run with the default thread count and OpenMP wait policy."""
    return not row.get("threads") and not row.get("omp_wait_policy")


def find_row(results: dict, variant: str, n: int, resolution: int, threads=None, policy=None) -> dict | None:
    for row in results["rows"]:
        if ((row["variant"], row["n"], row["resolution"], row.get("threads"), row.get("omp_wait_policy"))
                == (variant, n, resolution, threads, policy)):
            return row
    return None


def goal_verdict(results: dict) -> tuple[bool, float]:
    row = find_row(results, "torch", *GOAL_CONFIG)
    total = row["forward_median_s"] + row["backward_median_s"]
    return total <= GOAL_SECONDS, total


def fwd_bwd(row: dict) -> str:
    total = row["forward_median_s"] + row["backward_median_s"]
    return f"{total:.3f} s (load average {row['load_average']:.1f})"


def table(rows: list[dict]) -> list[str]:
    lines = ["| variant | Gaussians | resolution | threads | OMP wait | forward s | backward s | fwd+bwd s "
             "| process CPU s | peak MiB | block pairs | load avg |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['variant']} | {r['n']:,} | {r['resolution']} | {r['torch_threads']} "
                     f"| {r.get('omp_wait_policy') or 'default'} | {r['forward_median_s']:.3f} "
                     f"| {r['backward_median_s']:.3f} | {r['forward_median_s'] + r['backward_median_s']:.3f} "
                     f"| {r['cpu_median_s']:.3f} | {r['peak_mb']:.0f} | {r.get('block_pairs', '')} "
                     f"| {r['load_average']:.1f} |")
    return lines


def markdown(results: dict, plot_note: str) -> str:
    m = results["machine"]
    met, total = goal_verdict(results)
    goal = find_row(results, "torch", *GOAL_CONFIG)
    single = find_row(results, "torch", *GOAL_CONFIG, threads=1)
    passive = find_row(results, "torch", *GOAL_CONFIG, policy="PASSIVE")
    dense = find_row(results, "dense_tiles", *GOAL_CONFIG) or find_row(results, "dense_tiles", 5_000, 256)
    counts = [r for r in results["rows"] if r["variant"] == "torch" and r["resolution"] == 256 and is_default(r)]
    sizes = [r for r in results["rows"] if r["variant"] == "torch" and r["n"] == 20_000 and is_default(r)]
    others = [r for r in results["rows"] if r not in counts and r not in sizes]
    phases = results["phases"]
    lines = [
        "# Rasterizer speed (pure-PyTorch 3D Gaussian splatting on CPU)", "",
        f"Measured {results['date_utc']} in {results['mode']} mode ({results['benchmark_seconds'] / 60:.1f} min) on "
        f"{m['cpu_model']}, {m['cpu_count']} CPUs, torch {m['torch']} with {m['torch_threads']} threads, "
        f"Python {m['python']}, {m['platform']}, git {m['git_revision']}.", "",
        *reproduce(results["command"]), "",
        f"**Goal (forward + backward of 20K Gaussians at 256x256 <= {GOAL_SECONDS} s): "
        f"{'met' if met else 'not met'}** - median forward {goal['forward_median_s']:.3f} s + backward "
        f"{goal['backward_median_s']:.3f} s = {total:.3f} s with {goal['torch_threads']} threads; peak memory "
        f"{goal['peak_mb']:.0f} MiB (mean load average {goal['load_average']:.1f}). Same configuration with one "
        f"thread: {fwd_bwd(single)}; with two threads and `OMP_WAIT_POLICY=PASSIVE`: {fwd_bwd(passive)}.", "",
        f"Load average (1 min) was {results['load_average_before'][0]:.1f} before and "
        f"{results['load_average_after'][0]:.1f} after the run (per row in the tables). Above the core count "
        "other processes share the CPUs and wall times grow; two-thread runs suffer most because libgomp's "
        "default wait policy spins at every parallel region's barrier while the other thread is descheduled. "
        "The `OMP_WAIT_POLICY=PASSIVE` row (threads sleep instead) and the single-thread row show what to "
        "expect on a shared machine.", "",
        f"Method: one fresh subprocess per row and round ({results['plan']['rounds']} interleaved round(s) of every "
        "row of the rasterizer, one of the baseline); a warm-up pass, then timed repeats, medians over all "
        "rounds' repeats; load avg is the mean over rounds; forward = "
        "`rasterize(...)`, backward = `(rgb.sum() + alpha.sum() + depth.sum()).backward()`; process CPU = "
        "`time.process_time` for forward + backward (both threads). Peak MiB = `ru_maxrss` at the end minus "
        f"the resident size before the first render. Block pairs = ({BLOCK}x{BLOCK} px block, Gaussian) pairs "
        "after culling. Scenes: see the docstring of `benchmarks/rasterizer_speed.py`.", "",
        "## Against the number of Gaussians (256x256)", "", *table(counts), "",
        "## Against the resolution (20K Gaussians)", "", *table(sizes), "",
        "## Single thread, passive OpenMP waiting and the dense-tiles baseline", "", *table(others), "",
    ]
    if not dense:
        lines += ["The dense-tiles baseline is not run in quick mode.", ""]
    if dense:
        ours = find_row(results, "torch", dense["n"], dense["resolution"])
        speedup = (dense["forward_median_s"] + dense["backward_median_s"]) / (
            ours["forward_median_s"] + ours["backward_median_s"])
        lines += [f"At {dense['n']:,} Gaussians the dense-tiles baseline takes {speedup:.0f}x as long as `rasterize` "
                  f"and {dense['peak_mb'] / max(ours['peak_mb'], 1):.0f}x the memory.", ""]
    lines += [
        "## Where the time goes (20K Gaussians, 256x256, medians)", "",
        "| stage | median s |", "|---|---:|",
        *[f"| {k.replace('_', ' ')} | {v:.3f} |" for k, v in phases.items()], "",
        "Compositing dominates: each step evaluates every pixel of a block against up to k Gaussians of "
        "its depth-sorted list (about a dozen tensor ops forward, two dozen backward, three transcendentals "
        "each way); binning drops (block, Gaussian) pairs whose alpha is below 1/255 on the whole block, so "
        "roughly half of the evaluated (pixel, Gaussian) pairs contribute. Two threads used "
        f"{goal['cpu_median_s']:.3f} s of process CPU against {single['cpu_median_s']:.3f} s for one: "
        f"{100 * (1 - single['cpu_median_s'] / goal['cpu_median_s']):.0f}% of it goes to waiting at the ends "
        "of parallel regions and to work that does not split (Python, small ops), as the steps are many "
        "medium-sized ops.", "",
        plot_note, "",
    ]
    return "\n".join(lines)


def plot(results: dict, path: Path) -> str:
    plt = pyplot()
    if plt is None:
        return "Plot skipped: matplotlib is not installed (`pip install matplotlib`, then `--report-only`)."
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, rows, label in (
            (axes[0], "n", [r for r in results["rows"] if r["variant"] == "torch" and r["resolution"] == 256
                            and is_default(r)], "Gaussians (256x256)"),
            (axes[1], "resolution", [r for r in results["rows"] if r["variant"] == "torch" and r["n"] == 20_000
                                     and is_default(r)], "resolution (20K Gaussians)")):
        rows = sorted(rows, key=lambda r: r[key])
        xs = [r[key] for r in rows]
        ax.plot(xs, [r["forward_median_s"] for r in rows], "o-", label="forward")
        ax.plot(xs, [r["backward_median_s"] for r in rows], "s-", label="backward")
        ax.set_xlabel(label)
        ax.set_ylabel("seconds (median)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return f"Plot: `{path.name}`."


def report_stem(mode: str) -> Path:
    """benchmarks/reports/rasterizer_speed (full mode) or rasterizer_speed_quick."""
    return REPORTS / report_name(NAME, mode == "quick")


def write_reports(results: dict) -> None:
    stem = report_stem(results["mode"])
    stem.parent.mkdir(parents=True, exist_ok=True)
    note = plot(results, stem.with_suffix(".png"))
    stem.with_suffix(".md").write_text(markdown(results, note))
    print(f"wrote {stem}.md")


# ------------------------------------------------------------------------------------------------
# Constants: the former ones against gsplat's


CONSTANTS_NAME = "rasterizer_constants"
CONSTANTS_RESOLUTION = 256


def three_sigma_radii(cov2d, opacities):
    """The former tile box: a square of half size ``ceil(3 sqrt(lambda_max(cov2d)))`` px (the reference
    3DGS rule, ``mid^2 - det`` floored at 0.1); same signature as ``rasterizer.tile_radii``."""
    a, b, c = cov2d.unbind(-1)
    r = torch.ceil(3.0 * torch.sqrt(0.5 * (a + c) + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp_min(0.1))))
    return torch.stack([r, r], -1)


# Name -> (alpha clamp, tile box rule); each is rendered and compared with today's constants.
CONSTANT_VARIANTS = {
    "former (0.99, 3 sigma box)": (0.99, three_sigma_radii),
    "alpha clamp 0.999 only": (0.999, three_sigma_radii),
    "gsplat box only": (0.99, rasterizer.tile_radii),
}


@contextlib.contextmanager
def rasterizer_constants(alpha_max: float, radii_rule):
    """Render with another alpha clamp and tile box rule (module attributes, restored on exit)."""
    saved = rasterizer.ALPHA_MAX, rasterizer.tile_radii
    rasterizer.ALPHA_MAX, rasterizer.tile_radii = alpha_max, radii_rule
    try:
        yield
    finally:
        rasterizer.ALPHA_MAX, rasterizer.tile_radii = saved


def constant_scenes():
    """(name, Gaussians dict, background (3,)) of the four heads, float32."""
    from panolam.config import preset
    from panolam.model import PanoLAM

    torch.manual_seed(0)
    model = PanoLAM(preset("tiny")).eval()
    with torch.no_grad():
        dense = model(torch.full((1, 3, 128, 128), 0.5)).dense
    yield ("PanoLAM `tiny` at initialisation over white (4,992 Gaussians, opacity 0.5: training's first renders)",
           {k: getattr(dense, k)[0] for k in ("means", "quats", "scales", "opacities", "colors")}, torch.ones(3))
    yield ("procedural head over black (20K Gaussians, opacities U[0.2, 1])", head_scene(20_000), torch.zeros(3))
    yield ("opaque procedural head over black (20K Gaussians, opacities U[0.95, 1]: a converged surface)",
           head_scene(20_000, opacity=(0.95, 1.0)), torch.zeros(3))
    yield ("coarse opaque procedural head over black (2K Gaussians 5x larger, 4 to 14 px sigma, opacities "
           "U[0.95, 1])", head_scene(2_000, opacity=(0.95, 1.0), scale=(0.015, 0.05)), torch.zeros(3))


def measure_constants(command: str) -> dict:
    """Per scene and variant: PSNR (dB, peak 1), largest difference and share of pixels that differ by
    more than 1/255 in any channel, of the RGB image against today's constants."""
    r = CONSTANTS_RESOLUTION
    view, K = head_camera(r)
    rows = []
    with torch.no_grad():
        for name, scene, background in constant_scenes():
            args = (*(scene[k] for k in ("means", "quats", "scales", "opacities", "colors")), view, K, r, r)
            today = rasterizer.rasterize(*args, background=background)[0]
            for variant, (alpha_max, rule) in CONSTANT_VARIANTS.items():
                with rasterizer_constants(alpha_max, rule):
                    other = rasterizer.rasterize(*args, background=background)[0]
                diff = (other - today).abs()
                rows.append({"scene": name, "variant": variant, "psnr_db": psnr_db(float(diff.square().mean())),
                             "max_abs": float(diff.max()),
                             "pixels_over_1_255": float((diff.amax(-1) > 1 / 255).float().mean())})
    return {"command": command, "machine": machine_info(), "resolution": r, "rows": rows,
            "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def constants_markdown(results: dict) -> str:
    lines = ["# Rasterizer constants: former against gsplat's", "",
             f"Measured {results['date_utc']} on the CPU (torch {results['machine']['torch']}, git "
             f"{results['machine']['git_revision']}); nothing here ran on a GPU or through gsplat: today's "
             "constants are gsplat's (>= 1.5, \"classic\"), rendered by the pure-PyTorch rasterizer.", "",
             *reproduce(results["command"]), "",
             f"RGB at {results['resolution']}x{results['resolution']} px from 2.7 units (yaw 20, pitch 10 degrees, "
             "EG3D's 18.837 degree FOV), each variant against today's constants (alpha clamp 0.999, tile box "
             "min(3.33, sqrt(2 ln(255 o))) sigma per axis, which holds the whole alpha >= 1/255 ellipse). "
             "PSNR with peak 1; 'over 1/255' is the share of pixels that differ by more than 1/255 in a channel.",
             "", "| scene | variant | PSNR dB | max abs diff | pixels over 1/255 |", "|---|---|---:|---:|---:|"]
    for row in results["rows"]:
        psnr = "identical" if row["psnr_db"] is None else f"{row['psnr_db']:.1f}"
        lines.append(f"| {row['scene']} | {row['variant']} | {psnr} | {row['max_abs']:.4f} "
                     f"| {100 * row['pixels_over_1_255']:.2f} % |")
    return "\n".join(lines + [""])


def constants_main(report_only: bool, argv) -> None:
    stem = REPORTS / CONSTANTS_NAME
    results = load_or_measure(stem.with_suffix(".json"), report_only,
                              lambda: measure_constants(command_line(Path(__file__), argv)))
    stem.with_suffix(".md").write_text(constants_markdown(results))
    print(f"wrote {stem}.md")


def main(argv=None) -> None:
    parser = benchmark_parser(__doc__, quick_help="a smoke run, under 2 minutes",
                              report_only_help="rewrite the markdown and plot from the JSON")
    parser.add_argument("--constants", action="store_true",
                        help="PSNR of the former constants against gsplat's (rasterizer_constants.md)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return
    if args.constants:
        constants_main(args.report_only, argv)
        return
    mode = "quick" if args.quick else "full"
    results = load_or_measure(report_stem(mode).with_suffix(".json"), args.report_only,
                              lambda: measure(QUICK if args.quick else FULL, mode, command_line(Path(__file__), argv)))
    write_reports(results)
    if not args.report_only:
        met, total = goal_verdict(results)
        print(f"goal ({GOAL_SECONDS} s for fwd+bwd, 20K, 256^2): {'met' if met else 'not met'} ({total:.3f} s)")


if __name__ == "__main__":
    main()
