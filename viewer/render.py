"""Draw a rig -- its (deformed) mesh with its own colours or texture, the keypoints as coloured markers with their
numbers, optionally the cage as a wireframe and the rest shape as a ghost -- to an image, and the camera maths, the
settings and the PNG files the editor shares.

:func:`render_rig` and :func:`render_frames` draw without a window of their own, with one of :data:`BACKENDS`:

``backend="egl"`` (what ``"auto"`` means)
    Open3D's legacy OpenGL renderer (:mod:`kpd.viewer.gl`) in a headless EGL context, in this process: no X server,
    first frame about 0.2 s after start and tens of milliseconds a frame with Mesa's software rasteriser.
``backend="xvfb"``
    the same renderer in a hidden window on a private ``Xvfb`` server.
``backend="window"``
    the same on the current ``$DISPLAY``.
``backend="offscreen"``
    Open3D's Filament ``OffscreenRenderer``, in a child process; slow without a GPU (shader compilation takes tens of
    seconds once another process holds a core).

Keypoint numbers are drawn into the image after rendering (a small built-in digit font at the projected keypoint
positions); the editor shows them as camera-facing digits in the 3D view instead. :class:`RigScene` (Filament) is
used by the ``offscreen`` backend only.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from kpd.errors import InputError, KpdError
from kpd.io.images import read_png, write_png

__all__ = [
    "ViewSettings", "RigScene", "Frame", "render_rig", "render_frames", "write_png", "read_png", "keypoint_palette",
    "camera_pose", "project", "pixel_ray", "overlay_labels", "BACKENDS", "private_display", "grab_screen",
]

log = logging.getLogger(__name__)

BACKENDS = ("auto", "egl", "xvfb", "window", "offscreen")

# The first twelve keypoint colours are picked by hand to be saturated and far apart (and far from the grey of an
# uncoloured mesh and from a white or black background); more keypoints get golden-angle hues.
_PALETTE = np.array([
    [0.90, 0.10, 0.10], [0.10, 0.35, 0.95], [0.10, 0.70, 0.20], [1.00, 0.55, 0.00], [0.60, 0.15, 0.85],
    [0.00, 0.75, 0.85], [0.95, 0.20, 0.70], [0.80, 0.75, 0.00], [0.55, 0.30, 0.10], [0.00, 0.50, 0.45],
    [0.35, 0.90, 0.10], [0.15, 0.15, 0.55],
])

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class ViewSettings:
    """How a rig is drawn: the one settings object of the editor and of :func:`render_rig`.

    Sizes are relative to the rest mesh's bounding-box diagonal, so they suit shapes in any units.
    """

    width: int = 960
    height: int = 720
    show_keypoints: bool = True
    show_labels: bool = True
    show_cage: bool = False
    show_ghost: bool = False
    xray: bool = False  # the mesh see-through, so keypoints inside it stay visible
    keypoint_size: float = 0.018  # marker radius / diagonal
    up: str = "+z"  # the shape's up axis: +x, -x, +y, -y, +z or -z
    azimuth: float = 30.0  # degrees around the up axis, from the front view
    elevation: float = 20.0  # degrees above the horizontal
    fov: float = 35.0  # vertical field of view, degrees
    zoom: float = 1.0  # > 1 moves the camera closer
    background: tuple = (1.0, 1.0, 1.0)
    mesh_color: tuple = (0.80, 0.80, 0.82)  # used when the mesh has neither colours nor a texture
    ghost_color: tuple = (0.30, 0.50, 0.95, 0.22)
    cage_color: tuple = (0.95, 0.45, 0.05)
    prior: bool = False  # editor: moving keypoints moves the others as the category prior says
    nudge_step: float = 0.01  # editor: arrow-key step / diagonal

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 16 <= value <= 8192:
                raise InputError(f"{name} must be an integer in [16, 8192]; got {value!r}")
        up_axis(self.up)
        for name in ("keypoint_size", "fov", "zoom", "nudge_step"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number; got {value!r}")
        if not self.fov < 170:
            raise InputError(f"fov must be below 170 degrees; got {self.fov}")

    def replace(self, **changes: Any) -> "ViewSettings":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ViewSettings":
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items() if k in known}
        return cls(**values)


def up_axis(up: str) -> np.ndarray:
    """(3,) unit vector of ``"+z"``, ``"-y"``, ``"x"``..."""
    text = str(up).strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    name = text.lstrip("+-")
    if name not in _AXES:
        raise InputError(f"up must be one of x, y, z with an optional sign (+z, -y...); got {up!r}")
    axis = np.zeros(3)
    axis[_AXES[name]] = sign
    return axis


def keypoint_palette(k: int) -> np.ndarray:
    """(K, 3) float64 in [0, 1]: a distinct colour per keypoint."""
    if k <= len(_PALETTE):
        return _PALETTE[:k].copy()
    extra = []
    for i in range(k - len(_PALETTE)):
        hue = (0.13 + i * 0.618033988749895) % 1.0
        extra.append(_hsv(hue, 0.85, 0.9))
    return np.vstack([_PALETTE, np.array(extra)])


def _hsv(h: float, s: float, v: float) -> list[float]:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


# --- camera ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A look-at camera: ``center`` looked at from ``eye`` with ``up``; vertical ``fov`` in degrees."""

    center: np.ndarray
    eye: np.ndarray
    up: np.ndarray
    fov: float
    near: float
    far: float


