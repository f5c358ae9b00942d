"""CPU threads: how many torch (and OpenMP/BLAS) threads each process of a command runs.

Every command decides here, once, before its work starts. The budget is the CPUs this process may
use (its affinity mask, capped by a cgroup CPU quota), less the CPUs that other processes are using
right now, shared among the worker processes the command starts. ``OMP_NUM_THREADS``, when the user
set it, is that budget instead (taken as given, load or not), and a command's ``--threads`` overrides
both for each of its processes.

Why the load counts: torch splits each op over its intra-op threads and waits for the slowest one.
When another process holds a core, the thread scheduled there waits for it, and a step made of
thousands of small ops waits thousands of times: on 2 busy cores a 2-thread training step, render or
reconstruction measured 3 to 18 times slower than on one thread (``benchmarks/threads.py``). The
other processes' demand is read from the kernel's count of runnable tasks (``/proc/loadavg``'s
fourth field, sampled a few times over 50 ms, the median), not from the one-minute load average,
which still counts a job that ended a minute ago and not yet one that just started.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import statistics
import sys
import time
from pathlib import Path

LOAD_SAMPLES, LOAD_INTERVAL_S = 5, 0.01


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity mask, capped by the cgroup's CPU quota (v2 or v1)."""
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    quota = _cgroup_quota()
    return max(1, min(n, math.ceil(quota)) if quota else n)


def _cgroup_quota() -> float | None:
    """CPUs' worth of time the cgroup may use per period (None: no quota, or no cgroup files)."""
    try:
        text = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if text and text[0] != "max":
            return int(text[0]) / int(text[1])
        return None
    except (OSError, ValueError, IndexError):
        pass
    try:
        quota = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())
        period = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        return quota / period if quota > 0 and period > 0 else None
    except (OSError, ValueError):
        return None


def busy_cpus() -> int:
    """How many CPUs other processes are using now: runnable tasks less this one (median of samples)."""
    counts = []
    for k in range(LOAD_SAMPLES):
        try:
            running = int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
        except (OSError, ValueError, IndexError):
            return 0
        counts.append(max(0, running - 1))
        if k + 1 < LOAD_SAMPLES:
            time.sleep(LOAD_INTERVAL_S)
    return int(statistics.median_low(counts))


def choose(workers: int = 1, requested: int | None = None) -> int:
    """Threads for each of ``workers`` processes: ``requested`` when given (``--threads``), else the
    budget (``OMP_NUM_THREADS`` when set, else the usable CPUs less the busy ones) over the workers."""
    if requested is not None:
        return max(1, int(requested))
    given = os.environ.get("OMP_NUM_THREADS", "").strip()
    if given.isdigit() and int(given) > 0:
        budget = int(given)
    else:
        budget = usable_cpus() - busy_cpus()
    return max(1, budget // max(1, workers))


def use(threads: int) -> int:
    """Run this process's torch ops on ``threads`` threads (worker processes are handed their own
    count by the command that starts them). Returns ``threads``."""
    import torch
    torch.set_num_threads(threads)
    return threads


@contextlib.contextmanager
def for_command(requested: int | None = None, workers: int = 1):
    """Inside the block this process runs ``choose(workers, requested)`` threads: set now when torch is
    loaded, else through ``OMP_NUM_THREADS``, which torch reads when it loads (a command that never
    needs torch does not pay for importing it). Afterwards the variable and an already loaded torch's
    count are restored (commands also run in-process, from tests and notebooks)."""
    threads = choose(workers, requested)
    torch = sys.modules.get("torch")
    previous = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(threads)
    given = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        yield
    finally:
        if given is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = given
        if previous is not None:
            torch.set_num_threads(previous)


def add_option(parser, what: str = "each worker process") -> None:
    """The ``--threads N`` option of a command that starts workers."""
    def count(text: str) -> int:
        if not text.isdigit() or int(text) < 1:
            raise argparse.ArgumentTypeError(f"must be a whole number of at least 1, not {text!r}")
        return int(text)
    parser.add_argument("--threads", type=count, default=None, metavar="N",
                        help=f"torch CPU threads of {what} (default: the CPUs this process may use, less those "
                             "other processes keep busy, over the workers; OMP_NUM_THREADS sets that budget)")
