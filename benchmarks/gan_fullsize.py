"""The 3D-GAN generators at their released sizes: CPU time per stage, FLOPs per image, the GPU bound.

Writes ``benchmarks/reports/gan_fullsize.{json,md}`` (``gan_fullsize_quick.*`` with ``--quick``).

    python -m benchmarks.gan_fullsize                # one 32-view 512 px subject per model (~15 min, 2 cores)
    python -m benchmarks.gan_fullsize --quick        # 2 views per model (~3 min)
    python -m benchmarks.gan_fullsize --report-only  # rewrite the markdown from the JSON

Each generator is built from the released models' constructor kwargs (EG3D ``ffhq512-128`` /
``ffhqrebalanced512-128`` as ``train.py --cfg=ffhq`` builds them for a 512 dataset; PanoHead's
training configuration, which SphereHead's released model is assumed to share): mapping width 512,
backbone ``channel_base`` 32768 / ``channel_max`` 512, tri-planes 256 px, 128 px neural render with
48 + 48 samples per ray, ``SuperresolutionHybrid8XDC`` to 512 px. The weights are random (none can
be downloaded here): time and FLOPs depend on the sizes, not on the values. Stages are timed by
wrapping the generator's methods during a normal ``render`` (``benchmarks.common.stage_clock``);
FLOPs are counted with ``torch.utils.flop_counter`` on one view (convolutions and matrix products;
grid sampling, activations and compositing are not counted, so the figure is a lower bound).
"""
from __future__ import annotations

import functools
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from benchmarks.common import (bullets, fmt, load_note, measurement_header, report_main, reproduce,
                               run_sections, stage_clock, table)
from datagen.cameras import sample_views
from datagen.generators import gan as gan_module
from datagen.generators.base import STREAM_CAMERAS, subject_rng
from datagen.generators.gan import GANConfig, GANHeads
from datagen.gans.checkpoint import LoadedCheckpoint
from datagen.gans.kinds import GAN_KINDS, KINDS
from datagen.gans.triplane import TriPlaneGenerator
from datagen.dataset.shards import encode_subject

NAME = "gan_fullsize"
MODELS = KINDS
PROTOCOL = {kind.name: kind.protocol for kind in GAN_KINDS.values()}
RESOLUTION = 512
PAPER_SUBJECTS = 165_000  # 48K EG3D + 117K SphereHead subjects kept after curation
VIEWS = 32
GOAL_IMAGES_PER_S = 200
# One H100 SXM5 (NVIDIA's datasheet, dense, no sparsity): TFLOP/s and memory bandwidth.
H100 = {"fp16_tensor_tflops": 989.0, "tf32_tensor_tflops": 495.0, "fp32_tflops": 67.0, "hbm_tb_s": 3.35}
STAGES = ("mapping", "backbone", "background", "march", "super_resolution", "encoding")


def released_kwargs(kind: str) -> dict:
    """Constructor kwargs of the released 512 models (what their pickles store as ``init_kwargs``)."""
    rendering = {"image_resolution": 512, "disparity_space_sampling": False, "clamp_mode": "softplus",
                 "superresolution_module": "training.superresolution.SuperresolutionHybrid8XDC",
                 "c_gen_conditioning_zero": False, "c_scale": 1.0, "superresolution_noise_mode": "none",
                 "decoder_lr_mul": 1.0, "sr_antialias": True, "depth_resolution": 48,
                 "depth_resolution_importance": 48, "ray_start": 2.25, "ray_end": 3.3, "box_warp": 1,
                 "avg_camera_radius": 2.7, "avg_camera_pivot": [0, 0, 0.2]}
    if kind != "eg3d":
        rendering.update(decoder_activation="none", use_torgb_raw=True, triplane_size=256, triplane_depth=3,
                         use_background=True, density_noise=0)
    return {"z_dim": 512, "w_dim": 512, "mapping_kwargs": {"num_layers": 2}, "channel_base": 32768,
            "channel_max": 512, "fused_modconv_default": "inference_only", "rendering_kwargs": rendering,
            "num_fp16_res": 0, "sr_num_fp16_res": 4, "conv_clamp": None, "c_dim": 25, "img_resolution": 512,
            "img_channels": 3, "sr_kwargs": {"channel_base": 32768, "channel_max": 512,
                                             "fused_modconv_default": "inference_only"}}


