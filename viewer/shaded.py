"""A mesh ready to draw (:class:`ShadedMesh`): one legacy Open3D ``TriangleMesh`` per texture, each frame uploading the
triangles that show in a pixel (:mod:`kpd.viewer.culling`) with colours shaded by the mesh's shading normals
(:mod:`kpd.viewer.normals`).

A triangle over the same corners as an earlier one is drawn once (:func:`distinct_triangles`: CAD meshes store many
triangles twice, once each way round), and where two materials lie over the same corners, which one shows is decided
here (:func:`material_sides`), never left to the renderer's order of geometries.
"""

from __future__ import annotations

import threading
from typing import Any, NamedTuple, Sequence

import numpy as np

from kpd._compiled import njit
from kpd.grouping import same_corners
from kpd.viewer.culling import CullingLayout, Viewport, visible_triangles
from kpd.viewer.normals import ShadingNormals, Welding, shade

__all__ = ["CULL_TRIANGLES", "ShadedMesh", "distinct_triangles", "material_sides", "textured", "mean_rgb"]

CULL_TRIANGLES = 100_000  # a mesh part with more triangles uploads only those that cover a pixel centre, each frame


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
    over their own vertices, with colours shaded by the mesh's shading normals (:class:`ShadingNormals`): what the
    picture needs of a mesh with more triangles than pixels, and the same picture.

    Parameters
    ----------
    mesh : kpd.io.Mesh (its colours, UVs and textures are drawn).
    color : (3,) RGB in [0, 1] for a mesh with neither colours nor a texture (or to override them).
    once : a mesh drawn once (a picture) is culled in its own order with each triangle judged alone: a
        :class:`CullingLayout` costs more to make than it saves in one frame, and the neighbours it pairs across
        edges make fewer triangles to draw, not a faster picture.
    """

    def __init__(self, mesh: Any, color: Sequence[float] = (0.80, 0.80, 0.82), *, override: bool = False,
                 once: bool = False) -> None:
        import open3d as o3d

        self.mesh = mesh
        self.color, self.override = tuple(float(c) for c in color), bool(override)  # as made (_shaded_layer)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        self.welding = Welding(mesh.vertices, grouped=mesh.position_groups())  # the binding's groups too
        self.parts: list[_Part] = []
        t = len(triangles)
        by_materials = textured(mesh) and not override
        ids = (mesh.triangle_material_ids if mesh.triangle_material_ids is not None else np.zeros(t, np.int64)) \
            if by_materials else np.zeros(t, np.int64)
        materials = np.unique(ids) if by_materials and t else [0]
        # two materials over the same corners: the two sides of a face, or one painted over the other
        hidden, sided = material_sides(triangles, ids, self.welding) if len(materials) > 1 else (None, None)
        for material in materials:
            chosen = (np.flatnonzero(ids == material) if hidden is None else
                      np.flatnonzero((ids == material) & ~hidden)) if by_materials else None  # None: every triangle
            part = o3d.geometry.TriangleMesh()
            texture = mesh.textures[int(material)] if by_materials and 0 <= material < len(mesh.textures) else None
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
                albedo = mean_rgb(texture).astype(np.float32) / 255.0  # (3,)
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
        self._normals = ShadingNormals(drawn, self.welding)  # shading normals from the triangles drawn
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


def material_sides(triangles: np.ndarray, ids: np.ndarray, welding: Welding) -> tuple[np.ndarray, np.ndarray]:
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


def textured(mesh: Any) -> bool:
    """Whether ``mesh`` is drawn by its materials (textures, and the UVs they need), not in one colour."""
    return bool(mesh.textures) and mesh.triangle_uvs is not None


def mean_rgb(texture: np.ndarray) -> np.ndarray:
    """(3,) float64 in [0, 255]: a texture's mean colour (a plain material's colour, read as a 1x1 image)."""
    rgb = texture.reshape(-1, texture.shape[2]) if texture.ndim == 3 else texture.reshape(-1, 1)
    rgb = rgb[:, :3] if rgb.shape[1] >= 3 else np.repeat(rgb[:, :1], 3, axis=1)
    return rgb.mean(axis=0)


@njit(nogil=True, error_model="numpy")
def _texture_coordinates(uvs, chosen, edge_u, edge_v, out):  # pragma: no cover - compiled
    """``out[r]``, (3, 2): the UVs of triangle ``chosen[r]`` (rows 3t, 3t + 1, 3t + 2 of ``uvs``) moved by whole tiles
    into the first one (minus the floor of their smallest), kept within the outer texel centres (``edge_u``,
    ``edge_v`` to 1 minus them) and v turned (1 - v): the numpy steps' values, NaN kept, in one pass instead of six
    over (T, 3, 2) arrays (numpy reduces along a short middle axis slowly)."""
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
