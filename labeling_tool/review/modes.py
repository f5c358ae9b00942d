"""The review window's three modes over one :class:`ReviewSession`: what each draws and what its keys do.

:class:`GridMode` ("review") shows every view of one subject; :class:`SurfaceMode` ("3d") the subject's
surface, turned with the mouse; :class:`TriageMode` ("triage") one view of a page of subjects. A mode's
:meth:`Mode.keys` maps key names to actions; a key a mode lacks does nothing there (the window's own keys,
help and Escape, work in every mode). Verdict keys in the grid and the 3D view save the verdict and show
the next subject's views; in triage they mark the cell under the cursor, written when the page is committed.
"""
from __future__ import annotations

from functools import cached_property

from .layout import REVIEW_KEYS, TRIAGE_KEYS, VIEW3D_KEYS, Layout, cell_state, review_frame, triage_page
from .session import QueueItem
from .surface import frame_front, polydata, subject_surface, surface_actor

TRIAGE_YAWS = (0.0, 180.0, 90.0, 270.0)   # the view shown in triage: front, back, left, right (c cycles)
SURFACE_AFTER_S = 1.0                     # a subject's 3D surface is made ahead once shown this long


class Mode:
    """One way of showing the queue in the window (``app``, a :class:`labeling_tool.review.app.ReviewApp`)."""

    name = ""

    def __init__(self, app):
        self.app, self.session = app, app.session

    @cached_property
    def bindings(self) -> dict:
        """key name -> action, for the keys this mode answers (made once, on the first key)."""
        return self.keys()

    def keys(self) -> dict:
        """The table :attr:`bindings` holds."""
        return {}

    def show(self):
        """Draw the mode for the session's current state (on entering it, and after a resize)."""

    def refresh(self):
        """Redraw the heads-up text (and what depends on the session's state) without drawing the rest again."""

    def leave(self):
        """Take down what only this mode shows."""

    def show_undone(self, pos: int):
        """Show the subject at ``pos`` whose verdict was just undone."""
        self.app.goto(pos)


class GridMode(Mode):
    """One subject: every view, under the heads-up block."""

    name = "review"

    def keys(self) -> dict:
        return {**subject_keys(self.app), "v": self.app.surface.open}

    def show(self):
        app, size, item = self.app, self.app.window_size(), self.session.item
        frame = app.frames.get((item.subject, size), lambda: self.frame_of(item, size))
        app.layout, app.current_frame = frame.layout, frame
        app.show_canvas(frame.pixels)
        app.cursor.hide()
        if frame.error:
            app.notice = ("error", frame.error)
        self.refresh()
        queue, pos = self.session.queue, self.session.pos
        ahead = [queue[p] for p in (pos + 1, pos + 2, pos - 1) if 0 <= p < len(queue)]
        work = [((it.subject, size), (lambda it=it: self.frame_of(it, size))) for it in ahead]
        if frame.meta is not None:  # this subject's 3D surface, once the next two are ready and the
            # reviewer has stayed a while (most subjects are never seen in 3D; v makes it at once)
            work.insert(2, (("surface", item.subject), lambda: app.surface.arrays_of(item, frame), SURFACE_AFTER_S))
        app.frames.want(work)

    def open(self):
        """Back to the views of the current subject (from the 3D view or triage)."""
        self.app.enter(self)
        self.show()

    def frame_of(self, item: QueueItem, size: tuple[int, int]):
        return review_frame(self.app.reader, item, size, self.app.columns)

    def refresh(self):
        self.app.draw_text(*self.app.status_text(), REVIEW_KEYS)
        self.app.render()


class SurfaceMode(Mode):
    """One subject's surface (its stored shape, else one made from its views), turned with the mouse."""

    name = "3d"

    def __init__(self, app):
        super().__init__(app)
        self.actor = None     # the surface on screen
        self.source = None    # what it was made from, for the heads-up text
        self._bounds = None

    def keys(self) -> dict:
        return {**subject_keys(self.app), "v": self.app.grid.open, "r": self.reframe}

    def arrays_of(self, item: QueueItem, frame):
        return subject_surface(self.app.reader, item, frame.meta)

    def open(self):
        """Show the current subject's surface; a notice (and the views kept) when it has none."""
        app, frame, item = self.app, self.app.current_frame, self.session.item
        if frame.meta is None:
            app.notice = ("error", f"no 3D view: {frame.error}")
            app.refresh()
            return
        arrays, source = app.frames.get(("surface", item.subject), lambda: self.arrays_of(item, frame))
        if arrays is None:
            app.notice = ("warn", f"{item.subject}: no view has a depth inside its mask; nothing to show in 3D")
            app.refresh()
            return
        mesh = polydata(*arrays)
        app.grid_layer.hide()
        self.actor = surface_actor(app.window.plotter, mesh)
        self._bounds, self.source = mesh.bounds, source
        app.window.set_style("3d")
        app.enter(self)
        self.reframe()

    def show(self):
        self.refresh()

    def reframe(self):
        """Look at the head from the front (+z), the whole surface in view."""
        frame_front(self.app.window.plotter, self._bounds)
        self.refresh()

    def refresh(self):
        self.app.draw_text(*self.app.status_text(), VIEW3D_KEYS)
        self.app.render()

    def leave(self):
        if self.actor is not None:
            self.app.window.plotter.remove_actor(self.actor, reset_camera=False, render=False)
        self.actor = None
        self.app.window.set_style("grid")


