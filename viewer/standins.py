"""Stand-ins: lighter meshes the editor draws in place of a large one while a gesture is in progress, made of the
mesh's own vertices so that the stand-in of a deformed mesh is the deformed mesh's rows (no deformation of its own).

A mesh of more than :data:`COARSE_STAND_IN_TRIANGLES` triangles gets a coarse stand-in of at most that many
(:func:`coarse_stand_in`); one of more than :data:`STAND_IN_TRIANGLES` a fine stand-in that looks like it
(:func:`fine_stand_in`), which the editor draws while the whole mesh's frames take long
(:func:`kpd.viewer.scheduler.draws_stand_in`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from kpd._compiled import njit
from kpd.grouping import same_corners
from kpd.viewer.camera import box
from kpd.viewer.shaded import mean_rgb, textured

__all__ = ["COARSE_STAND_IN_TRIANGLES", "STAND_IN_TRIANGLES", "FINE_STAND_IN_CELLS", "coarse_stand_in",
           "fine_stand_in", "stand_in", "stand_in_colors", "image_maps"]

COARSE_STAND_IN_TRIANGLES = 50000  # larger meshes are drawn by a coarse stand-in while a gesture is in progress
STAND_IN_TRIANGLES = 10_000  # meshes drawing more triangles than this (up to the above) get a fine stand-in
FINE_STAND_IN_CELLS = 250  # the fine stand-in's grid: cells across the mesh's largest side


def coarse_stand_in(vertices: np.ndarray, triangles: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray] | None:
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
    scratch = _cluster_scratch(len(vertices), len(triangles))  # for every try: fresh memory costs as much as a try
    for _ in range(12):
        kept, faces = _clustered(vertices, triangles, lo, hi, size, scratch)
        if len(faces) <= limit:
            return kept, faces
        size *= 1.1 * math.sqrt(len(faces) / limit)
    return kept, faces[:limit]


def fine_stand_in(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A stand-in that looks like the mesh, for one of few vertices and many triangles (a CAD mesh: many of its
    triangles cover less than a pixel): :func:`coarse_stand_in`' clustering on a grid of
    :data:`FINE_STAND_IN_CELLS` cells across the mesh's largest side, which only collapses what is smaller than a
    cell: about half the triangles of a ShapeNet chair, and the same picture but for a fraction of a percent of its
    pixels. ``(kept, faces)`` as :func:`coarse_stand_in` gives them; None when it would keep more than three quarters
    of the triangles (nothing to gain)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if not len(triangles):
        return None
    lo, hi = box([vertices])
    extent = float((hi - lo).max()) or 1.0
    kept, faces = _clustered(vertices, triangles, lo, hi, extent / FINE_STAND_IN_CELLS)
    return (kept, faces) if 4 * len(faces) <= 3 * len(triangles) else None


def stand_in(vertices: np.ndarray, triangles: np.ndarray, *, fine: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """The editor's stand-in of a mesh drawing ``triangles``: a coarse one of at most :data:`COARSE_STAND_IN_TRIANGLES`
    triangles for a larger mesh (:func:`coarse_stand_in`), with ``fine`` a fine one for a mesh of more than
    :data:`STAND_IN_TRIANGLES` (:func:`fine_stand_in`), else None. A stand-in is drawn in per-vertex colours
    (:func:`stand_in_colors`): the editor asks for a fine one only for a mesh without a texture image
    (:func:`image_maps`), which would change colour while it is dragged."""
    if len(triangles) > COARSE_STAND_IN_TRIANGLES:
        return coarse_stand_in(vertices, triangles, COARSE_STAND_IN_TRIANGLES)
    if fine and len(triangles) > STAND_IN_TRIANGLES:
        return fine_stand_in(vertices, triangles)
    return None


def image_maps(mesh: Any) -> bool:
    """Whether ``mesh`` is drawn with a texture image (not only plain material colours, which kpd.io reads as 1x1
    images): its stand-ins, drawn in per-vertex colours, would change colour."""
    return textured(mesh) and any(t.shape[0] * t.shape[1] > 1 for t in mesh.textures)


def stand_in_colors(mesh: Any) -> np.ndarray | None:
    """(V, 3) float64 colours in [0, 1] for a stand-in of ``mesh``: its vertex colours, or of a mesh whose materials
    are plain colours each vertex's material colour (of the last triangle it is a corner of: a cell of a stand-in
    takes one of its vertices' colours); None for a mesh drawn in one colour."""
    if not textured(mesh):
        return None if mesh.vertex_colors is None else np.asarray(mesh.vertex_colors, dtype=np.float64)
    palette = np.array([mean_rgb(texture) / 255.0 for texture in mesh.textures])  # an image map's: its mean
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
