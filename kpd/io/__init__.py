"""Read and write meshes, point clouds and keypoints; clear errors, atomic writes.

Formats
-------
=========================  ==========================================================================================
meshes                     ``.obj .ply .off .stl .gltf .glb``  (:func:`read_mesh`, :func:`write_mesh`)
point sets                 ``.ply .pcd .xyz .pts .npy .npz``, and any mesh format (its vertices) (:func:`read_points`,
                           :func:`write_points`)
keypoints                  ``.json`` (``{"keypoints": [[x, y, z], ...], ...}`` or a bare list) and ``.txt`` (rows
                           ``x y z`` or the authors' ``%03d x y z``) (:func:`read_keypoints`, :func:`write_keypoints`)
=========================  ==========================================================================================

Meshes and point clouds go through Open3D, with the checks Open3D leaves out: Open3D returns an empty or half-read
geometry with a console warning for a missing, broken or truncated file, and kpd raises
:class:`~kpd.errors.InputError` naming the file and the problem instead. glTF is written by kpd itself (Open3D 0.20
writes neither UVs nor textures to glTF and writes ``.glb`` files without their binary chunk).

Conventions
-----------
- ``Mesh.triangle_uvs`` has one row per triangle corner, ``(3T, 2)``, origin at the bottom left (OBJ convention).
  Textures are stored as they appear in the image file (top row first), so the nearest texel of ``(u, v)`` is
  ``texture[int((1 - v) * H), int(u * W)]``. (Open3D keeps its textures upside down in memory;
  :meth:`Mesh.from_open3d` and :meth:`Mesh.to_open3d` flip them.)
- ``triangle_material_ids`` index ``textures``. Reading compacts them to the materials the triangles use; a used
  material without an image gets a 1x1 white texture; a mesh without any texture image has ``textures == []`` and
  ``triangle_material_ids is None``.
- OBJ, STL and glTF are read by Assimp inside Open3D, which splits a vertex wherever its UV or normal differs between
  triangles (the banana scan: 7,866 ``v`` lines become 10,710 vertices) and orders vertices by first use in the face
  list. STL vertices are welded back by position (STL stores no shared vertices). OBJ faces must be triangles:
  Assimp would drop polygons silently, so kpd refuses them.
- Precision: PLY keeps float64, PCD and glTF float32, OBJ and OFF (written by Open3D) six significant digits, and
  the text formats kpd writes (``.xyz``, ``.pts``) nine significant digits (float32-exact).

Writes are atomic (:mod:`kpd.io.atomic`, the one writer every kpd output goes through): everything is written
under a temporary name in the target folder, fsynced, checked (Open3D's writers report a full disk only on stderr
and return success, so the file is re-read: PLY/PCD/OFF headers against the bytes that follow, OBJ vertex and face
counts, STL size, PNG end chunk) and renamed into place only when complete; a failed write raises
:class:`~kpd.errors.WriteError` and leaves nothing behind. Formats with companion files (OBJ: ``.mtl`` and one
``<name>_<i>.png`` per texture; ``.gltf``: the PNGs) are written under their final names into a temporary folder
first, then moved together.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import logging
import os
import re
import secrets
import shutil
import struct
import sys
import tempfile
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np

from kpd.errors import InputError, KpdError, WriteError
from kpd.io.atomic import Outputs, atomic_files, atomic_output, check_output, remove_stale_temporaries
from kpd.io.atomic import _check_target, disk_full  # noqa: F401  (kept importable from kpd.io)

if TYPE_CHECKING:  # pragma: no cover
    import open3d

__all__ = [
    "MESH_FORMATS",
    "POINT_FORMATS",
    "KEYPOINT_FORMATS",
    "Mesh",
    "PointSet",
    "read_mesh",
    "write_mesh",
    "read_points",
    "write_points",
    "read_shape",
    "atomic_output",
    "atomic_files",
    "Outputs",
    "check_output",
    "remove_stale_temporaries",
    "verify_png",
    "mesh_companions",
    "write_keypoints",
    "read_keypoints",
]

log = logging.getLogger(__name__)

MESH_FORMATS = (".obj", ".ply", ".off", ".stl", ".gltf", ".glb")
POINT_FORMATS = (".ply", ".pcd", ".xyz", ".pts", ".npy", ".npz")
KEYPOINT_FORMATS = (".json", ".txt")

# Colours may stray this far outside [0, 1] through float rounding before they count as malformed.
_COLOR_SLACK = 1e-6


def _open3d():
    """Open3D, imported on first use so that ``import kpd.io`` stays light."""
    import open3d

    return open3d


@contextlib.contextmanager
def _open3d_log() -> Iterator[list[str]]:
    """Run Open3D calls with their warnings captured instead of printed; yields the list of captured lines.

    Open3D's Python module prints its log through ``sys.stdout`` and reports most failures only there (a failed read
    returns an empty or half-filled geometry), so kpd reads that log to tell success from failure. Lines that are
    not Open3D's (another thread printing meanwhile) are passed on to stdout.
    """
    o3d = _open3d()
    lines: list[str] = []
    buffer = io.StringIO()
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Warning):
            with contextlib.redirect_stdout(buffer):
                yield lines
    finally:
        for s in _ANSI.sub("", buffer.getvalue()).splitlines():
            tag = next((t for t in ("[Open3D WARNING] ", "[Open3D ERROR] ") if s.startswith(t)), None)
            if tag:
                lines.append(s[len(tag):].strip())
            elif s.strip():
                sys.stdout.write(s + "\n")


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
# Open3D warnings that mean the geometry was not (fully) read or written. A texture image that cannot be loaded
# ("Read geometry::Image failed") is not one of them: kpd warns about missing textures itself.
_FAILURE = re.compile(r"fail|unable|error|cannot|could not|invalid", re.I)


def _failures(lines: list[str]) -> list[str]:
    failed = [s for s in lines if _FAILURE.search(s) and "geometry::Image" not in s]
    for s in lines:
        if s not in failed:
            log.debug("Open3D: %s", s)
    return list(dict.fromkeys(failed))


def _count(n: int, plural: str, verb: str = "have", singular_verb: str = "has") -> str:
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
    path: str | None = None

    def __post_init__(self) -> None:
        # Not a dataclass field: groups of vertices sharing a position and a normal (UV-seam copies), computed by
        # with_vertices on first use and handed on to the meshes it makes.
        self._normal_groups: np.ndarray | None = None
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
                self._normal_groups = _first_occurrence_groups(np.hstack([self.vertices, self.vertex_normals]))[1]
            normals = _vertex_normals(new, self.triangles, self._normal_groups)
        out = object.__new__(Mesh)  # every other field is already checked: skip __post_init__
        out.__dict__.update(self.__dict__)
        out.vertices = new
        out.vertex_normals = normals
        return out

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
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise InputError(f"{where}{_count(int(bad.sum()), noun)} NaN or inf coordinates (first: index {first})")
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
    bad = ((a < 0) | (a >= V)).any(axis=1)
    if bad.any():
        raise InputError(
            f"{where}{_count(int(bad.sum()), 'triangles', 'index', 'indexes')} vertices outside [0, {V}) "
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
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise InputError(f"{where}{name}: {_count(int(bad.sum()), 'rows')} NaN or inf values")
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


def _first_occurrence_groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique rows of ``keys`` (R, D) in order of first occurrence: (first index of each group, group of each row)."""
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse.reshape(-1)]


