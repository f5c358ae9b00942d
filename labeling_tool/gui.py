"""The review window (pyvista): a subject's views as one grid, a triage grid, a 3D point-cloud view.

Review mode shows all views of one subject as textured planes in a single renderer (far faster than
one subplot per view) and a heads-up line. Triage mode shows one chosen view of many subjects;
the reviewer marks the bad ones and commits the page. Every verdict is appended to the reviewer's
event log (flushed and fsynced) as it is made, so closing or killing the window loses nothing, and
reopening resumes at the first subject without a verdict.

Keys (review): g good | 1-5 bad: 1 multiple faces, 2 broken back, 3 artifacts, 4 blur, 5 other |
s skip | Right/n next | Left/p previous | u next unreviewed | z undo | v 3D view | t triage |
h help | Escape quit.  Keys (triage): arrows move | 1-5 mark bad (reason) | g / space unmark |
Return commit page (marked bad, the rest good) | c cycle the shown view | t back to review.
Mouse (triage): left click toggles a cell's mark. pyvista's and VTK's own keys are disabled.
"""
from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass

import numpy as np
import pyvista as pv
import torch

from datagen.cameras import rays
from datagen.shards import decode_png, decode_sample, read_fields

from .events import REASONS, EventLog

REASON_KEYS = {str(i + 1): r for i, r in enumerate(REASONS)}
CELL = 1.06  # grid pitch in world units (planes are 1 x 1)
TRIAGE_ROWS, TRIAGE_COLS = 5, 8
HELP = "\n".join([
    "REVIEW                               TRIAGE",
    "g        good                        arrows   move the cursor",
    "1 .. 5   bad: 1 multiple faces,      1 .. 5   mark bad (reason)",
    "         2 broken back, 3 artifacts, g/space  unmark",
    "         4 blur, 5 other             click    toggle a mark",
    "s        skip                        Return   commit page (marked bad, rest good)",
    "Right/n  next     Left/p  previous   c        cycle the shown view",
    "u        next unreviewed             t        back to review",
    "z        undo (an event too)",
    "v        3D point cloud              h        this help",
    "t        triage                      Escape   quit (every verdict is already saved)",
])


@dataclass
class QueueItem:
    subject: str
    shard: str
    score: float | None = None
    flags: str = ""


class SubjectCache:
    """Subjects' raw fields and decoded RGB views by id; the next subject is prepared in the background.

    Only the RGB views are decoded for the grid; masks and depth are decoded when the 3D view asks.
    """

    def __init__(self, root, size: int = 8):
        self.root, self.size = root, size
        self._data: dict = {}
        self._lock = threading.Lock()
        self._threads: dict = {}

    def _load(self, item: QueueItem):
        fields = read_fields(self.root, int(item.shard.split("-")[1]), item.subject)
        meta = json.loads(fields["json"])
        rgb = [decode_png(fields[f"{v['name']}.png"]) for v in meta["views"]]
        return {"fields": fields, "meta": meta, "rgb": rgb}

    def _entry(self, item: QueueItem):
        t = self._threads.pop(item.subject, None)
        if t is not None:
            t.join()
        with self._lock:
            if item.subject in self._data:
                return self._data[item.subject]
        entry = self._load(item)
        self._store(item.subject, entry)
        return entry

    def views(self, item: QueueItem) -> list:
        """The subject's RGB views (H, W, 3) uint8."""
        return self._entry(item)["rgb"]

    def sample(self, item: QueueItem):
        """The fully decoded subject (masks and depth too)."""
        return decode_sample(item.subject, self._entry(item)["fields"], item.shard)

    def _store(self, key, entry):
        with self._lock:
            self._data[key] = entry
            while len(self._data) > self.size:
                self._data.pop(next(iter(self._data)))

    def prefetch(self, item: QueueItem):
        with self._lock:
            if item.subject in self._data or item.subject in self._threads:
                return
        t = threading.Thread(target=lambda: self._store(item.subject, self._load(item)), daemon=True)
        self._threads[item.subject] = t
        t.start()

    def thumbnail(self, item: QueueItem, yaw: float) -> np.ndarray:
        """The view of a subject closest to ``yaw`` (decodes only that image)."""
        fields = read_fields(self.root, int(item.shard.split("-")[1]), item.subject)
        meta = json.loads(fields["json"])
        d = [abs((v["yaw_deg"] - yaw + 180) % 360 - 180) + abs(v["pitch_deg"]) for v in meta["views"]]
        return decode_png(fields[f"{meta['views'][int(np.argmin(d))]['name']}.png"])


