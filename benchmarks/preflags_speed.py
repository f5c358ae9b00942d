"""Throughput of the automatic pre-flags (``label-tool auto``): subjects per second per core at 128 and
512 px, what each detector costs, and the hours for the paper's 165K subjects on 64 cores.

Protocol: a procedural 360 dataset (32 views, the generator's default defect rate, ``--seed``) at
each resolution, made once (``--keep`` reuses it). Each subject is read and measured in this one
process, one after the other, as one ``label-tool auto`` worker does: read+decode (the members the
detectors need), then each detector's ``measure``. Per-core throughput is subjects per CPU second
of this process (``time.process_time``, all its threads), so other work on the machine slows the
wall clock, not the figure; the wall-clock rate and the load average are reported beside it. The
scores (``score``, from the records) take milliseconds for a whole dataset and are left out. The
report's sha256 (less its timing) is recorded per dataset: the same code and seed give the same.

janus runs dlib's CNN face detector only where HOG or the eye cascade sees something face-like
(``janus.face_like``). For the comparison in the same run, on the same machine and load, the CNN
is also run (timed apart, then taken out of the figures) on every other back view: the throughput
with the CNN everywhere (``Janus.Settings.cnn_always``, the behaviour before) adds its CPU seconds,
and the report scored from records with those CNN results shows whether any score or flag changes.
The same check on a janus-rich dataset (``--janus-subjects``, seed + 1) counts the faces the CNN finds
where the gate kept it from running.

    python -m benchmarks.preflags_speed --keep /tmp/pfspeed   # about 10 min on 2 cores, datasets kept
    python -m benchmarks.preflags_speed --quick                # a smoke run, about 3 minutes
    python -m benchmarks.preflags_speed --report-only          # rewrite the markdown from the JSON

Writes ``benchmarks/reports/preflags_speed.{json,md}``.
"""
from __future__ import annotations

import hashlib
import json
import tempfile
import time
from pathlib import Path

from datagen.generators.procedural import ProceduralConfig
from datagen.dataset import Dataset
from datagen.dataset.preflags import write_preflags
from labeling_tool.preflags import DETECTORS, SubjectViews, measure_subject, score
from labeling_tool.preflags.janus import CNN_VIEW_PX, best_cnn_face
from labeling_tool.preflags.scoring import plan

from .common import REPORTS, benchmark_parser, command_line, load_average, machine_info, median, write_json
from .preflags_quality import generate

REPORT = REPORTS / "preflags_speed"
PAPER_SUBJECTS = 165_000   # 48K + 117K subjects kept in the paper's dataset
CLUSTER_CORES = 64
GOALS = {128: 5.0, 512: PAPER_SUBJECTS / (CLUSTER_CORES * 3600.0)}  # subjects/s/core: stated goal, 1 hour
JANUS_RATE = 0.6  # share of the gate check's subjects given a janus


