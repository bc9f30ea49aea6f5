"""Pictures of several shots with one hidden window (:func:`render_shots`): each :class:`Shot` shows meshes
(:class:`Layer`: shaded, wireframe or points), numbered keypoints and lines, framed by its own camera. The contact
sheets, galleries and figures of :mod:`kpd.viewer.pictures` are made of them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from kpd.grouping import first_occurrence_groups
from kpd.viewer.camera import box, camera_pose
from kpd.viewer.glview import GLView
from kpd.viewer.labels import label_image_at
from kpd.viewer.markers import Markers, line_set, mesh_edges
from kpd.viewer.normals import shade
from kpd.viewer.settings import keypoint_palette
from kpd.viewer.shaded import ShadedMesh

__all__ = ["Layer", "Shot", "frame_points", "render_shots"]


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
    triangles (distinct triangles, welding, normals' layout) is done once a sheet. The same picture as a new one
    (what it keeps depends on those alone).

    A mesh drawn in several parts (one per texture) gets a new one each shot: the legacy renderer draws its
    geometries in an order that follows their addresses, which decides a sample where two parts meet at one
    depth."""
    previous = shaded.get(slot)
    if previous is not None and len(previous.parts) == 1 and previous.override == override and \
            previous.color == tuple(map(float, color)):
        old = previous.mesh
        same = len(old.vertices) == len(mesh.vertices) and all(
            getattr(old, name) is getattr(mesh, name)
            for name in ("triangles", "triangle_uvs", "triangle_material_ids", "textures", "vertex_colors"))
        # grouped here, not kept on the mesh (a variant's groups would live as long as the caller holds it)
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
