"""Speed of the 3D-GAN generators (EG3D, PanoHead, SphereHead) on their tiny fixture checkpoints.

Writes ``benchmarks/reports/gan_speed.{json,md}`` (``gan_speed_quick.*`` with ``--quick``) and a
PNG plot beside them (the plot needs matplotlib; without it it is skipped with a note). The
markdown is regenerated from the JSON.

    python -m benchmarks.gan_speed                # default mode, about 4 minutes on 2 idle cores
    python -m benchmarks.gan_speed --quick        # a smoke run (8 views per subject), about 1 minute
    python -m benchmarks.gan_speed --report-only  # rewrite the markdown and plot from the JSON

The checkpoints are the tiny random-init generators of the shared fixtures
(``$PANOLAM_SHARED/fixtures/gan/<model>/<model>-tiny.pkl``, default ``../shared`` beside the
repository): neural rendering resolution 32, 12+12 samples per ray, super-resolution to 128 px,
backbone planes 256 px (EG3D) / 64 px (PanoHead, SphereHead). A model whose file is missing is
skipped with a note. Sections: (1) throughput of 32-view 128 px subjects, split into per-subject
work (mapping + backbone + background) and per-view rendering; (2) amortization and arrangement:
the backbone computed once for 32 views against once per view, and the default (chunks from the
memory budget) against one call for all views in the former arrangement (16384-ray chunks, all
views super-resolved at once) and one view per call, side by side with the arms rotated over
repeats; (3) samples per ray against error, against a 4x-samples reference; (4) the memory budget
against time; (5) clipping the rays to the generator's box: time and PSNR against the unclipped
render; (6) precision: the originals' fp16 super-resolution against fp32 on the production-SR
fixtures (``fixtures/gan-sr``, 512 px, clamps active), the fp16 convolutions summing in fp32 on the CPU. Times are
``time.perf_counter`` wall seconds after a warm-up; tables give medians.
"""
from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import (REPO, bullets, fmt, load_note, measurement_header, median, psnr_db, pyplot,
                               report_main, report_name, reproduce, run_sections, table)
from datagen.cameras import sample_views
from datagen.generators import GANS, make_generator
from datagen.generators.base import STREAM_CAMERAS, subject_rng
from datagen.generators.gan import ChunkPlan

NAME = "gan_speed"
SHARED = Path(os.environ.get("PANOLAM_SHARED", REPO.parent / "shared"))
SEED = 0
RESOLUTION = 128
PROTOCOL = "360"
REFERENCE_SAMPLES = (48, 48)    # 4x the fixtures' default (12, 12)
PSNR_TARGET_DB = 40.0           # image PSNR at which the sampling error counts as negligible
WARMUP_INDEX = 10_000           # a subject outside every measured set
SWEEP_FIRST_INDEX = 100         # sweep subjects, apart from the throughput subjects
ARMS = ("batched", "one_batch", "per_view", "regenerate")
# Paired ratios: the whole saving, the part due to reusing the backbone, the part due to batching views,
# and the former arrangement against the default.
RATIOS = {"regenerate_over_batched": ("regenerate", "batched"), "reuse": ("regenerate", "per_view"),
          "batching": ("per_view", "batched"), "former": ("one_batch", "batched")}
ARM_TITLES = {"batched": "backbone once, all views in one render call, chunks and batches from the memory budget "
                         "(the default)",
              "one_batch": "the former default: one render call, 16384-ray chunks, all views super-resolved at once",
              "per_view": "backbone once, one view per render call",
              "regenerate": "backbone again for every view, one view per call"}
FORMER_CHUNK_RAYS = 1 << 14
BUDGETS_MB = (8, 16, 32, 64, 128, 256, 1024)


@dataclass(frozen=True)
class Plan:
    """Sizes of one mode."""

    views: int                # views per subject in the throughput/amortization section
    subjects: int             # throughput/amortization subjects = repeats of the three arms
    sweep_subjects: int
    sweep_views: int
    sweep_repeats: int
    sample_settings: tuple


FULL = Plan(views=32, subjects=4, sweep_subjects=2, sweep_views=8, sweep_repeats=2,
            sample_settings=((4, 4), (6, 6), (8, 8), (12, 12), (16, 16), (24, 24)))
QUICK = Plan(views=8, subjects=3, sweep_subjects=1, sweep_views=4, sweep_repeats=1,
             sample_settings=((4, 4), (8, 8), (12, 12), (24, 24)))


# ------------------------------------------------------------------------------------------------
# Generators, views, timing

def checkpoint_samples(g) -> tuple:
    """The checkpoint's own (coarse, importance) samples per ray."""
    rk = g.G.rendering_kwargs
    return rk["depth_resolution"], rk["depth_resolution_importance"]


