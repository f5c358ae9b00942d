"""Review-window latency as a reviewer sees it: from a key press to the changed frame on the screen.

Starts a virtual X display (Xvfb, 1920x1080), opens ``label-tool review`` on it as a reviewer
would (its own process, a real pyvista window) and types keys through the XTEST extension, the way
xdotool types them. Each key is timed from the moment it is sent to the X server to the last
frame the window draws in answer (X DAMAGE events, until the window stays still for 150 ms);
the window's pixels are read before and after to check that the frame did change. Keys come at
a reviewer's pace (a pause after each answered key), so background preparation counts as it
would for a person.

Measured, per view size (128 px and 512 px views, 32 per subject): opening the shard (from
starting the command to the first complete frame), next subject, a verdict (event fsynced, next
subject shown), 3D on and off, entering triage, a triage page change (to a page not seen yet)
and a triage commit (40 events, next page shown). Reports p50/p95 against the goals and the
reviewer throughput they imply. The start-up is also taken apart, in fresh processes on the same
display: importing pyvista, its plotting package (which imports matplotlib), the window module,
making the plotter and its window (with and without pyvista's own probe of the display, which the
window skips) and drawing the first, empty frame.

Datasets: a few procedural subjects are rendered per size and their bytes repeated under new
subject ids (1,000 subjects at 128 px; fewer at 512 px, whose subjects are 18 MB each); the
window's costs do not depend on which head is shown. They are kept in ``--work`` for later runs.

    python -m benchmarks.gui_latency [--quick] [--work DIR] [--report-only]

Writes benchmarks/reports/gui_latency.md and .json (gui_latency_quick.* with --quick), and a
screenshot of each mode.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np


from benchmarks.common import (REPORTS, add_work_folder, benchmark_parser, bullets, command_line, load_average,
                               machine_info, report_stem, reproduce, table, write_report)
from datagen.pipeline import JobSpec, make_index, run_sample, software_info
from datagen.files import atomic_write
from datagen.dataset.shards import INDEX_NAME, ShardWriter, dumps, iter_tar_samples, read_index, subject_id

SCREEN = (1920, 1080)
GOALS_MS = {"next": 150, "verdict": 150, "triage_page": 300, "view3d_on": 500}
GOAL_OPEN_S = 3.0        # opening a 1,000-subject shard, pyvista's start-up included
QUIET_S = 0.15           # a frame is complete when the window stays still this long
JUDGE_S = 1.0            # assumed: a reviewer decides on one subject in about a second (review mode)
SCAN_PAGE_S = 10.0       # assumed: scanning a triage page of 40 and marking its few bad cells
CONFIGS = {  # view size -> (subjects, next, verdict, 3D, page changes / commits); quick halves the work
    128: (1000, 30, 30, 6, 8),
    512: (360, 30, 30, 6, 3),
}


# ------------------------------------------------------------------------------------------------
# Datasets


def build_dataset(work: Path, subjects: int, resolution: int, distinct: int = 4) -> Path:
    """A one-shard dataset of ``subjects`` subjects at ``resolution`` px, repeating ``distinct`` rendered ones."""
    out = work / f"heads-{resolution}px-{subjects}"
    if (out / INDEX_NAME).exists():
        return out
    seed_dir = work / f"seed-{resolution}px"
    spec = JobSpec(out=str(seed_dir), subjects=distinct, resolution=resolution, shard_size=distinct, seed=5,
                   generator_options={"defect_rate": 0.5}, software=software_info())
    if not (seed_dir / INDEX_NAME).exists():
        print(f"rendering {distinct} subjects at {resolution} px ...", flush=True)
        run_sample(spec, progress=False)
    samples = list(iter_tar_samples(seed_dir / "shard-000000.tar"))
    tmp = work / f".{out.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    writer = ShardWriter(tmp, 0)
    for i in range(subjects):
        _, fields = samples[i % len(samples)]
        key = subject_id(i)
        meta = json.loads(fields["json"])
        meta.update(subject_id=key, subject_index=i)
        writer.add_subject(key, [(f"{key}.json", dumps(meta))] + [(f"{key}.{f}", b) for f, b in fields.items()
                                                                   if f != "json"])
    writer.commit()
    big = JobSpec(out=str(out), subjects=subjects, resolution=resolution, shard_size=subjects, seed=5,
                  software=spec.software)
    atomic_write(tmp / INDEX_NAME, dumps(make_index(big, read_index(seed_dir)["generator"])))
    tmp.rename(out)
    return out


# ------------------------------------------------------------------------------------------------
# The X side: Xvfb, keys through XTEST, frames through DAMAGE, pixels through XGetImage


class XImage(ctypes.Structure):
    _fields_ = [("width", ctypes.c_int), ("height", ctypes.c_int), ("xoffset", ctypes.c_int),
                ("format", ctypes.c_int), ("data", ctypes.c_void_p), ("byte_order", ctypes.c_int),
                ("bitmap_unit", ctypes.c_int), ("bitmap_bit_order", ctypes.c_int), ("bitmap_pad", ctypes.c_int),
                ("depth", ctypes.c_int), ("bytes_per_line", ctypes.c_int), ("bits_per_pixel", ctypes.c_int)]


def start_xvfb() -> tuple[subprocess.Popen, str]:
    """Xvfb on a free display number (-noreset: it must not reset when a client disconnects)."""
    for n in range(120, 200):
        if not Path(f"/tmp/.X{n}-lock").exists() and not Path(f"/tmp/.X11-unix/X{n}").exists():
            break
    proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24", "-nolisten", "tcp",
                             "-noreset"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 30
    while not Path(f"/tmp/.X11-unix/X{n}").exists():
        if time.time() > deadline or proc.poll() is not None:
            raise RuntimeError("Xvfb did not start")
        time.sleep(0.05)
    return proc, f":{n}"


class XClient:
    """A reviewer's hands and eyes on one X display."""

    def __init__(self, display: str):
        x = ctypes.CDLL(ctypes.util.find_library("X11"))
        self.x = x
        self.tst = ctypes.CDLL("libXtst.so.6")
        self.dmg = ctypes.CDLL("libXdamage.so.1")
        vp, c_int, c_ulong = ctypes.c_void_p, ctypes.c_int, ctypes.c_ulong
        x.XOpenDisplay.restype, x.XOpenDisplay.argtypes = vp, [ctypes.c_char_p]
        x.XDefaultRootWindow.restype, x.XDefaultRootWindow.argtypes = c_ulong, [vp]
        x.XConnectionNumber.argtypes = [vp]
        x.XPending.argtypes = [vp]
        x.XNextEvent.argtypes = [vp, vp]
        x.XFlush.argtypes = [vp]
        x.XSync.argtypes = [vp, c_int]
        x.XStringToKeysym.restype, x.XStringToKeysym.argtypes = c_ulong, [ctypes.c_char_p]
        x.XKeysymToKeycode.restype, x.XKeysymToKeycode.argtypes = ctypes.c_ubyte, [vp, c_ulong]
        x.XQueryTree.argtypes = [vp, c_ulong, ctypes.POINTER(c_ulong), ctypes.POINTER(c_ulong),
                                 ctypes.POINTER(ctypes.POINTER(c_ulong)), ctypes.POINTER(ctypes.c_uint)]
        x.XFetchName.argtypes = [vp, c_ulong, ctypes.POINTER(ctypes.c_char_p)]
        x.XFree.argtypes = [vp]
        x.XSetInputFocus.argtypes = [vp, c_ulong, c_int, c_ulong]
        x.XGetImage.restype = ctypes.POINTER(XImage)
        x.XGetImage.argtypes = [vp, c_ulong, c_int, c_int, ctypes.c_uint, ctypes.c_uint, c_ulong, c_int]
        x.XGetGeometry.argtypes = [vp, c_ulong, ctypes.POINTER(c_ulong), ctypes.POINTER(c_int), ctypes.POINTER(c_int),
                                   ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_uint),
                                   ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_uint)]
        self.tst.XTestFakeKeyEvent.argtypes = [vp, ctypes.c_uint, c_int, c_ulong]
        self.dmg.XDamageQueryExtension.argtypes = [vp, ctypes.POINTER(c_int), ctypes.POINTER(c_int)]
        self.dmg.XDamageCreate.restype, self.dmg.XDamageCreate.argtypes = c_ulong, [vp, c_ulong, c_int]
        # windows come and go while we look at them: an X error is not fatal here
        self._on_error = ctypes.CFUNCTYPE(c_int, vp, vp)(lambda d, e: 0)
        x.XSetErrorHandler(self._on_error)
        self.dpy = x.XOpenDisplay(display.encode())
        if not self.dpy:
            raise RuntimeError(f"cannot open display {display}")
        base, err = c_int(), c_int()
        if not self.dmg.XDamageQueryExtension(self.dpy, ctypes.byref(base), ctypes.byref(err)):
            raise RuntimeError("the X server has no DAMAGE extension")
        self.damage_event = base.value  # XDamageNotify = event base + 0
        self.fd = x.XConnectionNumber(self.dpy)
        self.root = x.XDefaultRootWindow(self.dpy)
        self.window = None
        self._event = (ctypes.c_long * 24)()

    def find_window(self, title: str):
        """The top-level window whose name starts with ``title``, or None."""
        root, parent, n = ctypes.c_ulong(), ctypes.c_ulong(), ctypes.c_uint()
        children = ctypes.POINTER(ctypes.c_ulong)()
        if not self.x.XQueryTree(self.dpy, self.root, ctypes.byref(root), ctypes.byref(parent), ctypes.byref(children),
                                 ctypes.byref(n)):
            return None
        found = None
        for i in range(n.value):
            name = ctypes.c_char_p()
            if self.x.XFetchName(self.dpy, children[i], ctypes.byref(name)) and name.value:
                if name.value.decode(errors="replace").startswith(title):
                    found = children[i]
                self.x.XFree(name)
        if n.value:
            self.x.XFree(children)
        return found

    def watch(self, window: int):
        self.window = window
        self.dmg.XDamageCreate(self.dpy, window, 0)  # XDamageReportRawRectangles: an event per drawing
        self.x.XSetInputFocus(self.dpy, window, 2, 0)
        self.x.XSync(self.dpy, 0)

    def size(self) -> tuple[int, int]:
        root, x, y = ctypes.c_ulong(), ctypes.c_int(), ctypes.c_int()
        w, h, b, d = (ctypes.c_uint() for _ in range(4))
        self.x.XGetGeometry(self.dpy, self.window, ctypes.byref(root), ctypes.byref(x), ctypes.byref(y),
                            ctypes.byref(w), ctypes.byref(h), ctypes.byref(b), ctypes.byref(d))
        return w.value, h.value

    def pixels(self) -> np.ndarray:
        """The window's pixels (H, W, 3) uint8."""
        w, h = self.size()
        img = self.x.XGetImage(self.dpy, self.window, 0, 0, w, h, 0xFFFFFFFF, 2)  # ZPixmap
        im = img.contents
        rows, stride = im.height, im.bytes_per_line
        raw = ctypes.string_at(im.data, stride * rows)
        self.x.XFree(im.data)
        self.x.XFree(img)
        a = np.frombuffer(raw, np.uint8).reshape(rows, stride // 4, 4)[:, :w]
        return a[..., 2::-1].copy()  # BGRX -> RGB

    def damage_times(self, timeout: float) -> list[float]:
        """Times of the damage events arriving within ``timeout`` s of silence (waits while they come)."""
        times = []
        while True:
            while self.x.XPending(self.dpy):
                self.x.XNextEvent(self.dpy, self._event)
                if ctypes.cast(self._event, ctypes.POINTER(ctypes.c_int))[0] == self.damage_event:
                    times.append(time.perf_counter())
            ready, _, _ = select.select([self.fd], [], [], timeout)
            if not ready:
                return times

    def key(self, name: str) -> float:
        """Press and release a key; returns the time it was sent."""
        code = self.x.XKeysymToKeycode(self.dpy, self.x.XStringToKeysym(name.encode()))
        self.tst.XTestFakeKeyEvent(self.dpy, code, 1, 0)
        self.tst.XTestFakeKeyEvent(self.dpy, code, 0, 0)
        t = time.perf_counter()
        self.x.XFlush(self.dpy)
        return t

    def timed_key(self, name: str, limit: float = 20.0) -> dict:
        """Key -> the last frame drawn in answer (ms), the first one, and whether the pixels changed."""
        self.damage_times(QUIET_S)                     # the window is still
        before = zlib.crc32(self.pixels().tobytes())
        t0 = self.key(name)
        times, deadline = [], time.perf_counter() + limit
        while not times and time.perf_counter() < deadline:
            times = self.damage_times(0.5)
        times += self.damage_times(QUIET_S)
        changed = zlib.crc32(self.pixels().tobytes()) != before
        if not times:
            return {"ms": None, "first_ms": None, "changed": changed}
        return {"ms": 1e3 * (times[-1] - t0), "first_ms": 1e3 * (times[0] - t0), "changed": changed}


# ------------------------------------------------------------------------------------------------
# One session


def open_window(client: XClient, dataset: Path, labels: Path, env: dict) -> tuple[subprocess.Popen, float]:
    """Start ``label-tool review`` and wait for its first complete frame; returns (process, seconds)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "labeling_tool.cli", "review", str(dataset), "--reviewer", "bench",
                             "--labels", str(labels), "--window-size", f"{SCREEN[0]}x{SCREEN[1]}"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    window, found_at = None, None
    while window is None:
        if proc.poll() is not None:
            raise RuntimeError(f"label-tool review exited: {proc.stderr.read()[-2000:]}")
        window = client.find_window("label-tool review: bench")
        found_at = time.perf_counter()
        time.sleep(0.01)
    client.watch(window)
    while True:  # drawn: the heads-up text and the grid are there, and nothing moves
        times = client.damage_times(0.3)
        img = client.pixels()
        if img[:60].std() > 10 and img[200:].std() > 10:
            return proc, (max(times) if times else found_at) - t0
        if proc.poll() is not None:
            raise RuntimeError(f"label-tool review exited: {proc.stderr.read()[-2000:]}")


def session(dataset: Path, display: str, counts, shots: Path, tag: str) -> dict:
    """Open the window on ``dataset`` and time every kind of key (see the module docstring)."""
    _, n_next, n_verdict, n_3d, n_pages = counts
    labels = Path(tempfile.mkdtemp(prefix="gui-latency-labels-"))
    env = dict(os.environ, DISPLAY=display, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)
    client = XClient(display)
    load = {"before": load_average()}
    proc, open_s = open_window(client, dataset, labels, env)
    out = {"open_s": open_s, "keys": {}, "load_average": load}

    def run(kind, key, times, think):
        for _ in range(times):
            out["keys"].setdefault(kind, []).append(client.timed_key(key))
            time.sleep(think)
        load[kind] = load_average()

    try:
        time.sleep(1.0)
        for _ in range(3):  # a frame that uploads only the help panel: near the floor of any key
            run("help_on", "h", 1, 0.5)
            run("help_off", "h", 1, 0.5)
        run("next", "Right", n_next, 0.8)
        run("verdict", "g", n_verdict, 0.8)
        save_png(client.pixels(), shots / f"gui_latency_{tag}_review.png")
        for _ in range(n_3d):
            run("view3d_on", "v", 1, 1.0)
            run("view3d_off", "v", 1, 0.8)
        grid = client.pixels()
        client.key("v")
        deadline = time.perf_counter() + 30   # the surface may be made only now: wait for the 3D frame
        while np.array_equal(client.pixels(), grid) and time.perf_counter() < deadline:
            client.damage_times(0.3)
        client.damage_times(0.5)
        save_png(client.pixels(), shots / f"gui_latency_{tag}_3d.png")
        client.key("v")
        run("triage_enter", "t", 1, 2.0)
        for _ in range(n_pages):
            run("triage_page", "n", 1, 2.0)
            run("triage_commit", "Return", 1, 2.0)
        save_png(client.pixels(), shots / f"gui_latency_{tag}_triage.png")
        client.key("Escape")
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    events = (labels / "bench.jsonl").read_text().count("\n")
    shutil.rmtree(labels, ignore_errors=True)
    out.update(exit_code=proc.returncode, stdout=stdout.strip(), stderr=stderr.strip()[-1000:], events=events)
    return out


# The start-up, taken apart: each run a fresh process on the benchmark's display. ``probe`` 0 or 1:
# whether pyvista probes the display itself (the window sets ALLOW_PLOTTING to skip that probe).
STARTUP_PROBE = """
import json, sys, time
t = [time.perf_counter()]
import pyvista
t.append(time.perf_counter())
import pyvista.plotting
t.append(time.perf_counter())
from labeling_tool.review import window
t.append(time.perf_counter())
if sys.argv[1] == "1":
    settings = window.plotter_settings
    window.plotter_settings = lambda off: {k: v for k, v in settings(off).items() if k != "ALLOW_PLOTTING"}
display = window.XDisplay()
win = window.Window(False, (1920, 1080), "start-up probe")
t.append(time.perf_counter())
win.show()
t.append(time.perf_counter())
win.close()
display.close()
print(json.dumps([b - a for a, b in zip(t, t[1:])]))
"""
STARTUP_PARTS = ("import pyvista (core)", "import pyvista.plotting (matplotlib)", "import the window module",
                 "the plotter and its X window", "the first frame (empty, 1920x1080)")


def startup(display: str, runs: int) -> dict:
    """Seconds of each part of the window's start-up ({"window": [[part, ...] per run], "with_probe": ...})."""
    env = dict(os.environ, DISPLAY=display, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)
    out = {"window": [], "with_probe": []}
    for _ in range(runs):
        for kind, flag in (("window", "0"), ("with_probe", "1")):
            done = subprocess.run([sys.executable, "-c", STARTUP_PROBE, flag], env=env, capture_output=True, text=True,
                                  timeout=120, check=True)
            out[kind].append(json.loads(done.stdout.strip().splitlines()[-1]))
    return out


def save_png(pixels: np.ndarray, path: Path):
    from PIL import Image

    Image.fromarray(pixels).save(path)


# ------------------------------------------------------------------------------------------------
# Report


def percentile(values, q):
    return float(np.percentile(values, q)) if values else None


def summarize(result: dict) -> dict:
    s = {}
    for kind, samples in result["keys"].items():
        ms = [x["ms"] for x in samples if x["ms"] is not None]
        s[kind] = {"n": len(samples), "answered": len(ms), "changed": sum(x["changed"] for x in samples),
                   "p50": percentile(ms, 50), "p95": percentile(ms, 95), "max": max(ms) if ms else None,
                   "first_frame_p50": percentile([x["first_ms"] for x in samples if x["first_ms"] is not None], 50)}
    return s


def render(results: dict) -> str:
    lines = ["# Review window latency: key to changed frame", "",
             f"Window {SCREEN[0]}x{SCREEN[1]} on Xvfb (software OpenGL), one `label-tool review` process (its window a "
             "pyvista plotter); keys sent "
             "through XTEST (as xdotool sends them), frames seen through X DAMAGE events; a frame is complete when "
             f"the window stays still {QUIET_S * 1e3:.0f} ms (that wait is not counted).", ""]
    m = results["machine"]
    lines += [f"Machine: {m['cpu_model']}, {m['usable_cpus']} usable CPUs, {m['platform']}, "
              f"git {m['git_revision'][:10] if m['git_revision'] else 'unknown'}, {results['date']}.", ""]
    rows, verdicts = [], {}
    for tag, r in results["sessions"].items():
        s = summarize(r)
        load = r["load_average"]
        lines += [f"## {tag}", "",
                  f"{r['subjects']} subjects x 32 views of {r['resolution']} px in one shard; 1-minute load average "
                  + ", ".join(f"{v:.2f} {k}" for k, v in load.items()) + ".", ""]
        rows = []
        for kind, label in [("help_on", "help panel on (h): one small upload and a frame"),
                            ("help_off", "help panel off (h)"), ("next", "next subject (Right)"), ("verdict", "verdict (g: fsync + next subject)"),
                            ("view3d_on", "3D surface on (v)"), ("view3d_off", "3D off, back to the grid (v)"),
                            ("triage_enter", "enter triage (t)"), ("triage_page", "triage page change (n, new page)"),
                            ("triage_commit", "triage commit (Return: 40 events, next page)")]:
            if kind not in s:
                continue
            k = s[kind]
            goal = GOALS_MS.get(kind)
            verdict = "-" if goal is None else ("met" if k["p95"] is not None and k["p95"] <= goal else "NOT met")
            verdicts[(tag, kind)] = verdict
            fmt = (lambda v: "-" if v is None else f"{v:.0f}")
            rows.append([label, f"{k['answered']}/{k['n']}", k["changed"], fmt(k["p50"]), fmt(k["p95"]), fmt(k["max"]),
                         fmt(k["first_frame_p50"]), "-" if goal is None else f"<= {goal}", verdict])
        open_verdict = "met" if r["open_s"] <= GOAL_OPEN_S else "NOT met"
        lines += table(["key", "answered", "frames changed", "p50 ms", "p95 ms", "max ms", "first frame p50 ms",
                        "goal p95 ms", "goal"], rows)
        lines += ["", f"Opening the shard (command start to the first complete frame): **{r['open_s']:.2f} s** "
                      f"(goal <= {GOAL_OPEN_S:.0f} s: {open_verdict}).", ""]
        review_h = 3600 / (JUDGE_S + s["verdict"]["p50"] / 1e3)
        triage_h = 40 * 3600 / (SCAN_PAGE_S + s["triage_commit"]["p50"] / 1e3)
        tool_share = s["verdict"]["p50"] / 1e3 / (JUDGE_S + s["verdict"]["p50"] / 1e3)
        lines += bullets([
            f"Review mode: {review_h:,.0f} subjects/hour at {JUDGE_S:.0f} s of judgement per subject plus the "
            f"verdict's p50 (the window's share of the time: {100 * tool_share:.0f} %); 100K subjects take "
            f"{100_000 / review_h:.0f} reviewer-hours.",
            f"Triage mode: {triage_h:,.0f} subjects/hour at {SCAN_PAGE_S:.0f} s to scan a page of 40 plus the commit's "
            f"p50; 100K subjects take {100_000 / triage_h:.0f} reviewer-hours.",
            f"Session: exit code {r['exit_code']}, {r['events']} events written; `{r['stdout']}`."]) + [""]
        lines += [f"Screenshots: gui_latency_{tag}_review.png, gui_latency_{tag}_3d.png, "
                  f"gui_latency_{tag}_triage.png.", ""]
    if "startup" in results:
        st = results["startup"]
        parts = np.median(np.array(st["window"]), axis=0)
        probe = np.median(np.array(st["with_probe"]), axis=0)
        lines += ["## Start-up", "",
                  f"Medians of {len(st['window'])} fresh processes on the same display (1-minute load average "
                  f"{st['load_average']:.2f}); a second column with pyvista's own probe of the display, which the "
                  "window skips (ALLOW_PLOTTING: the display was checked already, or EGL renders off-screen). "
                  "pyvista's plotting package imports matplotlib (pyplot included) as it loads, for its colour maps: "
                  "that import is part of every pyvista window, paid once per session (and the first import after "
                  "matplotlib is installed also builds its font cache, once per user).", ""]
        lines += table(["part", "s", "with pyvista's probe, s"],
                       [[name, f"{a:.2f}", f"{b:.2f}"] for name, a, b in zip(STARTUP_PARTS, parts, probe)]
                       + [["total", f"{parts.sum():.2f}", f"{probe.sum():.2f}"]])
        lines += [""]
    lines += ["## Notes", ""] + bullets([
        "p95 of 30 keys is close to their second-largest value: a rough tail. The machine is shared (load "
        "averages above, against 2 CPUs); timings on a quiet machine are lower.",
        "The help panel rows are the floor of any key at that load: a frame of the 1920x1080 window (software "
        "OpenGL draws it, then it is copied to the X server) plus one small upload. Keys whose p50 is near that "
        "floor spend their time drawing the frame, not preparing it.",
        "Keys come at a reviewer's pace (0.8 s after each answered review key, 2 s in triage), which gives the "
        "background thread time to prepare the next subjects and the next page; held-down keys are slower.",
        "A subject's 3D surface is prepared ahead only once the subject has been on screen for 1 s (most subjects are "
        "never seen in 3D, and on 2 CPUs that work competes with the keys); with 0.8 s between keys here, `v` finds "
        "it not made or being made, so the 3D row includes decoding the 32 depth maps and masks and building the "
        "mesh.",
        "The throughput figures assume the judgement times stated; they say how much of a reviewer's hour the window "
        "itself takes, not how fast people are."]) + [""]
    lines += reproduce(results["command"])
    return "\n".join(lines) + "\n"


def measure(quick: bool, work: Path, command: str) -> dict:
    if not (shutil.which("Xvfb")):
        raise SystemExit("Xvfb is needed: apt-get install -y xvfb")
    work.mkdir(parents=True, exist_ok=True)
    results = {"command": command, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "machine": machine_info(), "sessions": {}}
    xvfb, display = start_xvfb()
    try:
        print("start-up, taken apart ...", flush=True)
        results["startup"] = dict(startup(display, 2 if quick else 5), load_average=load_average())
        for resolution, counts in CONFIGS.items():
            if quick:
                counts = (counts[0] // 4, 10, 10, 2, 2)
            dataset = build_dataset(work, counts[0], resolution)
            tag = f"{resolution}px" + ("_quick" if quick else "")
            print(f"session: {counts[0]} subjects at {resolution} px ...", flush=True)
            r = session(dataset, display, counts, REPORTS, tag)
            r.update(subjects=counts[0], resolution=resolution)
            results["sessions"][tag] = r
    finally:
        xvfb.terminate()
        xvfb.wait()
    results["machine"]["load_average_after"] = list(os.getloadavg())
    return results


def main(argv=None):
    parser = benchmark_parser(__doc__, "fewer subjects and keys (a check that the script works)",
                              "rewrite the report from the saved JSON")
    add_work_folder(parser, "gui-latency", "the benchmark datasets are built and kept")
    args = parser.parse_args(argv)
    stem = report_stem("gui_latency", args.quick)
    if args.report_only:
        results = json.loads(stem.with_suffix(".json").read_text())
    else:
        results = measure(args.quick, args.work, command_line(Path(__file__), argv))
    write_report(stem, results, render(results))


if __name__ == "__main__":
    main()
