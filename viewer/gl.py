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

__all__ = ["GLView", "ShadedMesh", "RigDrawing", "Shot", "Layer", "render_shots", "shading_normals", "NoWindowError",
           "stand_in"]

log = logging.getLogger(__name__)

PROXY_TRIANGLES = 50000  # larger meshes are drawn by a coarse stand-in while a gesture is in progress
# meshes drawing more triangles than this (up to PROXY_TRIANGLES) get a fine stand-in (FINE_STAND_IN_CELLS), which the
# editor draws during gestures while the whole mesh's frames take long (kpd.viewer.app.draws_stand_in)
STAND_IN_TRIANGLES = 10_000
FINE_STAND_IN_CELLS = 250  # the fine stand-in's grid: cells across the mesh's largest side
CULL_TRIANGLES = 100_000  # a mesh part with more triangles uploads only those that cover a pixel centre, each frame


class NoWindowError(KpdError):
    """No OpenGL window could be opened (no display, no GL driver)."""


@njit(nogil=True, error_model="numpy")
def _texture_coordinates(uvs, chosen, edge_u, edge_v, out):  # pragma: no cover - compiled
    """``out[r]``, (3, 2): the UVs of triangle ``chosen[r]`` (rows 3t, 3t + 1, 3t + 2 of ``uvs``) moved by whole tiles
    into the first one (minus the floor of their smallest), kept within the outer texel centres (``edge_u``,
    ``edge_v`` to 1 minus them) and v turned (1 - v): the numpy steps' values, NaN kept (one pass instead of six over
    (T, 3, 2) arrays; numpy's reduction over the three corners alone took 0.33 s for 2.5M triangles)."""
    for r in range(chosen.shape[0]):
        t = chosen[r]
        for k in range(2):
            lo = edge_u if k == 0 else edge_v
            hi = 1.0 - lo
            a = np.float64(uvs[3 * t, k])
            b = np.float64(uvs[3 * t + 1, k])
            c = np.float64(uvs[3 * t + 2, k])
            low = a
            if b < low:
                low = b
            if c < low:
                low = c
            if a != a or b != b or c != c:
                low = np.nan
            tile = np.floor(low)
            for j in range(3):
                x = np.float64(uvs[3 * t + j, k]) - tile
                if x < lo:
                    x = lo
                elif x > hi:
                    x = hi
                out[r, j, k] = 1.0 - x if k == 1 else x


@njit(nogil=True)
def _compact(triangles, keep, remap, used, local):  # pragma: no cover - compiled
    """The kept triangles over their own vertices: ``used[:n]`` the vertices in order of first use, ``local[:m]`` the
    kept triangles indexing ``used``; returns (n, m). ``remap`` (V,) must hold -1 and is left so."""
    n = 0
    m = 0
    for t in range(triangles.shape[0]):
        if not keep[t]:
            continue
        for k in range(3):
            v = triangles[t, k]
            if remap[v] < 0:
                remap[v] = n
                used[n] = v
                n += 1
            local[m, k] = remap[v]
        m += 1
    for i in range(n):
        remap[used[i]] = -1
    return n, m


# --- meshes to draw ---------------------------------------------------------------------------------------------------


class _Part:
    """One legacy ``TriangleMesh`` of a :class:`ShadedMesh`: the triangles (into the whole mesh's vertices) it draws,
    their base colours (per vertex of the whole mesh, or one colour; None for a texture) and corner UVs."""

    def __init__(self, geometry: Any, vertices: np.ndarray, triangles: np.ndarray, albedo: np.ndarray | None,
                 uvs: np.ndarray | None, *, once: bool = False) -> None:
        self.geometry, self.triangles, self.albedo, self.uvs = geometry, triangles, albedo, uvs
        self.layout: tuple[np.ndarray, np.ndarray] | None = None  # (used, local) of all triangles, once uploaded
        self.scratch: dict = {}  # visible_triangles' arrays, reused frame after frame
        self.sided: np.ndarray | None = None  # of the triangles, those drawn only from the front (material_sides)
        # whether a frame draws only the triangles that show; the order they are judged in and a buffer of the
        # verdicts in the part's order (a mesh drawn once is judged in its own order, each triangle alone, into
        # visible_triangles' scratch: see ShadedMesh)
        self.culled = len(triangles) > CULL_TRIANGLES
        self.layout_for_culling = CullingLayout(vertices, triangles) if self.culled and not once else None
        self.keep = np.empty(len(triangles), dtype=np.bool_) if self.layout_for_culling is not None else None


