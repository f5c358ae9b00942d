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
scored (:func:`is_stale`). ``labeling_tool.preflags`` computes the reports.

Each detector's ``threshold`` is the score that flags (0.5); ``measure_threshold`` its own threshold on
what it measures; ``calibrated_cut`` the cut this dataset's calibration set, in units of that
threshold (1: unchanged); ``false_alarm_share`` its part of ``calibration.false_alarm_rate``, the
share of clean subjects the union of detectors may flag (cut 1 and share None when scored
uncalibrated). ``calibration`` names the rule's settings (``labeling_tool/preflags/detector.py``):
the quantiles its null fit spans, the fewest subjects a fit needs and its rounds.
"""
from __future__ import annotations

import json
from pathlib import Path

from .errors import DatasetError
from .files import atomic_write, read_json
from .shards import index_sha256

FORMAT = "panolam-preflags/1"
PREFLAGS_NAME = "preflags.json"


def write_preflags(root, report: dict, path=None) -> Path:
    """Write the report to ``path`` (default ``<root>/preflags.json``) atomically."""
    if report.get("format") != FORMAT:
        raise ValueError(f"not a pre-flags report (format {report.get('format')!r})")
    path = Path(path) if path is not None else Path(root) / PREFLAGS_NAME
    return atomic_write(path, (json.dumps(report, indent=1, allow_nan=False) + "\n").encode())


def read_preflags(root, path=None) -> dict:
    """Read ``<root>/preflags.json`` (or ``path``); errors name the file."""
    path = Path(path) if path is not None else Path(root) / PREFLAGS_NAME
    if not path.exists():
        raise DatasetError(f"{path}: no pre-flags here (run 'label-tool auto' first)")
    return read_json(path, "pre-flags report", FORMAT)


def is_stale(root, report: dict) -> bool:
    """True when the dataset's index.json changed since the report was made."""
    return index_sha256(root) != report.get("dataset_index_sha256")
