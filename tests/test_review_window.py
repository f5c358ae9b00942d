"""The review window driven by its keys: what each key writes, what the screen says, the 3D surface.

Sessions run off-screen (EGL) through the same key and click handlers as the window; one session
runs in a real window on Xvfb, typed with xdotool, when both are installed.
"""
import ctypes.util
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pyvista = pytest.importorskip("pyvista", reason="the review window needs pyvista")

from PIL import Image, ImageDraw, ImageFont  # noqa: E402

from datagen.cameras import intrinsics, look_at, rays  # noqa: E402
from datagen.errors import UserError  # noqa: E402
from datagen.files import atomic_write  # noqa: E402
from datagen.pipeline import JobSpec, make_index, run_sample, software_info  # noqa: E402
from datagen.shapes import decode_mesh  # noqa: E402
from datagen.dataset.shards import (INDEX_NAME, SHAPE_FIELD, ShardWriter, dumps, iter_tar_samples, read_index,  # noqa: E402
                            subject_id)
from tests.conftest import tiny_spec  # noqa: E402
from labeling_tool.review import app as review_app  # noqa: E402
from labeling_tool.cli import build_queue, main as label_main  # noqa: E402
from datagen.cameras import depth_points  # noqa: E402
from datagen.dataset.events import EventLog, read_log  # noqa: E402
from datagen.preview import font  # noqa: E402
from labeling_tool.review import (BACKGROUND, COLORS, FLAG_REASON, HELP, Layout, Prefetcher,  # noqa: E402
                                  QueueItem, ReviewApp, Window, fit_window, polydata, surface_actor, surface_mesh)
from labeling_tool.review.layout import NOTICE_COLORS, hud_height, text_line, text_size  # noqa: E402
from labeling_tool.compiler import compile_manifest  # noqa: E402
from labeling_tool.preflags import DETECTOR_NAMES  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
S0, S1, S2 = "subj00000000", "subj00000001", "subj00000002"


@pytest.fixture
def make_app(tiny_dataset, tmp_path):
    apps = []

    def make(reviewer="alice", queue=None, dataset=tiny_dataset, **kw):
        if queue is None:
            _, queue = build_queue(str(dataset), "all")
        kw.setdefault("window_size", (800, 450))
        app = ReviewApp(dataset, queue, reviewer, tmp_path / "labels", off_screen=True, **kw)
        apps.append(app)
        return app
    yield make
    for a in apps:
        a.close()


def written(tmp_path, reviewer="alice"):
    events, problems = read_log(tmp_path / "labels" / f"{reviewer}.jsonl")
    assert problems == []
    return [(e.subject, e.action, e.reasons) for e in events]


def press(app, keys: str):
    for k in keys.split():
        app.press(k)


# ------------------------------------------------------------------------------------------------
# Triage commits


def test_triage_commit_writes_only_the_changes_and_new_cells(make_app, tmp_path):
    app = make_app()
    press(app, "Right 2")                   # review: subject 1 bad (broken back)
    press(app, "t")
    assert app.mode == "triage"
    lines, frame = app.cell_state(app.queue[1])
    assert "saved bad: back" in lines[0][0][0] and frame is not None  # the saved verdict is on the cell
    press(app, "Return")
    assert written(tmp_path) == [(S1, "bad", ("broken_back",)), (S0, "good", ()), (S2, "good", ())]
    assert app.log.verdict(S1).action == "bad"  # not overwritten by the commit
    press(app, "Return")                    # the same page again: nothing to write, and it says so
    assert len(written(tmp_path)) == 3
    assert app.notice[0] == "warn" and "nothing to commit" in app.notice[1]


def test_triage_flips_a_saved_verdict_only_when_told(make_app, tmp_path):
    app = make_app()
    press(app, "2 g g t")                   # 0 bad, 1 good, 2 good; triage opens on subject 2
    assert app.triage_cursor == 2
    press(app, "Left Left space")           # cell 0 (saved bad) flips to good
    press(app, "Right 5")                   # cell 1 (saved good) becomes bad: other
    assert app.pending == {S0: ("good", ()), S1: ("bad", ("other",))}
    press(app, "Right 5 g")                 # a change back to the saved verdict is no change
    assert S2 not in app.pending
    press(app, "Return")
    assert written(tmp_path)[3:] == [(S0, "good", ()), (S1, "bad", ("other",))]
    assert "1 kept their saved verdict" in app.notice[1]


def test_pages_can_be_left_and_revisited_without_committing(make_app, tmp_path):
    app = make_app(triage_shape=(1, 2), start_in_triage=True)   # pages [0, 1], [2]
    press(app, "3")                         # subject 0 bad: artifacts, not written yet
    press(app, "n")
    assert app.triage_page == 1 and written(tmp_path) == []
    press(app, "Return")                    # commits page 2 only
    assert written(tmp_path) == [(S2, "good", ())]
    assert "last page" in app.notice[1]
    press(app, "p")
    assert app.pending == {S0: ("bad", ("artifacts",))}  # the change waited on its page
    lines, frame = app.cell_state(app.queue[0])
    assert "new > bad: artifacts" in lines[0][0][0] and frame[1] >= 4
    press(app, "Next Prior Return")         # PgDn / PgUp move too
    assert written(tmp_path)[1:] == [(S0, "bad", ("artifacts",)), (S1, "good", ())]
    assert app.triage_page == 1             # a commit moves on to the next page


