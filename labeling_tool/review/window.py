"""The VTK window: the X display check, the render window with its interactor, images drawn as textures."""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import select

import numpy as np
from vtkmodules import vtkRenderingOpenGL2
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData
from vtkmodules.vtkInteractionStyle import vtkInteractorStyleTrackballCamera, vtkInteractorStyleUser
from vtkmodules.vtkRenderingCore import (vtkActor2D, vtkPolyDataMapper2D, vtkRenderer, vtkRenderWindow,
                                         vtkRenderWindowInteractor, vtkTexture, vtkTexturedActor2D,
                                         vtkWindowToImageFilter)
from vtkmodules.vtkRenderingUI import vtkGenericRenderWindowInteractor

from datagen.errors import UserError

from .layout import BACKGROUND

# imported for what it registers: the OpenGL window behind vtkRenderWindow (vtkRenderingUI registers
# the X interactor behind vtkRenderWindowInteractor)
VTK_BACKENDS = (vtkRenderingOpenGL2,)
OFF_SCREEN_SIZE = (1600, 900)


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
        self.running = False
        self.interactor.AddObserver("KeyPressEvent", lambda *_: self._on_key())
        self.interactor.AddObserver("ExitEvent", lambda *_: self.stop())

    def _on_key(self):
        fn = self.keys.get(self.interactor.GetKeySym())
        if fn is not None:
            fn()

    def set_style(self, kind: str):
        """grid: no mouse interaction (clicks are the program's); 3d: trackball camera. VTK's own keys stay off."""
        style = vtkInteractorStyleTrackballCamera() if kind == "3d" else vtkInteractorStyleUser()
        # VTK's styles handle characters themselves (q/e quit, w/s wireframe/surface, ...); an observer stops that
        style.AddObserver("CharEvent", lambda *_: None)
        self.interactor.SetInteractorStyle(style)

    def press(self, key: str):
        """Deliver a key as the window would (KeyPressEvent then CharEvent)."""
        it = self.interactor
        it.Enable()
        it.SetKeySym(key)
        it.SetKeyCode(key if len(key) == 1 else "\0")
        it.KeyPressEvent()
        it.CharEvent()

    def click(self, x: int, y: int):
        """A left click at display pixel (x, y from the top)."""
        it = self.interactor
        it.SetEventInformation(int(x), self.size()[1] - 1 - int(y), 0, 0)
        it.LeftButtonPressEvent()
        it.LeftButtonReleaseEvent()

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

    def loop(self, display: XDisplay | None):
        """Deliver the window's events until :meth:`stop` or :meth:`close`, waiting for X events
        without holding the interpreter, so that the prefetch thread can work."""
        fd = self._x_connection(display)
        self.running = True
        while self.running:
            self.interactor.ProcessEvents()
            if not self.running:
                break
            if fd is None:
                select.select([], [], [], 0.005)
            else:
                select.select([fd], [], [], 0.05)

    def _x_connection(self, display: XDisplay | None):
        """File descriptor of VTK's X connection (None when it cannot be found)."""
        try:
            handle = int(self.render_window.GetGenericDisplayId().split("_")[1], 16)
            return display.lib.XConnectionNumber(handle) if display and display.lib else None
        except (AttributeError, ValueError, IndexError, TypeError):
            return None

    def stop(self):
        self.running = False

    def close(self):
        self.running = False
        self.render_window.Finalize()
        self.interactor.TerminateApp()
        self.render_window = self.renderer = self.interactor = None


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


class Outline:
    """A rectangle's outline drawn over the window (the triage cursor), ``width`` px of one colour."""

    def __init__(self, renderer, color, width: int):
        self._points = vtkPoints()
        for _ in range(4):
            self._points.InsertNextPoint(0, 0, 0)
        outline = vtkPolyData()
        outline.SetPoints(self._points)
        lines = vtkCellArray()
        lines.InsertNextCell(5, [0, 1, 2, 3, 0])
        outline.SetLines(lines)
        mapper = vtkPolyDataMapper2D()
        mapper.SetInputData(outline)
        self.actor = vtkActor2D()
        self.actor.SetMapper(mapper)
        self.actor.GetProperty().SetColor(*[c / 255 for c in color])
        self.actor.GetProperty().SetLineWidth(width)
        self.actor.SetVisibility(False)
        renderer.AddViewProp(self.actor)

    def show(self, box, window_height: int):
        """Outline ``box`` (x0, y0, x1, y1 in display pixels from the top-left)."""
        x0, y0, x1, y1 = box
        for k, (x, y) in enumerate([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]):
            self._points.SetPoint(k, x, window_height - 1 - y, 0)
        self._points.Modified()
        self.actor.SetVisibility(True)

    def hide(self):
        self.actor.SetVisibility(False)
