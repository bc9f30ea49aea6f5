"""The mesh and point-set types every kpd module passes around, with their checks.

:class:`Mesh` holds a triangle mesh with everything kpd keeps through reading, deforming and writing (normals,
colours, UVs, textures, material ids); :class:`PointSet` a point cloud. Both check and convert every field in their
constructors and raise :class:`~kpd.errors.InputError` for a malformed one, so code that receives them trusts them.
Reading and writing them is :mod:`kpd.io`'s work.

Conventions
-----------
- ``Mesh.triangle_uvs`` has one row per triangle corner, ``(3T, 2)``, origin at the bottom left (OBJ convention).
  Textures are stored as they appear in the image file (top row first), so the nearest texel of ``(u, v)`` is
  ``texture[int((1 - v) * H), int(u * W)]``. (Open3D keeps its textures upside down in memory;
  :meth:`Mesh.from_open3d` and :meth:`Mesh.to_open3d` flip them.)
- ``triangle_material_ids`` index ``textures``: one texture per material the triangles use (in order of first use
  when read from OBJ or glTF). A material without an image has a 1x1 texture of its colour (OBJ ``Kd``, glTF
  ``baseColorFactor``; white through Open3D), which the drawing code shades like a vertex colour; a mesh whose
  materials all look the same and have no image has ``textures == []`` and ``triangle_material_ids is None``.
- ``triangle_uv_mask`` marks the triangles that have texture coordinates when only some do (an OBJ that mixes
  ``f 1/1/1`` and ``f 5//2``, a glTF with primitives without ``TEXCOORD_0``); the others' UVs are zeros. None means
  every triangle has them (or none, with ``triangle_uvs`` None).
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from kpd.errors import InputError
from kpd.grouping import first_occurrence_groups
from kpd.triangles import vertex_normals

if TYPE_CHECKING:  # pragma: no cover
    import open3d

__all__ = ["Mesh", "PointSet", "count_phrase", "MAX_COORDINATE"]

# Coordinates beyond this size are refused: kpd squares distances and areas (and draws in float32, whose range
# ends at 3.4e38), which overflow past it. Real shapes are many orders of magnitude smaller.
MAX_COORDINATE = 1e18

# Colours may stray this far outside [0, 1] through float rounding before they count as malformed.
_COLOR_SLACK = 1e-6



def _open3d():
    """Open3D, imported on first use so that ``import kpd.mesh`` stays light."""
    from kpd._open3d import defer_plotly_helpers

    defer_plotly_helpers()
    import open3d

    return open3d


def count_phrase(n: int, plural: str, verb: str = "have", singular_verb: str = "has") -> str:
    """'1 vertex has' / '3 vertices have' for the nouns kpd's messages use."""
    if n != 1:
        return f"{n} {plural} {verb}"
    singular = {"vertices": "vertex", "keypoints": "keypoint", "points": "point"}.get(plural, plural[:-1])
    return f"1 {singular} {singular_verb}"


def _prefix(path: str | None, what: str) -> str:
    return f"{path}: " if path else f"{what}: "



