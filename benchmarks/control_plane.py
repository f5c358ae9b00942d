"""The control plane at the paper's size: indexes, reviewer logs, pre-flag slices and manifests of 165K subjects.

Builds a dataset of ``--subjects`` subjects cheaply and deterministically: ``datagen sample`` renders a
few real subjects at a tiny resolution (the templates), and the project's shard writer writes every
subject of the big dataset from a template's bytes under its own subject id (its metadata names it;
images, depth and hidden truth are the template's). Then, through the project's own APIs: one event log
per reviewer with a verdict for every subject, and the pre-flag slice files of a ``--slices``-way array
job (the templates' measured records under each subject's id). Each operation then runs in a fresh
process (its CPU time from ``os.wait4``, its peak resident set from its own VmHWM), all of them on a copy
of the code taken when the run starts (``freeze_code``):

- ``resume``: one reviewer's log opened for writing (lock, replay of every event);
- ``open``: the review window's session core: the queue from the index (and pre-flags when there are
  any), the reviewer's log, the first unreviewed subject's views decoded and drawn (not the window);
- ``merge``: ``label-tool auto --merge`` (every slice read and checked, the dataset scored, preflags.json);
- ``compile``: ``label-tool compile`` of every reviewer's log, with the shard check cold and cached;
- ``verify``: ``datagen verify``.

Writes ``benchmarks/reports/control_plane.md`` and ``.json`` (``--report`` elsewhere).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
REPORT = REPO / "benchmarks" / "reports" / "control_plane"
BUILD = "build.json"
REVIEWERS = ("ana", "ben", "chen")
RESUMED = REVIEWERS[0]                  # the reviewer whose log is resumed and whose session is opened
WINDOW_SIZE = (1600, 900)               # the off-screen window's size (labeling_tool/review/window.py)
COLUMNS = 8
BAD_IF_DEFECT, BAD_IF_CLEAN = 0.85, 0.03  # a reviewer's chance to say bad to a subject with / without a defect
SKIP_RATE, UNDO_RATE = 0.01, 0.002      # shares of verdicts that are skips, and that are undone and given again
WRITERS = 8                             # shard writers at a time while building (they mostly wait on fsync)
LOG_CHUNK = 10_000                      # events per append (one fsync each)
GOALS = {"resume": 3.0, "open": 3.0, "compile": 30.0}   # CPU seconds of the operation's process
PEAK_RSS_GOAL_MB = 2048.0


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="work folder: the big dataset, logs, slices")
    parser.add_argument("--subjects", type=int, default=165_000, help="subjects of the big dataset (paper: 165K)")
    parser.add_argument("--slices", type=int, default=1000, help="pre-flag array jobs (slice files)")
    parser.add_argument("--shard-size", type=int, default=8, help="subjects per shard (datagen sample's default)")
    parser.add_argument("--views", type=int, default=4, help="views per subject")
    parser.add_argument("--resolution", type=int, default=16, help="image size in pixels")
    parser.add_argument("--templates", type=int, default=16, help="real subjects rendered, whose bytes every "
                        "subject reuses")
    parser.add_argument("--seed", type=int, default=0, help="seed of the templates and of the reviewers' verdicts")
    parser.add_argument("--report", type=Path, default=REPORT, help="report stem (.md and .json are written)")
    parser.add_argument("--only", help="measure again only these operations (comma separated; the report's "
                        "other entries are kept)")
    parser.add_argument("--report-only", action="store_true", help="write the report from the measurements saved "
                        "in its .json, measuring nothing")
    parser.add_argument("--frozen", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


# ------------------------------------------------------------------------------------------------
# Building the big dataset, its reviewers' logs and its pre-flag slices


def paths(out: Path) -> dict[str, Path]:
    return {"template": out / "template", "dataset": out / "dataset", "labels": out / "labels",
            "manifest": out / "manifests" / "control-plane-v1.json"}


def build_settings(args) -> dict:
    """What determines the built files (a build with other settings is made again)."""
    return {"subjects": args.subjects, "slices": args.slices, "shard_size": args.shard_size, "views": args.views,
            "resolution": args.resolution, "seed": args.seed, "templates": args.templates,
            "reviewers": list(REVIEWERS)}


def make_templates(where: Path, args) -> None:
    """A few real subjects, rendered by ``datagen sample`` (a quarter with injected defects)."""
    command = [sys.executable, "-m", "datagen.cli", "sample", "--subjects", str(args.templates),
               "--resolution", str(args.resolution), "--views", str(args.views), "--shard-size",
               str(args.templates), "--defect-rate", "0.25", "--seed", str(args.seed), "--out", str(where), "--quiet"]
    subprocess.run(command, check=True, cwd=REPO)


def templates_match(where: Path, args) -> bool:
    """Whether ``where`` holds complete templates made with ``args``' settings."""
    from datagen.errors import DatasetError
    from datagen.dataset.shards import is_complete, read_index

    try:
        s = read_index(where)["settings"]
    except DatasetError:
        return False
    made = (s.get("subjects"), s.get("views"), s.get("resolution"), s.get("seed"))
    return made == (args.templates, args.views, args.resolution, args.seed) and is_complete(where, 0)


