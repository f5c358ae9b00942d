"""Scoring a dataset: one pass that measures every subject, then the dataset baselines and the scores.

The parent reads ``index.json`` and the sidecars (each subject's byte range); workers read and decode
the subjects they are given themselves, so no image bytes pass between processes. Every detector
measures each subject once (a small record); baselines and scores are then computed from the
records without decoding again.
"""
from __future__ import annotations

import time
from itertools import groupby

import numpy as np

from datagen.command_line import progress_bar
from datagen.errors import DatasetError
from datagen.dataset.preflags import FORMAT
from datagen.dataset import Dataset
from datagen.dataset.shards import read_sidecar, shard_index, tar_path
from datagen.runner import Placement, run_tasks

from .detector import (FALSE_ALARM_RATE, FLAG_AT, MIN_SUBJECTS, NULL_QUANTILES, NULL_ROUNDS, calibrated_cuts,
                       evidence, recalibrated)
from .learn import learn_from
from .registry import DETECTORS
from .views import SubjectViews

CHUNK_SUBJECTS = 16  # subjects of one shard per task: a few shards still spread over every worker


def _failed(key: str, error: str) -> dict:
    return {"key": key, "error": error}


def measure_subject(views: SubjectViews, detectors=DETECTORS) -> dict:
    """The record of one subject: its key and every detector's measurement."""
    return {"key": views.key, "n_views": views.n, "resolution": views.resolution,
            "protocol": views.meta.get("protocol"), "measured": {d.name: d.measure(views) for d in detectors}}


def measure(task):
    """Worker: (shard, tar, key, start, end, detectors) -> (shard, record); a failure is a record too."""
    shard, tar, key, start, end, detectors = task
    try:
        return shard, measure_subject(SubjectViews.read(tar, key, start, end), detectors)
    except DatasetError as e:
        return shard, _failed(key, str(e))
    except Exception as e:  # a detector crashing on odd input must not stop the whole dataset
        return shard, _failed(key, f"{tar}: subject {key}: measuring failed ({type(e).__name__}: {e})")


def plan(dataset: Dataset, skip_incomplete: bool = False, shards=None) -> tuple[list, list]:
    """(tasks without detectors, names of skipped shards) for every subject of the shards numbered
    ``shards`` (default: all the index lists) of ``dataset``, in index order.

    Each shard must pass :func:`datagen.dataset.shards.check_shards` (sidecar, size, sha256, subjects and byte
    ranges; cached): one that fails is a DatasetError naming it, unless ``skip_incomplete`` (then it
    is listed as skipped).
    """
    root = dataset.root
    listed = [sh for sh in dataset.shards if shards is None or shard_index(sh["name"]) in shards]
    problems = dataset.check_shards([shard_index(sh["name"]) for sh in listed])
    tasks, skipped = [], []
    for shard in listed:
        i = shard_index(shard["name"])
        if i in problems:
            if not skip_incomplete:
                raise DatasetError(f"{problems[i]}; its subjects cannot be scored ('datagen verify {root}' tells "
                                   "more; --skip-incomplete scores the other shards)")
            skipped.append(shard["name"])
            continue
        offsets = read_sidecar(root, i)["offsets"]
        tar = str(tar_path(root, i))
        tasks += [(shard["name"], tar, key, *offsets[key]) for key in shard["subjects"]]
    return tasks, skipped


def _measure_task(detectors, chunk: list, device: str, report) -> list:
    """The runner's task (:mod:`datagen.runner`): the (shard, record) of each planned subject of ``chunk``."""
    records = []
    for t in chunk:
        records.append(measure(t + (detectors,)))
        report(1)
    return records


