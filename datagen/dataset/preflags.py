"""Pre-flags reports, the format the review window, ``label-tool compile`` and the benchmarks share.

``<dataset>/preflags.json``::

    {"format": "panolam-preflags/1", "dataset_index_sha256",
     "detectors": {name: {"threshold", "measure_threshold", "calibrated_cut", "false_alarm_share",
                          "description"}},
     "calibration": {"false_alarm_rate", "null_quantiles", "min_subjects", "null_rounds"},
     "summary": {"subjects", "flagged", "per_detector", "skipped_shards"},
     "timing": {...},
     "subjects": [{"subject", "shard", "score", "flags", "detectors": {name: {"score", "why", "value"?}}}, ...]}

Subjects are sorted worst first; ``score`` is the largest detector score, ``flags`` the detectors
whose score is at least their threshold. ``dataset_index_sha256`` ties the report to the dataset it
scored (the review window and ``label-tool compile`` refuse or hide a report made for another index.json).
``labeling_tool.preflags`` computes the reports.

Each detector's ``threshold`` is the score that flags (0.5); ``measure_threshold`` its own threshold on
what it measures; ``calibrated_cut`` the cut this dataset's calibration set, in units of that
threshold (1: unchanged); ``false_alarm_share`` its part of ``calibration.false_alarm_rate``, the
share of clean subjects the union of detectors may flag (cut 1 and share None when scored
uncalibrated). ``calibration`` names the rule's settings (``labeling_tool/preflags/detector.py``):
the quantiles its null fit spans, the fewest subjects a fit needs and its rounds.

``<dataset>/preflags-queue.json``, written after each report of the dataset, is what the review window's
queue needs from it, small enough to open at once with 165K subjects (the report is ~2 KB a subject)::

    {"format": "panolam-preflags-queue/2", "report": {"bytes", "mtime_ns"}, "dataset_index_sha256",
     "subjects": [[subject, score, rank, "detector:score ..." (its flags, highest first)], ...]}

``report`` is the stat of the ``preflags.json`` it was made from: a queue whose report has changed since
is not used (the report itself is read). The review window and ``label-tool compile`` read it
(:func:`read_queue`), so neither needs the whole report.
"""
from __future__ import annotations

import io
import json
from pathlib import Path

from ..errors import DatasetError
from ..files import atomic_write, read_json

FORMAT = "panolam-preflags/1"
QUEUE_FORMAT = "panolam-preflags-queue/2"
PREFLAGS_NAME = "preflags.json"
QUEUE_NAME = "preflags-queue.json"


def write_preflags(root, report: dict, path=None) -> Path:
    """Write the report to ``path`` (default ``<root>/preflags.json``, then its review queue) atomically."""
    if report.get("format") != FORMAT:
        raise ValueError(f"not a pre-flags report (format {report.get('format')!r})")
    own = path is None
    path = Path(root) / PREFLAGS_NAME if own else Path(path)
    atomic_write(path, lambda f: _dump(report, f))
    if own:
        stat = path.stat()
        queue = {"format": QUEUE_FORMAT, "report": {"bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns},
                 "dataset_index_sha256": report.get("dataset_index_sha256"), "subjects": queue_rows(report)}
        atomic_write(Path(root) / QUEUE_NAME, (json.dumps(queue, separators=(",", ":")) + "\n").encode())
    return path


def _dump(report: dict, f) -> None:
    """``json.dumps(report, indent=1) + "\\n"`` written piece by piece: a 165K-subject report (~320 MB) is never
    held as one string."""
    text = io.TextIOWrapper(f, encoding="utf-8", write_through=False)
    for piece in json.JSONEncoder(indent=1, allow_nan=False).iterencode(report):
        text.write(piece)
    text.write("\n")
    text.flush()
    text.detach()


def queue_rows(report: dict) -> list:
    """[subject, score, rank, flags] per subject of a report: flags as text, "detector:score ...", highest
    first ("" for none; :func:`parse_flags` reads it); rank orders the worst-first queue (the learned rank
    where there is one, else the score). Text rather than pairs: 165K subjects' flags parse 4x faster."""
    return [[r["subject"], r["score"], r.get("rank", r["score"]),
             " ".join(f"{k}:{v!r}" for k, v in sorted(((k, r["detectors"][k]["score"]) for k in r["flags"]),
                                                      key=lambda f: -f[1]))]
            for r in report["subjects"]]


def parse_flags(text: str) -> tuple:
    """((detector, score), ...) of a queue row's flags (:func:`queue_rows`)."""
    return tuple((name, float(score)) for name, _, score in (part.rpartition(":") for part in text.split()))


def _current_queue(root) -> dict | None:
    """The dataset's queue file when it was made from the ``preflags.json`` there now, else None."""
    report_path = Path(root) / PREFLAGS_NAME
    try:
        queue = json.loads((Path(root) / QUEUE_NAME).read_bytes())
        stat = report_path.stat()
        if queue.get("format") == QUEUE_FORMAT and queue.get("report") == {"bytes": stat.st_size,
                                                                            "mtime_ns": stat.st_mtime_ns}:
            return queue
    except (OSError, ValueError, AttributeError):
        pass  # missing, unreadable or not a queue: the report has everything
    return None


def read_queue(root) -> tuple[str | None, list] | None:
    """(the index sha256 the pre-flags of the dataset at ``root`` were made for, the review queue's rows
    (:func:`queue_rows`)): from its queue file when that was made from the ``preflags.json`` there now,
    else from the report; None without a report."""
    if not (Path(root) / PREFLAGS_NAME).exists():
        return None
    queue = _current_queue(root)
    if queue is not None and "dataset_index_sha256" in queue:
        return queue["dataset_index_sha256"], queue["subjects"]
    report = read_preflags(root)
    return report.get("dataset_index_sha256"), queue_rows(report)


def read_preflags(root, path=None) -> dict:
    """Read ``<root>/preflags.json`` (or ``path``); errors name the file."""
    path = Path(path) if path is not None else Path(root) / PREFLAGS_NAME
    if not path.exists():
        raise DatasetError(f"{path}: no pre-flags here (run 'label-tool auto' first)")
    return read_json(path, "pre-flags report", FORMAT)