def _vertex_normals(vertices: np.ndarray, triangles: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, summed over each group of vertices; (V, 3) float64, zero where undefined."""
    corners = vertices[triangles]  # (T, 3, 3)
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # (T, 3), length = 2 * area
    index = groups[triangles].reshape(-1)  # (3T,)
    n_groups = int(groups.max()) + 1
    summed = np.stack(
        [np.bincount(index, weights=np.repeat(face[:, k], 3), minlength=n_groups) for k in range(3)], axis=1
    )  # (G, 3)
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    summed = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return summed[groups]


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


# --- reading -------------------------------------------------------------------------------------------------------


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh.

    Parameters
    ----------
    path : ``.obj``, ``.ply``, ``.off``, ``.stl``, ``.gltf`` or ``.glb``

    Returns
    -------
    Mesh
        With normals, colours, UVs, textures and material ids when the file has them.

    Raises
    ------
    InputError
        For a missing file, an unknown extension, an unreadable, truncated or empty file, a file without triangles,
        NaN or inf coordinates, or triangles that index missing vertices. A texture file that is missing is not an
        error: the mesh is read without it and a warning is logged.
    """
    p, ext = _input_path(path, MESH_FORMATS, "mesh")
    m = _read_open3d_mesh(p, ext)
    if len(m.triangles) == 0:
        raise InputError(
            f"{p}: has {len(m.vertices)} vertices but no triangles (a point cloud? use read_points or read_shape)"
        )
    return Mesh.from_open3d(m, path=os.fspath(path))


def read_points(path: str | os.PathLike, *, drop_nonfinite: bool = False) -> PointSet:
    """Read a point cloud, or the vertices of a mesh file.

    Parameters
    ----------
    path : ``.ply``, ``.pcd``, ``.xyz``, ``.pts``, ``.npy``, ``.npz`` or a mesh format (its vertices).
        ``.xyz``: whitespace-separated text, the first three columns are coordinates. ``.pts``: text with 3 or 6
        columns (xyz or xyz + normals, as in ShapeNetPart and the authors' demo); an optional first line holding
        only the point count is skipped. ``.npy``: an (N, 3) or (N, 6) (xyz + normals) array. ``.npz``: key
        ``points``, optional ``normals`` and ``colors``.
    drop_nonfinite : drop points whose coordinates or normals are NaN or inf (with a logged warning) instead of
        raising; for raw scans.

    Returns
    -------
    PointSet

    Raises
    ------
    InputError
        For a missing, unknown, unreadable, truncated or empty file, malformed rows or arrays, or non-finite points
        (unless ``drop_nonfinite``).
    """
    p, ext = _input_path(path, tuple(dict.fromkeys(POINT_FORMATS + MESH_FORMATS)), "point")
    name = os.fspath(path)
    points, normals, colors = _read_point_arrays(p, ext)
    if drop_nonfinite:
        bad = ~np.isfinite(points).all(axis=1)
        if normals is not None:
            bad |= ~np.isfinite(normals).all(axis=1)
        if bad.any():
            log.warning("%s: dropped %d of %d points with NaN or inf values", name, int(bad.sum()), len(points))
            keep = ~bad
            points = points[keep]
            normals = None if normals is None else normals[keep]
            colors = None if colors is None else colors[keep]
    return PointSet(points, normals, colors, path=name)


def read_shape(path: str | os.PathLike) -> Mesh | PointSet:
    """Read a file as a :class:`Mesh` if it has triangles, else as a :class:`PointSet`.

    Mesh formats (``.obj .off .stl .gltf .glb`` and ``.ply`` with faces) give a Mesh; ``.ply`` without faces and
    the point formats give a PointSet. Errors as in :func:`read_mesh` and :func:`read_points`.
    """
    p, ext = _input_path(path, tuple(dict.fromkeys(MESH_FORMATS + POINT_FORMATS)), "shape")
    if ext not in MESH_FORMATS:
        return read_points(path)
    m = _read_open3d_mesh(p, ext)
    if len(m.triangles) == 0:
        return PointSet(
            np.array(m.vertices, dtype=np.float64),
            np.array(m.vertex_normals, dtype=np.float64) if m.has_vertex_normals() else None,
            np.array(m.vertex_colors, dtype=np.float64) if m.has_vertex_colors() else None,
            path=os.fspath(path),
        )
    return Mesh.from_open3d(m, path=os.fspath(path))


def _input_path(path: str | os.PathLike, formats: tuple, kind: str) -> tuple[Path, str]:
    try:
        p = Path(path)
    except TypeError as exc:
        raise InputError(f"{kind} path must be a string or path; got {type(path).__name__}") from exc
    ext = p.suffix.lower()
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a {kind} file")
    if ext not in formats:
        raise InputError(
            f"{p}: unknown {kind} format {ext or '(no extension)'!r}; expected one of {' '.join(formats)}"
        )
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if not p.is_file():
        raise InputError(f"{p}: not a regular file")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: the file is empty (0 bytes)")
    return p, ext


def _read_open3d_mesh(p: Path, ext: str) -> "open3d.geometry.TriangleMesh":
    """Open3D's mesh for a mesh file, after kpd's own checks; vertices may lack triangles (a .ply point cloud)."""
    o3d = _open3d()
    obj_data = None
    if ext == ".ply":
        _check_ply_complete(p)
    elif ext == ".off":
        _check_off_complete(p)
    elif ext == ".obj":
        obj_data = p.read_bytes()
        _check_obj_faces(p, obj_data)
    with _open3d_log() as messages:
        m = o3d.io.read_triangle_mesh(str(p))
    failed = _failures(messages)
    if failed:
        raise InputError(f"{p}: could not be read as a mesh (Open3D: {'; '.join(failed)})")
    if len(m.vertices) == 0:
        raise InputError(f"{p}: no vertices (empty geometry)")
    if ext == ".stl":
        m = _weld_stl(m)
    elif ext == ".obj":
        _warn_missing_obj_textures(p, obj_data)
    elif ext in (".gltf", ".glb"):
        _fill_gltf_textures(p, m)
    return m


def _read_point_arrays(p: Path, ext: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Raw (unchecked) points, normals, colours of a point file."""
    if ext in (".ply", ".pcd"):
        o3d = _open3d()
        (_check_ply_complete if ext == ".ply" else _check_pcd_complete)(p)
        with _open3d_log() as messages:
            pc = o3d.io.read_point_cloud(str(p))
        failed = _failures(messages)
        if failed:
            raise InputError(f"{p}: could not be read as a point cloud (Open3D: {'; '.join(failed)})")
        if len(pc.points) == 0:
            raise InputError(f"{p}: no points (empty geometry)")
        return (
            np.array(pc.points, dtype=np.float64),
            np.array(pc.normals, dtype=np.float64) if pc.has_normals() else None,
            np.array(pc.colors, dtype=np.float64) if pc.has_colors() else None,
        )
    if ext in MESH_FORMATS:
        m = _read_open3d_mesh(p, ext)
        return (
            np.array(m.vertices, dtype=np.float64),
            np.array(m.vertex_normals, dtype=np.float64) if m.has_vertex_normals() else None,
            np.array(m.vertex_colors, dtype=np.float64) if m.has_vertex_colors() else None,
        )
    if ext == ".xyz":
        table = _read_table(p)
        if table.shape[1] < 3:
            raise InputError(f"{p}: rows must have at least 3 columns (x y z); got {table.shape[1]}")
        if table.shape[1] > 3:
            log.debug("%s: ignoring %d columns after x y z", p, table.shape[1] - 3)
        return table[:, :3], None, None
    if ext == ".pts":
        table = _read_table(p, count_header=True)
        if table.shape[1] not in (3, 6):
            raise InputError(f"{p}: rows must have 3 (x y z) or 6 (x y z nx ny nz) columns; got {table.shape[1]}")
        return table[:, :3], (table[:, 3:] if table.shape[1] == 6 else None), None
    if ext == ".npy":
        a = _load_numpy(p)
        if not isinstance(a, np.ndarray) or a.ndim != 2 or a.shape[1] not in (3, 6) or a.dtype.kind not in "iuf":
            raise InputError(f"{p}: expected a numeric (N, 3) or (N, 6) array; got {_describe(a)}")
        return a[:, :3].astype(np.float64), (a[:, 3:].astype(np.float64) if a.shape[1] == 6 else None), None
    # .npz
    z = _load_numpy(p)
    if not isinstance(z, dict):
        raise InputError(f"{p}: expected an .npz archive with the key 'points'; got a single {_describe(z)}")
    if "points" not in z:
        raise InputError(f"{p}: expected the key 'points'; found {sorted(z.keys()) or 'no arrays'}")
    arrays = {}
    for key in ("points", "normals", "colors"):
        if key in z:
            a = z[key]
            if a.ndim != 2 or a.shape[1] != 3 or a.dtype.kind not in "iuf":
                raise InputError(f"{p}: '{key}' must be a numeric (N, 3) array; got {_describe(a)}")
            arrays[key] = a
    colors = arrays.get("colors")
    return (
        arrays["points"].astype(np.float64),
        arrays["normals"].astype(np.float64) if "normals" in arrays else None,
        colors if colors is None or colors.dtype == np.uint8 else colors.astype(np.float64),
    )


def _load_numpy(p: Path):
    from kpd.io.integrity import load_numpy

    return load_numpy(p, "point file")


def _describe(a: Any) -> str:
    return f"{a.dtype} array of shape {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__


def _read_table(p: Path, *, count_header: bool = False) -> np.ndarray:
    """Whitespace-separated numbers, one row per line; '#' comments and blank lines are skipped."""
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not a text file ({exc.reason} at byte {exc.start})") from exc
    lines = [(i + 1, s) for i, s in enumerate(text.splitlines()) if s.strip() and not s.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{p}: no rows (empty geometry)")
    if count_header and len(lines[0][1].split()) == 1 and len(lines) > 1:
        declared = lines[0][1].strip()
        if not declared.isdigit() or int(declared) != len(lines) - 1:
            raise InputError(f"{p}: first line {declared!r} is not the row count {len(lines) - 1}")
        lines = lines[1:]
    rows = [s.split() for _, s in lines]
    ncol = len(rows[0])
    for (number, _), row in zip(lines, rows):
        if len(row) != ncol:
            raise InputError(f"{p}: line {number} has {len(row)} columns; line {lines[0][0]} has {ncol}")
    try:
        table = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"{p}: not a table of numbers ({exc})") from exc
    return table.reshape(len(lines), ncol)


# --- writing -------------------------------------------------------------------------------------------------------


def write_mesh(path: str | os.PathLike, mesh: Mesh) -> None:
    """Write a mesh atomically.

    Parameters
    ----------
    path : ``.obj`` (with ``<stem>.mtl`` and ``<stem>_<i>.png`` per texture when the mesh has UVs), ``.ply``
        (binary, float64), ``.off``, ``.stl`` (binary), ``.gltf`` (PNG textures beside it) or ``.glb``.
    mesh : Mesh

    Attributes the format cannot store (UVs and textures in PLY, OFF, STL; colours and normals in STL) are dropped
    with a logged warning.

    Raises
    ------
    InputError
        For an unknown extension or a missing target folder.
    KpdError
        If Open3D fails to write the file.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a kpd.io.Mesh; got {type(mesh).__name__}")
    p = _output_path(path, MESH_FORMATS, "mesh")
    ext = p.suffix.lower()
    dropped = [
        name
        for name, present, kept_in in (
            ("UVs and textures", mesh.triangle_uvs is not None or bool(mesh.textures), (".obj", ".gltf", ".glb")),
            ("vertex colors", mesh.vertex_colors is not None, (".obj", ".ply", ".off", ".gltf", ".glb")),
            ("vertex normals", mesh.vertex_normals is not None, (".obj", ".ply", ".off", ".gltf", ".glb")),
        )
        if present and ext not in kept_in
    ]
    if ext == ".obj" and mesh.textures and mesh.triangle_uvs is None:
        dropped.append("textures (the mesh has no UVs)")
    if dropped:
        log.warning("%s: %s cannot store %s; written without them", p, ext, " and ".join(dropped))
    if ext in (".gltf", ".glb"):
        if ext == ".gltf" and mesh.textures:
            with atomic_files(p) as target:
                _write_gltf(target, mesh, binary=False)
                for companion in target.parent.iterdir():
                    if companion != target:
                        _verify_companion(p.parent / companion.name, companion)
        else:
            with atomic_output(p) as target:
                _write_gltf(target, mesh, binary=ext == ".glb")
        return
    m = mesh.to_open3d()
    if ext == ".stl":
        m.compute_triangle_normals()
    if ext == ".obj":
        textured = mesh.triangle_uvs is not None
        with atomic_files(p) as target:
            _open3d_write(lambda: _open3d().io.write_triangle_mesh(str(target), m), p, target)
            expected = [target.with_suffix(".mtl")] if textured else []
            expected += [target.parent / f"{target.stem}_{i}.png" for i in range(len(mesh.textures) if textured else 0)]
            missing = [f.name for f in expected if not f.is_file()]
            if missing:
                raise WriteError(f"cannot write {p}: Open3D did not write {', '.join(missing)}")
            _verify_mesh_file(p, target, mesh, ext)
        return
    with atomic_output(p, verify=lambda tmp: _verify_mesh_file(p, tmp, mesh, ext)) as target:
        _open3d_write(lambda: _open3d().io.write_triangle_mesh(str(target), m), p, target)


def mesh_companions(path: str | os.PathLike, mesh: "Mesh") -> list[str]:
    """Names of the companion files :func:`write_mesh` adds beside ``path`` for ``mesh`` (OBJ: the ``.mtl`` and one
    PNG per texture when the mesh has UVs; ``.gltf``: the PNGs)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".obj" and mesh.triangle_uvs is not None:
        return [p.stem + ".mtl"] + [f"{p.stem}_{i}.png" for i in range(len(mesh.textures))]
    if ext == ".gltf" and mesh.textures and mesh.triangle_uvs is not None:
        return [f"{p.stem}_{i}.png" for i in range(len(mesh.textures))]
    return []


def write_points(
    path: str | os.PathLike,
    points: Any,
    normals: Any = None,
    colors: Any = None,
) -> None:
    """Write a point cloud atomically.

    Parameters
    ----------
    path : ``.ply`` (binary, float64), ``.pcd`` (binary, float32), ``.xyz`` (text x y z), ``.pts`` (text, 3 or 6
        columns), ``.npy`` ((N, 3), or (N, 6) with normals) or ``.npz`` (keys ``points``, ``normals``, ``colors``).
    points : (N, 3) array-like, or a :class:`PointSet` (then ``normals`` and ``colors`` come from it)
    normals : (N, 3) array-like or None
    colors : (N, 3) array-like in [0, 1] (or uint8) or None

    What the format cannot store (normals in ``.xyz``; colours in ``.xyz``, ``.pts``, ``.npy``) is dropped with a
    logged warning.
    """
    if isinstance(points, PointSet):
        if normals is not None or colors is not None:
            raise InputError("give normals and colors inside the PointSet, not as separate arguments")
        ps = points
    else:
        ps = PointSet(points, normals, colors)
    p = _output_path(path, POINT_FORMATS, "point")
    ext = p.suffix.lower()
    keeps = {".ply": ("normals", "colors"), ".pcd": ("normals", "colors"), ".npz": ("normals", "colors"),
             ".pts": ("normals",), ".npy": ("normals",), ".xyz": ()}[ext]
    dropped = [n for n in ("normals", "colors") if getattr(ps, n) is not None and n not in keeps]
    if dropped:
        log.warning("%s: %s cannot store %s; written without them", p, ext, " and ".join(dropped))
    normals_kept = ps.normals if "normals" in keeps else None
    with atomic_output(p, verify=lambda tmp: _verify_points_file(p, tmp, len(ps.points), ext)) as target:
        if ext in (".ply", ".pcd"):
            o3d = _open3d()
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ps.points))
            if ps.normals is not None:
                pc.normals = o3d.utility.Vector3dVector(ps.normals)
            if ps.colors is not None:
                pc.colors = o3d.utility.Vector3dVector(ps.colors)
            _open3d_write(lambda: o3d.io.write_point_cloud(str(target), pc), p, target)
        elif ext in (".xyz", ".pts"):
            table = ps.points if normals_kept is None else np.hstack([ps.points, normals_kept])
            np.savetxt(target, table, fmt="%.9g")
        elif ext == ".npy":
            np.save(target, ps.points if normals_kept is None else np.hstack([ps.points, normals_kept]))
        else:
            arrays = {"points": ps.points}
            arrays.update({k: getattr(ps, k) for k in ("normals", "colors") if getattr(ps, k) is not None})
            np.savez(target, **arrays)


def _output_path(path: str | os.PathLike, formats: tuple, kind: str) -> Path:
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in formats:
        raise InputError(f"{p}: unknown {kind} format {ext or '(no extension)'!r}; expected one of {' '.join(formats)}")
    return p


def _open3d_write(write: Callable[[], bool], p: Path, tmp: Path | None = None) -> None:
    """Run an Open3D writer and raise :class:`WriteError` if it failed, including the failures Open3D reports only
    in its log or on the C stderr ("RPly: Failed writing ...") while returning success."""
    with _open3d_log() as messages, _c_stderr() as c_lines:
        ok = write()
    failed = _failures(messages) + [s for s in c_lines if _FAILURE.search(s)]
    if not ok or failed:
        written = tmp if tmp is not None else p
        if disk_full(written.parent):
            raise WriteError(f"cannot write {p}: the disk is full (no space left on device)")
        raise WriteError(f"cannot write {p}: Open3D failed ({'; '.join(dict.fromkeys(failed)) or 'no reason given'})")


@contextlib.contextmanager
def _c_stderr() -> Iterator[list[str]]:
    """Capture what C code writes to file descriptor 2 (RPly's messages) while the block runs; yields the lines.
    Lines that are not about a failure are passed on to stderr."""
    lines: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
        sink = tempfile.TemporaryFile()
    except OSError:  # no descriptor or no room for the capture: run uncaptured
        yield lines
        return
    try:
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode("utf-8", errors="replace")
            lines.extend(s.strip() for s in _ANSI.sub("", text).splitlines() if s.strip())
            rest = [s for s in lines if not _FAILURE.search(s)]
            if rest:
                sys.stderr.write("\n".join(rest) + "\n")
    finally:
        sink.close()


def _incomplete(p: Path, detail: str) -> WriteError:
    cause = "the disk is full" if disk_full(p.parent) else "the writer stopped early"
    return WriteError(f"cannot write {p}: the written file is incomplete ({detail}; {cause})")


def _verify_mesh_file(p: Path, tmp: Path, mesh: "Mesh", ext: str) -> None:
    """Check a mesh file Open3D wrote: complete and holding what it was given (re-read header or counts)."""
    V, T = len(mesh.vertices), len(mesh.triangles)
    try:
        if ext == ".ply":
            _check_ply_complete(tmp)
            _check_header_counts(tmp, rb"element vertex (\d+)", V, rb"element face (\d+)", T)
        elif ext == ".off":
            _check_off_complete(tmp)
        elif ext == ".stl":
            size = tmp.stat().st_size
            if size != 84 + 50 * T:
                raise InputError(f"{size} bytes instead of {84 + 50 * T}")
        elif ext == ".obj":
            data = tmp.read_bytes()
            v, f = len(re.findall(rb"^v ", data, re.M)), len(re.findall(rb"^f ", data, re.M))
            if v != V or f != T or not data.endswith(b"\n"):
                raise InputError(f"{v} of {V} vertices and {f} of {T} faces")
            for companion in tmp.parent.iterdir():
                if companion != tmp:
                    _verify_companion(p.parent / companion.name, companion)
    except InputError as exc:
        raise _incomplete(p, str(exc).removeprefix(f"{tmp}: ")) from None


def _verify_companion(p: Path, tmp: Path) -> None:
    if tmp.stat().st_size == 0:
        raise _incomplete(p, "empty")
    if tmp.suffix.lower() == ".png":
        _verify_png(p, tmp)


def _verify_png(p: Path, tmp: Path) -> None:
    """A PNG ends with its IEND chunk; a file cut short by a full disk does not."""
    with open(tmp, "rb") as fh:
        head = fh.read(8)
        fh.seek(max(0, tmp.stat().st_size - 12))
        tail = fh.read()
    if head != b"\x89PNG\r\n\x1a\n" or not tail.endswith(b"IEND\xaeB`\x82"):
        raise _incomplete(p, "the PNG has no end chunk")


def _check_header_counts(tmp: Path, *pairs) -> None:
    with open(tmp, "rb") as fh:
        head = fh.read(1 << 14)
    for pattern, expected in zip(pairs[::2], pairs[1::2]):
        m = re.search(pattern, head)
        if m is None or int(m.group(1)) != expected:
            raise InputError(f"the header declares {m.group(1) if m else 'no'} of {expected} elements")


def _verify_points_file(p: Path, tmp: Path, n: int, ext: str) -> None:
    try:
        if ext == ".ply":
            _check_ply_complete(tmp)
            _check_header_counts(tmp, rb"element vertex (\d+)", n)
        elif ext == ".pcd":
            _check_pcd_complete(tmp)
            _check_header_counts(tmp, rb"POINTS (\d+)", n)
    except InputError as exc:
        raise _incomplete(p, str(exc).removeprefix(f"{tmp}: ")) from None


def verify_png(path: str | os.PathLike) -> None:
    """Raise :class:`WriteError` unless ``path`` is a complete PNG (use as ``atomic_output(..., verify=verify_png)``)."""
    _verify_png(Path(path), Path(path))



# --- keypoints -----------------------------------------------------------------------------------------------------


def write_keypoints(path: str | os.PathLike, keypoints: Any, **meta: Any) -> None:
    """Write keypoints atomically.

    Parameters
    ----------
    path : ``.json`` -> ``{"keypoints": [[x, y, z], ...], **meta}``; ``.txt`` -> the authors' rows ``%03d x y z``
        (no metadata).
    keypoints : (K, 3) array-like
    **meta : JSON-serialisable values (numpy arrays and scalars are converted), stored beside the keypoints.
    """
    p = _output_path(path, KEYPOINT_FORMATS, "keypoint")
    k = _vertex_array(keypoints, f"{p}: ", "keypoints", "keypoints")
    if p.suffix.lower() == ".txt":
        if meta:
            raise InputError(f"{p}: .txt keypoints cannot hold metadata ({', '.join(meta)}); use .json")
        text = "".join(f"{i:03d} {x!r} {y!r} {z!r}\n" for i, (x, y, z) in enumerate(k.tolist()))
    else:
        if "keypoints" in meta:
            raise InputError(f"{p}: 'keypoints' cannot also be a metadata key")
        try:
            text = json.dumps({"keypoints": k.tolist(), **meta}, indent=2, default=_json_default, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{p}: metadata is not JSON-serialisable ({exc})") from exc
    with atomic_output(p) as target:
        target.write_text(text + ("" if text.endswith("\n") else "\n"), encoding="utf-8")


def read_keypoints(path: str | os.PathLike) -> np.ndarray:
    """Read keypoints.

    Parameters
    ----------
    path : ``.json`` (``{"keypoints": [[x, y, z], ...], ...}`` or a bare list of triples) or ``.txt`` (rows
        ``x y z`` or ``%03d x y z``)

    Returns
    -------
    keypoints : (K, 3) float64
    """
    p, ext = _input_path(path, KEYPOINT_FORMATS, "keypoint")
    if ext == ".txt":
        table = _read_table(p)
        if table.shape[1] == 4:
            index = table[:, 0]
            if not np.array_equal(index, np.arange(len(table))):
                raise InputError(f"{p}: the first of 4 columns must count 0, 1, 2, ... (format '%03d x y z')")
            table = table[:, 1:]
        elif table.shape[1] != 3:
            raise InputError(f"{p}: rows must be 'x y z' or '%03d x y z'; got {table.shape[1]} columns")
        return _vertex_array(table, f"{p}: ", "keypoints", "keypoints")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: not valid JSON ({exc})") from exc
    if isinstance(data, dict):
        if "keypoints" not in data:
            raise InputError(f"{p}: expected the key 'keypoints'; found {sorted(data)}")
        data = data["keypoints"]
    return _vertex_array(data, f"{p}: ", "keypoints", "keypoints")


def _json_default(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"{type(x).__name__} is not JSON-serialisable")


# --- format-specific checks ----------------------------------------------------------------------------------------

_PLY_TYPE_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}


def _check_ply_complete(p: Path) -> None:
    """Raise if a PLY file holds less data than its header declares (Open3D returns a half-read cloud for that)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 20)
    if not re.match(rb"ply[ \t]*\r?\n", head):
        raise InputError(f"{p}: not a PLY file (it does not start with the line 'ply')")
    end = re.search(rb"^end_header[ \t]*\r?\n", head, re.M)
    if not end:
        raise InputError(f"{p}: not a PLY file (no 'end_header' line in the first MiB)")
    lines = head[: end.end()].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []
    for s in lines[1:]:
        tokens = s.split()
        if not tokens:
            continue
        if tokens[0] == "format" and len(tokens) >= 2:
            fmt = tokens[1]
        elif tokens[0] == "element" and len(tokens) == 3 and tokens[2].isdigit():
            elements.append([tokens[1], int(tokens[2]), 0])
        elif tokens[0] == "property" and elements:
            if len(tokens) == 5 and tokens[1] == "list":
                sizes = (_PLY_TYPE_SIZES.get(tokens[2]), _PLY_TYPE_SIZES.get(tokens[3]))
                if None in sizes:
                    return
                items = 3 if tokens[4] in ("vertex_indices", "vertex_index") else 0
                elements[-1][2] += sizes[0] + items * sizes[1]
            elif len(tokens) == 3 and tokens[1] in _PLY_TYPE_SIZES:
                elements[-1][2] += _PLY_TYPE_SIZES[tokens[1]]
            else:
                return
    declared = " and ".join(f"{count} {name!r}" for name, count, _ in elements) + " elements"
    data_size = p.stat().st_size - end.end()
    if fmt in ("binary_little_endian", "binary_big_endian"):
        need = sum(count * size for _, count, size in elements)
        if data_size < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {declared} (at least {need} bytes of data) "
                f"but {data_size} bytes follow"
            )
    elif fmt == "ascii":
        rows = _count_lines(p, end.end())
        need = sum(count for _, count, _ in elements)
        if rows < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {declared} ({need} rows) but {rows} rows follow"
            )