def camera_pose(vertices: Any, settings: ViewSettings, *, margin: float = 0.9) -> Camera:
    """The camera of a view: orbiting the bounding-box centre of ``vertices`` (V, 3) at the settings' azimuth and
    elevation around the up axis, as close as lets every vertex into the view with ``margin`` (a fraction of the
    view's half-width and half-height) to spare; ``settings.zoom`` > 1 moves it closer.

    The front view (azimuth 0) looks along the horizontal axis that follows the up axis (x -> y -> z -> x) in the
    positive direction, i.e. from ``-that axis``: for ModelNet (z up, chair backs towards +y) that is the view from
    the front of a chair.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-9)
    up = up_axis(settings.up)
    a = int(np.flatnonzero(up)[0])
    front = np.zeros(3)
    front[(a + 1) % 3] = -1.0  # from the front: the camera sits on the negative side of the next axis
    side = np.cross(up, front)
    az, el = math.radians(settings.azimuth), math.radians(settings.elevation)
    direction = math.cos(el) * (math.cos(az) * front + math.sin(az) * side) + math.sin(el) * up
    # as close as the view lets every vertex in, with ``margin`` of the half-width and half-height to spare
    forward = -direction
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    upward = np.cross(right, forward)
    offsets = vertices - center  # (V, 3)
    x, y, z = np.abs(offsets @ right), np.abs(offsets @ upward), offsets @ direction
    tan_v = math.tan(math.radians(settings.fov) / 2)
    tan_h = tan_v * settings.width / settings.height
    distance = float(np.max(z + np.maximum(x / (margin * tan_h), y / (margin * tan_v)))) if len(z) else 1.0
    distance = max(distance, 1e-3 * radius) / settings.zoom
    eye = center + distance * direction
    return Camera(center=center, eye=eye, up=up, fov=float(settings.fov), near=max(distance - 3 * radius, distance / 100),
                  far=distance + 3 * radius)


def look_at_matrix(camera: Camera) -> np.ndarray:
    """(4, 4) world -> camera (OpenGL: camera looks down -z)."""
    f = camera.center - camera.eye
    f = f / np.linalg.norm(f)
    s = np.cross(f, camera.up)
    if np.linalg.norm(s) < 1e-9:  # looking straight along up
        s = np.cross(f, np.roll(camera.up, 1))
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ camera.eye
    return m


def perspective_matrix(fov: float, aspect: float, near: float, far: float) -> np.ndarray:
    """(4, 4) OpenGL perspective projection, vertical ``fov`` in degrees."""
    t = 1.0 / math.tan(math.radians(fov) / 2)
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = t / aspect, t
    m[2, 2], m[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def project(points: Any, view: Any, projection: Any, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Screen positions of world points.

    Parameters
    ----------
    points : (N, 3) float64, world coordinates.
    view, projection : (4, 4) camera matrices (OpenGL conventions, as Open3D's ``Camera`` returns them).
    width, height : the viewport in pixels.

    Returns
    -------
    pixels : (N, 2) float64, x to the right and y down from the top-left corner of the viewport.
    depth : (N,) float64, distance in front of the camera along its axis (negative behind it).
    """
    points = np.asarray(points, dtype=np.float64)
    homogeneous = np.hstack([points, np.ones((len(points), 1))])  # (N, 4)
    eye = homogeneous @ np.asarray(view, dtype=np.float64).T  # (N, 4)
    clip = eye @ np.asarray(projection, dtype=np.float64).T
    w = np.where(np.abs(clip[:, 3]) < 1e-12, 1e-12, clip[:, 3])
    ndc = clip[:, :2] / w[:, None]
    pixels = np.column_stack([(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height])
    return pixels, -eye[:, 2]


def pixel_ray(x: float, y: float, view: Any, projection: Any, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """The world ray through pixel (x, y) of a perspective camera: origin (3,) at the eye and unit direction (3,).

    Works for any near and far planes, including the infinite far plane of Open3D's window cameras (unprojecting
    the far plane there divides by zero).
    """
    view = np.asarray(view, dtype=np.float64)
    projection = np.asarray(projection, dtype=np.float64)
    ndc_x, ndc_y = 2 * x / width - 1, 1 - 2 * y / height
    # eye space, on the plane z_e = -1: clip = P @ (x_e, y_e, -1, 1) with w = 1
    x_e = (ndc_x + projection[0, 2]) / projection[0, 0]
    y_e = (ndc_y + projection[1, 2]) / projection[1, 1]
    rotation, translation = view[:3, :3], view[:3, 3]
    origin = -rotation.T @ translation
    direction = rotation.T @ np.array([x_e, y_e, -1.0])
    return origin, direction / np.linalg.norm(direction)


def plane_hit(origin: np.ndarray, direction: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """Where a ray meets the plane through ``point`` with ``normal``; None when parallel."""
    denominator = float(direction @ normal)
    if abs(denominator) < 1e-12:
        return None
    t = float((point - origin) @ normal) / denominator
    return origin + t * direction


# --- the scene ---------------------------------------------------------------------------------------------------


@dataclass
class Frame:
    """What changes while editing: the mesh vertices, the keypoints, the cage, the selection (user units)."""

    vertices: np.ndarray  # (V, 3)
    keypoints: np.ndarray  # (K, 3)
    cage: np.ndarray | None = None  # (C, 3)
    selection: tuple = ()


def _sphere_template(resolution: int = 8) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    return np.asarray(sphere.vertices).copy(), np.asarray(sphere.triangles).copy()


def cage_edges(faces: Any) -> np.ndarray:
    """(E, 2) int64 unique undirected edges of triangles (F, 3)."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


class _MeshPart:
    """The triangles of one material (one texture, or the whole mesh) as a legacy Open3D mesh."""

    def __init__(self, name: str, mesh: Any, triangles: np.ndarray, texture: np.ndarray | None) -> None:
        import open3d as o3d

        self.name = name
        used = np.unique(mesh.triangles[triangles])  # (Vp,)
        self.all_vertices = len(used) == len(mesh.vertices)
        self.used = used
        local = np.searchsorted(used, mesh.triangles[triangles])  # (Tp, 3)
        part = o3d.geometry.TriangleMesh()
        part.vertices = o3d.utility.Vector3dVector(mesh.vertices[used])
        part.triangles = o3d.utility.Vector3iVector(local.astype(np.int32))
        if mesh.vertex_colors is not None:
            part.vertex_colors = o3d.utility.Vector3dVector(mesh.vertex_colors[used])
        if texture is not None and mesh.triangle_uvs is not None:
            corners = (3 * triangles[:, None] + np.arange(3)).ravel()  # (3 Tp,)
            part.triangle_uvs = o3d.utility.Vector2dVector(mesh.triangle_uvs[corners])
        self.o3d = part
        self.texture = texture
        self.has_colors = mesh.vertex_colors is not None

    def set_vertices(self, vertices: np.ndarray, normals: np.ndarray | None) -> None:
        import open3d as o3d

        self.o3d.vertices = o3d.utility.Vector3dVector(vertices if self.all_vertices else vertices[self.used])
        if normals is not None:
            self.o3d.vertex_normals = o3d.utility.Vector3dVector(normals if self.all_vertices else normals[self.used])


class RigScene:
    """The Open3D geometries of one shape being edited, and their materials.

    Parameters
    ----------
    mesh : kpd.io.Mesh, the rest mesh in user units (its colours, UVs and textures are shown).
    num_keypoints : K.
    cage_faces : (F, 3) int64 or None: the cage's triangles, drawn as a wireframe.
    settings : ViewSettings.

    Geometry names: ``mesh:<i>`` (one per texture), ``ghost``, ``keypoints``, ``selected``, ``cage``.
    """

    def __init__(self, mesh: Any, num_keypoints: int, cage_faces: Any = None, *,
                 settings: ViewSettings | None = None, eye: Any = None) -> None:
        from kpd.viewer.gl import _Welding

        self.mesh = mesh
        self.eye = None if eye is None else np.asarray(eye, dtype=np.float64)  # normals face this camera position
        self._welding = _Welding(mesh.vertices, np.asarray(mesh.triangles, dtype=np.int64))
        self.settings = settings or ViewSettings()
        self.num_keypoints = int(num_keypoints)
        self.colors = keypoint_palette(self.num_keypoints)
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        self.diagonal = float(np.linalg.norm(hi - lo)) or 1.0
        self.edges = None if cage_faces is None else cage_edges(cage_faces)
        self._sphere_v, self._sphere_t = _sphere_template()
        self.parts = self._split_parts()
        self._scene = None
        self._frame: Frame | None = None

    @property
    def marker_radius(self) -> float:
        return self.settings.keypoint_size * self.diagonal

    def _split_parts(self) -> list[_MeshPart]:
        mesh = self.mesh
        t = len(mesh.triangles)
        if mesh.textures and mesh.triangle_uvs is not None:
            ids = mesh.triangle_material_ids if mesh.triangle_material_ids is not None else np.zeros(t, np.int64)
            parts = []
            for material in np.unique(ids):
                triangles = np.flatnonzero(ids == material)
                texture = mesh.textures[int(material)] if 0 <= material < len(mesh.textures) else None
                parts.append(_MeshPart(f"mesh:{len(parts)}", mesh, triangles, texture))
            return parts
        return [_MeshPart("mesh:0", mesh, np.arange(t), None)]

    # --- materials ---------------------------------------------------------------------------------------------

    def _mesh_material(self, part: _MeshPart) -> Any:
        import open3d as o3d
        from open3d.visualization import rendering

        material = rendering.MaterialRecord()
        s = self.settings
        plain = part.texture is None and not part.has_colors
        color = list(s.mesh_color) if plain else [1.0, 1.0, 1.0]
        if s.xray:
            material.shader = "defaultLitTransparency"
            material.base_color = color + [0.45]
        else:
            material.shader = "defaultLit"
            material.base_color = color + [1.0]
        material.base_roughness = 0.7
        material.base_reflectance = 0.3
        if part.texture is not None:
            image = np.ascontiguousarray(part.texture)  # top row first, as the UVs (origin bottom left) expect
            if image.ndim == 3 and image.shape[2] == 1:
                image = np.ascontiguousarray(image[:, :, 0])
            material.albedo_img = o3d.geometry.Image(image)
        return material

    def _marker_material(self) -> Any:
        from open3d.visualization import rendering

        material = rendering.MaterialRecord()
        material.shader = "defaultUnlit"
        material.base_color = [1.0, 1.0, 1.0, 1.0]
        return material

    def _ghost_material(self) -> Any:
        from open3d.visualization import rendering

        material = rendering.MaterialRecord()
        material.shader = "defaultLitTransparency"
        material.base_color = list(self.settings.ghost_color)
        return material

    def _cage_material(self) -> Any:
        from open3d.visualization import rendering

        material = rendering.MaterialRecord()
        material.shader = "unlitLine"
        material.line_width = 1.5
        material.base_color = list(self.settings.cage_color) + [1.0]
        return material

    # --- geometry ------------------------------------------------------------------------------------------------

    def _markers(self, keypoints: np.ndarray, indices: Sequence[int], scale: float) -> Any:
        import open3d as o3d

        indices = np.asarray(list(indices), dtype=np.int64)
        n = len(self._sphere_v)
        radius = self.marker_radius * scale
        vertices = (keypoints[indices][:, None, :] + radius * self._sphere_v[None]).reshape(-1, 3)  # (k n, 3)
        triangles = (self._sphere_t[None] + n * np.arange(len(indices))[:, None, None]).reshape(-1, 3)
        colors = np.repeat(self.colors[indices], n, axis=0)
        markers = o3d.geometry.TriangleMesh()
        markers.vertices = o3d.utility.Vector3dVector(vertices)
        markers.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
        markers.vertex_colors = o3d.utility.Vector3dVector(colors)
        return markers

    def _halo(self, keypoints: np.ndarray, indices: Sequence[int]) -> Any:
        """Dark shells around the selected markers (a wireframe ring would need thick lines Open3D lacks)."""
        import open3d as o3d

        indices = list(indices)
        n = len(self._sphere_v)
        radius = self.marker_radius * 1.9
        vertices = (keypoints[indices][:, None, :] + radius * self._sphere_v[None]).reshape(-1, 3)
        triangles = (self._sphere_t[None] + n * np.arange(len(indices))[:, None, None]).reshape(-1, 3)
        halo = o3d.geometry.TriangleMesh()
        halo.vertices = o3d.utility.Vector3dVector(vertices)
        halo.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
        halo.vertex_colors = o3d.utility.Vector3dVector(np.tile([0.05, 0.05, 0.05], (len(vertices), 1)))
        halo.compute_vertex_normals()
        return halo

    def _plain_mesh(self, vertices: np.ndarray) -> Any:
        import open3d as o3d

        plain = o3d.geometry.TriangleMesh()
        plain.vertices = o3d.utility.Vector3dVector(vertices)
        plain.triangles = o3d.utility.Vector3iVector(self.mesh.triangles.astype(np.int32))
        plain.compute_vertex_normals()
        return plain

    def _cage_lines(self, cage: np.ndarray) -> Any:
        import open3d as o3d

        lines = o3d.geometry.LineSet()
        lines.points = o3d.utility.Vector3dVector(cage)
        lines.lines = o3d.utility.Vector2iVector(self.edges.astype(np.int32))
        lines.colors = o3d.utility.Vector3dVector(np.tile(self.settings.cage_color, (len(self.edges), 1)))
        return lines

    @staticmethod
    def _replace(scene: Any, name: str, geometry: Any, material: Any) -> None:
        if scene.has_geometry(name):
            scene.remove_geometry(name)
        scene.add_geometry(name, geometry, material, False)

    def attach(self, scene: Any, frame: Frame) -> None:
        """Add every geometry of ``frame`` to an ``open3d.visualization.rendering.Open3DScene``."""
        self._scene = scene
        scene.set_background(list(self.settings.background) + [1.0])
        self._ghost = self._plain_mesh(self.mesh.vertices)
        self._frame = None
        self.update(frame, normals=True)
        self.apply_settings(self.settings)

    def update(self, frame: Frame, *, normals: bool = True, mesh: bool = True) -> None:
        """Show ``frame``: new mesh vertices (``normals`` recomputed or kept from the last update), keypoint markers,
        selection halos and cage."""
        scene = self._scene
        if scene is None:
            raise KpdError("RigScene.update before attach")
        s = self.settings
        keypoints = np.asarray(frame.keypoints, dtype=np.float64)
        if mesh:
            from kpd.viewer.gl import shading_normals

            vertices = np.asarray(frame.vertices, dtype=np.float64)
            shade = shading_normals(vertices, self.mesh.triangles, self.eye, welding=self._welding) if normals else None
            for part in self.parts:
                part.set_vertices(vertices, shade)
                self._replace(scene, part.name, part.o3d, self._mesh_material(part))
        selection = [i for i in frame.selection if 0 <= i < self.num_keypoints]
        self._replace(scene, "keypoints", self._markers(keypoints, range(self.num_keypoints), 1.0),
                      self._marker_material())
        if scene.has_geometry("selected"):
            scene.remove_geometry("selected")
        if selection and s.show_keypoints:
            # the selected markers drawn larger, with the markers' own (unlit) material: a new material kind would
            # cost a shader compile, which software renderers make slow
            self._replace(scene, "selected", self._markers(keypoints, selection, 1.6), self._marker_material())
        if self.edges is not None and frame.cage is not None:
            self._replace(scene, "cage", self._cage_lines(np.asarray(frame.cage, dtype=np.float64)),
                          self._cage_material())
        self._frame = Frame(np.asarray(frame.vertices), keypoints, frame.cage, tuple(selection))
        self._show()

    def _ghost_material_dark(self) -> Any:
        from open3d.visualization import rendering

        material = rendering.MaterialRecord()
        material.shader = "defaultLitTransparency"
        material.base_color = [0.0, 0.0, 0.0, 0.35]
        return material

    def apply_settings(self, settings: ViewSettings) -> None:
        """Apply visibility and material settings (the editor calls this after every settings change)."""
        old = self.settings
        self.settings = settings
        scene = self._scene
        if scene is None:
            return
        scene.set_background(list(settings.background) + [1.0])
        if settings.xray != old.xray or not scene.has_geometry(self.parts[0].name):
            for part in self.parts:
                if scene.has_geometry(part.name):
                    scene.modify_geometry_material(part.name, self._mesh_material(part))
        if settings.keypoint_size != old.keypoint_size and self._frame is not None:
            self.update(self._frame, mesh=False)
        if not scene.has_geometry("ghost"):
            scene.add_geometry("ghost", self._ghost, self._ghost_material(), False)
        self._show()

    def _show(self) -> None:
        scene, s = self._scene, self.settings
        scene.show_geometry("ghost", s.show_ghost)
        scene.show_geometry("keypoints", s.show_keypoints)
        if scene.has_geometry("selected"):
            scene.show_geometry("selected", s.show_keypoints)
        if scene.has_geometry("cage"):
            scene.show_geometry("cage", s.show_cage)

    def label_positions(self, keypoints: Any) -> np.ndarray:
        """(K, 3) where the numbers go: beside each marker, along the camera-independent up axis."""
        return np.asarray(keypoints, dtype=np.float64) + 1.6 * self.marker_radius * up_axis(self.settings.up)


# --- keypoint numbers in images ----------------------------------------------------------------------------------

_DIGITS = {
    "0": ["01110", "10001", "10011", "10101", "11001", "10001", "01110"],
    "1": ["00100", "01100", "00100", "00100", "00100", "00100", "01110"],
    "2": ["01110", "10001", "00001", "00010", "00100", "01000", "11111"],
    "3": ["11110", "00001", "00001", "01110", "00001", "00001", "11110"],
    "4": ["00010", "00110", "01010", "10010", "11111", "00010", "00010"],
    "5": ["11111", "10000", "11110", "00001", "00001", "10001", "01110"],
    "6": ["00110", "01000", "10000", "11110", "10001", "10001", "01110"],
    "7": ["11111", "00001", "00010", "00100", "01000", "01000", "01000"],
    "8": ["01110", "10001", "10001", "01110", "10001", "10001", "01110"],
    "9": ["01110", "10001", "10001", "01111", "00001", "00010", "01100"],
}
_GLYPHS = {c: np.array([[ch == "1" for ch in row] for row in rows]) for c, rows in _DIGITS.items()}


def _text_mask(text: str, scale: int) -> np.ndarray:
    glyphs = [_GLYPHS[c] for c in text if c in _GLYPHS]
    if not glyphs:
        return np.zeros((7 * scale, 1), dtype=bool)
    spaced = []
    for g in glyphs:
        spaced += [g, np.zeros((7, 1), dtype=bool)]
    mask = np.hstack(spaced[:-1])
    return np.kron(mask, np.ones((scale, scale), dtype=bool))


def overlay_labels(image: np.ndarray, pixels: Any, labels: Sequence[str], colors: Any, *,
                   scale: int | None = None, visible: Any = None) -> np.ndarray:
    """Draw ``labels`` (digits) at ``pixels`` (N, 2) in ``colors`` (N, 3 in [0, 1]) with a white halo.

    Parameters
    ----------
    image : (H, W, 3) uint8 (modified copy returned).
    pixels : (N, 2) float, the label's lower-left corner (x right, y down).
    visible : (N,) bool, labels to draw (default all).
    """
    out = np.array(image, dtype=np.uint8, copy=True)
    h, w = out.shape[:2]
    scale = scale or max(2, int(round(h / 300)))
    pixels = np.asarray(pixels, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.float64)
    visible = np.ones(len(labels), dtype=bool) if visible is None else np.asarray(visible, dtype=bool)
    for text, (x, y), color, show in zip(labels, pixels, colors, visible):
        if not show or not np.isfinite([x, y]).all():
            continue
        mask = _text_mask(str(text), scale)
        mh, mw = mask.shape
        halo = np.zeros((mh + 2 * scale, mw + 2 * scale), dtype=bool)
        for dy in range(2 * scale + 1):
            for dx in range(2 * scale + 1):
                halo[dy:dy + mh, dx:dx + mw] |= mask
        x0, y0 = int(round(x)) - scale, int(round(y)) - mh - scale
        ink = np.clip(np.asarray(color) * 0.75 * 255, 0, 255).astype(np.uint8)
        for layer, value in ((halo, np.array([255, 255, 255], np.uint8)), (None, ink)):
            m = layer if layer is not None else np.pad(mask, scale)
            ys, xs = np.nonzero(m)
            ys, xs = ys + y0, xs + x0
            keep = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
            out[ys[keep], xs[keep]] = value
    return out


def label_image(image: np.ndarray, scene: RigScene, frame: Frame, camera: Camera) -> np.ndarray:
    """Keypoint numbers drawn onto a rendered image of ``frame`` seen by ``camera``."""
    s = scene.settings
    if not (s.show_labels and s.show_keypoints):
        return image
    return label_image_at(image, frame.keypoints, scene.marker_radius, camera)


def label_image_at(image: np.ndarray, keypoints: Any, radius: float, camera: Camera) -> np.ndarray:
    """Keypoint numbers (in the keypoint palette) drawn beside markers of ``radius`` at ``keypoints`` (K, 3), as
    ``camera`` sees them: up and to the right of each marker on screen."""
    h, w = image.shape[:2]
    keypoints = np.asarray(keypoints, dtype=np.float64)
    view = look_at_matrix(camera)
    projection = perspective_matrix(camera.fov, w / h, camera.near, camera.far)
    pixels, depth = project(keypoints, view, projection, w, h)
    distance = np.linalg.norm(keypoints - camera.eye, axis=1)
    focal = h / 2 / math.tan(math.radians(camera.fov) / 2)
    r = focal * radius / np.maximum(distance, 1e-12)  # (K,) marker radius in pixels
    pixels = pixels + np.stack([1.1 * r, -0.9 * r], axis=1)
    labels = [str(i) for i in range(len(keypoints))]
    return overlay_labels(image, pixels, labels, keypoint_palette(len(keypoints)), visible=depth > 0)


# --- rendering -----------------------------------------------------------------------------------------------------


def _rig_frames(rig: Any, keypoint_sets: Sequence[Any], selections: Sequence[Sequence[int]] | None) -> list[Frame]:
    frames = []
    for i, keypoints in enumerate(keypoint_sets):
        keypoints = np.asarray(keypoints, dtype=np.float64)
        selection = tuple(selections[i]) if selections is not None else ()
        frames.append(Frame(rig.deform(keypoints), keypoints, rig.deform_cage(keypoints), selection))
    return frames


def render_rig(rig: Any, keypoints: Any = None, *, settings: ViewSettings | None = None, selection: Sequence[int] = (),
               backend: str = "auto", timeout: float = 300.0) -> np.ndarray:
    """Draw a rig with its keypoints at ``keypoints`` (default: rest) without opening a window.

    Parameters
    ----------
    rig : kpd.rig.Rig.
    keypoints : (K, 3) float64 in the rig's units, or None for the rest keypoints.
    settings : ViewSettings (size, camera, what to show).
    selection : keypoint indices drawn as selected.
    backend : one of :data:`BACKENDS` (see the module notes).
    timeout : seconds to wait for a window backend's child process.

    Returns
    -------
    image : (H, W, 3) uint8.
    """
    keypoints = rig.keypoints if keypoints is None else keypoints
    return render_frames(rig, [keypoints], settings=settings, selections=[selection], backend=backend,
                         timeout=timeout)[0]


def render_frames(rig: Any, keypoint_sets: Sequence[Any], *, settings: ViewSettings | None = None,
                  selections: Sequence[Sequence[int]] | None = None, backend: str = "auto",
                  timeout: float = 300.0) -> list[np.ndarray]:
    """:func:`render_rig` of several keypoint sets with one renderer (a gallery of edits): a list of (H, W, 3).

    One camera frames every frame's deformed shape (and its keypoints), so edits that grow the shape stay in view and
    the frames compare on one scale.
    """
    settings = settings or ViewSettings()
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    k = rig.num_keypoints
    for keypoints in keypoint_sets:
        shape = np.shape(keypoints)
        if shape != (k, 3):
            raise InputError(f"keypoints must have shape ({k}, 3) for this rig; got {shape}")
    frames = _rig_frames(rig, keypoint_sets, selections)
    backend = resolve_backend(backend)
    camera = camera_pose(np.vstack([np.vstack([f.vertices, f.keypoints]) for f in frames]), settings)
    log.info("rendering %d frame(s) of %dx%d with the %s backend", len(frames), settings.width, settings.height, backend)
    if backend == "offscreen":
        return _render_offscreen_in_child(rig.mesh, k, rig.cage.faces, frames, settings, camera, timeout)
    with gl_display(backend, settings.width, settings.height):
        return _render_gl(rig, frames, settings, camera, on_display=backend != "egl")


@contextlib.contextmanager
def gl_display(backend: str, width: int, height: int) -> Iterator[None]:
    """Make ``$DISPLAY`` point at an X server for the OpenGL path for the duration of the block: a private Xvfb
    (``backend="xvfb"``) or the current display (``"window"``)."""
    backend = resolve_backend(backend)
    if backend == "window":
        yield
        return
    if backend == "egl":  # no X server: Open3D's legacy renderer then draws into a headless EGL context
        hidden = {name: os.environ.pop(name) for name in ("DISPLAY", "WAYLAND_DISPLAY") if name in os.environ}
        try:
            yield
        finally:
            os.environ.update(hidden)
        return
    if backend != "xvfb":
        raise InputError(f"the OpenGL path needs the egl, xvfb or window backend; got {backend!r}")
    saved = os.environ.get("DISPLAY")
    with private_display(width + 64, height + 64) as display:
        os.environ["DISPLAY"] = display
        try:
            yield
        finally:
            if saved is None:
                os.environ.pop("DISPLAY", None)
            else:
                os.environ["DISPLAY"] = saved


def _render_gl(rig: Any, frames: list[Frame], settings: ViewSettings, camera: Camera, *,
               on_display: bool = False) -> list[np.ndarray]:
    from kpd.viewer.gl import GLView, RigDrawing

    view = GLView(settings.width, settings.height, background=settings.background, on_display=on_display)
    try:
        drawing = RigDrawing(view, rig.mesh, rig.num_keypoints, rig.cage.faces, settings=settings, digits=False)
        view.set_box(np.vstack([np.vstack([f.vertices, f.keypoints]) for f in frames]))
        images = []
        for frame in frames:
            drawing.show(frame, camera)
            image = view.capture()
            if settings.show_labels and settings.show_keypoints:
                image = label_image_at(image, frame.keypoints, drawing.marker_radius, camera)
            images.append(image)
        return images
    finally:
        view.close()


def resolve_backend(backend: str) -> str:
    """The backend ``auto`` stands for (``egl``), after checking that the one asked for can run here."""
    if backend == "auto":
        return "egl"
    if backend == "xvfb" and not shutil.which("Xvfb"):
        raise KpdError("the xvfb backend needs the Xvfb program (Debian/Ubuntu: apt-get install xvfb); or use "
                       "--backend egl")
    if backend == "window" and not os.environ.get("DISPLAY"):
        raise KpdError("the window backend needs a display ($DISPLAY is not set); use --backend egl or xvfb")
    return backend


def _configure_view(scene: Any, settings: ViewSettings) -> None:
    from open3d.visualization import rendering

    # Post-processing (tone mapping, bloom, ambient occlusion) would tint the background and the unlit keypoint
    # colours; without it they come out exactly as given, and software rendering is faster.
    scene.view.set_post_processing(False)
    sun = _sun_direction(settings)
    scene.set_lighting(rendering.Open3DScene.LightingProfile.NO_SHADOWS, sun)
    add_fill_light(scene, sun)


def add_fill_light(scene: Any, sun: np.ndarray) -> None:
    """A weaker light from the opposite side, so faces turned away from the sun keep their colour (software
    renderers may have no image-based ambient light, which leaves those faces black)."""
    scene.scene.set_sun_light(sun.astype(np.float32), np.array([1.0, 1.0, 1.0], np.float32), 100000.0)
    scene.scene.enable_indirect_light(True)
    scene.scene.set_indirect_light_intensity(60000.0)
    scene.scene.add_directional_light("fill", np.array([1.0, 1.0, 1.0], np.float32), (-sun).astype(np.float32),
                                      60000.0, False)


def _sun_direction(settings: ViewSettings) -> np.ndarray:
    up = up_axis(settings.up)
    a = int(np.flatnonzero(up)[0])
    front = np.zeros(3)
    front[(a + 1) % 3] = 1.0
    side = np.cross(up, front)
    d = -0.8 * up + 0.45 * front + 0.4 * side
    return (d / np.linalg.norm(d)).astype(np.float32)


def _render_offscreen(mesh: Any, k: int, cage_faces: Any, frames: list[Frame], settings: ViewSettings,
                      camera: Camera) -> list[np.ndarray]:
    with _quiet_native_output():
        from open3d.visualization import rendering

        renderer = rendering.OffscreenRenderer(settings.width, settings.height)
        try:
            scene = RigScene(mesh, k, cage_faces, settings=settings, eye=camera.eye)
            scene.attach(renderer.scene, frames[0])
            _configure_view(renderer.scene, settings)
            renderer.setup_camera(camera.fov, camera.center.astype(np.float32), camera.eye.astype(np.float32),
                                  camera.up.astype(np.float32), camera.near, camera.far)
            images = []
            for i, frame in enumerate(frames):
                if i:
                    scene.update(frame)
                image = np.asarray(renderer.render_to_image())[:, :, :3].copy()
                images.append(label_image(image, scene, frame, camera))
        finally:
            del renderer
    return images


class _Said:
    """What native code printed inside :func:`_quiet_native_output` (filled in when the block ends)."""

    text = ""


@contextlib.contextmanager
def _quiet_native_output() -> Iterator[_Said]:
    """Send what Open3D's native code prints (Filament/Vulkan/GLFW banners) to the log instead of the terminal; the
    yielded object's ``text`` holds it after the block."""
    said = _Said()
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            yield said
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            said.text = sink.read().decode("utf-8", "replace").strip()
            if said.text:
                log.debug("Open3D said:\n%s", said.text)


# --- a private X server ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def private_display(width: int = 1280, height: int = 1024, *, timeout: float = 20.0,
                    fbdir: str | os.PathLike | None = None) -> Iterator[str]:
    """Run a private ``Xvfb`` server for the duration of the block; yields its ``DISPLAY`` string (``":N"``).

    The server picks a free display number itself (``-displayfd``) and is stopped (its process only) on exit.
    With ``fbdir`` the server keeps its screen in ``fbdir/Xvfb_screen0`` (XWD format), which :func:`grab_screen`
    reads: a screenshot of every window on it, the editor's panel included.
    """
    program = shutil.which("Xvfb")
    if program is None:
        raise KpdError("Xvfb is not installed (Debian/Ubuntu: apt-get install xvfb)")
    read_fd, write_fd = os.pipe()
    process = subprocess.Popen(
        [program, "-displayfd", str(write_fd), "-screen", "0", f"{int(width)}x{int(height)}x24", "-nolisten", "tcp",
         "-noreset", *(["-fbdir", str(fbdir)] if fbdir is not None else [])],
        pass_fds=(write_fd,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )
    os.close(write_fd)
    try:
        number = b""
        deadline = time.monotonic() + timeout
        while not number.endswith(b"\n"):
            remaining = deadline - time.monotonic()
            if remaining <= 0 or process.poll() is not None:
                raise KpdError("the private Xvfb server did not start")
            ready, _, _ = select.select([read_fd], [], [], remaining)
            if ready:
                chunk = os.read(read_fd, 16)
                if not chunk:
                    raise KpdError("the private Xvfb server did not start")
                number += chunk
        display = ":" + number.decode().strip()
        log.debug("private Xvfb on %s (pid %d)", display, process.pid)
        yield display
    finally:
        os.close(read_fd)
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def grab_screen(fbdir: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8: the screen of an Xvfb server started with ``-fbdir`` (see :func:`private_display`)."""
    path = Path(fbdir) / "Xvfb_screen0"
    data = path.read_bytes()
    header = struct.unpack(">25I", data[:100])
    size, width, height, bits, line, colours = header[0], header[4], header[5], header[11], header[12], header[19]
    if header[1] != 7 or bits != 32:
        raise KpdError(f"{path}: not a 32-bit XWD screen (version {header[1]}, {bits} bits per pixel)")
    pixels = np.frombuffer(data, np.uint8, count=line * height, offset=size + 12 * colours)
    bgrx = pixels.reshape(height, line)[:, :width * 4].reshape(height, width, 4)
    return np.ascontiguousarray(bgrx[:, :, [2, 1, 0]])


# --- the Filament renderer, in a child process ------------------------------------------------------------------


def _save_job(folder: Path, mesh: Any, k: int, cage_faces: Any, frames: list[Frame], settings: ViewSettings,
              camera: Camera) -> Path:
    """Everything a render child needs, as one npz of plain arrays (no pickle) and a JSON string."""
    arrays = {
        "vertices": np.stack([f.vertices for f in frames]),
        "keypoints": np.stack([f.keypoints for f in frames]),
        "triangles": mesh.triangles,
        "rest": mesh.vertices,
    }
    if cage_faces is not None and frames[0].cage is not None:
        arrays["cage"] = np.stack([f.cage for f in frames])
        arrays["cage_faces"] = np.asarray(cage_faces)
    for name in ("vertex_colors", "triangle_uvs", "triangle_material_ids"):
        value = getattr(mesh, name)
        if value is not None:
            arrays[name] = value
    for i, texture in enumerate(mesh.textures):
        arrays[f"texture_{i}"] = texture
    meta = {"settings": settings.to_dict(), "num_keypoints": k, "selections": [list(f.selection) for f in frames],
            "camera": {name: np.asarray(getattr(camera, name)).tolist() for name in ("center", "eye", "up")} |
            {"fov": camera.fov, "near": camera.near, "far": camera.far}}
    arrays["meta"] = np.array(json.dumps(meta))
    path = folder / "job.npz"
    np.savez(path, **arrays)
    return path


def _load_job(path: Path) -> tuple[Any, int, Any, list[Frame], ViewSettings, Camera]:
    from kpd.io import Mesh

    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    meta = json.loads(str(arrays["meta"]))
    textures = [arrays[n] for n in sorted((n for n in arrays if n.startswith("texture_")), key=lambda s: int(s[8:]))]
    mesh = Mesh(vertices=arrays["rest"], triangles=arrays["triangles"], vertex_colors=arrays.get("vertex_colors"),
                triangle_uvs=arrays.get("triangle_uvs"), textures=textures,
                triangle_material_ids=arrays.get("triangle_material_ids"))
    frames = []
    for i, selection in enumerate(meta["selections"]):
        cage = arrays["cage"][i] if "cage" in arrays else None
        frames.append(Frame(arrays["vertices"][i], arrays["keypoints"][i], cage, tuple(selection)))
    c = meta["camera"]
    camera = Camera(center=np.array(c["center"]), eye=np.array(c["eye"]), up=np.array(c["up"]), fov=c["fov"],
                    near=c["near"], far=c["far"])
    return (mesh, int(meta["num_keypoints"]), arrays.get("cage_faces"), frames, ViewSettings.from_dict(meta["settings"]),
            camera)


def _render_offscreen_in_child(mesh: Any, k: int, cage_faces: Any, frames: list[Frame], settings: ViewSettings,
                               camera: Camera, timeout: float) -> list[np.ndarray]:
    """Filament's OffscreenRenderer in a child process: it leaves its process's EGL unusable for the OpenGL path, and a
    crash of it (a signal) is reported here in one line instead of taking the caller down."""
    with tempfile.TemporaryDirectory(prefix="kpd-render-") as tmp:
        folder = Path(tmp)
        job = _save_job(folder, mesh, k, cage_faces, frames, settings, camera)
        command = [sys.executable, "-m", "kpd.viewer.render", "--offscreen", str(job)]
        try:
            done = subprocess.run(command, capture_output=True, timeout=timeout)
        except subprocess.TimeoutExpired as exc:
            raise KpdError(f"the offscreen (Filament) renderer took longer than {timeout:g} s and was stopped; "
                           "--backend egl is fast without a GPU") from exc
        images = []
        for i in range(len(frames)):
            out = folder / f"frame_{i}.npy"
            if done.returncode != 0 or not out.is_file():
                how = (f"was killed by signal {-done.returncode}" if done.returncode < 0
                       else f"failed (exit {done.returncode})")
                said = done.stderr.decode("utf-8", "replace").strip().splitlines()
                raise KpdError(f"the offscreen (Filament) renderer {how}" + (f": {said[-1]}" if said else "")
                               + "; try --backend egl")
            images.append(np.load(out, allow_pickle=False))
        return images


def _offscreen_worker(job: Path) -> int:
    """Child-process entry of :func:`_render_offscreen_in_child`: draw the job's frames, save them beside it."""
    mesh, k, cage_faces, frames, settings, camera = _load_job(job)
    for i, image in enumerate(_render_offscreen(mesh, k, cage_faces, frames, settings, camera)):
        np.save(job.parent / f"frame_{i}.npy", image)
    return 0


def _main(argv: Sequence[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="kpd.viewer.render child process (internal)")
    parser.add_argument("--offscreen", required=True, type=Path)
    args = parser.parse_args(argv)
    status = _offscreen_worker(args.offscreen)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)  # skip Filament's teardown, which may crash after the work is saved


if __name__ == "__main__":
    _main()
