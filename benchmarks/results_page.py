"""docs/results.md from the committed reports: every measured figure, with the report, seeds and machine it comes from.

    python -m benchmarks.results_page            # rewrite docs/results.md from benchmarks/reports/*.json and *.md
    python -m benchmarks.results_page --check    # exit 1 when docs/results.md differs from what the reports give

The page is only ever written by this script, so its figures cannot drift from their reports: rerun it
after a benchmark rewrites a report. Each section links the report's markdown and JSON, names the
machine (CPU, usable CPUs, torch, git revision, date, load average) and the seeds the JSON records,
and lists the headline figures read from the JSON. Reports this script has no reader for still get a
section (links, machine, seeds), so a new benchmark shows up without an edit here.
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from collections.abc import Callable

import numpy as np

from benchmarks.common import REPO, REPORTS, table
from benchmarks.data_value import trained_on
from datagen.files import atomic_write

PAGE = REPO / "docs" / "results.md"
LINK = "../benchmarks/reports"  # the reports folder as seen from docs/

# ------------------------------------------------------------------------------------------------
# Small formatting helpers


def num(value, digits: int = 2) -> str:
    """``value`` with ``digits`` decimals, "n/a" for a missing or NaN figure."""
    if value is None or (isinstance(value, float) and value != value):
        return "n/a"
    return f"{value:,.{digits}f}"


def mib(n_bytes: float) -> str:
    return f"{n_bytes / 2**20:.1f} MiB"


def median(values) -> float:
    return float(statistics.median(values))


def percentile(values, q: float) -> float:
    """The ``q``-th percentile with linear interpolation (numpy's default, as the latency benchmark computes it)."""
    return float(np.percentile(values, q))


# ------------------------------------------------------------------------------------------------
# Headline figures, one reader per report family (the quick and two-hour variants share the full run's)


def datagen_speed(d: dict) -> list[str]:
    one, pipe, samples = d["one_subject"], d["pipeline"], d["samples"]
    m = one["median"]
    lines = [f"One procedural subject, {one['views']} views at {one['resolution']} px, {one['threads']} threads: "
             f"{num(m['total_s'])} s (bake {num(m['bake_s'])} s, render {num(m['render_s'])} s; goal "
             f"<= {num(one['goal_s'], 1)} s: {'met' if one['goal_met'] else 'missed'}), "
             f"{num(one['images_per_s'], 1)} images/s.",
             "Time per subject against resolution: " + ", ".join(
                 f"{r['resolution']} px {num(r['total_s'])} s" for r in d["resolution"]["rows"])
             + f" (render time grows as resolution^{num(d['resolution']['render_exponent'])} per side).",
             f"A dataset of {pipe['subjects']} subjects ({pipe['images']} images at {pipe['resolution']} px): " + ", ".join(
                 f"{r['workers']} worker(s) x {r['threads_per_worker']} thread(s) {num(r['images_per_s'], 1)} images/s"
                 for r in pipe["rows"]) + "."]
    default = next(r for r in samples["rows"] if r["samples"] == samples["default_samples"])
    lines.append(f"Default samples per ray {default['samples']} against {samples['reference_samples']}: foreground "
                 f"PSNR {num(default['psnr_fg_db'], 1)} dB (worst subject {num(default['worst_subject_psnr_fg_db'], 1)}"
                 f" dB), render {num(default['render_s'])} s against {num(samples['reference_render_s'])} s.")
    return lines


def procedural_people(d: dict) -> list[str]:
    lines = []
    for name, r in d["identity"].items():
        dist = r["distances"]
        same = [x for x, s in zip(dist, r["same_sex"]) if s]
        other = [x for x, s in zip(dist, r["same_sex"]) if not s]
        below = sum(x < 0.6 for x in dist) / len(dist)
        lines.append(f"Generator {name}, {r['subjects']} subjects of seeds {r['seeds']}: dlib finds a face in "
                     f"{r['detected_128']} of {r['subjects']} frontal views at 128 px; median face-embedding distance "
                     f"between different subjects {num(median(dist), 3)} (per seed " + ", ".join(
                         f"{k}: {num(v, 3)}" for k, v in r["median_per_seed"].items())
                     + f"), {num(median(other), 3)} between sexes and {num(median(same), 3)} within one; "
                     f"{below:.0%} of the pairs fall below dlib's same-person threshold 0.6.")
    for name, runs in d["speed"].items():
        lines.append(f"Generator {name}: a subject (bake and render) takes "
                     f"{num(median([r['bake_s'] + r['render_s'] for r in runs]))} s (median of {len(runs)}).")
    return lines


def gan_speed(d: dict) -> list[str]:
    lines = []
    views = d["plan"]["views"]
    for model, thr in d["throughput"].items():
        batched = median([r["batched"]["total_s"] for r in thr["rows"]])
        line = f"{model}: a subject of {views} views in {num(batched)} s (views batched)"
        if model in d["samples"]:
            s = d["samples"][model]
            row = next(r for r in s["rows"] if r["samples"] == s["default_samples"])
            line += (f"; default samples per ray {row['samples']}: {num(row['ms_per_view'], 0)} ms/view, "
                     f"{num(row['psnr_rgb_db'], 1)} dB from the reference")
        if model in d.get("precision", {}):
            p = d["precision"][model]
            line += (f"; fp16 against fp32 at {p['resolution']} px: {num(p['psnr_db'], 1)} dB (max difference "
                     f"{num(p['max_abs'], 4)}, {p['levels_changed']:.1%} of 8-bit values change)")
        if model in d.get("clipping", {}):
            c = d["clipping"][model]
            line += (f"; `--clip-rays` keeps {c['mean_range_kept']:.0%} of the ray range, {num(c['psnr_rgb_db'], 1)} dB"
                     f" from the unclipped render, {num(c['clipped_s'])} s against {num(c['unclipped_s'])} s")
        lines.append(line + ".")
    return lines


def gan_fullsize(d: dict) -> list[str]:
    lines = []
    for model in d["plan"]["models"]:
        m = d[model]
        t = m["timing"]
        lines.append(f"{model} ({m['parameters']['total'] / 1e6:.1f} M parameters), {t['views']} views at 512 px "
                     f"on the CPU: {num(t['total_s'], 1)} s (ray march {num(t['seconds']['march'], 1)} s, "
                     f"super-resolution {num(t['seconds']['super_resolution'], 1)} s), {num(t['images_per_s'], 3)} "
                     f"images/s; {m['flops']['per_view'] / 1e9:,.0f} GFLOP per view.")
    return lines


def shape_speed(d: dict) -> list[str]:
    rows = []
    for kind in ("procedural", "eg3d_fixture"):
        for res in d["plan"]["resolutions"]:
            r = d[kind][str(res)]
            b = r["bytes"]
            rows.append([kind, f"{res}^3", f"{num(r['seconds'], 1)} s", f"{num(r['peak_rss_mb_above_start'], 0)} MiB",
                         f"{r['vertices']:,}", mib(b["ply"]), mib(b["obj"]), mib(b["glb"])])
    return table(["subject", "grid", "time", "peak memory", "vertices", "PLY", "OBJ", "GLB"], rows)


def preflags_quality(d: dict) -> list[str]:
    pooled = d["pooled"]["rows"]
    any_ = pooled["any"]
    clean = sum(r["eval"]["clean"] for r in d["runs"].values())
    lines = ["Runs: " + ", ".join(f"{name} (seed {r['seed']}, {r['eval']['subjects']} subjects)"
                                  for name, r in d["runs"].items())
             + f"; false-alarm rate {d['false_alarm_rate']}.",
             f"Any defect: precision {num(any_['precision'])}, recall {num(any_['recall'])} ({any_['tp']} of "
             f"{any_['positives']}), lowest AUC {num(any_['auc_min'])}; clean subjects flagged: "
             f"{d['pooled']['clean_flagged_share']:.1%} of {clean}.",
             "Per class (flagged as that class of the injected): " + ", ".join(
                 f"{name} {r['tp']} of {r['positives']}" for name, r in pooled.items() if name != "any") + "."]
    nulls: dict[str, dict[str, list[float]]] = {}
    for row in d["synthetic_nulls"]:
        for rule in ("own_thresholds", "calibrated"):
            nulls.setdefault(row["null"], {}).setdefault(rule, []).append(row[rule])
    lines.append("Share of synthetic clean subjects the union flags, at the detectors' own thresholds and "
                 "calibrated: " + "; ".join(
                     f"{name} " + " and ".join(f"{min(v):.1%} to {max(v):.1%}" for v in rules.values())
                     for name, rules in nulls.items()) + ".")
    return lines


def preflags_speed(d: dict) -> list[str]:
    lines = [f"{res} px ({r['subjects']} subjects): {num(r['subjects_per_cpu_second'])} subjects per CPU second, "
             f"janus's CNN detector {num(r['janus_cnn_ms'], 0)} ms a subject" for res, r in d["runs"].items()]
    return [line + "." for line in lines] + [
        f"165K subjects at 512 px on 64 cores: {num(d['hours_165k_on_64_cores'])} h."]


def gui_latency(d: dict) -> list[str]:
    names = {"next": "next subject", "verdict": "verdict", "triage_page": "triage page", "view3d_on": "3D on"}
    lines = []
    for session in d["sessions"].values():
        keys = session["keys"]
        lines.append(f"{session['resolution']} px ({session['subjects']:,} subjects): open to first frame "
                     f"{num(session['open_s'])} s; p50/p95 " + ", ".join(
                         f"{label} {num(percentile([k['ms'] for k in keys[key]], 50), 0)}/"
                         f"{num(percentile([k['ms'] for k in keys[key]], 95), 0)} ms"
                         for key, label in names.items()) + ".")
    return lines


def panolam_recipe(d: dict) -> list[str]:
    f = d["figures"]
    model, untrained, template = f["this model"], f["baseline: untrained"], f["baseline: mean colour template"]
    options = f" `{d['train_options']}`" if d.get("train_options") else ""
    return [f"{d['subjects']} subjects (seed {d['seed']}, {d['test_count']} held out), `tiny`{options} for "
            f"{d['time_limit_s']} s: {d['steps_done']} steps; last line `{d['last_step']}`.",
            f"Full-frame PSNR over {d['eval_subjects']} held-out subjects: {num(model['all']['psnr'])} dB, untrained "
            f"{num(untrained['all']['psnr'])} dB, mean-colour template {num(template['all']['psnr'])} dB.",
            f"Novel views, foreground PSNR: {num(model['novel']['psnr_fg'])} dB against the template's "
            f"{num(template['novel']['psnr_fg'])} dB ({model['novel']['psnr_fg'] - template['novel']['psnr_fg']:+.2f} "
            f"dB, difference of means); SSIM {num(model['all']['ssim'], 3)} (untrained "
            f"{num(untrained['all']['ssim'], 3)}).",
            f"One reconstruction: {num(d['reconstruct_s_median'], 3)} s (median).",
            "Load average around training: before " + num(d["load_average"]["before_training"][0])
            + ", after " + num(d["load_average"]["after_training"][0]) + "."]


def study_of_arms(d: dict) -> list[str]:
    """A study of arms at equal steps (data_value, recipe_tuning): each arm's figures, then its paired differences."""
    s = d["settings"]
    lines = [f"Every arm `tiny`, {s['steps']} steps of batch {s['batch_size']}; scored on {s['held_out']} held-out "
             f"subjects of seed {d['seeds']['held_out']} (novel views, foreground PSNR)."]
    lines += [f"{name}: {r['train_subjects']} training subjects, held-out {num(r['held_out']['novel']['psnr_fg'])} dB "
              f"(full frame {num(r['held_out']['all']['psnr'])} dB), training batches {num(r['train_batch_psnr'])} dB, "
              f"{num(r['step_s_median'])} s a step." for name, r in d["arms"].items()]
    lines += [f"{name}: {c['novel_psnr_fg']['mean']:+.2f} dB, 95 % interval {c['novel_psnr_fg']['ci95'][0]:+.2f} to "
              f"{c['novel_psnr_fg']['ci95'][1]:+.2f}." for name, c in d["comparisons"].items()]
    return lines + [line for line in trained_on(d["arms"]) if line]


def panolam_training(d: dict) -> list[str]:
    base = {name: b["per_view"]["all"]["psnr"] for name, b in d["baselines"].items()}
    main = d["final"]["main"]
    psnr = main["per_view"]["all"]["psnr"]
    lines = [f"`tiny` after {main['step']} steps on {d['args']['subjects'] - d['args']['test_count']} subjects: "
             f"PSNR {num(psnr)} dB, SSIM {num(main['per_view']['all']['ssim'], 3)} on {main['subjects']} held-out "
             f"subjects (front, left, back, right); " + ", ".join(
                 f"{name.replace('_', ' ')} {num(v)} dB ({psnr - v:+.2f} dB)" for name, v in base.items()) + ".",
             f"One reconstruction {num(main['reconstruct_s_median'] * 1000, 0)} ms, one view "
             f"{num(main['render_ms_per_view_median'], 0)} ms, {num(main['train_s_per_step_median'], 2)} s per step.",
             "Ablations: " + ", ".join(f"{name} {num(r['per_view']['all']['psnr'])} dB at step {r['step']}"
                                       for name, r in d["final"].items() if name != "main") + "."]
    return lines


def speed_vs_error(d: dict) -> list[str]:
    rows = [[r["axis"].replace("_", " "), r["value"], num(r["per_view"]["all"]["psnr"]),
             f"{num(r['reconstruct_s_median'] * 1000, 0)} ms", f"{num(r['render_ms_per_view_median'], 1)} ms",
             f"{num(r['peak_mb'], 0)} MiB"] for r in d["speed_vs_error"]]
    return table(["axis", "value", "PSNR (dB)", "reconstruction", "view", "peak memory"], rows)


def model_speed(d: dict) -> list[str]:
    rows = [[r["config"], r["dense_points"], num(r["forward_s"]), num(r.get("fwd_bwd_s")),
             f"{num(r.get('fwd_bwd_peak_mb') or r['forward_peak_mb'], 0)} MiB"] for r in d["rows"]]
    return table(["config", "dense points", "forward (s)", "forward+backward (s)", "peak memory"], rows)


def train_step(d: dict) -> list[str]:
    before = d["variants"]["before"]["cpu_median_s"]
    rows = [[v["what"], num(v["cpu_median_s"]), num(v["median_s"]), f"{before / v['cpu_median_s']:.2f}x"]
            for v in d["variants"].values()]
    return table(["`tiny` step", "CPU s/step", "wall s/step", "speed-up (CPU)"], rows) + [
        "", f"{d['threads']} thread(s), {d['rounds']} rounds; load average {num(d['load_before'])} before, "
            f"{num(d['load_after'])} after."]


def rasterizer_speed(d: dict) -> list[str]:
    rows = [[r["variant"], f"{r['n']:,}", r["resolution"], r["torch_threads"], r.get("omp_wait_policy", "default"),
             num(r["forward_median_s"], 3), num(r["backward_median_s"], 3), f"{num(r['peak_mb'], 0)} MiB",
             f"{r['block_pairs']:,}" if "block_pairs" in r else ""] for r in d["rows"]]
    return table(["variant", "Gaussians", "px", "threads", "OMP wait", "forward (s)", "backward (s)", "peak memory",
                  "block pairs"], rows)


def rasterizer_constants(d: dict) -> list[str]:
    rows = [[r["scene"], r["variant"], "identical" if r["psnr_db"] is None else num(r["psnr_db"], 1),
             num(r["max_abs"], 3)] for r in d["rows"]]
    return table(["scene", "variant against gsplat's constants", "PSNR (dB)", "max difference"], rows)


def threads(d: dict) -> list[str]:
    rows, worst = [], 0.0
    for condition, commands in d["seconds"].items():
        for command, times in commands.items():
            ratio = times["default"] / min(times.values())
            worst = max(worst, ratio)
            rows.append([condition, command] + [num(t, 1) for t in times.values()] + [f"{ratio:.2f}x"])
    settings = list(next(iter(next(iter(d["seconds"].values())).values())))
    return table(["machine", "command"] + [f"{s} (s)" for s in settings] + ["default / best"], rows) + [
        "", f"Worst default against the best setting: {worst:.2f}x."]


READERS: dict[str, Callable[[dict], list[str]]] = {
    "datagen_speed": datagen_speed, "procedural_people": procedural_people, "gan_speed": gan_speed,
    "gan_fullsize": gan_fullsize, "shape_speed": shape_speed, "preflags_quality": preflags_quality,
    "preflags_speed": preflags_speed, "gui_latency": gui_latency, "panolam_recipe": panolam_recipe,
    "panolam_training": panolam_training, "speed_vs_error": speed_vs_error, "model_speed": model_speed,
    "train_step": train_step, "rasterizer_speed": rasterizer_speed, "rasterizer_constants": rasterizer_constants,
    "threads": threads, "data_value": study_of_arms, "recipe_tuning": study_of_arms}

# The page's order: stems (and the variants that start with them) by what they measure.
GROUPS = {"Data generation": ["datagen_speed", "procedural_people", "gan_speed", "gan_fullsize", "shape_speed"],
          "Curation": ["preflags_quality", "preflags_tuning", "preflags_speed", "gui_latency"],
          "PanoLAM": ["panolam_recipe", "recipe_tuning", "data_value", "panolam_training", "speed_vs_error",
                      "model_speed", "train_step", "rasterizer_speed", "rasterizer_constants"],
          "Machine": ["threads"]}


def reader_for(stem: str) -> Callable[[dict], list[str]] | None:
    """The reader of ``stem`` or of the family it is a variant of (``datagen_speed_quick``, ``panolam_recipe_2h``)."""
    family = max((name for name in READERS if stem == name or stem.startswith(name + "_")), key=len, default=None)
    return READERS.get(family)


# ------------------------------------------------------------------------------------------------
# Machine, seeds, links


def machine_of(d: dict) -> dict | None:
    """The machine block a report records (the speed run's for speed_vs_error, the main run's for the study)."""
    return d.get("machine") or d.get("speed_machine") or d.get("final", {}).get("main", {}).get("machine")


def start_load(d: dict) -> float | None:
    """The 1-minute load average when the report's run began, wherever the report keeps it."""
    load = d.get("load_average")
    if isinstance(load, dict) and load.get("before") is not None:
        return load["before"]
    for key in ("load_before", "load_average_before"):
        if d.get(key) is not None:
            return d[key][0] if isinstance(d[key], list) else d[key]
    m = machine_of(d) or {}
    return m["load_average"][0] if m.get("load_average") else None


def machine_line(d: dict) -> str:
    """CPU, usable CPUs, torch, threads, revision, date and starting load of the run behind a report."""
    m = machine_of(d)
    if not m:
        return "Machine: not recorded."
    host = ", ".join(m[k] for k in ("cpu_family_model", "cpu_capability") if m.get(k))
    parts = [m.get("cpu_model", "unknown CPU") + (f" ({host})" if host else ""),
             f"{m.get('usable_cpus', m.get('cpu_count'))} usable CPUs", f"torch {m.get('torch', '?')}"]
    if m.get("torch_threads") is not None:
        parts.append(f"torch threads {m['torch_threads']}")
    if m.get("git_revision"):
        parts.append(f"revision {m['git_revision'][:7]}{'+dirty' if m['git_revision'].endswith('+dirty') else ''}")
    date = m.get("date") or d.get("date_utc") or d.get("date") or d.get("when")
    if date:
        parts.append(date[:10])
    if start_load(d) is not None:
        parts.append(f"load average {num(start_load(d))} at the start")
    return "Machine: " + ", ".join(parts) + "."


def seeds_of(d, depth: int = 0) -> set[int]:
    """Every integer recorded under a ``seed`` or ``seeds`` key in the top three levels of a report."""
    found: set[int] = set()
    if depth > 3:
        return found
    items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) and depth < 2 else ()
    for key, value in items:
        if key in ("seed", "seeds"):
            found |= {v for v in (value if isinstance(value, list) else [value]) if isinstance(v, int)}
        elif isinstance(value, (dict, list)):
            found |= seeds_of(value, depth + 1)
    return found