# --- Mesh ----------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Mesh:
    """A triangle mesh with the attributes kpd keeps through reading, deforming and writing.

    Attributes
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, indices into ``vertices``
    vertex_normals : (V, 3) float64 or None
    vertex_colors : (V, 3) float64 in [0, 1] or None
    triangle_uvs : (3T, 2) float64 or None, one row per triangle corner (origin bottom left)
    textures : list of (H, W, C) uint8, as in the image file (top row first)
    triangle_material_ids : (T,) int64 or None, indices into ``textures``
    triangle_uv_mask : (T,) bool or None, which triangles have texture coordinates (None: all of them, when
        ``triangle_uvs`` is given); the UVs of the others are zeros and mean nothing
    path : the file the mesh was read from, or None; used in error messages

    The constructor checks and converts every field and raises :class:`~kpd.errors.InputError` for a malformed one.
    Arrays are shared, not copied, by :meth:`with_vertices`; treat them as read-only.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_normals: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    triangle_uvs: np.ndarray | None = None
    textures: list = field(default_factory=list)
    triangle_material_ids: np.ndarray | None = None
    triangle_uv_mask: np.ndarray | None = None
    path: str | None = None

    def __post_init__(self) -> None:
        # Not dataclass fields: the file the mesh was read from when its writer can write that file's own structure
        # again with new positions (kpd.io.obj, kpd.io.gltf), and the image file of each texture (or None), so that
        # writers copy a JPEG as it is. with_vertices hands both on; any other new Mesh starts without them.
        self._source: Any = None
        self._texture_files: list = []
        # Not a dataclass field: groups of vertices sharing a position and a normal (UV-seam copies), computed by
        # with_vertices on first use and handed on to the meshes it makes.
        self._normal_groups: np.ndarray | None = None
        self._forget_positions()
        where = _prefix(self.path, "mesh")
        self.vertices = _vertex_array(self.vertices, where, "vertices", "vertices")
        V = len(self.vertices)
        self.triangles = _triangle_array(self.triangles, V, where)
        T = len(self.triangles)
        if self.vertex_normals is not None:
            self.vertex_normals = _attribute(self.vertex_normals, (V, 3), where, "vertex_normals")
        if self.vertex_colors is not None:
            self.vertex_colors = _colors(self.vertex_colors, V, where, "vertex_colors")
        if self.triangle_uvs is not None:
            self.triangle_uvs = _attribute(self.triangle_uvs, (3 * T, 2), where, "triangle_uvs")
        self.textures = [_texture(t, where, i) for i, t in enumerate(self.textures)]
        if self.triangle_material_ids is not None:
            self.triangle_material_ids = _material_ids(self.triangle_material_ids, T, len(self.textures), where)
        if self.triangle_uv_mask is not None:
            mask = np.asarray(self.triangle_uv_mask)
            if mask.shape != (T,) or mask.dtype != np.bool_:
                raise InputError(f"{where}triangle_uv_mask must be bool with shape ({T},); got {mask.dtype} "
                                 f"{mask.shape}")
            if self.triangle_uvs is None:
                raise InputError(f"{where}triangle_uv_mask needs triangle_uvs")
            self.triangle_uv_mask = None if mask.all() else np.ascontiguousarray(mask)

    def __repr__(self) -> str:
        extras = [
            name
            for name, value in (
                ("normals", self.vertex_normals), ("colors", self.vertex_colors), ("uvs", self.triangle_uvs)
            )
            if value is not None
        ]
        if self.textures:
            extras.append(f"{len(self.textures)} texture(s)")
        more = (", " + ", ".join(extras)) if extras else ""
        return f"Mesh({len(self.vertices)} vertices, {len(self.triangles)} triangles{more}, path={self.path!r})"

    def with_vertices(self, vertices: Any) -> "Mesh":
        """The same mesh with new vertex positions.

        Topology, UVs, colours, textures and material ids are shared with ``self`` (not copied). Vertex normals, if
        the mesh has them, are recomputed from the new positions (area-weighted); vertices that had the same position
        and normal in ``self`` (copies along a UV seam) keep equal normals, so seams stay invisible, while copies with
        different normals (hard edges) stay separate.

        Parameters
        ----------
        vertices : (V, 3) array-like, same V as ``self``

        Returns
        -------
        Mesh
        """
        where = _prefix(self.path, "mesh")
        new = _vertex_array(vertices, where, "new vertices", "vertices")
        if new.shape != self.vertices.shape:
            raise InputError(f"{where}new vertices must have shape {self.vertices.shape}; got {new.shape}")
        normals = None
        if self.vertex_normals is not None:
            if self._normal_groups is None:
                self._normal_groups = first_occurrence_groups(np.hstack([self.vertices, self.vertex_normals]))[1]
            normals = vertex_normals(new, self.triangles, self._normal_groups)
        out = object.__new__(Mesh)  # every other field is already checked: skip __post_init__
        out.__dict__.update(self.__dict__)
        out.vertices = new
        out.vertex_normals = normals
        out._forget_positions()  # new positions: grouped again when asked
        return out

    def position_groups(self) -> tuple[np.ndarray, np.ndarray]:
        """The vertices grouped by position: ``(first, index)``, the first vertex of each group in order of first
        occurrence (G,) and each vertex's group (V,), as :func:`kpd.grouping.first_occurrence_groups` of
        ``vertices``.

        Computed once per mesh, on first use, and kept (the arrays are shared: treat them as read-only): binding a
        mesh and getting it ready to draw both need them, and a command does the two at once on two threads (a
        second asker waits for the first's result).
        """
        with self._positions_lock:
            if self._positions is None:
                self._positions = first_occurrence_groups(self.vertices)
            return self._positions

    def _forget_positions(self) -> None:
        self._positions: tuple[np.ndarray, np.ndarray] | None = None
        self._positions_lock = threading.Lock()

    def __getstate__(self) -> dict:  # a copy (copy.deepcopy, multiprocessing) takes neither the lock nor the groups
        state = self.__dict__.copy()
        del state["_positions"], state["_positions_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._forget_positions()

    def to_open3d(self) -> "open3d.geometry.TriangleMesh":
        """An ``open3d.geometry.TriangleMesh`` with every attribute (textures flipped to Open3D's convention)."""
        o3d = _open3d()
        m = o3d.geometry.TriangleMesh()
        m.vertices = o3d.utility.Vector3dVector(self.vertices)
        m.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(self.triangles, dtype=np.int32))
        if self.vertex_normals is not None:
            m.vertex_normals = o3d.utility.Vector3dVector(self.vertex_normals)
        if self.vertex_colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors)
        if self.triangle_uvs is not None:
            m.triangle_uvs = o3d.utility.Vector2dVector(self.triangle_uvs)
        if self.textures:
            m.textures = [o3d.geometry.Image(_squeeze_channels(t[::-1])) for t in self.textures]
            ids = self.triangle_material_ids
            if ids is None:
                ids = np.zeros(len(self.triangles), dtype=np.int64)
            m.triangle_material_ids = o3d.utility.IntVector(np.ascontiguousarray(ids, dtype=np.int32))
        return m

    @classmethod
    def from_open3d(cls, mesh: "open3d.geometry.TriangleMesh", *, path: str | os.PathLike | None = None) -> "Mesh":
        """Copy an ``open3d.geometry.TriangleMesh`` (see the module notes on textures and material ids).

        Raises
        ------
        InputError
            If the mesh is empty, has non-finite vertices or triangles that index missing vertices.
        """
        textures, ids = _normalise_materials(
            [np.asarray(t) for t in mesh.textures],
            np.asarray(mesh.triangle_material_ids) if mesh.has_triangle_material_ids() else None,
        )
        return cls(
            vertices=np.array(mesh.vertices, dtype=np.float64),
            triangles=np.array(mesh.triangles, dtype=np.int64).reshape(-1, 3),
            vertex_normals=np.array(mesh.vertex_normals, dtype=np.float64) if mesh.has_vertex_normals() else None,
            vertex_colors=np.array(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else None,
            triangle_uvs=np.array(mesh.triangle_uvs, dtype=np.float64) if mesh.has_triangle_uvs() else None,
            textures=textures,
            triangle_material_ids=ids,
            path=None if path is None else os.fspath(path),
        )


def _vertex_array(x: Any, where: str, name: str, noun: str) -> np.ndarray:
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}{name} must be numeric with shape (N, 3); got {type(x).__name__}") from exc
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{where}{name} must have shape (N, 3); got {a.shape}")
    if len(a) == 0:
        raise InputError(f"{where}no {noun} (empty geometry)")
    # whole-array reductions first: numpy reduces an (N, 3) array along its rows about ten times more slowly
    if not np.isfinite(a).all():
        bad = ~np.isfinite(a).all(axis=1)
        first = int(np.flatnonzero(bad)[0])
        raise InputError(f"{where}{count_phrase(int(bad.sum()), noun)} NaN or inf coordinates (first: index {first})")
    if max(a.max(), -a.min()) > MAX_COORDINATE:
        size = np.abs(a).max(axis=1)  # (N,)
        big = size > MAX_COORDINATE
        raise InputError(f"{where}{count_phrase(int(big.sum()), noun)} coordinates beyond {MAX_COORDINATE:.0e} "
                         f"(up to {size.max():.3g} at index {int(np.argmax(size))}); kpd squares distances, which "
                         "overflow there: rescale the shape")
    return a


