"""CPU threads per process: the budget, the load, the override, and the commands that use them."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
import torch

from datagen import cli, threads
from datagen.cli import main as datagen_main


@pytest.fixture
def idle(monkeypatch):
    """A machine of 8 usable CPUs that nothing else uses, with no OMP_NUM_THREADS."""
    monkeypatch.setattr(threads, "usable_cpus", lambda: 8)
    monkeypatch.setattr(threads, "busy_cpus", lambda: 0)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)


def test_the_cpus_are_shared_among_the_workers(idle):
    assert threads.choose() == 8
    assert threads.choose(workers=2) == 4
    assert threads.choose(workers=3) == 2
    assert threads.choose(workers=16) == 1  # never below one


def test_cpus_other_processes_keep_busy_are_left_to_them(idle, monkeypatch):
    monkeypatch.setattr(threads, "busy_cpus", lambda: 6)
    assert threads.choose() == 2
    monkeypatch.setattr(threads, "busy_cpus", lambda: 20)
    assert threads.choose() == 1


def test_omp_num_threads_is_the_budget_and_threads_overrides_everything(idle, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "6")
    monkeypatch.setattr(threads, "busy_cpus", lambda: 8)  # the user's setting is taken as given
    assert threads.choose(workers=2) == 3
    assert threads.choose(workers=2, requested=5) == 5
    monkeypatch.setenv("OMP_NUM_THREADS", "not a number")
    assert threads.choose() == 1  # falls back to the machine: 8 usable, 8 busy


def test_busy_cpus_counts_processes_that_hold_a_cpu():
    spin = "import time\nend = time.time() + 20\nwhile time.time() < end: pass"
    children = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(3)]
    try:
        time.sleep(0.5)
        assert threads.busy_cpus() >= 3
    finally:
        for c in children:
            c.kill()
            c.wait()


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this platform")
def test_usable_cpus_follow_the_affinity_mask():
    code = "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); " \
           "from datagen.threads import usable_cpus; print(usable_cpus())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1"


def test_a_cgroup_quota_caps_the_cpus(monkeypatch):
    monkeypatch.setattr(threads, "_cgroup_quota", lambda: 1.5)
    assert threads.usable_cpus() == min(2, len(os.sched_getaffinity(0)))


def test_a_command_runs_on_its_threads_and_gives_the_count_back(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setitem(cli.COMMANDS, "verify", lambda args: seen.append(torch.get_num_threads()) or 0)
    before = torch.get_num_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert datagen_main(["verify", str(tmp_path)]) == 0
    assert seen == [1] and torch.get_num_threads() == before


def test_threads_must_be_a_positive_count(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        datagen_main(["sample", "--out", str(tmp_path / "d"), "--threads", "0"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--threads" in err[0] and "at least 1" in err[0]