def point_cloud(sample, max_points: int = 150_000):
    """World points coloured by RGB from every view's depth and mask, and the camera centres."""
    meta = sample.metadata
    res = meta["resolution"]
    c2w = np.array([v["cam2world"] for v in meta["views"]])
    K = np.array([v["intrinsics"] for v in meta["views"]])
    origins, dirs = rays(torch.tensor(c2w), torch.tensor(K), res)
    pts, cols = [], []
    for i in range(len(meta["views"])):
        inside = (sample.alpha[i] > 127).reshape(-1)
        depth = torch.from_numpy(sample.depth[i].reshape(-1)[inside])
        pts.append((origins[i][inside] + depth[:, None] * dirs[i][inside]).numpy())
        cols.append(sample.rgb[i].reshape(-1, 3)[inside])
    pts, cols = np.concatenate(pts), np.concatenate(cols)
    if len(pts) > max_points:
        keep = np.random.default_rng(0).choice(len(pts), max_points, replace=False)
        pts, cols = pts[keep], cols[keep]
    return pts, cols, c2w[:, :3, 3]


class ReviewApp:
    """One review session over a queue of subjects for one reviewer."""

    def __init__(self, dataset, queue: list[QueueItem], reviewer: str, labels_dir, off_screen: bool = False,
                 window_size=(1600, 900), columns: int = 8, start_in_triage: bool = False):
        if not queue:
            from datagen.errors import UserError

            raise UserError("nothing to review: the queue is empty")
        self.dataset, self.queue = dataset, queue
        self.log = EventLog(labels_dir, reviewer)
        self.cache = SubjectCache(dataset)
        self.columns = columns
        self.mode = "review"
        self.show_help = False
        self.triage_yaw = [0.0, 180.0, 90.0, 270.0]
        self.triage_page, self.triage_cursor, self.triage_marks = 0, 0, {}
        self.timings: dict[str, list[float]] = {"open": [], "next": []}
        t0 = time.perf_counter()
        if off_screen and not os.environ.get("DISPLAY"):
            # Render with EGL directly instead of first trying (and warning about) a missing X server.
            os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
        self.plotter = pv.Plotter(off_screen=off_screen, window_size=list(window_size),
                                  title=f"label-tool review: {reviewer}")
        self.plotter.set_background("#202020")
        self._grid_actors: list = []
        self._triage_actors: list = []
        self._frames: dict = {}
        self._bind_keys()
        self.pos = self.first_unreviewed()
        if start_in_triage:
            self.toggle_triage()
        else:
            self.show_subject()
        self.timings["open"].append(time.perf_counter() - t0)

    # -- state --------------------------------------------------------------------------------------
    @property
    def item(self) -> QueueItem:
        return self.queue[self.pos]

    def seen(self) -> dict:
        """subject -> effective verdict event of this reviewer."""
        return self.log.verdicts()

    def first_unreviewed(self, start: int = 0) -> int:
        seen = self.seen()
        for k in range(len(self.queue)):
            i = (start + k) % len(self.queue)
            if self.queue[i].subject not in seen:
                return i
        return min(start, len(self.queue) - 1)

    # -- keys ---------------------------------------------------------------------------------------
    def _bind_keys(self):
        pl = self.plotter
        for key in list(pl.iren._key_press_event_callbacks):
            pl.clear_events_for_key(key)
        bindings = {"g": self.key_good, "s": self.key_skip, "n": self.next, "Right": self.key_right,
                    "p": self.previous, "Left": self.key_left, "u": self.next_unreviewed, "z": self.undo,
                    "v": self.toggle_3d, "t": self.toggle_triage, "h": self.toggle_help, "question": self.toggle_help,
                    "Up": self.key_up, "Down": self.key_down, "Return": self.commit_page, "space": self.key_space,
                    "c": self.cycle_triage_view, "Escape": self.close}
        for k, reason in REASON_KEYS.items():
            bindings[k] = (lambda r=reason: self.key_bad(r))
        for key, fn in bindings.items():
            pl.add_key_event(key, fn)
        self.plotter.track_click_position(self._on_click, side="left")
        self._block_default_keys()

    def _block_default_keys(self):
        """VTK's style handles characters itself (q/e quit, w/s wireframe/surface, ...); an observer stops that."""
        style = self.plotter.iren.interactor.GetInteractorStyle()
        if style is not None and not style.HasObserver("CharEvent"):
            style.AddObserver("CharEvent", lambda *_: None)

    def press(self, key: str):
        """Deliver a key as the window would (KeyPressEvent then CharEvent); used by tests and scripts."""
        it = self.plotter.iren.interactor
        it.Enable()
        it.SetKeySym(key)
        it.SetKeyCode(key if len(key) == 1 else "\0")
        it.KeyPressEvent()
        it.CharEvent()

    # -- review mode ----------------------------------------------------------------------------------
    def key_good(self):
        if self.mode == "triage":
            self.triage_marks.pop(self._cursor_subject(), None)
            self._draw_triage_marks()
        else:
            self.verdict("good")

    def key_bad(self, reason):
        if self.mode == "triage":
            subject = self._cursor_subject()
            if subject:
                self.triage_marks[subject] = reason
                self._move_cursor(1)
        else:
            self.verdict("bad", (reason,))

    def key_skip(self):
        if self.mode == "review":
            self.verdict("skip")

    def key_right(self):
        self._move_cursor(1) if self.mode == "triage" else self.next()

    def key_left(self):
        self._move_cursor(-1) if self.mode == "triage" else self.previous()

    def key_up(self):
        if self.mode == "triage":
            self._move_cursor(-TRIAGE_COLS)

    def key_down(self):
        if self.mode == "triage":
            self._move_cursor(TRIAGE_COLS)

    def key_space(self):
        if self.mode == "triage":
            s = self._cursor_subject()
            if s in self.triage_marks:
                self.triage_marks.pop(s)
            elif s:
                self.triage_marks[s] = "artifacts"
            self._draw_triage_marks()

    def verdict(self, action: str, reasons=()):
        self.log.append(self.item.subject, self.item.shard, action, reasons)
        if self.pos < len(self.queue) - 1:
            self.next()
        else:
            self.update_hud()

    def undo(self):
        if self.mode != "review" or not self.log.verdicts():
            return
        self.log.append(self.item.subject, self.item.shard, "undo")
        last = [e for e in self.log.events if e.action != "undo"]
        # go back to the subject whose verdict was just withdrawn
        undone = {e.subject for e in last} - set(self.log.verdicts())
        target = next((i for i, q in enumerate(self.queue) if q.subject in undone), self.pos)
        self.goto(target)

    def next(self):
        self.goto(min(self.pos + 1, len(self.queue) - 1))

    def previous(self):
        self.goto(max(self.pos - 1, 0))

    def next_unreviewed(self):
        self.goto(self.first_unreviewed(self.pos + 1))

    def goto(self, pos: int):
        t0 = time.perf_counter()
        self.pos = pos
        if self.mode == "3d":
            self._clear_3d()
            self.mode = "review"
        if self.mode == "review":
            self.show_subject()
            self.timings["next"].append(time.perf_counter() - t0)

    def _grid_layout(self, n: int, columns: int):
        rows = -(-n // columns)
        return [((i % columns) * CELL, -(i // columns) * CELL) for i in range(n)], rows

    def show_subject(self):
        views = self.cache.views(self.item)
        if self.pos + 1 < len(self.queue):
            self.cache.prefetch(self.queue[self.pos + 1])
        cells, rows = self._grid_layout(len(views), self.columns)
        if len(self._grid_actors) != len(views):
            for a in self._grid_actors:
                self.plotter.remove_actor(a, render=False)
            self._grid_actors = []
            for i, (x, y) in enumerate(cells):
                plane = pv.Plane(center=(x, y, 0), direction=(0, 0, 1), i_size=1, j_size=1)
                self._grid_actors.append(self.plotter.add_mesh(plane, texture=pv.Texture(views[i]), name=f"view{i}",
                                                               lighting=False, render=False))
        else:
            for actor, img in zip(self._grid_actors, views):
                actor.texture = pv.Texture(img)
        for a in self._grid_actors:
            a.SetVisibility(True)
        self._frame_camera(self.columns, rows)
        self.update_hud()

    def _frame_camera(self, columns, rows):
        pl = self.plotter
        pl.enable_image_style()
        self._block_default_keys()
        cam = pl.camera
        cx, cy = (columns - 1) * CELL / 2, -(rows - 1) * CELL / 2
        cam.focal_point = (cx, cy, 0)
        cam.position = (cx, cy, 10)
        cam.up = (0, 1, 0)
        cam.enable_parallel_projection()
        w, h = pl.window_size
        cam.parallel_scale = max(rows * CELL / 2 + 0.35, columns * CELL / 2 * h / w) * 1.02
        pl.renderer.ResetCameraClippingRange()

    def hud_text(self) -> str:
        seen = self.seen()
        it = self.item
        done = sum(1 for q in self.queue if q.subject in seen)
        v = seen.get(it.subject)
        verdict = "none" if v is None else (v.action + (f" ({', '.join(v.reasons)})" if v.reasons else ""))
        flags = f"  flags: {it.flags}" if it.flags else ""
        score = f"  score {it.score:.2f}" if it.score is not None else ""
        return (f"{it.subject} ({it.shard})  [{self.pos + 1}/{len(self.queue)}]  reviewed {done}, "
                f"left {len(self.queue) - done}  verdict: {verdict}{score}{flags}\n"
                "g good   1 faces  2 back  3 artifacts  4 blur  5 other   s skip   arrows move   u unreviewed   "
                "z undo   v 3D   t triage   h help")

    def update_hud(self):
        pl = self.plotter
        pl.add_text(self.hud_text(), position="upper_left", font_size=10, color="white", name="hud", render=False)
        if self.show_help:
            pl.add_text(HELP, position="lower_left", font_size=10, color="yellow", name="help", font="courier", shadow=True,
                        render=False)
        else:
            pl.remove_actor("help", render=False)
        pl.render()

    def toggle_help(self):
        self.show_help = not self.show_help
        self.update_hud()

    # -- 3D view ----------------------------------------------------------------------------------------
    def toggle_3d(self):
        if self.mode == "triage":
            return
        if self.mode == "3d":
            self._clear_3d()
            self.mode = "review"
            self.show_subject()
            return
        pts, cols, cams = point_cloud(self.cache.sample(self.item))
        for a in self._grid_actors:
            a.SetVisibility(False)
        pl = self.plotter
        pl.camera.disable_parallel_projection()
        pl.add_points(pv.PolyData(cams), color="orange", point_size=12, render_points_as_spheres=True,
                      name="cams", render=False)
        pl.enable_trackball_style()
        self._block_default_keys()
        if len(pts):
            cloud = pv.PolyData(pts)
            cloud["rgb"] = cols
            pl.add_points(cloud, scalars="rgb", rgb=True, point_size=3, name="cloud", render=False)
            pl.view_xy()
            pl.reset_camera(bounds=cloud.bounds)  # frame the head; the cameras sit around it, off screen
        else:
            pl.reset_camera()
        self.mode = "3d"
        self.update_hud()

    def _clear_3d(self):
        for name in ("cloud", "cams"):
            self.plotter.remove_actor(name, render=False)

    # -- triage mode ------------------------------------------------------------------------------------
    def toggle_triage(self):
        if self.mode == "triage":
            for a in self._triage_actors + list(self._frames.values()):
                self.plotter.remove_actor(a, render=False)
            self._triage_actors, self._frames = [], {}
            self.plotter.remove_actor("cursor", render=False)
            self.mode = "review"
            self.show_subject()
            return
        if self.mode == "3d":
            self._clear_3d()
        for a in self._grid_actors:
            a.SetVisibility(False)
        self.mode = "triage"
        self.triage_page = self.pos // (TRIAGE_ROWS * TRIAGE_COLS)
        self.show_triage_page()

    def page_items(self) -> list[QueueItem]:
        n = TRIAGE_ROWS * TRIAGE_COLS
        return self.queue[self.triage_page * n:(self.triage_page + 1) * n]

    def show_triage_page(self):
        pl = self.plotter
        for a in self._triage_actors + list(self._frames.values()):
            pl.remove_actor(a, render=False)
        self._triage_actors, self._frames = [], {}
        items = self.page_items()
        cells, rows = self._grid_layout(len(items), TRIAGE_COLS)
        yaw = self.triage_yaw[0]
        for i, (item, (x, y)) in enumerate(zip(items, cells)):
            img = self.cache.thumbnail(item, yaw)
            plane = pv.Plane(center=(x, y, 0), direction=(0, 0, 1), i_size=1, j_size=1)
            self._triage_actors.append(pl.add_mesh(plane, texture=pv.Texture(img), lighting=False,
                                                   name=f"tri{i}", render=False))
        self.triage_cursor = 0
        self.triage_marks = {}
        self._frame_camera(TRIAGE_COLS, max(rows, 1))
        self._draw_triage_marks()

    def _frame(self, i: int, name: str, color: str, width: float):
        cells, _ = self._grid_layout(i + 1, TRIAGE_COLS)
        x, y = cells[i]
        box = pv.Box(bounds=(x - 0.5, x + 0.5, y - 0.5, y + 0.5, 0.01, 0.01))
        return self.plotter.add_mesh(box, style="wireframe", color=color, line_width=width, name=name,
                                     lighting=False, render=False)

    def _draw_triage_marks(self):
        pl = self.plotter
        for a in self._frames.values():
            pl.remove_actor(a, render=False)
        self._frames = {}
        items = self.page_items()
        for i, item in enumerate(items):
            if item.subject in self.triage_marks:
                self._frames[item.subject] = self._frame(i, f"mark{i}", "red", 6)
        if items:
            self._frame(self.triage_cursor, "cursor", "yellow", 3)
        marked = ", ".join(f"{s}:{r}" for s, r in self.triage_marks.items()) or "none"
        pl.add_text(f"TRIAGE page {self.triage_page + 1}/{-(-len(self.queue) // (TRIAGE_ROWS * TRIAGE_COLS))}, "
                    f"view yaw {self.triage_yaw[0]:.0f}  marked bad: {marked}\n"
                    "arrows move   1-5 mark bad   g/space unmark   click toggles   Return commit page   "
                    "c cycle view   t review", position="upper_left", font_size=10, color="white", name="hud",
                    render=False)
        pl.render()

    def _cursor_subject(self):
        items = self.page_items()
        return items[self.triage_cursor].subject if items else None

    def _move_cursor(self, step: int):
        n = len(self.page_items())
        if n:
            self.triage_cursor = min(max(self.triage_cursor + step, 0), n - 1)
            self._draw_triage_marks()

    def cycle_triage_view(self):
        if self.mode == "triage":
            self.triage_yaw = self.triage_yaw[1:] + self.triage_yaw[:1]
            marks, cursor = dict(self.triage_marks), self.triage_cursor
            self.show_triage_page()
            self.triage_marks, self.triage_cursor = marks, cursor
            self._draw_triage_marks()

    def commit_page(self):
        """Append the page's verdicts: marked subjects bad (their reason), the others good."""
        if self.mode != "triage":
            return
        for item in self.page_items():
            reason = self.triage_marks.get(item.subject)
            self.log.append(item.subject, item.shard, "bad" if reason else "good", (reason,) if reason else ())
        n_pages = -(-len(self.queue) // (TRIAGE_ROWS * TRIAGE_COLS))
        self.triage_page = min(self.triage_page + 1, n_pages - 1)
        self.show_triage_page()

    def _on_click(self, position):
        if self.mode != "triage" or position is None:
            return
        x, y = position[0], position[1]
        col, row = int(round(x / CELL)), int(round(-y / CELL))
        if not (0 <= col < TRIAGE_COLS and 0 <= row < TRIAGE_ROWS):
            return
        i = row * TRIAGE_COLS + col
        items = self.page_items()
        if i < len(items):
            self.triage_cursor = i
            s = items[i].subject
            if s in self.triage_marks:
                self.triage_marks.pop(s)
            else:
                self.triage_marks[s] = "artifacts"
            self._draw_triage_marks()

    # -- lifecycle ------------------------------------------------------------------------------------
    def screenshot(self, path=None):
        return self.plotter.screenshot(path, return_img=True)

    def run(self):
        """Open the window and hand control to the reviewer."""
        self.plotter.show()
        self.close()

    def close(self):
        self.log.close()
        self.plotter.close()
