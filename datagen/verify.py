"""``datagen verify``: checksums, decoding of every image and stored shape, counts and the metadata schema."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from .command_line import progress_bar, setting
from .errors import DatasetError
from .files import sha256_file
from .runner import ArrayJobOptions, Placement, run_tasks
from .shapes import check_mesh
from .dataset import Dataset
from .dataset.shards import (SHAPE_FIELD, TRUTH_DIR, decode_sample, iter_tar_samples, read_range,
                     read_sidecar, shard_index, sidecar_path, tar_path, truth_path)

SUBJECT_KEYS = ("format", "subject_id", "subject_index", "dataset_seed", "generator", "latent", "protocol",
                "pivot", "resolution", "views", "software", "depth", "camera_convention")
VIEW_KEYS = ("name", "yaw_deg", "pitch_deg", "radius", "fov_deg", "cam2world", "intrinsics")


def check_metadata(meta: dict, views: int, resolution: int) -> list[str]:
    """Schema problems of one subject's metadata (empty when it is valid)."""
    problems = [f"metadata lacks {k!r}" for k in SUBJECT_KEYS if k not in meta]
    if problems:
        return problems
    if len(meta["views"]) != views:
        problems.append(f"{len(meta['views'])} views, expected {views}")
    if meta["resolution"] != resolution:
        problems.append(f"resolution {meta['resolution']}, expected {resolution}")
    for k in ("name", "checkpoint_sha256"):
        if k not in meta["generator"]:
            problems.append(f"generator record lacks {k!r}")
    for k in ("version", "git_revision"):
        if k not in meta["software"]:
            problems.append(f"software record lacks {k!r}")
    for v in meta["views"]:
        missing = [k for k in VIEW_KEYS if k not in v]
        if missing:
            problems.append(f"view {v.get('name', '?')} lacks {', '.join(missing)}")
            continue
        c2w, K = np.asarray(v["cam2world"], dtype=float), np.asarray(v["intrinsics"], dtype=float)
        if c2w.shape != (4, 4) or K.shape != (3, 3) or not (np.isfinite(c2w).all() and np.isfinite(K).all()):
            problems.append(f"view {v['name']}: camera matrices malformed")
        elif abs(np.linalg.det(c2w[:3, :3]) - 1.0) > 1e-4:
            problems.append(f"view {v['name']}: cam2world rotation is not orthonormal")
    return problems


def verify_shard(root, shard: dict, views: int, resolution: int, shape: int = 0) -> list[str]:
    """Problems of one shard, each a line naming the file. ``shape``: the grid resolution of the
    shape each subject must hold (0: none may)."""
    i = shard_index(shard["name"])
    tar = tar_path(root, i)
    try:
        side = read_sidecar(root, i, strict=True)
    except DatasetError as e:
        return [f"{e} (the shard cannot be trusted; delete both files and rerun with --resume)"]
    if side is None:
        return [f"{tar}: incomplete (no sidecar {shard['name']}.json); rerun 'datagen sample ... --resume'"]
    if not tar.exists():
        return [f"{tar}: missing although its sidecar exists"]
    problems = []
    if tar.stat().st_size != side.get("tar_bytes"):
        problems.append(f"{tar}: size {tar.stat().st_size} differs from the sidecar's {side.get('tar_bytes')}")
    elif sha256_file(tar) != side.get("tar_sha256"):
        problems.append(f"{tar}: sha256 differs from the sidecar (corrupted)")
    if "truth_sha256" in side:
        tp = truth_path(root, i)
        if not tp.exists() or sha256_file(tp) != side["truth_sha256"]:
            problems.append(f"{tp}: missing or its sha256 differs from the sidecar")
    if side.get("subjects") != shard["subjects"]:
        problems.append(f"{tar}: sidecar subjects differ from the dataset index")
    seen, digests = [], {}
    try:
        for key, fields in iter_tar_samples(tar):
            seen.append(key)
            digests[key] = fields_digest(fields)
            expected_fields = 1 + 3 * views + sum(f.endswith(".npy") for f in fields) + bool(shape)
            if len(fields) != expected_fields or not any(f == "json" for f in fields) \
                    or (SHAPE_FIELD in fields) != bool(shape):
                problems.append(f"{tar}: subject {key} has {len(fields)} fields, expected {expected_fields}"
                                + (f" with {SHAPE_FIELD}" if shape else ""))
                continue
            sample = decode_sample(key, fields, str(tar))
            problems += [f"{tar}: subject {key}: {p}" for p in check_metadata(sample.metadata, views, resolution)]
            if shape:
                problems += check_shape(fields[SHAPE_FIELD], sample.metadata.get("shape"), shape,
                                        f"{tar}: subject {key}")
            if sorted(sample.arrays) != sorted(sample.metadata.get("arrays", {})):
                problems.append(f"{tar}: subject {key}: arrays differ from those its metadata lists")
            for v, (rgb, a, d) in enumerate(zip(sample.rgb, sample.alpha, sample.depth)):
                if rgb.shape != (resolution, resolution, 3) or a.shape != (resolution, resolution) \
                        or d.shape != (resolution, resolution):
                    problems.append(f"{tar}: subject {key} view {v}: image sizes wrong")
                elif not np.isfinite(d).all():
                    problems.append(f"{tar}: subject {key} view {v}: depth has NaN or Inf")
    except DatasetError as e:
        problems.append(str(e))
    if not problems and seen != shard["subjects"]:
        problems.append(f"{tar}: holds subjects {seen[:3]}..., the index lists {shard['subjects'][:3]}...")
    if not problems:
        problems += check_byte_ranges(root, i, side, digests)
    return problems