def measure_dataset(root: Path) -> dict:
    """Per subject: read+decode and each detector's CPU seconds; the whole run's wall and CPU seconds; the
    same with the CNN on every back view; whether that changes any score or flag."""
    dataset = Dataset(root)
    tasks, _ = plan(dataset)
    stages = {"read+decode": []} | {d.name: [] for d in DETECTORS}
    records, everywhere, cnn_cpu, cnn_wall, skipped_cpu = [], [], [], [], []
    found = missed = 0  # back views where the CNN finds a face; of them, where the gate kept it from running
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for shard, tar, key, start, end in tasks:
        t = time.process_time()
        views = SubjectViews.read(tar, key, start, end)
        stages["read+decode"].append(time.process_time() - t)
        measured = {}
        for d in DETECTORS:
            t = time.process_time()
            measured[d.name] = d.measure(views)
            stages[d.name].append(time.process_time() - t)
        record = measure_subject(views, ())
        record["measured"] = measured
        records.append((shard, record))
        janus = measured["janus"]
        if janus and "na" not in janus and views.rgb.get(views.back) is not None:
            t, c = time.perf_counter(), time.process_time()  # the part of janus that does not depend on the size
            confidence = best_cnn_face(views.rgb[views.back], views.mask(views.back))
            cnn_cpu.append(time.process_time() - c)
            cnn_wall.append(time.perf_counter() - t)
            if janus["cnn"] is None:
                skipped_cpu.append(cnn_cpu[-1])
                missed += confidence > 0.0
            found += confidence > 0.0
            janus = dict(janus, cnn=confidence)
        everywhere.append((shard, dict(record, measured=dict(measured, janus=janus))))
    wall, cpu = time.perf_counter() - wall0 - sum(cnn_wall), time.process_time() - cpu0 - sum(cnn_cpu)
    index_sha = dataset.index_sha256
    report = score({"index_sha256": index_sha, "records": records, "skipped_shards": []})
    reference = score({"index_sha256": index_sha, "records": everywhere, "skipped_shards": []})
    verdicts = {r["subject"]: (r["flags"], {k: d["score"] for k, d in r["detectors"].items()})
                for r in reference["subjects"]}
    changed = sorted(s["subject"] for s in report["subjects"]
                     if (s["flags"], {k: d["score"] for k, d in s["detectors"].items()}) != verdicts[s["subject"]])
    report.pop("timing")
    blob = write_preflags(root, report, root / "preflags-speed-report.json").read_bytes()
    n = len(tasks)
    return {"dataset": str(root), "subjects": n, "wall_seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
            "subjects_per_cpu_second": round(n / cpu, 3), "subjects_per_wall_second": round(n / wall, 3),
            "stage_ms": {k: {"median": round(1000 * median(v), 1), "mean": round(1000 * sum(v) / len(v), 1)}
                         for k, v in stages.items()},
            "janus_cnn_ms": round(1000 * median(cnn_cpu), 1) if cnn_cpu else None,
            "cnn_subjects": len(cnn_cpu) - len(skipped_cpu), "back_views": len(cnn_cpu),
            "cnn_faces": found, "cnn_faces_gate_closed": missed,
            "subjects_per_cpu_second_cnn_everywhere": round(n / (cpu + sum(skipped_cpu)), 3),
            "changed_with_cnn_everywhere": changed,
            "report_sha256": hashlib.sha256(blob).hexdigest(), "flagged": report["summary"]["flagged"]}


def hours_for(subjects: int, per_core: float, cores: int = CLUSTER_CORES) -> float:
    return subjects / (per_core * cores) / 3600.0


