"""The window on pyvista: the X display check, a plotter with our keys only, images drawn as textures."""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import select
from contextlib import contextmanager

import numpy as np
import pyvista as pv
from vtkmodules.vtkInteractionStyle import vtkInteractorStyleUser
from vtkmodules.vtkRenderingCore import vtkActor2D, vtkPolyDataMapper2D, vtkTexturedActor2D

from datagen.errors import UserError

from .layout import BACKGROUND

OFF_SCREEN_SIZE = (1600, 900)
WINDOW_KIND = "VTK_DEFAULT_OPENGL_WINDOW"   # VTK reads the class of a new render window from this variable


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


def set_environment(values: dict):
    """Set environment variables; a value of None unsets one."""
    for k, v in values.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@contextmanager
def environment(values: dict):
    """Environment variables set (a value of None: unset) inside the block, as they were after it."""
    before = {k: os.environ.get(k) for k in values}
    set_environment(values)
    try:
        yield
    finally:
        set_environment(before)


def plotter_settings(off_screen: bool) -> dict:
    """The environment a :class:`pyvista.Plotter` is made in. Off-screen without a display: EGL (no
    X attempted, no X warnings). A window: an X-backed one, whatever off-screen default is set.
    ``ALLOW_PLOTTING`` skips pyvista's own probe of the display (a subprocess, or a second OpenGL
    context): :class:`XDisplay` has checked it, or there is none and EGL renders."""
    values = {"ALLOW_PLOTTING": "true"}
    kind = os.environ.get(WINDOW_KIND)
    if off_screen and not os.environ.get("DISPLAY"):
        values[WINDOW_KIND] = kind or "vtkEGLRenderWindow"
    elif not off_screen and kind and "X" not in kind:
        values[WINDOW_KIND] = None
    return values


class Window:
    """A :class:`pyvista.Plotter` (one renderer, its render window and interactor) answering only the
    keys bound with :meth:`bind`: pyvista's own keys (q quits, v isometric, ...) and VTK's (w
    wireframe, e quits, ...) are off. No anti-aliasing and no lights (multisampling costs software
    OpenGL several frames' time; the images carry their own shading). Off-screen without a display
    it renders with EGL; on screen it needs an X-backed window (one line otherwise)."""

    def __init__(self, off_screen: bool, size, title: str):
        theme = pv.themes.Theme()
        theme.anti_aliasing = None
        theme.background = BACKGROUND
        with environment(plotter_settings(off_screen)):
            self.plotter = pv.Plotter(off_screen=off_screen, window_size=list(size), title=title, theme=theme,
                                      lighting=None)
        made = type(self.plotter.render_window).__name__
        if not off_screen and "X" not in made:
            self.plotter.close()
            raise UserError(f"VTK could not open a window on the display {os.environ.get('DISPLAY')!r} (it made a "
                            f"{made}); use --off-screen for a scripted session")
        self.off_screen, self.title = off_screen, title
        if not off_screen and hasattr(self.plotter.render_window, "SetFrameBlitModeToBlitToCurrent"):
            # the frame goes from VTK's framebuffer straight to the window's back buffer, colour only: the
            # default also copies colour and depth through a second framebuffer, which doubles the cost
            # of every frame under software OpenGL (Xvfb, remote desktops)
            self.plotter.render_window.SetFrameBlitModeToBlitToCurrent()
        iren = self.plotter.iren
        iren.clear_key_event_callbacks()
        iren.add_observer("ExitEvent", lambda *_: self.stop())
        self.plotter.enable_trackball_style()
        self._styles = {"3d": iren.style, "grid": vtkInteractorStyleUser()}
        for style in self._styles.values():
            # VTK's styles handle characters themselves (q/e quit, w/s wireframe/surface, ...); an observer stops that
            style.AddObserver("CharEvent", lambda *_: None)
        self.set_style("grid")
        self.running = False
        self._shown = False

    def bind(self, keys: dict):
        """Call ``keys[name]()`` when the key ``name`` (a VTK key symbol: "g", "Right", "Return") is pressed."""
        for key, fn in keys.items():
            self.plotter.add_key_event(key, fn)

    def observe(self, event: str, fn):
        """Call ``fn()`` at each VTK interactor ``event`` ("LeftButtonPressEvent", "ConfigureEvent", ...)."""
        self.plotter.iren.add_observer(event, lambda *_: fn())

    def event_position(self) -> tuple[int, int]:
        """Display pixel (x, y from the bottom) of the latest mouse event."""
        x, y = self.plotter.iren.get_event_position()
        return int(x), int(y)

    def set_style(self, kind: str):
        """grid: no mouse interaction (clicks are the program's); 3d: trackball camera."""
        self.plotter.iren.style = self._styles[kind]

    def press(self, key: str):
        """Deliver a key as the window would (KeyPressEvent, which pyvista's key events answer, then CharEvent)."""
        it = self.plotter.iren.interactor
        it.Enable()
        it.SetKeySym(key)
        it.SetKeyCode(key if len(key) == 1 else "\0")
        it.KeyPressEvent()
        it.CharEvent()

    def click(self, x: int, y: int):
        """A left click at display pixel (x, y from the top)."""
        it = self.plotter.iren.interactor
        it.SetEventInformation(int(x), self.size()[1] - 1 - int(y), 0, 0)
        it.LeftButtonPressEvent()
        it.LeftButtonReleaseEvent()

    def size(self) -> tuple[int, int]:
        w, h = self.plotter.window_size
        return int(w), int(h)

    def render(self):
        """Draw a frame; the first one is drawn by :meth:`show`."""
        if self._shown:
            self.plotter.render()
        else:
            self.show()

    def show(self):
        """Map the window (named by its title) and draw its first frame, without entering pyvista's
        event loop (:meth:`loop` is ours)."""
        if not self.off_screen:
            self.plotter.iren.initialize()
        self.plotter.show(title=self.title, interactive_update=True, auto_close=False)
        self._shown = True

    def screenshot(self) -> np.ndarray:
        """The window's pixels (H, W, 3) uint8, top row first."""
        return np.array(self.plotter.screenshot(return_img=True)[..., :3])

    def loop(self, display: XDisplay | None):
        """Deliver the window's events until :meth:`stop` or :meth:`close`, waiting for X events
        without holding the interpreter, so that the prefetch thread can work."""
        fd = self._x_connection(display)
        self.running = True
        while self.running:
            self.plotter.iren.process_events()
            if not self.running:
                break
            if fd is None:
                select.select([], [], [], 0.005)
            else:
                select.select([fd], [], [], 0.05)

    def _x_connection(self, display: XDisplay | None):
        """File descriptor of VTK's X connection (None when it cannot be found)."""
        try:
            handle = int(self.plotter.render_window.GetGenericDisplayId().split("_")[1], 16)
            return display.lib.XConnectionNumber(handle) if display and display.lib else None
        except (AttributeError, ValueError, IndexError, TypeError):
            return None

    def stop(self):
        self.running = False

    def close(self):
        self.running = False
        self.plotter.close()
        self.plotter = None


