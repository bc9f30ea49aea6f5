"""A rig in a view (:class:`RigDrawing`): the mesh (or its stand-in during a gesture), keypoint markers with the
selected ones larger, the cage wireframe, the rest shape as a ghost wireframe and the keypoint numbers as
camera-facing digits, in a :class:`~kpd.viewer.glview.GLView`."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from kpd.viewer.camera import box
from kpd.viewer.glview import GLView
from kpd.viewer.markers import Digits, Markers, line_set, mesh_edges
from kpd.viewer.settings import cage_edges, keypoint_palette
from kpd.viewer.shaded import ShadedMesh
from kpd.viewer.standins import stand_in_colors

__all__ = ["RigDrawing"]


class RigDrawing:
    """The geometries of one rig being edited, in a :class:`GLView`.

    Parameters
    ----------
    view : GLView.
    mesh : kpd.io.Mesh, the rest mesh in user units.
    num_keypoints : K (0: the mesh alone, until :meth:`set_keypoints`, while the editor binds it).
    cage_faces : (F, 3) or None.
    settings : kpd.viewer.render.ViewSettings.
    digits : draw the keypoint numbers as camera-facing glyphs (the editor); pictures draw them into the image.
    shaded : ``ShadedMesh(mesh, settings.mesh_color)`` made beforehand (on another thread, while the mesh is bound),
        or None to make it here.
    """

    def __init__(self, view: GLView, mesh: Any, num_keypoints: int = 0, cage_faces: Any = None, *, settings: Any,
                 digits: bool = True, shaded: ShadedMesh | None = None) -> None:
        self.view, self.mesh, self.settings = view, mesh, settings
        lo, hi = box([np.ascontiguousarray(mesh.vertices, dtype=np.float64)])
        self.diagonal = float(np.linalg.norm(hi - lo)) or 1.0
        reach = 0.5 * self.diagonal  # the rest box grown by this on every side: where edits take the mesh
        self._reach_corners = np.array(list(itertools.product(*np.stack([lo - reach, hi + reach]).T)))  # (8, 3)
        self.shaded = shaded if shaded is not None else ShadedMesh(mesh, settings.mesh_color)
        self.stand_in: ShadedMesh | None = None  # drawn during gestures (set_stand_in)
        self.stand_in_rows: np.ndarray | None = None  # (P,) the mesh's vertices the stand-in is made of
        self._with_digits = digits
        self._edges = None
        self.frame: Any = None
        self._camera: Any = None  # the camera the shown mesh was shaded and culled for
        self.stand_in_shown = False
        self._cage: Any = None  # the cage wireframe, its points updated in place
        self.set_keypoints(num_keypoints, cage_faces)

    def set_keypoints(self, num_keypoints: int, cage_faces: Any = None) -> None:
        """Draw ``num_keypoints`` markers (and numbers) and, with ``cage_faces``, the cage (a drawing that started
        with the mesh alone gets them when its rig is bound)."""
        self.num_keypoints = int(num_keypoints)
        self.colors = keypoint_palette(self.num_keypoints)
        self.markers = Markers(self.colors, self.marker_radius) if self.num_keypoints else None
        self.cage_edges = None if cage_faces is None else cage_edges(cage_faces)
        self.digits = Digits(self.colors, 1.5 * self.marker_radius) if self._with_digits and self.num_keypoints \
            else None

    def set_stand_in(self, kept: np.ndarray, faces: np.ndarray) -> None:
        """The stand-in drawn during gestures: ``(kept, faces)`` of :func:`kpd.viewer.standins.stand_in` for this
        mesh (made off the main thread: it takes a second or more for millions of triangles)."""
        from kpd.io import Mesh

        colors = stand_in_colors(self.mesh)
        colors = None if colors is None else colors[kept]
        self.stand_in = ShadedMesh(Mesh(vertices=self.mesh.vertices[kept], triangles=faces, vertex_colors=colors),
                                   self.settings.mesh_color)
        self.stand_in_rows = kept

    @property
    def marker_radius(self) -> float:
        return self.settings.keypoint_size * self.diagonal

    def label_anchors(self, keypoints: np.ndarray, camera: Any, scales: Any = 1.0) -> np.ndarray:
        """(K, 3) lower-left corners of the numbers: up and to the right of each marker (of ``scales`` times the
        marker radius) as the camera sees it."""
        forward = camera.center - camera.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, camera.up)
        right /= max(np.linalg.norm(right), 1e-12)
        up = np.cross(right, forward)
        r = self.marker_radius * np.broadcast_to(np.asarray(scales, dtype=np.float64), (len(keypoints),))[:, None]
        return np.asarray(keypoints) + 1.1 * r * right + 0.9 * r * up

    def labels_in_front(self, anchors: np.ndarray, camera: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(anchors, sizes)``: the labels' anchors (K, 3) moved along their lines of sight to just in front of
        where the mesh can be, and the factor (K,) to draw each one smaller by, so that they look as they would
        where they were and show whatever the mesh hides, as the numbers of ``kpd render`` pictures do (a number
        behind the surface showed as a piece of its white card cut off by the mesh). The mesh is taken to stay
        within its rest box grown by half its diagonal; a camera inside that box gets labels a tenth of the
        diagonal away (in front of the near clipping plane)."""
        anchors = np.asarray(anchors, dtype=np.float64)
        eye = np.asarray(camera.eye, dtype=np.float64)
        forward = np.asarray(camera.center, dtype=np.float64) - eye
        forward = forward / (np.linalg.norm(forward) or 1.0)
        depth = (anchors - eye) @ forward  # (K,)
        front = max(0.98 * float(((self._reach_corners - eye) @ forward).min()), 0.1 * self.diagonal)
        sizes = np.where(depth > front, front / np.maximum(depth, 1e-300), 1.0)
        return eye + (anchors - eye) * sizes[:, None], sizes

    def _wire(self) -> np.ndarray:
        if self._edges is None:
            self._edges = mesh_edges(self.mesh.triangles)
        return self._edges

    def show(self, frame: Any, camera: Any, *, mesh: bool = True, fast: bool = False, prepared: list | None = None,
             capture: bool = False) -> None:
        """Put ``frame`` (a :class:`kpd.viewer.settings.Frame`) in the view as ``camera`` sees it.

        ``fast``: a frame during a gesture; a mesh with a stand-in (:meth:`set_stand_in`) is then drawn by it, and in
        full again by the next frame that is not fast. ``prepared``: the whole mesh's
        :meth:`ShadedMesh.prepare` of ``frame.vertices`` for ``camera`` (made on another thread), uploaded as it is.
        ``capture``: the frame is to be read back (:meth:`GLView.capture`), not shown on the screen (the two sample
        pixels differently: the next frame on the screen must be drawn anew).
        """
        import open3d as o3d

        s, view = self.settings, self.view
        view.camera = camera
        moved = self._camera is None or not _same_camera(camera, self._camera)
        use_stand_in = fast and self.stand_in is not None
        if mesh or moved or self.frame is None or use_stand_in != self.stand_in_shown or capture:
            shown, hidden = (self.stand_in, self.shaded) if use_stand_in else (self.shaded, self.stand_in)
            if prepared is not None and not use_stand_in:
                shown.upload(prepared)
            else:
                shown.set_vertices(frame.vertices[self.stand_in_rows] if use_stand_in else frame.vertices, camera,
                                   view.viewport(camera, capture=capture))
            self._camera = None if capture else camera
            prefix, other = ("stand-in", "mesh") if use_stand_in else ("mesh", "stand-in")
            for i, part in enumerate(shown.geometries):
                view.put(f"{prefix}:{i}", part, show=not s.xray)
            if hidden is not None:
                for i in range(len(hidden.geometries)):
                    view.show(f"{other}:{i}", False)
            self.stand_in_shown = use_stand_in
            if s.xray:
                view.put("xray", line_set(frame.vertices, self._wire(), (0.45, 0.45, 0.5)))
            else:
                view.remove("xray")
        keypoints = np.asarray(frame.keypoints, dtype=np.float64).reshape(-1, 3)
        if self.markers is not None and len(keypoints) == self.num_keypoints:
            selected = np.zeros(self.num_keypoints, bool)
            selected[[i for i in frame.selection if 0 <= i < self.num_keypoints]] = True
            scales = np.where(selected, 1.6, 1.0)
            self.markers.set(keypoints, scales, camera)
            view.put("keypoints", self.markers.geometry, show=s.show_keypoints)
            if self.digits is not None:
                anchors, sizes = self.labels_in_front(self.label_anchors(keypoints, camera, scales), camera)
                self.digits.set(anchors, camera, sizes)
                view.put("numbers", self.digits.geometry, show=s.show_keypoints and s.show_labels)
        if self.cage_edges is not None and frame.cage is not None and s.show_cage:
            if self._cage is None:
                self._cage = line_set(frame.cage, self.cage_edges, s.cage_color)
            else:
                self._cage.points = o3d.utility.Vector3dVector(np.asarray(frame.cage, dtype=np.float64))
            view.put("cage", self._cage)
        else:
            view.show("cage", False)
        if s.show_ghost:
            if "ghost" not in view._geometries:
                view.put("ghost", line_set(self.mesh.vertices, self._wire(), s.ghost_color[:3]))
            view.show("ghost", True)
        else:
            view.show("ghost", False)
        self.frame = frame
        view.set_camera(camera)


def _same_camera(a: Any, b: Any) -> bool:
    """Whether two cameras see exactly alike (a frame culled for one is right for the other)."""
    return all(np.array_equal(np.asarray(getattr(a, k)), np.asarray(getattr(b, k))) for k in ("eye", "center", "up")) \
        and a.fov == b.fov
