"""Reviewers' append-only event logs: one JSON line per event, flushed and fsynced at once.

``<labels>/<reviewer>.jsonl`` holds events ``{"seq", "time", "reviewer", "subject", "shard", "action",
"reasons"}``: ``seq`` a positive integer, unique in the log; ``time`` an ISO 8601 UTC string;
``action`` one of good / bad / skip / undo; ``reasons`` a list of reason names, at least one for
bad and none otherwise (absent or null is read as none). Other keys are ignored. Nothing is ever
edited in place: undo is an event that cancels the reviewer's latest still-effective verdict (its
subject and shard name that verdict's). A log can be read back with any JSON-lines reader.

``skip`` means "decide later": it is kept (and undone) like any verdict, but a subject whose
verdict is skip is not reviewed. :data:`DECISIONS` (good, bad) are what count as reviewed, the same
for the review window (its reviewed count, ``u``, where a session resumes) and for ``compile`` /
``stats`` (a skipped subject is unreviewed there); :func:`is_decision` is that one test.

:func:`parse_event` is the one check of that format. Every reader (the review window and
``compile``/``stats``) goes through :func:`read_log`, so they count the same events and report the
same problems, each as ``<file>:<line>: <what>``: a line that is not a valid event (a wrong type),
a partial line (a write cut by a crash: a last line without its newline, or a JSON object never
closed), an event of another reviewer (ignored: a log holds one reviewer's events), a repeated
event number. Such lines are reported, never silently dropped, and never raise.

One writer per log (:class:`LogLock`): an :class:`EventLog` holds ``<reviewer>.jsonl.lock`` beside
the log while it is open, so a second window for the same reviewer (another terminal, or another
machine on a shared labels folder) is refused in one line naming the holder, instead of both writing
the same event numbers and one's undo cancelling the other's verdict. Readers (``compile``,
``stats``, ``auto --learn``) take no lock. The lock file is created with ``O_CREAT | O_EXCL`` and
records the holder's host, boot id, pid, process start time and opening time; the holder refreshes
its mtime (the heartbeat) every ``HEARTBEAT_S`` and removes it on close (and at exit). A lock is
stale, and is taken over, when its holder is on this machine (same host name and boot id) and its pid
is gone or belongs to a newer process (the start time in ``/proc`` differs), or when it is from
another machine and its heartbeat is older than ``STALE_AFTER_S``. Taking over is atomic: the one
contender that creates the claim file ``<lock>.takeover-<holder's token>`` (``O_EXCL`` again)
renames the stale lock away, and every contender then races for a new ``O_EXCL`` create, which one
wins. What this relies on: ``O_EXCL`` create and rename being atomic on the labels folder's
filesystem (true on local filesystems and NFSv3 or later), and the clocks of machines sharing a
folder agreeing to well within ``STALE_AFTER_S`` (the heartbeat is compared with the reader's
clock). A window whose heartbeat stopped that long (a machine asleep) may have lost its lock to
another: it checks the lock before every write and refuses the write, in one line, if so.
"""
from __future__ import annotations

import atexit
import errno
import gc
import json
import os
import re
import socket
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import NamedTuple

from ..defects import REVIEW_REASONS
from ..errors import UserError

ACTIONS = ("good", "bad", "skip", "undo")
VERDICTS = ("good", "bad", "skip")
DECISIONS = ("good", "bad")   # the verdicts that make a subject reviewed; skip is "decide later"
REASONS = REVIEW_REASONS
REVIEWER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
HEARTBEAT_S = 10.0       # seconds between the holder's refreshes of its lock's mtime
STALE_AFTER_S = 60.0     # a lock of another machine whose mtime is older than this is stale
CLAIM_STALE_S = 10.0     # a takeover claim older than this was left by a contender killed mid-takeover
ACQUIRE_WAIT_S = 30.0    # how long an opener waits for takeovers by other contenders to finish
UNWRITTEN_WAIT_S = 2.0   # how long an opener waits for a lock created this instant to be written