def build(kind: str, device: str = "cpu") -> GANHeads:
    torch.manual_seed(0)
    kwargs = released_kwargs(kind)
    G = TriPlaneGenerator(kind, **kwargs).eval().requires_grad_(False)
    G.neural_rendering_resolution = 128
    loaded = LoadedCheckpoint(kind, G, kwargs, kwargs["rendering_kwargs"], 128, "random-init", "released-size")
    return GANHeads(kind, loaded, GANConfig(device=device))


def parameters(g: GANHeads) -> dict:
    G = g.G
    count = lambda m: sum(p.numel() for p in m.parameters()) if m is not None else 0  # noqa: E731
    return {"total": count(G), "backbone": count(G.backbone), "super_resolution": count(G.superresolution),
            "decoder": count(G.decoder), "background": count(getattr(G, "bcg_synthesis", None))}


def stage_targets(g: GANHeads) -> dict:
    targets = {"mapping": (g.G, "mapping"), "backbone": (g.G, "planes"), "march": (gan_module, "render_rays_chunked"),
               "super_resolution": (g.G, "compose")}
    if g.name != "eg3d":
        targets["background"] = (g.G, "background")
    return targets


# ------------------------------------------------------------------------------------------------
# Measuring

def time_subject(g: GANHeads, views: int) -> dict:
    """Wall seconds per stage for one subject of ``views`` views at 512 px, encoding included."""
    cams = sample_views(PROTOCOL[g.name], subject_rng(0, 0, STREAM_CAMERAS), views)
    start = time.perf_counter()
    with stage_clock(stage_targets(g)) as seconds:
        subject = g.sample_subject(0, 0)
        out = g.render(subject, cams, RESOLUTION)
    t0 = time.perf_counter()
    encode_subject({"subject_id": "subj00000000"}, out.rgb, out.alpha, out.depth, subject.arrays)
    seconds["encoding"] = time.perf_counter() - t0
    total = time.perf_counter() - start
    seconds = {k: seconds.get(k, 0.0) for k in STAGES}
    return {"views": views, "seconds": seconds, "total_s": total,
            "other_s": total - sum(seconds.values()), "images_per_s": views / total}


def count_flops(g: GANHeads) -> dict:
    """FLOPs (convolutions and matrix products) of the per-subject work and of one rendered view."""
    cams = sample_views(PROTOCOL[g.name], subject_rng(0, 1, STREAM_CAMERAS), 1)
    with FlopCounterMode(display=False) as per_subject:
        subject = g.sample_subject(0, 1)
    counters = {}
    original = gan_module.render_rays_chunked

    def counted_march(*args, **kwargs):  # a second counter inside the first: both see the march
        with FlopCounterMode(display=False) as march:
            result = original(*args, **kwargs)
        counters["march"] = march.get_total_flops()
        return result

    gan_module.render_rays_chunked = counted_march
    try:
        with FlopCounterMode(display=False) as per_view:
            g.render(subject, cams, RESOLUTION)
    finally:
        gan_module.render_rays_chunked = original
    view = per_view.get_total_flops()
    return {"per_subject": per_subject.get_total_flops(), "per_view": view, "march_per_view": counters["march"],
            "super_resolution_per_view": view - counters["march"]}


def time_on_cuda(kind: str) -> dict | None:
    """Images/s of 32-view 512 px subjects on the first CUDA device (default precision), or None."""
    if not torch.cuda.is_available():
        return None
    g = build(kind, "cuda")
    cams = sample_views(PROTOCOL[kind], subject_rng(0, 0, STREAM_CAMERAS), VIEWS)
    g.render(g.sample_subject(0, 0), cams, RESOLUTION)  # warm-up
    torch.cuda.synchronize()
    start = time.perf_counter()
    for index in range(1, 4):
        g.render(g.sample_subject(0, index), cams, RESOLUTION)
    torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    return {"device": torch.cuda.get_device_name(), "precision": g.describe()["config"]["precision"],
            "plan": vars(g.plan), "images_per_s": 3 * VIEWS / seconds}