def _triangle_array(x: Any, V: int, where: str) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype.kind == "f" and np.isfinite(a).all() and np.array_equal(a, np.round(a)):
        a = a.astype(np.int64)  # integers written as floats (the authors' demo files)
    if a.ndim != 2 or a.shape[1] != 3 or not (a.dtype.kind in "iu" or a.size == 0):
        raise InputError(f"{where}triangles must be integers with shape (T, 3); got {a.dtype} {a.shape}")
    if len(a) == 0:
        raise InputError(f"{where}no triangles (empty geometry)")
    a = np.ascontiguousarray(a, dtype=np.int64)
    if a.min() < 0 or a.max() >= V:
        bad = ((a < 0) | (a >= V)).any(axis=1)
        raise InputError(
            f"{where}{count_phrase(int(bad.sum()), 'triangles', 'index', 'indexes')} vertices outside [0, {V}) "
            f"(indices from {int(a.min())} to {int(a.max())})"
        )
    return a


def _attribute(x: Any, shape: tuple, where: str, name: str) -> np.ndarray:
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}{name} must be numeric with shape {shape}; got {type(x).__name__}") from exc
    if a.shape != shape:
        raise InputError(f"{where}{name} must have shape {shape}; got {a.shape}")
    if not np.isfinite(a).all():
        bad = ~np.isfinite(a).all(axis=1)
        raise InputError(f"{where}{name}: {count_phrase(int(bad.sum()), 'rows')} NaN or inf values")
    return a


