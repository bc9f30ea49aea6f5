"""The OpenGL drawing path: Open3D's legacy ``Visualizer`` (GLFW + OpenGL 3.3), used by the editor's 3D view and by
every picture kpd draws.

Why this path and not Open3D's Filament GUI: without a GPU both draw with Mesa's software rasteriser (llvmpipe), and
measured on a 2-core machine under Xvfb the legacy renderer draws a 10k-vertex mesh with its keypoints in about 30 ms
a frame and its first frame about 0.4 s after start, where a Filament frame takes 120-210 ms and its first frame
24-38 s (shader compilation) when another process holds a core (``benchmarks/bench_viewer.py``).

* :class:`ShadedMesh` -- a mesh ready to draw (one legacy ``TriangleMesh`` per texture). Its normals are recomputed
  after every edit by :func:`shading_normals`: from welded positions (unwelded copies of a vertex shade alike) and with
  each triangle turned towards the camera before averaging, i.e. two-sided lighting, so double-sided and flipped
  triangles of CAD meshes come out cleanly shaded instead of in black and white blotches.
* :class:`GLView` -- one window (visible for the editor, hidden for pictures) with named geometries that are updated
  in place, a look-at camera (:class:`kpd.viewer.render.Camera`) and ``capture`` to an (H, W, 3) uint8 image.
* :class:`RigDrawing` -- the geometries of one rig in a view: mesh, keypoint markers (selected ones larger), cage
  wireframe, the rest shape as a ghost wireframe, keypoint numbers as camera-facing digits.
* :func:`render_shots` -- pictures of several :class:`Shot` (meshes, keypoints, lines) with one hidden window.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
from dataclasses import dataclass, field
from typing import Any, Sequence

import numba
import numpy as np

from kpd.errors import KpdError

__all__ = ["GLView", "ShadedMesh", "RigDrawing", "Shot", "Layer", "render_shots", "shading_normals", "NoWindowError"]

log = logging.getLogger(__name__)

PROXY_TRIANGLES = 50000  # larger meshes are drawn by a coarse stand-in while a gesture is in progress


class NoWindowError(KpdError):
    """No OpenGL window could be opened (no display, no GL driver)."""


# --- normals ---------------------------------------------------------------------------------------------------------


class _Welding:
    """Vertices grouped by position (``inverse`` (V,): the group of each vertex; ``groups``: how many)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        from kpd.grouping import merge_coincident

        self.inverse = merge_coincident(np.asarray(vertices, dtype=np.float64))[1]  # (V,) group of each vertex
        self.groups = int(self.inverse.max()) + 1 if len(vertices) else 0


def shading_normals(vertices: np.ndarray, triangles: np.ndarray, eye: np.ndarray | None = None, *,
                    welding: _Welding | None = None) -> np.ndarray:
    """(V, 3) float32 unit vertex normals for drawing.

    Parameters
    ----------
    vertices : (V, 3) float64.
    triangles : (T, 3) int64.
    eye : (3,) the camera position: each triangle's normal is turned towards it before averaging (two-sided lighting),
        so a surface shades the same whichever way its triangles wind. None keeps the winding.
    welding : the vertex groups of these triangles (computed when not given): vertices at one position share a normal.

    Each vertex's normal is the sum of its position's triangles' ``(b - a) x (c - a)`` (area-weighted), in one
    compiled pass over the triangles (a few tens of milliseconds per million triangles).
    """
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    welding = welding or _Welding(vertices, triangles)
    out = np.empty((len(vertices), 3), dtype=np.float32)
    if not len(vertices):
        return out
    eye_point = np.zeros(3) if eye is None else np.asarray(eye, dtype=np.float64).reshape(3)
    _welded_normals(vertices, triangles, welding.inverse, welding.groups, eye_point, eye is not None, out)
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _welded_normals(vertices, triangles, inverse, groups, eye, towards, out):  # pragma: no cover - compiled
    acc = np.zeros((groups, 3))
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        ux, uy, uz = vertices[b, 0] - ax, vertices[b, 1] - ay, vertices[b, 2] - az
        vx, vy, vz = vertices[c, 0] - ax, vertices[c, 1] - ay, vertices[c, 2] - az
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        if towards and nx * (eye[0] - ax) + ny * (eye[1] - ay) + nz * (eye[2] - az) < 0:
            nx, ny, nz = -nx, -ny, -nz  # the eye is on the other side of the triangle's plane
        for corner in (a, b, c):
            g = inverse[corner]
            acc[g, 0] += nx
            acc[g, 1] += ny
            acc[g, 2] += nz
    for g in range(groups):
        length = np.sqrt(acc[g, 0] ** 2 + acc[g, 1] ** 2 + acc[g, 2] ** 2)
        if length == 0.0:  # a position of degenerate triangles only: no normal
            length = 1.0
        acc[g] /= length
    for v in range(inverse.shape[0]):
        g = inverse[v]
        out[v, 0] = acc[g, 0]
        out[v, 1] = acc[g, 1]
        out[v, 2] = acc[g, 2]