def check_shape(data: bytes, record, resolution: int, where: str) -> list[str]:
    """A stored shape: its metadata record is there with the dataset's grid resolution, and the
    mesh passes :func:`datagen.shapes.check_mesh` (decodes, not empty, inside its box)."""
    if not isinstance(record, dict):
        return [f"{where}: metadata lacks the 'shape' record of its {SHAPE_FIELD}"]
    if record.get("resolution") != resolution:
        return [f"{where}: shape resolution {record.get('resolution')}, expected {resolution}"]
    return check_mesh(data, record, where)


def fields_digest(fields: dict) -> str:
    """sha256 over a subject's field names and bytes, in order."""
    h = hashlib.sha256()
    for name, data in fields.items():
        h.update(name.encode() + b"\0" + len(data).to_bytes(8, "little") + data)
    return h.hexdigest()


def check_byte_ranges(root, i: int, side: dict, digests: dict) -> list[str]:
    """Each subject's byte range in the sidecar must read back as exactly that subject's fields."""
    offsets = side["offsets"]
    if sorted(offsets) != sorted(digests):
        return [f"{sidecar_path(root, i)}: byte ranges are given for {len(offsets)} subjects, the tar holds "
                f"{len(digests)}"]
    problems = []
    for key in digests:
        try:
            fields = read_range(tar_path(root, i), key, *offsets[key])
        except DatasetError as e:
            problems.append(f"{e} (byte range {offsets[key]} in {sidecar_path(root, i).name})")
            continue
        if fields_digest(fields) != digests[key]:
            problems.append(f"{sidecar_path(root, i)}: byte range {offsets[key]} of {key} does not read back as "
                            f"that subject")
    return problems


@dataclass(frozen=True)
class VerifyOptions(ArrayJobOptions):
    """The options of ``datagen verify``."""

    quiet: bool = setting(False, "no progress bar")


def _verify_task(job: tuple, shard: dict, device: str, report) -> list[str]:
    """The runner's task (:mod:`datagen.runner`): the problems of one shard of the index."""
    root, views, resolution, shape = job
    return verify_shard(root, shard, views, resolution, shape)


def verify_dataset(dataset, progress: bool = False, placement: Placement = Placement(), shards=None) -> dict:
    """Verify the shards numbered ``shards`` (default all) of ``dataset`` (a Dataset or its folder) where
    ``placement`` says; returns {'shards', 'complete', 'subjects', 'problems', 'stray'}."""
    dataset = Dataset.of(dataset)
    root, index = dataset.root, dataset.index
    job = (root, index["views_per_subject"], index["settings"]["resolution"], index["settings"].get("save_shape", 0))
    wanted = None if shards is None else set(shards)
    listed = [sh for n, sh in zip(dataset.shard_numbers, dataset.shards) if wanted is None or n in wanted]
    found = [None] * len(listed)
    bar = progress_bar(len(listed), "shard", "verifying", progress)
    try:
        for i, problems in run_tasks(_verify_task, job, listed, [1] * len(listed), placement, bar,
                                     lambda shard: f"verifying {shard['name']}"):
            found[i] = problems
    finally:
        bar.close()
    problems = [p for found_here in found for p in found_here]
    valid = [sh for sh, p in zip(listed, found) if not p]
    stray = sorted(str(p) for p in list(root.glob(".*tmp-*")) + list((root / TRUTH_DIR).glob(".*tmp-*")))
    return {"shards": len(listed), "complete": len(valid), "subjects": sum(len(sh["subjects"]) for sh in valid),
            "problems": problems, "stray": stray}
