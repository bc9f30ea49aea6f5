"""The editor's frame scheduler: input is never blocked behind drawing.

The loop takes every pending input first (window-system events of both windows, then what worker threads handed back),
then draws at most one frame of the newest state: mouse moves of a drag are coalesced to the latest position, keys are
applied as they arrive, and nothing is drawn while nothing changed. A mesh with a stand-in
(:mod:`kpd.viewer.standins`) is drawn by it while input flows (:func:`draws_stand_in`), and whole again once input
pauses: the whole frame is prepared on the frame thread after :data:`_PREPARE_AFTER` s (an input stops the
preparation within a few milliseconds, see :func:`kpd.viewer.culling.visible_triangles`) and drawn from
:data:`_REFINE_AFTER` s if it is still the state on the screen.

:class:`FrameScheduler` is a part of :class:`kpd.viewer.app.EditorApp`.
"""

from __future__ import annotations

import collections
import math
import queue
import time
from typing import Any, Callable

import numpy as np

from kpd.viewer.settings import Frame

__all__ = ["FrameScheduler", "draws_stand_in", "GESTURE_BUDGET_MS"]

_PREPARE_AFTER = 0.05  # s without input before a large mesh's whole frame is prepared on the frame thread
_REFINE_AFTER = 0.3  # s without input before a large mesh's stand-in is replaced by the whole mesh
# a mesh with a fine stand-in is drawn by it while input flows when the median of its last _WHOLE_FRAMES whole frames
# took longer than this on the main thread (draws_stand_in)
GESTURE_BUDGET_MS = 25.0
_WHOLE_FRAMES = 5


def draws_stand_in(drawn: int, whole_ms: Any) -> bool:
    """Whether the editor draws a mesh of ``drawn`` triangles that has a stand-in by it while input flows (the whole
    mesh again once input pauses): always above :data:`kpd.viewer.standins.COARSE_STAND_IN_TRIANGLES`; below, when
    the median of the whole mesh's last frames ``whole_ms`` (milliseconds on the main thread) is over
    :data:`GESTURE_BUDGET_MS`, so that a machine which draws the whole mesh fast enough keeps it whole, and one
    without a GPU draws a CAD chair's fine stand-in (:func:`kpd.viewer.standins.fine_stand_in`, the same picture)
    faster (docs/results.md)."""
    from kpd.viewer.standins import COARSE_STAND_IN_TRIANGLES

    if drawn > COARSE_STAND_IN_TRIANGLES:
        return True
    return len(whole_ms) > 0 and float(np.median(np.asarray(whole_ms, dtype=np.float64))) > GESTURE_BUDGET_MS


