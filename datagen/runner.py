"""Run a command's tasks in this process, in local worker processes or as Ray tasks: the one place
``datagen sample``, ``datagen verify`` and ``label-tool auto`` run their work.

A task is a module-level function ``task(job, item, device, report) -> result``: ``job`` is what every
task shares (picklable), ``item`` one unit of work (a shard, or some of a shard's subjects), ``device``
where it runs ("cpu" or "cuda:N"), and ``report(n)`` adds ``n`` to the progress display. Tasks are
pure functions of (job, item), so where they run never changes what they return. Array jobs pick their
items before they get here (:func:`datagen.dataset.shards.job_shards`).

- In this process: one device, or at most one item.
- Local workers: one process per device, started from a fresh server process that has imported the
  task's module (forkserver; spawn where there is none), never forked from this one, which may already
  run native thread pools (BLAS, dlib) or hold a GPU. Each sets its torch threads and current GPU first.
- Ray: one task per item on the cluster this process is connected to, else the one at the address
  given or RAY_ADDRESS, else a private local one (:mod:`datagen.raycluster`); progress advances as
  items finish.

After an error or an interrupt, items not yet started are cancelled and the error is raised here; an
interrupt (Ctrl-C, or SIGTERM through :func:`datagen.command_line.run_command`) also stops local workers
at once.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import queue as queue_module
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import closing
from dataclasses import dataclass
from typing import Callable, Iterator

from .command_line import at_least, setting
from .errors import SettingError
from .threads import choose, usable_cpus, use

BACKENDS = ("local", "ray")


@dataclass(frozen=True)
class Placement:
    """Where tasks run. ``devices``: one local worker per element (a single one runs in this process);
    with Ray, how many ways the CPU cores are divided. ``threads``: torch CPU threads of each worker or
    Ray task (None: :func:`datagen.threads.choose` over the workers locally, the cores over the devices
    on Ray). ``ray_gpus``: each Ray task's share of one GPU when it runs on CUDA (None: CPU tasks)."""

    devices: tuple[str, ...] = ("cpu",)
    threads: int | None = None
    backend: str = "local"
    ray_address: str | None = None
    ray_gpus: float | None = None

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise SettingError(f"{{backend}} {self.backend!r}: choose local or ray")
        if self.ray_address is not None and self.backend != "ray":
            raise SettingError("{ray_address}: only with {backend} ray")
        if not self.devices:
            raise SettingError("{workers} must be at least 1")


@dataclass(frozen=True)
class RunOptions:
    """The options of a command whose work the runner spreads over CPU workers (``datagen verify``,
    ``label-tool auto``); ``--threads`` comes with them (:func:`datagen.threads.add_option`)."""

    workers: int = setting(1, "worker processes on this machine", parse=at_least(1), metavar="N")
    backend: str = setting("local", "local worker processes (--workers), or tasks of a shard (or part of one) each "
                                    "on a Ray cluster", choices=BACKENDS)
    ray_address: str | None = setting(None, "Ray cluster to use (default: RAY_ADDRESS, else a local Ray instance)",
                                      metavar="ADDR")

    def placement(self, threads: int | None = None) -> Placement:
        """Where the work runs: ``workers`` CPU workers; on Ray, tasks of one CPU each unless ``threads``."""
        return Placement(("cpu",) * self.workers, threads or (1 if self.backend == "ray" else None), self.backend,
                         self.ray_address)


@dataclass(frozen=True)
class ArrayJobOptions(RunOptions):
    """:class:`RunOptions` and the array-job split of a command that runs over a dataset's shards."""

    shard_index: int = setting(0, "array jobs: this job's part K of --num-shards", parse=at_least(0), metavar="K")
    num_shards: int = setting(1, "array jobs: split the shards over N jobs; job K takes the shards s with s %% N == K",
                              parse=at_least(1), metavar="N")


def run_tasks(task: Callable, job, items: list, units: list[int], placement: Placement, bar,
              describe: Callable[[object], str] = str) -> Iterator[tuple[int, object]]:
    """(position in ``items``, result) of each task as it finishes. ``units``: the progress each item
    adds to ``bar`` when done (what its task reported is topped up to this). ``describe(item)`` names
    an item in errors from Ray."""
    if not items:
        return
    progress = _Progress(bar, units)
    if placement.backend == "ray":
        yield from _on_ray(task, job, items, placement, progress, describe)
    elif len(placement.devices) == 1 or len(items) == 1:
        for i, item in enumerate(items):
            result = task(job, item, placement.devices[0], lambda n, i=i: progress.add(i, n))
            progress.done(i)
            yield i, result
    else:
        yield from _on_workers(task, job, items, placement, progress)


class _Progress:
    """The bar, advanced by what tasks report and topped up to each item's units when it finishes."""

    def __init__(self, bar, units: list[int]):
        self.bar, self.units, self.seen = bar, units, [0] * len(units)

    def add(self, i: int, n: int) -> None:
        n = max(0, min(n, self.units[i] - self.seen[i]))
        self.seen[i] += n
        self.bar.update(n)

    def done(self, i: int) -> None:
        self.add(i, self.units[i])


