"""Where training runs: this process, ``--nproc N`` processes on this machine, or one of the
processes ``torchrun`` started (``torchrun --nproc-per-node N -m panolam train ...``, which sets
``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK``).

Processes average gradients with torch.distributed: gloo on CPU (each process gets its share of
the cores, :mod:`datagen.threads`), NCCL on CUDA (the process of local rank i on GPU i: ``--device cuda``, no index). A user
mistake in any process is one line and exit status 2, as in a single process.
"""
from __future__ import annotations

import os
import socket
import sys
from dataclasses import dataclass
from typing import Optional

from datagen.command_line import flag_of
from datagen.errors import SettingError, UserError, os_error_line
from datagen.threads import choose, use

from .config import ModelConfig, TrainConfig


@dataclass(frozen=True)
class Job:
    """What ``panolam train`` was asked to do (see :func:`panolam.train.train` for each field)."""

    data: str
    manifest: str
    out: str
    resume: bool
    device: str
    model: ModelConfig
    training: TrainConfig
    progress: bool = True
    started: Optional[float] = None  # time.monotonic() the time limit counts from
    threads: Optional[int] = None  # torch CPU threads of each process (None: datagen.threads.choose)

    def run(self, device: str) -> dict:
        from .train import train
        return train(self.data, self.manifest, self.model, self.training, self.out, resume=self.resume,
                     device=device, progress=self.progress, started=self.started)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (for the process group's rendezvous)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def process_device(requested: str, local_rank: int, gpus: int) -> str:
    """The device of the process of ``local_rank`` (its index on this machine) in a job on
    ``requested`` ('cpu', 'cuda' or 'cuda:N'), on a machine with ``gpus`` CUDA devices: GPU
    ``local_rank`` for CUDA, else the CPU. A UserError when that GPU is not there."""
    kind, _, index = requested.partition(":")
    if kind != "cuda":
        return "cpu"
    if index:
        raise SettingError(f"{{device}} {requested} names one GPU, but each of several processes takes the GPU of its "
                           "local rank; give {device} cuda")
    if local_rank >= gpus:
        raise UserError(f"process {local_rank} on this machine needs GPU {local_rank}, and it has {gpus}: start at "
                        f"most {gpus} processes per machine")
    return f"cuda:{local_rank}"


def _join(job: Job, local_rank: int, **init) -> str:
    """Bind this process to its device and join the process group (NCCL on CUDA, gloo on the CPU);
    returns the device. ``init``: rank and world size when no environment variables give them."""
    import torch
    import torch.distributed as dist
    device = process_device(job.device, local_rank, torch.cuda.device_count())
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.set_device(device)  # first: NCCL's communicator binds to the current GPU
    dist.init_process_group("nccl" if cuda else "gloo", device_id=torch.device(device) if cuda else None, **init)
    return device


def launched_by_torchrun() -> bool:
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def run(job: Job, nproc: int = 1) -> Optional[dict]:
    """Train ``job`` here, in ``nproc`` new processes, or as this torchrun process; returns the last
    log entry (None when the work ran in child processes, and on torchrun ranks other than 0)."""
    if launched_by_torchrun():
        return _as_torchrun_process(job)
    if nproc == 1:
        return job.run(job.device)
    import torch
    import torch.multiprocessing as mp
    from .train import check_start
    # Each process checks again as it starts; checking here first makes a mistake one line, not one per process.
    process_device(job.device, nproc - 1, torch.cuda.device_count())
    check_start(job.data, job.manifest, job.model, job.training, job.out, job.resume)
    processes = mp.spawn(_child, args=(nproc, free_port(), job), nprocs=nproc, join=False)
    try:
        while not processes.join():
            pass
    except mp.ProcessExitedException as e:
        if e.exit_code == 2:  # the process has said why
            raise SystemExit(2) from None
        raise
    except KeyboardInterrupt:
        # Ctrl-C reaches the whole process group, SIGTERM (kill PID) only this process: stop the others too,
        # or they train on alone. A checkpoint is written under a temporary name, so none is left half-written.
        for process in processes.processes:
            process.terminate()
        raise
    return None


def _as_torchrun_process(job: Job) -> Optional[dict]:
    """This process's share of a torchrun job; the log entry on rank 0 only (one report per run)."""
    import torch.distributed as dist
    use(choose(int(os.environ.get("LOCAL_WORLD_SIZE", "1")), job.threads))
    device = _join(job, int(os.environ.get("LOCAL_RANK", "0")))
    try:
        entry = job.run(device)
        return entry if dist.get_rank() == 0 else None
    finally:
        dist.destroy_process_group()


def _child(rank: int, world: int, port: int, job: Job) -> None:
    """One of ``nproc`` processes started by :func:`run`."""
    import torch.distributed as dist
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world))
    use(choose(world, job.threads))
    device = _join(job, rank, rank=rank, world_size=world)
    try:
        job.run(device)
    except (UserError, OSError) as e:
        line = e.worded(flag_of) if isinstance(e, SettingError) else str(e) if isinstance(e, UserError) \
            else os_error_line(e)
        if line is None:
            raise
        print(f"panolam train: error (process {rank}): {line}", file=sys.stderr)
        sys.exit(2)
    finally:
        dist.destroy_process_group()
