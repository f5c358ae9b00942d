"""Speed of the procedural head generator and the volume renderer, measured side by side in one run.

Writes ``benchmarks/reports/datagen_speed.{json,md}`` and PNG plots beside them (plots need
matplotlib; without it they are skipped with a note). The markdown is regenerated from the JSON.

    python -m benchmarks.datagen_speed            # default mode, about 10 minutes on 2 cores
    python -m benchmarks.datagen_speed --quick    # a smoke run, under 2 minutes
    python -m benchmarks.datagen_speed --report-only   # rewrite the markdown and plots from the JSON

Sections: (1) one 32-view 128 px subject, split into bake and render; (2) scaling with image
resolution; (3) the full ``run_sample`` pipeline with 1 and 2 workers; (4) render time against
error for the number of samples per ray, against a high-sample reference; (5) the bake grid
resolution (time and memory only). Times are ``time.perf_counter`` wall seconds after a warm-up;
tables give medians over repeats.
"""
from __future__ import annotations

import math
import multiprocessing as mp
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (bullets, fmt, load_note, measurement_header, median, peak_rss_since_reset_mb,
                               psnr_db, pyplot, report_main, report_name, reproduce, run_sections, stage_clock, table)
from datagen.cameras import sample_views
from datagen.generators.base import STREAM_CAMERAS, STREAM_LATENT, subject_rng
from datagen.generators.procedural import ProceduralConfig, ProceduralHeads, bake, generator, sample_params
from datagen.pipeline import JobSpec, run_sample, software_info

NAME = "datagen_speed"
SEED = 0
VIEWS = 32
PROTOCOL = "360"
GOAL_SECONDS = 2.0            # the goal for one 32-view 128 px subject on 2 cores
PSNR_TARGET_DB = 40.0         # foreground PSNR at which the sampling error counts as negligible
NEAR_BEST_DB = 0.5
REFERENCE_SAMPLES = (96, 96)
DEFAULT_SAMPLES = (ProceduralConfig.samples, ProceduralConfig.samples_importance)
FG_ALPHA = 1e-3               # a pixel is foreground when either image covers it this much
DEPTH_ALPHA = 0.5             # depth is compared where both images are at least this opaque
WARMUP_INDEX = 10_000         # a subject outside every measured set
# The procedural generator's stages, timed by wrapping the functions where they are called (see common.stage_clock).
STAGES = {"head_field": (bake, "head_field"), "sphere_trace": (generator, "sphere_trace"),
          "render_rays_chunked": (generator, "render_rays_chunked")}


@dataclass(frozen=True)
class Plan:
    """Sizes of one mode."""

    speed_subjects: int
    resolutions: dict            # image resolution -> subjects rendered at it
    pipeline_subjects: int
    pipeline_shard_size: int
    pipeline_workers: tuple
    pipeline_repeats: int
    accuracy_subjects: int       # chosen with distinct hair styles
    accuracy_views: int
    accuracy_resolution: int
    accuracy_repeats: int
    sample_settings: tuple
    grid_resolutions: tuple
    grid_subjects: int


FULL = Plan(speed_subjects=8, resolutions={64: 3, 128: 3, 256: 3, 512: 1},
            pipeline_subjects=8, pipeline_shard_size=4, pipeline_workers=(1, 2), pipeline_repeats=2,
            accuracy_subjects=4, accuracy_views=VIEWS, accuracy_resolution=128, accuracy_repeats=2,
            sample_settings=((4, 4), (6, 6), (8, 8), (12, 12), (16, 16), (24, 24), (32, 32)),
            grid_resolutions=(96, 128, 160), grid_subjects=3)
QUICK = Plan(speed_subjects=4, resolutions={64: 1, 128: 1, 256: 1},
             pipeline_subjects=4, pipeline_shard_size=2, pipeline_workers=(1, 2), pipeline_repeats=1,
             accuracy_subjects=3, accuracy_views=8, accuracy_resolution=64, accuracy_repeats=1,
             sample_settings=((4, 4), (8, 8), (12, 12), (24, 24)),
             grid_resolutions=(96, 128, 160), grid_subjects=1)


# ------------------------------------------------------------------------------------------------
# Timing helpers

def generator(samples=DEFAULT_SAMPLES, deterministic=False, grid_resolution=128) -> ProceduralHeads:
    return ProceduralHeads(ProceduralConfig(grid_resolution=grid_resolution, samples=samples[0],
                                            samples_importance=samples[1], deterministic=deterministic))


def views_of(index: int, n_views: int = VIEWS):
    return sample_views(PROTOCOL, subject_rng(SEED, index, STREAM_CAMERAS), n_views)


