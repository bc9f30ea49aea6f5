"""The keypoint editor: an Open3D window in which keypoints are picked and dragged and the mesh deforms live.

:class:`EditorApp` owns the window (STYLE.md, "the editor is an app class"): widgets are attributes, callbacks are
``_on_<event>`` methods, the UI state is one :class:`~kpd.viewer.render.ViewSettings` applied in
:meth:`EditorApp._apply_settings`. Deformation stays in :class:`kpd.rig.Rig` and the edit history in
:class:`~kpd.viewer.session.EditSession`; the app only turns gestures into keypoint edits.

Mouse and keys (also listed in the panel):

* left click on a keypoint: select it; shift + click: add it to (or take it out of) the selection;
  left drag from a selected keypoint: move the selection in the plane facing the camera (the mesh follows live);
  left drag elsewhere: orbit, wheel: zoom, right/middle drag: pan (Open3D's camera controls).
* arrow keys: nudge the selection right/left/up/down on screen; page up / page down: towards / away from the camera.
* U (or Ctrl+Z): undo; Y (or Ctrl+Y): redo; R: reset; S: save the deformed mesh; J: save the session (JSON);
  L: load the session; P: screenshot (PNG); T: the prior on/off; Esc: clear the selection.

With ``events=PATH`` the app appends one JSON object per line for each thing it does (``ready`` with the camera
matrices and the 3D view's place in the window, ``select``, ``drag``, ``release``, ``nudge``, ``undo``, ``redo``,
``reset``, ``save``...), each with the selection and the current keypoints, so scripts and tests can follow the
window without reading pixels.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from kpd.errors import InputError, KpdError
from kpd.viewer.render import (
    Frame, RigScene, ViewSettings, add_fill_light, camera_pose, label_image, pixel_ray, plane_hit, project, write_png,
)
from kpd.viewer.session import EditSession, component_offsets, propose

__all__ = ["EditorApp", "PANEL_WIDTH"]

log = logging.getLogger(__name__)

PANEL_WIDTH = 300  # pixels at scaling 1
_PICK_PIXELS = 14.0  # a click this close to a marker's centre picks it
_MAX_SLIDERS = 8


class EditorApp:
    """The editor window for one rig.

    Parameters
    ----------
    rig : kpd.rig.Rig, the shape to edit (mesh in its own units).
    prior : kpd.prior.KeypointPrior or None: enables the "prior" toggle and the PCA sliders.
    settings : ViewSettings (window size of the 3D view, what to show, the prior toggle, the nudge step).
    out : where "save mesh" writes the deformed mesh; None disables saving.
    session_path : where "save session" writes and "load session" reads (JSON).
    screenshot_path : screenshots go to this path with a running number before the suffix.
    events : a JSON-lines file to append events to, or None.
    title : the window title.
    """

    def __init__(self, rig: Any, *, prior: Any = None, settings: ViewSettings | None = None,
                 out: str | os.PathLike | None = None, session_path: str | os.PathLike | None = None,
                 screenshot_path: str | os.PathLike | None = None, events: str | os.PathLike | None = None,
                 title: str = "kpd view", initial_session: str | os.PathLike | None = None) -> None:
        if prior is not None and prior.num_keypoints != rig.num_keypoints:
            raise InputError(f"the model's prior has {prior.num_keypoints} keypoints; the rig has {rig.num_keypoints}")
        self.rig = rig
        self.prior = prior
        self.settings = settings or ViewSettings()
        self.out = None if out is None else Path(out)
        self.session_path = None if session_path is None else Path(session_path)
        self.screenshot_path = Path(screenshot_path) if screenshot_path is not None else Path("kpd_view.png")
        self.title = title
        self.session = EditSession(rig.keypoints)
        if initial_session is not None:
            self.session.load(initial_session)
        self.selection: list[int] = []
        self._events = None if events is None else Path(events)
        self._drag: dict | None = None
        self._gesture = 0
        self._shots = 0
        self._sigmas = np.zeros(0)
        self._slider_base = self.session.keypoints
        self._ctrl = False
        self._buffer = np.empty_like(rig.mesh.vertices)
        self._labels: list[Any] = []

    # --- window --------------------------------------------------------------------------------------------------

    def run(self) -> int:
        """Open the window and run until it is closed; returns 0."""
        import open3d.visualization.gui as gui

        app = gui.Application.instance
        app.initialize()
        self._build(app)
        app.run()
        return 0

    def _build(self, app: Any) -> None:
        import open3d.visualization.gui as gui
        import open3d.visualization.rendering as rendering

        s = self.settings
        self.app = app
        self.window = app.create_window(self.title, s.width + PANEL_WIDTH, s.height)
        w = self.window
        em = w.theme.font_size
        self.widget = gui.SceneWidget()
        self.widget.scene = rendering.Open3DScene(w.renderer)
        self.widget.set_on_mouse(self._on_mouse)
        w.add_child(self.widget)
        self._build_panel(gui, em)
        w.set_on_layout(self._on_layout)
        w.set_on_key(self._on_key)
        w.set_on_close(self._on_close)
        self.scene = RigScene(self.rig.mesh, self.rig.num_keypoints, self.rig.cage.faces, settings=s)
        self.scene.attach(self.widget.scene, self._frame())
        self.widget.scene.view.set_post_processing(False)
        self.widget.scene.set_lighting(rendering.Open3DScene.LightingProfile.NO_SHADOWS, _sun(s))
        add_fill_light(self.widget.scene, _sun(s))
        self._camera = camera_pose(self.rig.mesh.vertices, s)
        self._reset_camera()
        self._make_labels()
        self._apply_settings()
        self._ready_pending = True
        w.set_on_tick_event(self._on_tick)

    def _build_panel(self, gui: Any, em: float) -> None:
        margin = gui.Margins(0.5 * em, 0.5 * em, 0.5 * em, 0.5 * em)
        panel = gui.ScrollableVert(0.3 * em, margin)
        self.panel = panel
        panel.add_child(gui.Label(f"{self.title}\n{self.rig.num_keypoints} keypoints, "
                                  f"{len(self.rig.mesh.vertices)} vertices"))

        show = gui.CollapsableVert("Show", 0.25 * em, gui.Margins(em, 0, 0, 0))
        self.show_keypoints = gui.Checkbox("keypoints")
        self.show_labels = gui.Checkbox("numbers")
        self.show_cage = gui.Checkbox("cage (wireframe)")
        self.show_ghost = gui.Checkbox("original shape (ghost)")
        self.xray = gui.Checkbox("see-through mesh")
        for box, name in ((self.show_keypoints, "show_keypoints"), (self.show_labels, "show_labels"),
                          (self.show_cage, "show_cage"), (self.show_ghost, "show_ghost"), (self.xray, "xray")):
            box.checked = getattr(self.settings, name)
            box.set_on_checked(lambda checked, name=name: self._on_setting(name, checked))
            show.add_child(box)
        panel.add_child(show)

        edit = gui.CollapsableVert("Edit", 0.25 * em, gui.Margins(em, 0, 0, 0))
        self.prior_box = gui.Checkbox("prior (others follow the category)")
        self.prior_box.checked = self.settings.prior and self.prior is not None
        self.prior_box.enabled = self.prior is not None
        self.prior_box.set_on_checked(lambda checked: self._on_setting("prior", checked))
        edit.add_child(self.prior_box)
        row = gui.Horiz(0.25 * em)
        row.add_child(gui.Label("nudge step"))
        self.step = gui.NumberEdit(gui.NumberEdit.DOUBLE)
        self.step.double_value = self.settings.nudge_step
        self.step.set_limits(1e-4, 0.5)
        self.step.set_on_value_changed(lambda value: self._on_setting("nudge_step", float(value)))
        row.add_child(self.step)
        edit.add_child(row)
        buttons = [("Undo (U)", self._on_undo), ("Redo (Y)", self._on_redo), ("Reset (R)", self._on_reset),
                   ("Save mesh (S)", self._on_save), ("Save session (J)", self._on_save_session),
                   ("Load session (L)", self._on_load_session), ("Screenshot (P)", self._on_screenshot)]
        for i in range(0, len(buttons), 2):
            row = gui.Horiz(0.25 * em)
            for text, callback in buttons[i:i + 2]:
                button = gui.Button(text)
                button.horizontal_padding_em = 0.3
                button.set_on_clicked(callback)
                row.add_child(button)
            edit.add_child(row)
        panel.add_child(edit)

        self.sliders = []
        self.pca_panel = None
        if self.prior is not None:
            # a plain Vert pinned under the scrolling panel: inside a ScrollableVert, Open3D draws a slider's track in
            # the panel's own colour, and only the thumb would show
            count = min(len(self.prior.components_), _MAX_SLIDERS)
            self.pca_panel = gui.Vert(0.25 * em, margin)
            self.pca_panel.add_child(gui.Label("Category (PCA, std. dev.)"))
            self._sigmas = np.zeros(len(self.prior.components_))
            grid = gui.VGrid(2, 0.25 * em)
            for m in range(count):
                grid.add_child(gui.Label(f"{m + 1}"))
                slider = gui.Slider(gui.Slider.DOUBLE)
                slider.set_limits(-3.0, 3.0)
                slider.double_value = 0.0
                slider.set_on_value_changed(lambda value, m=m: self._on_slider(m, value))
                grid.add_child(slider)
                self.sliders.append(slider)
            self.pca_panel.add_child(grid)

        panel.add_child(gui.Label("click: select   shift+click: add\n"
                                  "drag a keypoint: move it\n"
                                  "drag elsewhere: orbit   wheel: zoom\n"
                                  "arrows, PgUp/PgDn: nudge\n"
                                  "U undo  Y redo  R reset  T prior\n"
                                  "S save mesh  J/L session  P shot"))
        self.status = gui.Label("")
        panel.add_child(self.status)
        self.window.add_child(panel)
        if self.pca_panel is not None:
            self.window.add_child(self.pca_panel)

    def _on_layout(self, context: Any) -> None:
        import open3d.visualization.gui as gui

        r = self.window.content_rect
        width = int(round(PANEL_WIDTH * self.window.scaling))
        self.widget.frame = gui.Rect(r.x, r.y, max(r.width - width, 1), r.height)
        below = 0
        if self.pca_panel is not None:
            below = min(self.pca_panel.calc_preferred_size(context, gui.Widget.Constraints()).height, r.height // 2)
            self.pca_panel.frame = gui.Rect(r.get_right() - width, r.get_bottom() - below, width, below)
        self.panel.frame = gui.Rect(r.get_right() - width, r.y, width, r.height - below)
        self._set_projection()

    def _reset_camera(self) -> None:
        c = self._camera
        self.widget.look_at(c.center.astype(np.float32), c.eye.astype(np.float32), c.up.astype(np.float32))
        self.widget.center_of_rotation = c.center.astype(np.float32)
        self._set_projection()

    def _set_projection(self) -> None:
        import open3d.visualization.rendering as rendering

        frame = self.widget.frame
        aspect = frame.width / max(frame.height, 1) if frame.width > 1 else self.settings.width / self.settings.height
        c = self._camera
        self.widget.scene.camera.set_projection(c.fov, aspect, c.near, c.far, rendering.Camera.FovType.Vertical)

    def _on_tick(self) -> bool:
        if self._ready_pending and self.widget.frame.width > 1:
            self._ready_pending = False
            self._emit("ready")
        return False

    def _on_close(self) -> bool:
        self._emit("close")
        return True

    # --- the scene --------------------------------------------------------------------------------------------

    def _frame(self) -> Frame:
        keypoints = self.session.keypoints
        vertices = self.rig.deform(keypoints, out=self._buffer)
        return Frame(vertices, keypoints, self.rig.deform_cage(keypoints), tuple(self.selection))

    def _refresh(self, *, mesh: bool = True) -> None:
        """Show the session's current keypoints: deform, upload, move the markers and numbers."""
        frame = self._frame()
        self.scene.update(frame, mesh=mesh)
        for label, position in zip(self._labels, self._label_positions(frame.keypoints)):
            label.position = position.astype(np.float32)
        self._update_status()
        self.window.post_redraw()

    def _label_positions(self, keypoints: np.ndarray) -> np.ndarray:
        """(K, 3): beside each marker, up and to the right as the start camera sees it (clear of the marker)."""
        c = self._camera
        forward = (c.center - c.eye) / np.linalg.norm(c.center - c.eye)
        right = np.cross(forward, c.up)
        right /= max(np.linalg.norm(right), 1e-12)
        return np.asarray(keypoints) + self.scene.marker_radius * (1.3 * right + 1.0 * c.up)

    def _make_labels(self) -> None:
        import open3d.visualization.gui as gui

        for label in self._labels:
            self.widget.remove_3d_label(label)
        self._labels = []
        if not (self.settings.show_labels and self.settings.show_keypoints):
            return
        positions = self._label_positions(self.session.keypoints)
        for i, position in enumerate(positions):
            label = self.widget.add_3d_label(position.astype(np.float32), str(i))
            r, g, b = (0.75 * self.scene.colors[i]).tolist()
            label.color = gui.Color(r, g, b, 1.0)
            label.scale = 1.4
            self._labels.append(label)

    def _apply_settings(self) -> None:
        """The one place where the settings reach the widgets and the scene."""
        s = self.settings
        self.scene.apply_settings(s)
        self.show_keypoints.checked = s.show_keypoints
        self.show_labels.checked = s.show_labels
        self.show_cage.checked = s.show_cage
        self.show_ghost.checked = s.show_ghost
        self.xray.checked = s.xray
        self.prior_box.checked = s.prior and self.prior is not None
        self._make_labels()
        self._update_status()
        self.window.post_redraw()

    def _on_setting(self, name: str, value: Any) -> None:
        if name == "prior" and self.prior is None:
            value = False
        self.settings = self.settings.replace(**{name: value})
        self._apply_settings()
        self._emit("settings", name=name, value=value)

    def _update_status(self) -> None:
        moved = len(self.session.moved)
        prior = "on" if self.settings.prior and self.prior is not None else "off"
        self.status.text = (f"selected: {', '.join(map(str, self.selection)) or '-'}\n"
                            f"moved: {moved}   undo: {self.session.depth}   prior: {prior}")

    # --- gestures ---------------------------------------------------------------------------------------------

    def _matrices(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        camera = self.widget.scene.camera
        frame = self.widget.frame
        return (np.asarray(camera.get_view_matrix(), dtype=np.float64),
                np.asarray(camera.get_projection_matrix(), dtype=np.float64), float(frame.width), float(frame.height))

    def pick(self, x: float, y: float) -> int | None:
        """The keypoint under widget pixel (x, y), or None (the nearest marker centre within the pick radius)."""
        view, projection, w, h = self._matrices()
        keypoints = self.session.keypoints
        pixels, depth = project(keypoints, view, projection, w, h)
        distance = np.linalg.norm(pixels - np.array([x, y]), axis=1)
        focal = h / 2 / math.tan(math.radians(self._camera.fov) / 2)
        radius = np.maximum(_PICK_PIXELS, 1.3 * focal * self.scene.marker_radius / np.maximum(depth, 1e-12))
        distance[(depth <= 0) | (distance > radius)] = np.inf
        if not np.isfinite(distance).any():
            return None
        candidates = np.flatnonzero(distance <= distance.min() + 2.0)
        return int(candidates[np.argmin(depth[candidates])])  # the front one of overlapping markers

    def _on_mouse(self, event: Any) -> Any:
        import open3d.visualization.gui as gui

        ignored = gui.Widget.EventCallbackResult.IGNORED
        consumed = gui.Widget.EventCallbackResult.CONSUMED
        frame = self.widget.frame
        x, y = event.x - frame.x, event.y - frame.y
        left = event.is_button_down(gui.MouseButton.LEFT)
        if event.type == gui.MouseEvent.Type.BUTTON_DOWN and left:
            index = self.pick(x, y)
            if index is None:
                return ignored  # orbit
            shift = event.is_modifier_down(gui.KeyModifier.SHIFT)
            if shift:
                if index in self.selection:
                    self.selection.remove(index)
                else:
                    self.selection.append(index)
            elif index not in self.selection:
                self.selection = [index]
            self._refresh(mesh=False)
            self._emit("select", x=x, y=y, picked=index)
            if self.selection:
                self._start_drag(x, y)
            return consumed
        if event.type == gui.MouseEvent.Type.DRAG and self._drag is not None:
            try:
                self._drag_to(x, y)
            except KpdError as exc:  # a degenerate ray; keep the window alive
                self._message(f"drag ignored: {exc}")
            return consumed
        if event.type == gui.MouseEvent.Type.BUTTON_UP and self._drag is not None:
            moved = self._drag["moved"]
            self._drag = None
            self.session.end_gesture()
            self._emit("release", moved=moved)
            return consumed
        return ignored

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
        """Move the selection by ``delta`` from ``base`` (the others by the prior when it is on) and show it."""
        edits = {i: base[i] + delta for i in self.selection}
        prior = self.prior if self.settings.prior else None
        keypoints = propose(base, edits, prior=prior, normalizer=self.rig.normalizer)
        if self.session.apply(keypoints, label=label, merge=merge):
            self._slider_base = self.session.keypoints
            self._reset_sliders()
            self._refresh()

    def _nudge(self, axis: str, sign: float) -> None:
        if not self.selection:
            return
        view = self._matrices()[0]
        direction = {"right": view[0, :3], "up": view[1, :3], "forward": -view[2, :3]}[axis]
        step = self.settings.nudge_step * self.scene.diagonal
        self._gesture += 1
        self._edit(self.session.keypoints, sign * step * direction, label="nudge", merge=None)
        self._emit("nudge", axis=axis, sign=sign)

    def _on_key(self, event: Any) -> Any:
        import open3d.visualization.gui as gui

        ignored = gui.Widget.EventCallbackResult.IGNORED
        handled = gui.Widget.EventCallbackResult.HANDLED
        key = event.key
        if key in (gui.KeyName.LEFT_CONTROL, gui.KeyName.RIGHT_CONTROL):
            self._ctrl = event.type == gui.KeyEvent.Type.DOWN
            return ignored
        if event.type != gui.KeyEvent.Type.DOWN:
            return ignored
        arrows = {gui.KeyName.RIGHT: ("right", 1.0), gui.KeyName.LEFT: ("right", -1.0),
                  gui.KeyName.UP: ("up", 1.0), gui.KeyName.DOWN: ("up", -1.0),
                  gui.KeyName.PAGE_UP: ("forward", 1.0), gui.KeyName.PAGE_DOWN: ("forward", -1.0)}
        if key in arrows:
            self._nudge(*arrows[key])
            return handled
        actions = {gui.KeyName.U: self._on_undo, gui.KeyName.Y: self._on_redo, gui.KeyName.R: self._on_reset,
                   gui.KeyName.S: self._on_save, gui.KeyName.J: self._on_save_session,
                   gui.KeyName.L: self._on_load_session, gui.KeyName.P: self._on_screenshot,
                   gui.KeyName.T: lambda: self._on_setting("prior", not self.settings.prior),
                   gui.KeyName.ESCAPE: self._on_clear}
        if self._ctrl and key == gui.KeyName.Z:
            self._on_undo()
            return handled
        if key in actions:
            actions[key]()
            return handled
        return ignored

    def _on_clear(self) -> None:
        self.selection = []
        self._refresh(mesh=False)
        self._emit("select", picked=None)

    def _on_undo(self) -> None:
        if self.session.undo():
            self._after_history()
        self._emit("undo")

    def _on_redo(self) -> None:
        if self.session.redo():
            self._after_history()
        self._emit("redo")

    def _on_reset(self) -> None:
        if self.session.reset():
            self._after_history()
        self._emit("reset")

    def _after_history(self) -> None:
        self._slider_base = self.session.keypoints
        self._reset_sliders()
        self._refresh()

    def _reset_sliders(self) -> None:
        self._sigmas[:] = 0.0
        for slider in self.sliders:
            slider.double_value = 0.0

    def _on_slider(self, m: int, value: float) -> None:
        self._sigmas[m] = float(value)
        keypoints = self._slider_base + component_offsets(self.prior, self.rig.normalizer, self._sigmas)
        if self.session.apply(keypoints, label="component", merge=("component", m)):
            self._refresh()
        self._emit("component", component=m, value=float(value))

    # --- files -----------------------------------------------------------------------------------------------

    def _on_save(self) -> None:
        from kpd.io import write_mesh

        if self.out is None:
            self._message("no output path: start kpd view with --out")
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
        path = self._session_file()
        try:
            self.session.save(path, prior=bool(self.settings.prior and self.prior is not None))
        except KpdError as exc:
            self._message(f"session not saved: {exc}")
            return
        self._message(f"saved {path}")
        self._emit("save_session", path=str(path))

    def _on_load_session(self) -> None:
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
        self._shots += 1
        base = self.screenshot_path
        path = base.with_name(f"{base.stem}_{self._shots:03d}{base.suffix or '.png'}")
        while path.exists():
            self._shots += 1
            path = base.with_name(f"{base.stem}_{self._shots:03d}{base.suffix or '.png'}")
        frame = self._frame()
        view, projection, w, h = self._matrices()

        def on_image(image: Any) -> None:
            array = np.asarray(image)[:, :, :3].copy()
            camera = self._camera_now()
            labelled = label_image(array, self.scene, frame, camera)
            self.app.post_to_main_thread(self.window, lambda: self._write_shot(path, labelled))

        self.widget.scene.scene.render_to_image(on_image)
        self.window.post_redraw()

    def _write_shot(self, path: Path, image: np.ndarray) -> None:
        try:
            write_png(path, image)
        except KpdError as exc:
            self._message(f"screenshot failed: {exc}")
            return
        self._message(f"saved {path}")
        self._emit("screenshot", path=str(path))

    def _camera_now(self) -> Any:
        """The current (possibly orbited) camera as a render.Camera, for drawing numbers into screenshots."""
        from kpd.viewer.render import Camera

        view = self._matrices()[0]
        rotation, translation = view[:3, :3], view[:3, 3]
        eye = -rotation.T @ translation
        forward = -rotation[2]
        c = self._camera
        return Camera(center=eye + forward, eye=eye, up=rotation[1], fov=c.fov, near=c.near, far=c.far)

    def _message(self, text: str) -> None:
        log.info("%s", text)
        self._update_status()
        self.status.text = self.status.text + "\n" + text
        self.window.post_redraw()

    def _emit(self, event: str, **data: Any) -> None:
        if self._events is None:
            return
        record = {"event": event, "time": time.time(), "selection": list(self.selection),
                  "keypoints": self.session.keypoints.tolist(), "undo": self.session.depth, **data}
        if event == "ready":
            view, projection, w, h = self._matrices()
            frame = self.widget.frame
            record.update(view=view.tolist(), projection=projection.tolist(), viewport=[frame.x, frame.y, w, h],
                          scaling=float(self.window.scaling), title=self.title,
                          sliders=[[f.x, f.y, f.width, f.height] for f in (s.frame for s in self.sliders)])
        with open(self._events, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(record) + "\n")


def _sun(settings: ViewSettings) -> np.ndarray:
    from kpd.viewer.render import _sun_direction

    return _sun_direction(settings)