class ShadedMesh:
    """A mesh as legacy Open3D geometries: one ``TriangleMesh`` per texture (or one for the whole mesh).

    Each frame (:meth:`set_vertices`) uploads the triangles that cover a pixel centre (:func:`visible_triangles`),
    over their own vertices, with colours shaded by the mesh's shading normals (:class:`_Normals`): what the picture
    needs of a mesh with more triangles than pixels, and the same picture.

    Parameters
    ----------
    mesh : kpd.io.Mesh (its colours, UVs and textures are drawn).
    color : (3,) RGB in [0, 1] for a mesh with neither colours nor a texture (or to override them).
    once : a mesh drawn once (a picture) is culled in its own order with each triangle judged alone: a
        :class:`CullingLayout` costs more to make than it saves in one frame (of a 1.37M-vertex chair, 0.17 s to
        make and no faster a frame; 1.0 s and 0.2 s faster with its triangles shuffled), and the neighbours it
        pairs across edges (0.2-0.3 s) make fewer triangles to draw, not a faster picture.
    """

    def __init__(self, mesh: Any, color: Sequence[float] = (0.80, 0.80, 0.82), *, override: bool = False,
                 once: bool = False) -> None:
        import open3d as o3d

        self.mesh = mesh
        self.color, self.override = tuple(float(c) for c in color), bool(override)  # as made (_shaded_layer)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        self.welding = _Welding(mesh.vertices, grouped=mesh.position_groups())  # the binding's groups too
        self.parts: list[_Part] = []
        t = len(triangles)
        textured = _textured(mesh) and not override
        ids = (mesh.triangle_material_ids if mesh.triangle_material_ids is not None else np.zeros(t, np.int64)) \
            if textured else np.zeros(t, np.int64)
        materials = np.unique(ids) if textured and t else [0]
        # two materials over the same corners: the two sides of a face, or one painted over the other
        hidden, sided = material_sides(triangles, ids, self.welding) if len(materials) > 1 else (None, None)
        for material in materials:
            chosen = (np.flatnonzero(ids == material) if hidden is None else
                      np.flatnonzero((ids == material) & ~hidden)) if textured else None  # None: every triangle
            part = o3d.geometry.TriangleMesh()
            texture = mesh.textures[int(material)] if textured and 0 <= material < len(mesh.textures) else None
            if texture is None or texture.shape[0] * texture.shape[1] == 1:
                # a triangle over the same corners as an earlier one draws nothing new: two-sided lighting and back
                # faces shown (CAD meshes store many triangles twice, once each way round: half of ShapeNet's)
                first = distinct_triangles(triangles if chosen is None else triangles[chosen])
                chosen = first if chosen is None else chosen[first]
            elif chosen is None:
                chosen = np.arange(t)
            uvs = None
            if texture is not None and texture.shape[0] * texture.shape[1] == 1:
                # a material's plain colour (kpd.io reads an OBJ material without a map as a 1x1 image): shaded
                albedo = _mean_rgb(texture).astype(np.float32) / 255.0  # (3,)
            elif texture is not None:
                # (Tp, 3, 2). Tiled maps (UVs beyond [0, 1], common in CAD models): the legacy renderer does not
                # repeat a texture (black beyond it), so each triangle moves by whole tiles into the first one;
                # within the outer texel centres (the renderer's border, black, lies beyond them); v turned, as the
                # legacy renderer reads v from the top row down
                uvs = np.empty((len(chosen), 3, 2), dtype=np.float64)
                _texture_coordinates(np.asarray(mesh.triangle_uvs).reshape(-1, 2), chosen.astype(np.int64, copy=False),
                                     0.5 / texture.shape[1], 0.5 / texture.shape[0], uvs)
                image = np.ascontiguousarray(texture[:, :, :3] if texture.ndim == 3 else
                                             np.repeat(texture[:, :, None], 3, axis=2))
                part.textures = [o3d.geometry.Image(image)]
                albedo = None
            elif mesh.vertex_colors is not None and not override:
                albedo = np.asarray(mesh.vertex_colors, dtype=np.float32)  # (V, 3)
            else:
                albedo = np.asarray(color, dtype=np.float32)[:3]  # (3,)
            self.parts.append(_Part(part, mesh.vertices, triangles[chosen], albedo, uvs, once=once))
            if sided is not None and chosen is not None and sided[chosen].any():
                self.parts[-1].sided = np.flatnonzero(sided[chosen])
        drawn = (self.parts[0].triangles if len(self.parts) == 1 else np.concatenate([p.triangles for p in self.parts])
                 ) if self.parts else np.zeros((0, 3), np.int64)
        self._normals = _Normals(drawn, self.welding)  # shading normals from the triangles drawn
        self._remap = np.full(len(mesh.vertices), -1, dtype=np.int32)  # (V,) scratch of _compact
        self._used = np.empty(len(mesh.vertices), dtype=np.int64)
        self._local = np.empty((max((len(p.triangles) for p in self.parts), default=0), 3), dtype=np.int32)
        self._lock = threading.Lock()  # one preparation at a time: it works in the scratch arrays above

    @property
    def geometries(self) -> list[Any]:
        return [part.geometry for part in self.parts]

    @property
    def drawn(self) -> np.ndarray:
        """(D, 3) int64: the triangles drawn (each set of corners once where the two sides shade alike)."""
        return self._normals.triangles

    def set_vertices(self, vertices: np.ndarray, camera: Any, viewport: Viewport | None = None) -> None:
        """New vertex positions (V, 3), shaded as ``camera`` sees them (normals turned towards it); with ``viewport``
        (the view's size and this camera), only the triangles that show in a pixel are uploaded."""
        self.upload(self.prepare(vertices, camera, viewport))

    def prepare(self, vertices: np.ndarray, camera: Any, viewport: Viewport | None = None, *,
                stop: np.ndarray | None = None) -> list | None:
        """What :meth:`set_vertices` uploads, worked out without touching the geometries: a thread may prepare a
        frame while the main thread draws others (one preparation at a time). ``stop`` (1,) uint8, set non-zero by
        another thread once the frame is no longer wanted, abandons the work (returns None) within milliseconds."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        with self._lock:
            normals: list = []  # the shading normals, once the first part that needs them has its triangles
            uploads = []
            for part in self.parts:
                if stop is not None and stop[0]:
                    return None
                upload = self._prepare_part(part, vertices, normals, camera, viewport, stop)
                if upload is None:
                    return None
                uploads.append(upload)
            return uploads

    def _prepare_part(self, part: _Part, vertices: np.ndarray, normals: list, camera: Any,
                      viewport: Viewport | None, stop: np.ndarray | None = None) -> _Upload | None:
        layout = part.layout
        triangles = uvs = keep = None
        if viewport is not None and part.culled:
            keep = visible_triangles(vertices, part.triangles, viewport, scratch=part.scratch, stop=stop) \
                if part.layout_for_culling is None else \
                part.layout_for_culling.visible(vertices, viewport, part.keep, scratch=part.scratch, stop=stop)
            if keep is None:
                return None
        if part.sided is not None:  # one side of a face with two materials: drawn when its front faces the camera
            corners = vertices[part.triangles[part.sided]]  # (S, 3, 3)
            front = np.einsum("ij,ij->i", np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                              np.asarray(camera.eye, dtype=np.float64) - corners[:, 0])
            keep = np.ones(len(part.triangles), dtype=np.bool_) if keep is None else keep.copy()
            keep[part.sided[front < 0]] = False
        if keep is not None:
            n, m = _compact(part.triangles, keep, self._remap, self._used, self._local)
            used, triangles = self._used[:n], self._local[:m].copy()
            part.layout = None
        elif layout is None:  # every triangle, uploaded once
            keep = np.ones(len(part.triangles), dtype=np.bool_)
            n, m = _compact(part.triangles, keep, self._remap, self._used, self._local)
            used, triangles = self._used[:n].copy(), self._local[:m].copy()
            part.layout = (used, triangles)
        else:
            keep, (used, _) = None, layout
        if triangles is not None and part.albedo is None:
            uvs = np.compress(keep, part.uvs.reshape(-1, 6), axis=0).reshape(-1, 2)  # a third of uvs[keep]'s time
        colors = None
        if part.albedo is not None:
            if stop is not None and stop[0]:  # after the culling, which a newer frame may cut short
                return None
            if len(self.parts) == 1 and len(used) < len(self.welding.inverse) // 2:  # the normals it shows alone
                shading = self._normals.of(vertices, camera.eye, used)
            else:
                if not normals:
                    normals.append(self._normals(vertices, camera.eye))
                shading = normals[0][self.welding.inverse[used]]
            albedo = part.albedo if part.albedo.ndim == 1 else part.albedo[used]
            colors = shade(albedo, shading, camera).astype(np.float64)
        return _Upload(vertices[used], triangles, colors, uvs)

    def upload(self, uploads: list) -> None:
        """Put a :meth:`prepare`'s arrays into the geometries (Open3D copies them: float64 rows at memcpy speed)."""
        import open3d as o3d

        for part, up in zip(self.parts, uploads):
            geometry = part.geometry
            geometry.vertices = o3d.utility.Vector3dVector(up.vertices)
            if up.triangles is not None:
                geometry.triangles = o3d.utility.Vector3iVector(up.triangles)
                if up.uvs is not None:
                    geometry.triangle_uvs = o3d.utility.Vector2dVector(up.uvs)
                    geometry.triangle_material_ids = o3d.utility.IntVector(np.zeros(len(up.triangles), np.int32))
            if up.colors is not None:
                geometry.vertex_colors = o3d.utility.Vector3dVector(up.colors)