def _check_pcd_complete(p: Path) -> None:
    """Raise if a PCD file holds fewer points than its header declares (Open3D pads such files with zeros)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    end = re.search(rb"^DATA[ \t]+(\w+)[ \t]*\r?\n", head, re.M)
    if not end:
        return
    header = {}
    for s in head[: end.start()].decode("ascii", errors="replace").splitlines():
        tokens = s.split()
        if tokens and not tokens[0].startswith("#"):
            header[tokens[0].upper()] = tokens[1:]
    try:
        n = int(header["POINTS"][0])
        sizes = [int(x) for x in header["SIZE"]]
        counts = [int(x) for x in header.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError):
        return
    kind = end.group(1).decode()
    if kind == "binary":
        need = n * sum(s * c for s, c in zip(sizes, counts))
        have = p.stat().st_size - end.end()
        if have < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {n} points ({need} bytes) but {have} bytes follow"
            )
    elif kind == "ascii":
        rows = _count_lines(p, end.end())
        if rows < n:
            raise InputError(f"{p}: the file is truncated: its header declares {n} points but {rows} rows follow")


def _check_off_complete(p: Path) -> None:
    """Raise if a text OFF file has fewer rows than its header declares (Open3D keeps the vertices it got)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    header = re.match(rb"[ \t]*[A-Z]*OFF[ \t]*\r?\n(?:[ \t]*(?:#[^\n]*)?\n)*[ \t]*(\d+)[ \t]+(\d+)[^\n]*\n", head)
    if not header:
        return  # binary OFF, counts on the first line, or not OFF at all: Open3D decides
    n_vertices, n_faces = int(header.group(1)), int(header.group(2))
    rows = _count_lines(p, header.end())
    if rows < n_vertices + n_faces:
        raise InputError(
            f"{p}: the file is truncated: its header declares {n_vertices} vertices and {n_faces} faces "
            f"({n_vertices + n_faces} rows) but {rows} rows follow"
        )


