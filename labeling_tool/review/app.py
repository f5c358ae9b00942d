"""The review window (pyvista): one subject's views as a grid, a triage grid of many subjects, a 3D surface.

Review mode shows every view of one subject, each labelled with its yaw and pitch, under a
heads-up block (subject, progress, verdict, pre-flags, the confirmation of the last action, the
keys). Triage mode shows one view of 40 subjects; each cell carries the subject id, its saved
verdict, its pre-flags and the change the reviewer made to it on this visit. The 3D view is an
occluding surface built from every view's depth and mask (so a face painted on the back of a head
is seen only from behind), framed on the head. The keys act on a :class:`ReviewSession`, which
keeps the verdicts; quitting with triage changes not committed asks for a second Escape. Verdict
keys in the 3D view act as in review: the verdict is saved and the next subject's views come.

A key costs at most one texture upload, the heads-up text (its lines are cached) and one frame; a
window on a display draws the frame straight into its back buffer (colour only). The next subjects
and the next triage pages are drawn in a background thread; the window runs its own event loop so
that the thread gets the interpreter while the window waits for keys.
"""
from __future__ import annotations

import numpy as np
from PIL import Image

from datagen.errors import UserError
from datagen.events import REASONS

from .layout import (COLORS, NOTICE_COLORS, REVIEW_KEYS, TRIAGE_KEYS, VIEW3D_KEYS, Layout, cell_state, draw_hud,
                     help_panel, hud_height, review_frame, text_size, to_vtk_order, triage_page)
from .prefetch import Prefetcher
from .reader import SubjectReader
from .session import TRIAGE_SHAPE, QueueItem, ReviewSession
from .surface import frame_front, polydata, subject_surface, surface_actor
from .window import OFF_SCREEN_SIZE, ImageLayer, Outline, Window, XDisplay, fit_window

REASON_KEYS = {str(i + 1): r for i, r in enumerate(REASONS)}
TRIAGE_YAWS = (0.0, 180.0, 90.0, 270.0)   # the view shown in triage: front, back, left, right (c cycles)
SURFACE_AFTER_S = 1.0                     # a subject's 3D surface is made ahead once shown this long


def _session_state(name: str) -> property:
    return property(lambda self: getattr(self.session, name), doc=f"The session's {name} (read only).")