class _Upload(NamedTuple):
    """One part's arrays for the next frame: vertices (n, 3) float64, triangles (m, 3) int32 into them (None: as
    uploaded before), colours (n, 3) float64 or None, corner UVs (3m, 2) or None."""

    vertices: np.ndarray
    triangles: np.ndarray | None
    colors: np.ndarray | None
    uvs: np.ndarray | None


def distinct_triangles(triangles: np.ndarray) -> np.ndarray:
    """(T',) sorted indices of the first triangle over each set of three corners (whatever their order); by a counting
    sort on each triangle's smallest corner, in linear time (the same as :func:`_distinct_triangles_reference`)."""
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if not len(triangles):
        return np.zeros(0, dtype=np.int64)
    top = int(triangles.max()) + 1
    same = np.empty(len(triangles), dtype=np.int64)
    same_corners(triangles, np.arange(top, dtype=np.int64), top, False, same)
    return np.flatnonzero(same == np.arange(len(triangles)))


def material_sides(triangles: np.ndarray, ids: np.ndarray, welding: _Welding) -> tuple[np.ndarray, np.ndarray]:
    """Where triangles of two materials lie over the same corners (by position): ``(hidden, sided)``, (T,) bool each.

    Wound the other way round, they are the two sides of one face (SketchUp exports a face's front and back
    materials so: a cup's label outside, its white inside): each is ``sided``, drawn only when its front faces the
    camera. Wound the same way, the one later in the file is drawn, as a painter would, and the others are
    ``hidden``. Which of two coincident surfaces shows is then never left to the renderer's order of geometries.
    """
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    count = len(triangles)
    if not count:
        return np.zeros(0, dtype=np.bool_), np.zeros(0, dtype=np.bool_)
    corners = welding.inverse.astype(np.int64, copy=False)[triangles]  # (T, 3) by position
    same = np.empty(count, dtype=np.int64)
    same_corners(corners, np.arange(welding.groups, dtype=np.int64), welding.groups, False, same)
    # the winding against the first triangle over the same corners: the corner after the smallest, in each
    low = corners.argmin(axis=1)
    after = corners[np.arange(count), (low + 1) % 3]
    flipped = (after != after[same]).astype(np.int64)
    key = 2 * same + flipped  # (T,) one number per set of corners and winding
    last = np.full(2 * count, -1, dtype=np.int64)
    np.maximum.at(last, key, np.arange(count))
    ids = np.asarray(ids)
    hidden = ids[last[key]] != ids
    other = last[key ^ 1]  # the last triangle wound the other way over these corners, -1 for none
    sided = ~hidden & (other >= 0) & (ids[np.maximum(other, 0)] != ids)
    return hidden, sided