def _count_lines(p: Path, start: int) -> int:
    """Number of lines from byte ``start`` on (a last line without a newline counts)."""
    count, last = 0, b"\n"
    with open(p, "rb") as fh:
        fh.seek(start)
        while chunk := fh.read(1 << 22):
            count += chunk.count(b"\n")
            last = chunk[-1:]
    return count + (last != b"\n")


_OBJ_POLYGON = re.compile(rb"^[ \t]*f[ \t]+\S+[ \t]+\S+[ \t]+\S+[ \t]+[^\s#]", re.M)
_OBJ_SHORT_FACE = re.compile(rb"^[ \t]*f(?:[ \t]+[^\s#]+){0,2}[ \t]*(?:#.*)?\r?$", re.M)


def _check_obj_faces(p: Path, data: bytes) -> None:
    """Refuse OBJ faces that are not triangles: Assimp (inside Open3D) drops such faces and their objects silently."""
    polygons = len(_OBJ_POLYGON.findall(data))
    if polygons:
        raise InputError(
            f"{p}: {_count(polygons, 'faces')} more than 3 vertices; kpd reads triangle meshes only "
            "(triangulate it first, e.g. Blender: Triangulate Faces)"
        )
    short = len(_OBJ_SHORT_FACE.findall(data))
    if short:
        raise InputError(f"{p}: {_count(short, 'faces')} fewer than 3 vertices")