def checkpoint_path(model: str) -> Path:
    return SHARED / "fixtures" / "gan" / model / f"{model}-tiny.pkl"


def load_generators() -> tuple[dict, list[str]]:
    """The deterministic generators whose checkpoints exist, and a note for each one skipped."""
    generators, notes = {}, []
    for model in GANS:
        path = checkpoint_path(model)
        if path.exists():
            generators[model] = make_generator(model, str(path), {"deterministic": True})
        else:
            notes.append(f"{model} skipped: {path} not found (set PANOLAM_SHARED to the shared/ folder)")
            print(notes[-1])
    return generators, notes


def views_of(index: int, n_views: int):
    return sample_views(PROTOCOL, subject_rng(SEED, index, STREAM_CAMERAS), n_views)


def timed(fn, *args):
    """(fn(*args), wall seconds)."""
    start = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - start


def warm_up(generators: dict) -> None:
    for g in generators.values():
        g.render(g.sample_subject(SEED, WARMUP_INDEX), views_of(WARMUP_INDEX, 8), RESOLUTION)


@contextmanager
def samples_per_ray(g, samples: tuple):
    """Render with ``samples`` = (coarse, importance) per ray while the block runs."""
    rk = g.G.rendering_kwargs
    saved = rk["depth_resolution"], rk["depth_resolution_importance"]
    rk["depth_resolution"], rk["depth_resolution_importance"] = samples
    try:
        yield
    finally:
        rk["depth_resolution"], rk["depth_resolution_importance"] = saved


# ------------------------------------------------------------------------------------------------
# 1 + 2. Throughput and amortization: three ways to render the views of a subject

def run_batched(g, index: int, views) -> tuple[np.ndarray, dict]:
    subject, subject_s = timed(g.sample_subject, SEED, index)
    out, render_s = timed(g.render, subject, views, RESOLUTION)
    return out.rgb, {"subject_s": subject_s, "render_s": render_s, "total_s": subject_s + render_s}


@contextmanager
def plan(g, chunk_plan: ChunkPlan):
    """Render with ``chunk_plan`` instead of the generator's own while the block runs."""
    saved, g.plan = g.plan, chunk_plan
    try:
        yield
    finally:
        g.plan = saved


def run_one_batch(g, index: int, views) -> tuple[np.ndarray, dict]:
    with plan(g, ChunkPlan(rays=FORMER_CHUNK_RAYS, images=len(views))):
        return run_batched(g, index, views)


def run_per_view(g, index: int, views) -> tuple[np.ndarray, dict]:
    subject, subject_s = timed(g.sample_subject, SEED, index)
    rgbs, render_s = [], 0.0
    for k in range(len(views)):
        out, seconds = timed(g.render, subject, views.subset([k]), RESOLUTION)
        rgbs.append(out.rgb)
        render_s += seconds
    return np.concatenate(rgbs), {"subject_s": subject_s, "render_s": render_s, "total_s": subject_s + render_s}


def run_regenerate(g, index: int, views) -> tuple[np.ndarray, dict]:
    """As per-image sampling scripts do: mapping + backbone again before every view."""
    rgbs, subject_s, render_s = [], 0.0, 0.0
    for k in range(len(views)):
        subject, s1 = timed(g.sample_subject, SEED, index)
        out, s2 = timed(g.render, subject, views.subset([k]), RESOLUTION)
        rgbs.append(out.rgb)
        subject_s, render_s = subject_s + s1, render_s + s2
    return np.concatenate(rgbs), {"subject_s": subject_s, "render_s": render_s, "total_s": subject_s + render_s}


RUNNERS = {"batched": run_batched, "one_batch": run_one_batch, "per_view": run_per_view,
           "regenerate": run_regenerate}


def throughput_model(g, plan: Plan) -> dict:
    """One subject per repeat; the order of the arms rotates so that drift hits every arm alike."""
    rows, max_diff = [], 0.0
    for index in range(plan.subjects):
        views = views_of(index, plan.views)
        order = ARMS[index % len(ARMS):] + ARMS[:index % len(ARMS)]
        row, images = {"index": index, "order": list(order)}, {}
        for arm in order:
            images[arm], row[arm] = RUNNERS[arm](g, index, views)
        max_diff = max(max_diff, *(float(np.abs(images[a] - images["batched"]).max()) for a in ARMS[1:]))
        rows.append(row)
    med = {arm: {k: median(r[arm][k] for r in rows) for k in ("subject_s", "render_s", "total_s")} for arm in ARMS}
    return {"rows": rows, "median": med, "images_per_s": plan.views / med["batched"]["total_s"],
            "ratios": {name: paired_ratio(rows, a, b) for name, (a, b) in RATIOS.items()},
            "max_abs_rgb_diff_between_arms": max_diff}