def read_templates(where: Path) -> tuple[dict, list]:
    """The template dataset's index and its subjects as (fields {field: bytes} in tar order, truth)."""
    from datagen.dataset.shards import iter_tar_samples, read_index, tar_path

    index = read_index(where)
    truth = json.loads((where / "truth" / "shard-000000.json").read_text())
    return index, [(fields, truth[key]) for key, fields in iter_tar_samples(tar_path(where, 0))]


def write_dataset(root: Path, template_index: dict, templates: list, subjects: int, shard_size: int) -> dict:
    """The big dataset: its index (the templates' settings, ``subjects`` subjects) and every shard, subject
    i from template i mod the template count; returns the index."""
    from datagen.pipeline import JobSpec, make_index, prepare_output

    settings = dict(template_index["settings"], subjects=subjects, shard_size=shard_size)
    spec = JobSpec(out=str(root), **settings)
    index = make_index(spec, template_index["generator"])
    prepare_output(spec, index)
    with ThreadPoolExecutor(WRITERS) as pool:  # each shard's writer waits on its fsyncs, not on the others'
        list(pool.map(lambda s: write_shard(root, s, spec.shard_subjects(s), templates, spec.views),
                      range(spec.num_shard_files)))
    return index


def write_shard(root: Path, shard: int, subjects: range, templates: list, views: int) -> None:
    """Shard ``shard`` of the big dataset through :class:`datagen.dataset.shards.ShardWriter`: subject i is template
    i mod the template count, its metadata naming it (the bytes ``dumps`` gives that metadata)."""
    from datagen.dataset.shards import ShardWriter, subject_id

    writer = ShardWriter(root, shard)
    for i in subjects:
        fields, truth = templates[i % len(templates)]
        key = subject_id(i)
        members = [(f"{key}.{name}", renamed_metadata(data, key, i) if name == "json" else data)
                   for name, data in fields.items()]
        writer.add_subject(key, members, truth)
    writer.commit({"views_per_subject": views})


def renamed_metadata(data: bytes, key: str, index: int) -> bytes:
    """A subject's canonical metadata bytes (:func:`datagen.dataset.shards.dumps`) with its ``subject_id`` and
    ``subject_index`` set to ``key`` and ``index``: the same bytes ``dumps`` gives the changed metadata,
    without its (slow, indented) encoding."""
    meta = json.loads(data)
    for field, value in (("subject_id", key), ("subject_index", index)):
        old = f'\n "{field}": {json.dumps(meta[field])},\n'.encode()
        if data.count(old) != 1:
            raise ValueError(f"{field} is not a top-level field of this metadata")
        data = data.replace(old, f'\n "{field}": {json.dumps(value)},\n'.encode())
    return data