def figures_of(markdown: str) -> list[str]:
    """The PNG files a report's markdown shows, in order, once each."""
    return list(dict.fromkeys(re.findall(r"\]\(([^)\s]+\.png)\)", markdown)))


def section(stem: str) -> list[str]:
    md_path, json_path = REPORTS / f"{stem}.md", REPORTS / f"{stem}.json"
    markdown = md_path.read_text() if md_path.exists() else ""
    title = next((line[2:].strip() for line in markdown.splitlines() if line.startswith("# ")), stem)
    links = [f"[{p.name}]({LINK}/{p.name})" for p in (md_path, json_path) if p.exists()]
    lines = [f"### {title} (`{stem}`)", "", f"Report: {', '.join(links)}."]
    figures = [f"[{name}]({LINK}/{name})" for name in figures_of(markdown) if (REPORTS / name).exists()]
    if figures:
        lines[-1] += f" Figures: {', '.join(figures)}."
    if not json_path.exists():
        return lines + ["", "No JSON: the figures are in the report."]
    try:
        data = json.loads(json_path.read_text())
    except json.JSONDecodeError as e:
        raise SystemExit(f"results_page: {json_path}: not valid JSON ({e})")
    command = data.get("command") or data.get("args", {}).get("command")
    if command:
        lines += ["", f"Command: `{command}`."]
    seeds = seeds_of(data)
    lines += ["", machine_line(data) + (f" Seeds: {', '.join(map(str, sorted(seeds)))}." if seeds else "")]
    reader = reader_for(stem)
    if reader is None:
        return lines + ["", "No headline reader for this report: the figures are in it."]
    try:
        body = reader(data)
    except (KeyError, TypeError, StopIteration, ValueError, ZeroDivisionError) as e:
        raise SystemExit(f"results_page: {json_path}: lacks a field its headline reader needs ({e!r})")
    if body and body[0].startswith("|"):
        return lines + [""] + body
    return lines + [""] + [f"- {line}" for line in body]