def camera_lights(camera: Any) -> np.ndarray:
    """(2, 3) unit directions towards a key light (above left, in front) and a fill light (right), fixed to the
    camera so that every view of a shape is lit alike."""
    forward = np.asarray(camera.center, dtype=np.float64) - np.asarray(camera.eye, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= max(np.linalg.norm(right), 1e-12)
    up = np.cross(right, forward)
    key = -0.55 * forward + 0.65 * up - 0.5 * right
    fill = -0.6 * forward - 0.2 * up + 0.75 * right
    return np.stack([key / np.linalg.norm(key), fill / np.linalg.norm(fill)])


def shade(albedo: np.ndarray, normals: np.ndarray, camera: Any) -> np.ndarray:
    """(N, 3) colours in [0, 1]: ``albedo`` (N, 3) lit by :func:`camera_lights` (ambient + Lambert) at ``normals``.

    The renderer draws unlit (Open3D's legacy lights saturate on surfaces facing the camera and cannot be set from
    Python), so shading is computed here, the same for every picture and the editor."""
    lights = camera_lights(camera).astype(np.float32)
    lambert = np.einsum("ij,kj->ik", np.asarray(normals, dtype=np.float32), lights)  # (N, 2); no BLAS threads
    np.maximum(lambert, 0.0, out=lambert)
    light = 0.38 + 0.52 * lambert[:, 0] + 0.22 * lambert[:, 1]  # (N,), at most 1.12
    colors = np.asarray(albedo, dtype=np.float32) * light[:, None]
    return np.minimum(colors, 1.0, out=colors)


class ShadedMesh:
    """A mesh as legacy Open3D geometries: one ``TriangleMesh`` per texture (or one for the whole mesh).

    Parameters
    ----------
    mesh : kpd.io.Mesh (its colours, UVs and textures are drawn).
    color : (3,) RGB in [0, 1] for a mesh with neither colours nor a texture (or to override them).
    """

    def __init__(self, mesh: Any, color: Sequence[float] = (0.80, 0.80, 0.82), *, override: bool = False) -> None:
        import open3d as o3d

        self.mesh = mesh
        self.triangles = np.asarray(mesh.triangles, dtype=np.int64)
        self.welding = _Welding(mesh.vertices, self.triangles)
        self.parts: list[tuple[np.ndarray, Any]] = []  # (used vertex indices or None for all, TriangleMesh)
        self._albedo: list[np.ndarray | None] = []  # per part: (Vp, 3) base colours to light, None for a texture
        t = len(self.triangles)
        textured = bool(mesh.textures) and mesh.triangle_uvs is not None and not override
        ids = (mesh.triangle_material_ids if mesh.triangle_material_ids is not None else np.zeros(t, np.int64)) \
            if textured else np.zeros(t, np.int64)
        for material in np.unique(ids) if textured and t else [0]:
            chosen = np.flatnonzero(ids == material) if textured else np.arange(t)
            present = np.zeros(len(mesh.vertices), dtype=bool)
            present[self.triangles[chosen]] = True
            whole = bool(present.all())
            used = np.flatnonzero(present)  # sorted, as the local indices below need
            part = o3d.geometry.TriangleMesh()
            part.vertices = o3d.utility.Vector3dVector(mesh.vertices if whole else mesh.vertices[used])
            local = self.triangles[chosen] if whole else np.searchsorted(used, self.triangles[chosen])
            texture = mesh.textures[int(material)] if textured and 0 <= material < len(mesh.textures) else None
            if texture is None or texture.shape[0] * texture.shape[1] == 1:
                # a triangle over the same corners as an earlier one draws nothing new: two-sided lighting and back
                # faces shown (CAD meshes store many triangles twice, once each way round: half of ShapeNet's)
                local = local[distinct_triangles(local)]
            part.triangles = o3d.utility.Vector3iVector(local.astype(np.int32))
            if texture is not None and texture.shape[0] * texture.shape[1] == 1:
                # a material's plain colour (kpd.io reads an OBJ material without a map as a 1x1 image): shaded
                rgb = texture.reshape(-1)[:3] if texture.shape[-1] >= 3 else np.repeat(texture.reshape(-1)[:1], 3)
                albedo = np.tile(rgb.astype(np.float32) / 255.0, (len(used), 1))
            elif texture is not None:
                corners = (3 * chosen[:, None] + np.arange(3)).ravel()  # (3 Tp,)
                uvs = np.array(mesh.triangle_uvs[corners], dtype=np.float64).reshape(-1, 3, 2)
                # tiled maps (UVs beyond [0, 1], common in CAD models): the legacy renderer does not repeat a
                # texture (black beyond it), so each triangle moves by whole tiles into the first one
                uvs -= np.floor(uvs.min(axis=1, keepdims=True))
                # within the outer texel centres: the renderer's border (black) lies beyond them
                edge = 0.5 / np.array([texture.shape[1], texture.shape[0]], dtype=np.float64)
                uvs = np.clip(uvs, edge, 1.0 - edge).reshape(-1, 2)
                uvs[:, 1] = 1.0 - uvs[:, 1]  # the legacy renderer reads v from the top row down
                part.triangle_uvs = o3d.utility.Vector2dVector(uvs)
                image = np.ascontiguousarray(texture[:, :, :3] if texture.ndim == 3 else
                                             np.repeat(texture[:, :, None], 3, axis=2))
                part.textures = [o3d.geometry.Image(image)]
                part.triangle_material_ids = o3d.utility.IntVector(np.zeros(len(chosen), np.int32))
                albedo = None
            elif mesh.vertex_colors is not None and not override:
                albedo = np.asarray(mesh.vertex_colors if whole else mesh.vertex_colors[used], dtype=np.float32)
            else:
                albedo = np.tile(np.asarray(color, dtype=np.float32)[:3], (len(used), 1))
            self.parts.append((None if whole else used, part))
            self._albedo.append(albedo)

    @property
    def geometries(self) -> list[Any]:
        return [part for _, part in self.parts]

    def set_vertices(self, vertices: np.ndarray, camera: Any) -> None:
        """New vertex positions (V, 3), shaded as ``camera`` sees them (normals turned towards it)."""
        import open3d as o3d

        vertices = np.asarray(vertices, dtype=np.float64)
        normals = shading_normals(vertices, self.triangles, camera.eye, welding=self.welding)
        for (used, part), albedo in zip(self.parts, self._albedo):
            part.vertices = o3d.utility.Vector3dVector(vertices if used is None else vertices[used])
            n = normals if used is None else normals[used]
            # Vector3dVector copies float64 rows at memcpy speed, other dtypes element by element
            part.vertex_normals = o3d.utility.Vector3dVector(n.astype(np.float64))
            if albedo is not None:
                part.vertex_colors = o3d.utility.Vector3dVector(shade(albedo, n, camera).astype(np.float64))


def distinct_triangles(triangles: np.ndarray) -> np.ndarray:
    """(T',) sorted indices of the first triangle over each set of three corners (whatever their order)."""
    triangles = np.asarray(triangles, dtype=np.int64)
    if not len(triangles):
        return np.zeros(0, dtype=np.int64)
    ordered = np.sort(triangles, axis=1)
    top = int(ordered.max()) + 1
    if top < 1 << 21:  # three indices in one int64
        _, first = np.unique((ordered[:, 0] << 42) | (ordered[:, 1] << 21) | ordered[:, 2], return_index=True)
    else:
        order = np.lexsort(ordered.T[::-1])
        new = np.ones(len(order), dtype=bool)
        new[1:] = (ordered[order[1:]] != ordered[order[:-1]]).any(axis=1)
        first = order[new]
    return np.sort(first)


def proxy_triangles(vertices: np.ndarray, triangles: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A coarse stand-in of a large mesh for frames drawn during a gesture: vertices clustered on a grid, one
    original vertex kept per cell, triangles that collapse dropped.

    Returns None when the mesh has at most ``limit`` triangles, else ``(kept, faces)``: (P,) indices of the kept
    original vertices and (Q, 3) triangles into ``kept`` with Q <= ``limit``. Its vertices are original vertices, so
    the stand-in of a deformed mesh is the deformed mesh's rows ``kept``: no deformation of its own.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if len(triangles) <= limit:
        return None
    lo = vertices.min(axis=0)
    extent = float(np.ptp(vertices, axis=0).max()) or 1.0
    size = extent / math.sqrt(limit)  # about sqrt(limit) cells across the largest side
    for _ in range(12):
        cells = np.floor((vertices - lo) / size).astype(np.int64)  # (V, 3)
        span = cells.max(axis=0) + 1
        key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]  # (V,) one number per cell
        _, kept, cluster = np.unique(key, return_index=True, return_inverse=True)
        faces = cluster.reshape(-1)[triangles]  # (T, 3)
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
        n = len(kept)
        ordered = np.sort(faces, axis=1)
        _, unique = np.unique((ordered[:, 0] * n + ordered[:, 1]) * n + ordered[:, 2], return_index=True)
        faces = faces[np.sort(unique)]
        if len(faces) <= limit:
            return kept, faces
        size *= 1.1 * math.sqrt(len(faces) / limit)
    return kept, faces[:limit]


# --- the window ----------------------------------------------------------------------------------------------------


def _runtime_dir() -> None:
    """GLFW and Mesa complain on stderr when $XDG_RUNTIME_DIR is unset; give them a private one."""
    path = os.environ.get("XDG_RUNTIME_DIR")
    if path and os.path.isdir(path):
        return
    os.environ["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="kpd-xdg-")


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

    def set_box(self, vertices: np.ndarray) -> None:
        """Make the view's bounding box (which sets the clipping planes) hold ``vertices`` (N, 3)."""
        import open3d as o3d

        lo, hi = np.min(vertices, axis=0), np.max(vertices, axis=0)
        pad = 1.5 * (hi - lo).max()
        box = o3d.geometry.LineSet()
        box.points = o3d.utility.Vector3dVector(np.array([lo - pad, hi + pad]))
        box.lines = o3d.utility.Vector2iVector(np.zeros((0, 2), np.int32))
        self.vis.add_geometry(box, reset_bounding_box=True)
        self.vis.remove_geometry(box, reset_bounding_box=False)
        self._boxed = True

    # camera

    def set_camera(self, camera: Any) -> None:
        """Look from ``camera.eye`` at ``camera.center`` with ``camera.up`` and vertical ``camera.fov``."""
        import open3d as o3d

        from kpd.viewer.render import look_at_matrix

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


# --- markers, lines, digits ----------------------------------------------------------------------------------------


def _sphere(resolution: int = 10) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    return np.asarray(sphere.vertices).copy(), np.asarray(sphere.triangles).copy()


class Markers:
    """Coloured spheres at points: one legacy TriangleMesh, updated in place."""

    def __init__(self, colors: np.ndarray, radius: float) -> None:
        import open3d as o3d

        self.colors = np.asarray(colors, dtype=np.float64)
        self.radius = float(radius)
        self._v, self._t = _sphere()
        n, k = len(self._v), len(self.colors)
        self.geometry = o3d.geometry.TriangleMesh()
        triangles = (self._t[None] + n * np.arange(k)[:, None, None]).reshape(-1, 3)
        self.geometry.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
        self.geometry.vertex_colors = o3d.utility.Vector3dVector(np.repeat(self.colors, n, axis=0))
        self.geometry.vertex_normals = o3d.utility.Vector3dVector(np.tile(self._v, (k, 1)))
        self._lit_for: np.ndarray | None = None

    def set(self, points: np.ndarray, scales: np.ndarray | None = None, camera: Any = None) -> None:
        import open3d as o3d

        if camera is not None and (self._lit_for is None or not np.allclose(self._lit_for, camera.eye)):
            # brighter than the mesh (ambient 0.55): markers must stand out, and keep their palette colour
            lambert = np.clip(self._v @ camera_lights(camera).T, 0.0, None)
            light = np.clip(0.6 + 0.45 * lambert[:, 0] + 0.1 * lambert[:, 1], 0.0, 1.15)  # (n,)
            colors = np.clip(self.colors[:, None, :] * light[None, :, None], 0.0, 1.0).reshape(-1, 3)
            self.geometry.vertex_colors = o3d.utility.Vector3dVector(colors)
            self._lit_for = np.asarray(camera.eye, dtype=np.float64).copy()

        points = np.asarray(points, dtype=np.float64)
        scales = np.ones(len(points)) if scales is None else np.asarray(scales, dtype=np.float64)
        vertices = points[:, None, :] + (self.radius * scales)[:, None, None] * self._v[None]  # (K, n, 3)
        self.geometry.vertices = o3d.utility.Vector3dVector(vertices.reshape(-1, 3))


def line_set(points: np.ndarray, edges: np.ndarray, color: Sequence[float]) -> Any:
    import open3d as o3d

    lines = o3d.geometry.LineSet()
    lines.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    lines.lines = o3d.utility.Vector2iVector(np.asarray(edges, dtype=np.int32).reshape(-1, 2))
    lines.colors = o3d.utility.Vector3dVector(np.tile(np.asarray(color, dtype=np.float64), (len(lines.lines), 1)))
    return lines


def mesh_edges(triangles: np.ndarray, limit: int = 60000) -> np.ndarray:
    """(E, 2) unique undirected edges of triangles (T, 3), thinned to at most ``limit`` (a ghost or x-ray wireframe)."""
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    if len(edges) > limit:
        edges = edges[np.linspace(0, len(edges) - 1, limit).astype(np.int64)]
    return edges


class Digits:
    """Keypoint numbers as flat, camera-facing digit glyphs on a white card (legacy OpenGL draws no text)."""

    def __init__(self, colors: np.ndarray, height: float) -> None:
        import open3d as o3d

        from kpd.viewer.labels import _GLYPHS

        self.colors = np.asarray(colors, dtype=np.float64)
        self.height = float(height)  # world height of a digit
        self.geometry = o3d.geometry.TriangleMesh()
        cells, colors_, cards = [], [], []
        for i in range(len(self.colors)):
            text = str(i)
            columns = 6 * len(text) - 1
            cards.append((i, columns))
            for j, ch in enumerate(text):
                rows, cols = np.nonzero(_GLYPHS[ch])
                for r, c in zip(rows, cols):
                    cells.append((i, 6 * j + c, 6 - r))  # (label, column, row from the bottom)
                    colors_.append(0.75 * self.colors[i])
        self._cells = np.array(cells, dtype=np.float64).reshape(-1, 3)
        self._cards = np.array(cards, dtype=np.float64).reshape(-1, 2)
        n_cells, n_cards = len(self._cells), len(self._cards)
        quads = np.arange(4 * (n_cells + n_cards)).reshape(-1, 4)
        triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        self.geometry.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
        ink = np.repeat(np.array(colors_).reshape(-1, 3), 4, axis=0)
        white = np.ones((4 * n_cards, 3))
        self.geometry.vertex_colors = o3d.utility.Vector3dVector(np.vstack([ink, white]))

    def set(self, anchors: np.ndarray, camera: Any) -> None:
        """Place label i's lower-left corner at ``anchors[i]`` (K, 3), facing ``camera``."""
        import open3d as o3d

        forward = camera.center - camera.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, camera.up)
        right /= max(np.linalg.norm(right), 1e-12)
        up = np.cross(right, forward)
        cell = self.height / 7
        corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)  # (4, 2)
        anchors = np.asarray(anchors, dtype=np.float64)
        toward = -forward * 0.02 * self.height
        label, col, row = self._cells.T.astype(np.int64) if len(self._cells) else (np.zeros(0, int),) * 3
        grid = np.stack([col, row], axis=1)[:, None, :] + corners[None]  # (n, 4, 2)
        ink = anchors[label][:, None, :] + cell * (grid[..., :1] * right + grid[..., 1:] * up) + toward
        k, columns = self._cards[:, 0].astype(np.int64), self._cards[:, 1]
        box = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        extent = np.stack([columns + 1, np.full_like(columns, 8.0)], axis=1)[:, None, :]  # (c, 1, 2)
        low = np.array([[-1.0, -1.0]])
        card_grid = np.where(box[None] < 0, low[None], extent)  # (c, 4, 2)
        cards = anchors[k][:, None, :] + cell * (card_grid[..., :1] * right + card_grid[..., 1:] * up)
        vertices = np.vstack([ink.reshape(-1, 3), cards.reshape(-1, 3)])
        self.geometry.vertices = o3d.utility.Vector3dVector(vertices)
        self.geometry.vertex_normals = o3d.utility.Vector3dVector(np.tile(-forward, (len(vertices), 1)))


