"""Pre-flags at scale: array jobs measure slices of the shards, one merge scores the whole dataset.

``label-tool auto DIR --shard-index K --num-shards N`` measures the subjects of the shards s with
s % N == K (the rule of ``datagen sample``'s array jobs, :func:`datagen.dataset.shards.job_shards`) and writes
their records to ``<folder>/slice-K-of-N.json`` (folder: ``DIR/preflags-slices`` or ``--out``),
atomically. ``label-tool auto DIR --merge`` reads the N slices and scores the dataset: the
report equals a one-process run's apart from its ``timing``. A slice file::

    {"format": "panolam-preflags-slice/1", "dataset_index_sha256", "detectors_sha256",
     "slice": [K, N], "shards": [measured shard names], "skipped_shards": [...], "seconds",
     "records": [[shard name, record], ...]}

``detectors_sha256`` covers every detector's settings and the pre-flags code, so a merge refuses
slices measured by other settings or another version; ``dataset_index_sha256`` refuses slices of
an index.json that changed since. Records keep their exact values and types (numbers as
``float.hex``, arrays as dtype, shape and base64 bytes, dicts with other keys than strings
as pairs), so scoring them gives the same report.
"""
from __future__ import annotations

import base64
import hashlib
import json
import re
import time
from pathlib import Path

import numpy as np

from datagen.errors import DatasetError, UserError
from datagen.files import atomic_write, read_json
from datagen.dataset import Dataset
from datagen.dataset.shards import job_shards
from datagen.runner import Placement

from .detector import FALSE_ALARM_RATE
from .scoring import extract, finish
from .registry import DETECTORS

SLICE_FORMAT = "panolam-preflags-slice/1"
SLICES_DIR = "preflags-slices"
_SLICE_NAME = re.compile(r"slice-(\d+)-of-(\d+)\.json")


def slice_path(folder, k: int, n: int) -> Path:
    return Path(folder) / f"slice-{k:05d}-of-{n:05d}.json"


def slices_folder(root, out=None) -> Path:
    """Where the slice files of the dataset at ``root`` go: ``out``, else ``root/preflags-slices``."""
    return Path(out) if out is not None else Path(root) / SLICES_DIR


def detectors_sha256(detectors=DETECTORS) -> str:
    """sha256 over the detectors' names and settings and the source of the pre-flags package."""
    h = hashlib.sha256()
    for d in detectors:
        h.update(f"{d.name}\0{d.settings!r}\0".encode())
    for path in sorted(Path(__file__).parent.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def encode(value):
    """A record as JSON values that :func:`decode` turns back into equal values of the same types."""
    if value is None or isinstance(value, (bool, str)) or type(value) is int:
        return value
    if type(value) is float:
        return {"f": value.hex()}
    if isinstance(value, np.ndarray):
        data = np.ascontiguousarray(value)
        return {"a": data.dtype.str, "s": list(data.shape), "b": base64.b64encode(data.tobytes()).decode()}
    if isinstance(value, np.generic):
        return {"n": value.dtype.str, "b": base64.b64encode(value.tobytes()).decode()}
    if isinstance(value, (list, tuple)):
        return {"l" if isinstance(value, list) else "t": [encode(v) for v in value]}
    if isinstance(value, dict):
        if all(type(k) is str for k in value):
            return {"d": {k: encode(v) for k, v in value.items()}}
        return {"m": [[encode(k), encode(v)] for k, v in value.items()]}
    raise TypeError(f"a pre-flags record holds a {type(value).__name__}, which slices cannot store")


def decode(value):
    """Inverse of :func:`encode`."""
    if not isinstance(value, dict):
        return value
    if "f" in value:
        return float.fromhex(value["f"])
    if "a" in value:
        return np.frombuffer(base64.b64decode(value["b"]), dtype=np.dtype(value["a"])).reshape(value["s"]).copy()
    if "n" in value:
        return np.frombuffer(base64.b64decode(value["b"]), dtype=np.dtype(value["n"]))[0]
    if "l" in value:
        return [decode(v) for v in value["l"]]
    if "t" in value:
        return tuple(decode(v) for v in value["t"])
    if "m" in value:
        return {decode(k): decode(v) for k, v in value["m"]}
    return {k: decode(v) for k, v in value["d"].items()}


def slice_shards(dataset: Dataset, k: int, n: int) -> list[int]:
    """The shard numbers of slice ``k`` of ``n`` among those the dataset index lists."""
    listed = dataset.shard_numbers
    mine = set(job_shards(max(listed, default=-1) + 1, k, n))
    return [i for i in listed if i in mine]


def write_slice(dataset: Dataset, k: int, n: int, extracted: dict, out=None, detectors=DETECTORS) -> Path:
    """Write the records ``extracted`` (:func:`scoring.extract` of slice ``k`` of ``n``) atomically."""
    skipped = list(extracted["skipped_shards"])
    names = dict(zip(dataset.shard_numbers, (sh["name"] for sh in dataset.shards)))
    measured = [names[i] for i in slice_shards(dataset, k, n) if names[i] not in skipped]
    doc = {"format": SLICE_FORMAT, "dataset_index_sha256": extracted["index_sha256"],
           "detectors_sha256": detectors_sha256(detectors), "slice": [k, n],
           "shards": measured, "skipped_shards": skipped, "seconds": extracted["seconds"],
           "records": [[shard, encode(r)] for shard, r in extracted["records"]]}
    path = slice_path(slices_folder(dataset.root, out), k, n)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, (json.dumps(doc, separators=(",", ":"), allow_nan=False) + "\n").encode())