def write_markdown(data: dict) -> str:
    m = data["machine"]
    lines = ["# Pre-flags throughput", "",
             f"`{data['command']}` on {data['when']}; {m['cpu_model']}, {m['usable_cpus']} usable CPUs; load average "
             f"(1 min) {data['load_before']:.2f} before, {data['load_after']:.2f} after "
             "(the machine is shared; per-core figures count this process's CPU seconds).", "",
             "Procedural 360 datasets (32 views, default defect rate, seed "
             f"{data['seed']}); one process measures subject after subject, as one `label-tool auto` worker does.", "",
             "| resolution | subjects | subjects/s/core (CPU) | subjects/s (wall) | goal, subjects/s/core | "
             f"{PAPER_SUBJECTS // 1000}K subjects on {CLUSTER_CORES} cores | subjects/s/core, CNN on every back view |",
             "|---|---|---|---|---|---|---|"]
    for res, r in data["runs"].items():
        goal = GOALS[int(res)]
        met = "met" if r["subjects_per_cpu_second"] >= goal else "**missed**"
        lines.append(f"| {res} px | {r['subjects']} | {r['subjects_per_cpu_second']:.2f} | "
                     f"{r['subjects_per_wall_second']:.2f} | {goal:.2f} ({met}) | "
                     f"{hours_for(PAPER_SUBJECTS, r['subjects_per_cpu_second']):.2f} h | "
                     f"{r['subjects_per_cpu_second_cnn_everywhere']:.2f} |")
    lines += ["", "Per subject, CPU milliseconds (median; mean in brackets), most expensive first at the largest size:", ""]
    sizes = list(data["runs"])
    names = sorted(data["runs"][sizes[-1]]["stage_ms"], key=lambda k: -data["runs"][sizes[-1]]["stage_ms"][k]["mean"])
    lines += ["| stage | " + " | ".join(f"{s} px" for s in sizes) + " |", "|---|" + "---|" * len(sizes)]
    for k in names:
        lines.append(f"| {k} | " + " | ".join(f"{data['runs'][s]['stage_ms'][k]['median']:.1f} "
                                              f"({data['runs'][s]['stage_ms'][k]['mean']:.1f})" for s in sizes) + " |")
    lines += ["", "Report sha256 (less its timing) per dataset, to compare runs of the same seed: " +
              ", ".join(f"{s} px `{data['runs'][s]['report_sha256'][:16]}`" for s in sizes), ""]
    for s in sizes:
        r = data["runs"][s]
        if r["janus_cnn_ms"]:
            changed = r["changed_with_cnn_everywhere"]
            lines.append(f"- {s} px: dlib's CNN face detector (janus, on the back view's head scaled to "
                         f"{CNN_VIEW_PX} px, so the same cost at any size) costs {r['janus_cnn_ms']:.0f} CPU ms a "
                         f"back view; it ran on {r['cnn_subjects']} of {r['back_views']} back views (where HOG or "
                         "the eye cascade saw something face-like). Run on every back view it changes "
                         + (f"the scores or flags of {len(changed)} subjects ({', '.join(changed)})." if changed
                            else "no score and no flag (the explanations say where it was not run)."))
    j = data.get("janus_check")
    if j:
        changed = j["changed_with_cnn_everywhere"]
        lines.append(f"- The CNN's gate on a janus-rich dataset (seed {j['seed']}, {j['subjects']} subjects at 128 px, "
                     f"{100 * j['defect_rate']:.0f} % given a janus): run on every back view the CNN finds "
                     f"{j['cnn_faces']} faces, {j['cnn_faces_gate_closed']} of them where the gate kept it from "
                     f"running; the gate opened on {j['cnn_subjects']} of {j['back_views']} back views. Run "
                     "everywhere it changes " + (f"the scores or flags of {len(changed)} subjects ({', '.join(changed)})."
                                                 if changed else "no score and no flag."))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = benchmark_parser(__doc__, "fewer subjects (8 at 128 px, 2 at 512 px)", "rewrite the markdown from the JSON")
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--subjects", type=int, nargs=2, default=[32, 8], metavar=("AT_128", "AT_512"))
    ap.add_argument("--janus-subjects", type=int, default=48,
                    help="subjects of a janus-rich dataset at 128 px (seed + 1, 60 %% given a janus) that checks "
                         "the CNN's gate (0: none)")
    ap.add_argument("--keep", help="folder for the datasets, reused when run again (default: a temporary folder)")
    args = ap.parse_args(argv)
    if args.report_only:
        data = json.loads(REPORT.with_suffix(".json").read_text())
        REPORT.with_suffix(".md").write_text(write_markdown(data))
        return 0
    counts = (8, 2) if args.quick else tuple(args.subjects)
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="preflags-speed-"))
    data = {"when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "command": command_line(Path(__file__), argv),
            "machine": machine_info(), "seed": args.seed, "generation_seconds": {}, "runs": {}}
    rate = ProceduralConfig().defect_rate
    roots = {}
    for res, n in zip((128, 512), counts):
        roots[res] = base / f"seed{args.seed}-{n}x{res}"
        print(f"dataset {roots[res]}", flush=True)
        data["generation_seconds"][res] = generate(roots[res], args.seed, rate, n, res, workers=1)
    data["load_before"] = load_average()
    for res, root in roots.items():
        print(f"measuring {res} px ...", flush=True)
        data["runs"][res] = measure_dataset(root)
    data["load_after"] = load_average()
    janus_subjects = min(args.janus_subjects, 8) if args.quick else args.janus_subjects
    if janus_subjects:
        root = base / f"seed{args.seed + 1}-{janus_subjects}x128-janus"
        print(f"checking the CNN's gate on {root} ...", flush=True)
        generate(root, args.seed + 1, JANUS_RATE, janus_subjects, 128, workers=1, defect_types=["janus"])
        data["janus_check"] = dict(measure_dataset(root), seed=args.seed + 1, defect_rate=JANUS_RATE)
    best = data["runs"][512]["subjects_per_cpu_second"]
    data["hours_165k_on_64_cores"] = round(hours_for(PAPER_SUBJECTS, best), 3)
    write_json(REPORT.with_suffix(".json"), data)
    REPORT.with_suffix(".md").write_text(write_markdown(data))
    print(REPORT.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
