"""What the review window shows, drawn with Pillow: the grids, their cells, the heads-up block, the help.

The grid is drawn as one image at the window's pixel size; a subject's grid (:func:`review_frame`)
and a triage page (:func:`triage_page`), cells and all, are pure functions of the data and the
session's state, safe to make in the background thread.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw

from datagen.errors import UserError
from datagen.preview import font

from .reader import decode_image, nearest_view
from .session import REASON_SHORT, verdict_text

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
               "v back to the views   Left/Right other subject   g 1-5 s verdict (then the next subject)")
HELP = [  # (keys, what they do); a row without a description is a heading
    ("REVIEW: one subject, all its views", None),
    ("g", "good"),
    ("1 2 3 4 5", "bad: 1 multiple faces, 2 broken back, 3 artifacts, 4 blur, 5 other"),
    ("s", "skip: decide later (the subject stays unreviewed; u comes back to it)"),
    ("Right / n,  Left / p", "next subject, previous subject"),
    ("u", "next unreviewed subject (no verdict yet, or skipped)"),
    ("z", "undo the latest verdict (written as an undo event)"),
    ("v", "3D surface from the views' depth and masks: drag turns it, wheel zooms, r re-frames"),
    ("", "g, 1-5 and s work there too: the verdict is saved and the next subject's views come"),
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


def fit_square(img: np.ndarray, side: int) -> np.ndarray:
    """``img`` (H, W, 3) uint8 resized to (side, side, 3)."""
    if img.shape[0] == side and img.shape[1] == side:
        return img
    return np.asarray(Image.fromarray(img).resize((side, side), Image.BILINEAR, reducing_gap=2.0))


@lru_cache(maxsize=8)
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


def fit_text(text, f, room: float) -> str:
    """``text`` cut (ending in '~') to fit ``room`` pixels in font ``f``; ``text`` may be a tuple of
    forms, longest first: the first that fits, or the last cut."""
    for form in (text,) if isinstance(text, str) else text:
        if f.getlength(form) <= room:
            return form
    text = form
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


def help_panel(width: int, height: int) -> Image.Image:
    """The help panel at the largest text size (up to 22 px) that fits a window ``width`` x ``height``."""
    size = max(10, min(22, height // 48))
    panel = draw_help(size)
    while size > 10 and (panel.width > width - 20 or panel.height > height - 20):
        size -= 1
        panel = draw_help(size)
    return panel


def to_vtk_order(canvas: Image.Image) -> np.ndarray:
    """(H, W, 3) uint8 rows bottom-up, as vtkImageData wants them."""
    return np.ascontiguousarray(np.asarray(canvas)[::-1])


@dataclass
class TriagePage:
    """One triage page drawn: its thumbnails [(image or None, error or None)], the canvas (PIL) and
    what each cell shows on it [(lines, frame)]; ``pixels``: the canvas in VTK row order, once made."""

    thumbs: list
    canvas: Image.Image
    states: list
    pixels: np.ndarray | None = None

    def update(self, session, layout: Layout, cells) -> bool:
        """Draw again the ``cells`` whose state changed since they were drawn; True when one had.
        ``pixels`` is the canvas as it is now."""
        items = session.page_items()
        changed = False
        for i in cells:
            img, error = self.thumbs[i]
            state = cell_drawing(session, items[i], error)
            if state != self.states[i]:
                draw_cell(self.canvas, layout, i, img, *state)
                self.states[i] = state
                self.pixels = None
                changed = True
        if self.pixels is None:
            self.pixels = to_vtk_order(self.canvas)
        return changed


@dataclass
class ReviewFrame:
    """One subject drawn for review: the canvas (VTK row order), its layout, its views at cell size,
    its metadata (None, with the error, when it cannot be read)."""

    pixels: np.ndarray
    layout: Layout
    views: list
    meta: dict | None
    error: str | None = None


def review_frame(reader, item, size: tuple[int, int], columns: int) -> ReviewFrame:
    """Decode a subject's views and draw its grid for a window of ``size`` (also in the background)."""
    try:
        meta = reader.metadata(item)
        names = [f"{v['name']}.png" for v in meta["views"]]
        layout = Layout.fit(*size, len(names), columns, 1)
        data = reader.read(item, names)
        views = [fit_square(decode_image(data[n], f"{item.shard}: {item.subject} {n}"), layout.cell) for n in names]
    except (UserError, KeyError, TypeError) as e:
        message = str(e) if isinstance(e, UserError) else f"{item.subject}: malformed metadata ({e})"
        layout = Layout.fit(*size, 1, columns, 1)
        canvas = blank_canvas(layout)
        ImageDraw.Draw(canvas).text((20, layout.top + 20), message, fill=COLORS["bad"], font=font(layout.font))
        return ReviewFrame(to_vtk_order(canvas), layout, [], None, message)
    canvas = blank_canvas(layout)
    for i, (img, v) in enumerate(zip(views, meta["views"])):
        label = f"{v['name']}  yaw {round(v['yaw_deg']) % 360}  pitch {round(v['pitch_deg'])}"
        draw_cell(canvas, layout, i, img, [(label, COLORS["dim"])])
    return ReviewFrame(to_vtk_order(canvas), layout, views, meta)