def paired_ratio(rows: list[dict], numerator: str, denominator: str) -> dict:
    """Median, min and max over subjects of the ratio of two arms run back to back on the same subject."""
    ratios = [r[numerator]["total_s"] / r[denominator]["total_s"] for r in rows]
    return {"median": median(ratios), "min": min(ratios), "max": max(ratios)}


def throughput(generators: dict, plan: Plan) -> dict:
    return {model: throughput_model(g, plan) for model, g in generators.items()}


# ------------------------------------------------------------------------------------------------
# 3. Samples per ray against error

def errors(out, ref) -> dict:
    """Per-view squared errors of the image and the mask against the reference."""
    rgb = ((out.rgb.astype(np.float64) - ref.rgb) ** 2).mean(axis=(1, 2, 3))
    alpha = ((out.alpha.astype(np.float64) - ref.alpha) ** 2).mean(axis=(1, 2))
    return {"rgb_mse": rgb.tolist(), "alpha_mse": alpha.tolist()}


def error_summary(per_subject: list[dict]) -> dict:
    rgb = [m for e in per_subject for m in e["rgb_mse"]]
    alpha = [m for e in per_subject for m in e["alpha_mse"]]
    return {"psnr_rgb_db": psnr_db(float(np.mean(rgb))), "worst_view_psnr_rgb_db": psnr_db(max(rgb)),
            "psnr_alpha_db": psnr_db(float(np.mean(alpha)))}


def sweep_model(g, plan: Plan) -> dict:
    indices = range(SWEEP_FIRST_INDEX, SWEEP_FIRST_INDEX + plan.sweep_subjects)
    subjects = {i: g.sample_subject(SEED, i) for i in indices}  # the planes do not depend on the samples
    views = {i: views_of(i, plan.sweep_views) for i in indices}
    with samples_per_ray(g, REFERENCE_SAMPLES):
        reference = {i: g.render(subjects[i], views[i], RESOLUTION) for i in indices}
    # The reference is timed among the settings, and must come out identical to its first render.
    settings = tuple(sorted(set(plan.sample_settings) | {checkpoint_samples(g), REFERENCE_SAMPLES}))
    seconds = {s: [] for s in settings}
    errs = {}
    for repeat in range(plan.sweep_repeats):
        for samples in settings[repeat % len(settings):] + settings[:repeat % len(settings)]:
            with samples_per_ray(g, samples):
                for i in indices:
                    out, s = timed(g.render, subjects[i], views[i], RESOLUTION)
                    seconds[samples].append(s / plan.sweep_views)
                    errs.setdefault(samples, {})[i] = errors(out, reference[i])  # deterministic: same each repeat
    rows = [{"samples": list(s), "reference": s == REFERENCE_SAMPLES, "ms_per_view": 1e3 * median(seconds[s]),
             **error_summary([errs[s][i] for i in indices])} for s in settings]
    return {"rows": rows, "default_samples": list(checkpoint_samples(g))}


def sweep(generators: dict, plan: Plan) -> dict:
    return {model: sweep_model(g, plan) for model, g in generators.items()}


# ------------------------------------------------------------------------------------------------
# 4. The memory budget: chunk sizes against time

def budget_model(g, plan_: Plan) -> dict:
    from datagen.generators.gan import chunk_plan
    views = views_of(0, plan_.views)
    subject = g.sample_subject(SEED, 0)
    plans = {mb: chunk_plan(g.G, mb * 2 ** 20, False) for mb in BUDGETS_MB}
    seconds = {mb: [] for mb in BUDGETS_MB}
    reference = None
    same = True
    for repeat in range(plan_.subjects):
        order = BUDGETS_MB[repeat % len(BUDGETS_MB):] + BUDGETS_MB[:repeat % len(BUDGETS_MB)]
        for mb in order:
            with plan(g, plans[mb]):
                out, t = timed(g.render, subject, views, RESOLUTION)
            seconds[mb].append(t)
            reference = out.rgb if reference is None else reference
            same = same and np.array_equal(out.rgb, reference)
    return {"rows": [{"budget_mb": mb, "rays": plans[mb].rays, "images": plans[mb].images,
                      "render_s": median(seconds[mb])} for mb in BUDGETS_MB],
            "default_mb": g.budget_bytes() / 2 ** 20, "identical_images": bool(same)}


def budget(generators: dict, plan_: Plan) -> dict:
    return {model: budget_model(g, plan_) for model, g in generators.items()}


# ------------------------------------------------------------------------------------------------
# 5. Clipping each ray to the generator's box