# ----------------------------------------------------------------------------------------------
# Local worker processes

_WORKER: tuple | None = None  # in a worker process: (progress queue, its device)


def enter_worker(threads: int, device: str) -> None:
    """Set up a worker process (or a Ray task) to run on ``device`` with ``threads`` torch CPU threads.
    A CUDA worker makes its GPU the current one, so nothing it runs lands on another."""
    use(threads)
    if device.startswith("cuda"):
        import torch

        torch.cuda.set_device(torch.device(device))


def _init_worker(threads: int, progress, devices) -> None:
    """Pool initializer: each worker process takes the next device from the ``devices`` queue."""
    global _WORKER
    device = devices.get()
    enter_worker(threads, device)
    _WORKER = (progress, device)


def _worker_task(task: Callable, job, i: int, item):
    progress, device = _WORKER
    return task(job, item, device, lambda n: progress.put((i, n)))


def worker_context(module: str):
    """The start method of local workers: a forkserver that has imported ``module``, else spawn."""
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload([module])
    return ctx


def _on_workers(task, job, items, placement: Placement, progress: _Progress):
    devices = placement.devices[:len(items)]
    ctx = worker_context(task.__module__)
    reports, handout = ctx.Queue(), ctx.Queue()
    for device in devices:
        handout.put(device)
    threads = choose(len(devices), placement.threads)
    with ProcessPoolExecutor(max_workers=len(devices), mp_context=ctx, initializer=_init_worker,
                             initargs=(threads, reports, handout)) as pool:
        pending = {pool.submit(_worker_task, task, job, i, item): i for i, item in enumerate(items)}
        try:
            while pending:
                finished, _ = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                _drain(reports, progress)
                for future in finished:
                    i = pending.pop(future)
                    result = future.result()  # a worker's error is raised here
                    progress.done(i)
                    yield i, result
        except KeyboardInterrupt:
            # Stop the workers now: they would otherwise finish their items and the ones queued to them
            # (the pool's own processes: the executor has no public way before Python 3.14). A task stopped
            # midway leaves only temporary files, which the next run removes. The pending futures fail as
            # the pool breaks; cancelling them as well would race with that.
            for process in list(pool._processes.values()):
                process.terminate()
            raise
        except BaseException:
            for future in pending:
                future.cancel()
            raise
        finally:
            _drain(reports, progress)


def _drain(reports, progress: _Progress) -> None:
    while True:
        try:
            progress.add(*reports.get_nowait())
        except queue_module.Empty:
            return


# ----------------------------------------------------------------------------------------------
# Ray

def ray_task_options(nodes: list[dict], threads: int, gpus: float | None) -> dict:
    """What one task asks Ray for: ``threads`` CPUs and, when it runs on CUDA, ``gpus`` of one GPU
    (None: a CPU task). ``nodes`` is ``ray.nodes()``: the CPUs are capped at the largest alive node
    that could run the task, since a task asking for more than any node has would wait forever; for
    the same reason a GPU task on a cluster without GPUs is refused."""
    alive = [n.get("Resources", {}) for n in nodes if n.get("Alive")]
    if gpus:
        alive = [r for r in alive if r.get("GPU", 0) > 0]
        if not alive:
            raise SettingError("the Ray cluster has no GPU; run on the CPU with {device} cpu")
    biggest = max((r.get("CPU", 0) for r in alive), default=0)
    options = {"num_cpus": max(1, min(threads, int(biggest) or threads))}
    if gpus:
        options["num_gpus"] = gpus
    return options


def _ray_task(task: Callable, job, item, threads: int, cuda: bool):
    # Ray workers are reused across tasks and jobs: set the threads for every task. A GPU task runs
    # in a fresh worker (Ray's default for tasks that ask for GPUs) that sees the GPU it was given.
    # A CPU task stays on the CPU even on a node with GPUs.
    device = "cpu"
    if cuda:
        import ray

        from .device import ray_task_device

        device = ray_task_device(ray.get_gpu_ids(), os.environ.get("CUDA_VISIBLE_DEVICES"))
    enter_worker(threads, device)
    return task(job, item, device, lambda n: None)


def _on_ray(task, job, items, placement: Placement, progress: _Progress, describe: Callable[[object], str]):
    from .raycluster import ray_connection, ray_results

    threads = placement.threads or max(1, usable_cpus() // len(placement.devices))
    with ray_connection(placement.ray_address) as ray:
        options = ray_task_options(ray.nodes(), threads, placement.ray_gpus)
        remote = ray.remote(**options)(_ray_task)
        pending = {remote.remote(task, job, item, options["num_cpus"], bool(placement.ray_gpus)): i
                   for i, item in enumerate(items)}
        with closing(ray_results(ray, pending, lambda i: describe(items[i]))) as finished:
            for i, result in finished:
                progress.done(i)
                yield i, result