def _warn_missing_obj_textures(p: Path, data: bytes) -> None:
    folder = p.parent
    for match in re.finditer(rb"^[ \t]*mtllib[ \t]+(.+?)[ \t]*\r?$", data, re.M):
        name = match.group(1).decode("utf-8", errors="replace")
        mtl = folder / name
        if not mtl.is_file():
            log.warning("%s: material library %r is missing; read without materials and textures", p, name)
            continue
        mtl_data = mtl.read_bytes()
        missing = []
        for tex in re.finditer(rb"^[ \t]*map_Kd[ \t]+(.+?)[ \t]*\r?$", mtl_data, re.M):
            tex_name = tex.group(1).split()[-1].decode("utf-8", errors="replace").replace("\\", "/")
            if not (folder / tex_name).is_file() and not (folder / Path(tex_name).name).is_file():
                missing.append(tex_name)
        if missing:
            log.warning(
                "%s: texture file(s) %s named in %s are missing; read without them",
                p, ", ".join(dict.fromkeys(missing)), name,
            )


def _weld_stl(m: "open3d.geometry.TriangleMesh") -> "open3d.geometry.TriangleMesh":
    """STL has no shared vertices (Assimp keeps one per distinct facet normal): merge equal positions, drop the
    facet normals."""
    o3d = _open3d()
    vertices = np.asarray(m.vertices)
    first, group = _first_occurrence_groups(vertices)
    out = o3d.geometry.TriangleMesh()
    out.vertices = o3d.utility.Vector3dVector(vertices[first])
    out.triangles = o3d.utility.Vector3iVector(group[np.asarray(m.triangles)].astype(np.int32))
    return out