def clipping_model(g, plan_: Plan) -> dict:
    views = views_of(1, plan_.views)
    subject = g.sample_subject(SEED, 1)
    box = g.G.content_box()
    seconds = {False: [], True: []}
    outs = {}
    for repeat in range(plan_.subjects):
        for clip in ((False, True) if repeat % 2 == 0 else (True, False)):
            g.config = dataclasses.replace(g.config, clip_rays=clip)
            outs[clip], t = timed(g.render, subject, views, RESOLUTION)
            seconds[clip].append(t)
    g.config = dataclasses.replace(g.config, clip_rays=False)
    # how many rays miss the box at all, and how much of the marched range lies outside it
    from datagen.cameras import rays as camera_rays
    from datagen.render import box_interval
    rk = g.G.rendering_kwargs
    o, d = camera_rays(views.cam2world, views.K, g.checkpoint.neural_rendering_resolution)
    shift = np.repeat(views.radius - rk["avg_camera_radius"], o.shape[1])
    start = rk["ray_start"] + shift
    end = rk["ray_end"] + shift
    near, far = (t.numpy() for t in box_interval(o.reshape(-1, 3), d.reshape(-1, 3), box))
    kept = np.clip(np.minimum(end, far) - np.maximum(start, near), 0, None) / (end - start)
    mse = float(np.mean((outs[True].rgb.astype(np.float64) - outs[False].rgb) ** 2))
    return {"box": list(box), "unclipped_s": median(seconds[False]), "clipped_s": median(seconds[True]),
            "missing_rays": float(np.mean(kept == 0)), "mean_range_kept": float(kept.mean()),
            "psnr_rgb_db": psnr_db(mse),
            "psnr_alpha_db": psnr_db(float(np.mean((outs[True].alpha.astype(np.float64) - outs[False].alpha) ** 2)))}


def clipping(generators: dict, plan_: Plan) -> dict:
    return {model: clipping_model(g, plan_) for model, g in generators.items()}


# ------------------------------------------------------------------------------------------------
# 6. Precision: fp16 super-resolution against fp32 on the production-SR fixtures

def sr_checkpoint_path(model: str) -> Path:
    return SHARED / "fixtures" / "gan-sr" / model / f"{model}-sr.pkl"


PRECISION_VIEWS = 4  # a few 512 px views tell the difference


def precision(generators: dict, plan_: Plan) -> dict:
    out = {}
    for model in generators:
        path = sr_checkpoint_path(model)
        if not path.exists():
            out[model] = {"skipped": f"{path} not found"}
            continue
        g = make_generator(model, str(path), {"deterministic": True})
        views = views_of(2, min(plan_.sweep_views, PRECISION_VIEWS))
        subject = g.sample_subject(SEED, 2)
        images = {}
        for p in ("fp32", "fp16"):
            g.G.precision = p
            images[p], images[p + "_s"] = timed(g.render, subject, views, g.G.img_resolution)
        diff = np.abs(images["fp16"].rgb.astype(np.float64) - images["fp32"].rgb)
        out[model] = {"views": len(views), "resolution": g.G.img_resolution, "max_abs": float(diff.max()),
                      "mean_abs": float(diff.mean()), "psnr_db": psnr_db(float(np.mean(diff ** 2))),
                      "levels_changed": float(np.mean(np.round(images["fp16"].rgb * 255) !=
                                                      np.round(images["fp32"].rgb * 255))),
                      "fp32_s": images["fp32_s"], "fp16_cpu_s": images["fp16_s"]}
    return out


# ------------------------------------------------------------------------------------------------
# Running

SECTIONS = (("throughput", "1+2. throughput, amortization and arrangement", throughput),
            ("samples", "3. samples per ray", sweep),
            ("budget", "4. memory budget", budget),
            ("clipping", "5. clipping rays to the box", clipping),
            ("precision", "6. fp16 against fp32 (production super-resolution)", precision))


def fixture_info(generators: dict) -> dict:
    """The configuration of each measured checkpoint, read from the loaded generator."""
    info = {}
    for model, g in generators.items():
        info[model] = {"checkpoint": str(checkpoint_path(model)), "sha256": g.checkpoint.sha256,
                       "neural_rendering_resolution": g.checkpoint.neural_rendering_resolution,
                       "image_resolution": g.G.img_resolution,
                       "samples": list(checkpoint_samples(g)),
                       "plane_resolution": 256 if model == "eg3d" else g.G.rendering_kwargs["triplane_size"]}
    return info


def measure(quick: bool, command: str) -> dict:
    plan = QUICK if quick else FULL
    generators, notes = load_generators()
    if not generators:
        sys.exit("no GAN fixture checkpoint found; nothing to measure")
    results = {**measurement_header("quick" if quick else "default", command, asdict(plan)),
               "fixtures": fixture_info(generators), "notes": notes}
    run_sections(results, SECTIONS, (generators, plan), lambda: warm_up(generators))
    return results


# ------------------------------------------------------------------------------------------------
# Conclusions, computed from the JSON

def _samples(row) -> str:
    return f"({row['samples'][0]}+{row['samples'][1]})"


