"""STL: binary files read by numpy, ASCII ones by Open3D; either way the corners are welded back into one vertex per
position (STL stores no shared vertices).

A binary STL is an 80-byte header, a uint32 count n and n records of 50 bytes (a facet normal and three corners, 12
float32, then a uint16 attribute). Open3D's reader (Assimp) takes a file for binary exactly when its size is
84 + 50 n, whatever its header says (many exporters start a binary header with ``solid``), else for ASCII when it
starts with ``solid``; :func:`read` decides the same way, except that a file of another size with a NUL byte in its
first 84 bytes is a damaged binary STL, refused with the size its header declares, not handed on as text.

Open3D keeps one vertex per distinct (position, facet normal, colour) in the order the corners first use them, in
float64, and :func:`weld` merges those that share a position. :func:`read` gives the same vertices and triangles to
the bit (``tests/test_io_stl.py`` compares the two on real meshes): the distinct corner positions, equal as numbers,
in the order the corners first use them, each as its first corner holds it (``-0.0`` included), converted exactly to
float64, with degenerate triangles kept as Open3D keeps them.

Reading through numpy takes a fraction of Open3D's time and memory at scan sizes, most of it the weld of the
float32 corners in :func:`kpd.grouping.first_occurrence_groups`'s hash table (figures in ``docs/formats.md``).

:func:`write` writes a binary STL through numpy, in the bytes Open3D's ``compute_triangle_normals`` and
``write_triangle_mesh`` give (``tests/test_io_stl.py`` compares them on real and random meshes), in blocks, so
that writing takes no more memory than reading.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kpd.errors import InputError
from kpd.grouping import first_occurrence_groups
from kpd.io.capture import open3d_module

if TYPE_CHECKING:  # pragma: no cover
    import open3d

__all__ = ["read", "to_open3d", "weld", "write"]

_RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])  # 50 bytes
_HEADER = b"Created by Open3D".ljust(80, b"\0")
_BLOCK = 1 << 16  # triangles per block written


def read(p: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The welded mesh of a binary STL, or None for an ASCII STL (Open3D reads those).

    Returns
    -------
    vertices : (V, 3) float64, the distinct corner positions in the order the corners first use them
    triangles : (T, 3) int64, into ``vertices``, in the file's order

    Raises
    ------
    InputError
        For a binary STL whose size is not the 84 + 50 n bytes its count n declares (truncated, or with bytes after
        its records), that declares no triangles, or a file too short to be either kind. Non-finite coordinates are
        left to :class:`~kpd.mesh.Mesh` to refuse, as they were after Open3D's reader.
    """
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(84)
    count = int.from_bytes(head[80:84], "little") if len(head) == 84 else None
    if count is not None and size == 84 + 50 * count:
        if count == 0:
            raise InputError(f"{p}: no triangles (a binary STL whose header declares 0)")
        corners = np.fromfile(p, dtype=_RECORD, count=count, offset=84)["corners"]  # (n, 3, 3) float32
        if len(corners) != count:  # shortened since its size was read
            raise InputError(f"{p}: the file is truncated: its header declares {count} triangles but "
                             f"{len(corners)} follow")
        corners = corners.reshape(-1, 3)  # (3n, 3), copied out of the records
        first, group = first_occurrence_groups(corners)
        return corners[first].astype(np.float64), group.reshape(-1, 3)
    if head.lstrip(b" \t").startswith(b"solid") and b"\0" not in head:
        return None
    if count is None:
        raise InputError(f"{p}: not an STL file: {size} bytes, fewer than a binary STL's 84-byte header, and not "
                         "ASCII STL text (which starts with 'solid')")
    need = 84 + 50 * count
    damage = "is truncated: its header declares" if size < need else "is longer than its header declares:"
    raise InputError(f"{p}: the file {damage} {count} triangles ({need} bytes) but the file has {size} bytes")


def write(p: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Write ``vertices`` (V, 3) float64 and ``triangles`` (T, 3) to ``p`` as a binary STL, the bytes Open3D's
    ``compute_triangle_normals`` then ``write_triangle_mesh`` give: the header ``Created by Open3D``, then per
    triangle its unit normal and its corners as float32 and a zero attribute, in blocks of ``_BLOCK`` triangles.

    The normal is Eigen's, in float64: the cross product of ``v1 - v0`` and ``v2 - v0`` divided by the square root of
    ``(x² + y²) + z²`` where that is positive (a degenerate triangle keeps its zero cross product, signed zeros
    included); one whose ``x`` is then NaN (after an overflow) becomes ``(0, 0, 1)``.
    """
    records = np.zeros(min(len(triangles), _BLOCK), dtype=_RECORD)
    with open(p, "wb") as fh, np.errstate(over="ignore", invalid="ignore"):
        fh.write(_HEADER + len(triangles).to_bytes(4, "little"))
        for start in range(0, len(triangles), _BLOCK):
            corners = np.take(vertices, triangles[start:start + _BLOCK], axis=0)  # (n, 3, 3)
            out = records[:len(corners)]
            out["corners"] = corners
            c = corners.transpose(1, 2, 0)  # (corner, axis, n)
            a, b = np.subtract(c[1], c[0], order="C"), np.subtract(c[2], c[0], order="C")  # (3, n)
            normal = np.empty_like(a)
            for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
                np.subtract(a[j] * b[k], a[k] * b[j], out=normal[i])
            z = normal[0] * normal[0]
            z += normal[1] * normal[1]
            z += normal[2] * normal[2]
            normal /= np.sqrt(z, out=np.ones_like(z), where=z > 0)
            normal[:, np.isnan(normal[0])] = [[0.0], [0.0], [1.0]]
            out["normal"] = normal.T
            out.tofile(fh)


def to_open3d(vertices: np.ndarray, triangles: np.ndarray) -> "open3d.geometry.TriangleMesh":
    """An Open3D mesh of ``vertices`` (V, 3) and ``triangles`` (T, 3), nothing else."""
    o3d = open3d_module()
    out = o3d.geometry.TriangleMesh()
    out.vertices = o3d.utility.Vector3dVector(vertices)
    out.triangles = o3d.utility.Vector3iVector(np.asarray(triangles).astype(np.int32))
    return out


def weld(m: "open3d.geometry.TriangleMesh") -> "open3d.geometry.TriangleMesh":
    """STL has no shared vertices (Assimp keeps one per distinct facet normal): merge equal positions, drop the
    facet normals."""
    vertices = np.asarray(m.vertices)
    first, group = first_occurrence_groups(vertices)
    return to_open3d(vertices[first], group[np.asarray(m.triangles)])