# --- glTF ----------------------------------------------------------------------------------------------------------

_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
_FLOAT, _UINT = 5126, 5125


def _write_gltf(target: Path, mesh: Mesh, *, binary: bool) -> None:
    """Write glTF 2.0: one primitive per material, vertices split where UVs differ, PNG textures (embedded in .glb,
    beside a .gltf)."""
    blob = bytearray()
    views: list[dict] = []
    accessors: list[dict] = []

    def add_view(data: bytes, target_kind: int | None = None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        view = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)}
        if target_kind:
            view["target"] = target_kind
        blob.extend(data)
        views.append(view)
        return len(views) - 1

    def add_accessor(a: np.ndarray, kind: str, component: int, target_kind: int, bounds: bool = False) -> int:
        acc = {"bufferView": add_view(a.tobytes(), target_kind), "componentType": component, "count": len(a)}
        acc["type"] = kind
        if bounds:
            acc["min"], acc["max"] = a.min(axis=0).tolist(), a.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    textured = bool(mesh.textures) and mesh.triangle_uvs is not None
    ids = mesh.triangle_material_ids
    if textured and ids is None:
        ids = np.zeros(len(mesh.triangles), dtype=np.int64)
    groups = [(int(u), np.flatnonzero(ids == u)) for u in np.unique(ids)] if textured else [(None, None)]
    primitives = []
    for material, rows in groups:
        tri = mesh.triangles if rows is None else mesh.triangles[rows]  # (t, 3)
        corner_vertex = tri.reshape(-1)  # (3t,)
        if mesh.triangle_uvs is not None:
            uv = mesh.triangle_uvs.reshape(-1, 3, 2)
            corner_uv = (uv if rows is None else uv[rows]).reshape(-1, 2)  # (3t, 2)
            first, index = _first_occurrence_groups(np.hstack([corner_vertex[:, None], corner_uv]))
        else:
            corner_uv = None
            first, index = _first_occurrence_groups(corner_vertex[:, None])
        source = corner_vertex[first]  # (n,) vertex of each written vertex
        attributes = {
            "POSITION": add_accessor(mesh.vertices[source].astype(np.float32), "VEC3", _FLOAT, 34962, bounds=True)
        }
        if mesh.vertex_normals is not None:
            attributes["NORMAL"] = add_accessor(mesh.vertex_normals[source].astype(np.float32), "VEC3", _FLOAT, 34962)
        if mesh.vertex_colors is not None:
            attributes["COLOR_0"] = add_accessor(mesh.vertex_colors[source].astype(np.float32), "VEC3", _FLOAT, 34962)
        if corner_uv is not None:
            st = corner_uv[first] * [1.0, -1.0] + [0.0, 1.0]  # glTF puts the UV origin at the top left
            attributes["TEXCOORD_0"] = add_accessor(st.astype(np.float32), "VEC2", _FLOAT, 34962)
        indices = add_accessor(index.astype(np.uint32), "SCALAR", _UINT, 34963)
        primitive = {"attributes": attributes, "indices": indices, "mode": 4}  # mode 4: triangles
        if material is not None:
            primitive["material"] = material
        primitives.append(primitive)

    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "kpd"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": primitives}],
    }
    if textured:
        images = []
        for i, texture in enumerate(mesh.textures):
            png = _png_bytes(texture)
            if binary:
                images.append({"bufferView": add_view(png), "mimeType": "image/png"})
            else:
                name = f"{target.stem}_{i}.png"
                (target.parent / name).write_bytes(png)
                images.append({"uri": urllib.parse.quote(name)})
        doc["images"] = images
        doc["textures"] = [{"source": i} for i in range(len(images))]
        doc["materials"] = [
            {
                "name": f"{target.stem}_{i}",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": i}, "metallicFactor": 0.0, "roughnessFactor": 1.0
                },
            }
            for i in range(len(images))
        ]
    blob.extend(b"\0" * (-len(blob) % 4))
    doc["bufferViews"] = views
    doc["accessors"] = accessors
    buffer: dict[str, Any] = {"byteLength": len(blob)}
    if binary:
        doc["buffers"] = [buffer]
        text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        text += b" " * (-len(text) % 4)
        out = struct.pack("<III", _GLB_MAGIC, 2, 12 + 8 + len(text) + 8 + len(blob))
        out += struct.pack("<II", len(text), _GLB_JSON) + text + struct.pack("<II", len(blob), _GLB_BIN) + bytes(blob)
        target.write_bytes(out)
    else:
        buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode("ascii")
        doc["buffers"] = [buffer]
        target.write_text(json.dumps(doc, indent=1), encoding="utf-8")


