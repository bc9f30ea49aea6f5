"""The window every picture and the editor draw in: Open3D's legacy ``Visualizer`` (GLFW + OpenGL 3.3), one window
(visible for the editor, hidden for pictures) with named geometries updated in place, a look-at camera and
``capture`` to an image; and the environment Mesa's software rasteriser is given.

Why this path and not Open3D's Filament GUI: without a GPU both draw with Mesa's software rasteriser (llvmpipe), and
the legacy renderer's frames and first frame are several times faster (``benchmarks/bench_viewer.py``).
"""

from __future__ import annotations

import atexit
import contextlib
import math
import os
import shutil
import tempfile
from typing import Any, Sequence

import numpy as np

from kpd.errors import KpdError
from kpd.viewer.camera import look_at_matrix
from kpd.viewer.culling import PIXEL_CENTRE, Viewport

__all__ = ["GLView", "NoWindowError"]


class NoWindowError(KpdError):
    """No OpenGL window could be opened (no display, no GL driver)."""


def _runtime_dir() -> None:
    """GLFW and Mesa complain on stderr when $XDG_RUNTIME_DIR is unset; give them a private one, removed when the
    program ends."""
    path = os.environ.get("XDG_RUNTIME_DIR")
    if path and os.path.isdir(path):
        return
    made = tempfile.mkdtemp(prefix="kpd-xdg-")
    atexit.register(shutil.rmtree, made, ignore_errors=True)
    os.environ["XDG_RUNTIME_DIR"] = made


def _raster_threads() -> None:
    """Mesa's software rasteriser (llvmpipe) draws with one thread per processor unless ``$LP_NUM_THREADS`` says
    otherwise; kpd asks for :data:`_RASTER_THREADS_PER_PROCESSOR` a processor (at most :data:`_MAX_RASTER_THREADS`),
    unless the user has set it. The frame is cut into tiles that its threads take in turn: beside another busy
    process, the system shares the cores among the threads, so more threads keep a larger share of them, and a thread
    that the system holds back for a time slice holds back a smaller share of the frame (docs/results.md); quiet, the
    count makes no difference. The pictures do not change (each tile is drawn alike whatever thread takes it). A GPU
    driver ignores it."""
    os.environ.setdefault("LP_NUM_THREADS", str(min(_RASTER_THREADS_PER_PROCESSOR * (os.cpu_count() or 1),
                                                    _MAX_RASTER_THREADS)))


_RASTER_THREADS_PER_PROCESSOR = 8
_MAX_RASTER_THREADS = 16