def _db(value) -> float:
    return math.inf if value is None else value


def default_row(sweep_result: dict) -> dict:
    """The row of the checkpoint's own samples per ray."""
    return next(r for r in sweep_result["rows"] if r["samples"] == sweep_result["default_samples"])


def throughput_conclusions(results: dict) -> list[str]:
    data = results["throughput"]
    rate = {m: d["images_per_s"] for m, d in data.items()}
    fast, slow = max(rate, key=rate.get), min(rate, key=rate.get)
    share = {m: d["median"]["batched"]["subject_s"] / d["median"]["batched"]["total_s"] for m, d in data.items()}
    lines = [", ".join(f"{m} {rate[m]:.1f}" for m in data) +
             f" images/s ({results['plan']['views']} views at {RESOLUTION} px, "
             f"{results['machine']['torch_threads']} torch threads)."]
    if fast != slow:
        lines[-1] += f" {fast} is x{rate[fast] / rate[slow]:.2f} the speed of {slow}."
    verdict = ("rendering (ray marching + super-resolution) dominates" if max(share.values()) < 0.5
               else "the per-subject work is a large part")
    lines.append("The per-subject work (mapping + backbone + background) takes " +
                 ", ".join(f"{100 * share[m]:.1f} % ({m})" for m in data) +
                 f" of the time for {results['plan']['views']} views: {verdict}.")
    return lines


def amortization_conclusions(results: dict) -> list[str]:
    lines = []
    views = results["plan"]["views"]
    for model, d in results["throughput"].items():
        med, ratio = d["median"], {k: v["median"] for k, v in d["ratios"].items()}
        total = d["ratios"]["regenerate_over_batched"]
        lines.append(f"{model}: regenerating the backbone for every view takes x{total['median']:.2f} the time of "
                     f"computing it once and rendering the {views} views in one call "
                     f"(x{total['min']:.2f} to x{total['max']:.2f} over subjects; medians "
                     f"{med['regenerate']['total_s']:.2f} s vs {med['batched']['total_s']:.2f} s). Reusing the "
                     f"backbone alone is worth x{ratio['reuse']:.2f} (both one view per call); one view per call "
                     + (f"takes x{ratio['batching']:.2f} the default's time" if ratio["batching"] >= 1 else
                        f"is FASTER than the default (x{ratio['batching']:.2f} its time)")
                     + f"; the former one-call arrangement (16384-ray chunks, all {views} views super-resolved "
                     f"at once) takes x{ratio['former']:.2f}.")
    diff = max(d["max_abs_rgb_diff_between_arms"] for d in results["throughput"].values())
    same = "the same images" if diff < 1e-4 else "DIFFERENT images"
    lines.append(f"The arms give {same} (max |rgb difference| {diff:.1e} over all subjects and models: the "
                 "convolution kernels differ by batch size in the last bits).")
    return lines


def budget_conclusions(results: dict) -> list[str]:
    lines = []
    for model, d in results["budget"].items():
        best = min(d["rows"], key=lambda r: r["render_s"])
        default = next(r for r in d["rows"] if r["budget_mb"] == d["default_mb"])
        lines.append(f"{model}: the fastest budget is {best['budget_mb']} MB ({best['rays']} rays, {best['images']} "
                     f"views per batch, {best['render_s']:.2f} s); the default {default['budget_mb']} MB takes "
                     f"x{default['render_s'] / best['render_s']:.2f} that; the images are "
                     + ("bit-identical across budgets." if d["identical_images"] else "NOT bit-identical across budgets."))
    return lines


def clipping_conclusions(results: dict) -> list[str]:
    lines = []
    for model, d in results["clipping"].items():
        lines.append(f"{model}: clipping keeps {100 * d['mean_range_kept']:.0f} % of the marched range on average and "
                     f"{100 * d['missing_rays']:.1f} % of the rays miss the box, so with the same samples per ray "
                     f"it saves x{d['unclipped_s'] / d['clipped_s']:.2f} in time; against the unclipped render the "
                     f"image is at {fmt(d['psnr_rgb_db'], 1)} dB, the mask at {fmt(d['psnr_alpha_db'], 1)} dB "
                     f"(the samples move closer together inside the box).")
    return lines


def precision_conclusions(results: dict) -> list[str]:
    lines = []
    for model, d in results["precision"].items():
        if "skipped" in d:
            lines.append(f"{model}: precision not measured ({d['skipped']}).")
            continue
        lines.append(f"{model}: the fp16 super-resolution (the originals' CUDA arithmetic, on the CPU) against "
                     f"fp32 at {d['resolution']} px: {fmt(d['psnr_db'], 1)} dB, max |difference| "
                     f"{d['max_abs']:.1e}, {100 * d['levels_changed']:.1f} % of the 8-bit values change.")
    return lines