class TriageMode(Mode):
    """One view of a page of subjects; verdicts are marked on cells and written when the page is committed."""

    name = "triage"

    def __init__(self, app):
        super().__init__(app)
        self.yaw = 0             # index into TRIAGE_YAWS
        self.page = None         # the page on screen (TriagePage)

    def keys(self) -> dict:
        keys = {"g": lambda: self.mark(("good", ())), "Right": lambda: self.move(1), "Left": lambda: self.move(-1),
                "Up": lambda: self.move(-self.session.triage_shape[1]),
                "Down": lambda: self.move(self.session.triage_shape[1]),
                "space": lambda: self.flip(self.session.triage_cursor), "c": self.cycle_view,
                "n": lambda: self.turn_page(+1), "Next": lambda: self.turn_page(+1),
                "p": lambda: self.turn_page(-1), "Prior": lambda: self.turn_page(-1),
                "Return": self.commit_page, "KP_Enter": self.commit_page, "t": self.app.grid.open}
        for key, reason in self.app.reason_keys.items():
            keys[key] = (lambda r=reason: self.mark(("bad", (r,))))
        return keys

    def open(self):
        app = self.app
        app.enter(self)
        self.session.point_at(self.session.pos)
        self.show()

    def leave(self):
        self.session.leave_triage()
        self.app.cursor.hide()

    def show(self):
        app = self.app
        w, h = app.window_size()
        layout = Layout.fit(w, h, self.session.page_size, self.session.triage_shape[1], 2)
        app.layout = layout
        yaw, page = TRIAGE_YAWS[self.yaw], self.session.triage_page
        self.page = app.thumbs.get((page, self.yaw, layout), lambda: self.page_of(page, yaw, layout))
        self.session.move_cursor(0)  # on a cell of this page
        # only the cells that changed since the page was drawn (a verdict undone, a change made on it)
        self.draw(cells=range(len(self.session.page_items())), shown=False)
        ahead = [p for p in (page + 1, page - 1) if 0 <= p < self.session.n_pages]
        app.thumbs.want([((p, self.yaw, layout), (lambda p=p: self.page_of(p, yaw, layout))) for p in ahead])

    def page_of(self, page: int, yaw: float, layout: Layout):
        return triage_page(self.app.reader, self.session, page, yaw, layout)

    def refresh(self):
        self.draw()

    def draw(self, cells=(), shown: bool = True):
        """Draw the page's ``cells`` whose state changed (all of them when the page is not on screen yet,
        ``shown`` False), then the cursor and the heads-up text."""
        app, layout = self.app, self.app.layout
        if self.page.update(self.session, layout, cells) or not shown:
            app.show_canvas(self.page.pixels)
        sx, sy = layout.slot(self.session.triage_cursor)
        app.cursor.show((sx + 2, sy - 2, sx + layout.slot_w - 3, sy + layout.slot_h - 3), layout.height)
        status, detail = self.session.triage_lines(TRIAGE_YAWS[self.yaw])
        app.draw_text(status, detail, TRIAGE_KEYS)
        app.render()

    def show_undone(self, pos: int):
        page = self.session.triage_page
        self.session.point_at(pos)
        if page != self.session.triage_page:
            self.show()
        else:
            self.draw(cells=[self.session.triage_cursor])  # the cell shows its verdict as it is now

    def mark(self, change: tuple[str, tuple]):
        """A change to the cell under the cursor (see :meth:`ReviewSession.set_pending`)."""
        self.session.set_pending(self.session.cursor_item(), change)
        self.draw(cells=[self.session.triage_cursor])

    def flip(self, i: int):
        self.session.flip(i)
        self.draw(cells=[i])

    def move(self, step: int):
        self.session.move_cursor(step)
        self.draw()

    def turn_page(self, step: int):
        """Show the next (+1) or previous (-1) page; changes stay where they were made."""
        if self.session.turn_page(step):
            self.show()
        else:
            self.app.notice = ("warn", f"this is the {'last' if step > 0 else 'first'} page")
            self.draw()

    def cycle_view(self):
        self.yaw = (self.yaw + 1) % len(TRIAGE_YAWS)
        self.show()

    def commit_page(self):
        """Write the page's changes and good for its cells without a verdict; nothing else."""
        page = self.session.triage_page
        self.app.notice = self.session.commit_page()
        if self.session.triage_page != page:
            self.show()
        else:
            self.draw(cells=range(len(self.session.page_items())))

    def clicked(self, x: int, y: int):
        """A left click at window pixel (x, y from the bottom) flips the cell under it."""
        i = self.app.layout.index_at(x, self.app.layout.height - 1 - y)
        if i is not None and i < len(self.session.page_items()):
            self.app.quit_armed = False
            self.session.triage_cursor = i
            self.flip(i)

    def cell_state(self, item: QueueItem):
        """(lines of text, frame) of a triage cell: saved verdict, change not committed, pre-flags."""
        return cell_state(self.session, item)


def subject_keys(app) -> dict:
    """The keys of the grid and the 3D view, which show one subject: g good, s skip, 1-5 bad with that reason,
    moving through the queue (n/Right, p/Left, u) and t to triage."""
    keys = {"g": lambda: app.verdict("good"), "s": lambda: app.verdict("skip"), "n": app.next, "Right": app.next,
            "p": app.previous, "Left": app.previous, "u": app.next_unreviewed, "t": app.triage.open}
    for key, reason in app.reason_keys.items():
        keys[key] = (lambda r=reason: app.verdict("bad", (r,)))
    return keys
