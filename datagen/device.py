"""Compute devices: names users give on the command line -> torch devices (one home for the check),
which device each worker uses, and constants made once per device.

A tensor built from Python numbers on an accelerator (``torch.tensor(values, device=d)``,
``x.new_tensor(values)``) is a blocking host-to-device copy: on CUDA it waits for every kernel
queued before it, a host sync in the middle of the work. :func:`constant` pays that once per device.
"""
from __future__ import annotations

import contextlib
import functools
from typing import TYPE_CHECKING

from .errors import UserError

if TYPE_CHECKING:
    import torch

DEVICE_HELP = "cpu, cuda, cuda:N or auto (CUDA when available)"


def resolve_device(name: str) -> torch.device:
    """'auto', 'cpu', 'cuda' or 'cuda:N' -> a torch device that exists here; a UserError otherwise."""
    import torch  # here, so that command-line help can name the choices without importing torch
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    kind, _, index = name.partition(":")
    if kind not in ("cpu", "cuda") or (index and (kind == "cpu" or not index.isdigit())):
        raise UserError(f"unknown device {name!r}; use {DEVICE_HELP}")
    if kind == "cuda":
        if not torch.cuda.is_available():
            raise UserError(f"device {name}: CUDA is not available on this machine (torch {torch.__version__})")
        if index and int(index) >= torch.cuda.device_count():
            raise UserError(f"device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return torch.device(name)


@functools.lru_cache(maxsize=None)
def constant(values: tuple, device: torch.device) -> torch.Tensor:
    """``values`` (a tuple of floats, nested for more dimensions) as a float32 tensor on ``device``,
    made on the first call for that device; shared by every caller, so never modify it in place."""
    import torch
    return torch.tensor(values, dtype=torch.float32, device=device)


def worker_devices(requested: str, workers: int | str, cpu_workers: int) -> list[str]:
    """The device of each local worker process: element k is worker k's device.

    ``requested`` is a --device name; ``workers`` a count or 'auto'. On the CPU, 'auto' means
    ``cpu_workers`` workers. On CUDA, 'cuda' (or 'auto' resolving to it) spreads the workers over
    the visible GPUs, worker k on cuda:(k mod GPU count), so more workers than GPUs share them, and
    'auto' means one worker per GPU; 'cuda:N' puts every worker on that GPU, and 'auto' means one.
    """
    import torch
    device = resolve_device(requested)
    if device.type == "cpu":
        return ["cpu"] * (cpu_workers if workers == "auto" else workers)
    if device.index is not None:
        return [str(device)] * (1 if workers == "auto" else workers)
    gpus = torch.cuda.device_count()
    return [f"cuda:{k % gpus}" for k in range(gpus if workers == "auto" else workers)]


def ray_task_device(gpu_ids: list, visible: str | None) -> str:
    """The torch device of the GPU Ray assigned a task.

    ``gpu_ids``: ``ray.get_gpu_ids()`` inside the task (one id: a shard task asks for at most one GPU,
    several tasks may share it). ``visible``: the task's CUDA_VISIBLE_DEVICES, which Ray sets to the
    assigned ids (so the result is usually cuda:0); it lists the node's own choice instead when
    RAY_EXPERIMENTAL_NOSET_CUDA_VISIBLE_DEVICES is set, and then the id's position in it is the index;
    unset, the id is the index.
    """
    if not gpu_ids:
        raise RuntimeError("Ray assigned no GPU to a task that asked for one")
    first = str(gpu_ids[0])
    listed = [v.strip() for v in visible.split(",")] if visible else None
    return f"cuda:{listed.index(first) if listed else int(first)}"


@contextlib.contextmanager
def one_cpu_thread():
    """Torch's CPU ops on one thread inside the block (the thread count is restored after).

    Transcendental ops (sin, exp, atan2, ...) compute the body of each thread's slice with vector
    code and its ragged end with scalar code, which round differently in the last bit; where the
    slices start depends on the thread count. One thread gives the same bits on any machine."""
    import torch
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
