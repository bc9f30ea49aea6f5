"""The OpenGL drawing path: Open3D's legacy ``Visualizer`` (GLFW + OpenGL 3.3), used by the editor's 3D view and by
every picture kpd draws.

Why this path and not Open3D's Filament GUI: without a GPU both draw with Mesa's software rasteriser (llvmpipe), and
measured on a 2-core machine under Xvfb the legacy renderer draws a 10k-vertex mesh with its keypoints in about 30 ms
a frame and its first frame about 0.4 s after start, where a Filament frame takes 120-210 ms and its first frame
24-38 s (shader compilation) when another process holds a core (``benchmarks/bench_viewer.py``).

* :class:`ShadedMesh` -- a mesh ready to draw (one legacy ``TriangleMesh`` per texture). Its normals are recomputed
  after every edit (:func:`shading_normals`, :class:`_Normals`): from welded positions (unwelded copies of a vertex
  shade alike) and with each triangle turned towards the camera before averaging, i.e. two-sided lighting, so
  double-sided and flipped triangles of CAD meshes come out cleanly shaded instead of in black and white blotches.
  A frame of a large mesh uploads only the triangles that show in a pixel (:func:`visible_triangles`: the same
  picture; a scan-sized mesh has several triangles a pixel), and can be prepared on another thread
  (:meth:`ShadedMesh.prepare`) while the main thread takes input.
* :class:`GLView` -- one window (visible for the editor, hidden for pictures) with named geometries that are updated
  in place, a look-at camera (:class:`kpd.viewer.render.Camera`) and ``capture`` to an (H, W, 3) uint8 image.
* :class:`RigDrawing` -- the geometries of one rig in a view: mesh, keypoint markers (selected ones larger), cage
  wireframe, the rest shape as a ghost wireframe, keypoint numbers as camera-facing digits.
* :func:`render_shots` -- pictures of several :class:`Shot` (meshes, keypoints, lines) with one hidden window.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import logging
import math
import os
import shutil
import tempfile
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, NamedTuple, Sequence

import numpy as np

from kpd._compiled import njit
from kpd.errors import KpdError
from kpd.grouping import first_occurrence_groups, same_corners
from kpd.viewer.camera import box
from kpd.viewer.threads import draw_pool as _pool, in_halves as _halves  # noqa: F401
from kpd.viewer.normals import ShadingNormals as _Normals, Welding as _Welding, camera_lights, shade, shading_normals  # noqa: F401
from kpd.viewer.culling import (_BLOCK, DEPTH_SLACK, PIXEL_CENTRE, CullingLayout, Viewport, _block_hidden, _margin,  # noqa: F401
                                _project, _showing, edge_neighbours, visible_triangles)
from kpd.viewer.shaded import (CULL_TRIANGLES, ShadedMesh, _distinct_triangles_reference, _texture_coordinates,  # noqa: F401
                               distinct_triangles, material_sides, mean_rgb as _mean_rgb, textured as _textured)
from kpd.viewer.standins import (COARSE_STAND_IN_TRIANGLES, FINE_STAND_IN_CELLS, STAND_IN_TRIANGLES,  # noqa: F401
                                 coarse_stand_in, fine_stand_in, image_maps, stand_in, stand_in_colors)
PROXY_TRIANGLES, proxy_triangles = COARSE_STAND_IN_TRIANGLES, coarse_stand_in
from kpd.viewer.glview import GLView, NoWindowError, _raster_threads, _runtime_dir, _sample_points  # noqa: F401
from kpd.viewer.markers import Digits, Markers, line_set, mesh_edges  # noqa: F401

__all__ = ["GLView", "ShadedMesh", "RigDrawing", "Shot", "Layer", "render_shots", "shading_normals", "NoWindowError",
           "stand_in"]

log = logging.getLogger(__name__)


# --- a rig in a view -------------------------------------------------------------------------------------------------


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
        self.proxy: ShadedMesh | None = None  # the coarse stand-in of a large mesh (set_stand_in)
        self._kept: np.ndarray | None = None  # (P,) the mesh's vertices the stand-in is made of
        self._with_digits = digits
        self._edges = None
        self.frame: Any = None
        self._camera: Any = None  # the camera the shown mesh was shaded and culled for
        self._proxy_shown = False
        self._cage: Any = None  # the cage wireframe, its points updated in place
        self.set_keypoints(num_keypoints, cage_faces)

    def set_keypoints(self, num_keypoints: int, cage_faces: Any = None) -> None:
        """Draw ``num_keypoints`` markers (and numbers) and, with ``cage_faces``, the cage (a drawing that started
        with the mesh alone gets them when its rig is bound)."""
        from kpd.viewer.render import cage_edges, keypoint_palette

        self.num_keypoints = int(num_keypoints)
        self.colors = keypoint_palette(self.num_keypoints)
        self.markers = Markers(self.colors, self.marker_radius) if self.num_keypoints else None
        self.cage_edges = None if cage_faces is None else cage_edges(cage_faces)
        self.digits = Digits(self.colors, 1.5 * self.marker_radius) if self._with_digits and self.num_keypoints \
            else None

    def set_stand_in(self, kept: np.ndarray, faces: np.ndarray) -> None:
        """The coarse stand-in drawn during gestures: ``(kept, faces)`` of :func:`proxy_triangles` for this mesh
        (made off the main thread: it takes a second or more for millions of triangles)."""
        from kpd.io import Mesh

        colors = stand_in_colors(self.mesh)
        colors = None if colors is None else colors[kept]
        self.proxy = ShadedMesh(Mesh(vertices=self.mesh.vertices[kept], triangles=faces, vertex_colors=colors),
                                self.settings.mesh_color)
        self._kept = kept

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
        """Put ``frame`` (a kpd.viewer.render.Frame) in the view as ``camera`` sees it.

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
        use_proxy = fast and self.proxy is not None
        if mesh or moved or self.frame is None or use_proxy != self._proxy_shown or capture:
            shown, hidden = (self.proxy, self.shaded) if use_proxy else (self.shaded, self.proxy)
            if prepared is not None and not use_proxy:
                shown.upload(prepared)
            else:
                shown.set_vertices(frame.vertices[self._kept] if use_proxy else frame.vertices, camera,
                                   view.viewport(camera, capture=capture))
            self._camera = None if capture else camera
            prefix, other = ("proxy", "mesh") if use_proxy else ("mesh", "proxy")
            for i, part in enumerate(shown.geometries):
                view.put(f"{prefix}:{i}", part, show=not s.xray)
            if hidden is not None:
                for i in range(len(hidden.geometries)):
                    view.show(f"{other}:{i}", False)
            self._proxy_shown = use_proxy
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