class ImageLayer:
    """An RGB image (rows bottom-up) drawn at a place in the window, in display pixels.

    The image is a texture on a rectangle of its own size (nearest texel: pixel for pixel). The
    texture is uploaded once per image: a frame that does not change the image (another layer
    changed, the help panel was toggled) draws it from the texture already there.
    """

    def __init__(self, plotter: pv.Plotter):
        self.texture = pv.Texture()
        self.texture.interpolate = False
        self.texture.wrap = pv.Texture.WrapType.CLAMP_TO_EDGE
        self._quad = pv.PolyData(np.zeros((4, 3), np.float32), faces=[4, 0, 1, 2, 3])
        self._quad.active_texture_coordinates = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        mapper = vtkPolyDataMapper2D()
        mapper.SetInputData(self._quad)
        self.actor = vtkTexturedActor2D()
        self.actor.SetMapper(mapper)
        self.actor.SetTexture(self.texture)
        self.actor.SetVisibility(False)
        plotter.add_actor(self.actor, reset_camera=False, pickable=False, render=False)
        self.pixels = None  # kept alive: the texture reads this memory
        self.uploads = 0    # images handed to the texture (each is uploaded once, at the next frame)

    def show(self, pixels: np.ndarray, x: int, y_top: int, window_height: int):
        """Show ``pixels`` with its top-left corner at (x, y_top from the window's top)."""
        h, w, _ = pixels.shape
        if pixels is not self.pixels:
            image = pv.ImageData(dimensions=(w, h, 1))
            image.point_data.set_array(pixels.reshape(-1, 3), "rgb")
            image.point_data.active_scalars_name = "rgb"
            if self.pixels is None or self.pixels.shape != pixels.shape:
                self._quad.points = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], np.float32)
            self.pixels = pixels
            self.texture.SetInputDataObject(image)
            self.uploads += 1
        self.actor.SetPosition(x, window_height - y_top - h)
        self.actor.SetVisibility(True)

    def hide(self):
        self.actor.SetVisibility(False)

    def visible(self) -> bool:
        return bool(self.actor.GetVisibility())


class Outline:
    """A rectangle's outline drawn over the window (the triage cursor), ``width`` px of one colour."""

    def __init__(self, plotter: pv.Plotter, color, width: int):
        self._outline = pv.PolyData(np.zeros((4, 3), np.float32), lines=[5, 0, 1, 2, 3, 0])
        mapper = vtkPolyDataMapper2D()
        mapper.SetInputData(self._outline)
        self.actor = vtkActor2D()
        self.actor.SetMapper(mapper)
        self.actor.GetProperty().SetColor(*[c / 255 for c in color])
        self.actor.GetProperty().SetLineWidth(width)
        self.actor.SetVisibility(False)
        plotter.add_actor(self.actor, reset_camera=False, pickable=False, render=False)

    def show(self, box, window_height: int):
        """Outline ``box`` (x0, y0, x1, y1 in display pixels from the top-left)."""
        x0, y0, x1, y1 = box
        self._outline.points = np.array([(x, window_height - 1 - y, 0) for x, y in
                                         [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]], np.float32)
        self.actor.SetVisibility(True)

    def hide(self):
        self.actor.SetVisibility(False)
