"""``datagen sample``: plan a dataset, render its shards with local workers or on a Ray cluster.

Data flows one way: subject index -> (generator) subject + views -> encoded members -> shard.
The unit of work is a shard task (:func:`write_shard`), a pure function of the job spec and the
shard number, so any backend, worker count or cluster split produces the same bytes.
"""
from __future__ import annotations

import errno
import platform
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .cameras import protocol_pivot, sample_views
from .device import worker_devices
from .errors import SettingError, UserError
from .command_line import progress_bar
from .job import JobSpec
from .files import LockBusy, atomic_write, byte_lock
from .generators import GANS, make_generator
from .generators.base import STREAM_CAMERAS, subject_rng
from .runner import Placement, run_tasks
from .shapes import encode_mesh, extract_shape
from .dataset.shards import (FORMAT, INDEX_NAME, ShardWriter, dumps, encode_subject, is_complete, job_shards,
                     read_index, remove_partial, shard_name, subject_id, tar_path, view_name)
from .threads import usable_cpus

DEPTH_MEANING = "distance along the unit ray from the camera centre, world units; 0 where alpha is 0"
CAMERA_CONVENTION = ("OpenCV cam2world (x right, y down, z forward); intrinsics normalized by image size; "
                     "world y up, face toward +z")


def software_info() -> dict:
    """Package version and git revision of the code that renders (recorded per subject)."""
    here = Path(__file__).resolve().parent.parent
    rev = "unknown"
    try:
        out = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if out.returncode == 0:
            rev = out.stdout.strip()
            dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                                   capture_output=True, text=True, timeout=10)
            if dirty.stdout.strip():
                rev += "+dirty"
    except (OSError, subprocess.SubprocessError):
        pass
    return {"package": "panolam-toolkit", "version": __version__, "git_revision": rev,
            "torch": torch.__version__.split("+")[0], "numpy": np.__version__, "python": platform.python_version()}


def make_index(spec: JobSpec, generator_description: dict) -> dict:
    return {
        "format": FORMAT,
        "settings": spec.settings(),
        "generator": generator_description,
        "views_per_subject": spec.views,
        "num_subjects": spec.subjects,
        "shards": [{"name": shard_name(s), "subjects": [subject_id(i) for i in spec.shard_subjects(s)]}
                   for s in range(spec.num_shard_files)],
    }


# ----------------------------------------------------------------------------------------------
# The shard task

LOCK_NAME = ".datagen.lock"  # byte 0: the index; byte 1 + s: shard s

_GENERATORS: dict = {}


def _generator(spec: JobSpec):
    key = (spec.gan, spec.checkpoint, dumps(spec.generator_options))
    if key not in _GENERATORS:
        _GENERATORS[key] = make_generator(spec.gan, spec.checkpoint, spec.generator_options)
    return _GENERATORS[key]


def render_subject(spec: JobSpec, index: int):
    """Sample and render one subject; returns (metadata, RenderedViews, Subject)."""
    gen = _generator(spec)
    subject = gen.sample_subject(spec.seed, index)
    views = sample_views(spec.protocol, subject_rng(spec.seed, index, STREAM_CAMERAS), spec.views)
    out = gen.render(subject, views, spec.resolution)
    records = views.to_records()
    for i, r in enumerate(records):
        r["name"] = view_name(i)
    description = gen.describe()
    metadata = {
        "format": FORMAT,
        "subject_id": subject_id(index),
        "subject_index": index,
        "dataset_seed": spec.seed,
        "generator": {"name": description["name"], "checkpoint": description["checkpoint"],
                      "checkpoint_sha256": description["checkpoint_sha256"], "config": description["config"]},
        "latent": subject.latent,
        "truncation_psi": subject.latent.get("truncation_psi"),
        "protocol": spec.protocol,
        "pivot": list(protocol_pivot(spec.protocol)),
        "resolution": spec.resolution,
        "background": description["config"].get("background"),
        "depth": DEPTH_MEANING,
        "camera_convention": CAMERA_CONVENTION,
        "views": records,
        "arrays": {k: {"shape": list(a.shape), "dtype": str(a.dtype)} for k, a in sorted(subject.arrays.items())},
        "software": spec.software,
    }
    return metadata, out, subject