def _png_bytes(texture: np.ndarray) -> bytes:
    o3d = _open3d()
    with tempfile.TemporaryDirectory() as folder:
        f = Path(folder) / "texture.png"
        _open3d_write(lambda: o3d.io.write_image(str(f), o3d.geometry.Image(_squeeze_channels(texture))), f)
        return f.read_bytes()


def _fill_gltf_textures(p: Path, m: "open3d.geometry.TriangleMesh") -> None:
    """Load the base-colour images that Open3D leaves out (images inside a .glb or a data URI); warn for missing
    ones. Open3D's texture i belongs to glTF material i."""
    try:
        doc, chunk = _read_gltf_json(p)
    except (ValueError, KeyError, struct.error, UnicodeDecodeError) as exc:
        log.warning("%s: could not inspect the glTF materials (%s); textures may be missing", p, exc)
        return
    o3d = _open3d()
    textures = list(m.textures)
    changed = False
    for i, material in enumerate(doc.get("materials", [])):
        ref = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if ref is None or (i < len(textures) and not textures[i].is_empty()):
            continue
        try:
            image = doc["images"][doc["textures"][ref["index"]]["source"]]
            image_array = _gltf_image(p, doc, chunk, image)
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            log.warning("%s: the texture of material %d cannot be read (%s); read without it", p, i, exc)
            continue
        if image_array is None:
            continue
        while len(textures) <= i:
            textures.append(o3d.geometry.Image())
        textures[i] = o3d.geometry.Image(np.ascontiguousarray(image_array[::-1]))  # Open3D's flipped convention
        changed = True
    if changed:
        m.textures = textures