class Event(NamedTuple):
    """One line of a reviewer's log (a named tuple: a log of 165K events is read into memory at once)."""

    seq: int
    time: str
    reviewer: str
    subject: str
    shard: str
    action: str
    reasons: tuple = ()

    def to_json(self) -> str:
        return json.dumps({"seq": self.seq, "time": self.time, "reviewer": self.reviewer, "subject": self.subject,
                           "shard": self.shard, "action": self.action, "reasons": list(self.reasons)},
                          sort_keys=True)


def check_reviewer(name: str) -> str:
    if not isinstance(name, str) or not REVIEWER_NAME.match(name):
        raise UserError(f"reviewer name {name!r} must be letters, digits, '.', '_' or '-' (at most 64)")
    return name


def log_path(labels_dir, reviewer: str) -> Path:
    return Path(labels_dir) / f"{check_reviewer(reviewer)}.jsonl"


class ForeignEvent(ValueError):
    """A valid event in the log of another reviewer."""


def parse_event(line: str, reviewer: str | None = None) -> Event:
    """One log line -> Event, checking every field; ValueError says what is wrong.

    ``reviewer``: the log's owner; an event naming another reviewer raises :class:`ForeignEvent`.
    """
    d = json.loads(line)
    if not isinstance(d, dict):
        raise ValueError("not a JSON object")
    missing = [k for k in ("seq", "time", "reviewer", "subject", "shard", "action") if k not in d]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    seq = d["seq"]
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 1:
        raise ValueError(f"seq must be a positive integer, not {json.dumps(seq)}")
    for key in ("time", "reviewer", "subject", "shard"):
        if not isinstance(d[key], str) or not d[key]:
            raise ValueError(f"{key} must be a non-empty string, not {json.dumps(d[key])}")
    if d["action"] not in ACTIONS:
        raise ValueError(f"unknown action {json.dumps(d['action'])}")
    reasons = d.get("reasons")
    reasons = [] if reasons is None else reasons
    if not isinstance(reasons, list) or not all(isinstance(r, str) for r in reasons):
        raise ValueError(f"reasons must be a list of reason names, not {json.dumps(reasons)}")
    unknown = [r for r in reasons if r not in REASONS]
    if unknown:
        raise ValueError(f"unknown reason(s) {', '.join(unknown)}")
    if d["action"] == "bad" and not reasons:
        raise ValueError("a bad verdict without a reason")
    if d["action"] != "bad" and reasons:
        raise ValueError(f"reasons on a {d['action']} event")
    if reviewer is not None and d["reviewer"] != reviewer:
        raise ForeignEvent(f"an event of reviewer {d['reviewer']!r} in the log of {reviewer!r} (ignored)")
    return Event(seq, d["time"], d["reviewer"], d["subject"], d["shard"], d["action"], tuple(reasons))


_scan_json = json.JSONDecoder().scan_once  # one JSON value from a position: (value, end); raises when there is none
_REASON_SET = frozenset(REASONS)


def _common_event(raw: bytes, reviewer: str) -> Event | None:
    """The event on line ``raw`` when it is a valid event of ``reviewer`` in the form :meth:`Event.to_json`
    writes (one JSON object, nothing around it), read with less checking code than :func:`parse_event`
    (a log of 165K events resumes in about a second); None whenever the line is anything else, for
    :func:`parse_event` to decide and word its problem. Where both accept a line they give the same Event."""
    try:
        text = raw.decode("utf-8")
        d, end = _scan_json(text, 0)
    except (ValueError, StopIteration, RecursionError):
        return None
    if end != len(text) or type(d) is not dict:
        return None
    seq, when, subject, shard, action, reasons = (d.get("seq"), d.get("time"), d.get("subject"), d.get("shard"),
                                                  d.get("action"), d.get("reasons"))
    if (type(seq) is not int or seq < 1 or d.get("reviewer") != reviewer or type(when) is not str
            or type(subject) is not str or type(shard) is not str or not (when and subject and shard)):
        return None
    if action == "bad":
        try:
            if type(reasons) is not list or not reasons or not _REASON_SET.issuperset(reasons):
                return None
        except TypeError:  # an unhashable reason
            return None
    elif action not in ACTIONS or not (reasons is None or (type(reasons) is list and not reasons)):
        return None
    return Event(seq, when, reviewer, subject, shard, action, tuple(reasons or ()))