def grouped() -> dict[str, list[str]]:
    """Every report under benchmarks/reports/ (by its .md or .json) under its heading; reports of no group last."""
    found = sorted({p.stem for p in REPORTS.glob("*.md")} | {p.stem for p in REPORTS.glob("*.json")})
    groups: dict[str, list[str]] = {}
    placed: set[str] = set()
    for name, bases in GROUPS.items():
        groups[name] = [s for base in bases for s in found
                        if (s == base or s.startswith(base + "_")) and s not in placed]
        placed.update(groups[name])
    groups["Other reports"] = [s for s in found if s not in placed]
    return groups


def build() -> str:
    """The page's text."""
    lines = ["# Results", "",
             "Written by `python -m benchmarks.results_page` from the committed reports in `benchmarks/reports/`; "
             "do not edit by hand. Every figure below is read from the report's JSON and names its report; "
             "each section gives the machine and seeds that report records. Run the benchmark (its command is "
             "given), then this script, to update a section. What each benchmark measures: "
             "[benchmarks.md](benchmarks.md)."]
    shown: set[str] = set()
    for name, members in grouped().items():
        if members:
            lines += ["", f"## {name}"]
        for stem in members:
            lines += [""] + section(stem)
            md_path = REPORTS / f"{stem}.md"
            shown.update(figures_of(md_path.read_text()) if md_path.exists() else [])
    loose = sorted(p.name for p in REPORTS.glob("*.png") if p.name not in shown)
    if loose:
        lines += ["", "## Other figures", "", "Images under `benchmarks/reports/` that no report shows: "
                  + ", ".join(f"[{n}]({LINK}/{n})" for n in loose) + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.results_page", description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="only compare docs/results.md with the reports")
    args = parser.parse_args(argv)
    text = build()
    if args.check:
        if not PAGE.exists() or PAGE.read_text() != text:
            print(f"{PAGE}: out of date with benchmarks/reports/; run python -m benchmarks.results_page",
                  file=sys.stderr)
            return 1
        print(f"{PAGE}: up to date")
        return 0
    atomic_write(PAGE, text.encode())
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