class GLView:
    """One Open3D legacy window with named geometries and a look-at camera.

    Parameters
    ----------
    width, height : the drawing area in pixels.
    title : the window title.
    visible : False for pictures: a hidden window on ``$DISPLAY`` or, without one, a headless EGL context.
    left, top : where a visible window opens on the screen.
    background : RGB in [0, 1].
    on_display : must it be on the X display (default: when visible)? Then Open3D's fallback to EGL is refused.
    """

    def __init__(self, width: int, height: int, *, title: str = "kpd", visible: bool = False, left: int = 40,
                 top: int = 40, background: Sequence[float] = (1.0, 1.0, 1.0), on_display: bool | None = None) -> None:
        import open3d as o3d

        from kpd.io.capture import native_output as _quiet_native_output

        display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        if visible and not display:
            raise NoWindowError("no display to open a window on ($DISPLAY is not set); run under xvfb-run, or draw "
                                "pictures with kpd render")
        _runtime_dir()
        _raster_threads()
        self.width, self.height = int(width), int(height)
        self.vis = o3d.visualization.VisualizerWithKeyCallback()
        with _quiet_native_output() as said:
            ok = self.vis.create_window(title, self.width, self.height, int(left), int(top), bool(visible))
        # without a usable display Open3D falls back to a headless EGL context: right for pictures, not for a window
        headless = "falling back to EGL" in said.text
        on_display = visible if on_display is None else on_display  # must it be on the X display (not EGL)?
        if not ok or (on_display and headless):
            where = f"display {display!r}" if display else "EGL (no display)"
            raise NoWindowError(f"could not open an OpenGL {'window' if on_display else 'context'} on {where}: "
                                "install Mesa's OpenGL (apt-get install libgl1-mesa-dri libegl-mesa0)"
                                + (", check $DISPLAY" if on_display else ", or use --backend xvfb"))
        options = self.vis.get_render_option()
        options.mesh_show_back_face = True  # flipped triangles of CAD meshes stay visible
        options.background_color = np.asarray(background, dtype=np.float64)
        options.light_on = False  # shaded by kpd (see shade): Open3D's legacy lights saturate facing the camera
        options.point_size = 3.0
        self._geometries: dict[str, Any] = {}
        self._shown: dict[str, bool] = {}
        self._boxed = False
        self.camera: Any = None
        self.visible = bool(visible)
        # frames upload only the triangles that show in a pixel (visible_triangles) when OpenGL draws the window's
        # pixels (not on a display that scales the window), sampled where the window's framebuffer samples them
        intrinsic = self.vis.get_view_control().convert_to_pinhole_camera_parameters().intrinsic
        self._culls = (intrinsic.width, intrinsic.height) == (self.width, self.height)
        self._samples = _sample_points() if self.visible else PIXEL_CENTRE

    # geometry

    def put(self, name: str, geometry: Any, *, show: bool = True) -> None:
        """Show ``geometry`` under ``name``: updated in place when it is the object already there, else replaced."""
        old = self._geometries.get(name)
        if old is geometry and self._shown.get(name):
            if show:
                self.vis.update_geometry(geometry)
                return
        if old is not None and self._shown.get(name):
            self.vis.remove_geometry(old, reset_bounding_box=False)
        self._geometries[name] = geometry
        self._shown[name] = False
        if show:
            self._add(name)

    def show(self, name: str, visible: bool) -> None:
        if name not in self._geometries or self._shown[name] == visible:
            return
        if visible:
            self._add(name)
        else:
            self.vis.remove_geometry(self._geometries[name], reset_bounding_box=False)
            self._shown[name] = False

    def remove(self, name: str) -> None:
        self.show(name, False)
        self._geometries.pop(name, None)
        self._shown.pop(name, None)

    def clear(self) -> None:
        self.vis.clear_geometries()
        self._geometries.clear()
        self._shown.clear()
        self._boxed = False

    def _add(self, name: str) -> None:
        # the first geometry sets the view's bounding box, which the renderer's near and far planes come from
        self.vis.add_geometry(self._geometries[name], reset_bounding_box=not self._boxed)
        self._boxed = True
        self._shown[name] = True
        if self.camera is not None:
            self.set_camera(self.camera)

    def set_box(self, vertices: Any) -> None:
        """Make the view's bounding box (which sets the clipping planes) hold ``vertices`` (N, 3), or a list of such
        arrays."""
        import open3d as o3d

        from kpd.viewer.camera import box

        lo, hi = box([np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
                      for p in (vertices if isinstance(vertices, (list, tuple)) else [vertices])])
        pad = 1.5 * (hi - lo).max()
        box = o3d.geometry.LineSet()
        box.points = o3d.utility.Vector3dVector(np.array([lo - pad, hi + pad]))
        box.lines = o3d.utility.Vector2iVector(np.zeros((0, 2), np.int32))
        self.vis.add_geometry(box, reset_bounding_box=True)
        self.vis.remove_geometry(box, reset_bounding_box=False)
        self._boxed = True

    # camera

    def viewport(self, camera: Any, *, capture: bool = False) -> Viewport | None:
        """The view's pixels seen through ``camera``, for drawing only the triangles that show in them
        (:func:`visible_triangles`): sampled where the window's framebuffer samples them when the view is on the
        screen, at the centres for ``capture`` (and in a hidden view, only ever read back); None when OpenGL draws
        another number of pixels than the window's, or its samples are not known."""
        samples = self._samples if self.visible and not capture else PIXEL_CENTRE
        if not self._culls or samples is None:
            return None
        return Viewport(camera, self.width, self.height, samples)

    def set_camera(self, camera: Any) -> None:
        """Look from ``camera.eye`` at ``camera.center`` with ``camera.up`` and vertical ``camera.fov``."""
        import open3d as o3d

        self.camera = camera
        view = look_at_matrix(camera)  # OpenGL: x right, y up, looking down -z
        extrinsic = np.diag([1.0, -1.0, -1.0, 1.0]) @ view  # OpenCV: y down, looking down +z
        focal = self.height / 2 / math.tan(math.radians(camera.fov) / 2)
        intrinsic = o3d.camera.PinholeCameraIntrinsic(self.width, self.height, focal, focal, self.width / 2 - 0.5,
                                                      self.height / 2 - 0.5)
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic, params.extrinsic = intrinsic, extrinsic
        self.vis.get_view_control().convert_from_pinhole_camera_parameters(params, allow_arbitrary=True)

    # drawing

    def draw(self) -> None:
        """Draw a frame now and show it (swap buffers)."""
        self.vis.update_renderer()
        self.vis.poll_events()

    def capture(self) -> np.ndarray:
        """(H, W, 3) uint8: the scene as drawn now."""
        image = np.asarray(self.vis.capture_screen_float_buffer(do_render=True))
        return np.clip(np.rint(image * 255), 0, 255).astype(np.uint8)[:, :, :3]

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.vis.destroy_window()


_GL_SAMPLES, _GL_SAMPLE_POSITION = 0x80A9, 0x8E50


def _sample_points() -> np.ndarray | None:
    """(S, 2) where OpenGL samples a pixel of the current context's framebuffer (its multisampling points, from the
    pixel's lower-left corner; the centre without multisampling), asked through the system's OpenGL library; None
    when it cannot be asked."""
    import ctypes
    import ctypes.util

    try:
        gl = ctypes.CDLL(ctypes.util.find_library("GL") or "libGL.so.1")
        get_integer, get_position, get_error = gl.glGetIntegerv, gl.glGetMultisamplefv, gl.glGetError
    except (OSError, AttributeError):
        return None
    get_integer.argtypes = [ctypes.c_uint, ctypes.POINTER(ctypes.c_int)]
    get_position.argtypes = [ctypes.c_uint, ctypes.c_uint, ctypes.POINTER(ctypes.c_float)]
    get_error.restype = ctypes.c_uint
    count = ctypes.c_int(-1)
    get_integer(_GL_SAMPLES, ctypes.byref(count))
    if get_error() != 0 or count.value < 0:
        return None
    if count.value <= 1:
        return PIXEL_CENTRE
    points = np.empty((count.value, 2))
    position = (ctypes.c_float * 2)()
    for i in range(count.value):
        get_position(_GL_SAMPLE_POSITION, i, position)
        points[i] = position[0], position[1]
    if get_error() != 0 or not ((points >= 0) & (points <= 1)).all():
        return None
    return points
