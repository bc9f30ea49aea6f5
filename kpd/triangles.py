"""Triangle geometry: cross products, areas, unit normals and area-weighted vertex normals.

One home for these so that sampling, metrics, scan cleaning, rig straightening and I/O compute them the same way.
Inputs are trusted (checked by the caller: :class:`kpd.mesh.Mesh` or a public function's own checks).
"""

from __future__ import annotations

import numpy as np

from kpd._compiled import compiled_on_first_call

__all__ = ["cross", "areas", "unit_normals", "vertex_normals", "turned_normals", "turned_over"]


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
    slots = triangles if groups is None else groups[triangles]  # (T, 3) the group of each corner
    summed = _face_sums(vertices, triangles, slots, len(vertices) if groups is None else int(groups.max()) + 1)
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    summed = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return summed if groups is None else summed[groups]


@compiled_on_first_call
def _face_sums(vertices, triangles, slots, n):  # pragma: no cover - compiled
    """(n, 3) float64: per slot, the sum of :func:`cross` of the triangles whose corners name it in ``slots``
    (T, 3) (-1: none), added in the order of the corners (triangle by triangle): ``np.bincount`` of the corners'
    slots weighted by their triangles' cross products, to the bit, without the (3T, 3) weights (a 1.37M-vertex
    mesh's normals in a tenth of the time and memory)."""
    out = np.zeros((n, 3))
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        u0, u1, u2 = vertices[b, 0] - vertices[a, 0], vertices[b, 1] - vertices[a, 1], vertices[b, 2] - vertices[a, 2]
        w0, w1, w2 = vertices[c, 0] - vertices[a, 0], vertices[c, 1] - vertices[a, 1], vertices[c, 2] - vertices[a, 2]
        x, y, z = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        for k in range(3):
            j = slots[t, k]
            if j >= 0:
                out[j, 0] += x
                out[j, 1] += y
                out[j, 2] += z
    return out


def turned_over(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> int:
    """How many triangles point against their normal before an edit: ``cross(vertices, triangles) · normals < 0``,
    counted in one pass without the (T, 3) temporaries (a draw's fold check is this count; in numpy it costs eight
    times the draw itself).

    Parameters
    ----------
    vertices : (V, 3) float64, after the edit; triangles : (T, 3) int; normals : (T, 3) float64, :func:`cross`
        before it.
    """
    if not len(triangles):
        return 0
    return int(_turned_over(np.ascontiguousarray(vertices, dtype=np.float64), triangles, normals))


@compiled_on_first_call
def _turned_over(vertices, triangles, normals):  # pragma: no cover - compiled
    """:func:`turned_over`'s count: :func:`cross`'s products, term for term, and their dot with ``normals``."""
    count = 0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        u0, u1, u2 = vertices[b, 0] - vertices[a, 0], vertices[b, 1] - vertices[a, 1], vertices[b, 2] - vertices[a, 2]
        w0, w1, w2 = vertices[c, 0] - vertices[a, 0], vertices[c, 1] - vertices[a, 1], vertices[c, 2] - vertices[a, 2]
        x, y, z = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        if x * normals[t, 0] + y * normals[t, 1] + z * normals[t, 2] < 0:
            count += 1
    return count


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
    def around(vertices: np.ndarray) -> np.ndarray:
        out = _face_sums(vertices, triangles, corner_normals, len(normals))  # (n, 3)
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
