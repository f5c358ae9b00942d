"""``datagen sample``: plan a dataset, render its shards with local workers or on a Ray cluster.

Data flows one way: subject index -> (generator) subject + views -> encoded members -> shard.
The unit of work is a shard task (:func:`write_shard`), a pure function of the job spec and the
shard number, so any backend, worker count or cluster split produces the same bytes.
"""
from __future__ import annotations

import errno
import os
import platform
import subprocess
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .cameras import PROTOCOLS, protocol_pivot, sample_views
from .errors import UserError
from .files import LockBusy, atomic_write, byte_lock
from .generators import make_generator
from .generators.base import STREAM_CAMERAS, subject_rng
from .shards import (FORMAT, INDEX_NAME, ShardWriter, dumps, encode_subject, is_complete,
                     read_index, remove_partial, shard_name, subject_id, tar_path, view_name)

DEPTH_MEANING = "distance along the unit ray from the camera centre, world units; 0 where alpha is 0"
CAMERA_CONVENTION = ("OpenCV cam2world (x right, y down, z forward); intrinsics normalized by image size; "
                     "world y up, face toward +z")


@dataclass(frozen=True)
class JobSpec:
    """Everything that determines a dataset's bytes (plus where to write it)."""

    out: str
    gan: str = "procedural"
    checkpoint: str | None = None
    generator_options: dict = field(default_factory=dict)
    protocol: str = "360"
    subjects: int = 16
    resolution: int = 128
    views: int = 32
    seed: int = 0
    shard_size: int = 8
    software: dict = field(default_factory=dict)

    @property
    def num_shard_files(self) -> int:
        return -(-self.subjects // self.shard_size)

    def shard_subjects(self, shard: int) -> range:
        return range(shard * self.shard_size, min(self.subjects, (shard + 1) * self.shard_size))

    def settings(self) -> dict:
        s = asdict(self)
        s.pop("out")
        return s


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


def validate(spec: JobSpec) -> None:
    if spec.protocol not in PROTOCOLS:
        raise UserError(f"unknown protocol {spec.protocol!r}; choose one of: {', '.join(PROTOCOLS)}")
    checks = [(spec.subjects >= 1, "--subjects must be at least 1"),
              (16 <= spec.resolution <= 4096, "--resolution must be between 16 and 4096"),
              (1 <= spec.views <= 1024, "--views must be between 1 and 1024"),
              (spec.shard_size >= 1, "--shard-size must be at least 1"),
              (spec.seed >= 0, "--seed must be non-negative")]
    for ok, message in checks:
        if not ok:
            raise UserError(message)


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
        raise UserError(f"{tar_path(spec.out, shard)} is being written by another datagen run into {spec.out}; "
                        "wait for it, or give each job its own --shard-index") from None


def _write_shard(spec: JobSpec, shard: int, progress) -> dict:
    remove_partial(spec.out, shard)
    writer = ShardWriter(spec.out, shard)
    try:
        for index in spec.shard_subjects(shard):
            metadata, out, subject = render_subject(spec, index)
            members = encode_subject(metadata, out.rgb, out.alpha, out.depth, subject.arrays)
            writer.add_subject(metadata["subject_id"], members, subject.truth or None)
            if progress:
                progress(len(out.rgb))
        return writer.commit({"views_per_subject": spec.views})
    except BaseException:
        writer.abort()
        raise


# ----------------------------------------------------------------------------------------------
# Backends

def _init_worker(threads: int, queue) -> None:
    torch.set_num_threads(threads)
    global _QUEUE
    _QUEUE = queue


_QUEUE = None


def _pool_task(spec: JobSpec, shard: int) -> dict:
    return write_shard(spec, shard, progress=_QUEUE.put)


def _run_local(spec: JobSpec, shards: list[int], workers: int, bar) -> None:
    if workers == 1 or len(shards) <= 1:  # (none left: a resumed dataset that was complete)
        for s in shards:
            write_shard(spec, s, progress=bar.update)
        return
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    threads = max(1, (os.cpu_count() or 1) // workers)
    with ProcessPoolExecutor(max_workers=min(workers, len(shards)), mp_context=ctx,
                             initializer=_init_worker, initargs=(threads, queue)) as pool:
        pending = {pool.submit(_pool_task, spec, s) for s in shards}
        while pending:
            done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            _drain(queue, bar)
            for fut in done:
                fut.result()  # re-raise a worker's error here
        _drain(queue, bar)


def _drain(queue, bar) -> None:
    import queue as queue_mod

    while True:
        try:
            bar.update(queue.get_nowait())
        except queue_mod.Empty:
            return


def _ray_task(spec: JobSpec, shard: int, threads: int) -> dict:
    # Ray workers are reused across tasks and jobs: set the thread count for every task.
    torch.set_num_threads(threads)
    return write_shard(spec, shard)


def _run_ray(spec: JobSpec, shards: list[int], address: str | None, threads: int, bar) -> None:
    """Run the shard tasks on Ray: the cluster this process is already connected to, else the one
    at ``address`` / RAY_ADDRESS, else a private local instance. Only a connection or instance made
    here is closed here."""
    try:
        import ray
    except ImportError:
        raise UserError("the ray backend needs the optional extra: pip install 'panolam-toolkit[ray]'") from None
    import logging

    ray_logger = logging.getLogger("ray")
    level = ray_logger.level
    started = not ray.is_initialized()
    if started:
        target = address or os.environ.get("RAY_ADDRESS") or ""
        host, sep, port = target.split("://", 1)[-1].rpartition(":")
        if sep and port.isdigit():
            # Ray itself keeps retrying an address that does not answer, for many minutes.
            import socket

            try:
                socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=10).close()
            except OSError as e:
                raise UserError(f"cannot reach the Ray cluster at {target}: {e.strerror or e}") from None
        # A local instance started here reports no usage statistics, has no dashboard UI and keeps
        # its workers' output and its own informational messages off the terminal.
        set_usage_env = "RAY_USAGE_STATS_ENABLED" not in os.environ
        if set_usage_env:
            os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.ERROR)
        except Exception as e:
            ray.shutdown()  # whatever a failed start left running
            ray_logger.setLevel(level)
            raise UserError(f"cannot start or reach Ray ({target or 'local'}): "
                            f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from e
        finally:
            if set_usage_env:
                os.environ.pop("RAY_USAGE_STATS_ENABLED", None)
    pending: dict = {}
    try:
        # A task asking for more CPUs than any node has would wait forever.
        biggest = max((n.get("Resources", {}).get("CPU", 0) for n in ray.nodes() if n.get("Alive")), default=0)
        threads = max(1, min(threads, int(biggest) or threads))
        task = ray.remote(num_cpus=threads)(_ray_task)
        pending = {task.remote(spec, s, threads): s for s in shards}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            shard = pending.pop(done[0])
            try:
                sidecar = ray.get(done[0])
            except ray.exceptions.RayTaskError as e:
                cause = getattr(e, "cause", None)
                if isinstance(cause, Exception):
                    # The task's own error, as the local backend raises it; the chained error
                    # carries the remote traceback.
                    raise cause from e
                raise RuntimeError(f"shard {shard} failed on Ray: {e}") from e
            except ray.exceptions.RayError as e:
                raise RuntimeError(f"shard {shard} failed on Ray ({type(e).__name__}): {e}") from e
            bar.update(len(sidecar["subjects"]) * spec.views)
    finally:
        for ref in pending:  # after an error or an interrupt: stop the rest (each removes its partial shard)
            try:
                ray.cancel(ref)
            except Exception:
                pass
        if started:
            ray.shutdown()
            ray_logger.setLevel(level)


class _NullBar:
    def update(self, n=1):
        pass

    def close(self):
        pass


def _progress_bar(total: int, enabled: bool):
    if not enabled:
        return _NullBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="img", unit_scale=False, dynamic_ncols=True, desc="rendering", smoothing=0.1)


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
        differing = sorted(k for k in index["settings"]
                           if k != "software" and existing["settings"].get(k) != index["settings"][k])
        if differing or existing["generator"] != index["generator"]:
            what = ", ".join(differing) or "generator configuration"
            raise UserError(f"{out} already holds a dataset made with other settings ({what}); "
                            "choose another --out")
        return
    atomic_write(out / INDEX_NAME, dumps(index))


