"""The review window (VTK): one subject's views as a grid, a triage grid of many subjects, a 3D surface.

Review mode shows every view of one subject, each labelled with its yaw and pitch, under a
heads-up block (subject, progress, verdict, pre-flags, the confirmation of the last action, the
keys). Triage mode shows one view of 40 subjects; each cell carries the subject id, its saved
verdict, its pre-flags and the change the reviewer made to it on this visit. The 3D view is an
occluding surface built from every view's depth and mask (so a face painted on the back of a head
is seen only from behind), framed on the head.

Every verdict is appended to the reviewer's event log (flushed and fsynced) as it is made, so
closing or killing the window loses nothing; reopening resumes at the first subject not reviewed.
A verdict equal to the saved one writes nothing. Reviewed means good or bad: a skip is "decide
later", so a skipped subject stays unreviewed (in the counts, for ``u`` and where a session
resumes), as ``compile`` counts it.

Triage commit (Return) writes exactly: the changes made on that page (a cell marked bad with a
reason, or a saved verdict flipped to good) and good for cells that had no verdict yet; cells with
a saved verdict that were not touched keep it (a skipped one stays skipped, for later). A page
without anything to write writes nothing and says so. Changes wait, per cell, until their page is
committed; pages can be left and revisited without committing, and quitting with changes not
committed asks for a second Escape.

The grid is drawn as one image at the window's pixel size (composed with Pillow; the next subjects
and the next triage pages, cells and all, in a background thread), shown as a texture that is
uploaded once per image. A key costs at most one texture upload, the heads-up text (its lines are
cached) and one frame; a window on a display draws the frame straight into its back buffer
(colour only). The window runs its own event loop so that the background thread gets the
interpreter while the window waits for keys.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import select
import tarfile
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from vtkmodules import vtkRenderingOpenGL2
from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData
from vtkmodules.vtkInteractionStyle import vtkInteractorStyleTrackballCamera, vtkInteractorStyleUser
from vtkmodules.vtkRenderingCore import (vtkActor, vtkActor2D, vtkPolyDataMapper, vtkPolyDataMapper2D, vtkRenderer,
                                         vtkRenderWindow, vtkRenderWindowInteractor, vtkTexture, vtkTexturedActor2D,
                                         vtkWindowToImageFilter)
from vtkmodules.vtkRenderingUI import vtkGenericRenderWindowInteractor

from datagen.errors import DatasetError, UserError
from datagen.events import REASONS, EventLog, is_decision
from datagen.shards import decode_exr, decode_png, read_sidecar, tar_path

# imported for what it registers: the OpenGL window behind vtkRenderWindow (vtkRenderingUI registers
# the X interactor behind vtkRenderWindowInteractor)
VTK_BACKENDS = (vtkRenderingOpenGL2,)
REASON_KEYS = {str(i + 1): r for i, r in enumerate(REASONS)}
REASON_SHORT = {"multiple_faces": "faces", "broken_back": "back", "artifacts": "artifacts", "blur": "blur",
                "other": "other"}
# the reason a triage click or space gives a cell, from its strongest pre-flag (labeling_tool.preflags)
FLAG_REASON = {"janus": "multiple_faces", "holes": "broken_back", "flat_back": "broken_back", "seam": "broken_back",
               "floaters": "artifacts", "haze": "artifacts", "washed_out": "artifacts", "blur": "blur",
               "blurry_back": "blur", "empty": "other", "implausible": "other", "duplicate": "other"}
DEFAULT_REASON = "artifacts"
TRIAGE_SHAPE = (5, 8)                     # rows, columns of a triage page
TRIAGE_YAWS = (0.0, 180.0, 90.0, 270.0)   # the view shown in triage: front, back, left, right (c cycles)
OFF_SCREEN_SIZE = (1600, 900)
SURFACE_AFTER_S = 1.0                     # a subject's 3D surface is made ahead once shown this long
HUD_LINES = ("status", "detail", "notice", "keys")  # the heads-up block, top to bottom
BACKGROUND = (32, 32, 32)
COLORS = {"good": (60, 200, 90), "bad": (235, 60, 50), "skip": (150, 150, 150), "cursor": (255, 220, 0),
          "text": (235, 235, 235), "dim": (165, 165, 165)}
NOTICE_COLORS = {"saved": (110, 255, 110), "undo": (100, 215, 255), "warn": (255, 180, 50), "error": (255, 100, 100)}
REVIEW_KEYS = ("g good   1 faces  2 back  3 artifacts  4 blur  5 other   s skip   Left/Right move   "
               "u next unreviewed   z undo   v 3D   t triage   h help   Esc quit")
TRIAGE_KEYS = ("arrows move   1-5 bad (reason)   g good   space/click flip   Return commit page   "
               "n/p or PgDn/PgUp page   c view   z undo   t review   h help")
VIEW3D_KEYS = ("3D surface: drag rotates   shift+drag pans   wheel or right-drag zooms   r re-frames   "
               "v back to the views   Left/Right other subject")
HELP = [  # (keys, what they do); a row without a description is a heading
    ("REVIEW: one subject, all its views", None),
    ("g", "good"),
    ("1 2 3 4 5", "bad: 1 multiple faces, 2 broken back, 3 artifacts, 4 blur, 5 other"),
    ("s", "skip: decide later (the subject stays unreviewed; u comes back to it)"),
    ("Right / n,  Left / p", "next subject, previous subject"),
    ("u", "next unreviewed subject (no verdict yet, or skipped)"),
    ("z", "undo the latest verdict (written as an undo event)"),
    ("v", "3D surface from the views' depth and masks: drag turns it, wheel zooms, r re-frames"),
    ("t", "triage mode"),
    ("TRIAGE: 40 subjects, one view each", None),
    ("arrows", "move the yellow cursor"),
    ("1 2 3 4 5,  g", "mark the cell bad with that reason, or good (the cursor stays)"),
    ("space / click", "flip the cell: bad with its pre-flag's reason, or good; again takes it back"),
    ("Return", "commit the page: your changes, and good for cells without a verdict;"),
    ("", "cells that had a verdict and were not touched keep it; nothing is written twice"),
    ("n / PgDn,  p / PgUp", "next page, previous page (changes wait on their page until committed)"),
    ("c", "show another view: front, back, left, right"),
    ("z,  t", "undo the latest verdict, back to review"),
    ("ANYWHERE", None),
    ("h / ?", "this help"),
    ("Escape", "close the help, or quit (every verdict is already saved)"),
]


@dataclass
class QueueItem:
    subject: str
    shard: str
    score: float | None = None
    flags: tuple = ()  # ((detector, score), ...) of the detectors that flag the subject, strongest first

    @property
    def default_reason(self) -> str:
        """The reason a triage flip gives this subject: its strongest pre-flag's."""
        return FLAG_REASON.get(self.flags[0][0], DEFAULT_REASON) if self.flags else DEFAULT_REASON

    def flags_text(self) -> str:
        return ", ".join(f"{name} {score:.2f}" for name, score in self.flags)


def verdict_text(action: str | None, reasons=()) -> str:
    if action is None:
        return "none"
    return f"{action}: {', '.join(REASON_SHORT.get(r, r) for r in reasons)}" if reasons else action


# ------------------------------------------------------------------------------------------------
# The X display


