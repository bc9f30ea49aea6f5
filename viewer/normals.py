"""Shading: the vertex normals a mesh is lit by, and the lights fixed to the camera.

Normals are recomputed after every edit, from welded positions (unwelded copies of a vertex shade alike) and with each
triangle turned towards the camera before averaging (two-sided lighting), so that the double-sided and flipped
triangles of CAD meshes shade cleanly instead of in black and white blotches. :class:`ShadingNormals` computes the
sums of :func:`shading_normals` again and again for one set of triangles, on two threads.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from kpd._compiled import njit
from kpd.viewer.threads import in_halves

__all__ = ["Welding", "shading_normals", "ShadingNormals", "camera_lights", "shade"]


class Welding:
    """Vertices grouped by position (``inverse`` (V,): the group of each vertex; ``groups``: how many)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray | None = None, *,
                 grouped: tuple[np.ndarray, np.ndarray] | None = None) -> None:  # triangles: not needed
        from kpd.grouping import first_occurrence_groups

        # groups numbered in order of first occurrence, found through a hash table (a sort took 5x as long);
        # ``grouped``: that result already at hand (a mesh's own, kpd.mesh.Mesh.position_groups)
        first, self.inverse = grouped or first_occurrence_groups(np.asarray(vertices, dtype=np.float64))
        self.groups = len(first)


def shading_normals(vertices: np.ndarray, triangles: np.ndarray, eye: np.ndarray | None = None, *,
                    welding: Welding | None = None) -> np.ndarray:
    """(V, 3) float32 unit vertex normals for drawing.

    Each vertex's normal is the sum of its position's triangles' ``(b - a) x (c - a)`` (area-weighted), in one
    compiled pass over the triangles (a few tens of milliseconds per million triangles). :class:`ShadedMesh` computes
    the same sums, bit for bit, on two threads (:class:`ShadingNormals`).

    Parameters
    ----------
    vertices : (V, 3) float64.
    triangles : (T, 3) int64.
    eye : (3,) the camera position: each triangle's normal is turned towards it before averaging (two-sided lighting),
        so a surface shades the same whichever way its triangles wind. None keeps the winding.
    welding : the vertex groups of these triangles (computed when not given): vertices at one position share a normal.
    """
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    welding = welding or Welding(vertices)
    out = np.empty((len(vertices), 3), dtype=np.float32)
    if not len(vertices):
        return out
    eye_point = np.zeros(3) if eye is None else np.asarray(eye, dtype=np.float64).reshape(3)
    _welded_normals(vertices, triangles, welding.inverse, welding.groups, eye_point, eye is not None, out)
    return out


@njit(nogil=True, error_model="numpy", inline="always")
def _turned_normal(vertices, a, b, c, eye, towards):  # pragma: no cover - compiled
    """A triangle's ``(b - a) x (c - a)``, turned towards ``eye`` when ``towards`` (two-sided lighting)."""
    ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
    ux, uy, uz = vertices[b, 0] - ax, vertices[b, 1] - ay, vertices[b, 2] - az
    vx, vy, vz = vertices[c, 0] - ax, vertices[c, 1] - ay, vertices[c, 2] - az
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    if towards and nx * (eye[0] - ax) + ny * (eye[1] - ay) + nz * (eye[2] - az) < 0:
        return -nx, -ny, -nz  # the eye is on the other side of the triangle's plane
    return nx, ny, nz


@njit(nogil=True, error_model="numpy")
def _welded_normals(vertices, triangles, inverse, groups, eye, towards, out):  # pragma: no cover - compiled
    acc = np.zeros((groups, 3))
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        nx, ny, nz = _turned_normal(vertices, a, b, c, eye, towards)
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