def _read_gltf_json(p: Path) -> tuple[dict, bytes | None]:
    data = p.read_bytes()
    if p.suffix.lower() != ".glb":
        return json.loads(data.decode("utf-8")), None
    magic, _, _ = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC:
        raise ValueError("not a binary glTF file")
    doc, chunk, offset = None, None, 12
    while offset + 8 <= len(data):
        length, kind = struct.unpack_from("<II", data, offset)
        body = data[offset + 8 : offset + 8 + length]
        if kind == _GLB_JSON:
            doc = json.loads(body.decode("utf-8"))
        elif kind == _GLB_BIN:
            chunk = body
        offset += 8 + length
    if doc is None:
        raise ValueError("no JSON chunk")
    return doc, chunk


def _gltf_image(p: Path, doc: dict, chunk: bytes | None, image: dict) -> np.ndarray | None:
    """Decode one glTF image; None (with a warning) when its file is missing."""
    if "bufferView" in image:
        view = doc["bufferViews"][image["bufferView"]]
        buffer = doc["buffers"][view["buffer"]]
        data = _gltf_uri_bytes(p, buffer["uri"]) if "uri" in buffer else chunk
        if data is None:
            return None
        start = view.get("byteOffset", 0)
        raw = data[start : start + view["byteLength"]]
        suffix = ".jpg" if image.get("mimeType") == "image/jpeg" else ".png"
    else:
        raw = _gltf_uri_bytes(p, image["uri"])
        if raw is None:
            return None
        jpeg = image["uri"].lower().endswith((".jpg", ".jpeg")) or image["uri"].startswith("data:image/jpeg")
        suffix = ".jpg" if jpeg else ".png"
    o3d = _open3d()
    with tempfile.TemporaryDirectory() as folder:
        f = Path(folder) / f"texture{suffix}"
        f.write_bytes(raw)
        with _open3d_log():
            decoded = np.asarray(o3d.io.read_image(str(f)))
    if not decoded.size:
        raise ValueError("the image data cannot be decoded")
    return decoded.copy()


def _gltf_uri_bytes(p: Path, uri: str) -> bytes | None:
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    f = p.parent / urllib.parse.unquote(uri)
    if not f.is_file():
        log.warning("%s: texture file %r is missing; read without it", p, uri)
        return None
    return f.read_bytes()
