"""A reviewer's pass over a queue, without a window: where it stands, verdicts, undo, triage pages.

Every verdict is appended to the reviewer's event log (flushed and fsynced) as it is made, so
closing or killing the window loses nothing; reopening resumes at the first subject not reviewed.
A verdict equal to the saved one writes nothing. Reviewed means good or bad: a skip is "decide
later", so a skipped subject stays unreviewed (in the counts, for ``u`` and where a session
resumes), as ``compile`` counts it.

Triage commit writes exactly: the changes made on that page (a cell marked bad with a reason, or
a saved verdict flipped to good) and good for cells that had no verdict yet; cells with a saved
verdict that were not touched keep it (a skipped one stays skipped, for later). A page without
anything to write writes nothing and says so. Changes wait, per cell, until their page is
committed; pages can be left and revisited without committing.
"""
from __future__ import annotations

from dataclasses import dataclass

from datagen.defects import DEFECT_CLASSES, REASON_LABELS
from datagen.errors import UserError
from datagen.dataset.events import DECISIONS, EventLog, is_decision
from datagen.dataset.preflags import parse_flags

REASON_SHORT = REASON_LABELS
# the reason a triage click or space gives a cell, from its strongest pre-flag (labeling_tool.preflags)
FLAG_REASON = {c.name: c.reason for c in DEFECT_CLASSES}
DEFAULT_REASON = "artifacts"
TRIAGE_SHAPE = (5, 8)                     # rows, columns of a triage page


@dataclass
class QueueItem:
    """A subject in the review queue, with its pre-flag score and flags when the queue is by score."""

    subject: str
    shard: str
    score: float | None = None
    flags: tuple | str = ()  # the detectors that flag the subject, strongest first: ((detector, score), ...),
    #                          or the queue file's text of them, read when shown (165K subjects open faster)

    @property
    def flag_pairs(self) -> tuple:
        """((detector, score), ...) of :attr:`flags`."""
        return parse_flags(self.flags) if isinstance(self.flags, str) else self.flags

    @property
    def default_reason(self) -> str:
        """The reason a triage flip gives this subject: its strongest pre-flag's."""
        return FLAG_REASON.get(self.flag_pairs[0][0], DEFAULT_REASON) if self.flags else DEFAULT_REASON

    def flags_text(self) -> str:
        return ", ".join(f"{name} {score:.2f}" for name, score in self.flag_pairs)


def verdict_text(action: str | None, reasons=()) -> str:
    """A verdict as the window writes it: "bad: back, blur", "good", "none"."""
    if action is None:
        return "none"
    return f"{action}: {', '.join(REASON_SHORT.get(r, r) for r in reasons)}" if reasons else action