class FrameScheduler:
    """The frame scheduler of an editor app. The app provides the scene (``drawing``, ``view``, ``camera``, ``rig``,
    ``mesh``, ``session``, ``selection``), ``_show`` (a frame of the newest state), ``_apply_pending`` (the newest
    mouse position), ``_emit`` and ``_on_worker_failed``; its panel (``root``, ``_update_status``) comes from
    :class:`kpd.viewer.panel.EditorPanel`."""

    def _init_scheduler(self) -> None:
        self._posted: queue.SimpleQueue = queue.SimpleQueue()  # callables from the worker threads
        self._frames_thread: Any = None  # prepares a large mesh's whole frame (ShadedMesh.prepare)
        self._preparing: tuple | None = None  # the state being prepared there
        self._stop = np.zeros(1, np.uint8)  # (1,) set to abandon the preparation on the frame thread
        self._whole: tuple | None = None  # (state, vertices, uploads, milliseconds) of a prepared whole frame
        self._spares: list[np.ndarray] = []  # (V, 3) buffers for the frame thread's deformations, none in use
        self._inputs = 0  # input events received
        self._last_input = -math.inf  # time.monotonic() of the newest one
        self._dirty_mesh = True
        self._dirty = True
        self._frames = 0
        self._whole_ms: collections.deque = collections.deque(maxlen=_WHOLE_FRAMES)  # the last whole frames' draws
        self._running = False

    def post_to_main_thread(self, action: Callable[[], Any]) -> None:
        """Run ``action()`` on the main thread, between two frames (how the worker hands its results back)."""
        self._posted.put(action)

    def _run_posted(self) -> None:
        while True:
            try:
                action = self._posted.get_nowait()
            except queue.Empty:
                return
            action()

    def _count_input(self, kind: str, **data: Any) -> None:
        self._inputs += 1
        self._last_input = time.monotonic()
        self._stop[0] = 1  # a whole frame being prepared may no longer be the one wanted (a newer one will be)
        self._emit("input", kind=kind, **data)

    def _changed(self, *, mesh: bool = True) -> None:
        self._dirty = True
        self._dirty_mesh = self._dirty_mesh or mesh
        self._update_status()

    def _loop(self) -> None:
        self._running = True
        vis = self.view.vis
        while self._running:
            if not vis.poll_events():  # window-system events of the 3D view: the callbacks only record them
                break
            self.root.update()  # the panel's events
            self._run_posted()  # results of the worker threads
            if not self._running:
                break
            self._apply_pending()
            if self._dirty:
                self._draw()
            elif not self._refine():
                time.sleep(0.004)

    def _draw(self) -> None:
        """Draw the newest state: one frame, whatever number of inputs it answers. A mesh with a stand-in is drawn by
        it; its whole frame comes from :meth:`_refine`."""
        started = time.perf_counter()
        serial = self._inputs
        fast = self.drawing.stand_in is not None and draws_stand_in(len(self.drawing.shaded.drawn), self._whole_ms)
        self._show(mesh=self._dirty_mesh, fast=fast)
        self._dirty = self._dirty_mesh = False
        self.view.draw()
        self._frames += 1
        milliseconds = 1000 * (time.perf_counter() - started)
        if not self.drawing.stand_in_shown and self._frames > 1:  # the first frame's draw compiles llvmpipe's shaders
            self._whole_ms.append(milliseconds)
        self._emit("frame", serial=serial, draw_ms=round(milliseconds, 3), frame=self._frames,
                   stand_in=self.drawing.stand_in_shown)

    def _refine(self) -> bool:
        """Once input pauses, a large mesh's whole frame in place of its stand-in: prepared on the frame thread
        after :data:`_PREPARE_AFTER` s (the deformation, normals, the triangles that show, colours), drawn from
        :data:`_REFINE_AFTER` s when it is ready and still the state on the screen. Returns whether it drew."""
        if not self.drawing.stand_in_shown:
            return False
        idle = time.monotonic() - self._last_input
        if idle < _PREPARE_AFTER:
            return False
        state = self._state()
        if self._whole is None or self._whole[0] != state:
            if self._preparing != state:
                self._prepare_whole(state)
            return False
        if idle < _REFINE_AFTER:
            return False
        _, vertices, uploads, prepare_ms = self._whole
        self._whole = None
        started = time.perf_counter()
        serial = self._inputs
        keypoints = np.zeros((0, 3)) if self.session is None else self.session.keypoints
        cage = None if self.rig is None else self.rig.deform_cage(keypoints)
        self.drawing.show(Frame(vertices, keypoints, cage, tuple(self.selection)), self.camera, prepared=uploads)
        self._spare(vertices)  # the geometries hold their own copies now
        self.view.draw()
        self._frames += 1
        milliseconds = 1000 * (time.perf_counter() - started)
        self._whole_ms.append(milliseconds)
        self._emit("frame", serial=serial, draw_ms=round(milliseconds, 3), prepare_ms=prepare_ms, frame=self._frames,
                   stand_in=False)
        return True

    def _state(self) -> tuple:
        """What a whole frame depends on: the keypoints and the camera."""
        c = self.camera
        keypoints = None if self.session is None else self.session.keypoints.tobytes()
        return keypoints, tuple(c.eye), tuple(c.center), tuple(c.up), c.fov

    def _prepare_whole(self, state: tuple) -> None:
        from concurrent.futures import ThreadPoolExecutor

        if self._frames_thread is None:
            self._frames_thread = ThreadPoolExecutor(1, thread_name_prefix="kpd-editor-frames")
        self._preparing = state
        rig, mesh, drawing, camera = self.rig, self.mesh, self.drawing, self.camera
        keypoints = None if self.session is None else self.session.keypoints
        self._stop = stop = np.zeros(1, np.uint8)  # set by the next input (_count_input): the frame is not wanted
        # a buffer the main thread hands out and takes back: fresh memory for a large mesh is slow to touch
        out = None if rig is None else (self._spares.pop() if self._spares else np.empty_like(mesh.vertices))

        def work() -> None:
            try:
                started = time.perf_counter()
                vertices = mesh.vertices if rig is None else rig.deform(keypoints, out=out)
                uploads = None if stop[0] else drawing.shaded.prepare(vertices, camera, drawing.view.viewport(camera),
                                                                      stop=stop)
                milliseconds = round(1000 * (time.perf_counter() - started), 3)
                self.post_to_main_thread(lambda: self._on_prepared(state, vertices, uploads, milliseconds))
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread, which ends with it
                self.post_to_main_thread(lambda failure=exc: self._on_worker_failed(failure))

        self._frames_thread.submit(work)

    def _on_prepared(self, state: tuple, vertices: np.ndarray, uploads: list | None, milliseconds: float) -> None:
        if self._preparing == state:
            self._preparing = None
        if uploads is None:
            self._spare(vertices)
            return
        if self._whole is not None:
            self._spare(self._whole[1])
        self._whole = (state, vertices, uploads, milliseconds)

    def _spare(self, vertices: np.ndarray) -> None:
        """Take back a deformation buffer of the frame thread (not the rest mesh's vertices)."""
        if vertices is not self.mesh.vertices:
            self._spares.append(vertices)