def measure_model(kind: str, views: int) -> dict:
    print(f"  {kind}: building the released-size generator", flush=True)
    g = build(kind)
    flops = count_flops(g)
    print(f"  {kind}: {flops['per_view'] / 1e9:.0f} GFLOP per view; timing {views} views", flush=True)
    timing = time_subject(g, views)
    return {"parameters": parameters(g), "plan": vars(g.plan), "flops": flops, "timing": timing,
            "cuda": time_on_cuda(kind),
            "samples_per_ray": [g.G.rendering_kwargs["depth_resolution"],
                                g.G.rendering_kwargs["depth_resolution_importance"]],
            "neural_rendering_resolution": g.G.neural_rendering_resolution}


def measure(quick: bool, command: str) -> dict:
    views = 2 if quick else VIEWS
    results = measurement_header("quick" if quick else "default", command, {"views": views, "models": list(MODELS)})
    sections = tuple((kind, f"{kind} at full size", functools.partial(measure_model, kind, views)) for kind in MODELS)
    run_sections(results, sections, (), lambda: None)
    return results


# ------------------------------------------------------------------------------------------------
# The GPU bound, computed from the JSON

def flops_per_image(d: dict) -> float:
    """Counted FLOPs per 512 px image with the per-subject work spread over the 32 views."""
    return d["flops"]["per_view"] + d["flops"]["per_subject"] / VIEWS


def gpu_bound(d: dict, tflops: float) -> dict:
    rate = tflops * 1e12 / flops_per_image(d)
    return {"images_per_s": rate, "gpu_hours_paper": PAPER_SUBJECTS * VIEWS / rate / 3600}


# ------------------------------------------------------------------------------------------------
# Markdown

def conclusions(results: dict) -> list[str]:
    lines = []
    for kind in MODELS:
        d = results[kind]
        t, f = d["timing"], d["flops"]
        share = {k: v / t["total_s"] for k, v in t["seconds"].items()}
        top = sorted(share, key=share.get, reverse=True)[:2]
        fp16 = gpu_bound(d, H100["fp16_tensor_tflops"])
        lines.append(f"{kind}: {t['total_s'] / t['views']:.2f} s per 512 px image on this CPU "
                     f"({t['images_per_s']:.2f} images/s); {flops_per_image(d) / 1e9:.0f} GFLOP per image, "
                     f"{100 * f['super_resolution_per_view'] / f['per_view']:.0f} % of it in the super-resolution; "
                     f"time goes to {top[0].replace('_', ' ')} ({100 * share[top[0]]:.0f} %) and "
                     f"{top[1].replace('_', ' ')} ({100 * share[top[1]]:.0f} %). At the H100's dense fp16 peak the "
                     f"counted FLOPs allow at most {fp16['images_per_s']:,.0f} images/s "
                     f"({fp16['gpu_hours_paper']:.1f} GPU-hours for {PAPER_SUBJECTS // 1000}K x {VIEWS} images).")
    worst = min(gpu_bound(results[k], H100["fp16_tensor_tflops"])["images_per_s"] for k in MODELS)
    need = GOAL_IMAGES_PER_S / worst
    lines.append(f"The goal of {GOAL_IMAGES_PER_S} images/s on one H100 needs {100 * need:.0f} % of the fp16 peak "
                 f"for the heaviest model (the super-resolution convolutions run on tensor cores in fp16, as the "
                 f"originals do on CUDA); the ray march is memory-bound (grid sampling, not counted), so the FLOP "
                 f"bound is an upper limit.")
    measured = {k: results[k]["cuda"] for k in MODELS if results[k].get("cuda")}
    if measured:
        lines.append("Measured on " + ", ".join(f"{d['device']} ({k}, {d['precision']}): {d['images_per_s']:.0f} "
                                                f"images/s" for k, d in measured.items()) + ".")
    else:
        lines.append("Not measured on a GPU: none was available to this run (the script times one when CUDA is "
                     "present).")
    return lines


def stage_table(results: dict) -> list[str]:
    rows = []
    for kind in MODELS:
        t = results[kind]["timing"]
        rows.append([kind, t["views"], *(fmt(t["seconds"][s], 1) for s in STAGES), fmt(t["other_s"], 1),
                     fmt(t["total_s"], 1), fmt(t["total_s"] / t["views"], 2)])
    return table(["model", "views", *(f"{s.replace('_', ' ')} s" for s in STAGES), "other s", "total s",
                  "s per image"], rows)