def run_sample(spec: JobSpec, *, workers: int = 1, backend: str = "local", ray_address: str | None = None,
               shard_index: int = 0, num_shards: int = 1, resume: bool = False, progress: bool = True) -> dict:
    """Write this job's part of the dataset (shards s with s % num_shards == shard_index).

    Returns a summary: shards written and skipped, images, seconds.
    """
    validate(spec)
    if num_shards < 1 or not 0 <= shard_index < num_shards:
        raise UserError("--shard-index must satisfy 0 <= shard-index < num-shards")
    if workers < 1:
        raise UserError("--workers must be at least 1")
    if backend not in ("local", "ray"):
        raise UserError(f"unknown backend {backend!r}; choose local or ray")
    generator = make_generator(spec.gan, spec.checkpoint, spec.generator_options)
    index = make_index(spec, generator.describe())
    prepare_output(spec, index)
    mine = [s for s in range(spec.num_shard_files) if s % num_shards == shard_index]
    done = [s for s in mine if is_complete(spec.out, s)]
    if done and not resume:
        raise UserError(f"{spec.out} already has {len(done)} complete shard(s) of this job; "
                        "pass --resume to continue, or choose another --out")
    todo = [s for s in mine if s not in done]
    images = sum(len(spec.shard_subjects(s)) for s in todo) * spec.views
    bar = _progress_bar(images, progress)
    start = time.perf_counter()
    try:
        if backend == "ray":
            _run_ray(spec, todo, ray_address, max(1, (os.cpu_count() or 1) // max(1, workers)), bar)
        else:
            _run_local(spec, todo, workers, bar)
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise UserError(f"disk full while writing {e.filename or spec.out}; "
                            "rerun with --resume once space is free") from None
        raise
    finally:
        bar.close()
    return {"shards_written": len(todo), "shards_skipped": len(done), "images": images,
            "seconds": time.perf_counter() - start}