def test_quitting_with_changes_not_committed_asks_twice(make_app, tmp_path):
    app = make_app(start_in_triage=True)
    press(app, "2 Escape")
    assert not app.closed and app.notice[0] == "warn" and "not committed" in app.notice[1]
    press(app, "Escape")
    assert app.closed and written(tmp_path) == []


def test_a_skip_is_decided_later_in_review_and_compile_alike(make_app, tiny_dataset, tmp_path):
    """s means "decide later": not reviewed in the window (counts, u, where a session resumes, a triage
    commit leaves it) nor in compile (unreviewed there)."""
    app = make_app()
    press(app, "s g")                       # 0 skipped, 1 good; on subject 2
    assert (app.pos, app.done, app.skipped) == (2, 1, 1)
    assert "reviewed 1, left 2 (1 skipped)" in app.hud_lines[0][0]
    press(app, "Right u")                   # u comes back to the skipped subject
    assert app.pos == 0
    m = compile_manifest(tiny_dataset, tmp_path / "labels")
    counts = m["header"]["counts"]
    assert counts["reviewed"] == 1 and counts["unreviewed"] == 2
    assert {r["subject"]: r["reviewers"] for r in m["subjects"]}[S0] == []
    strict = compile_manifest(tiny_dataset, tmp_path / "labels", unreviewed="reject")
    assert {r["subject"]: r["verdict"] for r in strict["subjects"]} == {S0: "rejected", S1: "accepted",
                                                                       S2: "rejected"}
    app.close()
    again = make_app()                      # a new session resumes at the skipped subject
    assert (again.pos, again.done, again.skipped) == (0, 1, 1)
    press(again, "t Return")                # a commit: good for the new cell, the skipped one waits
    assert written(tmp_path)[2:] == [(S2, "good", ())] and again.log.verdict(S0).action == "skip"
    assert "1 skipped left unreviewed" in again.notice[1] and (again.done, again.skipped) == (2, 1)
    press(again, "t")
    assert again.pos == 0
    press(again, "g")                       # decided: reviewed now
    assert (again.done, again.skipped) == (3, 0)
    press(again, "z")                       # undone: skipped again, unreviewed again
    assert (again.done, again.skipped) == (2, 1) and again.log.verdict(S0).action == "skip"
    press(again, "u")
    assert again.pos == 0


# ------------------------------------------------------------------------------------------------
# Undo, reasons, the cursor


def test_undo_names_the_subject_whose_verdict_it_cancels(make_app, tmp_path):
    app = make_app()
    press(app, "g 5 z")
    assert written(tmp_path) == [(S0, "good", ()), (S1, "bad", ("other",)), (S1, "undo", ())]
    assert app.pos == 1 and app.notice[0] == "undo" and S1 in app.notice[1]
    press(app, "Right g z")                 # on the last subject (no move after the verdict)
    assert written(tmp_path)[-2:] == [(S2, "good", ()), (S2, "undo", ())]
    press(app, "z z z")                     # undo subject 0 too, then nothing is left to undo
    assert written(tmp_path)[-1] == (S0, "undo", ()) and app.log.verdicts() == {}
    assert app.notice == ("warn", "nothing to undo")
    press(app, "t Return z")                # in triage: the last committed cell
    assert written(tmp_path)[-1] == (S2, "undo", ()) and app.triage_cursor == 2


def test_the_confirmation_follows_the_subject_it_speaks_of(make_app):
    """A confirmation is shown with the view it was given on (the next subject after a verdict) and
    goes when another subject or page is shown; the 3D view of the same subject keeps it."""
    app = make_app()
    press(app, "4")
    assert app.pos == 1 and app.hud_lines[2][0] == f"saved: {S0} bad: blur"
    press(app, "Right")
    assert app.notice == ("saved", "") and app.hud_lines[2][0] == ""
    press(app, "Left Left")
    assert app.pos == 0 and app.hud_lines[2][0] == ""
    press(app, "z")                          # the undo goes to subject 0, and says so there
    assert app.pos == 0 and app.hud_lines[2][0].startswith(f"undone: {S0}")
    press(app, "v")
    assert app.mode == "3d" and app.hud_lines[2][0].startswith(f"undone: {S0}")
    press(app, "v t Return")                 # a commit's line stays while the cursor moves on its page
    press(app, "Left")
    assert app.hud_lines[2][0].startswith("committed page 1")
    press(app, "t")
    assert app.hud_lines[2][0] == ""


def test_u_with_nothing_left_to_review_says_so_and_stays(make_app, tmp_path):
    app = make_app()
    press(app, "g s")                        # on subject 2, the skipped 1 behind
    press(app, "u")
    assert app.pos == 1
    press(app, "g g Left")                   # all three reviewed; on subject 1
    press(app, "u")
    assert app.pos == 1 and app.notice == ("warn", "all 3 subjects of this queue are reviewed: no unreviewed "
                                                   "subject left")
    press(app, "v u")                        # in the 3D view too: the head stays
    assert (app.mode, app.pos) == ("3d", 1) and app.surface.actor is not None and app.notice[0] == "warn"
    assert len(written(tmp_path)) == 4


def test_the_window_opens_with_what_the_log_held(make_app, tmp_path):
    log = EventLog(tmp_path / "labels", "alice")
    log.append(S0, "shard-000000", "good")
    log.close()
    with open(log.path, "ab") as f:
        f.write(b'{"seq": 2, "subj')
    app = make_app()
    assert app.hud_lines[2] == (f"resumed: 1 verdict from {log.path} (1 of 3 in this queue reviewed); "
                                "line 2: partial last line, dropped", NOTICE_COLORS["warn"])