class ShadingNormals:
    """:func:`shading_normals` of one set of triangles, for new positions again and again: each triangle's turned
    ``(b - a) x (c - a)`` on two threads, then each position's sum over its triangles' corners, listed once in the
    serial kernel's order (so the sums are its own, bit for bit), on two threads.

    Parameters
    ----------
    triangles : (T, 3) int64.
    welding : the vertices' groups by position.
    """

    def __init__(self, triangles: np.ndarray, welding: Welding) -> None:
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        self.welding = welding
        self.starts = np.zeros(welding.groups + 1, dtype=np.int64)  # (G + 1,) each group's corners in ``entries``
        self.entries = np.empty(3 * len(self.triangles), dtype=np.int32)  # (3T,) the triangle of each corner, grouped
        _corner_lists(self.triangles, welding.inverse, self.starts, self.entries)
        self._face = np.empty((len(self.triangles), 3))  # (T, 3)
        self._groups = np.empty((welding.groups, 3), dtype=np.float32)  # (G, 3)

    def __call__(self, vertices: np.ndarray, eye: np.ndarray | None) -> np.ndarray:
        """(G, 3) float32 unit normal of each position (index it with ``welding.inverse`` for the vertices')."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        eye_point = np.zeros(3) if eye is None else np.asarray(eye, dtype=np.float64).reshape(3)
        in_halves(_turned_faces, len(self.triangles), vertices, self.triangles, eye_point, eye is not None, self._face)
        in_halves(_summed_groups, len(self._groups), self._face, self.starts, self.entries, self._groups)
        return self._groups

    def of(self, vertices: np.ndarray, eye: np.ndarray | None, used: np.ndarray) -> np.ndarray:
        """(n, 3) float32: ``self(vertices, eye)[welding.inverse[used]]``, bit for bit, summed for the vertices
        ``used`` (n,) alone (a frame of a large mesh shows a third of its vertices or fewer)."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        eye_point = np.zeros(3) if eye is None else np.asarray(eye, dtype=np.float64).reshape(3)
        in_halves(_turned_faces, len(self.triangles), vertices, self.triangles, eye_point, eye is not None, self._face)
        out = np.empty((len(used), 3), dtype=np.float32)
        in_halves(_summed_used, len(used), self._face, self.starts, self.entries, self.welding.inverse, used, out)
        return out


@njit(nogil=True)
def _corner_lists(triangles, inverse, starts, entries):  # pragma: no cover - compiled
    """Counting sort of the triangles' corners by their vertex's group: ``entries[starts[g]:starts[g + 1]]`` are the
    triangles of group g's corners in corner order (a triangle twice if two of its corners are in g)."""
    for t in range(triangles.shape[0]):
        for k in range(3):
            starts[inverse[triangles[t, k]] + 1] += 1
    for g in range(1, starts.shape[0]):
        starts[g] += starts[g - 1]
    fill = starts[:-1].copy()
    for t in range(triangles.shape[0]):
        for k in range(3):
            g = inverse[triangles[t, k]]
            entries[fill[g]] = t
            fill[g] += 1


@njit(nogil=True, error_model="numpy")
def _turned_faces(lo, hi, vertices, triangles, eye, towards, out):  # pragma: no cover - compiled
    for t in range(lo, hi):
        nx, ny, nz = _turned_normal(vertices, triangles[t, 0], triangles[t, 1], triangles[t, 2], eye, towards)
        out[t, 0] = nx
        out[t, 1] = ny
        out[t, 2] = nz


@njit(nogil=True, error_model="numpy", inline="always")
def _group_normal(g, face, starts, entries, out, n):  # pragma: no cover - compiled
    """``out[n]``: the unit sum of group ``g``'s face vectors (zero when they cancel)."""
    x = y = z = 0.0
    for i in range(starts[g], starts[g + 1]):
        t = entries[i]
        x += face[t, 0]
        y += face[t, 1]
        z += face[t, 2]
    length = np.sqrt(x ** 2 + y ** 2 + z ** 2)
    if length == 0.0:
        length = 1.0
    out[n, 0] = x / length
    out[n, 1] = y / length
    out[n, 2] = z / length


@njit(nogil=True, error_model="numpy")
def _summed_groups(lo, hi, face, starts, entries, out):  # pragma: no cover - compiled
    for g in range(lo, hi):
        _group_normal(g, face, starts, entries, out, g)


@njit(nogil=True, error_model="numpy")
def _summed_used(lo, hi, face, starts, entries, inverse, used, out):  # pragma: no cover - compiled
    """:func:`_summed_groups` of the groups of the vertices ``used[lo:hi]``, into ``out[lo:hi]``."""
    for n in range(lo, hi):
        _group_normal(inverse[used[n]], face, starts, entries, out, n)


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
    """(N, 3) colours in [0, 1]: ``albedo`` (N, 3) or (3,) lit by :func:`camera_lights` (ambient + Lambert) at
    ``normals`` (N, 3).

    The renderer draws unlit (Open3D's legacy lights saturate on surfaces facing the camera and cannot be set from
    Python), so shading is computed here, the same for every picture and the editor."""
    lights = camera_lights(camera).astype(np.float32)
    lambert = np.einsum("ij,kj->ik", np.asarray(normals, dtype=np.float32), lights)  # (N, 2); no BLAS threads
    np.maximum(lambert, 0.0, out=lambert)
    light = 0.38 + 0.52 * lambert[:, 0] + 0.22 * lambert[:, 1]  # (N,), at most 1.12
    colors = np.asarray(albedo, dtype=np.float32) * light[:, None]
    return np.minimum(colors, 1.0, out=colors)