def sample_conclusions(results: dict) -> list[str]:
    lines = []
    for model, d in results["samples"].items():
        rows = [r for r in d["rows"] if not r["reference"]]
        reference = next(r for r in d["rows"] if r["reference"])
        default = default_row(d)
        enough = next((r for r in rows if _db(r["psnr_rgb_db"]) >= PSNR_TARGET_DB), None)
        fewest = rows[0]
        text = (f"{model}: the checkpoint default {_samples(default)} is at {default['psnr_rgb_db']:.1f} dB image / "
                f"{default['psnr_alpha_db']:.1f} dB mask PSNR against {REFERENCE_SAMPLES[0]}+{REFERENCE_SAMPLES[1]}, "
                f"{default['ms_per_view']:.0f} ms per view; ")
        if enough is None:
            text += f"no setting reaches {PSNR_TARGET_DB:.0f} dB. "
        else:
            text += (f"the fewest samples reaching {PSNR_TARGET_DB:.0f} dB are {_samples(enough)} "
                     f"({enough['psnr_rgb_db']:.1f} dB, x{enough['ms_per_view'] / default['ms_per_view']:.2f} the "
                     "default's time). ")
        text += (f"From {_samples(fewest)} to the reference {_samples(reference)} the samples grow "
                 f"x{sum(reference['samples']) / sum(fewest['samples']):.0f} and the time per view "
                 f"x{reference['ms_per_view'] / fewest['ms_per_view']:.1f}.")
        lines.append(text)
    return lines


# ------------------------------------------------------------------------------------------------
# Markdown

def scope_section(results: dict) -> list[str]:
    rows = [[m, f["neural_rendering_resolution"], f"{f['samples'][0]}+{f['samples'][1]}", f["image_resolution"],
             f["plane_resolution"], f["sha256"][:12]] for m, f in results["fixtures"].items()]
    return (["**These are tiny random-init configurations**, the shared test fixtures, not the released models. "
             "The released checkpoints render many more rays per view (e.g. 128x128 instead of 32x32) with more "
             "samples per ray and super-resolve to 512 px, so their per-view cost is far higher and the per-subject "
             "share smaller still: `benchmarks/reports/gan_fullsize.md` times the released sizes.", ""] +
            table(["model", "neural render px", "samples/ray", "output px", "plane px", "sha256"], rows) +
            [""] + [f"Note: {n}" for n in results["notes"]])


def machine_section(results: dict) -> list[str]:
    m = results["machine"]
    return [
        f"Measured {results['date_utc']} in {results['mode']} mode ({results['benchmark_seconds'] / 60:.1f} min) on "
        f"{m['cpu_model']}: {m['cpu_count']} CPUs ({m['usable_cpus']} usable), torch {m['torch']} (CPU) with "
        f"{m['torch_threads']} threads, Python {m['python']}, numpy {m['numpy']}, {m['platform']}, "
        f"git {m['git_revision']}.",
        "",
        load_note(results, m["torch_threads"], "**other work competed for the CPUs**: absolute times are inflated "
                  "and noisy; the ratios, measured side by side with the arms interleaved, are the numbers to trust."),
        "",
        *reproduce(results["command"]),
        "",
        "Wall time by `time.perf_counter` after one warm-up subject per model; generators built with "
        "`deterministic=True` (no stratified jitter).",
    ]


def throughput_section(results: dict) -> list[str]:
    rows = []
    views = results["plan"]["views"]
    for model, d in results["throughput"].items():
        med = d["median"]["batched"]
        rows.append([model, fmt(med["subject_s"], 3), fmt(med["render_s"]), fmt(1e3 * med["render_s"] / views, 0),
                     fmt(med["total_s"]), fmt(d["images_per_s"], 1),
                     f"{100 * med['subject_s'] / med['total_s']:.1f} %"])
    n = results["plan"]["subjects"]
    return ([f"{views} views (`360` protocol) at {RESOLUTION} px per subject, backbone once and all views in one "
             f"`render` call; medians over {n} subjects.", ""] +
            table(["model", "per-subject s", "render s", "render ms/view", "total s", "images/s", "per-subject share"],
                  rows))