def write_shard(spec: JobSpec, shard: int, progress=None) -> dict:
    """Render and publish one shard; ``progress(n_images)`` is called after each subject.

    Holds the shard's lock while it works, so a second run into the same folder can neither write
    the same shard nor remove this run's temporary files.
    """
    try:
        with byte_lock(Path(spec.out) / LOCK_NAME, 1 + shard, blocking=False):
            return _write_shard(spec, shard, progress)
    except LockBusy:
        raise SettingError(f"{tar_path(spec.out, shard)} is being written by another datagen run into {spec.out}; "
                           "wait for it, or give each job its own {shard_index}") from None


def _write_shard(spec: JobSpec, shard: int, progress) -> dict:
    remove_partial(spec.out, shard)
    writer = ShardWriter(spec.out, shard)
    try:
        for index in spec.shard_subjects(shard):
            metadata, out, subject = render_subject(spec, index)
            shape = None
            if spec.save_shape:
                mesh = extract_shape(_generator(spec), subject, spec.save_shape, spec.shape_level)
                metadata["shape"] = mesh.record
                shape = encode_mesh(mesh)
            members = encode_subject(metadata, out.rgb, out.alpha, out.depth, subject.arrays, shape)
            writer.add_subject(metadata["subject_id"], members, subject.truth or None)
            if progress:
                progress(len(out.rgb))
        return writer.commit({"views_per_subject": spec.views})
    except BaseException:
        writer.abort()
        raise


# ----------------------------------------------------------------------------------------------
# Backends

def requested_device(spec: JobSpec) -> str:
    """The --device a job asks for: the GANs' option (default 'auto'); the procedural generator is CPU only."""
    return spec.generator_options.get("device", "auto") if spec.gan in GANS else "cpu"


def on_device(spec: JobSpec, device: str) -> JobSpec:
    """``spec`` rendering on ``device``. A GAN's device is not recorded with its data, and the index
    is written from the job's own spec, so the bytes do not depend on where a shard is rendered."""
    if spec.gan not in GANS:
        return spec
    return replace(spec, generator_options={**spec.generator_options, "device": device})


def _shard_task(spec: JobSpec, shard: int, device: str, report) -> dict:
    """The runner's task (:mod:`datagen.runner`): render and publish one shard on ``device``."""
    return write_shard(on_device(spec, device), shard, progress=report)


def render_shards(spec: JobSpec, shards: list[int], placement: Placement, bar) -> None:
    """Render ``shards`` where ``placement`` says (:func:`datagen.runner.run_tasks`)."""
    units = [len(spec.shard_subjects(s)) * spec.views for s in shards]
    for _ in run_tasks(_shard_task, spec, shards, units, placement, bar, lambda shard: f"shard {shard}"):
        pass


