"""Reviewers' append-only event logs: one JSON line per event, flushed and fsynced at once.

``<labels>/<reviewer>.jsonl`` holds events ``{"seq", "time", "reviewer", "subject", "shard", "action",
"reasons"}`` with action one of good / bad / skip / undo. Nothing is ever edited in place: undo is an
event that cancels the reviewer's latest still-effective verdict. A log can be read back with any
JSON-lines reader; lines that do not parse (e.g. a write cut by a crash) are reported with their
line number, never silently dropped.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from datagen.errors import UserError

ACTIONS = ("good", "bad", "skip", "undo")
REASONS = ("multiple_faces", "broken_back", "artifacts", "blur", "other")
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
    if not REVIEWER_NAME.match(name or ""):
        raise UserError(f"reviewer name {name!r} must be letters, digits, '.', '_' or '-' (at most 64)")
    return name


def log_path(labels_dir, reviewer: str) -> Path:
    return Path(labels_dir) / f"{check_reviewer(reviewer)}.jsonl"


def parse_event(line: str) -> Event:
    """One log line -> Event; raises ValueError saying what is wrong."""
    d = json.loads(line)
    if not isinstance(d, dict):
        raise ValueError("not a JSON object")
    missing = [k for k in ("seq", "time", "reviewer", "subject", "shard", "action") if k not in d]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    if d["action"] not in ACTIONS:
        raise ValueError(f"unknown action {d['action']!r}")
    reasons = tuple(d.get("reasons") or ())
    unknown = [r for r in reasons if r not in REASONS]
    if unknown:
        raise ValueError(f"unknown reason(s) {unknown}")
    if d["action"] == "bad" and not reasons:
        raise ValueError("a bad verdict without a reason")
    return Event(int(d["seq"]), str(d["time"]), str(d["reviewer"]), str(d["subject"]), str(d["shard"]),
                 d["action"], reasons)


def read_log(path) -> tuple[list[Event], list[str]]:
    """Events of one log and its problems ('<path>:<line>: <what>'), in file order."""
    events, problems = [], []
    path = Path(path)
    data = path.read_bytes()
    lines = data.split(b"\n")
    for i, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        partial = i == len(lines) and not data.endswith(b"\n")
        try:
            events.append(parse_event(raw.decode("utf-8")))
        except (ValueError, UnicodeDecodeError) as e:
            what = "partial last line (an interrupted write)" if partial else f"unreadable event ({e})"
            problems.append(f"{path}:{i}: {what}")
    seqs = [e.seq for e in events]
    if len(set(seqs)) != len(seqs):
        problems.append(f"{path}: duplicated event numbers")
    return events, problems


def read_logs(labels_dir) -> tuple[dict[str, list[Event]], list[str]]:
    """All reviewers' events {reviewer: events} and every problem found."""
    labels_dir = Path(labels_dir)
    if not labels_dir.is_dir():
        raise UserError(f"{labels_dir}: no labels folder here")
    logs, problems = {}, []
    for path in sorted(labels_dir.glob("*.jsonl")):
        events, p = read_log(path)
        problems += p
        wrong = {e.reviewer for e in events} - {path.stem}
        if wrong:
            problems.append(f"{path}: events of other reviewers {sorted(wrong)} in this log")
        logs[path.stem] = [e for e in events if e.reviewer == path.stem]
    return logs, problems


def verdicts(events: list[Event]) -> dict[str, Event]:
    """A reviewer's effective verdict per subject (good / bad / skip) after applying undos."""
    stack: list[Event] = []
    for e in events:
        if e.action == "undo":
            if stack:
                stack.pop()
        else:
            stack.append(e)
    out: dict[str, Event] = {}
    for e in stack:
        out[e.subject] = e
    return out


class EventLog:
    """A reviewer's log opened for appending; every event is on disk when :meth:`append` returns."""

    def __init__(self, labels_dir, reviewer: str):
        self.reviewer = check_reviewer(reviewer)
        self.path = log_path(labels_dir, reviewer)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            existing, self.problems = read_log(self.path) if self.path.exists() else ([], [])
            self.events = existing
            self._file = open(self.path, "ab")
        except OSError as e:
            raise UserError(f"cannot write the review log {self.path}: {e.strerror}") from None
        if self.path.stat().st_size and not self.path.read_bytes().endswith(b"\n"):
            self._write(b"\n")  # close a line cut by a crash; it stays in the file and is reported
        self.seq = max((e.seq for e in existing), default=0)

    def _write(self, data: bytes) -> None:
        self._file.write(data)
        self._file.flush()
        os.fsync(self._file.fileno())

    def append(self, subject: str, shard: str, action: str, reasons=()) -> Event:
        if action not in ACTIONS:
            raise ValueError(f"unknown action {action!r}")
        self.seq += 1
        event = Event(self.seq, datetime.now(timezone.utc).isoformat(timespec="milliseconds"), self.reviewer,
                      subject, shard, action, tuple(reasons))
        self._write((event.to_json() + "\n").encode())
        self.events.append(event)
        return event

    def verdicts(self) -> dict[str, Event]:
        return verdicts(self.events)

    def close(self) -> None:
        self._file.close()