def bake(gen: ProceduralHeads, index: int):
    """(subject, seconds, stage seconds)."""
    with stage_clock(STAGES) as stages:
        start = time.perf_counter()
        subject = gen.sample_subject(SEED, index)
        seconds = time.perf_counter() - start
    return subject, seconds, dict(stages)


def render(gen: ProceduralHeads, subject, views, resolution: int):
    """(RenderedViews, seconds, stage seconds)."""
    with stage_clock(STAGES) as stages:
        start = time.perf_counter()
        out = gen.render(subject, views, resolution)
        seconds = time.perf_counter() - start
    return out, seconds, dict(stages)


def warm_up() -> None:
    gen = generator()
    subject = gen.sample_subject(SEED, WARMUP_INDEX)
    gen.render(subject, views_of(WARMUP_INDEX), 128)


# ------------------------------------------------------------------------------------------------
# 1. One subject

def one_subject(plan: Plan) -> dict:
    gen = generator()
    rows = []
    for index in range(plan.speed_subjects):
        subject, bake_s, bake_stages = bake(gen, index)
        _, render_s, render_stages = render(gen, subject, views_of(index), 128)
        rows.append({"index": index, "hair_style": subject.latent["params"]["hair_style"],
                     "bake_s": bake_s, "render_s": render_s, "total_s": bake_s + render_s,
                     "field_s": bake_stages["head_field"], "trace_s": render_stages["sphere_trace"],
                     "integrate_s": render_stages["render_rays_chunked"]})
    med = {k: median(r[k] for r in rows) for k in ("bake_s", "render_s", "total_s", "field_s", "trace_s", "integrate_s")}
    threads = torch.get_num_threads()
    images_per_s = VIEWS / med["total_s"]
    return {"views": VIEWS, "resolution": 128, "subjects": rows, "median": med,
            "images_per_s": images_per_s, "images_per_s_per_thread": images_per_s / threads,
            "threads": threads, "goal_s": GOAL_SECONDS, "goal_met": med["total_s"] <= GOAL_SECONDS}


# ------------------------------------------------------------------------------------------------
# 2. Image resolution

def resolution_scaling(plan: Plan) -> dict:
    gen = generator()
    bake_times, render_times = [], {res: [] for res in plan.resolutions}
    for index in range(max(plan.resolutions.values())):
        subject, bake_s, _ = bake(gen, index)
        bake_times.append(bake_s)
        for res, n_subjects in plan.resolutions.items():
            if index < n_subjects:
                render_times[res].append(render(gen, subject, views_of(index), res)[1])
    bake_s = median(bake_times)
    rows = []
    for res, times in render_times.items():
        render_s = median(times)
        rows.append({"resolution": res, "subjects": len(times), "bake_s": bake_s, "render_s": render_s,
                     "total_s": bake_s + render_s, "images_per_s": VIEWS / (bake_s + render_s),
                     "render_us_per_pixel": 1e6 * render_s / (VIEWS * res * res)})
    pixels = np.log([r["resolution"] ** 2 for r in rows])
    exponent = float(np.polyfit(pixels, np.log([r["render_s"] for r in rows]), 1)[0]) if len(rows) > 1 else None
    return {"rows": rows, "render_exponent": exponent}


# ------------------------------------------------------------------------------------------------
# 3. The run_sample pipeline with 1 and 2 workers

def pipeline_run(plan: Plan, workers: int, software: dict, subjects: int) -> float:
    with tempfile.TemporaryDirectory(prefix="datagen_speed_") as tmp:
        spec = JobSpec(out=str(Path(tmp) / "dataset"), subjects=subjects, resolution=128,
                       shard_size=plan.pipeline_shard_size, seed=SEED, software=software)
        start = time.perf_counter()
        run_sample(spec, workers=workers, progress=False)
        return time.perf_counter() - start