def prepare_output(spec: JobSpec, index: dict) -> None:
    """Create the output folder and publish the index; refuse a folder holding another dataset.

    The check and the write happen under the folder's index lock, so of two runs with different
    settings started together exactly one proceeds.
    """
    out = Path(spec.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with byte_lock(out / LOCK_NAME, 0):
            _publish_index(out, index)
    except PermissionError:
        raise UserError(f"cannot write to {out}: permission denied") from None
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise UserError(f"disk full while writing {e.filename or out}") from None
        raise UserError(f"cannot write to {out}: {e.strerror}") from None


def _publish_index(out: Path, index: dict) -> None:
    if (out / INDEX_NAME).exists():
        # Another job of the same dataset may have written the index; the software version
        # may differ (each subject records its own), nothing else may.
        existing = read_index(out)
        differing = sorted(k for k in set(index["settings"]) | set(existing["settings"])
                           if k != "software" and existing["settings"].get(k) != index["settings"].get(k))
        if differing or existing["generator"] != index["generator"]:
            what = ", ".join(differing) or "generator configuration"
            raise SettingError(f"{out} already holds a dataset made with other settings ({what}); "
                               "choose another {out}")
        return
    atomic_write(out / INDEX_NAME, dumps(index))


def run_sample(spec: JobSpec, *, workers: int | str = 1, backend: str = "local", ray_address: str | None = None,
               gpus_per_task: float | None = None, shard_index: int = 0, num_shards: int = 1, resume: bool = False,
               progress: bool = True, threads: int | None = None) -> dict:
    """Write this job's part of the dataset (shards s with s % num_shards == shard_index).

    ``workers``: a count or 'auto' (see :func:`datagen.device.worker_devices`; on the CPU, 'auto' is
    one per CPU core up to this job's shard count); the local backend runs one process per worker,
    Ray gives each task the CPU cores divided by the workers. ``gpus_per_task``: Ray only, the share
    of a GPU each task asks for when rendering on CUDA (default 1). ``threads``: torch CPU threads of
    each worker process or task (default: :func:`datagen.threads.choose`; Ray: the cores over the workers).
    A job whose shards are all complete writes nothing, with or without ``resume``.
    Returns a summary: shards written and skipped, subjects in this job's shards, images, seconds.
    """
    spec.check()
    if workers != "auto" and not (isinstance(workers, int) and workers >= 1):
        raise SettingError("{workers} must be auto or at least 1")
    mine = job_shards(spec.num_shard_files, shard_index, num_shards)
    requested = requested_device(spec)
    devices = worker_devices(requested, workers, max(1, min(usable_cpus(), len(mine))))
    placement = Placement(tuple(devices), threads, backend, ray_address,
                          _ray_gpus(backend, requested, devices[0], gpus_per_task))
    generator = make_generator(spec.gan, spec.checkpoint, spec.generator_options)
    index = make_index(spec, generator.describe())
    prepare_output(spec, index)
    done = [s for s in mine if is_complete(spec.out, s)]
    if done and not resume and len(done) < len(mine):
        raise SettingError(f"{spec.out} already has {len(done)} complete shard(s) of this job; "
                           "pass {resume} to continue, or choose another {out}")
    todo = [s for s in mine if s not in done]
    subjects = sum(len(spec.shard_subjects(s)) for s in mine)
    if done and not todo:  # the same job asked again
        return {"shards_written": 0, "shards_skipped": len(done), "subjects": subjects, "images": 0, "seconds": 0.0}
    images = sum(len(spec.shard_subjects(s)) for s in todo) * spec.views
    bar = progress_bar(images, "img", "rendering", progress)
    start = time.perf_counter()
    try:
        render_shards(spec, todo, placement, bar)
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise SettingError(f"disk full while writing {e.filename or spec.out}; "
                               "rerun with {resume} once space is free") from None
        raise
    finally:
        bar.close()
    return {"shards_written": len(todo), "shards_skipped": len(done), "subjects": subjects, "images": images,
            "seconds": time.perf_counter() - start}


def _ray_gpus(backend: str, requested: str, device: str, gpus_per_task: float | None) -> float | None:
    """Each Ray task's share of a GPU (None: CPU tasks), or a UserError for a request that cannot be met.
    ``requested``: the --device given; ``device``: what it resolved to here (the first worker's)."""
    cuda = device.startswith("cuda")
    if gpus_per_task is not None:
        if backend != "ray":
            raise SettingError("{gpus_per_task}: only for {backend} ray")
        if not 0 < gpus_per_task <= 1:
            raise SettingError("{gpus_per_task} must be above 0 and at most 1 (a shard task renders on one GPU)")
        if not cuda:
            raise SettingError("{gpus_per_task}: the device is the CPU; Ray tasks ask for GPUs only to render on CUDA")
    if backend != "ray" or not cuda:
        return None
    if ":" in requested:
        raise SettingError(f"{{device}} {requested} pins a GPU of this machine; with {{backend}} ray use cuda or auto "
                        "(each task renders on the GPU Ray gives it)")
    return 1 if gpus_per_task is None else gpus_per_task