class ReviewApp:
    """The window of one review session (:class:`ReviewSession`) over a queue of subjects for one reviewer."""

    queue, log, pos, done, skipped, pending, triage_page, triage_cursor = map(
        _session_state, ("queue", "log", "pos", "done", "skipped", "pending", "triage_page", "triage_cursor"))

    def __init__(self, dataset, queue: list[QueueItem], reviewer: str, labels_dir, off_screen: bool = False,
                 window_size=None, columns: int = 8, start_in_triage: bool = False, triage_shape=TRIAGE_SHAPE):
        self.session = ReviewSession(queue, reviewer, labels_dir, triage_shape)  # the queue checked, the log open
        self.dataset, self.columns = dataset, columns
        self.reader = SubjectReader(dataset)
        self.frames = Prefetcher(size=6)        # review canvases and 3D surfaces
        self.thumbs = Prefetcher(size=4)        # triage pages' thumbnails
        self.display = None
        try:
            if not off_screen:
                self.display = XDisplay()
            if window_size is None:
                window_size = OFF_SCREEN_SIZE if off_screen else fit_window(self.display.screen_size())
            if not start_in_triage:  # decode the first subject while the window is being made
                size, item = tuple(window_size), self.session.item
                self.frames.want([((item.subject, size), lambda: review_frame(self.reader, item, size, columns))])
            self.window = Window(off_screen, window_size, f"label-tool review: {reviewer}")
        except UserError:
            self.frames.close()
            self.thumbs.close()
            self.session.close(discard_if_empty=True)  # no display or no window: nothing left behind
            if self.display is not None:
                self.display.close()
            raise
        self.mode = "review"
        self.show_help = False
        self.notice = self.session.resume_notice()
        self.quit_armed = False
        self.triage_yaw = 0
        self._page_thumbs: list = []
        self._page = None            # the triage page on screen (TriagePage)
        self._layout = None
        self._current_frame = None
        # a window on a display draws its first frame in run(), once, with everything in place (each
        # frame before it would cost the start-up a full frame of software OpenGL)
        self._deferred = not off_screen
        self._make_actors()
        self._bind_keys()
        if start_in_triage:
            self.toggle_triage()
        else:
            self.show_subject()

    # -- the notice line -------------------------------------------------------------------------------
    @property
    def notice(self) -> tuple[str, str]:
        """The confirmation of the last action (kind, message), or an empty line."""
        return self._notice

    @notice.setter
    def notice(self, value: tuple[str, str]):
        self._notice, self._notice_on = value, None   # it belongs to the view it is first drawn on

    def _shown(self):
        """What is on screen, for the notice: the subject (review and 3D) or the triage page."""
        return ("page", self.triage_page) if self.mode == "triage" else ("subject", self.pos)

    # -- actors ---------------------------------------------------------------------------------------
    def _make_actors(self):
        """Three 2D images (the grid, the heads-up block, the help panel) and the triage cursor."""
        plotter = self.window.plotter
        self._grid = ImageLayer(plotter)
        self._cursor = Outline(plotter, COLORS["cursor"], 3)
        self._hud = ImageLayer(plotter)
        self._help = ImageLayer(plotter)
        self._help_size = None
        self._hud_key = self._hud_pixels = None
        self._surface = None
        self._surface_source = None

    def window_size(self) -> tuple[int, int]:
        return self.window.size()

    @property
    def closed(self) -> bool:
        return self.window is None

    def _show_canvas(self, pixels: np.ndarray):
        """Put a canvas (H, W, 3 rows bottom-up) on screen as the window's grid."""
        self._grid.show(pixels, 0, 0, self.window_size()[1])

    def _draw_text(self, status: str, detail: str, keys: str):
        """The heads-up block (status, detail, the last action's confirmation, the keys) and the help panel."""
        w, h = self.window_size()
        shown = self._shown()
        if self._notice_on != shown:
            if self._notice_on is not None:  # it spoke of a subject (or page) no longer on screen
                self._notice = ("saved", "")
            self._notice_on = shown
        kind, message = self.notice
        self.hud_lines = [(status, COLORS["text"]), (detail, COLORS["dim"]), (message, NOTICE_COLORS[kind]),
                          (keys, (150, 150, 150))]
        size = text_size(h)
        key = (w, h, tuple(self.hud_lines))
        if key != self._hud_key:  # the same text (the help toggled, a move in 3D) is not drawn or uploaded again
            self._hud_pixels = to_vtk_order(draw_hud(w, hud_height(h), self.hud_lines, size))
            self._hud_key = key
        self._hud.show(self._hud_pixels, 0, 0, h)
        if self.show_help and self._help_size != (w, h):
            panel = help_panel(w, h)
            self._help_panel = to_vtk_order(panel)
            self._help_size = (w, h)
            self._help_origin = (max(0, (w - panel.width) // 2), max(0, (h - panel.height) // 2))
        if self.show_help:
            self._help.show(self._help_panel, *self._help_origin, h)
        else:
            self._help.hide()

    def _render(self):
        if not self._deferred:
            self.window.render()

    # -- keys ---------------------------------------------------------------------------------------
    def _bind_keys(self):
        bindings = {"g": self.key_good, "s": self.key_skip, "n": self.key_next, "Right": self.key_right,
                    "p": self.key_previous, "Left": self.key_left, "u": self.next_unreviewed, "z": self.undo,
                    "v": self.toggle_3d, "t": self.toggle_triage, "h": self.toggle_help, "question": self.toggle_help,
                    "Up": self.key_up, "Down": self.key_down, "Return": self.commit_page, "KP_Enter": self.commit_page,
                    "space": self.key_space, "c": self.cycle_triage_view, "Next": lambda: self.turn_page(+1),
                    "Prior": lambda: self.turn_page(-1), "r": self.reframe_3d, "Escape": self.key_escape}
        for k, reason in REASON_KEYS.items():
            bindings[k] = (lambda r=reason: self.key_bad(r))
        self.window.bind({key: self._guarded(key, fn) for key, fn in bindings.items()})
        self.window.observe("LeftButtonPressEvent", self._on_click)
        self.window.observe("ConfigureEvent", self._on_resize)

    def _guarded(self, key: str, fn):
        """A key handler whose one-line errors (an unreadable subject) become the heads-up notice."""
        def handler():
            if key != "Escape":
                self.quit_armed = False
            try:
                fn()
            except UserError as e:
                self.notice = ("error", str(e))
                self.refresh()
        return handler

    def press(self, key: str):
        """Deliver a key as the window would; used by tests and scripts."""
        self.window.press(key)

    def click(self, x: int, y: int):
        """A left click at display pixel (x, y from the top), as the window would deliver it."""
        self.window.click(x, y)

    def cell_center(self, i: int) -> tuple[int, int]:
        """Display pixel (x, y from the top) at the middle of cell ``i`` of the grid on screen."""
        x0, y0, x1, y1 = self._layout.image_box(i)
        return (x0 + x1) // 2, (y0 + y1) // 2

    def key_good(self):
        if self.mode == "triage":
            self._set_pending(("good", ()))
        else:
            self.verdict("good")

    def key_bad(self, reason):
        if self.mode == "triage":
            self._set_pending(("bad", (reason,)))
        else:
            self.verdict("bad", (reason,))

    def key_skip(self):
        if self.mode != "triage":
            self.verdict("skip")

    def key_right(self):
        self._move_cursor(1) if self.mode == "triage" else self.next()

    def key_left(self):
        self._move_cursor(-1) if self.mode == "triage" else self.previous()

    def key_next(self):
        self.turn_page(+1) if self.mode == "triage" else self.next()

    def key_previous(self):
        self.turn_page(-1) if self.mode == "triage" else self.previous()

    def key_up(self):
        if self.mode == "triage":
            self._move_cursor(-self.session.triage_shape[1])

    def key_down(self):
        if self.mode == "triage":
            self._move_cursor(self.session.triage_shape[1])

    def key_space(self):
        if self.mode == "triage":
            self._flip(self.triage_cursor)

    def key_escape(self):
        if self.show_help:
            self.toggle_help()
            return
        if self.pending and not self.quit_armed:
            self.quit_armed = True
            self.notice = ("warn", f"{len(self.pending)} triage change(s) not committed: Return commits a page; "
                                   "Escape again quits without them")
            self.refresh()
            return
        self.close()

    def toggle_help(self):
        self.show_help = not self.show_help
        self.refresh()

    def refresh(self):
        """Redraw the heads-up text (and in triage the page) for the current state."""
        if self.mode == "triage":
            self._draw_triage()
        else:
            self._draw_text(*self.status_text(), VIEW3D_KEYS if self.mode == "3d" else REVIEW_KEYS)
            self._render()

    # -- review mode ----------------------------------------------------------------------------------
    def verdict(self, action: str, reasons=()):
        """The verdict of the subject shown (in review or 3D), then the next subject's views."""
        pos = self.pos
        self.notice = self.session.verdict(action, reasons)
        if self.pos != pos:
            self.goto(self.pos)
        else:
            self.refresh()

    def undo(self):
        self.notice, where = self.session.undo()
        if where is None:   # nothing undone: the view stays as it is (the 3D view too), with the notice
            self.refresh()
        elif self.mode == "triage":
            page = self.triage_page
            self.session.point_at(where)
            if page != self.triage_page:
                self.show_triage_page()
            else:
                self._draw_triage(cells=[self.triage_cursor])  # the cell shows its verdict as it is now
        else:
            self.goto(where)

    def next(self):
        self.goto(min(self.pos + 1, len(self.queue) - 1))

    def previous(self):
        self.goto(max(self.pos - 1, 0))

    def next_unreviewed(self):
        if self.mode == "triage":
            return
        notice = self.session.next_unreviewed()
        if notice is None:
            self.goto(self.pos)
        else:
            self.notice = notice     # none other: the subject (or its 3D view) stays, with the notice
            self.refresh()

    def goto(self, pos: int):
        self.session.pos = pos
        if self.mode == "3d":
            self._leave_3d()
        if self.mode == "review":
            self.show_subject()

    def _review_frame(self, item: QueueItem, size: tuple[int, int]):
        return review_frame(self.reader, item, size, self.columns)

    def show_subject(self):
        size = self.window_size()
        item = self.session.item
        frame = self.frames.get((item.subject, size), lambda: self._review_frame(item, size))
        self._layout = frame.layout
        self._current_frame = frame
        self._show_canvas(frame.pixels)
        self._cursor.hide()
        if frame.error:
            self.notice = ("error", frame.error)
        self.refresh()
        ahead = [self.queue[p] for p in (self.pos + 1, self.pos + 2, self.pos - 1) if 0 <= p < len(self.queue)]
        work = [((it.subject, size), (lambda it=it: self._review_frame(it, size))) for it in ahead]
        if frame.meta is not None:  # this subject's 3D surface, once the next two are ready and the
            # reviewer has stayed a while (most subjects are never seen in 3D; v makes it at once)
            work.insert(2, (("surface", item.subject), lambda: self._surface_of(item, frame), SURFACE_AFTER_S))
        self.frames.want(work)

    def status_text(self) -> tuple[str, str]:
        """The heads-up block's first two lines in review and 3D mode."""
        return self.session.status_lines(view3d=self._surface_source if self.mode == "3d" else None)

    def _on_resize(self) -> bool:
        """Lay the window out again when its size changed; True when it did (and was drawn)."""
        if self._layout is not None and self.window_size() != (self._layout.width, self._layout.height):
            if self.mode == "review":
                self.show_subject()
            elif self.mode == "triage":
                self.show_triage_page()
            else:
                self.refresh()
            return True
        return False

    # -- 3D view ----------------------------------------------------------------------------------------
    def toggle_3d(self):
        if self.mode == "triage":
            return
        if self.mode == "3d":
            self._leave_3d()
            self.show_subject()
            return
        frame = self._current_frame
        if frame.meta is None:
            self.notice = ("error", f"no 3D view: {frame.error}")
            self.refresh()
            return
        item = self.session.item
        arrays, source = self.frames.get(("surface", item.subject), lambda: self._surface_of(item, frame))
        if arrays is None:
            self.notice = ("warn", f"{item.subject}: no view has a depth inside its mask; nothing to show in 3D")
            self.refresh()
            return
        mesh = polydata(*arrays)
        self._grid.hide()
        self._surface = surface_actor(self.window.plotter, mesh)
        self._surface_bounds = mesh.bounds
        self._surface_source = source
        self.window.set_style("3d")
        self.mode = "3d"
        self.reframe_3d()

    def _surface_of(self, item: QueueItem, frame):
        return subject_surface(self.reader, item, frame.meta, frame.views)

    def reframe_3d(self):
        """Look at the head from the front (+z), the whole surface in view."""
        if self.mode != "3d":
            return
        frame_front(self.window.plotter, self._surface_bounds)
        self.refresh()

    def _leave_3d(self):
        if self._surface is not None:
            self.window.plotter.remove_actor(self._surface, reset_camera=False, render=False)
        self._surface = None
        self.window.set_style("grid")
        self.mode = "review"

    # -- triage mode ------------------------------------------------------------------------------------
    def toggle_triage(self):
        if self.mode == "triage":
            self.session.leave_triage()
            self.mode = "review"
            self._cursor.hide()
            self.show_subject()
            return
        if self.mode == "3d":
            self._leave_3d()
        self.mode = "triage"
        self.session.point_at(self.pos)
        self.show_triage_page()

    def _triage_layout(self) -> Layout:
        w, h = self.window_size()
        return Layout.fit(w, h, self.session.page_size, self.session.triage_shape[1], 2)

    def _page_key(self, page: int, layout: Layout):
        return page, self.triage_yaw, layout

    def show_triage_page(self):
        layout = self._triage_layout()
        self._layout = layout
        yaw = TRIAGE_YAWS[self.triage_yaw]
        page = self.triage_page
        self._page = self.thumbs.get(self._page_key(page, layout), lambda: self._triage_page(page, yaw, layout))
        self._page_thumbs = self._page.thumbs
        self.session.move_cursor(0)  # on a cell of this page
        # only the cells that changed since the page was drawn (a verdict undone, a change made on it)
        self._draw_triage(cells=range(len(self.session.page_items())), shown=False)
        ahead = [p for p in (page + 1, page - 1) if 0 <= p < self.session.n_pages]
        self.thumbs.want([(self._page_key(p, layout), (lambda p=p: self._triage_page(p, yaw, layout)))
                          for p in ahead])

    def _triage_page(self, page: int, yaw: float, layout: Layout):
        return triage_page(self.reader, self.session, page, yaw, layout)

    def cell_state(self, item: QueueItem):
        """(lines of text, frame) of a triage cell: saved verdict, change not committed, pre-flags."""
        return cell_state(self.session, item)

    def _draw_triage(self, cells=(), shown: bool = True):
        """Draw the page's ``cells`` whose state changed (all of them when the page is not on screen yet,
        ``shown`` False), then the cursor and the heads-up text."""
        layout, page = self._layout, self._page
        if page.update(self.session, layout, cells) or not shown:
            self._show_canvas(page.pixels)
        sx, sy = layout.slot(self.triage_cursor)
        self._cursor.show((sx + 2, sy - 2, sx + layout.slot_w - 3, sy + layout.slot_h - 3), layout.height)
        status, detail = self.session.triage_lines(TRIAGE_YAWS[self.triage_yaw])
        self._draw_text(status, detail, TRIAGE_KEYS)
        self._render()

    def _set_pending(self, change: tuple[str, tuple]):
        """A change to the cell under the cursor (see :meth:`ReviewSession.set_pending`)."""
        self.session.set_pending(self.session.cursor_item(), change)
        self._draw_triage(cells=[self.triage_cursor])

    def _flip(self, i: int):
        self.session.flip(i)
        self._draw_triage(cells=[i])

    def _move_cursor(self, step: int):
        self.session.move_cursor(step)
        self._draw_triage()

    def turn_page(self, step: int):
        """Show the next (+1) or previous (-1) triage page; changes stay where they were made."""
        if self.mode != "triage":
            return
        if self.session.turn_page(step):
            self.show_triage_page()
        else:
            self.notice = ("warn", f"this is the {'last' if step > 0 else 'first'} page")
            self._draw_triage()

    def cycle_triage_view(self):
        if self.mode == "triage":
            self.triage_yaw = (self.triage_yaw + 1) % len(TRIAGE_YAWS)
            self.show_triage_page()

    def commit_page(self):
        """Write the page's changes and good for its cells without a verdict; nothing else."""
        if self.mode != "triage":
            return
        page = self.triage_page
        self.notice = self.session.commit_page()
        if self.triage_page != page:
            self.show_triage_page()
        else:
            self._draw_triage(cells=range(len(self.session.page_items())))

    def _on_click(self):
        if self.mode != "triage":
            return
        x, y = self.window.event_position()
        i = self._layout.index_at(x, self._layout.height - 1 - y)
        if i is not None and i < len(self.session.page_items()):
            self.quit_armed = False
            self.session.triage_cursor = i
            self._flip(i)

    # -- lifecycle ------------------------------------------------------------------------------------
    def screenshot(self, path=None) -> np.ndarray:
        """The window's pixels (H, W, 3) uint8; also saved as PNG at ``path`` when given."""
        img = self.window.screenshot()
        if path is not None:
            Image.fromarray(img).save(path)
        return img

    def run(self):
        """Open the window and hand control to the reviewer until the window is closed or Escape."""
        self._deferred = False
        self.window.show()      # the first frame, everything in place
        self._on_resize()       # drawn again only when the window did not come out at the size asked
        self.window.loop(self.display)
        self.close()

    def close(self):
        if getattr(self, "window", None) is None:
            return
        self.frames.close()
        self.thumbs.close()
        self.session.close()
        self.window.close()
        self.window = None
        if self.display is not None:
            self.display.close()
