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
same problems, each as ``<file>:<line>: <what>``: a line that is not a valid event (a write cut
by a crash, a wrong type), an event of another reviewer (ignored: a log holds one reviewer's
events), a repeated event number. Such lines are reported, never silently dropped, and never
raise.
"""
from __future__ import annotations

import errno
import json
import os
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from .defects import REVIEW_REASONS
from .errors import UserError

ACTIONS = ("good", "bad", "skip", "undo")
VERDICTS = ("good", "bad", "skip")
DECISIONS = ("good", "bad")   # the verdicts that make a subject reviewed; skip is "decide later"
REASONS = REVIEW_REASONS
REVIEWER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True)
class Event:
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
    events, problems, first_line = [], [], {}
    lines = data.split(b"\n")
    for i, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        partial = i == len(lines) and not data.endswith(b"\n")
        try:
            event = parse_event(raw.decode("utf-8"), reviewer)
        except ForeignEvent as e:
            problems.append(f"{path}:{i}: {e}")
            continue
        except (ValueError, UnicodeDecodeError) as e:
            what = "partial last line (an interrupted write)" if partial else f"not a valid event ({e})"
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
        for e in events:
            self.apply(e)

    def undo_target(self) -> Event | None:
        """The verdict the next undo cancels."""
        return self.stack[-1] if self.stack else None

    def apply(self, e: Event) -> None:
        if e.action != "undo":
            self.stack.append(e)
            self.current[e.subject] = e
            return
        if not self.stack:
            return
        gone = self.stack.pop()
        earlier = next((x for x in reversed(self.stack) if x.subject == gone.subject), None)
        if earlier is None:
            self.current.pop(gone.subject, None)
        else:
            self.current[gone.subject] = earlier


def is_decision(event: Event | None) -> bool:
    """Whether a subject with this effective verdict (None: none) counts as reviewed."""
    return event is not None and event.action in DECISIONS


def verdicts(events: list[Event]) -> dict[str, Event]:
    """A reviewer's effective verdict per subject (good / bad / skip) after applying undos."""
    return dict(Verdicts(events).current)


class EventLog:
    """A reviewer's log opened for appending; every event is on disk when :meth:`append` returns."""

    def __init__(self, labels_dir, reviewer: str):
        self.reviewer = check_reviewer(reviewer)
        self.path = log_path(labels_dir, reviewer)
        self._created = not self.path.exists()
        self.failed_writes = 0  # writes that failed (each taken back and reported as a UserError)
        # the folders this log makes, deepest first, so that a session that writes nothing leaves none
        self._made_dirs = [d for d in (self.path.parent, *self.path.parent.parents) if not d.exists()]
        problem = log_file_problem(self.path) if self.path.exists() else None
        if problem:
            raise UserError(problem)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.events, self.problems = read_log(self.path, reviewer) if self.path.exists() else ([], [])
            self._file = open(self.path, "ab", buffering=0)
        except OSError as e:
            raise UserError(f"cannot write the review log {self.path}: {e.strerror}") from None
        if self.path.stat().st_size and not self.path.read_bytes().endswith(b"\n"):
            self._write(b"\n")  # close a line cut by a crash; it stays in the file and is reported
        self.seq = max((e.seq for e in self.events), default=0)
        self._verdicts = Verdicts(self.events)

    def _write(self, data: bytes) -> None:
        """Append ``data`` and fsync; a write that fails (a full disk) is taken back whole, so the log
        ends with the last event that was saved, and becomes a UserError naming the log."""
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
        nothing, and the folders it made for it when they are still empty."""
        self._file.close()
        if discard_if_empty and self._created and self.path.stat().st_size == 0:
            self.path.unlink()
            for d in self._made_dirs:
                try:
                    d.rmdir()
                except OSError:  # not empty: something else was put there meanwhile
                    break