def test_triage_reason_keys_stay_on_the_cell_and_flips_use_the_preflag(make_app, tmp_path):
    queue = [QueueItem(S0, "shard-000000", 0.9, (("janus", 0.9), ("blur", 0.6))),
             QueueItem(S1, "shard-000000", 0.7, (("blur", 0.7),)), QueueItem(S2, "shard-000001")]
    app = make_app(queue=queue, start_in_triage=True)
    press(app, "4")
    assert app.triage_cursor == 0 and app.pending == {S0: ("bad", ("blur",))}
    press(app, "1")                          # another reason for the same cell: still cell 0
    assert app.triage_cursor == 0 and app.pending == {S0: ("bad", ("multiple_faces",))}
    app.click(*app.cell_center(1))
    app.click(*app.cell_center(2))
    assert app.pending[S1] == ("bad", ("blur",)) and app.pending[S2] == ("bad", ("artifacts",))
    lines, _ = app.cell_state(queue[0])
    assert "janus 0.90, blur 0.60" in lines[1][0] and "flip=faces" in lines[1][0]
    press(app, "Return")
    assert written(tmp_path) == [(S0, "bad", ("multiple_faces",)), (S1, "bad", ("blur",)),
                                 (S2, "bad", ("artifacts",))]


def test_every_detector_has_a_default_reason():
    assert set(FLAG_REASON) == set(DETECTOR_NAMES)


def test_a_repeated_verdict_writes_nothing_and_says_so(make_app, tmp_path):
    app = make_app()
    press(app, "3 Left 3")
    assert written(tmp_path) == [(S0, "bad", ("artifacts",))]
    assert "already bad: artifacts" in app.notice[1]


# ------------------------------------------------------------------------------------------------
# What the screen shows


