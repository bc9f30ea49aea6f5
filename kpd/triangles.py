"""Triangle geometry: cross products, areas, unit normals and area-weighted vertex normals.

One home for these so that sampling, metrics, scan cleaning, rig straightening and I/O compute them the same way.
Inputs are trusted (checked by the caller: :class:`kpd.mesh.Mesh` or a public function's own checks).
"""

from __future__ import annotations

import numpy as np

__all__ = ["cross", "areas", "unit_normals", "vertex_normals", "turned_normals"]


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


def turned_normals(old_vertices: np.ndarray, new_vertices: np.ndarray, triangles: np.ndarray,
                   corner_normals: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3) a file's normals turned with the surface around them, each keeping its length (OBJ ``vn``, glTF
    NORMAL).

    Each normal ``n`` is turned by the smallest rotation that takes the area-weighted normal of the faces whose
    corners use it, before the edit, to the same after the edit: a normal that was the faces' own (flat or smooth)
    becomes the new faces' own, and an artist's normal keeps its offset from the surface.

    Parameters
    ----------
    old_vertices, new_vertices : (V, 3) float64, the surface before and after an edit
    triangles : (T, 3) int
    corner_normals : (T, 3) int, the normal each triangle corner uses (-1: none)
    normals : (N, 3) float64, the normals as stored
    """
    used = corner_normals >= 0
    index = corner_normals[used]
    n = len(normals)

    def around(vertices: np.ndarray) -> np.ndarray:
        face = cross(vertices, triangles)  # (T, 3)
        per_corner = np.repeat(face[:, None, :], 3, axis=1)[used]  # (c, 3)
        out = np.stack([np.bincount(index, weights=per_corner[:, k], minlength=n) for k in range(3)],
                       axis=1).astype(np.float64)  # (n, 3); bincount of nothing is integer
        length = np.linalg.norm(out, axis=1, keepdims=True)
        return np.divide(out, length, out=np.zeros_like(out), where=length > 0)

    a, b = around(old_vertices), around(new_vertices)
    valid = (np.linalg.norm(a, axis=1) > 0) & (np.linalg.norm(b, axis=1) > 0)
    out = normals.copy()
    # Rodrigues with axis a x b: R v = v cos + (k x v) sin + k (k . v)(1 - cos), written without dividing by sin
    k = np.cross(a, b)  # |k| = sin
    c = np.einsum("ij,ij->i", a, b)
    v = normals
    kv = np.cross(k, v)
    kdotv = np.einsum("ij,ij->i", k, v)
    factor = np.divide(1.0, 1.0 + c, out=np.zeros_like(c), where=(1.0 + c) > 1e-12)
    turned = v * c[:, None] + kv + k * (kdotv * factor)[:, None]
    opposite = valid & ((1.0 + c) <= 1e-12)
    turned[opposite] = -v[opposite]
    out[valid] = turned[valid]
    return out  # a rotation: each normal keeps its length (some files store them scaled)
