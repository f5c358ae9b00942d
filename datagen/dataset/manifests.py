"""Curated manifests, the format every package shares: which subjects of a dataset are accepted.

A manifest is one JSON file (readable with ``json.load`` or ``pandas.json_normalize``)::

    {"header": {"format", "version", "parent_version", "policy", "unreviewed", "test_count",
                "counts", "conflicts", "reviewers", "dataset", "dataset_index_sha256",
                "log_problems", "created"},
     "subjects": [{"subject", "shard", "verdict", "reasons", "reviewers", "votes", "split"}, ...]}

verdict: ``accepted`` / ``rejected``; split: ``train`` / ``test`` for accepted subjects (None for
rejected). Subjects nobody reviewed are accepted (``unreviewed: accept``), rejected (``reject``),
or rejected only when the dataset's pre-flags flag them (``reject-flagged``); ``counts`` says how
many were unreviewed, how many of those were flagged (None without pre-flags) and how many flagged
ones were accepted unreviewed. The test split is the ``test_count`` accepted subjects with the smallest
sha256(subject id): deterministic, and independent of reviewing order. The version is the file's
name without extension; a new review produces a new file (``parent_version`` names the one it
revises); a published manifest is never edited. ``dataset_index_sha256`` ties a manifest to the
dataset it was compiled for. ``label-tool compile`` writes them; training and evaluation read them.
The file holds the header indented and one subject per line (``manifest_bytes``).
"""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import DatasetError, UserError
from ..files import read_json, require
from . import Dataset
from .shards import shard_index

FORMAT = "panolam-manifest/1"
VERDICTS = ("accepted", "rejected")
SPLITS = ("train", "test", None)
_ROW = json.JSONEncoder(sort_keys=True, allow_nan=False).encode  # compact rows need no Python-level encoder


def manifest_bytes(header: dict, subjects: list[dict]) -> bytes:
    """A manifest's canonical bytes (sorted keys): the header indented, then one subject per line, so a
    diff of two versions shows a line per changed subject (and 165K rows encode in about a second)."""
    head = json.dumps(header, sort_keys=True, indent=1, allow_nan=False).replace("\n", "\n ")
    rows = "[\n  " + ",\n  ".join(map(_ROW, subjects)) + "\n ]" if subjects else "[]"
    return ('{\n "header": ' + head + ',\n "subjects": ' + rows + "\n}\n").encode()


def read_manifest(path) -> dict:
    """A manifest, its structure checked; a UserError naming the file and the field otherwise."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such manifest")
    try:
        m = read_json(path, "manifest", FORMAT)
        require(m, "header", dict, path)
        for i, row in enumerate(require(m, "subjects", list, path)):
            where = f"subjects[{i}]"
            if not isinstance(row, dict):
                raise DatasetError(f"{path}: {where} must be an object")
            require(row, "subject", str, path, where)
            require(row, "shard", str, path, where)
            try:
                shard_index(row["shard"])
            except DatasetError as e:
                raise DatasetError(f"{path}: {where}.shard: {e}") from None
            if row.get("verdict") not in VERDICTS:
                raise DatasetError(f"{path}: {where}.verdict must be accepted or rejected, not {row.get('verdict')!r}")
            if row.get("split") not in SPLITS:
                raise DatasetError(f"{path}: {where}.split must be train, test or null, not {row.get('split')!r}")
    except DatasetError as e:
        raise UserError(str(e)) from None
    return m


def check_dataset(manifest: dict, dataset, where="the manifest") -> None:
    """UserError unless ``manifest`` was compiled for ``dataset`` (a :class:`Dataset` or its folder; same
    index.json)."""
    dataset = Dataset.of(dataset)
    if manifest["header"].get("dataset_index_sha256") != dataset.index_sha256:
        raise UserError(f"{where} was compiled for another dataset than {dataset.root} (its index.json differs); "
                        f"compile one for this dataset with 'label-tool compile {dataset.root} ...'")