def reviewer_plan(reviewer: int, subjects: list[str], defective: np.ndarray, seed: int) -> list[tuple]:
    """One reviewer's events in order, (subject, action, reasons): a verdict for every subject (bad
    with a reason drawn from the review reasons, skip, or good), some of them undone and given again."""
    from datagen.dataset.events import REASONS

    rng = np.random.default_rng([seed, reviewer])
    draws = rng.random((len(subjects), 3))
    events = []
    for subject, bad_if, (u_bad, u_skip, u_undo), reason in zip(
            subjects, np.where(defective, BAD_IF_DEFECT, BAD_IF_CLEAN), draws,
            rng.integers(0, len(REASONS), len(subjects))):
        verdict = ("bad", (REASONS[reason],)) if u_bad < bad_if else ("skip", ()) if u_skip < SKIP_RATE else ("good", ())
        if u_undo < UNDO_RATE:  # a slip, taken back at once
            slip = ("good", ()) if verdict[0] != "good" else ("bad", (REASONS[reason],))
            events += [(subject, *slip), (subject, "undo", ())]
        events.append((subject, *verdict))
    return events


def effective_decisions(events: list[tuple]) -> dict[str, tuple]:
    """{subject: (good|bad, reasons)} that a plan of :func:`reviewer_plan` leaves (its undos follow their slips)."""
    final = {}
    for subject, action, reasons in events:
        if action == "undo":
            final.pop(subject)
        else:
            final[subject] = (action, reasons)
    return {s: v for s, v in final.items() if v[0] in ("good", "bad")}


def subject_list(index: dict) -> list[tuple[str, str]]:
    """(subject, shard name) of every subject, in index order."""
    return [(s, sh["name"]) for sh in index["shards"] for s in sh["subjects"]]


def defective_subjects(root: Path, index: dict) -> np.ndarray:
    """Whether each subject (index order) has an injected defect, from the dataset's hidden truth."""
    flags = []
    for sh in index["shards"]:
        truth = json.loads((root / "truth" / f"{sh['name']}.json").read_text())
        flags += [bool(truth[s]["defects"]) for s in sh["subjects"]]
    return np.array(flags)


def plans(root: Path, index: dict, seed: int) -> dict[str, list[tuple]]:
    """Every reviewer's plan of events (:func:`reviewer_plan`) over the dataset at ``root``."""
    subjects = [s for s, _ in subject_list(index)]
    defective = defective_subjects(root, index)
    return {name: reviewer_plan(r, subjects, defective, seed) for r, name in enumerate(REVIEWERS)}


def write_logs(labels: Path, index: dict, reviewer_plans: dict) -> None:
    """Each reviewer's plan through :class:`datagen.dataset.events.EventLog`, ``LOG_CHUNK`` events per append."""
    from datagen.dataset.events import EventLog

    shard_of = dict(subject_list(index))
    for name, events in reviewer_plans.items():
        log = EventLog(labels, name)
        try:
            for start in range(0, len(events), LOG_CHUNK):
                log.append_all([(s, shard_of[s], action, reasons) for s, action, reasons in
                                events[start:start + LOG_CHUNK]])
        finally:
            log.close()


def write_slices(root: Path, template_records: dict, n: int) -> None:
    """The ``n`` slice files of an array job over the dataset, each subject's record its template's
    (subject i: template i mod the template count) under its id, through ``slices.write_slice``.
    ``template_records``: :func:`labeling_tool.preflags.scoring.extract` of the templates."""
    from datagen.dataset import Dataset
    from labeling_tool.preflags.slices import slice_shards, write_slice

    dataset = Dataset(root)
    position = {s: i for i, (s, _) in enumerate(subject_list(dataset.index))}
    by_number = dict(zip(dataset.shard_numbers, dataset.shards))
    seconds_each = template_records["seconds"] / len(template_records["records"])
    records = [r for _, r in template_records["records"]]
    for k in range(n):
        mine = [(sh["name"], dict(records[position[s] % len(records)], key=s))
                for i in slice_shards(dataset, k, n) for sh in [by_number[i]] for s in sh["subjects"]]
        write_slice(dataset, k, n, {"index_sha256": dataset.index_sha256, "records": mine, "skipped_shards": [],
                                    "seconds": seconds_each * len(mine)})


