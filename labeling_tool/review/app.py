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
from datagen.dataset.events import REASONS

from .layout import (COLORS, NOTICE_COLORS, draw_hud, help_panel, hud_height, review_frame, text_size,
                     to_vtk_order)
from .modes import GridMode, SurfaceMode, TriageMode
from .prefetch import Prefetcher
from .reader import SubjectReader
from .session import TRIAGE_SHAPE, QueueItem, ReviewSession
from .window import OFF_SCREEN_SIZE, ImageLayer, Outline, Window, XDisplay, fit_window


def _session_state(name: str) -> property:
    return property(lambda self: getattr(self.session, name), doc=f"The session's {name} (read only).")


class ReviewApp:
    """The window of one review session (:class:`ReviewSession`) over a queue of subjects for one reviewer:
    its layers, the heads-up block, the keys, and the mode on screen (:mod:`.modes`)."""

    queue, log, pos, done, skipped, pending, triage_page, triage_cursor = map(
        _session_state, ("queue", "log", "pos", "done", "skipped", "pending", "triage_page", "triage_cursor"))
    reason_keys = {str(i + 1): r for i, r in enumerate(REASONS)}

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
        self.show_help = False
        self.notice = self.session.resume_notice()
        self.quit_armed = False
        self.layout = None           # the layout of the grid on screen
        self.current_frame = None    # the subject's grid on screen (ReviewFrame)
        # a window on a display draws its first frame in run(), once, with everything in place (each
        # frame before it would cost the start-up a full frame of software OpenGL)
        self._deferred = not off_screen
        self._make_layers()
        self.grid, self.surface, self.triage = GridMode(self), SurfaceMode(self), TriageMode(self)
        self.current = self.grid
        self._bind_keys()
        if start_in_triage:
            self.triage.open()
        else:
            self.grid.show()

    @property
    def mode(self) -> str:
        """The mode on screen: "review", "3d" or "triage"."""
        return self.current.name

    def enter(self, mode):
        """Make ``mode`` the one on screen, taking down the one that was."""
        if mode is not self.current:
            self.current.leave()
            self.current = mode

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

    # -- layers ---------------------------------------------------------------------------------------
    def _make_layers(self):
        """Three 2D images (the grid, the heads-up block, the help panel) and the triage cursor."""
        plotter = self.window.plotter
        self.grid_layer = ImageLayer(plotter)
        self.cursor = Outline(plotter, COLORS["cursor"], 3)
        self._hud = ImageLayer(plotter)
        self.help_layer = ImageLayer(plotter)
        self._help_size = None
        self._hud_key = self._hud_pixels = None

    def window_size(self) -> tuple[int, int]:
        return self.window.size()

    @property
    def closed(self) -> bool:
        return self.window is None

    def show_canvas(self, pixels: np.ndarray):
        """Put a canvas (H, W, 3 rows bottom-up) on screen as the window's grid."""
        self.grid_layer.show(pixels, 0, 0, self.window_size()[1])

    def draw_text(self, status: str, detail: str, keys: str):
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
            self.help_origin = (max(0, (w - panel.width) // 2), max(0, (h - panel.height) // 2))
        if self.show_help:
            self.help_layer.show(self._help_panel, *self.help_origin, h)
        else:
            self.help_layer.hide()

    def render(self):
        if not self._deferred:
            self.window.render()

    def status_text(self) -> tuple[str, str]:
        """The heads-up block's first two lines in review and 3D mode."""
        return self.session.status_lines(view3d=self.surface.source if self.mode == "3d" else None)

    # -- keys ---------------------------------------------------------------------------------------
    def _bind_keys(self):
        everywhere = {"z": self.undo, "h": self.toggle_help, "question": self.toggle_help, "Escape": self.key_escape}
        names = set(everywhere).union(*(m.bindings for m in (self.grid, self.surface, self.triage)))
        self.window.bind({key: self._guarded(key, everywhere.get(key)) for key in names})
        self.window.observe("LeftButtonPressEvent", self._on_click)
        self.window.observe("ConfigureEvent", self._on_resize)

    def _guarded(self, key: str, everywhere):
        """The handler of ``key``: the mode's action for it (or one of every mode's); its one-line errors
        (an unreadable subject) become the heads-up notice."""
        def handler():
            if key != "Escape":
                self.quit_armed = False
            action = everywhere or self.current.bindings.get(key)
            if action is None:
                return
            try:
                action()
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
        x0, y0, x1, y1 = self.layout.image_box(i)
        return (x0 + x1) // 2, (y0 + y1) // 2

    def cell_state(self, item: QueueItem):
        """(lines of text, frame) of a triage cell: saved verdict, change not committed, pre-flags."""
        return self.triage.cell_state(item)

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
        self.current.refresh()

    # -- moving through the queue (the grid and the 3D view) ----------------------------------------------
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
        else:
            self.current.show_undone(where)

    def next(self):
        self.goto(min(self.pos + 1, len(self.queue) - 1))

    def previous(self):
        self.goto(max(self.pos - 1, 0))

    def next_unreviewed(self):
        notice = self.session.next_unreviewed()
        if notice is None:
            self.goto(self.pos)
        else:
            self.notice = notice     # none other: the subject (or its 3D view) stays, with the notice
            self.refresh()

    def goto(self, pos: int):
        """Show the views of the subject at ``pos`` (leaving the 3D view)."""
        self.session.pos = pos
        self.enter(self.grid)
        self.grid.show()

    def _on_resize(self) -> bool:
        """Lay the window out again when its size changed; True when it did (and was drawn)."""
        if self.layout is not None and self.window_size() != (self.layout.width, self.layout.height):
            self.current.show()
            return True
        return False

    def _on_click(self):
        if self.mode == "triage":
            self.triage.clicked(*self.window.event_position())

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