class XDisplay:
    """A connection to the X display named by $DISPLAY, kept open while the window lives (so that an
    Xvfb serving only this program does not reset between our check and VTK's own connection)."""

    def __init__(self):
        name = os.environ.get("DISPLAY")
        if not name:
            raise UserError("no display: $DISPLAY is not set; run it on a desktop, under xvfb-run, or with "
                            "--off-screen --keys ... for a scripted session")
        self.lib = None
        self.handle = None
        found = ctypes.util.find_library("X11")
        if found is None:  # cannot check; VTK will say whether it can open the display
            return
        self.lib = ctypes.CDLL(found)
        self.lib.XOpenDisplay.restype = ctypes.c_void_p
        self.lib.XOpenDisplay.argtypes = [ctypes.c_char_p]
        for fn in ("XDefaultScreen", "XCloseDisplay", "XConnectionNumber"):
            getattr(self.lib, fn).argtypes = [ctypes.c_void_p]
        for fn in ("XDisplayWidth", "XDisplayHeight"):
            getattr(self.lib, fn).argtypes = [ctypes.c_void_p, ctypes.c_int]
        self.lib.XQueryExtension.argtypes = [ctypes.c_void_p, ctypes.c_char_p] + [ctypes.POINTER(ctypes.c_int)] * 3
        self.handle = self.lib.XOpenDisplay(name.encode())
        if not self.handle:
            raise UserError(f"cannot open the X display {name!r} (is the X server or Xvfb running?); "
                            "use --off-screen for a scripted session")
        opcode, event, error = ctypes.c_int(), ctypes.c_int(), ctypes.c_int()
        if not self.lib.XQueryExtension(self.handle, b"GLX", ctypes.byref(opcode), ctypes.byref(event),
                                        ctypes.byref(error)):
            self.close()  # said here in one line, before VTK tries (and warns) and before anything is created
            raise UserError(f"the X display {name!r} has no OpenGL (GLX), so VTK cannot open a window on it; "
                            "use --off-screen for a scripted session")

    def screen_size(self) -> tuple[int, int] | None:
        if not self.handle:
            return None
        screen = self.lib.XDefaultScreen(self.handle)
        return self.lib.XDisplayWidth(self.handle, screen), self.lib.XDisplayHeight(self.handle, screen)

    def close(self):
        if self.handle:
            self.lib.XCloseDisplay(self.handle)
            self.handle = None


def fit_window(screen: tuple[int, int] | None) -> tuple[int, int]:
    """The default window size: most of the screen, leaving room for panels and decorations."""
    if screen is None:
        return OFF_SCREEN_SIZE
    w, h = screen
    return max(640, int(w * 0.96)) // 2 * 2, max(400, int(h * 0.9)) // 2 * 2


class Window:
    """A VTK render window with its renderer and interactor, in plain VTK (no pyvista, which would
    import matplotlib: seconds of start-up). Off-screen without a display it renders with EGL (no X
    attempted, no X warnings); on screen it needs an X-backed window (one line otherwise)."""

    def __init__(self, off_screen: bool, size, title: str):
        kind = "VTK_DEFAULT_OPENGL_WINDOW"
        before = os.environ.get(kind)
        if off_screen and not os.environ.get("DISPLAY"):
            os.environ.setdefault(kind, "vtkEGLRenderWindow")
        elif not off_screen and before and "X" not in before:
            os.environ.pop(kind)  # a window needs X, whatever off-screen default is set
        try:
            self.render_window = vtkRenderWindow()  # the class is chosen here, from the environment
        finally:
            if before is None:
                os.environ.pop(kind, None)
            else:
                os.environ[kind] = before
        made = type(self.render_window).__name__
        if not off_screen and "X" not in made:
            raise UserError(f"VTK could not open a window on the display {os.environ.get('DISPLAY')!r} (it made a "
                            f"{made}); use --off-screen for a scripted session")
        self.off_screen = off_screen
        self.render_window.SetSize(*size)
        self.render_window.SetWindowName(title)
        self.render_window.SetMultiSamples(0)  # multisampling costs software OpenGL several frames' time
        if not off_screen and hasattr(self.render_window, "SetFrameBlitModeToBlitToCurrent"):
            # the frame goes from VTK's framebuffer straight to the window's back buffer, colour only: the
            # default also copies colour and depth through a second framebuffer, which doubles the cost
            # of every frame under software OpenGL (Xvfb, remote desktops)
            self.render_window.SetFrameBlitModeToBlitToCurrent()
        self.render_window.SetOffScreenRendering(bool(off_screen))
        self.renderer = vtkRenderer()
        self.renderer.SetBackground(*[c / 255 for c in BACKGROUND])
        self.render_window.AddRenderer(self.renderer)
        self.interactor = vtkGenericRenderWindowInteractor() if off_screen else vtkRenderWindowInteractor()
        self.interactor.SetRenderWindow(self.render_window)
        self.keys: dict = {}
        self.interactor.AddObserver("KeyPressEvent", lambda *_: self._on_key())

    def _on_key(self):
        fn = self.keys.get(self.interactor.GetKeySym())
        if fn is not None:
            fn()

    def size(self) -> tuple[int, int]:
        w, h = self.render_window.GetSize()
        return int(w), int(h)

    def render(self):
        self.render_window.Render()

    def show(self):
        """Get the window ready for events (it is mapped and drawn by the first frame rendered)."""
        self.interactor.Initialize()

    def screenshot(self) -> np.ndarray:
        """The window's pixels (H, W, 3) uint8, top row first."""
        grab = vtkWindowToImageFilter()
        grab.SetInput(self.render_window)
        grab.SetInputBufferTypeToRGB()
        grab.ReadFrontBufferOff()
        grab.Update()
        image = grab.GetOutput()
        w, h, _ = image.GetDimensions()
        return vtk_to_numpy(image.GetPointData().GetScalars()).reshape(h, w, 3)[::-1].copy()

    def close(self):
        self.render_window.Finalize()
        self.interactor.TerminateApp()
        self.render_window = self.renderer = self.interactor = None


# ------------------------------------------------------------------------------------------------
# Reading subjects: only the members asked for, by their byte ranges


class SubjectReader:
    """Reads single members of a subject's tar sample (through the sidecar's byte ranges and the tar
    headers, never the whole sample). Thread-safe."""

    def __init__(self, root, cache_subjects: int = 4096):
        self.root = root
        self._sidecars: dict = {}
        self._members: OrderedDict = OrderedDict()
        self._cache_subjects = cache_subjects
        self._lock = threading.Lock()

    def _sidecar(self, shard: int) -> dict:
        with self._lock:
            side = self._sidecars.get(shard)
        if side is None:
            side = read_sidecar(self.root, shard)
            if side is None:
                raise DatasetError(f"{tar_path(self.root, shard)}: incomplete shard (no sidecar)")
            with self._lock:
                self._sidecars[shard] = side
        return side

    def members(self, item: QueueItem) -> dict:
        """{field: (offset, size)} of the subject's members in its shard."""
        with self._lock:
            if item.subject in self._members:
                self._members.move_to_end(item.subject)
                return self._members[item.subject]
        shard = int(item.shard.split("-")[1])
        path = tar_path(self.root, shard)
        try:
            start, end = self._sidecar(shard)["offsets"][item.subject]
        except KeyError:
            raise DatasetError(f"{path}: no subject {item.subject} in this shard") from None
        table = {}
        try:
            with open(path, "rb") as f:
                f.seek(start)
                with tarfile.open(fileobj=f, mode="r:") as tar:
                    for m in tar:
                        if m.offset >= end:
                            break
                        if m.isfile():
                            table[m.name.partition(".")[2]] = (m.offset_data, m.size)
        except (tarfile.TarError, EOFError, OSError) as e:
            raise DatasetError(f"{path}: corrupt subject {item.subject} ({e})") from None
        with self._lock:
            self._members[item.subject] = table
            while len(self._members) > self._cache_subjects:
                self._members.popitem(last=False)
        return table

    def read(self, item: QueueItem, fields) -> dict:
        """{field: bytes} for the fields asked for."""
        table = self.members(item)
        path = tar_path(self.root, int(item.shard.split("-")[1]))
        out = {}
        try:
            with open(path, "rb") as f:
                for field in fields:
                    if field not in table:
                        raise DatasetError(f"{path}: subject {item.subject} lacks field {field}")
                    offset, size = table[field]
                    f.seek(offset)
                    out[field] = f.read(size)
        except OSError as e:
            raise DatasetError(f"{path}: cannot read subject {item.subject} ({e.strerror})") from None
        return out

    def metadata(self, item: QueueItem) -> dict:
        try:
            return json.loads(self.read(item, ["json"])["json"])
        except ValueError as e:
            raise DatasetError(f"{item.shard}: subject {item.subject} has unreadable metadata ({e})") from None