def test_confirmation_labels_and_help_panel(make_app):
    app = make_app(window_size=(1280, 720))
    press(app, "4")
    assert app.notice == ("saved", f"saved: {S0} bad: blur")
    assert app.hud_lines[2][0] == f"saved: {S0} bad: blur"
    shot = app.screenshot()
    assert (np.abs(shot[app.layout.top // 2:app.layout.top].astype(int) - BACKGROUND).sum(-1) > 150).sum() > 200
    layout = app.layout
    x0, y0, x1, y1 = layout.image_box(0)
    label = shot[y1 + 3:y1 + 3 + layout.label_font + 4, x0 - 4:x1]   # the view label under cell 0
    assert (np.abs(label.astype(int) - BACKGROUND).sum(-1) > 150).sum() > 20
    press(app, "h")
    assert app.help_layer.visible()
    x0, y0 = app.help_origin                # an opaque dark panel over the views
    panel = app.screenshot()[y0 + 5:y0 + 20, x0 + 5:x0 + 300].astype(int)   # above the first heading
    assert panel.std(axis=(0, 1)).max() < 1 and panel.mean() < 30
    keys = {k for k, _ in HELP}
    assert {"Return", "z", "space / click", "Escape"} <= keys
    press(app, "Escape")                     # Escape closes the help first
    assert not app.closed and not app.show_help and not app.help_layer.visible()


def ink(img: np.ndarray) -> np.ndarray | None:
    """The part of ``img`` inside the bounding box of what differs from the background (None: nothing)."""
    rows, cols = np.nonzero(np.abs(img.astype(int) - BACKGROUND).sum(-1) > 30)
    return None if not len(rows) else img[rows.min():rows.max() + 1, cols.min():cols.max() + 1]


def written_label(text: str, size: int, shape) -> np.ndarray:
    """``text`` as the window's font writes it, in the label colour, on the background."""
    img = Image.new("RGB", (shape[1], shape[0]), BACKGROUND)
    ImageDraw.Draw(img).text((4, 2), text, fill=COLORS["dim"], font=ImageFont.load_default(size=size))
    return np.asarray(img)


def test_view_labels_name_yaw_and_pitch(make_app, tiny_dataset):
    """The text under each view on the screen is its name, yaw and pitch, as the dataset stores them."""
    app = make_app(window_size=(1280, 720), columns=4)
    _, fields = next(iter_tar_samples(Path(tiny_dataset) / "shard-000000.tar"))   # read apart from the window
    views = json.loads(fields["json"])["views"]
    assert len(views) == 4
    shot, layout = app.screenshot(), app.layout
    for i, v in enumerate(views):
        x0, y0, x1, y1 = layout.image_box(i)
        sx, _ = layout.slot(i)
        strip = shot[y1 + 2:y1 + 6 + layout.label_font + 6, sx:sx + layout.slot_w]   # under the image
        on_screen = ink(strip)
        yaw, pitch = round(v["yaw_deg"]) % 360, round(v["pitch_deg"])
        want = ink(written_label(f"{v['name']}  yaw {yaw}  pitch {pitch}", layout.label_font, strip.shape))
        assert on_screen is not None and on_screen.shape == want.shape, f"view {i}: {v['name']}"
        assert np.abs(on_screen.astype(int) - want).mean() < 2, f"view {i}: {v['name']}"
        other = ink(written_label(f"{v['name']}  yaw {(yaw + 45) % 360}  pitch {pitch}", layout.label_font,
                                  strip.shape))       # the check can fail: another yaw is not what is shown
        assert other.shape != on_screen.shape or np.abs(on_screen.astype(int) - other).mean() > 2


def test_default_window_fits_the_screen():
    for screen in [(1920, 1080), (1366, 768), (3840, 2160)]:
        w, h = fit_window(screen)
        assert w <= screen[0] and h <= screen[1] and w >= 0.9 * screen[0] and h >= 0.85 * screen[1]


def test_layout_cells_do_not_overlap_and_clicks_find_them():
    lay = Layout.fit(1920, 1080, 40, 8, 2)
    boxes = [lay.image_box(i) for i in range(40)]
    assert all(b[2] <= lay.width and b[3] <= lay.height for b in boxes) and lay.cell >= 120
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        assert lay.index_at((x0 + x1) / 2, (y0 + y1) / 2) == i
    assert lay.index_at(5, 5) is None


@pytest.mark.parametrize("value", ["big", "1920", "10x10", "1920x-5"])
def test_window_size_mistakes_are_one_line(tiny_dataset, tmp_path, capsys, value):
    with pytest.raises(SystemExit) as e:
        label_main(["review", str(tiny_dataset), "--reviewer", "a", "--labels", str(tmp_path / "l"),
                    "--off-screen", "--window-size", value])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1 and "--window-size" in err


# ------------------------------------------------------------------------------------------------
# The 3D surface


def sphere_views(radius=0.3, resolution=48):
    """Depth and mask of a sphere at the origin seen from the front (+z, red) and the back (-z, blue)."""
    K = intrinsics(4.2634)
    out = []
    for z, color in ((2.7, (220, 30, 30)), (-2.7, (30, 30, 220))):
        c2w = look_at(np.array([0.0, 0.0, z]))
        o, d = (t[0].numpy().astype(np.float64) for t in rays(c2w[None], K[None], resolution))
        b = (o * d).sum(1)
        disc = b ** 2 - ((o * o).sum(1) - radius ** 2)
        hit = disc > 0
        depth = np.where(hit, -b - np.sqrt(np.maximum(disc, 0)), 0).reshape(resolution, resolution)
        alpha = np.where(hit, 255, 0).astype(np.uint8).reshape(resolution, resolution)
        rgb = np.broadcast_to(np.array(color, np.uint8), (resolution, resolution, 3)).copy()
        out.append((c2w, K, rgb, alpha, depth.astype(np.float32)))
    return out


def test_depth_points_follow_the_camera_convention():
    views = sphere_views()
    for c2w, K, _, alpha, depth in views:
        rr, cc = np.nonzero(alpha)
        p = depth_points(c2w, K, 48, rr, cc, depth[rr, cc].astype(np.float64))
        assert np.allclose(np.linalg.norm(p, axis=1), 0.3, atol=1e-4)


def test_the_surface_occludes_what_is_behind_it():
    arrays = surface_mesh(sphere_views())
    assert arrays is not None and len(arrays[1]) > 500
    mesh = polydata(*arrays)
    assert mesh.GetNumberOfPolys() == len(arrays[1]) and mesh.GetNumberOfPoints() == len(arrays[0])
    for z, want in ((-3.0, 2), (3.0, 0)):   # from behind only the back camera's blue, from the front red
        win = Window(True, (200, 200), "test")
        win.plotter.set_background("black")
        surface_actor(win.plotter, mesh)
        win.plotter.camera_position = [(0, 0, z), (0, 0, 0), (0, 1, 0)]
        win.render()
        img = win.screenshot().astype(int)
        win.close()
        obj = img.sum(-1) > 60
        assert obj.mean() > 0.05
        assert (img[obj].argmax(-1) == want).mean() > 0.97


def step_views(jump: float, resolution: int = 48):
    """A plane facing the camera at depth 2.7 with its right half nearer by ``jump`` (a depth
    discontinuity down the middle), one view."""
    K = intrinsics(4.2634)
    c2w = look_at(np.array([0.0, 0.0, 2.7]))
    depth = np.full((resolution, resolution), 2.7, np.float32)
    depth[:, resolution // 2:] -= jump
    alpha = np.full((resolution, resolution), 255, np.uint8)
    rgb = np.full((resolution, resolution, 3), 128, np.uint8)
    return [(c2w, K, rgb, alpha, depth)], K, resolution


def test_the_surface_has_no_triangle_across_a_depth_discontinuity():
    for jump in (0.03, 0.06, 0.3):          # 2.3, 4.5 and 23 times the sample spacing (0.013 at 48 px)
        views, K, R = step_views(jump)
        points, tris, _ = surface_mesh(views)
        near = np.abs(np.linalg.norm(points - np.array([0, 0, 2.7]), axis=1) - 2.7) > jump / 2   # moved half
        sides = near[tris]
        assert len(tris) > 1000
        assert np.all(sides.all(axis=1) | ~sides.any(axis=1)), f"a triangle spans the jump of {jump}"
    views, _, _ = step_views(0.0)           # a plane tilted 45 degrees (steep but smooth) stays whole
    c2w, K, rgb, alpha, _ = views[0]
    rr, cc = np.mgrid[0:48, 0:48]
    xn, yn = ((cc + 0.5) / 48 - K[0, 2]) / K[0, 0], ((rr + 0.5) / 48 - K[1, 2]) / K[1, 1]
    t = 2.7 / (1 - xn)                      # the plane Z = 2.7 + X in camera coordinates
    tilted = (t * np.sqrt(1 + xn ** 2 + yn ** 2)).astype(np.float32)   # distance along each ray
    _, tris, _ = surface_mesh([(c2w, K, rgb, alpha, tilted)])
    assert len(tris) >= 0.95 * 2 * 47 ** 2


def test_a_delayed_job_is_made_only_if_still_wanted_or_needed():
    """The 3D surface is prepared ahead only for a subject the reviewer stays on, and v never waits
    for that delay."""
    made = []

    def maker(key):
        return lambda: made.append(key) or key
    jobs = Prefetcher(4)
    jobs.want([("a", maker("a"), 0.5)])
    jobs.want([("b", maker("b"))])          # moved on before a was due: a is not made
    assert jobs.get("b", maker("b")) == "b"
    time.sleep(0.8)
    assert made == ["b"]
    jobs.want([("c", maker("c"), 30.0)])
    started = time.monotonic()
    assert jobs.get("c", maker("c")) == "c" and time.monotonic() - started < 10   # needed now: made at once
    assert made == ["b", "c"]
    jobs.close()


def test_3d_view_is_a_surface_framed_on_the_head(make_app):
    app = make_app(window_size=(640, 480))
    press(app, "v")
    assert app.mode == "3d" and app.surface.actor.GetMapper().GetInput().GetNumberOfPolys() > 100
    img = app.screenshot()
    obj = np.abs(img.astype(int) - BACKGROUND).sum(-1) > 40
    obj[:app.layout.top] = False            # the heads-up text
    rows, cols = np.nonzero(obj)
    assert rows.max() - rows.min() > 0.4 * 480 and abs((cols.min() + cols.max()) / 2 - 320) < 60
    assert "drag rotates" in app.hud_lines[3][0]
    press(app, "Right")                      # moving on leaves the 3D view
    assert app.mode == "review" and app.pos == 1 and app.surface.actor is None


def test_3d_view_shows_the_stored_mesh_when_there_is_one(make_app, tmp_path_factory):
    """A dataset made with --save-shape: v shows each subject's stored mesh, as stored, and says so;
    without one the surface is built from the views, and says that."""
    shaped = tmp_path_factory.mktemp("shaped") / "ds"
    run_sample(tiny_spec(shaped, subjects=2, views=4, resolution=32, save_shape=32), progress=False)
    fields = dict(iter_tar_samples(shaped / "shard-000000.tar"))[S0]
    stored = decode_mesh(fields[SHAPE_FIELD], S0)
    app = make_app(dataset=shaped, window_size=(640, 480))
    press(app, "v")
    shown = app.surface.actor.GetMapper().GetInput()
    assert app.mode == "3d" and shown.GetNumberOfPoints() == len(stored.vertices)
    assert shown.GetNumberOfPolys() == len(stored.faces)
    assert np.allclose(pyvista.wrap(shown).points, stored.vertices)
    assert app.hud_lines[0][0].endswith(f"3D view: the stored mesh ({SHAPE_FIELD}, {len(stored.vertices):,} "
                                        "vertices)")
    plain = make_app(reviewer="bob", window_size=(640, 480))
    press(plain, "v")
    assert plain.hud_lines[0][0].endswith("3D view: built from the views' depth and masks (no stored mesh)")


def test_verdicts_and_undo_typed_in_the_3d_view(make_app, tmp_path):
    """A verdict in 3D is saved and the next subject's views come (on the last subject the 3D view
    stays); z with nothing to undo leaves the head on screen, with the notice; an undo goes to the
    subject whose verdict it cancels."""
    app = make_app(window_size=(640, 480))
    press(app, "v")
    top = app.layout.top                    # the heads-up block above, the head below
    head = app.screenshot()
    press(app, "z")
    assert app.mode == "3d" and app.surface.actor is not None and app.notice == ("warn", "nothing to undo")
    shot = app.screenshot()
    assert np.array_equal(shot[top:], head[top:])                 # the head, as it was
    assert (np.abs(head[top:].astype(int) - BACKGROUND).sum(-1) > 40).mean() > 0.05
    assert (np.abs(shot[:top].astype(int) - head[:top]).sum(-1) > 30).sum() > 50   # the notice, redrawn
    press(app, "2")
    assert written(tmp_path) == [(S0, "bad", ("broken_back",))]
    assert (app.mode, app.pos, app.surface.actor, app.grid_layer.visible()) == ("review", 1, None, True)
    press(app, "v z")
    assert written(tmp_path)[-1] == (S0, "undo", ()) and (app.mode, app.pos, app.grid_layer.visible()) == ("review", 0, True)
    press(app, "Right Right v g")            # the last subject: saved, and its head stays on screen
    assert written(tmp_path)[-1] == (S2, "good", ()) and app.mode == "3d" and app.notice[0] == "saved"
    assert (np.abs(app.screenshot()[top:].astype(int) - BACKGROUND).sum(-1) > 40).mean() > 0.05


# ------------------------------------------------------------------------------------------------
# Without a display


@pytest.mark.parametrize("display, message", [(None, "no display: $DISPLAY is not set"),
                                              (":987", "cannot open the X display ':987'")])
def test_no_display_is_one_line_and_creates_nothing(tiny_dataset, tmp_path, display, message):
    if display and ctypes.util.find_library("X11") is None:
        pytest.skip("libX11 is not installed: the display cannot be checked")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    if display:
        env["DISPLAY"] = display
    env["PYTHONPATH"] = str(ROOT)
    labels = tmp_path / "labels"
    done = subprocess.run([sys.executable, "-m", "labeling_tool.cli", "review", str(tiny_dataset), "--reviewer", "a",
                           "--labels", str(labels)], env=env, capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0].startswith("label-tool review: error: ") and message in lines[0]
    assert done.stdout == "" and not labels.exists()


# ------------------------------------------------------------------------------------------------
# A whole session: what compile gives is exactly what was typed


def test_a_session_in_review_and_triage_compiles_to_the_typed_verdicts(make_app, tiny_dataset, tmp_path):
    app = make_app(triage_shape=(1, 2))
    press(app, "2 g z 1")          # 0 bad (back); 1 good, undone, then bad (faces)
    press(app, "t")                # triage on subject 2's page
    press(app, "Return")           # 2 new -> good
    press(app, "p space Right g Return")   # page 1: flip 0 to good, 1 to good
    press(app, "z")                # undo the last commit's last verdict: 1 is bad (faces) again
    app.close()
    m = compile_manifest(tiny_dataset, tmp_path / "labels")
    got = {r["subject"]: (r["verdict"], r["reasons"]) for r in m["subjects"]}
    assert got == {S0: ("accepted", []), S1: ("rejected", ["multiple_faces"]), S2: ("accepted", [])}


def start_xvfb(*extra):
    """A virtual display (Xvfb, 1280x800) -> (process, name); skips when Xvfb or xdotool is missing
    (they are not required: CI machines may lack them)."""
    if not (shutil.which("Xvfb") and shutil.which("xdotool")):
        pytest.skip("Xvfb and xdotool are needed for the real-window session (apt-get install xvfb xdotool)")
    for n in range(140, 200):
        if not Path(f"/tmp/.X{n}-lock").exists() and not Path(f"/tmp/.X11-unix/X{n}").exists():
            break
    proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", "1280x800x24", "-nolisten", "tcp", "-noreset", *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 20
    while not Path(f"/tmp/.X11-unix/X{n}").exists() and time.time() < deadline:
        time.sleep(0.05)
    return proc, f":{n}"


@pytest.fixture
def xvfb():
    proc, name = start_xvfb()
    yield name
    proc.terminate()
    proc.wait()


@pytest.fixture
def xvfb_without_opengl():
    proc, name = start_xvfb("-extension", "GLX")
    yield name
    proc.terminate()
    proc.wait()


def test_a_display_without_opengl_is_one_line_and_creates_nothing(xvfb_without_opengl, tiny_dataset, tmp_path):
    env = dict(os.environ, DISPLAY=xvfb_without_opengl, PYTHONPATH=str(ROOT))
    labels = tmp_path / "new" / "labels"
    done = subprocess.run([sys.executable, "-m", "labeling_tool.cli", "review", str(tiny_dataset), "--reviewer", "a",
                           "--labels", str(labels)], env=env, capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert "has no OpenGL (GLX)" in lines[0] and "--off-screen" in lines[0]
    assert not (tmp_path / "new").exists()


def test_a_window_vtk_cannot_open_leaves_no_labels_folder(tiny_dataset, tmp_path, monkeypatch):
    """The display opens, then VTK fails to make the window: no log and no folder stay behind."""
    class Display:
        lib = handle = None

        def screen_size(self):
            return 1280, 800

        def close(self):
            pass

    def no_window(*args, **kwargs):
        raise UserError("VTK could not open a window on the display ':0' (it made a vtkEGLRenderWindow)")

    monkeypatch.setattr(review_app, "XDisplay", Display)
    monkeypatch.setattr(review_app, "Window", no_window)
    _, queue = build_queue(str(tiny_dataset), "all")
    labels = tmp_path / "new" / "deeper" / "labels"
    with pytest.raises(UserError, match="VTK could not open a window"):
        ReviewApp(tiny_dataset, queue, "alice", labels)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "kept").mkdir()              # a folder that was there before stays, with its logs
    (tmp_path / "kept" / "bob.jsonl").write_text("")
    with pytest.raises(UserError):
        ReviewApp(tiny_dataset, queue, "alice", tmp_path / "kept")
    assert sorted(p.name for p in (tmp_path / "kept").iterdir()) == ["bob.jsonl"]


@pytest.fixture(scope="module")
def two_page_dataset(tiny_dataset, tmp_path_factory):
    """45 subjects in one shard (two triage pages of 40): the tiny dataset's subjects under new ids."""
    out = tmp_path_factory.mktemp("two-pages") / "ds"
    samples = list(iter_tar_samples(Path(tiny_dataset) / "shard-000000.tar"))
    tmp = out.parent / "building"
    tmp.mkdir()
    writer = ShardWriter(tmp, 0)
    for i in range(45):
        _, fields = samples[i % len(samples)]
        key = subject_id(i)
        meta = dict(json.loads(fields["json"]), subject_id=key, subject_index=i)
        writer.add_subject(key, [(f"{key}.json", dumps(meta))] + [(f"{key}.{f}", b) for f, b in fields.items()
                                                                   if f != "json"])
    writer.commit()
    tiny = read_index(tiny_dataset)
    spec = JobSpec(out=str(out), gan="procedural", generator_options=tiny["settings"]["generator_options"],
                   protocol="360", subjects=45, resolution=32, views=4, seed=7, shard_size=45,
                   software=software_info())
    atomic_write(tmp / INDEX_NAME, dumps(make_index(spec, tiny["generator"])))
    tmp.rename(out)
    return out


def grab(display: str, path: Path) -> np.ndarray:
    """The X screen's pixels, as a person would see them (ImageMagick's import reads the X server)."""
    subprocess.run(["import", "-window", "root", str(path)], env=dict(os.environ, DISPLAY=display), check=True,
                   capture_output=True, timeout=60)
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


class RealWindow:
    """``label-tool review`` in a real window on an Xvfb display (run in ``tmp_path``, so that a
    relative --labels is as a person types it), typed with xdotool, its screen read with import."""

    def __init__(self, display: str, tmp_path: Path, dataset, reviewer: str, labels: str, size: str):
        self.display, self.tmp_path, self.log = display, tmp_path, tmp_path / labels / f"{reviewer}.jsonl"
        self.env = dict(os.environ, DISPLAY=display, PYTHONPATH=str(ROOT))
        self.shots = iter(range(1000))
        self.proc = subprocess.Popen([sys.executable, "-m", "labeling_tool.cli", "review", str(dataset),
                                      "--reviewer", reviewer, "--labels", labels, "--window-size", size],
                                     env=self.env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        deadline, window = time.time() + 90, ""
        while not window and self.proc.poll() is None and time.time() < deadline:
            window = self.xdo("search", "--name", f"label-tool review: {reviewer}").strip()
            time.sleep(0.2)
        assert window, f"no window: {self.proc.poll()} {self.proc.stderr.read() if self.proc.poll() is not None else ''}"
        self.window = window.split()[0]
        self.xdo("windowfocus", "--sync", self.window)
        deadline = time.time() + 60
        while self.screen().std() < 20 and time.time() < deadline:   # the first frame: views and text
            time.sleep(0.2)

    def xdo(self, *args) -> str:
        return subprocess.run(["xdotool", *args], env=self.env, capture_output=True, text=True, timeout=60).stdout

    def events(self) -> list:
        return read_log(self.log)[0] if self.log.exists() else []

    def screen(self, name: str | None = None) -> np.ndarray:
        return grab(self.display, self.tmp_path / f"{name or f'shot{next(self.shots)}'}.png")

    def key(self, k: str, expect: int):
        """Type ``k`` and wait until the log holds ``expect`` events."""
        self.xdo("key", "--window", self.window, k)
        deadline = time.time() + 60
        while len(self.events()) < expect and time.time() < deadline:
            time.sleep(0.05)
        assert len(self.events()) == expect, f"after {k}: {self.events()}"

    def settled(self, name: str | None = None) -> np.ndarray:
        """The screen once two grabs in a row agree (saved as ``name``.png when named)."""
        last = self.screen()
        for _ in range(50):
            time.sleep(0.1)
            now = self.screen()
            if np.array_equal(now, last):
                break
            last = now
        return self.screen(name) if name else last

    def key_changes_screen(self, k: str, before: np.ndarray, least: float, name: str | None = None) -> np.ndarray:
        """Type ``k``, wait for the screen to change (a share ``least`` of its pixels) and settle; the new screen."""
        self.xdo("key", "--window", self.window, k)
        deadline = time.time() + 60
        while time.time() < deadline:
            time.sleep(0.1)
            if (np.abs(self.screen() - before).sum(-1) > 30).mean() > least:
                return self.settled(name)
        raise AssertionError(f"the screen did not change after {k}")

    def finish(self) -> tuple[str, str]:
        """(stdout, stderr) once the window has closed with exit status 0 and no traceback."""
        out, err = self.proc.communicate(timeout=60)
        assert self.proc.returncode == 0 and "Traceback" not in err, err
        return out, err


@pytest.fixture
def real_window(xvfb, tmp_path):
    if not shutil.which("import"):
        pytest.skip("ImageMagick's import is needed to read the screen")
    opened = []

    def start(dataset, reviewer, labels="labels", size="1000x600"):
        opened.append(RealWindow(xvfb, tmp_path, dataset, reviewer, labels, size))
        return opened[-1]
    yield start
    for w in opened:
        if w.proc.poll() is None:
            w.proc.kill()
            w.proc.wait()


def test_real_window_session_typed_with_xdotool(real_window, two_page_dataset, tmp_path):
    win = real_window(two_page_dataset, "zoe")
    grid = win.settled()
    assert grid.std() > 20                  # not a blank window
    win.key("4", 1)                         # 0 bad (blur)
    win.key("g", 2)                         # 1 good
    win.key("z", 3)                         # undo names subject 1
    win.key("5", 4)                         # 1 bad (other)
    grid = win.settled()
    surface = win.key_changes_screen("v", grid, least=0.04)   # 3D on: the grid of views gives way to a head
    middle = surface[150:500, 350:650]      # the window is at the screen's top left, 1000x600
    assert (np.abs(middle - BACKGROUND).sum(-1) > 40).mean() > 0.2   # the head, in the middle
    views = win.key_changes_screen("v", surface, least=0.04)  # and back to the views
    assert np.abs(views - grid).sum(-1).mean() < 5            # as they were (the notice line aside)
    triage = win.key_changes_screen("t", views, least=0.1)
    flipped = win.key_changes_screen("space", triage, least=0.0005)   # cell 2 (no verdict) flips to bad: framed red
    red = (flipped[..., 0] > 200) & (flipped[..., 1] < 90) & (flipped[..., 2] < 90)
    assert red.sum() > 3 * (red & (triage[..., 0] > 200)).sum() and red.sum() > 200
    win.key("Return", 4 + 38)               # page 1: 2 bad (artifacts), 37 more good, 0 and 1 kept; page 2 shown
    page2 = win.settled()
    assert (np.abs(page2 - flipped).sum(-1) > 30).mean() > 0.1   # 5 subjects on the second page, not 40
    page1 = win.key_changes_screen("p", page2, least=0.1)       # a triage page change: back to page 1 ...
    assert (np.abs(page1 - flipped).sum(-1) > 30).mean() < 0.05  # ... as it was, the flipped cell included
    win.key_changes_screen("n", page1, least=0.1)
    win.key("Escape", 42)
    out, _ = win.finish()
    assert "zoe: 40/45 reviewed" in out
    got = [(e.subject, e.action, e.reasons) for e in win.events()]
    assert got[:5] == [(S0, "bad", ("blur",)), (S1, "good", ()), (S1, "undo", ()), (S1, "bad", ("other",)),
                       (S2, "bad", ("artifacts",))]
    assert got[5:] == [(subject_id(i), "good", ()) for i in range(3, 40)]
    m = compile_manifest(two_page_dataset, tmp_path / "labels")
    verdicts = {r["subject"]: r["verdict"] for r in m["subjects"]}
    assert [verdicts[s] for s in (S0, S1, S2)] == ["rejected"] * 3 and m["header"]["counts"]["unreviewed"] == 5


def hud_line(shot: np.ndarray, k: int, window_height: int, window_width: int) -> np.ndarray:
    """Line ``k`` of the heads-up block (0 status, 1 detail, 2 notice, 3 keys) of a window at the screen's top left."""
    size = text_size(window_height)
    y = 5 + k * (size + 6)
    return shot[y:y + size + 6, 8:window_width - 8]


def test_real_window_says_what_the_log_recovered_and_what_u_finds(real_window, two_page_dataset, tmp_path):
    """Reopened after a crash cut its last line, the window says what it resumed from and names the
    cut line; u with every subject reviewed says so and stays; the notice goes when another subject
    is shown; triage cells at 1000x650 keep their verdicts in text."""
    log = EventLog(tmp_path / "labels", "yan")
    reasons = ["multiple_faces", "broken_back", "blur"]
    for i in range(44):
        log.append(subject_id(i), "shard-000000", *(("bad", (reasons[i % 3],)) if i % 5 == 3 else ("good",)))
    log.append(subject_id(44), "shard-000000", "skip")
    log.close()
    with open(log.path, "ab") as f:
        f.write(b'{"action": "good", "reasons": [], "reviewer": "y')   # a write a crash cut short
    W, H = 1000, 650
    win = real_window(two_page_dataset, "yan", size=f"{W}x{H}")
    size = text_size(H)

    def notice_reads(shot, message, kind):
        want = np.asarray(text_line(message, NOTICE_COLORS[kind], size, W - 16)).astype(int)
        return np.abs(hud_line(shot, 2, H, W) - want).mean() < 1

    opened = win.settled("review_restart_after_cut_line")
    assert notice_reads(opened, "resumed: 45 verdicts from labels/yan.jsonl (44 of 45 in this queue reviewed); "
                                "line 46: partial last line, dropped", "warn")
    win.key("g", 46)                        # the skipped subject, the last one left, good: all reviewed
    saved = win.settled()
    nothing_left = win.key_changes_screen("u", saved, least=0.0003, name="review_u_nothing_left")
    assert notice_reads(nothing_left, "all 45 subjects of this queue are reviewed: no unreviewed subject left",
                        "warn")
    assert np.array_equal(hud_line(nothing_left, 0, H, W), hud_line(saved, 0, H, W))   # still on the last subject
    assert np.array_equal(nothing_left[hud_height(H):H, :W], saved[hud_height(H):H, :W])
    assert len(win.events()) == 46
    previous = win.key_changes_screen("Left", nothing_left, least=0.01)
    assert (np.abs(hud_line(previous, 2, H, W) - BACKGROUND).sum(-1) == 0).all()   # the notice spoke of 44
    page2 = win.key_changes_screen("t", previous, least=0.01)
    page1 = win.key_changes_screen("p", page2, least=0.1)
    flipped = win.key_changes_screen("space", page1, least=0.0003, name="review_triage_1000x650")
    layout = Layout.fit(W, H, 40, 8, 2)
    for i, text, color in ((0, "subj00000000  good", "good"), (3, "~0003 bad>good", "good"),
                           (8, "subj00000008  bad", "bad")):
        sx, _ = layout.slot(i)
        x0, y0, x1, y1 = layout.image_box(i)
        box = (slice(y1 + 6, y1 + 6 + layout.label_font), slice(sx + 4, sx + layout.slot_w - 5))   # no frame, no cursor
        want = Image.new("RGB", (W, H), BACKGROUND)
        ImageDraw.Draw(want).text((sx + 6, y1 + 4), text, fill=COLORS[color], font=font(layout.label_font))
        assert np.abs(flipped[box] - np.asarray(want).astype(int)[box]).mean() < 1, f"cell {i}: {text}"
    win.key_changes_screen("Escape", flipped, least=0.0003)   # a change not committed: a second Escape quits
    win.xdo("key", "--window", win.window, "Escape")
    _, err = win.finish()
    assert f"note: {Path('labels') / 'yan.jsonl'}:46: partial last line, dropped" in err
