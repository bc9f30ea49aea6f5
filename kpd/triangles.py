"""Triangle geometry: cross products, areas, unit normals and area-weighted vertex normals.

One home for these so that sampling, metrics, scan cleaning, rig straightening and I/O compute them the same way.
Inputs are trusted (checked by the caller: :class:`kpd.mesh.Mesh` or a public function's own checks).
"""

from __future__ import annotations

import numpy as np

__all__ = ["cross", "areas", "unit_normals", "vertex_normals"]


def cross(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) float64: ``(b - a) x (c - a)`` per triangle; its length is twice the area, its direction the normal
    by the right-hand rule over the corner order.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int, indices into ``vertices``
    """
    a, b, c = (vertices[triangles[:, i]] for i in range(3))  # (T, 3) each
    return np.cross(b - a, c - a)


def areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) float64 triangle areas."""
    return 0.5 * np.linalg.norm(cross(vertices, triangles), axis=1)


def unit_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3) float64 unit normals; zero for a triangle without area."""
    n = cross(vertices, triangles)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
    """(V, 3) float64 area-weighted unit vertex normals; zero where undefined.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int
    groups : (V,) int or None; vertices of one group (copies of a position along a UV seam, say) share the normal
        summed over all their triangles. None: every vertex is its own group.
    """
    if groups is None:
        groups = np.arange(len(vertices))
    face = cross(vertices, triangles)  # (T, 3), length = 2 * area
    index = groups[triangles].reshape(-1)  # (3T,)
    n_groups = int(groups.max()) + 1
    summed = np.stack(
        [np.bincount(index, weights=np.repeat(face[:, k], 3), minlength=n_groups) for k in range(3)], axis=1
    )  # (G, 3)
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    summed = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return summed[groups]