def log_file_problem(path) -> str | None:
    """Why ``path`` (which exists) cannot be a reviewer's log, or None."""
    path = Path(path)
    if not REVIEWER_NAME.match(path.stem):
        return f"{path}: not named <reviewer>.jsonl (letters, digits, '.', '_' or '-')"
    if not path.is_file():
        return f"{path}: not a file, so not a review log"
    return None


def read_log(path, reviewer: str | None = None) -> tuple[list[Event], list[str]]:
    """The valid events of one log (those of its reviewer, default the file's stem) and its problems
    ('<path>:<line>: <what>'), in file order. Never raises for the file's contents."""
    path = Path(path)
    reviewer = path.stem if reviewer is None else reviewer
    problem = log_file_problem(path)
    if problem:
        return [], [f"{problem}; skipped"]
    try:
        data = path.read_bytes()
    except OSError as e:
        return [], [f"{path}: cannot read ({e.strerror}); skipped"]
    with _collector_paused():
        return _parse_lines(path, data, reviewer)


@contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off for the block: a log's events hold no reference cycles, and
    the collector's passes over the growing list of them cost about a sixth of reading a long log."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _parse_lines(path: Path, data: bytes, reviewer: str) -> tuple[list[Event], list[str]]:
    """:func:`read_log` of the bytes ``data`` of the log ``path``."""
    events, problems, first_line = [], [], {}
    lines = data.split(b"\n")
    for i, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        try:
            event = _common_event(raw, reviewer) or parse_event(raw.decode("utf-8"), reviewer)
        except ForeignEvent as e:
            problems.append(f"{path}:{i}: {e}")
            continue
        except (ValueError, UnicodeDecodeError) as e:
            if i == len(lines) and not data.endswith(b"\n"):
                what = "partial last line, dropped"
            elif raw.lstrip().startswith(b"{") and not raw.rstrip().endswith(b"}"):
                what = "partial line (a write cut short, closed by a later session), dropped"
            else:
                what = f"not a valid event ({e})"
            problems.append(f"{path}:{i}: {what}")
            continue
        if event.seq in first_line:
            problems.append(f"{path}:{i}: event number {event.seq} repeats line {first_line[event.seq]}")
        first_line.setdefault(event.seq, i)
        events.append(event)
    return events, problems


def read_logs(labels_dir) -> tuple[dict[str, list[Event]], list[str]]:
    """All reviewers' events {reviewer: events} and every problem found (see :func:`read_log`)."""
    labels_dir = Path(labels_dir)
    if not labels_dir.is_dir():
        raise UserError(f"{labels_dir}: no labels folder here")
    logs, problems = {}, []
    for path in sorted(labels_dir.glob("*.jsonl")):
        events, p = read_log(path)
        problems += p
        if log_file_problem(path) is None:
            logs[path.stem] = events
    return logs, problems


class Verdicts:
    """A reviewer's effective verdicts, kept up to date event by event.

    Verdicts form a stack: an undo pops the latest one still in effect; a subject's verdict is its
    latest one on the stack.
    """

    def __init__(self, events=()):
        self.stack: list[Event] = []
        self.current: dict[str, Event] = {}
        self._stacked: dict[str, list[Event]] = {}  # each subject's verdicts on the stack, in stack order
        with _collector_paused():
            for e in events:
                self.apply(e)

    def undo_target(self) -> Event | None:
        """The verdict the next undo cancels."""
        return self.stack[-1] if self.stack else None

    def apply(self, e: Event) -> None:
        if e.action != "undo":
            self.stack.append(e)
            self.current[e.subject] = e
            self._stacked.setdefault(e.subject, []).append(e)
            return
        if not self.stack:
            return
        gone = self.stack.pop()
        stacked = self._stacked[gone.subject]
        stacked.pop()
        if stacked:
            self.current[gone.subject] = stacked[-1]
        else:
            self.current.pop(gone.subject, None)
            del self._stacked[gone.subject]


def is_decision(event: Event | None) -> bool:
    """Whether a subject with this effective verdict (None: none) counts as reviewed."""
    return event is not None and event.action in DECISIONS