def amortization_section(results: dict) -> list[str]:
    rows = []
    for model, d in results["throughput"].items():
        med, ratios = d["median"], d["ratios"]
        total = ratios["regenerate_over_batched"]
        rows.append([model, *(fmt(med[a]["total_s"]) for a in ARMS), fmt(med["regenerate"]["subject_s"]),
                     f"x{total['median']:.2f} (x{total['min']:.2f} - x{total['max']:.2f})",
                     f"x{ratios['reuse']['median']:.2f}", f"x{ratios['batching']['median']:.2f}",
                     f"x{ratios['former']['median']:.2f}"])
    n = results["plan"]["subjects"]
    arms = "; ".join(f"**{a}**: {ARM_TITLES[a]}" for a in ARMS)
    return ([f"Seconds for the {results['plan']['views']} views of one subject. {arms}. The arms run back to "
             f"back on the same subject, their order rotating from subject to subject. Times are medians over {n} "
             "subjects; ratios are medians (min - max) of the per-subject ratios, each taken between arms that ran "
             "seconds apart, so they are robust to load that drifts between subjects.", ""] +
            table(["model", *(f"{a} s" for a in ARMS), "of which backbone s",
                   "regenerate / batched (min - max)", "regenerate / per_view (reuse)",
                   "per_view / batched", "one_batch / batched"], rows))


def budget_section(results: dict) -> list[str]:
    rows = []
    for model, d in results["budget"].items():
        for r in d["rows"]:
            rows.append([model, r["budget_mb"] if r["budget_mb"] != d["default_mb"] else f"{r['budget_mb']} (default)",
                         r["rays"], r["images"], fmt(r["render_s"])])
    return ([f"One subject's {results['plan']['views']} views at {RESOLUTION} px per budget, the budgets in rotating "
             f"order, median over {results['plan']['subjects']} repeats. The budget sets the rays per march chunk "
             "(whole multiples of 1024) and the views per super-resolution batch (at least 2).", ""] +
            table(["model", "budget MB", "rays per chunk", "views per SR batch", "render s"], rows))


def clipping_section(results: dict) -> list[str]:
    rows = [[m, ", ".join(f"{v:.2f}" for v in d["box"]), f"{100 * d['missing_rays']:.1f} %",
             f"{100 * d['mean_range_kept']:.0f} %", fmt(d["unclipped_s"]), fmt(d["clipped_s"]),
             fmt(d["psnr_rgb_db"], 1), fmt(d["psnr_alpha_db"], 1)] for m, d in results["clipping"].items()]
    return ([f"`--clip-rays` against the originals' full ray range, {results['plan']['views']} views at "
             f"{RESOLUTION} px, deterministic sampling, same samples per ray. Box: half extents (x, y, z) in world "
             "units (PanoHead/SphereHead: their density crop in x and z).", ""] +
            table(["model", "box", "rays that miss", "range kept", "unclipped s", "clipped s", "image PSNR dB",
                   "mask PSNR dB"], rows) +
            ["", "Caveat: random-weight fixtures, whose density fills the whole box; a trained head leaves most of "
             "the box empty, so the PSNR here says how much the re-spaced samples change a dense volume."])


def precision_section(results: dict) -> list[str]:
    rows = [[m, d["views"], d["resolution"], fmt(d["psnr_db"], 1), f"{d['max_abs']:.1e}", f"{d['mean_abs']:.1e}",
             f"{100 * d['levels_changed']:.1f} %", fmt(d["fp32_s"]), fmt(d["fp16_cpu_s"])]
            for m, d in results["precision"].items() if "skipped" not in d]
    return (["The production-SR fixtures (8XDC, 128 -> 512 px, conv_clamp 256 active in some channels) rendered "
             "with the super-resolution in fp16 (weights and styles pre-normalized, bias and activation in fp32, "
             "clamped, as the originals on CUDA) against fp32, same planes and cameras. On CUDA `--precision auto` "
             "(the default) runs the fp16 path; `--precision fp32` opts out. This CPU has no usable fp16 "
             "convolutions (AVX2: a 256-channel 3x3 convolution at 256 px takes 3.5 s in fp32 and had not "
             "finished after 5 minutes in fp16), so on the CPU the fp16 path's convolutions take fp16 inputs, sum "
             "in fp32 and round their output to fp16, as CUDA's fp16 convolutions on tensor cores do "
             "(`datagen/gans/ops.py`); every other operation is the fp16 path as it is. The fp16 time says "
             "nothing about a GPU.", ""] +
            table(["model", "views", "px", "PSNR dB", "max abs", "mean abs", "8-bit values changed", "fp32 s",
                   "fp16 s (CPU, fp32 sums)"], rows))