# --- pictures ------------------------------------------------------------------------------------------------------


@dataclass
class Layer:
    """One mesh of a picture: drawn shaded (``style="solid"``), as a wireframe (``"wire"``) or as points."""

    mesh: Any  # kpd.io.Mesh, or (N, 3) points for style "points"
    color: tuple | None = None  # None: the mesh's own colours or texture, else plain grey
    style: str = "solid"


@dataclass
class Shot:
    """What one picture shows: layers, keypoints (numbered markers), the camera (framing all of it by default)."""

    layers: list = field(default_factory=list)
    keypoints: np.ndarray | None = None  # (K, 3)
    selection: tuple = ()
    lines: list = field(default_factory=list)  # [(points (P, 3), edges (E, 2), color)]
    camera: Any = None


def frame_points(shot: Shot) -> np.ndarray:
    """(N, 3): everything a shot shows, for framing the camera on it."""
    parts = []
    for layer in shot.layers:
        parts.append(np.asarray(layer.mesh.vertices if hasattr(layer.mesh, "vertices") else layer.mesh))
    if shot.keypoints is not None:
        parts.append(np.asarray(shot.keypoints))
    for points, _, _ in shot.lines:
        parts.append(np.asarray(points))
    return np.vstack(parts)


def _shaded_layer(shaded: dict, slot: int, mesh: Any, color: Sequence[float], *, override: bool) -> ShadedMesh:
    """A :class:`ShadedMesh` of ``mesh`` for layer ``slot`` of a shot, kept in ``shaded``: the slot's previous one when
    ``mesh`` differs from its mesh only in where the vertices are, with the same vertices at the same positions as
    each other (a shape and its variants, which a rig deforms alike at coincident vertices), so that the work on the
    triangles (distinct triangles, welding, normals' layout) is done once: 0.6 s a shot for a contact sheet of a
    1.37M-vertex chair's variants. The same picture as a new one (what it keeps depends on those alone).

    A mesh drawn in several parts (one per texture) gets a new one each shot: the legacy renderer draws its
    geometries in an order that follows their addresses, which decides a sample where two parts meet at one depth (a
    pixel of a 3-material ShapeNet bench's variant differed when its parts were kept)."""
    previous = shaded.get(slot)
    if previous is not None and len(previous.parts) == 1 and previous.override == override and \
            previous.color == tuple(map(float, color)):
        old = previous.mesh
        same = len(old.vertices) == len(mesh.vertices) and all(
            getattr(old, name) is getattr(mesh, name)
            for name in ("triangles", "triangle_uvs", "triangle_material_ids", "textures", "vertex_colors"))
        # grouped here, not kept on the mesh (22 MB a variant of 1.37M vertices, held by the caller)
        if same and (old is mesh or np.array_equal(previous.welding.inverse,
                                                   first_occurrence_groups(mesh.vertices)[1])):
            previous.mesh = mesh
            return previous
    shaded[slot] = ShadedMesh(mesh, color, override=override, once=True)
    return shaded[slot]