def _colors(x: Any, n: int, where: str, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype == np.uint8:
        a = a / 255.0
    a = _attribute(a, (n, 3), where, name)
    if a.size and (a.min() < -_COLOR_SLACK or a.max() > 1 + _COLOR_SLACK):
        raise InputError(f"{where}{name} must lie in [0, 1]; got values from {a.min():.6g} to {a.max():.6g}")
    return np.clip(a, 0.0, 1.0)


def _texture(t: Any, where: str, i: int) -> np.ndarray:
    a = np.asarray(t)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1 or a.shape[2] not in (1, 3, 4):
        raise InputError(f"{where}texture {i} must have shape (H, W, C) with C in 1, 3, 4; got {a.shape}")
    if a.dtype == np.uint16:
        a = (a // 257).astype(np.uint8)
    elif a.dtype.kind == "f":
        a = np.round(np.clip(a, 0.0, 1.0) * 255).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise InputError(f"{where}texture {i} must be uint8; got {a.dtype}")
    return np.ascontiguousarray(a)


def _material_ids(x: Any, T: int, n_textures: int, where: str) -> np.ndarray:
    a = np.asarray(x)
    if a.shape != (T,) or not (a.dtype.kind in "iu" or a.size == 0):
        raise InputError(f"{where}triangle_material_ids must be integers with shape ({T},); got {a.dtype} {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.int64)
    high = max(n_textures, 1)
    if a.size and (a.min() < 0 or (n_textures and a.max() >= high)):
        raise InputError(
            f"{where}triangle_material_ids must lie in [0, {high}); got values from {a.min()} to {a.max()}"
        )
    return a


def _squeeze_channels(t: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(t[:, :, 0] if t.shape[2] == 1 else t)


def _normalise_materials(textures: list, ids: np.ndarray | None) -> tuple[list, np.ndarray | None]:
    """Keep the materials the triangles use; an image-less used material gets a white 1x1 texture."""
    # Open3D keeps textures upside down; kpd keeps them as in the file.
    images = [np.ascontiguousarray(t[::-1]) if t.ndim >= 2 and t.size else None for t in textures]
    if not any(t is not None for t in images):
        return [], None
    if ids is None or ids.size == 0:
        return [t for t in images if t is not None], None
    used, compact = np.unique(ids, return_inverse=True)
    kept = [images[u] if 0 <= u < len(images) else None for u in used]
    if not any(t is not None for t in kept):
        return [], None
    channels = next(t for t in kept if t is not None)
    channels = 1 if channels.ndim == 2 else channels.shape[2]
    white = np.full((1, 1, channels), 255, dtype=np.uint8)
    kept = [t if t is not None else white for t in kept]
    return kept, compact.reshape(-1).astype(np.int64)



# --- PointSet ------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class PointSet:
    """A point cloud with optional per-point normals and colours.

    Attributes
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64 or None
    colors : (N, 3) float64 in [0, 1] or None
    path : the file the points were read from, or None; used in error messages
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    path: str | None = None

    def __post_init__(self) -> None:
        where = _prefix(self.path, "points")
        self.points = _vertex_array(self.points, where, "points", "points")
        n = len(self.points)
        if self.normals is not None:
            self.normals = _attribute(self.normals, (n, 3), where, "normals")
        if self.colors is not None:
            self.colors = _colors(self.colors, n, where, "colors")

    def __len__(self) -> int:
        return len(self.points)

    def __repr__(self) -> str:
        extras = "".join(f", {n}" for n, v in (("normals", self.normals), ("colors", self.colors)) if v is not None)
        return f"PointSet({len(self.points)} points{extras}, path={self.path!r})"