def extract(dataset, placement: Placement = Placement(), progress: bool = False, detectors=DETECTORS,
            skip_incomplete: bool = False, shards=None) -> dict:
    """First pass: {"index_sha256", "records": [(shard, record), ...] in index order, "skipped_shards",
    "seconds", "tasks"} for the shards numbered ``shards`` (default all) of ``dataset`` (a Dataset or its
    folder), measured where ``placement`` says in tasks of at most ``CHUNK_SUBJECTS`` subjects of one
    shard. Local workers are fresh processes (:func:`datagen.runner.worker_context`), which import the
    calling script as a module: scripts guard their entry point (``if __name__ == "__main__":``)."""
    t0 = time.perf_counter()
    dataset = Dataset.of(dataset)
    tasks, skipped = plan(dataset, skip_incomplete, shards)
    groups = [list(group) for _, group in groupby(tasks, key=lambda t: t[0])]
    chunks = [g[i:i + CHUNK_SUBJECTS] for g in groups for i in range(0, len(g), CHUNK_SUBJECTS)]
    bar = progress_bar(len(tasks), "subj", "preflags", progress)
    measured = [None] * len(chunks)
    try:
        for i, records in run_tasks(_measure_task, detectors, chunks, [len(c) for c in chunks], placement, bar,
                                    lambda chunk: f"measuring {chunk[0][2]}..{chunk[-1][2]}"):
            measured[i] = records
    finally:
        bar.close()
    return {"index_sha256": dataset.index_sha256, "records": [r for records in measured for r in records],
            "skipped_shards": skipped, "seconds": time.perf_counter() - t0, "tasks": len(chunks)}


def frontal_thumbnails(extracted: dict) -> dict:
    """{subject: its frontal thumbnail (the duplicate detector's) or None} of the records ``extracted``."""
    return {r["key"]: (r["measured"].get("duplicate") or {}).get("thumb")
            for _, r in extracted["records"] if "error" not in r}


def thumbnails(thumbs: dict, report: dict) -> list:
    """The thumbnails ``thumbs`` (:func:`frontal_thumbnails`) in the report's order; None where missing."""
    return [thumbs.get(s["subject"]) for s in report["subjects"]]