class ReviewSession:
    """One reviewer's session over a queue of subjects: the subject shown, the triage page and
    cursor, the triage changes not committed yet, and the verdicts, written to the reviewer's log.

    The methods that change verdicts return the notice (kind, message) that says what they did."""

    def __init__(self, queue: list[QueueItem], reviewer: str, labels_dir, triage_shape=TRIAGE_SHAPE):
        if not queue:
            raise UserError("nothing to review: the queue is empty")
        self.queue, self.triage_shape = queue, tuple(triage_shape)
        self.index = {q.subject: i for i, q in enumerate(queue)}
        self.log = EventLog(labels_dir, reviewer)
        # reviewed: good or bad; a skip is "decide later" (not reviewed, here as in compile)
        actions = [e.action for s, e in self.log.verdicts().items() if s in self.index]
        self.done = sum(actions.count(a) for a in DECISIONS)
        self.skipped = actions.count("skip")
        self.pos = self.first_unreviewed()
        self.triage_page, self.triage_cursor = 0, 0
        self.pending: dict[str, tuple[str, tuple]] = {}   # triage changes not committed yet

    @property
    def item(self) -> QueueItem:
        return self.queue[self.pos]

    def resume_notice(self) -> tuple[str, str]:
        """What the log held when the session opened: the verdicts it resumes from, and the log's
        problems (the first one, and how many more; every one is printed on the terminal)."""
        log, n = self.log, len(self.queue)
        if log.events:
            k = len(log.verdicts())
            text = f"resumed: {k} verdict{'s' * (k != 1)} from {log.path} ({self.done} of {n} in this queue reviewed)"
        else:
            text = f"new log {log.path}: {self.done} of {n} reviewed"
        if not log.problems:
            return "saved", text
        first = log.problems[0].removeprefix(f"{log.path}:")
        first = f"line {first}" if first[:1].isdigit() else first.strip()
        more = len(log.problems) - 1
        return "warn", (f"{text}; {first}"
                        + (f"; {more} more log problem{'s' * (more > 1)} (listed on the terminal)" if more else ""))

    def first_unreviewed(self, start: int = 0) -> int:
        """The first subject from ``start`` on (wrapping around) that is not reviewed: no verdict, or skip."""
        seen = self.log.verdicts()
        for k in range(len(self.queue)):
            i = (start + k) % len(self.queue)
            if not is_decision(seen.get(self.queue[i].subject)):
                return i
        return min(start, len(self.queue) - 1)

    def next_unreviewed(self) -> tuple[str, str] | None:
        """Go to the next subject not reviewed (wrapping around); when there is no other, stay and
        return the notice that says so."""
        i = self.first_unreviewed(self.pos + 1)
        if is_decision(self.log.verdict(self.queue[i].subject)):
            return "warn", f"all {len(self.queue)} subjects of this queue are reviewed: no unreviewed subject left"
        if i == self.pos:
            return "warn", f"{self.item.subject} (shown) is the only unreviewed subject left"
        self.pos = i
        return None

    def _count(self, subject: str, before) -> None:
        """Keep the reviewed and skipped counts up to date after ``subject``'s verdict changed from ``before``."""
        if subject in self.index:
            after = self.log.verdict(subject)
            self.done += is_decision(after) - is_decision(before)
            self.skipped += (after is not None and after.action == "skip") - (before is not None and
                                                                              before.action == "skip")

    def _record(self, item: QueueItem, action: str, reasons=()) -> bool:
        """Write a verdict unless it is the saved one; True when an event was written."""
        saved = self.log.verdict(item.subject)
        if saved is not None and (saved.action, saved.reasons) == (action, tuple(reasons)):
            return False
        self.log.append(item.subject, item.shard, action, reasons)
        self._count(item.subject, saved)
        return True

    def verdict(self, action: str, reasons=()) -> tuple[str, str]:
        """Record the verdict of the subject shown and move on to the next one (the last stays)."""
        item = self.item
        self.pending.pop(item.subject, None)
        what = verdict_text(action, reasons)
        if self._record(item, action, reasons):
            notice = ("saved", f"saved: {item.subject} {what}")
        else:
            notice = ("warn", f"{item.subject} is already {what}: nothing written")
        if self.pos < len(self.queue) - 1:
            self.pos += 1
            return notice
        return notice[0], notice[1] + "   (last subject of the queue; u finds any left)"

    def undo(self) -> tuple[tuple[str, str], int | None]:
        """Cancel the latest verdict: (the notice, the undone subject's place in the queue or None)."""
        target = self.log.undo()
        if target is None:
            return ("warn", "nothing to undo"), None
        self._count(target.subject, target)  # the undone verdict was the subject's effective one
        now = self.log.verdict(target.subject)
        now_text = verdict_text(now.action, now.reasons) if now else "none"
        notice = ("undo", f"undone: {target.subject} {verdict_text(target.action, target.reasons)}; "
                          f"its verdict is now {now_text}")
        if target.subject not in self.index:
            return ("undo", notice[1] + " (not in this queue)"), None
        return notice, self.index[target.subject]

    def status_lines(self, view3d: str | None = None) -> tuple[str, str]:
        """The heads-up block's status and detail lines in review mode, and in 3D (``view3d`` says
        what the 3D view shows)."""
        it = self.item
        v = self.log.verdict(it.subject)
        pending = f"   ({len(self.pending)} triage change(s) not committed)" if self.pending else ""
        view = f"   3D view: {view3d}" if view3d else ""
        skipped = f" ({self.skipped} skipped)" if self.skipped else ""
        status = (f"{it.subject} ({it.shard})   {self.pos + 1}/{len(self.queue)}   reviewed {self.done}, "
                  f"left {len(self.queue) - self.done}{skipped}{pending}{view}")
        score = f"   pre-flag score {it.score:.2f}" if it.score is not None else ""
        detail = (f"verdict: {verdict_text(v.action if v else None, v.reasons if v else ())}{score}"
                  f"   flags: {it.flags_text() or 'none'}")
        return status, detail

    def triage_lines(self, yaw: float) -> tuple[str, str]:
        """The heads-up block's status line on a triage page showing the views nearest ``yaw``, and
        its detail line on the cell under the cursor."""
        items = self.page_items()
        here = sum(1 for it in items if it.subject in self.pending)
        reviewed = sum(1 for it in items if is_decision(self.log.verdict(it.subject)))
        skipped = sum(1 for it in items if (v := self.log.verdict(it.subject)) is not None and v.action == "skip")
        elsewhere = len(self.pending) - here
        first = self.triage_page * self.page_size + 1
        cur = items[self.triage_cursor]
        status = (f"TRIAGE page {self.triage_page + 1}/{self.n_pages} "
                  f"(subjects {first}-{first + len(items) - 1}), "
                  f"view yaw {yaw:.0f}   here: {reviewed} reviewed, "
                  f"{f'{skipped} skipped, ' if skipped else ''}{here} changed"
                  f"{f', {elsewhere} changed on other pages' if elsewhere else ''}   "
                  f"reviewed {self.done}/{len(self.queue)}")
        saved, change = self.log.verdict(cur.subject), self.pending.get(cur.subject)
        flip = self.flip_change(cur)
        detail = (f"cursor {cur.subject}: saved {verdict_text(saved.action, saved.reasons) if saved else 'none'}"
                  f"{f', changed to {verdict_text(*change)} (not committed)' if change else ''}   "
                  f"pre-flags: {cur.flags_text() or 'none'}   space/click: "
                  f"{'take the change back' if flip is None else verdict_text(*flip)}")
        return status, detail

    # -- triage ---------------------------------------------------------------------------------------
    @property
    def page_size(self) -> int:
        return self.triage_shape[0] * self.triage_shape[1]

    @property
    def n_pages(self) -> int:
        return -(-len(self.queue) // self.page_size)

    def page_items(self, page: int | None = None) -> list[QueueItem]:
        page = self.triage_page if page is None else page
        return self.queue[page * self.page_size:(page + 1) * self.page_size]

    def cursor_item(self) -> QueueItem:
        return self.page_items()[self.triage_cursor]

    def point_at(self, pos: int) -> None:
        """Put the triage cursor on subject ``pos``'s cell, on its page."""
        self.triage_page, self.triage_cursor = divmod(pos, self.page_size)

    def leave_triage(self) -> None:
        """Back to review, at the subject under the triage cursor."""
        self.pos = min(self.triage_page * self.page_size + self.triage_cursor, len(self.queue) - 1)

    def move_cursor(self, step: int) -> None:
        self.triage_cursor = min(max(self.triage_cursor + step, 0), len(self.page_items()) - 1)

    def turn_page(self, step: int) -> bool:
        """Go to the next (+1) or previous (-1) page; False when there is none."""
        if 0 <= self.triage_page + step < self.n_pages:
            self.triage_page += step
            return True
        return False

    def set_pending(self, item: QueueItem, change: tuple[str, tuple]) -> None:
        """Record a change to a triage cell; a change back to what is saved (or to good for a new
        cell, which is what a commit writes anyway) is no change."""
        saved = self.log.verdict(item.subject)
        if (saved is not None and (saved.action, saved.reasons) == change) or (saved is None and change[0] == "good"):
            self.pending.pop(item.subject, None)
        else:
            self.pending[item.subject] = change

    def flip_change(self, item: QueueItem):
        """What space or a click does to a cell: None takes back this visit's change; otherwise a bad
        cell becomes good and any other bad with its pre-flag's reason."""
        if item.subject in self.pending:
            return None
        saved = self.log.verdict(item.subject)
        return ("good", ()) if saved and saved.action == "bad" else ("bad", (item.default_reason,))

    def flip(self, i: int) -> None:
        """Flip cell ``i`` of the page (see :meth:`flip_change`)."""
        item = self.page_items()[i]
        change = self.flip_change(item)
        if change is None:
            self.pending.pop(item.subject)
        else:
            self.set_pending(item, change)

    def commit_page(self) -> tuple[str, str]:
        """Write the page's changes and good for its cells without a verdict; nothing else. A page
        that wrote something is followed by the next page (when there is one)."""
        page = self.triage_page + 1
        writes, before, skipped = [], {}, 0
        for item in self.page_items():
            saved = self.log.verdict(item.subject)
            action, reasons = self.pending.get(item.subject) or (("good", ()) if saved is None else (None, ()))
            if action is not None and (saved is None or (saved.action, saved.reasons) != (action, reasons)):
                writes.append((item.subject, item.shard, action, reasons))
                before[item.subject] = saved
            elif saved is not None and saved.action == "skip":
                skipped += 1  # decide later: a commit leaves it for the reviewer, unreviewed
        self.log.append_all(writes)  # one fsync for the page; a failed write keeps the page's changes pending
        for item in self.page_items():
            self.pending.pop(item.subject, None)
        for subject, saved in before.items():
            self._count(subject, saved)
        bad = sum(1 for w in writes if w[2] == "bad")
        good = len(writes) - bad
        if not bad and not good:
            return "warn", (f"page {page}: nothing to commit (every cell has its verdict and none was changed); "
                            "nothing written")
        kept = len(self.page_items()) - bad - good - skipped
        message = (f"committed page {page}: {bad} bad, {good} good written"
                   f"{f', {kept} kept their saved verdict' if kept else ''}"
                   f"{f', {skipped} skipped left unreviewed (u finds them)' if skipped else ''}")
        if self.turn_page(+1):
            self.triage_cursor = 0
            return "saved", message
        return "saved", message + " (last page)"

    def close(self, discard_if_empty: bool = False) -> None:
        self.log.close(discard_if_empty=discard_if_empty)