def flop_table(results: dict) -> list[str]:
    rows = []
    for kind in MODELS:
        d = results[kind]
        f, p = d["flops"], d["parameters"]
        rows.append([kind, f"{p['total'] / 1e6:.1f} M", f"{f['per_subject'] / 1e9:.1f}",
                     f"{f['march_per_view'] / 1e9:.1f}", f"{f['super_resolution_per_view'] / 1e9:.1f}",
                     f"{flops_per_image(d) / 1e9:.1f}", f"{d['plan']['rays']} rays / {d['plan']['images']} views"])
    return table(["model", "parameters", "per-subject GFLOP", "march GFLOP/view", "SR + ToRGB GFLOP/view",
                  "GFLOP per image", "CPU chunk plan"], rows)


def bound_table(results: dict) -> list[str]:
    rows = []
    for kind in MODELS:
        d = results[kind]
        cells = [kind]
        for key in ("fp16_tensor_tflops", "tf32_tensor_tflops", "fp32_tflops"):
            b = gpu_bound(d, H100[key])
            cells.append(f"{b['images_per_s']:,.0f} img/s ({b['gpu_hours_paper']:.1f} h)")
        cells.append(f"{d['timing']['images_per_s']:.3f} img/s")
        rows.append(cells)
    return table(["model", f"H100 fp16 tensor ({H100['fp16_tensor_tflops']:.0f} TFLOP/s)",
                  f"H100 TF32 tensor ({H100['tf32_tensor_tflops']:.0f})", f"H100 fp32 ({H100['fp32_tflops']:.0f})",
                  "this CPU, measured"], rows)


def markdown(results: dict) -> str:
    m = results["machine"]
    views = results["plan"]["views"]
    lines = ["# 3D-GAN generators at their released size: where the time goes, FLOPs, the GPU bound", "",
             "Generated by `benchmarks/gan_fullsize.py` from its JSON; do not edit.", "",
             "Released-size EG3D / PanoHead / SphereHead with random weights (no checkpoint can be downloaded "
             "here; time and FLOPs depend on the sizes only): 128 px neural render, 48 + 48 samples per ray, "
             "256 px tri-planes, 8XDC super-resolution to 512 px. EG3D renders the `frontal` protocol, the "
             "others `360`.", "",
             f"Measured {results['date_utc']} on {m['cpu_model']} ({m['usable_cpus']} usable CPUs, torch "
             f"{m['torch']} with {m['torch_threads']} threads), git {m['git_revision']}.", "",
             load_note(results, m["torch_threads"], "**other work competed for the CPUs**: the times are inflated."),
             "", *reproduce(results["command"]), "", "## Conclusions", "", *bullets(conclusions(results)), "",
             f"## Time per stage: one subject, {views} views at {RESOLUTION} px (wall seconds)", "",
             "mapping: z -> w; backbone: StyleGAN2 synthesis of the planes (SphereHead: and its two projections); "
             "background: PanoHead/SphereHead's background synthesis; march: ray marching with the plane "
             "sampling and the decoder, all views; super resolution: compose = ToRGB / background composite and "
             "the 8XDC super-resolution, in the CPU plan's batches; encoding: PNG + EXR of the views.", "",
             *stage_table(results), "",
             "## FLOPs (convolutions and matrix products, counted by torch.utils.flop_counter)", "",
             *flop_table(results), "",
             f"## Bound on one H100 at its peak rate, and GPU-hours for the paper's {PAPER_SUBJECTS // 1000}K "
             f"subjects x {VIEWS} views", "",
             "images/s = peak FLOP/s / counted FLOPs per image; a hard upper limit (real kernels reach a fraction "
             "of the peak; the uncounted grid sampling and compositing are memory-bound). In parentheses: "
             f"GPU-hours for {PAPER_SUBJECTS * VIEWS / 1e6:.2f} M images at that rate.", "",
             *bound_table(results), ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    report_main(argv, script=Path(__file__), name=NAME, doc=__doc__,
                quick_help="2 views per model instead of 32 (about 3 minutes)",
                report_only_help="measure nothing: rewrite the markdown from the existing JSON",
                measure=measure, render=lambda results, _out: markdown(results))


if __name__ == "__main__":
    main()