def score(extracted: dict, detectors=DETECTORS, false_alarm_rate: float | None = FALSE_ALARM_RATE,
          release: bool = False) -> dict:
    """Second step: every detector's baseline from the records, its scores, its cut calibrated on the
    dataset (``detector.calibrated_cuts``: the union flags at most ``false_alarm_rate`` of clean
    subjects; None: each detector at its own threshold), then the report (worst first).
    ``release``: each detector's measurements are dropped from the records once it has scored them (the
    records then hold their keys only; at 165K subjects a gigabyte less at once)."""
    pairs = extracted["records"]
    records = [r for _, r in pairs]
    keys = [r["key"] for r in records]
    ok = ["error" not in r for r in records]
    names = [d.name for d in detectors]
    raw = {}
    for d in detectors:
        base = d.baseline([r["measured"][d.name] if good else None for r, good in zip(records, ok)])
        raw[d.name] = [d.score(r["measured"][d.name], base, idx, keys) if good else None
                       for idx, (r, good) in enumerate(zip(records, ok))]
        if release:
            for r, good in zip(records, ok):
                if good:
                    del r["measured"][d.name]
    cuts, shares = dict.fromkeys(names, 1.0), dict.fromkeys(names)
    if false_alarm_rate:
        def matrix(value, dtype=np.float64):  # (subjects, detectors), no Python number kept per entry
            return np.stack([np.fromiter(map(value, raw[n]), dtype, len(records)) for n in names], axis=1)

        c, t = calibrated_cuts(matrix(lambda f: np.nan if f is None else 0.0 if f.ratio is None else
                                      evidence(f.score, f.ratio)),
                               matrix(lambda f: f is not None and f.score >= FLAG_AT, bool), false_alarm_rate,
                               [d.calibrated for d in detectors],
                               matrix(lambda f: np.inf if f is None else 0.0 if f.ratio is None else f.ratio))
        cuts, shares = dict(zip(names, c.tolist())), dict(zip(names, t.tolist()))
    subjects = []
    for idx, (shard, r) in enumerate(pairs):
        dets = {}
        for d in detectors:
            f, raw[d.name][idx] = raw[d.name][idx], None  # each Flag freed once its entry is made
            if f is None:
                flag = {"score": 1.0, "why": f"does not decode: {r['error']}"} if d.name == "empty" else \
                    {"score": 0.0, "why": "not measured (subject does not decode)"}
            else:
                why = f.why if cuts[d.name] <= 1.0 else f"{f.why}; calibrated cut {cuts[d.name]:.2f}x that threshold"
                flag = {"score": round(float(min(1.0, max(0.0, recalibrated(f, cuts[d.name])))), 4), "why": why}
                if f.value is not None and np.isfinite(f.value):
                    flag["value"] = round(float(f.value), 4)
            dets[d.name] = flag
        top = max(f["score"] for f in dets.values())
        subjects.append({"subject": r["key"], "shard": shard, "score": top,
                         "flags": [n for n in names if dets[n]["score"] >= FLAG_AT], "detectors": dets})
    subjects.sort(key=lambda s: (-s["score"], -len(s["flags"]), s["subject"]))
    n = len(subjects)
    secs = extracted.get("seconds")
    return {
        "format": FORMAT,
        "dataset_index_sha256": extracted["index_sha256"],
        "detectors": {d.name: d.header(cuts[d.name], shares[d.name]) for d in detectors},
        "calibration": {"false_alarm_rate": false_alarm_rate, "null_quantiles": list(NULL_QUANTILES),
                        "min_subjects": MIN_SUBJECTS, "null_rounds": NULL_ROUNDS},
        "summary": {"subjects": n, "flagged": sum(1 for s in subjects if s["flags"]),
                    "per_detector": {name: sum(1 for s in subjects if name in s["flags"]) for name in names},
                    "skipped_shards": list(extracted.get("skipped_shards", []))},
        "timing": {"seconds": round(secs, 3) if secs is not None else None,
                   "subjects_per_second": round(n / secs, 2) if secs else None},
        "subjects": subjects,
    }


def score_dataset(dataset, progress: bool = False, placement: Placement = Placement(), detectors=DETECTORS,
                  skip_incomplete: bool = False, labels=None, false_alarm_rate: float | None = FALSE_ALARM_RATE
                  ) -> dict:
    """Score every subject of ``dataset`` (a Dataset or its folder), measured where ``placement`` says;
    returns the report (subjects sorted worst first).

    ``labels``: a folder of reviewers' event logs; the queue's ``rank`` then learns from their
    verdicts (``learn.py``). ``false_alarm_rate``: as in :func:`score`.
    """
    t0 = time.perf_counter()
    extracted = extract(dataset, placement, progress, detectors, skip_incomplete)
    timing = {"backend": placement.backend, "workers": len(placement.devices), "tasks": extracted["tasks"]}
    return finish(extracted, t0, timing, detectors, labels, false_alarm_rate)


def finish(extracted: dict, t0: float, timing: dict, detectors=DETECTORS, labels=None,
           false_alarm_rate: float | None = FALSE_ALARM_RATE) -> dict:
    """The report from the records ``extracted`` (:func:`score` at ``false_alarm_rate``, then learning
    from ``labels``), its ``timing`` the measuring seconds, the seconds since ``t0`` (perf_counter)
    and ``timing``. The records' measurements are released as they are scored."""
    thumbs = frontal_thumbnails(extracted) if labels is not None else None  # the records are released below
    report = score(extracted, detectors, false_alarm_rate, release=True)
    if labels is not None:
        learn_from(report, labels, thumbnails(thumbs, report))
    total = time.perf_counter() - t0
    n = report["summary"]["subjects"]
    report["timing"] = {"extract_seconds": round(extracted["seconds"], 3), "total_seconds": round(total, 3),
                        "subjects_per_second": round(n / total, 2) if total > 0 else None, **timing}
    return report
