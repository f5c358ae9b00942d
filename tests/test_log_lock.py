"""One writer per reviewer log (``datagen/dataset/events.py``, :class:`LogLock`), with real processes: a second
opener is refused while the first holds the log, a killed holder's lock is taken over, racing
contenders for a stale lock leave exactly one winner, and another machine's lock is judged by its
heartbeat. Readers take no lock."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from datagen.errors import UserError
from datagen.dataset.events import (
    STALE_AFTER_S,
    EventLog,
    LockState,
    read_log,
    read_logs,
    verdicts,
)

ROOT = Path(__file__).resolve().parents[1]

# A process that opens reviewer r1's log, optionally appends, says what happened on one line and
# holds the log until its stdin closes (or it is killed). argv: labels folder, start time, events.
HOLDER = """
import json, sys, time
from datagen.errors import UserError
from datagen.dataset.events import EventLog
labels, start, events = sys.argv[1], float(sys.argv[2]), json.loads(sys.argv[3])
while time.time() < start:
    pass
try:
    log = EventLog(labels, "r1")
except UserError as e:
    print("refused", e, flush=True)
    sys.exit(0)
for subject, action, reasons in events:
    log.undo() if action == "undo" else log.append(subject, "shard-000000", action, reasons)
print("won", flush=True)
sys.stdin.read()
log.close()
"""


def holder(labels, events=(), start=0.0) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-c", HOLDER, str(labels), str(start), json.dumps(list(events))],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)


def wait_for(proc) -> str:
    line = proc.stdout.readline().strip()
    assert line, "the holder process said nothing"
    return line


def finish(proc) -> None:
    proc.stdin.close()
    assert proc.wait(timeout=60) == 0


def lock_file(labels) -> Path:
    return Path(labels) / "r1.jsonl.lock"


def fake_lock(labels, age_s: float, **fields) -> Path:
    """A lock as another process would have left it, its heartbeat ``age_s`` old."""
    path = lock_file(labels)
    path.parent.mkdir(parents=True, exist_ok=True)
    info = {"host": "elsewhere", "boot_id": "another-boot", "pid": 4242, "process_start": "17",
            "token": "f" * 32, "opened": time.time() - age_s, **fields}
    path.write_text(json.dumps(info))
    os.utime(path, (time.time() - age_s,) * 2)
    return path


def test_a_second_writer_is_refused_while_the_first_holds(tmp_path):
    """The case that lost a bad verdict: B holds r1's log, so A cannot open it, and B's undo can only
    cancel B's own verdict; once B closes, A continues B's event numbers."""
    labels = tmp_path / "labels"
    b = holder(labels, [("s23", "good", [])])
    assert wait_for(b) == "won"
    with pytest.raises(UserError) as refused:
        EventLog(labels, "r1")
    line = str(refused.value)
    assert "\n" not in line and f"{labels / 'r1.jsonl'} is open for writing by pid {b.pid} on host " \
                                 f"{socket.gethostname()} since " in line and "close that window" in line
    events, problems = read_logs(labels)   # readers need no lock, and the lock file is no log
    assert problems == [] and [e.subject for e in events["r1"]] == ["s23"]
    finish(b)
    assert not lock_file(labels).exists()
    a = EventLog(labels, "r1")
    a.append("s05", "shard-000000", "bad", ["other"])
    a.undo()
    a.append("s05", "shard-000000", "bad", ["other"])
    a.close()
    events, problems = read_log(labels / "r1.jsonl")
    assert problems == [] and [e.seq for e in events] == [1, 2, 3, 4]
    assert {s: e.action for s, e in verdicts(events).items()} == {"s23": "good", "s05": "bad"}


def test_the_review_command_says_so_in_one_line(tiny_dataset, tmp_path, capsys):
    pytest.importorskip("pyvista")
    from labeling_tool.cli import main as label_main

    labels = tmp_path / "labels"
    b = holder(labels)
    assert wait_for(b) == "won"
    try:
        code = label_main(["review", str(tiny_dataset), "--reviewer", "r1", "--labels", str(labels),
                           "--off-screen", "--keys", "g"])
    finally:
        finish(b)
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and f"open for writing by pid {b.pid}" in lines[0], lines
    assert (labels / "r1.jsonl").read_bytes() == b""  # the refused window wrote nothing


def test_a_killed_holder_is_taken_over(tmp_path):
    labels = tmp_path / "labels"
    b = holder(labels, [("s01", "good", [])])
    assert wait_for(b) == "won"
    b.send_signal(signal.SIGKILL)
    b.wait()
    assert lock_file(labels).exists()  # left behind by the kill
    log = EventLog(labels, "r1")
    try:
        assert LockState.read(lock_file(labels)).info["pid"] == os.getpid()
        assert log.append("s02", "shard-000000", "good").seq == 2
    finally:
        log.close()
    assert not lock_file(labels).exists() and sorted(p.name for p in labels.iterdir()) == ["r1.jsonl"]


def test_a_reused_pid_is_taken_over(tmp_path):
    """A lock of this machine whose pid now belongs to another process (its start time differs)."""
    from datagen.dataset.events import _boot_id

    labels = tmp_path / "labels"
    fake_lock(labels, 0, host=socket.gethostname(), boot_id=_boot_id(), pid=os.getpid(), process_start="1")
    EventLog(labels, "r1").close()


def test_another_machines_lock_is_judged_by_its_heartbeat(tmp_path):
    labels = tmp_path / "labels"
    fake_lock(labels, 5)
    with pytest.raises(UserError, match=r"by pid 4242 on host elsewhere since .*taken over; its last was 5 s ago"):
        EventLog(labels, "r1")
    fake_lock(labels, STALE_AFTER_S + 30)
    log = EventLog(labels, "r1")
    assert LockState.read(lock_file(labels)).info["token"] == log.lock.token
    log.close()


@pytest.mark.parametrize("stale", ["killed", "other host", "empty"])
def test_racing_contenders_for_a_stale_lock_leave_one_winner(tmp_path, stale):
    labels = tmp_path / "labels"
    if stale == "killed":
        b = holder(labels)
        assert wait_for(b) == "won"
        b.send_signal(signal.SIGKILL)
        b.wait()
    elif stale == "other host":
        fake_lock(labels, STALE_AFTER_S + 30)
    else:  # created, then its writer died before writing a byte
        fake_lock(labels, STALE_AFTER_S + 30).write_bytes(b"")
        os.utime(lock_file(labels), (time.time() - STALE_AFTER_S - 30,) * 2)
    start = time.time() + 3.0  # every contender started and spinning by then
    contenders = [holder(labels, start=start) for _ in range(4)]
    said = [wait_for(p) for p in contenders]
    winners = [p for p, line in zip(contenders, said) if line == "won"]
    try:
        assert len(winners) == 1, said
        assert all(f"open for writing by pid {winners[0].pid} " in line for line in said if line != "won"), said
        assert LockState.read(lock_file(labels)).info["pid"] == winners[0].pid
    finally:
        for p in contenders:
            finish(p)
    assert sorted(p.name for p in labels.iterdir()) == ["r1.jsonl"]  # no claim or lock left


def test_a_window_whose_lock_was_taken_over_writes_nothing(tmp_path):
    """A holder whose heartbeat stopped (a machine asleep) and lost its lock to another refuses to write."""
    labels = tmp_path / "labels"
    log = EventLog(labels, "r1")
    log.append("s01", "shard-000000", "good")
    os.replace(fake_lock(tmp_path / "other", 0, pid=777), lock_file(labels))  # the new holder's lock
    with pytest.raises(UserError, match=r"lock was taken over \(now pid 777 on host elsewhere"):
        log.append("s02", "shard-000000", "bad", ["blur"])
    assert log.failed_writes == 1
    log.close()
    assert [e.subject for e in read_log(labels / "r1.jsonl")[0]] == ["s01"]
    assert LockState.read(lock_file(labels)).info["pid"] == 777  # the other holder's lock stays