def verdicts(events: list[Event]) -> dict[str, Event]:
    """A reviewer's effective verdict per subject (good / bad / skip) after applying undos: what
    :class:`Verdicts` keeps, in its order, from the final stack alone (165K events in a tenth of the time)."""
    stack = []
    for e in events:
        if e.action != "undo":
            stack.append(e)
        elif stack:
            stack.pop()
    return {e.subject: e for e in stack}


# ----------------------------------------------------------------------------------------------
# One writer per log

def _boot_id() -> str | None:
    """This machine's boot id (Linux), which tells a reboot or a namesake host from this boot."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return None


def _process_start(pid: int) -> str | None:
    """Process ``pid``'s start time in clock ticks since boot (``/proc/<pid>/stat`` field 22); None
    where there is no /proc, "gone" when there is no such (or only a zombie) process."""
    if not Path("/proc/self/stat").exists():
        return None
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return "gone"
    return "gone" if fields[0] in ("Z", "X") else fields[19]


def _pid_gone(pid: int, start: str | None) -> bool:
    """Whether process ``pid`` of this machine, started at ``start``, has ended (its pid may be reused)."""
    now = _process_start(pid)
    if now is None:  # no /proc: the pid alone (a reused pid looks alive)
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            pass
        return False
    return now == "gone" or (start is not None and now != start)


@dataclass(frozen=True)
class LockState:
    """A lock file as read: its fields (None while its writer has not written them yet, or when it is
    damaged), its inode and its mtime (the heartbeat, seconds since the epoch)."""
    info: dict | None
    inode: int
    mtime: float

    @staticmethod
    def read(path: Path) -> LockState | None:
        """The lock at ``path``, or None when there is none."""
        try:
            with open(path, "rb") as f:
                st, data = os.fstat(f.fileno()), f.read()
        except FileNotFoundError:
            return None
        try:
            info = json.loads(data)
            ok = (isinstance(info, dict) and isinstance(info.get("pid"), int) and isinstance(info.get("token"), str)
                  and isinstance(info.get("opened"), (int, float)))
        except ValueError:
            ok = False
        return LockState(info if ok else None, st.st_ino, st.st_mtime)

    def same(self, other: LockState | None) -> bool:
        return other is not None and other.inode == self.inode and other.info == self.info

    def age(self) -> float:
        return time.time() - self.mtime

    def holder(self) -> str:
        """'pid 1234 on host X since 12:03' (the opening time in local time)."""
        info = self.info
        opened = time.localtime(info["opened"])
        since = time.strftime("%H:%M" if opened[:3] == time.localtime()[:3] else "%Y-%m-%d %H:%M", opened)
        return f"pid {info['pid']} on host {info.get('host')} since {since}"


class LogLock:
    """The lock that makes one process the only writer of a reviewer's log (see the module's
    docstring); :meth:`acquire` takes it or raises a UserError naming the holder."""

    def __init__(self, log: Path):
        self.log = Path(log)
        self.path = self.log.with_name(self.log.name + ".lock")
        self.token = uuid.uuid4().hex
        self.me = {"host": socket.gethostname(), "boot_id": _boot_id(), "pid": os.getpid(),
                   "process_start": _process_start(os.getpid()), "token": self.token}
        self.inode: int | None = None
        self._stop = threading.Event()

    def acquire(self) -> None:
        started = time.monotonic()
        while True:
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                current = LockState.read(self.path)
                if current is not None and not self._stale(current):
                    if current.info is None and time.monotonic() - started < UNWRITTEN_WAIT_S:
                        time.sleep(0.05)  # created this instant: wait for its holder's fields to name it
                        continue
                    raise UserError(self._busy(current)) from None
                if current is not None and not self._take_over(current):
                    if time.monotonic() - started > ACQUIRE_WAIT_S:
                        raise UserError(f"{self.log}: could not take over its stale lock {self.path} within "
                                        f"{ACQUIRE_WAIT_S:.0f} s (other openers kept it busy); try again") from None
                    time.sleep(0.05)  # another contender is taking it over: its new lock decides
                continue
            except OSError as e:
                raise UserError(f"cannot lock the review log {self.log} ({self.path}: {e.strerror})") from None
            try:
                # no fsync: others see it on close (NFS close-to-open); after a crash it is stale anyway
                os.write(fd, json.dumps({**self.me, "opened": time.time()}).encode())
                self.inode = os.fstat(fd).st_ino
            finally:
                os.close(fd)
            atexit.register(self.release)
            threading.Thread(target=self._beat, name=f"heartbeat {self.path.name}", daemon=True).start()
            return

    def _same_machine(self, lock: LockState) -> bool:
        """Whether ``lock``'s holder ran on this machine since its last boot, where pids can be checked."""
        return (lock.info.get("host"), lock.info.get("boot_id")) == (self.me["host"], self.me["boot_id"])

    def _stale(self, lock: LockState) -> bool:
        """Whether ``lock``'s holder is gone: its process has ended (this machine), or its heartbeat is
        older than ``STALE_AFTER_S`` (another machine, or a lock left unreadable)."""
        if lock.info is not None and self._same_machine(lock):
            return _pid_gone(lock.info["pid"], lock.info.get("process_start"))
        return lock.age() > STALE_AFTER_S

    def _busy(self, lock: LockState) -> str:
        if lock.info is None:
            return (f"{self.log} is being opened for writing by another process ({self.path} is "
                    f"{lock.age():.0f} s old); try again in a moment")
        line = f"{self.log} is open for writing by {lock.holder()}; close that window"
        if self._same_machine(lock):
            return line + f" (or end pid {lock.info['pid']}) and try again, or review as another reviewer"
        return line + (f", or review as another reviewer (a lock whose heartbeat stops for {STALE_AFTER_S:.0f} s "
                       f"is taken over; its last was {lock.age():.0f} s ago)")

    def _take_over(self, stale: LockState) -> bool:
        """Remove the stale lock if this contender is the one that claims it; False when another does."""
        generation = stale.info["token"] if stale.info else f"inode-{stale.inode}"
        claim = self.path.with_name(f"{self.path.name}.takeover-{generation}")
        try:
            os.close(os.open(claim, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        except FileExistsError:
            try:
                if time.time() - claim.stat().st_mtime > CLAIM_STALE_S:
                    claim.unlink()  # its claimant was killed before it finished
            except FileNotFoundError:
                pass
            return False
        try:
            current = LockState.read(self.path)  # under the claim, only this process removes ``stale``
            if stale.same(current) and self._stale(current):
                self._remove_if(stale.inode)
        finally:
            claim.unlink(missing_ok=True)
        return True

    def _remove_if(self, inode: int) -> None:
        """Remove the lock file if it is still ``inode``; a lock that has just taken its place is put back."""
        aside = self.path.with_name(f"{self.path.name}.stale-{self.token}")
        try:
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        try:
            if os.stat(aside).st_ino != inode:
                try:
                    os.link(aside, self.path)
                except OSError:
                    pass  # a third lock is there already; the holder of this one finds out at its next write
        finally:
            os.unlink(aside)

    def held(self) -> bool:
        """Whether the lock file is still this process's (checked before every write)."""
        current = LockState.read(self.path)
        return (self.inode is not None and current is not None and current.inode == self.inode
                and current.info is not None and current.info.get("token") == self.token)

    def check(self) -> None:
        """A UserError when another process has taken the lock over (this one's heartbeat stopped)."""
        if self.held():
            return
        current = LockState.read(self.path)
        now = f"now {current.holder()}" if current is not None and current.info else "now nobody"
        raise UserError(f"{self.log}: this window's lock was taken over ({now}; its heartbeat had stopped for "
                        f"over {STALE_AFTER_S:.0f} s, e.g. while this machine slept), so this verdict was not "
                        "saved: close this window")

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                if not self.held():
                    return
                os.utime(self.path)
            except OSError:
                return

    def release(self) -> None:
        """Stop the heartbeat and remove the lock (only this process's own, and only once)."""
        self._stop.set()
        atexit.unregister(self.release)
        if self.inode is not None and self.me["pid"] == os.getpid():
            try:
                self._remove_if(self.inode)
            except OSError:
                pass  # left behind, it is stale (this pid ends) and taken over by the next opener
        self.inode = None


def _ends_with_newline(path: Path) -> bool:
    """Whether the (non-empty) file's last byte is a newline."""
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


class EventLog:
    """A reviewer's log opened for appending; every event is on disk when :meth:`append` returns."""

    def __init__(self, labels_dir, reviewer: str):
        self.reviewer = check_reviewer(reviewer)
        self.path = log_path(labels_dir, reviewer)
        self.failed_writes = 0  # writes that failed (each taken back and reported as a UserError)
        # the folders this log makes, deepest first, so that a session that writes nothing leaves none
        self._made_dirs = [d for d in (self.path.parent, *self.path.parent.parents) if not d.exists()]
        problem = log_file_problem(self.path) if self.path.exists() else None
        if problem:
            raise UserError(problem)
        self.lock = LogLock(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UserError(f"cannot write the review log {self.path}: {e.strerror}") from None
        try:
            self.lock.acquire()  # read and append only as the log's one writer
        except UserError:
            self._remove_made_dirs()
            raise
        self._created = not self.path.exists()
        try:
            self.events, self.problems = read_log(self.path, reviewer) if self.path.exists() else ([], [])
            self._file = open(self.path, "ab", buffering=0)
        except OSError as e:
            self.lock.release()
            raise UserError(f"cannot write the review log {self.path}: {e.strerror}") from None
        if self.path.stat().st_size and not _ends_with_newline(self.path):
            self._write(b"\n")  # close a line cut by a crash; it stays in the file and is reported
        self.seq = max((e.seq for e in self.events), default=0)
        self._verdicts = Verdicts(self.events)

    def _write(self, data: bytes) -> None:
        """Append ``data`` and fsync; a write that fails (a full disk) is taken back whole, so the log
        ends with the last event that was saved, and becomes a UserError naming the log. A log whose
        lock another process has taken over is not written (a UserError too)."""
        try:
            self.lock.check()
        except UserError:
            self.failed_writes += 1
            raise
        fd = self._file.fileno()
        end = os.fstat(fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[self._file.write(view):]
            os.fsync(fd)
        except OSError as e:
            try:
                os.ftruncate(fd, end)
            except OSError:
                pass  # a partial line stays; the next read reports it, as after a crash
            self.failed_writes += 1
            why = "disk full" if e.errno == errno.ENOSPC else (e.strerror or str(e))
            raise UserError(f"cannot write the review log {self.path}: {why}; the verdicts saved before this one "
                            "are kept, this one was not saved") from None

    def append(self, subject: str, shard: str, action: str, reasons=()) -> Event:
        return self.append_all([(subject, shard, action, reasons)])[0]

    def append_all(self, entries) -> list[Event]:
        """Append events [(subject, shard, action, reasons), ...] with one flush and fsync."""
        events = []
        for subject, shard, action, reasons in entries:
            if action not in ACTIONS:
                raise ValueError(f"unknown action {action!r}")
            now = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
            events.append(Event(self.seq + len(events) + 1, now, self.reviewer, subject, shard, action,
                                tuple(reasons)))
        if events:
            self._write("".join(e.to_json() + "\n" for e in events).encode())
            self.seq = events[-1].seq
        for event in events:
            self.events.append(event)
            self._verdicts.apply(event)
        return events

    def undo(self) -> Event | None:
        """Cancel the latest verdict still in effect; returns that verdict (None when there is none)."""
        target = self._verdicts.undo_target()
        if target is not None:
            self.append(target.subject, target.shard, "undo")
        return target

    def verdict(self, subject: str) -> Event | None:
        """The subject's effective verdict, or None."""
        return self._verdicts.current.get(subject)

    def verdicts(self) -> dict[str, Event]:
        return self._verdicts.current

    def close(self, discard_if_empty: bool = False) -> None:
        """Close the log; ``discard_if_empty`` removes it again when this session created it and wrote
        nothing, and the folders it made for it when they are still empty. Releases the lock."""
        self._file.close()
        discard = discard_if_empty and self._created and self.path.stat().st_size == 0
        if discard:
            self.path.unlink()
        self.lock.release()
        if discard:
            self._remove_made_dirs()

    def _remove_made_dirs(self) -> None:
        for d in self._made_dirs:
            try:
                d.rmdir()
            except OSError:  # not empty: something else was put there meanwhile
                break