def samples_section(results: dict) -> list[str]:
    plan = results["plan"]
    lines = [f"{plan['sweep_subjects']} subject(s) x {plan['sweep_views']} views at {RESOLUTION} px, deterministic. "
             f"PSNR of the final image (in [0, 1]) and of the alpha mask (the renderer's weight sum, upsampled to "
             f"{RESOLUTION} px as stored) against the {REFERENCE_SAMPLES[0]}+{REFERENCE_SAMPLES[1]} reference on "
             f"the same planes and cameras; PSNR from the mean squared error over all views. Time per view: median "
             f"over {plan['sweep_repeats']} repeat(s) x subjects of a {plan['sweep_views']}-view render call divided "
             "by the views, the settings (reference included) interleaved in rotating order. The reference row "
             "re-renders the reference and must read 'identical'.", ""]
    rows = []
    for model, d in results["samples"].items():
        default = default_row(d)
        default_ms = default["ms_per_view"]
        for r in d["rows"]:
            label = _samples(r) + (" reference" if r["reference"] else " default" if r is default else "")
            rows.append([model, label, fmt(r["ms_per_view"], 1), f"x{r['ms_per_view'] / default_ms:.2f}",
                         fmt(r["psnr_rgb_db"], 1), fmt(r["worst_view_psnr_rgb_db"], 1), fmt(r["psnr_alpha_db"], 1)])
    lines += table(["model", "samples (coarse+importance)", "ms/view", "time vs default", "image PSNR dB",
                    "worst view dB", "mask PSNR dB"], rows)
    return lines + ["", "Caveat: random-weight generators produce a dense, smooth volume with no trained surface "
                    "(most rays are largely opaque), so these curves characterize the renderer on these fixtures, not "
                    "the sampling a trained head with thin, sharp surfaces needs."]


def markdown(results: dict, plot: str | None) -> str:
    summary = (throughput_conclusions(results) + amortization_conclusions(results) + sample_conclusions(results) +
               budget_conclusions(results) + clipping_conclusions(results) + precision_conclusions(results))
    parts = [["# 3D-GAN generators (EG3D, PanoHead, SphereHead): speed on the tiny fixtures", "",
              f"Generated by `benchmarks/gan_speed.py` from `{results_name(results)}.json`; do not edit.", ""],
             scope_section(results), [""], machine_section(results), ["", "## Conclusions", ""], bullets(summary),
             ["", f"## 1. Throughput: {results['plan']['views']}-view {RESOLUTION} px subjects", ""],
             throughput_section(results),
             ["", "## 2. Amortization and arrangement: backbone once per subject, views per call", ""],
             amortization_section(results),
             ["", "## 3. Samples per ray: render time against error", ""], samples_section(results),
             ["", "## 4. Memory budget: chunk sizes against time", ""], budget_section(results),
             ["", "## 5. Clipping rays to the generator's box", ""], clipping_section(results),
             ["", "## 6. Precision: fp16 super-resolution against fp32", ""], precision_section(results)]
    if plot:
        parts.append(["", "## Plot", "", f"![{plot}]({plot})"])
    else:
        parts.append(["", "The plot was skipped: matplotlib is not installed."])
    return "\n".join(line for part in parts for line in part) + "\n"


def results_name(results: dict) -> str:
    return report_name(NAME, results["mode"] == "quick")


# ------------------------------------------------------------------------------------------------
# Plot

def write_plot(results: dict, out_dir: Path) -> str | None:
    """PSNR against time per view, per model; returns the file name (None without matplotlib)."""
    plt = pyplot()
    if plt is None:
        print("matplotlib is not installed: skipping the plot (pip install matplotlib)")
        return None
    name = f"{results_name(results)}_psnr_vs_time.png"
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, key, label in zip(axes, ("psnr_rgb_db", "psnr_alpha_db"), ("image", "alpha mask")):
        plot_psnr_vs_time(results, ax, key)
        ax.set_ylabel(f"{label} PSNR vs {REFERENCE_SAMPLES[0]}+{REFERENCE_SAMPLES[1]} (dB)")
        ax.grid(alpha=0.3)
    fig.suptitle(f"Samples per ray (coarse+importance), {RESOLUTION} px, tiny fixtures")
    fig.tight_layout()
    fig.savefig(out_dir / name, dpi=110)
    plt.close(fig)
    return name


def plot_psnr_vs_time(results: dict, ax, key: str) -> None:
    for model, d in results["samples"].items():
        rows = [r for r in d["rows"] if r[key] is not None]
        ax.plot([r["ms_per_view"] for r in rows], [r[key] for r in rows], "o-", label=model)
        for r in rows:
            ax.annotate(_samples(r), (r["ms_per_view"], r[key]), textcoords="offset points", xytext=(4, -10),
                        fontsize=7)
    ax.axhline(PSNR_TARGET_DB, color="grey", linestyle=":", label=f"{PSNR_TARGET_DB:.0f} dB")
    ax.set_xlabel("render ms per view")
    ax.legend(fontsize=8)


# ------------------------------------------------------------------------------------------------

def main(argv=None) -> None:
    report_main(argv, script=Path(__file__), name=NAME, doc=__doc__,
                quick_help="fewer subjects and settings (under 3 minutes)",
                report_only_help="measure nothing: rewrite the markdown and plot from the existing JSON",
                measure=measure, render=lambda results, out_dir: markdown(results, write_plot(results, out_dir)))


if __name__ == "__main__":
    main()
