"""The keypoint editor: a 3D view in which keypoints are picked and dragged and the mesh deforms live, and a panel.

:class:`EditorApp` owns its windows (docs/architecture.md, "The editor is an app class"): the 3D view is an Open3D
legacy OpenGL window (:class:`kpd.viewer.glview.GLView`, fast with software rendering), the panel a Tk window beside
it (:class:`kpd.viewer.panel.EditorPanel`: checkboxes, buttons, the PCA sliders), and its frames are scheduled so
that input is never blocked behind drawing (:class:`kpd.viewer.scheduler.FrameScheduler`); panel and scheduler are
parts of the app class. Callbacks are ``_on_<event>`` methods, the UI state is one
:class:`~kpd.viewer.render.ViewSettings` applied in :meth:`EditorApp._apply_settings`. Deformation stays in
:class:`kpd.rig.Rig` and the edit history in :class:`~kpd.viewer.session.EditSession`.

The mesh is shown as soon as it is read: a rig still to be made (:class:`PendingRig`) is bound on a worker thread
while the window shows the mesh (it can be turned, nothing edited) and says so in the panel; the keypoints appear
when the rig is ready. The stand-in of a large mesh (:mod:`kpd.viewer.standins`) is made on that thread too. Work
that leaves the main thread comes back through :meth:`EditorApp.post_to_main_thread`.

Mouse and keys (also listed in the panel):

* left click on a keypoint: select it; shift + click: add it to (or take it out of) the selection;
  left drag from a selected keypoint: move the selection in the plane facing the camera (the mesh follows live);
  left drag elsewhere: orbit; right drag: pan; wheel: zoom.
* arrow keys: nudge the selection right/left/up/down on screen; page up / page down: towards / away from the camera.
* U (or Ctrl+Z): undo; Y (or Ctrl+Y): redo; R: reset; S: save the deformed mesh; J: save the session (JSON);
  L: load the session; P: screenshot (PNG); T: the prior on/off; Esc: clear the selection.

With ``events=PATH`` the app appends one JSON object per line for each thing it does (:mod:`kpd.viewer.events`:
``shown`` when the mesh is first on the screen, ``ready`` when its rig is too, with the camera matrices, the 3D view's
place on the screen and the sliders', ``input`` for each mouse or key event received, ``frame`` for each frame drawn
with the newest input it shows, ``select``, ``drag``, ``release``, ``nudge``, ``undo``, ``redo``, ``reset``,
``save``...), so scripts, tests and the benchmark can follow the window without reading pixels.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from kpd.errors import InputError, KpdError
from kpd.viewer.events import EventLog, read_events, wait_for
from kpd.viewer.panel import PANEL_WIDTH, VIEW_LEFT, VIEW_TOP, EditorPanel
from kpd.viewer.scheduler import GESTURE_BUDGET_MS, FrameScheduler, draws_stand_in
from kpd.viewer.render import Camera, Frame, ViewSettings, camera_pose, pixel_ray, plane_hit, project, write_png
from kpd.viewer.session import EditSession, propose

__all__ = ["EditorApp", "PendingRig", "Binding", "PANEL_WIDTH", "read_events", "wait_for", "draws_stand_in",
           "GESTURE_BUDGET_MS"]

log = logging.getLogger(__name__)

_PICK_PIXELS = 14.0  # a click this close to a marker's centre picks it

# GLFW key codes and modifiers (https://www.glfw.org/docs/latest/group__keys.html)
_KEYS = {"right": 262, "left": 263, "down": 264, "up": 265, "page_up": 266, "page_down": 267, "escape": 256}
_SHIFT, _CTRL = 0x0001, 0x0002
_PRESS, _RELEASE, _REPEAT = 1, 0, 2


class PendingRig(NamedTuple):
    """A rig still to be made: the editor shows ``mesh`` at once and calls ``bind()`` on a worker thread; it returns
    the rig of that mesh (:class:`kpd.rig.Rig` or :class:`kpd.frame.ScanRig`) with ``num_keypoints`` keypoints, or
    raises (a :class:`~kpd.errors.KpdError` ends the editor with its message)."""

    mesh: Any
    num_keypoints: int
    bind: Callable[[], Any]


Binding = PendingRig  # its name before this version


class EditorApp(EditorPanel, FrameScheduler):
    """The editor windows for one rig.

    Parameters
    ----------
    rig : kpd.rig.Rig (or kpd.frame.ScanRig), the shape to edit (mesh in its own units); or a :class:`PendingRig`,
        bound on a worker thread while the window shows its mesh.
    prior : kpd.prior.KeypointPrior or None: enables the "prior" toggle and the PCA sliders.
    settings : ViewSettings (size of the 3D view, what to show, the prior toggle, the nudge step).
    out : where "save mesh" writes the deformed mesh; None disables saving.
    session_path : where "save session" writes and "load session" reads (JSON).
    screenshot_path : screenshots go to this path with a running number before the suffix.
    events : a JSON-lines file to append events to, or None.
    title : the window title (the panel's is the same with " - panel").
    force : let "save mesh" and "save session" replace existing files.
    """

    def __init__(self, rig: Any, *, prior: Any = None, settings: ViewSettings | None = None,
                 out: str | os.PathLike | None = None, session_path: str | os.PathLike | None = None,
                 screenshot_path: str | os.PathLike | None = None, events: str | os.PathLike | None = None,
                 title: str = "kpd view", initial_session: str | os.PathLike | None = None,
                 force: bool = False) -> None:
        self._pending_rig = rig if isinstance(rig, PendingRig) else None
        self.rig = None if self._pending_rig is not None else rig  # None until a PendingRig's rig is ready
        self.mesh = rig.mesh
        self.num_keypoints = int(rig.num_keypoints)
        if prior is not None and prior.num_keypoints != self.num_keypoints:
            raise InputError(f"the model's prior has {prior.num_keypoints} keypoints; the rig has "
                             f"{self.num_keypoints}")
        self.prior = prior
        self.settings = settings or ViewSettings()
        self.out = None if out is None else Path(out)
        self.session_path = None if session_path is None else Path(session_path)
        self.screenshot_path = Path(screenshot_path) if screenshot_path is not None else Path("kpd_view.png")
        self.title = title
        self.force = force
        self._initial_session = initial_session
        self.session: EditSession | None = None  # None until the rig is ready
        if self.rig is not None:
            self._start_session()
        elif initial_session is not None:  # a bad file ends here, before any window
            EditSession(np.zeros((self.num_keypoints, 3))).load(initial_session)
        self.selection: list[int] = []
        self._log = None if events is None else EventLog(events)
        self._drag: dict | None = None
        self._orbit: dict | None = None
        self._pending_move: tuple[float, float] | None = None
        self._gesture = 0
        self._shots = 0
        self._init_panel()
        self._slider_base = None if self.session is None else self.session.keypoints
        self._buffer = np.empty_like(self.mesh.vertices)
        self._failure: BaseException | None = None
        self._init_scheduler()
        self._mouse = (0.0, 0.0)
        self._mods = 0

    # --- windows ---------------------------------------------------------------------------------------------

    def run(self) -> int:
        """Open the windows and run until the 3D view or the panel is closed; returns 0.

        BLAS runs on one thread meanwhile: the editor's products are small ((V, K) by (K, 3)), and a multi-threaded
        BLAS waiting for a core that another process holds makes each of them many times slower. The objects made
        before the first frame (the libraries', the windows') are left out of Python's garbage collection: a full
        collection of them would land in a frame.
        """
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            self._build()
            gc.freeze()
            try:
                self._loop()
            finally:
                self._close()
        if self._failure is not None:  # the worker's binding failed: its error ends the editor
            raise self._failure
        return 0

    def _start_session(self) -> None:
        self.session = EditSession(self.rig.keypoints)
        if self._initial_session is not None:
            self.session.load(self._initial_session)
        self._slider_base = self.session.keypoints

    def _stand_in(self) -> Any:
        from kpd.viewer.standins import image_maps, stand_in

        return stand_in(self.mesh.vertices, self.drawing.shaded.drawn, fine=not image_maps(self.mesh))

    def _start_worker(self) -> None:
        """The rig of a :class:`PendingRig`, after the stand-in of a large mesh, on a worker thread."""
        pending = self._pending_rig
        if pending is None:
            return

        def work() -> None:
            try:
                stand_in = self._stand_in()
                if stand_in is not None:
                    self.post_to_main_thread(lambda: self.drawing.set_stand_in(*stand_in))
                started = time.perf_counter()
                rig = pending.bind()
                log.info("bound the mesh in %.1f s", time.perf_counter() - started)
                self.post_to_main_thread(lambda: self._on_bound(rig))
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread, which ends with it
                self.post_to_main_thread(lambda failure=exc: self._on_worker_failed(failure))

        threading.Thread(target=work, name="kpd-editor-worker", daemon=True).start()

    def _on_bound(self, rig: Any) -> None:
        """The rig of the :class:`PendingRig` is ready: keypoints, cage and editing."""
        if len(rig.mesh.vertices) != len(self.mesh.vertices) or rig.num_keypoints != self.num_keypoints:
            raise KpdError(f"the rig has {len(rig.mesh.vertices)} vertices and {rig.num_keypoints} keypoints; the "
                           f"mesh shown has {len(self.mesh.vertices)} and {self.num_keypoints} were expected")
        self.rig = rig
        self._pending_rig = None
        gc.freeze()  # the rig's objects live as long as the editor (see run)
        self._start_session()
        self.drawing.set_keypoints(rig.num_keypoints, rig.cage.faces)
        self._changed()
        self._emit("ready")

    def _on_worker_failed(self, exc: BaseException) -> None:
        self._failure = exc
        self._running = False

    def _build(self) -> None:
        from kpd.viewer.glview import GLView
        from kpd.viewer.rigdrawing import RigDrawing

        s = self.settings
        self._started = time.time()
        self.view = GLView(s.width, s.height, title=self.title, visible=True, left=VIEW_LEFT, top=VIEW_TOP,
                           background=s.background)
        rig = self.rig
        self.drawing = RigDrawing(self.view, self.mesh, 0 if rig is None else rig.num_keypoints,
                                  None if rig is None else rig.cage.faces, settings=s)
        rest = self.mesh.vertices
        self.view.set_box(rest)
        self._home = camera_pose(rest, s, margin=0.75, closest=False)  # room for edits that grow the shape
        self.camera = self._home
        vis = self.view.vis
        vis.register_mouse_button_callback(self._on_mouse_button)
        vis.register_mouse_move_callback(self._on_mouse_move)
        vis.register_mouse_scroll_callback(self._on_scroll)
        for code in self._key_codes():
            vis.register_key_action_callback(code, lambda _vis, action, mods, code=code:
                                             self._on_key(code, action, mods))
        self._build_panel()
        if self.rig is not None:  # editing starts with the first frame: the stand-in of a large mesh is needed now
            stand_in = self._stand_in()
            if stand_in is not None:
                self.drawing.set_stand_in(*stand_in)
        self._draw()
        self._emit("shown")
        if self.rig is not None:
            self._emit("ready")
        self._start_worker()

    def _key_codes(self) -> list[int]:
        # every letter, digit and the keys used: unregistered keys would reach Open3D's own viewer shortcuts
        return [*range(ord("A"), ord("Z") + 1), *range(ord("0"), ord("9") + 1), *_KEYS.values(),
                ord("-"), ord("="), ord("["), ord("]"), ord("."), ord(","), ord("/")]

    def _close(self) -> None:
        self._emit("close")
        if self._frames_thread is not None:
            self._frames_thread.shutdown(wait=False, cancel_futures=True)
        try:
            self.root.destroy()
        except Exception:  # noqa: BLE001 - the panel may be gone already
            pass
        self.view.close()
        if self._log is not None:
            self._log.close()

    # --- the scene --------------------------------------------------------------------------------------------

    def _frame(self, rows: np.ndarray | None = None) -> Frame:
        """The current state; with ``rows``, only those vertices are deformed (the others keep older positions).
        Before the rig is ready: the rest mesh, no keypoints."""
        if self.rig is None:
            return Frame(self.mesh.vertices, np.zeros((0, 3)), None, ())
        keypoints = self.session.keypoints
        vertices = self.rig.deform(keypoints, out=self._buffer, rows=rows)
        return Frame(vertices, keypoints, self.rig.deform_cage(keypoints), tuple(self.selection))

    def _show(self, *, mesh: bool = True, fast: bool = False) -> None:
        # a frame drawn by a large mesh's stand-in needs the stand-in's vertices only
        stand_in = fast and self.drawing.stand_in is not None and not self.settings.xray
        rows = self.drawing.stand_in_rows if stand_in else None
        self.drawing.show(self._frame(rows), self.camera, mesh=mesh, fast=fast)

    def _bound(self) -> bool:
        """Whether the rig is ready for editing; says so in the panel when not."""
        if self.rig is None:
            self._message("binding the mesh to the model: keypoints appear when it is done")
        return self.rig is not None

    # --- camera -----------------------------------------------------------------------------------------------

    def _matrices(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        from kpd.viewer.render import look_at_matrix, perspective_matrix

        c, s = self.camera, self.settings
        return (look_at_matrix(c), perspective_matrix(c.fov, s.width / s.height, c.near, c.far), float(s.width),
                float(s.height))

    def _orbit_to(self, dx: float, dy: float) -> None:
        base = self._orbit["camera"]
        offset = base.eye - base.center
        up = base.up / np.linalg.norm(base.up)
        yaw = -dx * 0.01
        pitch = dy * 0.01
        offset = _rotate(offset, up, yaw)
        right = np.cross(offset, up)
        right /= max(np.linalg.norm(right), 1e-12)
        turned = _rotate(offset, right, pitch)
        if abs(float(turned @ up)) / np.linalg.norm(turned) < 0.995:  # stop short of looking straight along up
            offset = turned
        self.camera = Camera(center=base.center, eye=base.center + offset, up=base.up, fov=base.fov, near=base.near,
                             far=base.far)

    def _pan_to(self, dx: float, dy: float) -> None:
        base = self._orbit["camera"]
        view = self._orbit["view"]
        distance = float(np.linalg.norm(base.eye - base.center))
        scale = 2 * distance * math.tan(math.radians(base.fov) / 2) / self.settings.height
        shift = (-dx * view[0, :3] + dy * view[1, :3]) * scale
        self.camera = Camera(center=base.center + shift, eye=base.eye + shift, up=base.up, fov=base.fov,
                             near=base.near, far=base.far)

    def _on_scroll(self, _vis: Any, dx: float, dy: float) -> bool:
        self._count_input("scroll")
        c = self.camera
        factor = 0.9 ** float(dy)
        offset = (c.eye - c.center) * factor
        self.camera = Camera(center=c.center, eye=c.center + offset, up=c.up, fov=c.fov, near=c.near, far=c.far)
        self._changed(mesh=False)
        return False

    # --- gestures ---------------------------------------------------------------------------------------------

    def pick(self, x: float, y: float) -> int | None:
        """The keypoint under view pixel (x, y), or None (the nearest marker centre within the pick radius)."""
        if self.rig is None:
            return None
        view, projection, w, h = self._matrices()
        keypoints = self.session.keypoints
        pixels, depth = project(keypoints, view, projection, w, h)
        distance = np.linalg.norm(pixels - np.array([x, y]), axis=1)
        focal = h / 2 / math.tan(math.radians(self.camera.fov) / 2)
        radius = np.maximum(_PICK_PIXELS, 1.3 * focal * self.drawing.marker_radius / np.maximum(depth, 1e-12))
        distance[(depth <= 0) | (distance > radius)] = np.inf
        if not np.isfinite(distance).any():
            return None
        candidates = np.flatnonzero(distance <= distance.min() + 2.0)
        return int(candidates[np.argmin(depth[candidates])])  # the front one of overlapping markers

    def _on_mouse_button(self, _vis: Any, button: int, action: int, mods: int) -> bool:
        x, y = self._mouse
        self._mods = mods
        self._count_input("button", button=button, action=action, x=x, y=y)
        if action == _PRESS:
            if button == 0:
                index = self.pick(x, y)
                if index is None:
                    self._orbit = {"start": (x, y), "camera": self.camera, "view": self._matrices()[0], "pan": False}
                    return False
                if mods & _SHIFT:
                    if index in self.selection:
                        self.selection.remove(index)
                    else:
                        self.selection.append(index)
                elif index not in self.selection:
                    self.selection = [index]
                self._changed(mesh=False)
                self._emit("select", x=x, y=y, picked=index)
                if self.selection:
                    self._start_drag(x, y)
            elif button in (1, 2):  # right or middle: pan
                self._orbit = {"start": (x, y), "camera": self.camera, "view": self._matrices()[0], "pan": True}
        elif action == _RELEASE:
            self._apply_pending()
            if self._drag is not None:
                moved = self._drag["moved"]
                self._drag = None
                self.session.end_gesture()
                self._emit("release", moved=moved)
            self._orbit = None
        return False

    def _on_mouse_move(self, _vis: Any, x: float, y: float) -> bool:
        self._mouse = (float(x), float(y))
        if self._drag is not None or self._orbit is not None:
            self._count_input("move", x=float(x), y=float(y))
            self._pending_move = self._mouse  # coalesced: only the newest position is applied
        return False

    def _apply_pending(self) -> None:
        if self._pending_move is None:
            return
        x, y = self._pending_move
        self._pending_move = None
        if self._drag is not None:
            try:
                self._drag_to(x, y)
            except KpdError as exc:  # a degenerate ray; keep the window alive
                self._message(f"drag ignored: {exc}")
        elif self._orbit is not None:
            sx, sy = self._orbit["start"]
            (self._pan_to if self._orbit["pan"] else self._orbit_to)(x - sx, y - sy)
            self._changed(mesh=False)

    def _start_drag(self, x: float, y: float) -> None:
        view, projection, w, h = self._matrices()
        base = self.session.keypoints
        anchor = base[self.selection].mean(axis=0)
        forward = -view[2, :3]  # the camera looks down -z of its frame
        origin, direction = pixel_ray(x, y, view, projection, w, h)
        start = plane_hit(origin, direction, anchor, forward)
        self._gesture += 1
        self._drag = {"base": base, "anchor": anchor, "normal": forward, "start": start, "gesture": self._gesture,
                      "moved": False}

    def _drag_to(self, x: float, y: float) -> None:
        drag = self._drag
        if drag["start"] is None:
            return
        view, projection, w, h = self._matrices()
        origin, direction = pixel_ray(x, y, view, projection, w, h)
        hit = plane_hit(origin, direction, drag["anchor"], drag["normal"])
        if hit is None:
            return
        delta = hit - drag["start"]
        self._edit(drag["base"], delta, label="drag", merge=("drag", drag["gesture"]))
        drag["moved"] = True
        self._emit("drag", x=x, y=y, delta=delta.tolist())

    def _edit(self, base: np.ndarray, delta: np.ndarray, *, label: str, merge: Any) -> None:
        """Move the selection by ``delta`` from ``base`` (the others by the prior when it is on)."""
        edits = {i: base[i] + delta for i in self.selection}
        prior = self.prior if self.settings.prior else None
        keypoints = propose(base, edits, prior=prior, normalizer=self.rig.normalizer)
        if self.session.apply(keypoints, label=label, merge=merge):
            self._slider_base = self.session.keypoints
            self._reset_sliders()
            self._changed()

    def _nudge(self, axis: str, sign: float) -> None:
        if not self.selection or not self._bound():
            return
        view = self._matrices()[0]
        direction = {"right": view[0, :3], "up": view[1, :3], "forward": -view[2, :3]}[axis]
        step = self.settings.nudge_step * self.drawing.diagonal
        self._gesture += 1
        self._edit(self.session.keypoints, sign * step * direction, label="nudge", merge=None)
        self._emit("nudge", axis=axis, sign=sign)

    def _on_key(self, code: int, action: int, mods: int) -> bool:
        if action == _RELEASE:
            return False
        self._count_input("key", key=code, action=action)
        arrows = {_KEYS["right"]: ("right", 1.0), _KEYS["left"]: ("right", -1.0), _KEYS["up"]: ("up", 1.0),
                  _KEYS["down"]: ("up", -1.0), _KEYS["page_up"]: ("forward", 1.0),
                  _KEYS["page_down"]: ("forward", -1.0)}
        if code in arrows:
            self._nudge(*arrows[code])
            return False
        if action == _REPEAT:
            return False  # holding a letter does not repeat undo, saves, screenshots
        if mods & _CTRL and code in (ord("Z"), ord("Y")):
            (self._on_undo if code == ord("Z") else self._on_redo)()
            return False
        actions = {ord("U"): self._on_undo, ord("Y"): self._on_redo, ord("R"): self._on_reset,
                   ord("S"): self._on_save, ord("J"): self._on_save_session, ord("L"): self._on_load_session,
                   ord("P"): self._on_screenshot, ord("T"): lambda: self._on_setting("prior", not self.settings.prior),
                   ord("H"): self._on_home, _KEYS["escape"]: self._on_clear}
        action_ = actions.get(code)
        if action_ is not None:
            action_()
        return False

    def _on_home(self) -> None:
        self.camera = self._home
        self._changed(mesh=False)

    def _on_clear(self) -> None:
        self.selection = []
        self._changed(mesh=False)
        self._emit("select", picked=None)

    def _on_undo(self) -> None:
        if self._bound() and self.session.undo():
            self._after_history()
        self._emit("undo")

    def _on_redo(self) -> None:
        if self._bound() and self.session.redo():
            self._after_history()
        self._emit("redo")

    def _on_reset(self) -> None:
        if self._bound() and self.session.reset():
            self._after_history()
        self._emit("reset")

    def _after_history(self) -> None:
        self._slider_base = self.session.keypoints
        self._reset_sliders()
        self._changed()

    # --- files -----------------------------------------------------------------------------------------------

    def _on_save(self) -> None:
        from kpd.io import write_mesh

        if self.out is None:
            self._message("no output path: start kpd view with --out")
            return
        if not self._bound():
            return
        try:
            write_mesh(self.out, self.rig.deformed_mesh(self.session.keypoints))
        except KpdError as exc:
            self._message(f"save failed: {exc}")
            return
        self._message(f"saved {self.out}")
        self._emit("save", path=str(self.out))

    def _session_file(self) -> Path:
        return self.session_path if self.session_path is not None else Path("kpd_session.json")

    def _on_save_session(self) -> None:
        if not self._bound():
            return
        path = self._session_file()
        try:
            self.session.save(path, prior=bool(self.settings.prior and self.prior is not None))
        except KpdError as exc:
            self._message(f"session not saved: {exc}")
            return
        self._message(f"saved {path}")
        self._emit("save_session", path=str(path))

    def _on_load_session(self) -> None:
        if not self._bound():
            return
        path = self._session_file()
        try:
            self.session.load(path)
        except KpdError as exc:
            self._message(f"session not loaded: {exc}")
            return
        self._after_history()
        self._message(f"loaded {path}")
        self._emit("load_session", path=str(path))

    def _on_screenshot(self) -> None:
        """The 3D view as it is now (drawn at once with the newest state), numbers included, to a PNG."""
        self._shots += 1
        base = self.screenshot_path
        path = base.with_name(f"{base.stem}_{self._shots:03d}{base.suffix or '.png'}")
        while path.exists():
            self._shots += 1
            path = base.with_name(f"{base.stem}_{self._shots:03d}{base.suffix or '.png'}")
        self._apply_pending()
        self.drawing.show(self._frame(), self.camera, capture=True)
        image = self.view.capture()
        self._changed()  # the window samples its pixels otherwise: its next frame is drawn anew
        try:
            write_png(path, image)
        except KpdError as exc:
            self._message(f"screenshot failed: {exc}")
            return
        self._message(f"saved {path}")
        self._emit("screenshot", path=str(path))

    def _emit(self, event: str, **data: Any) -> None:
        if self._log is None:
            return
        record: dict[str, Any] = {"event": event, "time": time.time(), **data}
        if event not in ("input", "frame") and self.session is not None:
            record.update(selection=list(self.selection), keypoints=self.session.keypoints.tolist(),
                          undo=self.session.depth)
        if event == "frame":
            record["keypoints"] = self.drawing.frame.keypoints.tolist()
        if event in ("shown", "ready"):
            view, projection, w, h = self._matrices()
            record.update(view=view.tolist(), projection=projection.tolist(), viewport=[0, 0, w, h],
                          title=self.title, started=self._started,
                          sliders=[[s.winfo_rootx(), s.winfo_rooty(), s.winfo_width(), s.winfo_height()]
                                   for s in self.sliders])
        self._log.write(record)


def _rotate(vector: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``vector`` turned by ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    axis = axis / max(np.linalg.norm(axis), 1e-12)
    return (vector * math.cos(angle) + np.cross(axis, vector) * math.sin(angle)
            + axis * (axis @ vector) * (1 - math.cos(angle)))