def pipeline_scaling(plan: Plan) -> dict:
    software = software_info()
    pipeline_run(plan, 1, software, subjects=1)  # warm-up: image and EXR encoders, tar writing
    times = {w: [] for w in plan.pipeline_workers}
    for _ in range(plan.pipeline_repeats):
        for workers in plan.pipeline_workers:
            times[workers].append(pipeline_run(plan, workers, software, plan.pipeline_subjects))
    images = plan.pipeline_subjects * VIEWS
    shards = -(-plan.pipeline_subjects // plan.pipeline_shard_size)
    base = median(times[plan.pipeline_workers[0]])
    rows = []
    for workers, ts in times.items():
        seconds = median(ts)
        threads = torch.get_num_threads() if workers == 1 else max(1, (os.cpu_count() or 1) // workers)
        rows.append({"workers": workers, "threads_per_worker": threads, "seconds": seconds, "repeats": len(ts),
                     "images_per_s": images / seconds, "speedup": base / seconds})
    return {"subjects": plan.pipeline_subjects, "shards": shards, "shard_size": plan.pipeline_shard_size,
            "resolution": 128, "images": images, "rows": rows}


# ------------------------------------------------------------------------------------------------
# 4. Samples per ray: render time against error

def distinct_hair_subjects(n: int) -> list[int]:
    """The first n subject indices whose hair styles all differ (drawn as sample_subject draws them)."""
    chosen, seen, index = [], set(), 0
    while len(chosen) < n:
        style = sample_params(subject_rng(SEED, index, STREAM_LATENT))["hair_style"]
        if style not in seen:
            seen.add(style)
            chosen.append(index)
        index += 1
    return chosen


def error_sums(out, ref) -> dict:
    """Squared/absolute error sums and counts of one render against the reference."""
    sq = (out.rgb.astype(np.float64) - ref.rgb) ** 2
    fg = (out.alpha > FG_ALPHA) | (ref.alpha > FG_ALPHA)
    both = (out.alpha > DEPTH_ALPHA) & (ref.alpha > DEPTH_ALPHA)
    return {"sse": float(sq.sum()), "n": sq.size, "sse_fg": float(sq[fg].sum()), "n_fg": int(fg.sum()) * 3,
            "alpha_abs": float(np.abs(out.alpha.astype(np.float64) - ref.alpha).sum()), "n_alpha": out.alpha.size,
            "depth_abs": float(np.abs(out.depth.astype(np.float64) - ref.depth)[both].sum()), "n_depth": int(both.sum())}


def error_metrics(per_subject: list[dict]) -> dict:
    total = {k: sum(s[k] for s in per_subject) for k in per_subject[0]}
    fg_per_subject = [psnr_db(s["sse_fg"] / max(1, s["n_fg"])) for s in per_subject]
    finite = [p for p in fg_per_subject if p is not None]
    return {"psnr_db": psnr_db(total["sse"] / total["n"]),
            "psnr_fg_db": psnr_db(total["sse_fg"] / max(1, total["n_fg"])),
            "worst_subject_psnr_fg_db": min(finite) if finite else None,
            "psnr_fg_db_per_subject": fg_per_subject,
            "alpha_mae": total["alpha_abs"] / total["n_alpha"],
            "depth_mae_in_mask": total["depth_abs"] / max(1, total["n_depth"])}


def sample_sweep(plan: Plan) -> dict:
    res = plan.accuracy_resolution
    indices = distinct_hair_subjects(plan.accuracy_subjects)
    baker = generator()
    subjects = {i: baker.sample_subject(SEED, i) for i in indices}  # the grid does not depend on the samples
    views = {i: views_of(i, plan.accuracy_views) for i in indices}
    reference_gen = generator(REFERENCE_SAMPLES, deterministic=True)
    reference, reference_s = {}, []
    for i in indices:
        reference[i], seconds, _ = render(reference_gen, subjects[i], views[i], res)
        reference_s.append(seconds)
    settings = sorted(set(plan.sample_settings) | {DEFAULT_SAMPLES})  # the default is always measured
    cases = [(s, True) for s in settings] + [(s, False) for s in settings]
    timings = {case: {i: [] for i in indices} for case in cases}
    stages = {case: {i: [] for i in indices} for case in cases}
    errors = {}
    for _ in range(plan.accuracy_repeats):  # interleaved so that drift hits every setting alike
        for samples, deterministic in cases:
            gen = generator(samples, deterministic)
            for i in indices:
                out, seconds, st = render(gen, subjects[i], views[i], res)
                timings[(samples, deterministic)][i].append(seconds)
                stages[(samples, deterministic)][i].append(st)
                errors.setdefault((samples, deterministic), {})[i] = error_sums(out, reference[i])
    rows = []
    for case in cases:
        samples, deterministic = case
        per_subject_s = [median(timings[case][i]) for i in indices]
        trace_s = [median(st["sphere_trace"] for st in stages[case][i]) for i in indices]
        integrate_s = [median(st["render_rays_chunked"] for st in stages[case][i]) for i in indices]
        rows.append({"samples": list(samples), "deterministic": deterministic,
                     "render_s": float(np.mean(per_subject_s)), "trace_s": float(np.mean(trace_s)),
                     "integrate_s": float(np.mean(integrate_s)),
                     **error_metrics([errors[case][i] for i in indices])})
    return {"resolution": res, "views": plan.accuracy_views, "repeats": plan.accuracy_repeats,
            "subjects": [{"index": i, "hair_style": subjects[i].latent["params"]["hair_style"]} for i in indices],
            "reference_samples": list(REFERENCE_SAMPLES), "reference_render_s": float(np.mean(reference_s)),
            "default_samples": list(DEFAULT_SAMPLES), "default_deterministic": ProceduralConfig().deterministic,
            "rows": rows}


# ------------------------------------------------------------------------------------------------
# 5. Bake grid resolution: time and memory

def peak_memory_child(grid_resolution: int) -> dict:
    """Run in a fresh process: peak resident memory added by one bake, then by rendering 32 views."""
    gen = generator(grid_resolution=grid_resolution)
    views = views_of(0)
    base = peak_rss_since_reset_mb()
    subject = gen.sample_subject(SEED, 0)
    after_bake = peak_rss_since_reset_mb()
    gen.render(subject, views, 128)
    return {"bake_peak_mb": after_bake - base, "bake_render_peak_mb": peak_rss_since_reset_mb() - base}


def peak_memory(grid_resolution: int) -> dict:
    """peak_memory_child in its own fresh process (peak resident memory only ever grows)."""
    with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
        return pool.submit(peak_memory_child, grid_resolution).result()


def grid_scaling(plan: Plan) -> dict:
    bake_s = {g: [] for g in plan.grid_resolutions}
    render_s = {g: [] for g in plan.grid_resolutions}
    grid_mb = {}
    for index in range(plan.grid_subjects):
        for g in plan.grid_resolutions:
            gen = generator(grid_resolution=g)
            subject, seconds, _ = bake(gen, index)
            bake_s[g].append(seconds)
            render_s[g].append(render(gen, subject, views_of(index), 128)[1])
            grid_mb[g] = (subject.state.sdf.nbytes + subject.state.rgb.nbytes) / 2 ** 20
    rows = [{"grid_resolution": g, "bake_s": median(bake_s[g]), "render_s": median(render_s[g]),
             "grid_mb": grid_mb[g], **peak_memory(g)} for g in plan.grid_resolutions]
    return {"subjects": plan.grid_subjects, "views": VIEWS, "resolution": 128, "rows": rows}


# ------------------------------------------------------------------------------------------------
# Running it all

SECTIONS = (("one_subject", "one 32-view 128 px subject", one_subject),
            ("resolution", "image resolution", resolution_scaling),
            ("pipeline", "run_sample with 1 and 2 workers", pipeline_scaling),
            ("samples", "samples per ray against error", sample_sweep),
            ("grid", "bake grid resolution", grid_scaling))


def measure(quick: bool, command: str) -> dict:
    plan = QUICK if quick else FULL
    results = measurement_header("quick" if quick else "default", command, asdict(plan))
    run_sections(results, SECTIONS, (plan,), warm_up)
    return results


# ------------------------------------------------------------------------------------------------
# Conclusions, computed from the JSON

def _db(value) -> float:
    return math.inf if value is None else value


def sample_rows(results: dict, deterministic: bool) -> list[dict]:
    """Rows of one mode, fewest samples first."""
    rows = [r for r in results["samples"]["rows"] if r["deterministic"] == deterministic]
    return sorted(rows, key=lambda r: sum(r["samples"]))


def recommend(rows: list[dict]) -> dict:
    """Fewest samples reaching PSNR_TARGET_DB (foreground), else fewest within NEAR_BEST_DB of the best."""
    best = max(_db(r["psnr_fg_db"]) for r in rows)
    near_best = next(r for r in rows if _db(r["psnr_fg_db"]) >= best - NEAR_BEST_DB)
    at_target = next((r for r in rows if _db(r["psnr_fg_db"]) >= PSNR_TARGET_DB), None)
    return {"row": at_target or near_best, "rule": "target" if at_target else "near_best",
            "near_best": near_best, "best_db": best}


def _pct(a: float, b: float) -> str:
    """a relative to b as a signed percentage."""
    return f"{100.0 * (a / b - 1.0):+.0f} %"


def _samples(row) -> str:
    return f"({row['samples'][0]},{row['samples'][1]})"


def subject_conclusions(results: dict) -> list[str]:
    one = results["one_subject"]
    med = one["median"]
    verdict = "met" if one["goal_met"] else "NOT met"
    margin = GOAL_SECONDS - med["total_s"]
    other = med["render_s"] - med["trace_s"] - med["integrate_s"]
    return [
        f"One 32-view 128 px subject takes {med['total_s']:.2f} s (median of {len(one['subjects'])} subjects): "
        f"bake {med['bake_s']:.2f} s + render {med['render_s']:.2f} s. The goal of <= {GOAL_SECONDS:.0f} s is "
        f"**{verdict}** ({abs(margin):.2f} s {'to spare' if margin >= 0 else 'over'}); "
        f"{one['images_per_s']:.1f} images/s, {one['images_per_s_per_thread']:.1f} images/s per torch thread.",
        f"Where the render time goes: sphere tracing {100 * med['trace_s'] / med['render_s']:.0f} %, "
        f"band integration (the volume renderer) {100 * med['integrate_s'] / med['render_s']:.0f} %, "
        f"the rest (rays, compositing, copies) {100 * other / med['render_s']:.0f} %. "
        f"The analytic field evaluation is {100 * med['field_s'] / med['bake_s']:.0f} % of the bake.",
    ]


def resolution_conclusions(results: dict) -> list[str]:
    rows = results["resolution"]["rows"]
    lo, hi = rows[0], rows[-1]
    exponent = results["resolution"]["render_exponent"]
    return [
        f"Render time grows as pixels^{exponent:.2f} from {lo['resolution']} to {hi['resolution']} px "
        f"(1.00 would be proportional); per pixel it costs {lo['render_us_per_pixel']:.2f} us at "
        f"{lo['resolution']} px and {hi['render_us_per_pixel']:.2f} us at {hi['resolution']} px. "
        f"The bake ({lo['bake_s']:.2f} s) does not depend on the image size, so it is "
        f"{100 * lo['bake_s'] / lo['total_s']:.0f} % of a subject at {lo['resolution']} px and "
        f"{100 * hi['bake_s'] / hi['total_s']:.1f} % at {hi['resolution']} px.",
    ]


def pipeline_conclusions(results: dict) -> list[str]:
    pipe = results["pipeline"]
    rows = pipe["rows"]
    lines = [f"workers={r['workers']}: {r['images_per_s']:.1f} images/s against {rows[0]['images_per_s']:.1f} with "
             f"workers={rows[0]['workers']}, a speed-up of x{r['speedup']:.2f}." for r in rows[1:]]
    same = [s["total_s"] for s in results["one_subject"]["subjects"] if s["index"] < pipe["subjects"]]
    if len(same) == pipe["subjects"]:
        per_subject = rows[0]["seconds"] / pipe["subjects"]
        lines.append(f"With workers={rows[0]['workers']} the pipeline spends {per_subject:.2f} s per subject against "
                     f"{np.mean(same):.2f} s to bake and render the same subjects alone: encoding (PNG, EXR), "
                     f"tar writing and job setup add {_pct(per_subject, float(np.mean(same)))}.")
    lines.append(f"With workers=1 torch uses {rows[0]['threads_per_worker']} intra-op threads in the main process; "
                 "with more workers each worker process gets cpu_count / workers threads, and the timing includes "
                 "starting those processes (they import torch).")
    return lines


def sample_conclusions(results: dict) -> list[str]:
    sweep = results["samples"]
    det_mode = sweep.get("default_deterministic", False)
    mode = "deterministic" if det_mode else "jittered"
    chosen, other = recommend(sample_rows(results, det_mode)), recommend(sample_rows(results, not det_mode))
    default = next(r for r in sample_rows(results, det_mode) if r["samples"] == sweep["default_samples"])
    jit_default = next(r for r in sample_rows(results, False) if r["samples"] == sweep["default_samples"])
    det_default = next(r for r in sample_rows(results, True) if r["samples"] == sweep["default_samples"])
    pick = chosen["row"]
    rule = (f"the fewest samples with foreground PSNR >= {PSNR_TARGET_DB:.0f} dB" if chosen["rule"] == "target"
            else f"no setting reaches {PSNR_TARGET_DB:.0f} dB; the fewest samples within {NEAR_BEST_DB} dB of the best")
    if pick["samples"] == default["samples"]:
        verdict = f"The current default {_samples(default)} is justified."
    elif sum(pick["samples"]) < sum(default["samples"]):
        verdict = (f"The current default {_samples(default)} is more than needed: {_samples(pick)} renders "
                   f"{_pct(pick['render_s'], default['render_s'])} the time at {pick['psnr_fg_db']:.1f} dB "
                   f"(default {default['psnr_fg_db']:.1f} dB).")
    else:
        verdict = (f"The current default {_samples(default)} is too low ({default['psnr_fg_db']:.1f} dB); "
                   f"{_samples(pick)} reaches {pick['psnr_fg_db']:.1f} dB at {_pct(pick['render_s'], default['render_s'])} "
                   "the render time.")
    trace_share = [r["trace_s"] / r["render_s"] for r in sample_rows(results, True)]
    fewest, most = sample_rows(results, True)[0], sample_rows(results, True)[-1]
    return [
        f"Recommended samples per ray: **{_samples(pick)}** in the {mode} mode that datasets use "
        f"({rule}; {pick['psnr_fg_db']:.1f} dB, {pick['render_s']:.2f} s per subject). "
        f"In the other mode the same rule gives {_samples(other['row'])}. {verdict}",
        f"At the default {_samples(default)} jitter costs {det_default['psnr_fg_db'] - jit_default['psnr_fg_db']:.1f} dB "
        f"against the deterministic mode ({jit_default['psnr_fg_db']:.1f} vs {det_default['psnr_fg_db']:.1f} dB "
        "foreground PSNR).",
        f"The render time is not proportional to the samples: from {_samples(fewest)} to {_samples(most)} "
        f"({sum(most['samples']) / sum(fewest['samples']):.0f}x the samples) it grows x{most['render_s'] / fewest['render_s']:.1f}, "
        f"because sphere tracing, which does not depend on the samples, takes {100 * max(trace_share):.0f} % to "
        f"{100 * min(trace_share):.0f} % of it. The reference {tuple(sweep['reference_samples'])} takes "
        f"{sweep['reference_render_s']:.2f} s per subject.",
    ]


def grid_conclusions(results: dict) -> list[str]:
    rows = results["grid"]["rows"]
    lo, hi = rows[0], rows[-1]
    return [
        f"From grid {lo['grid_resolution']}^3 to {hi['grid_resolution']}^3 the bake goes from {lo['bake_s']:.2f} s to "
        f"{hi['bake_s']:.2f} s (x{hi['bake_s'] / lo['bake_s']:.1f}; the voxels grow x{(hi['grid_resolution'] / lo['grid_resolution']) ** 3:.1f}), "
        f"the render from {lo['render_s']:.2f} s to {hi['render_s']:.2f} s, the baked grid from {lo['grid_mb']:.0f} MB to "
        f"{hi['grid_mb']:.0f} MB and the peak memory of a bake from {lo['bake_peak_mb']:.0f} MB to {hi['bake_peak_mb']:.0f} MB.",
        "Image error is not compared across grid resolutions: each grid resolution bakes a slightly different head, "
        "so a reference rendered from one grid measures the geometry change, not the renderer.",
    ]


# ------------------------------------------------------------------------------------------------
# Markdown

def machine_section(results: dict) -> list[str]:
    m = results["machine"]
    return [
        f"Measured {results['date_utc']} in {results['mode']} mode ({results['benchmark_seconds'] / 60:.1f} min) on "
        f"{m['cpu_model']}: {m['cpu_count']} CPUs ({m['usable_cpus']} usable), torch {m['torch']} with "
        f"{m['torch_threads']} intra-op / {m['torch_interop_threads']} inter-op threads, Python {m['python']}, "
        f"numpy {m['numpy']}, {m['platform']}, git {m['git_revision']}.",
        "",
        load_note(results, m["usable_cpus"], "**other work competed for the CPUs, so the times are inflated**."),
        "",
        *reproduce(results["command"]),
        "",
        "Wall time by `time.perf_counter` after a warm-up subject; tables give medians over repeats "
        "(over subjects where a subject is rendered once). Stage times come from wrapping the procedural "
        "module's `head_field`, `sphere_trace` and `render_rays_chunked` for the duration of each call.",
    ]


def one_subject_section(results: dict) -> list[str]:
    one = results["one_subject"]
    cols = ("bake_s", "field_s", "render_s", "trace_s", "integrate_s", "total_s")
    names = ("bake", "  of which analytic field", "render", "  of which sphere trace", "  of which band integration", "total")
    rows = [[name, fmt(one["median"][c]), fmt(min(s[c] for s in one["subjects"])), fmt(max(s[c] for s in one["subjects"]))]
            for name, c in zip(names, cols)]
    per_subject = [[s["index"], s["hair_style"], fmt(s["bake_s"]), fmt(s["render_s"]), fmt(s["total_s"])]
                   for s in one["subjects"]]
    return (table(["seconds per subject", "median", "min", "max"], rows) + [""] +
            [f"Throughput: {one['images_per_s']:.1f} images/s, {one['images_per_s_per_thread']:.1f} images/s per "
             f"torch thread ({one['threads']} threads). Goal <= {GOAL_SECONDS:.0f} s per subject: "
             f"{'met' if one['goal_met'] else 'not met'}.", "", "Per subject:", ""] +
            table(["subject", "hair", "bake s", "render s", "total s"], per_subject))


def resolution_section(results: dict) -> list[str]:
    rows = [[f"{r['resolution']} px", r["subjects"], fmt(r["bake_s"]), fmt(r["render_s"]), fmt(r["total_s"]),
             fmt(r["images_per_s"], 1), fmt(r["render_us_per_pixel"])] for r in results["resolution"]["rows"]]
    return table(["resolution", "subjects", "bake s", "render s", "s / subject", "images/s", "render us / pixel"], rows)


def pipeline_section(results: dict) -> list[str]:
    pipe = results["pipeline"]
    rows = [[r["workers"], r["threads_per_worker"], r["repeats"], fmt(r["seconds"]), fmt(r["images_per_s"], 1),
             f"x{r['speedup']:.2f}"] for r in pipe["rows"]]
    return ([f"`run_sample`: {pipe['subjects']} subjects x {VIEWS} views at {pipe['resolution']} px, "
             f"{pipe['shards']} shards of {pipe['shard_size']}, written to a temporary folder; PNG + mask PNG + "
             "depth EXR per view.", ""] +
            table(["workers", "torch threads / worker", "repeats", "seconds", "images/s", "speed-up"], rows))


def samples_section(results: dict) -> list[str]:
    sweep = results["samples"]
    styles = ", ".join(f"{s['index']} ({s['hair_style']})" for s in sweep["subjects"])
    rows = []
    for deterministic in (True, False):
        for r in sample_rows(results, deterministic):
            rows.append([_samples(r), "deterministic" if deterministic else "jittered", fmt(r["render_s"]),
                         fmt(r["trace_s"]), fmt(r["integrate_s"]), fmt(r["psnr_db"], 1), fmt(r["psnr_fg_db"], 1),
                         fmt(r["worst_subject_psnr_fg_db"], 1), f"{r['alpha_mae']:.1e}",
                         f"{r['depth_mae_in_mask']:.1e}"])
    return ([f"Subjects {styles}; {sweep['views']} views at {sweep['resolution']} px; "
             f"reference {tuple(sweep['reference_samples'])} deterministic on the same grids and views; "
             f"render times are per subject (median over {sweep['repeats']} repeat(s), mean over subjects). "
             f"PSNR of rgb over all pixels and over foreground pixels (alpha > {FG_ALPHA:g} in either image); "
             f"depth error where both alphas exceed {DEPTH_ALPHA} (world units; the head is about 0.5 wide).", ""] +
            table(["samples (coarse,importance)", "mode", "render s", "trace s", "band s", "PSNR dB", "PSNR fg dB",
                   "worst subject fg dB", "alpha MAE", "depth MAE"], rows))


def grid_section(results: dict) -> list[str]:
    grid = results["grid"]
    rows = [[f"{r['grid_resolution']}^3", fmt(r["bake_s"]), fmt(r["render_s"]), fmt(r["grid_mb"], 0),
             fmt(r["bake_peak_mb"], 0), fmt(r["bake_render_peak_mb"], 0)] for r in grid["rows"]]
    return ([f"{grid['subjects']} subject(s); render of {grid['views']} views at {grid['resolution']} px. Peak memory is "
             "the growth of the peak resident set of a fresh process over one bake, then over bake + render.", ""] +
            table(["grid", "bake s", "render s", "grid MB", "peak bake MB", "peak bake + render MB"], rows))


def markdown(results: dict, plots: list[str]) -> str:
    summary = (subject_conclusions(results) + resolution_conclusions(results) + pipeline_conclusions(results) +
               sample_conclusions(results) + grid_conclusions(results))
    parts = [["# Procedural head generator and volume renderer: speed", "",
              "Generated by `benchmarks/datagen_speed.py` from `" + results_name(results) + ".json`; do not edit.", ""],
             machine_section(results), ["", "## Conclusions", ""], bullets(summary),
             ["", "## 1. One 32-view 128 px subject", ""], one_subject_section(results),
             ["", "## 2. Image resolution", ""], resolution_section(results), [""], bullets(resolution_conclusions(results)),
             ["", "## 3. Workers: the full run_sample pipeline", ""], pipeline_section(results), [""],
             bullets(pipeline_conclusions(results)),
             ["", "## 4. Samples per ray: render time against error", ""], samples_section(results), [""],
             bullets(sample_conclusions(results)),
             ["", "## 5. Bake grid resolution (time and memory only)", ""], grid_section(results), [""],
             bullets(grid_conclusions(results))]
    if plots:
        parts.append(["", "## Plots", ""] + [f"![{p}]({p})" for p in plots])
    else:
        parts.append(["", "Plots were skipped: matplotlib is not installed."])
    return "\n".join(line for part in parts for line in part) + "\n"


def results_name(results: dict) -> str:
    return report_name(NAME, results["mode"] == "quick")


# ------------------------------------------------------------------------------------------------
# Plots

def write_plots(results: dict, out_dir: Path) -> list[str]:
    """PNG plots beside the report; returns their file names ([] without matplotlib)."""
    plt = pyplot()
    if plt is None:
        print("matplotlib is not installed: skipping the plots (pip install matplotlib)")
        return []
    stem = results_name(results)
    plots = {f"{stem}_psnr_vs_time.png": plot_psnr_vs_time, f"{stem}_render_breakdown.png": plot_render_breakdown,
             f"{stem}_resolution.png": plot_resolution, f"{stem}_grid.png": plot_grid}
    for name, plot in plots.items():
        fig, ax = plt.subplots(figsize=(7, 4.5))
        plot(results, ax)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / name, dpi=110)
        plt.close(fig)
    return list(plots)


def plot_psnr_vs_time(results: dict, ax) -> None:
    sweep = results["samples"]
    for deterministic, marker in ((True, "o-"), (False, "s--")):
        rows = [r for r in sample_rows(results, deterministic) if r["psnr_fg_db"] is not None]
        ax.plot([r["render_s"] for r in rows], [r["psnr_fg_db"] for r in rows], marker,
                label="deterministic" if deterministic else "jittered (dataset default)")
        for r in rows:
            ax.annotate(_samples(r), (r["render_s"], r["psnr_fg_db"]), textcoords="offset points",
                        xytext=(4, -10 if deterministic else 5), fontsize=7)
    ax.axhline(PSNR_TARGET_DB, color="grey", linestyle=":", label=f"{PSNR_TARGET_DB:.0f} dB")
    ax.set_xlabel(f"render seconds per subject ({sweep['views']} views, {sweep['resolution']} px)")
    ax.set_ylabel("foreground PSNR vs reference (dB)")
    ax.set_title(f"Samples per ray (coarse,importance) vs reference {tuple(sweep['reference_samples'])}")
    ax.legend(fontsize=8)


def plot_render_breakdown(results: dict, ax) -> None:
    rows = sample_rows(results, True)
    labels = [_samples(r) for r in rows]
    trace = np.array([r["trace_s"] for r in rows])
    band = np.array([r["integrate_s"] for r in rows])
    rest = np.array([r["render_s"] for r in rows]) - trace - band
    ax.bar(labels, trace, label="sphere trace")
    ax.bar(labels, band, bottom=trace, label="band integration")
    ax.bar(labels, rest, bottom=trace + band, label="rest")
    ax.set_xlabel("samples per ray (coarse,importance), deterministic")
    ax.set_ylabel("render seconds per subject")
    ax.set_title("Where the render time goes")
    ax.legend(fontsize=8)


def plot_resolution(results: dict, ax) -> None:
    rows = results["resolution"]["rows"]
    pixels = [r["resolution"] ** 2 for r in rows]
    ax.loglog(pixels, [r["render_s"] for r in rows], "o-", label="render")
    ax.loglog(pixels, [r["total_s"] for r in rows], "s--", label="bake + render")
    for r, p in zip(rows, pixels):
        ax.annotate(f"{r['resolution']} px", (p, r["render_s"]), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set_xlabel("pixels per view")
    ax.set_ylabel("seconds per 32-view subject")
    ax.set_title(f"Image resolution (render ~ pixels^{results['resolution']['render_exponent']:.2f})")
    ax.legend(fontsize=8)


def plot_grid(results: dict, ax) -> None:
    rows = results["grid"]["rows"]
    res = [r["grid_resolution"] for r in rows]
    ax.plot(res, [r["bake_s"] for r in rows], "o-", label="bake")
    ax.plot(res, [r["render_s"] for r in rows], "s--", label="render (32 views, 128 px)")
    ax.set_xticks(res)
    ax.set_xlabel("bake grid resolution (voxels per side)")
    ax.set_ylabel("seconds per subject")
    ax.set_title("Bake grid resolution")
    ax.legend(fontsize=8)


# ------------------------------------------------------------------------------------------------

def main(argv=None) -> None:
    report_main(argv, script=Path(__file__), name=NAME, doc=__doc__,
                quick_help="few repeats and small sizes (under 2 minutes)",
                report_only_help="measure nothing: rewrite the markdown and plots from the existing JSON",
                measure=measure, render=lambda results, out_dir: markdown(results, write_plots(results, out_dir)))


if __name__ == "__main__":
    main()