def build(args, slices: bool = True) -> dict:
    """Make (or reuse, when built with the same settings) the templates, the dataset, the logs and
    the slices under ``args.out``; returns what the build recorded. With ``slices``, slices of other
    pre-flags code than the current (which a merge refuses) are written again (the last is written last)."""
    import shutil

    from labeling_tool.preflags.slices import detectors_sha256, slice_path, slices_folder

    out, where = args.out, paths(args.out)
    stamp = out / BUILD
    settings = build_settings(args)
    record = json.loads(stamp.read_text()) if stamp.exists() else {}
    if record.get("settings") != settings:
        for p in (stamp, where["dataset"], where["labels"], out / "manifests"):
            if p.is_dir():
                shutil.rmtree(p)
            p.unlink(missing_ok=True)
        t0 = time.perf_counter()
        if not templates_match(where["template"], args):
            shutil.rmtree(where["template"], ignore_errors=True)
            make_templates(where["template"], args)
        template_index, templates = read_templates(where["template"])
        seconds = {"templates": time.perf_counter() - t0}
        t0 = time.perf_counter()
        index = write_dataset(where["dataset"], template_index, templates, args.subjects, args.shard_size)
        seconds["dataset"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        reviewer_plans = plans(where["dataset"], index, args.seed)
        write_logs(where["labels"], index, reviewer_plans)
        seconds["logs"] = time.perf_counter() - t0
        record = {"settings": settings, "seconds": seconds, "shards": len(index["shards"]),
                  "events": {name: len(events) for name, events in reviewer_plans.items()},
                  "bytes": {name: folder_bytes(where[name]) for name in ("dataset", "labels")}}
    last = slice_path(slices_folder(where["dataset"]), args.slices - 1, args.slices)
    if not last.exists() or (slices and json.loads(last.read_text())["detectors_sha256"] != detectors_sha256()):
        from labeling_tool.preflags.scoring import extract

        t0 = time.perf_counter()
        write_slices(where["dataset"], extract(where["template"]), args.slices)
        record["seconds"]["slices"] = time.perf_counter() - t0
        record["bytes"]["slices"] = folder_bytes(slices_folder(where["dataset"]))
        stamp.write_text(json.dumps(record, indent=1) + "\n")
    return record


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


# ------------------------------------------------------------------------------------------------
# The operations, each run in a fresh process


def op_resume(where: dict) -> dict:
    from datagen.dataset.events import EventLog

    log = EventLog(where["labels"], RESUMED)
    result = {"events": len(log.events), "verdicts": len(log.verdicts()), "problems": len(log.problems)}
    log.close()
    return result


def op_open(where: dict) -> dict:
    from labeling_tool.cli import build_queue
    from labeling_tool.review.layout import review_frame
    from labeling_tool.review.reader import SubjectReader
    from labeling_tool.review.session import ReviewSession

    _, queue = build_queue(str(where["dataset"]), "all")
    session = ReviewSession(queue, RESUMED, where["labels"])
    frame = review_frame(SubjectReader(where["dataset"]), session.item, WINDOW_SIZE, COLUMNS)
    result = {"queue": len(queue), "position": session.pos, "subject": session.item.subject, "reviewed": session.done,
              "views_drawn": len(frame.views), "error": frame.error}
    session.close()
    return result


def op_merge(where: dict) -> dict:
    from datagen.dataset.preflags import write_preflags
    from labeling_tool.preflags.slices import merge_slices

    report = merge_slices(where["dataset"])
    path = write_preflags(where["dataset"], report)
    return {"subjects": report["summary"]["subjects"], "flagged": report["summary"]["flagged"],
            "slices": report["timing"]["slices"], "preflags_bytes": path.stat().st_size}


def op_compile(where: dict, cold: bool) -> dict:
    from datagen.dataset.shards import SHARD_CHECKS
    from labeling_tool.cli import main

    if cold:
        (where["dataset"] / SHARD_CHECKS).unlink(missing_ok=True)
    where["manifest"].unlink(missing_ok=True)
    code = main(["compile", str(where["dataset"]), "--labels", str(where["labels"]), "--out", str(where["manifest"])])
    counts = json.loads(where["manifest"].read_text())["header"]["counts"]
    return {"exit": code, "subjects": counts["subjects"], "reviewed": counts["reviewed"],
            "rejected": counts["rejected"], "conflicts": counts["conflicts"],
            "manifest_bytes": where["manifest"].stat().st_size}


def op_verify(where: dict) -> dict:
    from datagen.verify import verify_dataset

    report = verify_dataset(where["dataset"])
    return {"shards": report["shards"], "complete": report["complete"], "subjects": report["subjects"],
            "problems": len(report["problems"]), "first_problem": (report["problems"] or [None])[0]}


OPERATIONS = {
    "resume": ("resume one reviewer's log (EventLog: lock, replay)", op_resume),
    "open": ("review session open + first subject drawn", op_open),
    "merge": ("merge the pre-flag slices, score, write preflags.json", op_merge),
    "open_preflagged": ("review session open + first subject drawn, with preflags.json", op_open),
    "compile_cold": ("label-tool compile, shard check cold", lambda where: op_compile(where, cold=True)),
    "compile": ("label-tool compile, shard check cached", lambda where: op_compile(where, cold=False)),
    "verify": ("datagen verify", op_verify),
}
GOAL_OF = {"resume": "resume", "open": "open", "open_preflagged": "open", "compile_cold": "compile",
           "compile": "compile"}


def child(name: str, out: Path, result: Path) -> None:
    """Run operation ``name`` in this process and write its result (and its own clock readings) to ``result``."""
    wall, cpu = time.perf_counter(), time.process_time()
    value = OPERATIONS[name][1](paths(out))
    value.update(seconds=time.perf_counter() - wall, operation_cpu_seconds=time.process_time() - cpu,
                 peak_rss_mb=peak_rss_mb())
    result.write_text(json.dumps(value) + "\n")


def peak_rss_mb() -> float:
    """This process's peak resident set (VmHWM, MiB). Not ``ru_maxrss``: on Linux a process's
    ``ru_maxrss`` (and ``os.wait4``'s) keeps the peak of the image it replaced at exec, here the parent's."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("/proc/self/status has no VmHWM: peak memory cannot be read on this platform")


def measure(name: str, out: Path) -> dict:
    """Run operation ``name`` in a fresh process: its result, wall and CPU seconds, peak resident set (MiB)."""
    result = out / "results" / f"{name}.json"
    result.parent.mkdir(parents=True, exist_ok=True)
    result.unlink(missing_ok=True)
    command = [sys.executable, "-m", "benchmarks.control_plane", "--out", str(out), "--child", name,
               "--result", str(result)]
    with open(result.with_suffix(".log"), "wb") as printed:
        start = time.perf_counter()
        proc = subprocess.Popen(command, cwd=REPO, stdout=printed, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"operation {name} failed (exit {proc.returncode}); see {result.with_suffix('.log')}")
    return {"what": OPERATIONS[name][0], "process_seconds": wall, "cpu_seconds": usage.ru_utime + usage.ru_stime,
            "load_average_after": list(os.getloadavg()), **json.loads(result.read_text())}


# ------------------------------------------------------------------------------------------------
# The report


def goal_text(name: str) -> str:
    goal = GOALS.get(GOAL_OF.get(name, ""))
    return (f"{goal:.0f} CPU s, " if goal else "") + f"{PEAK_RSS_GOAL_MB / 1024:.0f} GB"


def meets(name: str, row: dict) -> bool:
    """Whether the operation met its goals: CPU seconds (wall time on a shared machine says more about
    the other work than about this) and peak resident set."""
    goal = GOALS.get(GOAL_OF.get(name, ""))
    return row["peak_rss_mb"] < PEAK_RSS_GOAL_MB and (goal is None or row["cpu_seconds"] <= goal)


def render(results: dict) -> str:
    from benchmarks.common import bullets, reproduce, table

    b, s = results["build"], results["build"]["settings"]
    rows = [[name, row["what"], f"{row['cpu_seconds']:.2f}", f"{row['process_seconds']:.2f}", f"{row['seconds']:.2f}",
             f"{row['peak_rss_mb']:.0f}", goal_text(name), "yes" if meets(name, row) else "**no**"]
            for name, row in results["operations"].items()]
    m, ops = results["machine"], results["operations"]
    missing = [name for name in OPERATIONS if name not in ops]
    lines = [
        f"# The control plane at {s['subjects']:,} subjects",
        "",
        f"A dataset of {s['subjects']:,} subjects in {b['shards']:,} shards of {s['shard_size']} ({s['views']} views "
        f"of {s['resolution']} px each; {b['bytes']['dataset'] / 2 ** 30:.2f} GiB), "
        f"{len(s['reviewers'])} reviewers' logs of {min(b['events'].values()):,} to {max(b['events'].values()):,} "
        f"events ({b['bytes']['labels'] / 2 ** 20:.0f} MiB), {s['slices']:,} pre-flag slice files "
        f"({b['bytes']['slices'] / 2 ** 20:.0f} MiB). Each operation ran in a fresh process: *process* is its wall "
        "time from start to exit (interpreter start included), *operation* the child's own clock around the "
        "operation (its imports included), CPU the process's user + system seconds (`os.wait4`), peak RSS its "
        "maximum resident set (VmHWM).",
        "",
        *table(["operation", "what", "CPU s", "process wall s", "operation wall s", "peak RSS MiB", "goal", "met"],
               rows),
        *([f"Not measured: {', '.join(missing)}."] if missing else []),
        "",
        *([f"preflags.json (read by the session's queue and by compile): {ops['merge']['preflags_bytes'] / 2 ** 20:.0f} "
           "MiB."] if "merge" in ops else []),
        *([f"The manifest: {ops['compile']['manifest_bytes'] / 2 ** 20:.0f} MiB."] if "compile" in ops else []),
        "",
        *(["Notes on this run:", "", *bullets(results["notes"]), ""] if results.get("notes") else []),
        "Results, checked by the run:",
        "",
        *bullets(results["checks"]),
        "",
        f"Build: templates {b['seconds']['templates']:.0f} s, dataset {b['seconds']['dataset']:.0f} s, logs "
        f"{b['seconds']['logs']:.0f} s, slices {b['seconds']['slices']:.0f} s.",
        "",
        f"Machine: {m['cpu_model']}, {m['usable_cpus']} usable CPUs; load average "
        f"{', '.join(f'{v:.2f}' for v in results['load_average_before'])} (1, 5, 15 min) before the run, "
        + "; ".join(f"{v['load_average_after'][0]:.2f} after {k}" for k, v in results["operations"].items())
        + f". Git revision {m['git_revision']}, {m['date']}.",
        "",
        *reproduce(results["command"]),
        *([f"Operations measured again afterwards: {'; '.join(f'`{c}`' for c in results['remeasured'])}."]
          if results.get("remeasured") else []),
    ]
    return "\n".join(lines) + "\n"


def checks(results: dict, out: Path) -> list[str]:
    """What the operations' results must be, from the build's own plans; each line says what agreed.
    A RuntimeError names the first that does not."""
    from datagen.dataset.shards import read_index

    where = paths(out)
    index = read_index(where["dataset"])
    n = len(subject_list(index))
    reviewer_plans = plans(where["dataset"], index, results["build"]["settings"]["seed"])
    ops = results["operations"]
    decided = {name: effective_decisions(events) for name, events in reviewer_plans.items()}
    expected = []
    if "resume" in ops:
        expected.append((ops["resume"]["events"] == len(reviewer_plans[RESUMED]) and ops["resume"]["problems"] == 0,
                         f"resume replayed all {len(reviewer_plans[RESUMED]):,} events of {RESUMED}'s log, no problems"))
    for name in ("open", "open_preflagged"):
        if name in ops:
            row = ops[name]
            expected.append((row["queue"] == n and row["reviewed"] == len(decided[RESUMED]) and row["error"] is None
                             and row["views_drawn"] == results["build"]["settings"]["views"],
                             f"{name}: a queue of {n:,}, {len(decided[RESUMED]):,} reviewed, first unreviewed subject "
                             f"{row['subject']} drawn"))
    if "merge" in ops:
        expected.append((ops["merge"]["subjects"] == n and ops["merge"]["slices"] == results["build"]["settings"]["slices"],
                         f"merge scored all {n:,} subjects from {ops['merge']['slices']:,} slices"))
    compiled = [name for name in ("compile_cold", "compile") if name in ops]
    if compiled:
        manifest = json.loads(where["manifest"].read_text())
        votes_ok = all(row["votes"] == {r: decided[r][row["subject"]][0] for r in REVIEWERS if row["subject"] in
                                        decided[r]} for row in manifest["subjects"])
        expected.append((all(ops[k]["subjects"] == n and ops[k]["exit"] == 0 for k in compiled) and votes_ok
                         and len(manifest["subjects"]) == n,
                         f"the manifest holds all {n:,} subjects, each with the votes the reviewers' plans leave"))
    if "verify" in ops:
        expected.append((ops["verify"]["problems"] == 0 and ops["verify"]["subjects"] == n,
                         f"verify: {ops['verify']['complete']:,} of {ops['verify']['shards']:,} shards complete, "
                         "no problem"))
    for ok, line in expected:
        if not ok:
            raise RuntimeError(f"control plane check failed: {line}")
    return [line for _, line in expected]


def freeze_code(out: Path) -> Path:
    """A copy of the project's packages (and this script) in ``out/code``, which the run then uses
    throughout: pre-flag slices name the code that measured them, and a merge refuses them when the
    pre-flags code changed since, as it may in a working tree while a long run goes on. The working
    tree's git revision is kept beside it (REVISION)."""
    import shutil

    from datagen.pipeline import software_info

    code = out.resolve() / "code" / str(os.getpid())  # a run's own: another run may still be using its copy
    for package in ("datagen", "labeling_tool"):
        shutil.copytree(REPO / package, code / package, ignore=shutil.ignore_patterns("__pycache__"))
    (code / "benchmarks").mkdir()
    for name in ("__init__.py", "common.py", "control_plane.py"):
        shutil.copy2(REPO / "benchmarks" / name, code / "benchmarks" / name)
    (code / "REVISION").write_text(software_info()["git_revision"] + "\n")
    return code


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.child:
        child(args.child, args.out, args.result)
        return
    argv = list(argv if argv is not None else sys.argv[1:])
    small = [name for name in ("subjects", "slices", "shard_size", "views", "templates") if getattr(args, name) < 1]
    if small:
        sys.exit(f"--{small[0].replace('_', '-')} must be at least 1")
    if args.resolution < 16:
        sys.exit("--resolution must be at least 16 (datagen sample's smallest)")
    if args.report_only and not args.report.with_suffix(".json").exists():
        sys.exit(f"{args.report.with_suffix('.json')}: no saved measurements to report (run without --report-only)")
    if not args.frozen and not args.report_only:
        code = freeze_code(args.out)
        os.chdir(code)
        os.execv(sys.executable, [sys.executable, "-m", "benchmarks.control_plane", *argv, "--out",
                                  str(args.out.resolve()), "--report", str(args.report.resolve()), "--frozen"])
    from benchmarks.common import machine_info, write_json, write_report

    if args.report_only:
        results = json.loads(args.report.with_suffix(".json").read_text())
        write_report(args.report, results, render(results))
        return

    only = args.only.split(",") if args.only else list(OPERATIONS)
    unknown = sorted(set(only) - set(OPERATIONS))
    if unknown:
        sys.exit(f"--only: unknown operation {unknown[0]}; choose from {', '.join(OPERATIONS)}")
    saved = args.report.with_suffix(".json")
    results = json.loads(saved.read_text()) if args.only and saved.exists() else {"operations": {}}
    command = " ".join(["python -m benchmarks.control_plane", *argv[:-5]])  # as given, before freeze_code's additions
    if "command" in results:  # a report measured before: these operations are measured again
        results.setdefault("remeasured", []).append(command)
    else:
        results["command"] = command
    results.update(load_average_before=list(os.getloadavg()), build=build(args, slices="merge" in only))
    failed = []
    for name in only:
        print(f"{name} ...", flush=True)
        try:
            results["operations"][name] = measure(name, args.out)
        except RuntimeError as e:  # the others are still measured; --only measures this one again
            print(e, file=sys.stderr)
            results["operations"].pop(name, None)
            failed.append(name)
    results["operations"] = {name: results["operations"][name] for name in OPERATIONS if name in results["operations"]}
    write_json(saved, results)  # kept should a check fail
    results["checks"] = checks(results, args.out)
    results["machine"] = dict(machine_info(), git_revision=(REPO / "REVISION").read_text().strip())  # the tree's
    write_report(args.report, results, render(results))
    if failed:
        sys.exit(f"{', '.join(failed)} failed (see {args.out / 'results'}); measure again with --only")


if __name__ == "__main__":
    main()