def render_shots(shots: Iterable[Shot], settings: Any, *, view: GLView | None = None,
                 keypoint_radius: float | None = None) -> list[np.ndarray]:
    """Draw each shot with one hidden window; a list of (H, W, 3) uint8 with the keypoint numbers drawn in. The
    shots are taken once, in order: they may be made as they are asked for.

    The caller provides the display (``private_display`` for no screen); ``view`` reuses an open window.
    """
    import open3d as o3d

    from kpd.viewer.render import camera_pose, keypoint_palette, label_image_at

    own = view is None
    view = view or GLView(settings.width, settings.height, background=settings.background)
    view.vis.get_render_option().point_size = max(2.0, settings.height / 130)
    images = []
    shaded_layers: dict[int, ShadedMesh] = {}  # each layer slot's last mesh, ready to draw (_shaded_layer)
    try:
        for shot in shots:
            view.clear()
            points = frame_points(shot)
            camera = shot.camera or camera_pose(points, settings)
            view.set_box(points)
            view.camera = camera
            lo, hi = box([points])
            diagonal = float(np.linalg.norm(hi - lo)) or 1.0
            for i, layer in enumerate(shot.layers):
                if layer.style in ("points", "splats"):
                    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(layer.mesh, np.float64)))
                    color = np.asarray(layer.color or (0.55, 0.65, 0.85), dtype=np.float64)
                    if layer.style == "splats":  # lit as a surface: normals from the neighbours, towards the camera
                        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
                        cloud.orient_normals_towards_camera_location(np.asarray(camera.eye, dtype=np.float64))
                        colors = shade(np.tile(color, (len(cloud.points), 1)), np.asarray(cloud.normals), camera)
                        cloud.colors = o3d.utility.Vector3dVector(colors.astype(np.float64))
                    else:
                        cloud.paint_uniform_color(color)
                    view.put(f"layer:{i}", cloud)
                elif layer.style == "wire":
                    view.put(f"layer:{i}", line_set(layer.mesh.vertices, mesh_edges(layer.mesh.triangles),
                                                    layer.color or (0.3, 0.3, 0.3)))
                else:
                    shaded = _shaded_layer(shaded_layers, i, layer.mesh, layer.color or settings.mesh_color,
                                           override=layer.color is not None)
                    shaded.set_vertices(layer.mesh.vertices, camera, view.viewport(camera))
                    for j, part in enumerate(shaded.geometries):
                        view.put(f"layer:{i}:{j}", part)
            for i, (points_, edges, color) in enumerate(shot.lines):
                view.put(f"lines:{i}", line_set(points_, edges, color))
            radius = None
            if shot.keypoints is not None and settings.show_keypoints:
                k = len(shot.keypoints)
                radius = keypoint_radius or settings.keypoint_size * diagonal
                markers = Markers(keypoint_palette(k), radius)
                scales = np.ones(k)
                scales[[i for i in shot.selection if 0 <= i < k]] = 1.6
                markers.set(shot.keypoints, scales, camera)
                view.put("keypoints", markers.geometry)
            view.set_camera(camera)
            image = view.capture()
            if radius is not None and settings.show_labels:
                image = label_image_at(image, shot.keypoints, radius, camera)
            images.append(image)
    finally:
        if own:
            view.close()
    return images