def nearest_view(views: list[dict], yaw: float) -> int:
    """Index of the view closest to ``yaw`` (degrees) on the equator."""
    d = [abs((v["yaw_deg"] - yaw + 180) % 360 - 180) + abs(v["pitch_deg"]) for v in views]
    return int(np.argmin(d))


def decode_image(data: bytes, where: str) -> np.ndarray:
    try:
        return decode_png(data)
    except Exception as e:  # a decoder's own error: say which subject
        raise DatasetError(f"{where}: image does not decode ({type(e).__name__}: {e})") from None


def fit_square(img: np.ndarray, side: int) -> np.ndarray:
    """``img`` (H, W, 3) uint8 resized to (side, side, 3)."""
    if img.shape[0] == side and img.shape[1] == side:
        return img
    return np.asarray(Image.fromarray(img).resize((side, side), Image.BILINEAR, reducing_gap=2.0))


# ------------------------------------------------------------------------------------------------
# Layout and drawing of the grids (pure functions of pixels; safe in the background thread)


@lru_cache(maxsize=8)
def font(size: int) -> ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=size)


def text_size(height: int) -> int:
    """Font size (px) for a window ``height`` px tall."""
    return int(min(20, max(12, height // 62)))


@dataclass(frozen=True)
class Layout:
    """Where the cells of a grid sit in a window (display pixels, origin top-left).

    Each cell is a square image of ``cell`` px in a slot of ``slot_w`` x ``slot_h`` px, with
    ``label_lines`` lines of text under the image.
    """

    width: int
    height: int
    columns: int
    rows: int
    top: int
    cell: int
    slot_w: int
    slot_h: int
    left: int
    label_lines: int
    font: int
    label_font: int

    @classmethod
    def fit(cls, width: int, height: int, n: int, columns: int, label_lines: int) -> "Layout":
        size = text_size(height)
        top = hud_height(height)
        rows = max(1, -(-n // columns))
        slot_w = max(24, (width - 16) // columns)
        slot_h = max(24, (height - top - 8) // rows)
        label_font = max(11, size - 3)
        label_h = label_lines * (label_font + 3) + 4
        cell = max(8, min(slot_w - 10, slot_h - label_h - 8))
        return cls(width, height, columns, rows, top, cell, slot_w, slot_h, (width - columns * slot_w) // 2,
                   label_lines, size, label_font)

    def slot(self, i: int) -> tuple[int, int]:
        """Top-left corner of slot ``i``."""
        return self.left + (i % self.columns) * self.slot_w, self.top + (i // self.columns) * self.slot_h

    def image_box(self, i: int) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) of cell ``i``'s image."""
        sx, sy = self.slot(i)
        x0 = sx + (self.slot_w - self.cell) // 2
        return x0, sy + 4, x0 + self.cell, sy + 4 + self.cell

    def index_at(self, x: float, y: float) -> int | None:
        """The slot under display pixel (x, y from the top), or None."""
        c, r = int((x - self.left) // self.slot_w), int((y - self.top) // self.slot_h)
        if 0 <= c < self.columns and 0 <= r < self.rows and x >= self.left and y >= self.top:
            return r * self.columns + c
        return None


def blank_canvas(layout: Layout) -> Image.Image:
    return Image.new("RGB", (layout.width, layout.height), BACKGROUND)


def draw_cell(canvas: Image.Image, layout: Layout, i: int, img: np.ndarray | None, lines, frame=None) -> None:
    """Cell ``i``: its image (or a grey square), an optional frame (colour, width) and text lines
    [(text, colour), ...] under it."""
    x0, y0, x1, y1 = layout.image_box(i)
    draw = ImageDraw.Draw(canvas)
    sx, _ = layout.slot(i)
    draw.rectangle((sx + 1, y0 - 6, sx + layout.slot_w - 2, y1 + 3 + layout.label_lines * (layout.label_font + 3) + 2),
                   fill=BACKGROUND)
    if img is None:
        draw.rectangle((x0, y0, x1 - 1, y1 - 1), fill=(70, 70, 70))
    else:
        canvas.paste(Image.fromarray(img), (x0, y0))
    if frame is not None:
        color, width = frame
        draw.rectangle((x0 - width, y0 - width, x1 - 1 + width, y1 - 1 + width), outline=color, width=width)
    f = font(layout.label_font)
    for k, (text, color) in enumerate(lines):
        draw.text((sx + 6, y1 + 4 + k * (layout.label_font + 3)), fit_text(text, f, layout.slot_w - 10), fill=color,
                  font=f)


def fit_text(text: str, f, room: float) -> str:
    """``text`` cut (ending in '~') to fit ``room`` pixels in font ``f``."""
    if f.getlength(text) <= room:
        return text
    lo, hi = 0, len(text)  # the longest prefix that fits with its '~' (a binary search: few measurements)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if f.getlength(text[:mid] + "~") <= room:
            lo = mid
        else:
            hi = mid - 1
    return text[:lo] + "~"


@lru_cache(maxsize=512)
def text_line(text: str, color: tuple, size: int, width: int) -> Image.Image:
    """One line of the heads-up block as an image ``width`` px wide (cut to fit), on the background.
    Cached: most lines (the keys, the notice, the detail) come back key after key."""
    img = Image.new("RGB", (width, size + 6), BACKGROUND)
    f = font(size)
    ImageDraw.Draw(img).text((0, 0), fit_text(text, f, width), fill=color, font=f)
    return img


def hud_height(window_height: int) -> int:
    """Height (px) of the heads-up block at the top of a window."""
    return len(HUD_LINES) * (text_size(window_height) + 6) + 10


def draw_hud(width: int, height: int, lines, size: int) -> Image.Image:
    """The heads-up block: [(text, colour), ...] one per line, on the window's background."""
    img = Image.new("RGB", (width, height), BACKGROUND)
    for k, (text, color) in enumerate(lines):
        img.paste(text_line(text, tuple(color), size, width - 16), (8, 5 + k * (size + 6)))
    return img


def draw_help(size: int) -> Image.Image:
    """The help panel: keys and what they do, on an opaque dark box with a frame."""
    f, bold = font(size), font(size + 2)
    key_w = max(f.getlength(k) for k, what in HELP if what) + 2 * size
    text_w = max(f.getlength(what) if what else bold.getlength(k) for k, what in HELP)
    line = size + 7
    pad = 2 * size
    img = Image.new("RGB", (int(key_w + text_w + 2 * pad), len(HELP) * line + 2 * pad), (14, 14, 22))
    draw = ImageDraw.Draw(img)
    draw.rectangle((0, 0, img.width - 1, img.height - 1), outline=COLORS["cursor"], width=3)
    for k, (key, what) in enumerate(HELP):
        y = pad + k * line
        if what is None:
            draw.text((pad, y), key, fill=COLORS["cursor"], font=bold)
        else:
            draw.text((pad, y), key, fill=(255, 240, 190), font=f)
            draw.text((pad + key_w, y), what, fill=COLORS["text"], font=f)
    return img


class ImageLayer:
    """An RGB image (rows bottom-up) drawn at a place in the window, in display pixels.

    The image is a texture on a rectangle of its own size (nearest texel: pixel for pixel). The
    texture is uploaded once per image: a frame that does not change the image (another layer
    changed, the help panel was toggled) draws it from the texture already there. (vtkImageMapper,
    by contrast, converts and uploads its whole image at every frame.)
    """

    def __init__(self, renderer):
        self.texture = vtkTexture()
        self.texture.InterpolateOff()
        self.texture.RepeatOff()
        self.texture.EdgeClampOn()
        self.texture.SetColorModeToDirectScalars()
        self._corners = vtkPoints()
        for _ in range(4):
            self._corners.InsertNextPoint(0, 0, 0)
        tcoords = numpy_to_vtk(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32), deep=True)
        quad = vtkPolyData()
        quad.SetPoints(self._corners)
        cells = vtkCellArray()
        cells.InsertNextCell(4, [0, 1, 2, 3])
        quad.SetPolys(cells)
        quad.GetPointData().SetTCoords(tcoords)
        self._quad = quad
        self.mapper = vtkPolyDataMapper2D()
        self.mapper.SetInputData(quad)
        self.actor = vtkTexturedActor2D()
        self.actor.SetMapper(self.mapper)
        self.actor.SetTexture(self.texture)
        self.actor.SetVisibility(False)
        renderer.AddViewProp(self.actor)
        self.pixels = None  # kept alive: VTK reads this memory
        self.uploads = 0    # images handed to the texture (each is uploaded once, at the next frame)

    def show(self, pixels: np.ndarray, x: int, y_top: int, window_height: int):
        """Show ``pixels`` with its top-left corner at (x, y_top from the window's top)."""
        h, w, _ = pixels.shape
        if pixels is not self.pixels:
            image = vtkImageData()
            image.SetDimensions(w, h, 1)
            image.GetPointData().SetScalars(numpy_to_vtk(pixels.reshape(-1, 3), deep=False))
            if self.pixels is None or self.pixels.shape != pixels.shape:
                for k, (px, py) in enumerate(((0, 0), (w, 0), (w, h), (0, h))):
                    self._corners.SetPoint(k, px, py, 0)
                self._corners.Modified()
                self._quad.Modified()
            self.pixels = pixels
            self.texture.SetInputData(image)
            self.uploads += 1
        self.actor.SetPosition(x, window_height - y_top - h)
        self.actor.SetVisibility(True)

    def hide(self):
        self.actor.SetVisibility(False)

    def visible(self) -> bool:
        return bool(self.actor.GetVisibility())


def to_vtk_order(canvas: Image.Image) -> np.ndarray:
    """(H, W, 3) uint8 rows bottom-up, as vtkImageData wants them."""
    return np.ascontiguousarray(np.asarray(canvas)[::-1])


# ------------------------------------------------------------------------------------------------
# The 3D surface


def view_points(cam2world: np.ndarray, K: np.ndarray, resolution: int, rows: np.ndarray, cols: np.ndarray,
                depth: np.ndarray) -> np.ndarray:
    """World points (N, 3) at pixels (rows, cols) of a view with ``depth`` (distance along the ray).

    Rays go through pixel centres ((col + 0.5) / R, (row + 0.5) / R in normalized coordinates),
    OpenCV camera, normalized intrinsics with skew: the convention of :func:`datagen.cameras.rays`.
    """
    u, v = (cols + 0.5) / resolution, (rows + 0.5) / resolution
    fx, fy, cx, cy, sk = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    x = (u - cx + cy * sk / fy - sk * v / fy) / fx
    y = (v - cy) / fy
    d = np.stack([x, y, np.ones_like(x)], axis=-1) @ cam2world[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return cam2world[:3, 3] + depth[..., None] * d


def surface_mesh(views, max_grid: int = 80, slope: float = 2.0, min_facing: float = 0.2):
    """A triangle surface coloured by the images, from each view's depth and mask: (points (N, 3)
    float32, triangles (M, 3) int64, colours (N, 3) uint8), or None.

    ``views``: [(cam2world 4x4, K 3x3, rgb (h, w, 3) at any size, alpha (R, R), depth (R, R)), ...].
    Each view is sampled on a grid of at most ``max_grid`` pixels a side, away from its silhouette
    (whose depth and colour blend with the background); each cell of four neighbouring samples
    becomes two triangles. Both are dropped when the depths of the cell's corners differ by more than
    ``slope`` times the cell's size (the spacing of its samples at its depth): that is a depth
    discontinuity (glasses in front of the eyes, the side of the nose, an ear), not a surface, and
    meshing it stretches triangles across the gap, smeared with both sides' colours (the spikes
    around glasses, eyes and nose of a slope of 5, which let a jump of 5 cells through). A surface
    steeper than ~63 degrees (slope 2) is left to the views that see it less obliquely (32 views
    around the head), as are triangles facing the camera at a grazing angle (|cos| < ``min_facing``).
    The surfaces of all views occlude each other, so what is hidden from a direction stays hidden.
    None when no view has any surface. Plain arrays: safe to make in the background thread.
    """
    points, colors, faces, base = [], [], [], 0
    for c2w, K, rgb, alpha, depth in views:
        c2w, K = np.asarray(c2w, np.float64), np.asarray(K, np.float64)
        R = depth.shape[0]
        step = max(1, -(-R // max_grid))
        idx = np.arange(step // 2, R, step)
        rr, cc = np.meshgrid(idx, idx, indexing="ij")
        d = depth[rr, cc].astype(np.float64)
        inside = alpha > 250
        reach = step // 2 + 1
        valid = inside[rr, cc] & np.isfinite(d) & (d > 0)
        for dr, dc in ((reach, 0), (-reach, 0), (0, reach), (0, -reach)):
            valid &= inside[np.clip(rr + dr, 0, R - 1), np.clip(cc + dc, 0, R - 1)]
        if not valid.any():
            continue
        pts = view_points(c2w, K, R, rr, cc, np.where(valid, d, 0))
        scale = rgb.shape[0] / R
        col = rgb[np.minimum((rr * scale).astype(int), rgb.shape[0] - 1),
                  np.minimum((cc * scale).astype(int), rgb.shape[1] - 1)]
        number = np.full(valid.shape, -1)
        number[valid] = np.arange(valid.sum())
        quad = np.stack([number[:-1, :-1], number[:-1, 1:], number[1:, :-1], number[1:, 1:]])
        dq = np.stack([d[:-1, :-1], d[:-1, 1:], d[1:, :-1], d[1:, 1:]])
        size = dq.mean(axis=0) * step / (K[0, 0] * R)   # the cell's side in world units, at its depth
        keep = np.all(quad >= 0, axis=0) & (dq.max(axis=0) - dq.min(axis=0) <= slope * size)
        a, b, c, e = quad[:, keep]
        tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e], 1)])
        p = pts[valid]
        normal = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
        ray = p[tris].mean(axis=1) - c2w[:3, 3]
        norms = np.linalg.norm(normal, axis=1) * np.linalg.norm(ray, axis=1) + 1e-12
        facing = np.abs((normal * ray).sum(1)) / norms
        tris = tris[facing >= min_facing]
        faces.append(tris + base)
        points.append(p)
        colors.append(col[valid])
        base += len(p)
    if not faces or not sum(len(f) for f in faces):
        return None
    return (np.concatenate(points).astype(np.float32), np.concatenate(faces).astype(np.int64),
            np.concatenate(colors).astype(np.uint8))


def polydata(points: np.ndarray, triangles: np.ndarray, colors: np.ndarray) -> vtkPolyData:
    """A VTK triangle mesh with RGB point colours (array "rgb")."""
    cells = vtkCellArray()
    cells.SetData(numpy_to_vtkIdTypeArray(np.arange(0, 3 * len(triangles) + 1, 3), deep=True),
                  numpy_to_vtkIdTypeArray(triangles.ravel(), deep=True))
    pts = vtkPoints()
    pts.SetData(numpy_to_vtk(points, deep=True))
    rgb = numpy_to_vtk(colors, deep=True)
    rgb.SetName("rgb")
    mesh = vtkPolyData()
    mesh.SetPoints(pts)
    mesh.SetPolys(cells)
    mesh.GetPointData().SetScalars(rgb)
    return mesh


def surface_actor(mesh: vtkPolyData) -> vtkActor:
    """The surface drawn with its own colours, unlit (the images carry their shading)."""
    mapper = vtkPolyDataMapper()
    mapper.SetInputData(mesh)
    mapper.SetColorModeToDirectScalars()
    mapper.SetScalarModeToUsePointData()
    actor = vtkActor()
    actor.SetMapper(mapper)
    actor.GetProperty().LightingOff()
    return actor


# ------------------------------------------------------------------------------------------------
# Background preparation


_DROPPED = object()  # what a delayed job that is no longer wanted returns


class Prefetcher:
    """Values by key, made in one background thread when asked ahead (:meth:`want`) or at once when
    needed (:meth:`get`); the newest ``size`` are kept.

    A job may wait ``delay`` seconds before it starts: it is made only if it is still wanted then
    (or at once when :meth:`get` needs it), so costly work that may never be used (the 3D surface
    of a subject the reviewer passes in under a second) does not compete with the keys.
    """

    def __init__(self, size: int):
        self.size = size
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="label-tool-prefetch")
        self._values: OrderedDict = OrderedDict()
        self._futures: dict = {}
        self._wanted: set = set()   # the keys of the latest want()
        self._needed: set = set()   # keys get() waits for: a delayed job starts at once
        self._lock = threading.Lock()

    def _keep(self, key, value):
        with self._lock:
            self._values[key] = value
            self._values.move_to_end(key)
            while len(self._values) > self.size:
                self._values.popitem(last=False)

    def want(self, jobs) -> None:
        """Make these values in the background, in order: jobs (key, maker) or (key, maker, delay
        in seconds); queued work for other keys is dropped."""
        jobs = [(job[0], job[1], job[2] if len(job) > 2 else 0.0) for job in jobs]
        now = time.monotonic()
        with self._lock:
            self._wanted = {k for k, _, _ in jobs}
            for key in list(self._futures):
                if key not in self._wanted and self._futures[key].cancel():
                    del self._futures[key]
            for key, fn, delay in jobs:
                if key not in self._values and key not in self._futures:
                    self._futures[key] = self._pool.submit(self._run, key, fn, now + delay)

    def _run(self, key, fn, start_at: float):
        while time.monotonic() < start_at:
            with self._lock:
                if key in self._needed:
                    break
                if key not in self._wanted:  # moved on before it was due: not made
                    self._futures.pop(key, None)
                    return _DROPPED
            time.sleep(0.02)
        value = fn()
        self._keep(key, value)
        with self._lock:  # done: the value is kept, the future need not be
            self._futures.pop(key, None)
        return value

    def get(self, key, fn):
        with self._lock:
            if key in self._values:
                self._values.move_to_end(key)
                return self._values[key]
            future = self._futures.pop(key, None)
            if future is not None:
                self._needed.add(key)
        try:
            if future is not None and not future.cancel():
                value = future.result()
                if value is not _DROPPED:
                    return value
        finally:
            with self._lock:
                self._needed.discard(key)
        value = fn()
        self._keep(key, value)
        return value

    def clear(self):
        with self._lock:
            self._wanted = set()
            for f in self._futures.values():
                f.cancel()
            self._futures.clear()
            self._values.clear()

    def close(self):
        self.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)


@dataclass
class TriagePage:
    """One triage page drawn: its thumbnails [(image or None, error or None)], the canvas (PIL) and
    what each cell shows on it [(lines, frame)]; ``pixels``: the canvas in VTK row order, once made."""

    thumbs: list
    canvas: Image.Image
    states: list
    pixels: np.ndarray | None = None


@dataclass
class ReviewFrame:
    """One subject drawn for review: the canvas (VTK row order), its layout, its views at cell size,
    its metadata (None, with the error, when it cannot be read)."""

    pixels: np.ndarray
    layout: Layout
    views: list
    meta: dict | None
    error: str | None = None


# ------------------------------------------------------------------------------------------------
# The window


class ReviewApp:
    """One review session over a queue of subjects for one reviewer."""

    def __init__(self, dataset, queue: list[QueueItem], reviewer: str, labels_dir, off_screen: bool = False,
                 window_size=None, columns: int = 8, start_in_triage: bool = False, triage_shape=TRIAGE_SHAPE):
        if not queue:
            raise UserError("nothing to review: the queue is empty")
        self.display = None if off_screen else XDisplay()  # before anything is created
        if window_size is None:
            window_size = OFF_SCREEN_SIZE if off_screen else fit_window(self.display.screen_size())
        self.dataset, self.queue, self.columns, self.triage_shape = dataset, queue, columns, tuple(triage_shape)
        self.index = {q.subject: i for i, q in enumerate(queue)}
        self.log = EventLog(labels_dir, reviewer)
        # reviewed: good or bad; a skip is "decide later" (not reviewed, here as in compile)
        self.done = sum(1 for s, e in self.log.verdicts().items() if s in self.index and is_decision(e))
        self.skipped = sum(1 for s, e in self.log.verdicts().items() if s in self.index and e.action == "skip")
        self.reader = SubjectReader(dataset)
        self.frames = Prefetcher(size=6)        # review canvases and 3D surfaces
        self.thumbs = Prefetcher(size=4)        # triage pages' thumbnails
        self.pos = self.first_unreviewed()
        if not start_in_triage:  # decode the first subject while the window is being made
            size, item = tuple(window_size), self.item
            self.frames.want([((item.subject, size), lambda: self._make_review_frame(item, size))])
        try:
            self.window = Window(off_screen, window_size, f"label-tool review: {reviewer}")
        except UserError:
            self.frames.close()
            self.thumbs.close()
            self.log.close(discard_if_empty=True)  # no window, nothing left behind
            if self.display is not None:
                self.display.close()
            raise
        self.mode = "review"
        self.show_help = False
        self.notice = ("saved", f"{self.done} of {len(queue)} reviewed so far; log {self.log.path}")
        self.quit_armed = False
        self.triage_yaw, self.triage_page, self.triage_cursor = 0, 0, 0
        self.pending: dict[str, tuple[str, tuple]] = {}   # triage changes not committed yet
        self._page_thumbs: list = []
        self._page = None            # the triage page on screen (TriagePage)
        self._canvas_image = None    # its canvas (PIL)
        self._layout = None
        self._current_frame = None
        self._running = False
        # a window on a display draws its first frame in run(), once, with everything in place (each
        # frame before it would cost the start-up a full frame of software OpenGL)
        self._deferred = not off_screen
        self._make_actors()
        self._bind_keys()
        if start_in_triage:
            self.toggle_triage()
        else:
            self.show_subject()

    # -- state --------------------------------------------------------------------------------------
    @property
    def item(self) -> QueueItem:
        return self.queue[self.pos]

    def first_unreviewed(self, start: int = 0) -> int:
        """The first subject from ``start`` on (wrapping around) that is not reviewed: no verdict, or skip."""
        seen = self.log.verdicts()
        for k in range(len(self.queue)):
            i = (start + k) % len(self.queue)
            if not is_decision(seen.get(self.queue[i].subject)):
                return i
        return min(start, len(self.queue) - 1)

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

    # -- actors ---------------------------------------------------------------------------------------
    def _make_actors(self):
        """Three 2D images (the grid, the heads-up block, the help panel) and the triage cursor."""
        renderer = self.window.renderer
        self._grid = ImageLayer(renderer)
        self._cursor_points = vtkPoints()
        cursor = vtkPolyData()
        cursor.SetPoints(self._cursor_points)
        lines = vtkCellArray()
        lines.InsertNextCell(5, [0, 1, 2, 3, 0])
        cursor.SetLines(lines)
        for _ in range(4):
            self._cursor_points.InsertNextPoint(0, 0, 0)
        mapper = vtkPolyDataMapper2D()
        mapper.SetInputData(cursor)
        self._cursor = vtkActor2D()
        self._cursor.SetMapper(mapper)
        self._cursor.GetProperty().SetColor(*[c / 255 for c in COLORS["cursor"]])
        self._cursor.GetProperty().SetLineWidth(3)
        self._cursor.SetVisibility(False)
        renderer.AddViewProp(self._cursor)
        self._hud = ImageLayer(renderer)
        self._help = ImageLayer(renderer)
        self._help_size = None
        self._hud_key = self._hud_pixels = None
        self._surface = None

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
            size = max(10, min(22, h // 48))
            panel = draw_help(size)
            while size > 10 and (panel.width > w - 20 or panel.height > h - 20):  # the panel fits the window
                size -= 1
                panel = draw_help(size)
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
                    "space": self.key_space, "c": self.cycle_triage_view, "Next": self.next_page,
                    "Prior": self.previous_page, "r": self.reframe_3d, "Escape": self.key_escape}
        for k, reason in REASON_KEYS.items():
            bindings[k] = (lambda r=reason: self.key_bad(r))
        self.window.keys = {key: self._guarded(key, fn) for key, fn in bindings.items()}
        interactor = self.window.interactor
        interactor.AddObserver("LeftButtonPressEvent", lambda *_: self._on_click())
        interactor.AddObserver("ConfigureEvent", lambda *_: self._on_resize())
        interactor.AddObserver("ExitEvent", lambda *_: self._stop())
        self._set_style("grid")

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

    def _set_style(self, kind: str):
        """grid: no mouse interaction (clicks are ours); 3d: trackball camera. VTK's own keys stay off."""
        style = vtkInteractorStyleTrackballCamera() if kind == "3d" else vtkInteractorStyleUser()
        # VTK's styles handle characters themselves (q/e quit, w/s wireframe/surface, ...); an observer stops that
        style.AddObserver("CharEvent", lambda *_: None)
        self.window.interactor.SetInteractorStyle(style)

    def press(self, key: str):
        """Deliver a key as the window would (KeyPressEvent then CharEvent); used by tests and scripts."""
        it = self.window.interactor
        it.Enable()
        it.SetKeySym(key)
        it.SetKeyCode(key if len(key) == 1 else "\0")
        it.KeyPressEvent()
        it.CharEvent()

    def click(self, x: int, y: int):
        """A left click at display pixel (x, y from the top), as the window would deliver it."""
        it = self.window.interactor
        it.SetEventInformation(int(x), self.window_size()[1] - 1 - int(y), 0, 0)
        it.LeftButtonPressEvent()
        it.LeftButtonReleaseEvent()

    def cell_center(self, i: int) -> tuple[int, int]:
        """Display pixel (x, y from the top) at the middle of cell ``i`` of the grid on screen."""
        x0, y0, x1, y1 = self._layout.image_box(i)
        return (x0 + x1) // 2, (y0 + y1) // 2

    def key_good(self):
        if self.mode == "triage":
            self._set_pending(self._cursor_item(), ("good", ()))
        elif self.mode == "review":
            self.verdict("good")

    def key_bad(self, reason):
        if self.mode == "triage":
            self._set_pending(self._cursor_item(), ("bad", (reason,)))
        elif self.mode == "review":
            self.verdict("bad", (reason,))

    def key_skip(self):
        if self.mode == "review":
            self.verdict("skip")

    def key_right(self):
        self._move_cursor(1) if self.mode == "triage" else self.next()

    def key_left(self):
        self._move_cursor(-1) if self.mode == "triage" else self.previous()

    def key_next(self):
        self.next_page() if self.mode == "triage" else self.next()

    def key_previous(self):
        self.previous_page() if self.mode == "triage" else self.previous()

    def key_up(self):
        if self.mode == "triage":
            self._move_cursor(-self.triage_shape[1])

    def key_down(self):
        if self.mode == "triage":
            self._move_cursor(self.triage_shape[1])

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
        item = self.item
        self.pending.pop(item.subject, None)
        what = verdict_text(action, reasons)
        if self._record(item, action, reasons):
            self.notice = ("saved", f"saved: {item.subject} {what}")
        else:
            self.notice = ("warn", f"{item.subject} is already {what}: nothing written")
        if self.pos < len(self.queue) - 1:
            self.goto(self.pos + 1)
        else:
            self.notice = (self.notice[0], self.notice[1] + "   (last subject of the queue; u finds any left)")
            self.refresh()

    def undo(self):
        if self.mode == "3d":
            self._leave_3d()
        target = self.log.undo()
        if target is None:
            self.notice = ("warn", "nothing to undo")
            self.refresh()
            return
        self._count(target.subject, target)  # the undone verdict was the subject's effective one
        now = self.log.verdict(target.subject)
        now_text = verdict_text(now.action, now.reasons) if now else "none"
        self.notice = ("undo", f"undone: {target.subject} {verdict_text(target.action, target.reasons)}; "
                               f"its verdict is now {now_text}")
        if target.subject not in self.index:
            self.notice = ("undo", self.notice[1] + " (not in this queue)")
            self.refresh()
            return
        if self.mode == "triage":
            page, self.triage_cursor = divmod(self.index[target.subject], self.page_size)
            if page != self.triage_page:
                self.triage_page = page
                self.show_triage_page()
            else:
                self._draw_triage(cells=[self.triage_cursor])  # the cell shows its verdict as it is now
        else:
            self.goto(self.index[target.subject])

    def next(self):
        self.goto(min(self.pos + 1, len(self.queue) - 1))

    def previous(self):
        self.goto(max(self.pos - 1, 0))

    def next_unreviewed(self):
        if self.mode != "triage":
            self.goto(self.first_unreviewed(self.pos + 1))

    def goto(self, pos: int):
        self.pos = pos
        if self.mode == "3d":
            self._leave_3d()
        if self.mode == "review":
            self.show_subject()

    def _make_review_frame(self, item: QueueItem, size: tuple[int, int]) -> ReviewFrame:
        """Decode a subject's views and draw its grid for a window of ``size`` (also in the background)."""
        try:
            meta = self.reader.metadata(item)
            names = [f"{v['name']}.png" for v in meta["views"]]
            layout = Layout.fit(*size, len(names), self.columns, 1)
            data = self.reader.read(item, names)
            views = [fit_square(decode_image(data[n], f"{item.shard}: {item.subject} {n}"), layout.cell) for n in names]
        except (UserError, KeyError, TypeError) as e:
            message = str(e) if isinstance(e, UserError) else f"{item.subject}: malformed metadata ({e})"
            layout = Layout.fit(*size, 1, self.columns, 1)
            canvas = blank_canvas(layout)
            ImageDraw.Draw(canvas).text((20, layout.top + 20), message, fill=COLORS["bad"], font=font(layout.font))
            return ReviewFrame(to_vtk_order(canvas), layout, [], None, message)
        canvas = blank_canvas(layout)
        for i, (img, v) in enumerate(zip(views, meta["views"])):
            label = f"{v['name']}  yaw {round(v['yaw_deg']) % 360}  pitch {round(v['pitch_deg'])}"
            draw_cell(canvas, layout, i, img, [(label, COLORS["dim"])])
        return ReviewFrame(to_vtk_order(canvas), layout, views, meta)

    def show_subject(self):
        size = self.window_size()
        item = self.item
        frame = self.frames.get((item.subject, size), lambda: self._make_review_frame(item, size))
        self._layout = frame.layout
        self._current_frame = frame
        self._show_canvas(frame.pixels)
        self._cursor.SetVisibility(False)
        if frame.error:
            self.notice = ("error", frame.error)
        self.refresh()
        ahead = [self.queue[p] for p in (self.pos + 1, self.pos + 2, self.pos - 1) if 0 <= p < len(self.queue)]
        work = [((it.subject, size), (lambda it=it: self._make_review_frame(it, size))) for it in ahead]
        if frame.meta is not None:  # this subject's 3D surface, once the next two are ready and the
            # reviewer has stayed a while (most subjects are never seen in 3D; v makes it at once)
            work.insert(2, (("surface", item.subject), lambda: self._surface_of(item, frame), SURFACE_AFTER_S))
        self.frames.want(work)

    def status_text(self) -> tuple[str, str]:
        """The heads-up block's first two lines in review and 3D mode."""
        it = self.item
        v = self.log.verdict(it.subject)
        pending = f"   ({len(self.pending)} triage change(s) not committed)" if self.pending else ""
        view = "   3D view" if self.mode == "3d" else ""
        skipped = f" ({self.skipped} skipped)" if self.skipped else ""
        status = (f"{it.subject} ({it.shard})   {self.pos + 1}/{len(self.queue)}   reviewed {self.done}, "
                  f"left {len(self.queue) - self.done}{skipped}{pending}{view}")
        score = f"   pre-flag score {it.score:.2f}" if it.score is not None else ""
        detail = (f"verdict: {verdict_text(v.action if v else None, v.reasons if v else ())}{score}"
                  f"   flags: {it.flags_text() or 'none'}")
        return status, detail

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
        item = self.item
        arrays = self.frames.get(("surface", item.subject), lambda: self._surface_of(item, frame))
        if arrays is None:
            self.notice = ("warn", f"{item.subject}: no view has a depth inside its mask; nothing to show in 3D")
            self.refresh()
            return
        mesh = polydata(*arrays)
        self._grid.hide()
        self._surface = surface_actor(mesh)
        self.window.renderer.AddActor(self._surface)
        self._surface_bounds = mesh.GetBounds()
        self._set_style("3d")
        self.mode = "3d"
        self.reframe_3d()

    def _surface_of(self, item: QueueItem, frame: ReviewFrame):
        meta = frame.meta
        names = [v["name"] for v in meta["views"]]
        data = self.reader.read(item, [f"{n}.mask.png" for n in names] + [f"{n}.depth.exr" for n in names])
        where = f"{item.shard}: {item.subject}"
        views = []
        for n, v, rgb in zip(names, meta["views"], frame.views):
            try:
                depth = decode_exr(data[f"{n}.depth.exr"])
            except Exception as e:  # the decoder's own error
                raise DatasetError(f"{where} {n}.depth.exr does not decode ({type(e).__name__}: {e})") from None
            views.append((np.array(v["cam2world"]), np.array(v["intrinsics"]), rgb,
                          decode_image(data[f"{n}.mask.png"], f"{where} {n}.mask.png"), depth))
        return surface_mesh(views)

    def reframe_3d(self):
        """Look at the head from the front (+z), the whole surface in view."""
        if self.mode != "3d":
            return
        b = self._surface_bounds
        center = np.array([(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2])
        radius = 0.5 * np.linalg.norm([b[1] - b[0], b[3] - b[2], b[5] - b[4]])
        cam = self.window.renderer.GetActiveCamera()
        cam.ParallelProjectionOff()
        cam.SetViewAngle(30.0)
        cam.SetFocalPoint(*center)
        cam.SetPosition(*(center + np.array([0.0, 0.0, 1.05 * radius / np.sin(np.radians(15.0))])))
        cam.SetViewUp(0.0, 1.0, 0.0)
        self.window.renderer.ResetCameraClippingRange()
        self.refresh()

    def _leave_3d(self):
        if self._surface is not None:
            self.window.renderer.RemoveActor(self._surface)
        self._surface = None
        self._set_style("grid")
        self.mode = "review"

    # -- triage mode ------------------------------------------------------------------------------------
    @property
    def page_size(self) -> int:
        return self.triage_shape[0] * self.triage_shape[1]

    @property
    def n_pages(self) -> int:
        return -(-len(self.queue) // self.page_size)

    def page_items(self, page: int | None = None) -> list[QueueItem]:
        page = self.triage_page if page is None else page
        return self.queue[page * self.page_size:(page + 1) * self.page_size]

    def toggle_triage(self):
        if self.mode == "triage":
            self.pos = min(self.triage_page * self.page_size + self.triage_cursor, len(self.queue) - 1)
            self.mode = "review"
            self._cursor.SetVisibility(False)
            self.show_subject()
            return
        if self.mode == "3d":
            self._leave_3d()
        self.mode = "triage"
        self.triage_page, self.triage_cursor = divmod(self.pos, self.page_size)
        self.show_triage_page()

    def _triage_layout(self) -> Layout:
        w, h = self.window_size()
        return Layout.fit(w, h, self.page_size, self.triage_shape[1], 2)

    def _make_thumbs(self, page: int, yaw: float, side: int) -> list:
        """The page's subjects, each as (image at ``side`` px or None, error or None)."""
        out = []
        for item in self.page_items(page):
            try:
                views = self.reader.metadata(item)["views"]
                name = f"{views[nearest_view(views, yaw)]['name']}.png"
                img = decode_image(self.reader.read(item, [name])[name], f"{item.shard}: {item.subject} {name}")
                out.append((fit_square(img, side), None))
            except (UserError, KeyError, TypeError, ValueError) as e:
                out.append((None, str(e)))
        return out

    def _make_page(self, page: int, yaw: float, layout: Layout) -> "TriagePage":
        """A triage page drawn whole: its thumbnails and every cell as it stands now (also in the
        background; the cells whose state changes before it is shown are drawn again then)."""
        thumbs = self._make_thumbs(page, yaw, layout.cell)
        canvas = blank_canvas(layout)
        states = []
        for i, item in enumerate(self.page_items(page)):
            state = self._cell_drawing(item, thumbs[i][1])
            draw_cell(canvas, layout, i, thumbs[i][0], *state)
            states.append(state)
        return TriagePage(thumbs, canvas, states, to_vtk_order(canvas))

    def _page_key(self, page: int, layout: Layout):
        return page, self.triage_yaw, layout

    def show_triage_page(self):
        layout = self._triage_layout()
        self._layout = layout
        yaw = TRIAGE_YAWS[self.triage_yaw]
        page = self.triage_page
        self._page = self.thumbs.get(self._page_key(page, layout), lambda: self._make_page(page, yaw, layout))
        self._page_thumbs = self._page.thumbs
        self._canvas_image = self._page.canvas
        self.triage_cursor = min(self.triage_cursor, len(self.page_items()) - 1)
        # only the cells that changed since the page was drawn (a verdict undone, a change made on it)
        self._draw_triage(cells=range(len(self.page_items())), shown=False)
        ahead = [p for p in (page + 1, page - 1) if 0 <= p < self.n_pages]
        self.thumbs.want([(self._page_key(p, layout), (lambda p=p: self._make_page(p, yaw, layout)))
                          for p in ahead])

    def _cell_drawing(self, item: QueueItem, error: str | None):
        """What a triage cell shows: (lines, frame), with a thumbnail's error in place of the pre-flags."""
        lines, frame = self.cell_state(item)
        if error:
            lines = [lines[0], (error[-60:], COLORS["bad"])]
        return lines, frame

    def cell_state(self, item: QueueItem):
        """(lines of text, frame) of a triage cell: saved verdict, change not committed, pre-flags."""
        saved = self.log.verdict(item.subject)
        change = self.pending.get(item.subject)
        saved_text = verdict_text(saved.action, saved.reasons) if saved else "new"
        if change:
            top = (f"{item.subject}  {saved_text} > {verdict_text(*change)}", COLORS[change[0]])
            frame = (COLORS[change[0]], 5)
        elif saved:
            top = (f"{item.subject}  saved {saved_text}", COLORS[saved.action])
            frame = (tuple(c * 2 // 3 for c in COLORS[saved.action]), 2)
        else:
            top = (f"{item.subject}  new", COLORS["text"])
            frame = None
        bottom = (f"{item.flags_text() or 'no flag'}  flip={REASON_SHORT[item.default_reason]}", COLORS["dim"])
        return [top, bottom], frame

    def _draw_triage(self, cells=(), shown: bool = True):
        """Draw the page's ``cells`` whose state changed (all of them when the page is not on screen yet,
        ``shown`` False), then the cursor and the heads-up text."""
        layout = self._layout
        items = self.page_items()
        page = self._page
        changed = False
        for i in cells:
            img, error = page.thumbs[i]
            state = self._cell_drawing(items[i], error)
            if state != page.states[i]:
                draw_cell(page.canvas, layout, i, img, *state)
                page.states[i] = state
                page.pixels = None
                changed = True
        if page.pixels is None:
            page.pixels = to_vtk_order(page.canvas)
        if changed or not shown:
            self._show_canvas(page.pixels)
        sx, sy = layout.slot(self.triage_cursor)
        x0, y0, x1, y1 = sx + 2, sy - 2, sx + layout.slot_w - 3, sy + layout.slot_h - 3
        h = layout.height
        for k, (x, y) in enumerate([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]):
            self._cursor_points.SetPoint(k, x, h - 1 - y, 0)
        self._cursor_points.Modified()
        self._cursor.SetVisibility(True)
        here = sum(1 for it in items if it.subject in self.pending)
        reviewed = sum(1 for it in items if is_decision(self.log.verdict(it.subject)))
        skipped = sum(1 for it in items if (v := self.log.verdict(it.subject)) is not None and v.action == "skip")
        elsewhere = len(self.pending) - here
        first = self.triage_page * self.page_size + 1
        cur = items[self.triage_cursor]
        status = (f"TRIAGE page {self.triage_page + 1}/{self.n_pages} (subjects {first}-{first + len(items) - 1}), "
                  f"view yaw {TRIAGE_YAWS[self.triage_yaw]:.0f}   here: {reviewed} reviewed, "
                  f"{f'{skipped} skipped, ' if skipped else ''}{here} changed"
                  f"{f', {elsewhere} changed on other pages' if elsewhere else ''}   "
                  f"reviewed {self.done}/{len(self.queue)}")
        saved, change, flip = self.log.verdict(cur.subject), self.pending.get(cur.subject), self._flip_change(cur)
        detail = (f"cursor {cur.subject}: saved {verdict_text(saved.action, saved.reasons) if saved else 'none'}"
                  f"{f', changed to {verdict_text(*change)} (not committed)' if change else ''}   "
                  f"pre-flags: {cur.flags_text() or 'none'}   space/click: "
                  f"{'take the change back' if flip is None else verdict_text(*flip)}")
        self._draw_text(status, detail, TRIAGE_KEYS)
        self._render()

    def _cursor_item(self) -> QueueItem:
        return self.page_items()[self.triage_cursor]

    def _set_pending(self, item: QueueItem, change: tuple[str, tuple]):
        """Record a change to a triage cell; a change back to what is saved (or to good for a new
        cell, which is what a commit writes anyway) is no change."""
        saved = self.log.verdict(item.subject)
        if (saved is not None and (saved.action, saved.reasons) == change) or (saved is None and change[0] == "good"):
            self.pending.pop(item.subject, None)
        else:
            self.pending[item.subject] = change
        self._draw_triage(cells=[self.page_items().index(item)])

    def _flip_change(self, item: QueueItem):
        """What space or a click does to a cell: None takes back this visit's change; otherwise a bad
        cell becomes good and any other bad with its pre-flag's reason."""
        if item.subject in self.pending:
            return None
        saved = self.log.verdict(item.subject)
        return ("good", ()) if saved and saved.action == "bad" else ("bad", (item.default_reason,))

    def _flip(self, i: int):
        item = self.page_items()[i]
        change = self._flip_change(item)
        if change is None:
            self.pending.pop(item.subject)
            self._draw_triage(cells=[i])
        else:
            self._set_pending(item, change)

    def _move_cursor(self, step: int):
        n = len(self.page_items())
        self.triage_cursor = min(max(self.triage_cursor + step, 0), n - 1)
        self._draw_triage()

    def next_page(self):
        self._turn_page(+1)

    def previous_page(self):
        self._turn_page(-1)

    def _turn_page(self, step: int):
        """Show the next (+1) or previous (-1) triage page; changes stay where they were made."""
        if self.mode != "triage":
            return
        if 0 <= self.triage_page + step < self.n_pages:
            self.triage_page += step
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
        page = self.triage_page + 1
        writes, before, skipped = [], {}, 0
        for item in self.page_items():
            saved = self.log.verdict(item.subject)
            action, reasons = self.pending.pop(item.subject, None) or (("good", ()) if saved is None else (None, ()))
            if action is not None and (saved is None or (saved.action, saved.reasons) != (action, reasons)):
                writes.append((item.subject, item.shard, action, reasons))
                before[item.subject] = saved
            elif saved is not None and saved.action == "skip":
                skipped += 1  # decide later: a commit leaves it for the reviewer, unreviewed
        self.log.append_all(writes)  # one fsync for the page
        for subject, saved in before.items():
            self._count(subject, saved)
        bad = sum(1 for w in writes if w[2] == "bad")
        good = len(writes) - bad
        if not bad and not good:
            self.notice = ("warn", f"page {page}: nothing to commit (every cell has its verdict and none was "
                                   "changed); nothing written")
            self._draw_triage()
            return
        kept = len(self.page_items()) - bad - good - skipped
        self.notice = ("saved", f"committed page {page}: {bad} bad, {good} good written"
                                f"{f', {kept} kept their saved verdict' if kept else ''}"
                                f"{f', {skipped} skipped left unreviewed (u finds them)' if skipped else ''}")
        if self.triage_page + 1 < self.n_pages:
            self.triage_page += 1
            self.triage_cursor = 0
            self.show_triage_page()
        else:
            self.notice = ("saved", self.notice[1] + " (last page)")
            self._draw_triage(cells=range(len(self.page_items())))

    def _on_click(self):
        if self.mode != "triage":
            return
        x, y = self.window.interactor.GetEventPosition()
        i = self._layout.index_at(x, self._layout.height - 1 - y)
        if i is not None and i < len(self.page_items()):
            self.quit_armed = False
            self.triage_cursor = i
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
        self.window.show()
        self._set_style("3d" if self.mode == "3d" else "grid")
        self._deferred = False
        if not self._on_resize():
            self.refresh()      # the first frame
        fd = self._x_connection()
        self._running = True
        while self._running:
            self.window.interactor.ProcessEvents()
            if not self._running:
                break
            # wait for X events without holding the interpreter, so the prefetch thread can work
            if fd is None:
                select.select([], [], [], 0.005)
            else:
                select.select([fd], [], [], 0.05)
        self.close()

    def _x_connection(self):
        """File descriptor of VTK's X connection (None when it cannot be found)."""
        display = self.display
        try:
            handle = int(self.window.render_window.GetGenericDisplayId().split("_")[1], 16)
            return display.lib.XConnectionNumber(handle) if display and display.lib else None
        except (AttributeError, ValueError, IndexError, TypeError):
            return None

    def _stop(self):
        self._running = False

    def close(self):
        self._running = False
        if getattr(self, "window", None) is None:
            return
        self.frames.close()
        self.thumbs.close()
        self.log.close()
        self.window.close()
        self.window = None
        if self.display is not None:
            self.display.close()
