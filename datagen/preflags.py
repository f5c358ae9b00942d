"""Pre-flags reports, the format the review window, ``label-tool compile`` and the benchmarks share.

``<dataset>/preflags.json``::

    {"format": "panolam-preflags/1", "dataset_index_sha256",
     "detectors": {name: {"threshold", "measure_threshold", "description"}},
     "summary": {"subjects", "flagged", "per_detector", "skipped_shards"},
     "timing": {...},
     "subjects": [{"subject", "shard", "score", "flags", "detectors": {name: {"score", "why", "value"?}}}, ...]}

Subjects are sorted worst first; ``score`` is the largest detector score, ``flags`` the detectors
whose score is at least their threshold. ``dataset_index_sha256`` ties the report to the dataset it
scored (:func:`is_stale`). ``labeling_tool.preflags`` computes the reports.
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