def read_slices(dataset: Dataset, out=None, detectors=DETECTORS) -> dict:
    """The records of every slice in the folder, as :func:`scoring.extract` returns them for the
    whole dataset (index order; ``seconds``: the slices' measuring time added up). A UserError or
    DatasetError in one line when a slice is missing, stale, from other detector settings, or the
    folder holds slices of two splits."""
    root = dataset.root
    folder = slices_folder(root, out)
    found = {}
    for p in sorted(folder.glob("slice-*-of-*.json")) if folder.is_dir() else []:
        m = _SLICE_NAME.fullmatch(p.name)
        if m:
            found[int(m[1]), int(m[2])] = p
    if not found:
        raise UserError(f"{folder}: no slices to merge; measure them first with 'label-tool auto {root} "
                        "--shard-index K --num-shards N' for every K")
    splits = sorted({n for _, n in found})
    if len(splits) > 1:
        raise UserError(f"{folder}: holds slices of {' and of '.join(map(str, splits))} jobs; remove the "
                        "stale ones")
    n = splits[0]
    missing = [k for k in range(n) if (k, n) not in found]
    if missing:
        raise UserError(f"{slice_path(folder, missing[0], n)}: missing ({len(missing)} of the {n} slices are not "
                        f"measured yet); run 'label-tool auto {root} --shard-index {missing[0]} --num-shards {n}'")
    index_sha, det_sha = dataset.index_sha256, detectors_sha256(detectors)
    shards = dataset.shards
    names = dict(zip(dataset.shard_numbers, (sh["name"] for sh in shards)))
    subjects = {sh["name"]: sh["subjects"] for sh in shards}
    by_shard, skipped, seconds = {}, set(), 0.0
    for k in range(n):
        path = found[k, n]
        doc = read_json(path, "pre-flags slice", SLICE_FORMAT)
        rerun = f"run 'label-tool auto {root} --shard-index {k} --num-shards {n}' again"
        if doc.get("dataset_index_sha256") != index_sha:
            raise UserError(f"{path}: stale, measured for another index.json of {root}; {rerun}")
        if doc.get("detectors_sha256") != det_sha:
            raise UserError(f"{path}: measured with other detector settings or pre-flags code; {rerun}")
        try:
            held = set(doc["shards"]) | set(doc["skipped_shards"])
            if doc["slice"] != [k, n] or held != {names[i] for i in slice_shards(dataset, k, n)}:
                raise DatasetError(f"{path}: does not hold the shards of slice {k} of {n}; {rerun}")
            skipped.update(doc["skipped_shards"])
            seconds += float(doc["seconds"])
            pairs = [(shard, decode(record)) for shard, record in doc["records"]]
            for name in doc["shards"]:
                mine = [r["key"] for shard, r in pairs if shard == name]
                if mine != subjects[name]:
                    raise DatasetError(f"{path}: holds records of {len(mine)} subjects of {name}, which has "
                                       f"{len(subjects[name])} in the dataset index; {rerun}")
            if {shard for shard, _ in pairs} - set(doc["shards"]):
                raise DatasetError(f"{path}: holds records of shards it did not measure; {rerun}")
            for shard, record in pairs:
                by_shard.setdefault(shard, []).append((shard, record))
        except (KeyError, TypeError, ValueError) as e:
            raise DatasetError(f"{path}: not a readable pre-flags slice ({type(e).__name__}: {e}); {rerun}") from None
    order = [sh["name"] for sh in shards]
    records = [pair for name in order for pair in by_shard.get(name, [])]
    return {"index_sha256": index_sha, "records": records, "skipped_shards": [s for s in order if s in skipped],
            "seconds": seconds, "slices": n}


def measure_slice(dataset, k: int, n: int, out=None, placement: Placement = Placement(), progress: bool = False,
                  detectors=DETECTORS, skip_incomplete: bool = False) -> tuple[Path, dict]:
    """Measure slice ``k`` of ``n`` of ``dataset`` (a Dataset or its folder) where ``placement`` says and
    write it; returns (its path, the extract)."""
    dataset = Dataset.of(dataset)
    extracted = extract(dataset, placement, progress, detectors, skip_incomplete, shards=slice_shards(dataset, k, n))
    return write_slice(dataset, k, n, extracted, out, detectors), extracted


def merge_slices(dataset, out=None, detectors=DETECTORS, labels=None, false_alarm_rate: float | None = FALSE_ALARM_RATE
                 ) -> dict:
    """The report of the whole dataset from its slices (see :func:`read_slices`); ``labels`` and
    ``false_alarm_rate`` as in :func:`scoring.score_dataset`. Its ``timing`` counts the slices' measuring seconds added up
    and the merge's own."""
    t0 = time.perf_counter()
    extracted = read_slices(Dataset.of(dataset), out, detectors)
    return finish(extracted, t0 - extracted["seconds"], {"slices": extracted["slices"]}, detectors, labels,
                  false_alarm_rate)