def _distinct_triangles_reference(triangles: np.ndarray) -> np.ndarray:
    """:func:`distinct_triangles` by sorting: the corners of each triangle sorted, then the rows."""
    triangles = np.asarray(triangles, dtype=np.int64)
    if not len(triangles):
        return np.zeros(0, dtype=np.int64)
    ordered = np.sort(triangles, axis=1)
    order = np.lexsort(ordered.T[::-1])
    new = np.ones(len(order), dtype=bool)
    new[1:] = (ordered[order[1:]] != ordered[order[:-1]]).any(axis=1)
    return np.sort(order[new])


def proxy_triangles(vertices: np.ndarray, triangles: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A coarse stand-in of a large mesh for frames drawn during a gesture: vertices clustered on a grid, one
    original vertex kept per cell, triangles that collapse dropped (and each set of corners once).

    Returns None when the mesh has at most ``limit`` triangles, else ``(kept, faces)``: (P,) indices of the kept
    original vertices and (Q, 3) triangles into ``kept`` with Q <= ``limit``. Its vertices are original vertices, so
    the stand-in of a deformed mesh is the deformed mesh's rows ``kept``: no deformation of its own.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if len(triangles) <= limit:
        return None
    lo, hi = box([vertices])
    extent = float((hi - lo).max()) or 1.0
    size = extent / math.sqrt(limit)  # about sqrt(limit) cells across the largest side
    scratch = _cluster_scratch(len(vertices), len(triangles))  # for every try (fresh: 6 ms of a 73 ms try at 1.37M)
    for _ in range(12):
        kept, faces = _clustered(vertices, triangles, lo, hi, size, scratch)
        if len(faces) <= limit:
            return kept, faces
        size *= 1.1 * math.sqrt(len(faces) / limit)
    return kept, faces[:limit]


def fine_stand_in(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A stand-in that looks like the mesh, for one of few vertices and many triangles (a CAD mesh: many of its
    triangles cover less than a pixel): :func:`proxy_triangles`' clustering on a grid of
    :data:`FINE_STAND_IN_CELLS` cells across the mesh's largest side, which only collapses what is smaller than a
    cell. Of an unseen ShapeNet chair's 19,900 distinct triangles it keeps 10,468, and its picture at 960 x 720
    differs from the whole mesh's in 0.4% of the shape's pixels. ``(kept, faces)`` as :func:`proxy_triangles`
    gives them; None when it would keep more than three quarters of the triangles (nothing to gain)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if not len(triangles):
        return None
    lo, hi = box([vertices])
    extent = float((hi - lo).max()) or 1.0
    kept, faces = _clustered(vertices, triangles, lo, hi, extent / FINE_STAND_IN_CELLS)
    return (kept, faces) if 4 * len(faces) <= 3 * len(triangles) else None


def stand_in(vertices: np.ndarray, triangles: np.ndarray, *, fine: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """The editor's stand-in of a mesh drawing ``triangles``: a coarse one of at most :data:`PROXY_TRIANGLES`
    triangles for a larger mesh (:func:`proxy_triangles`), with ``fine`` a fine one for a mesh of more than
    :data:`STAND_IN_TRIANGLES` (:func:`fine_stand_in`), else None. A stand-in is drawn in per-vertex colours
    (:func:`stand_in_colors`): the editor asks for a fine one only for a mesh without a texture image
    (:func:`image_maps`), which would change colour while it is dragged."""
    if len(triangles) > PROXY_TRIANGLES:
        return proxy_triangles(vertices, triangles, PROXY_TRIANGLES)
    if fine and len(triangles) > STAND_IN_TRIANGLES:
        return fine_stand_in(vertices, triangles)
    return None


def _textured(mesh: Any) -> bool:
    """Whether ``mesh`` is drawn by its materials (textures, and the UVs they need), not in one colour."""
    return bool(mesh.textures) and mesh.triangle_uvs is not None


def _mean_rgb(texture: np.ndarray) -> np.ndarray:
    """(3,) float64 in [0, 255]: a texture's mean colour (a plain material's colour, read as a 1x1 image)."""
    rgb = texture.reshape(-1, texture.shape[2]) if texture.ndim == 3 else texture.reshape(-1, 1)
    rgb = rgb[:, :3] if rgb.shape[1] >= 3 else np.repeat(rgb[:, :1], 3, axis=1)
    return rgb.mean(axis=0)


def image_maps(mesh: Any) -> bool:
    """Whether ``mesh`` is drawn with a texture image (not only plain material colours, which kpd.io reads as 1x1
    images): its stand-ins, drawn in per-vertex colours, would change colour."""
    return _textured(mesh) and any(t.shape[0] * t.shape[1] > 1 for t in mesh.textures)


def stand_in_colors(mesh: Any) -> np.ndarray | None:
    """(V, 3) float64 colours in [0, 1] for a stand-in of ``mesh``: its vertex colours, or of a mesh whose materials
    are plain colours each vertex's material colour (of the last triangle it is a corner of: a cell of a stand-in
    takes one of its vertices' colours); None for a mesh drawn in one colour."""
    if not _textured(mesh):
        return None if mesh.vertex_colors is None else np.asarray(mesh.vertex_colors, dtype=np.float64)
    palette = np.array([_mean_rgb(texture) / 255.0 for texture in mesh.textures])  # an image map's: its mean
    ids = (np.zeros(len(mesh.triangles), np.int64) if mesh.triangle_material_ids is None
           else np.clip(np.asarray(mesh.triangle_material_ids, dtype=np.int64), 0, len(palette) - 1))
    colors = np.full((len(mesh.vertices), 3), 0.8)
    colors[np.asarray(mesh.triangles, dtype=np.int64).reshape(-1)] = np.repeat(palette[ids], 3, axis=0)
    return colors


def _cluster_scratch(num_vertices: int, num_triangles: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_clustered`'s working arrays: the cell of each vertex (numbered as first met), the first vertex of
    each cell, and each triangle's first triangle over the same cells."""
    return (np.empty(num_vertices, dtype=np.int64), np.empty(num_vertices, dtype=np.int64),
            np.empty(num_triangles, dtype=np.int64))


def _clustered(vertices: np.ndarray, triangles: np.ndarray, lo: np.ndarray, hi: np.ndarray, size: float,
               scratch: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices clustered on a grid of cells of ``size`` from ``lo``: ``(kept, faces)``, the first vertex of each
    cell and the triangles that do not collapse (each set of corners once) over them. ``scratch``: a
    :func:`_cluster_scratch` to work in (made here if None)."""
    cluster, first, same = scratch or _cluster_scratch(len(vertices), len(triangles))
    span = np.floor((hi - lo) / size).astype(np.int64) + 1  # cells along each axis
    count = _cells(vertices, lo, size, span, cluster, first)
    same_corners(triangles, cluster, count, True, same)
    faces = cluster[triangles[same == np.arange(len(triangles))]]  # (Q, 3)
    return first[:count].copy(), faces


@njit(nogil=True, error_model="numpy")
def _cells(vertices, lo, size, span, group, first):  # pragma: no cover - compiled
    """Vertices grouped by grid cell (``floor((v - lo) / size)`` on each axis) with a hash table: ``group[v]``
    numbers the cells as first met, ``first[g]`` is the first vertex in cell g; returns the number of cells."""
    n = vertices.shape[0]
    keys = np.empty(n, dtype=np.int64)
    slots = 1
    while slots < 2 * n:
        slots *= 2
    table = np.full(slots, -1, dtype=np.int64)
    mask = slots - 1
    count = 0
    for v in range(n):
        ix = int(np.floor((vertices[v, 0] - lo[0]) / size))
        iy = int(np.floor((vertices[v, 1] - lo[1]) / size))
        iz = int(np.floor((vertices[v, 2] - lo[2]) / size))
        k = (ix * span[1] + iy) * span[2] + iz
        keys[v] = k
        h = ((k * 2654435761) ^ (k >> 17)) & mask
        while True:
            g = table[h]
            if g < 0:
                table[h] = count
                first[count] = v
                group[v] = count
                count += 1
                break
            if keys[first[g]] == k:
                group[v] = g
                break
            h = (h + 1) & mask
    return count


# --- the window ----------------------------------------------------------------------------------------------------


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
    that the system holds back for a time slice holds back a smaller share of the frame. On 2 cores beside a busy
    process, the editor's drag steps on a ShapeNet chair of 40,504 triangles (``bench_viewer.py --runs 1 --drags 8
    --pauses 0 --sizes shapenet --loads loaded``, three alternations): at most 36-42 ms a session on 16 threads
    against 47-54 ms on 6 (medians 33-37 ms against 37-39 ms); drawing the 489k triangles that show of a 1.37M-vertex
    chair at 960 x 720 (4 samples a pixel): 310 ms on 3 threads against 350 ms on 2, and 299-355 ms on 6 against
    329-396 ms on 3. Quiet, the thread count made no difference. The pictures do not change (each tile is drawn alike
    whatever thread takes it). A GPU driver ignores it."""
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

    def set(self, anchors: np.ndarray, camera: Any, sizes: Any = 1.0) -> None:
        """Place label i's lower-left corner at ``anchors[i]`` (K, 3), facing ``camera``, ``sizes[i]`` times its
        height (a label drawn nearer the camera is drawn smaller, so that it looks the same)."""
        import open3d as o3d

        forward = camera.center - camera.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, camera.up)
        right /= max(np.linalg.norm(right), 1e-12)
        up = np.cross(right, forward)
        anchors = np.asarray(anchors, dtype=np.float64)
        cell = self.height / 7 * np.broadcast_to(np.asarray(sizes, dtype=np.float64), (len(anchors),))  # (K,)
        corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)  # (4, 2)
        label, col, row = self._cells.T.astype(np.int64) if len(self._cells) else (np.zeros(0, int),) * 3
        grid = np.stack([col, row], axis=1)[:, None, :] + corners[None]  # (n, 4, 2)
        step = cell[label][:, None, None]  # (n, 1, 1)
        ink = anchors[label][:, None, :] + step * (grid[..., :1] * right + grid[..., 1:] * up - 0.14 * forward)
        k, columns = self._cards[:, 0].astype(np.int64), self._cards[:, 1]
        box = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        extent = np.stack([columns + 1, np.full_like(columns, 8.0)], axis=1)[:, None, :]  # (c, 1, 2)
        low = np.array([[-1.0, -1.0]])
        card_grid = np.where(box[None] < 0, low[None], extent)  # (c, 4, 2)
        cards = anchors[k][:, None, :] + cell[k][:, None, None] * (card_grid[..., :1] * right + card_grid[..., 1:] * up)
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