# --- a rig in a view -------------------------------------------------------------------------------------------------


class RigDrawing:
    """The geometries of one rig being edited, in a :class:`GLView`.

    Parameters
    ----------
    view : GLView.
    mesh : kpd.io.Mesh, the rest mesh in user units.
    num_keypoints : K.
    cage_faces : (F, 3) or None.
    settings : kpd.viewer.render.ViewSettings.
    digits : draw the keypoint numbers as camera-facing glyphs (the editor); pictures draw them into the image.
    """

    def __init__(self, view: GLView, mesh: Any, num_keypoints: int, cage_faces: Any = None, *, settings: Any,
                 digits: bool = True) -> None:
        from kpd.viewer.render import cage_edges, keypoint_palette

        self.view, self.mesh, self.settings = view, mesh, settings
        self.num_keypoints = int(num_keypoints)
        self.colors = keypoint_palette(self.num_keypoints)
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        self.diagonal = float(np.linalg.norm(hi - lo)) or 1.0
        self.shaded = ShadedMesh(mesh, settings.mesh_color)
        self.proxy: ShadedMesh | None = None
        self._kept: np.ndarray | None = None
        stand_in = proxy_triangles(mesh.vertices, mesh.triangles, PROXY_TRIANGLES)
        if stand_in is not None:
            from kpd.io import Mesh

            self._kept, faces = stand_in
            colors = None if mesh.vertex_colors is None else mesh.vertex_colors[self._kept]
            self.proxy = ShadedMesh(Mesh(vertices=mesh.vertices[self._kept], triangles=faces, vertex_colors=colors),
                                    settings.mesh_color)
        self.markers = Markers(self.colors, self.marker_radius)
        self.cage_edges = None if cage_faces is None else cage_edges(cage_faces)
        self._edges = None
        self.digits = Digits(self.colors, 1.5 * self.marker_radius) if digits else None
        self.frame: Any = None
        self._eye: np.ndarray | None = None
        self._proxy_shown = False
        self._cage: Any = None  # the cage wireframe, its points updated in place

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

    def _wire(self) -> np.ndarray:
        if self._edges is None:
            self._edges = mesh_edges(self.mesh.triangles)
        return self._edges

    def show(self, frame: Any, camera: Any, *, mesh: bool = True, fast: bool = False) -> None:
        """Put ``frame`` (a kpd.viewer.render.Frame) in the view as ``camera`` sees it.

        ``fast``: a frame during a gesture; a mesh of more than :data:`PROXY_TRIANGLES` triangles is then drawn by its
        coarse stand-in (:func:`proxy_triangles`), and in full again by the next frame that is not fast.
        """
        import open3d as o3d

        s, view = self.settings, self.view
        view.camera = camera
        eye = np.asarray(camera.eye, dtype=np.float64)
        moved_eye = self._eye is None or not np.allclose(eye, self._eye)
        use_proxy = fast and self.proxy is not None
        if mesh or moved_eye or self.frame is None or use_proxy != self._proxy_shown:
            shown, hidden = (self.proxy, self.shaded) if use_proxy else (self.shaded, self.proxy)
            shown.set_vertices(frame.vertices[self._kept] if use_proxy else frame.vertices, camera)
            self._eye = eye.copy()
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
        keypoints = np.asarray(frame.keypoints, dtype=np.float64)
        selected = np.zeros(self.num_keypoints, bool)
        selected[[i for i in frame.selection if 0 <= i < self.num_keypoints]] = True
        scales = np.where(selected, 1.6, 1.0)
        self.markers.set(keypoints, scales, camera)
        view.put("keypoints", self.markers.geometry, show=s.show_keypoints)
        if self.digits is not None:
            self.digits.set(self.label_anchors(keypoints, camera, scales), camera)
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


def render_shots(shots: Sequence[Shot], settings: Any, *, view: GLView | None = None,
                 keypoint_radius: float | None = None) -> list[np.ndarray]:
    """Draw each shot with one hidden window; a list of (H, W, 3) uint8 with the keypoint numbers drawn in.

    The caller provides the display (``private_display`` for no screen); ``view`` reuses an open window.
    """
    import open3d as o3d

    from kpd.viewer.render import camera_pose, keypoint_palette, label_image_at

    own = view is None
    view = view or GLView(settings.width, settings.height, background=settings.background)
    view.vis.get_render_option().point_size = max(2.0, settings.height / 130)
    images = []
    try:
        for shot in shots:
            view.clear()
            points = frame_points(shot)
            camera = shot.camera or camera_pose(points, settings)
            view.set_box(points)
            view.camera = camera
            diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
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
                    shaded = ShadedMesh(layer.mesh, layer.color or settings.mesh_color,
                                        override=layer.color is not None)
                    shaded.set_vertices(layer.mesh.vertices, camera)
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