def thumbnails(reader, items, yaw: float, side: int) -> list:
    """The subjects ``items``, each as (image at ``side`` px or None, error or None)."""
    out = []
    for item in items:
        try:
            views = reader.metadata(item)["views"]
            name = f"{views[nearest_view(views, yaw)]['name']}.png"
            img = decode_image(reader.read(item, [name])[name], f"{item.shard}: {item.subject} {name}")
            out.append((fit_square(img, side), None))
        except (UserError, KeyError, TypeError, ValueError) as e:
            out.append((None, str(e)))
    return out


def triage_page(reader, session, page: int, yaw: float, layout: Layout) -> TriagePage:
    """A triage page drawn whole: its thumbnails and every cell as it stands now (also in the
    background; the cells whose state changes before it is shown are drawn again then)."""
    items = session.page_items(page)
    thumbs = thumbnails(reader, items, yaw, layout.cell)
    canvas = blank_canvas(layout)
    states = []
    for i, item in enumerate(items):
        state = cell_drawing(session, item, thumbs[i][1])
        draw_cell(canvas, layout, i, thumbs[i][0], *state)
        states.append(state)
    return TriagePage(thumbs, canvas, states, to_vtk_order(canvas))


def cell_drawing(session, item, error: str | None):
    """What a triage cell shows: (lines, frame), with a thumbnail's error in place of the pre-flags."""
    lines, frame = cell_state(session, item)
    if error:
        lines = [lines[0], (error[-60:], COLORS["bad"])]
    return lines, frame


def verdict_forms(verdict) -> tuple[str, str, str]:
    """A verdict ((action, reasons) or None: none yet) written long, as a word, as a letter."""
    if verdict is None:
        return "new", "new", "-"
    action, reasons = verdict
    return verdict_text(action, reasons), action, action[0].upper()


def cell_label(subject: str, forms) -> tuple:
    """A triage cell's first line in its forms, longest first (see :func:`fit_text`): the subject and
    its verdict's ``forms`` (longest first, the last a letter). As room runs out the verdict gets
    shorter, then the subject gives way to its last 4 characters, then goes: the verdict stays in text."""
    tail = "~" + subject[-4:]
    candidates = [f"{subject}  {v}" for v in forms[:-1]] + [f"{tail} {v}" for v in forms[-2:]] + list(forms[-2:])
    return tuple(dict.fromkeys(candidates))


def cell_state(session, item):
    """(lines of text, frame) of a triage cell: saved verdict, change not committed, pre-flags. The
    first line is a tuple of forms, longest first (see :func:`cell_label`)."""
    saved = session.log.verdict(item.subject)
    change = session.pending.get(item.subject)
    was = verdict_forms((saved.action, saved.reasons) if saved else None)
    if change:
        now = verdict_forms(change)
        top = (cell_label(item.subject, [f"{was[0]} > {now[0]}", f"{was[1]}>{now[1]}", f"{was[2]}>{now[2]}"]),
               COLORS[change[0]])
        frame = (COLORS[change[0]], 5)
    elif saved:
        top = (cell_label(item.subject, [f"saved {was[0]}", *was]), COLORS[saved.action])
        frame = (tuple(c * 2 // 3 for c in COLORS[saved.action]), 2)
    else:
        top = (cell_label(item.subject, was), COLORS["text"])
        frame = None
    bottom = (f"{item.flags_text() or 'no flag'}  flip={REASON_SHORT[item.default_reason]}", COLORS["dim"])
    return [top, bottom], frame
