"""Label-free keypoint quality: stability over independent point samples, distance to the surface, mirror
consistency; and the alignment chamfer of the paper's Fig. 7 (docs/method.md §6, on [-1, 1]-normalised shapes)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from kpd.errors import InputError
from kpd.geometry import as_points, chamfer
__all__ = [
    "keypoint_stability", "surface_distance", "point_triangle_distance", "fit_mirror_permutation",
    "mirror_consistency", "alignment_chamfer",
]

def _keypoint_sets(x: Any, name: str) -> np.ndarray:
    array = np.asarray(x, dtype=np.float64)
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1 or array.shape[1] < 1:
        raise InputError(f"{name} must have shape (S, K, 3) with S, K >= 1; got {array.shape}")
    if not np.isfinite(array).all():
        raise InputError(f"{name} must be finite; got NaN or inf")
    return array


def keypoint_stability(keypoint_sets: Any) -> float:
    """Spread of keypoints predicted from S independent point samples of one shape.

    Parameters
    ----------
    keypoint_sets : (S, K, 3) float64, keypoints of the same shape from S samples.

    Returns
    -------
    spread : mean over keypoints of the mean distance to that keypoint's centroid over the samples.
    """
    sets = _keypoint_sets(keypoint_sets, "keypoint_sets")
    centroid = sets.mean(axis=0)  # (K, 3)
    return float(np.linalg.norm(sets - centroid, axis=2).mean())


def point_triangle_distance(points: Any, vertices: Any, triangles: Any, chunk: int = 4096) -> np.ndarray:
    """Unsigned distance from each point to the nearest triangle (exact closest point on each triangle).

    Parameters
    ----------
    points : (P, 3) float64
    vertices : (V, 3) float64
    triangles : (T, 3) int
    chunk : triangles per block.

    Returns
    -------
    distance : (P,) float64
    """
    p = as_points(points, "points")
    v = as_points(vertices, "vertices")
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
        raise InputError(f"triangles must have shape (T, 3) with T >= 1; got {tri.shape}")
    if tri.min() < 0 or tri.max() >= len(v):
        raise InputError(f"triangle indices must lie in [0, {len(v)}); got [{tri.min()}, {tri.max()}]")
    best = np.full(len(p), np.inf)
    for s in range(0, len(tri), chunk):
        t = tri[s:s + chunk]
        a, b, c = v[t[:, 0]][None], v[t[:, 1]][None], v[t[:, 2]][None]  # (1, T, 3)
        q = _closest_on_triangles(p[:, None, :], a, b, c)  # (P, T, 3)
        d = np.sqrt(np.sum((q - p[:, None, :]) ** 2, axis=2)).min(axis=1)
        np.minimum(best, d, out=best)
    return best


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to p (Ericson, Real-Time Collision Detection §5.1.5), broadcast."""
    p, a, b, c = np.broadcast_arrays(p, a, b, c)
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.sum(ab * ap, -1), np.sum(ac * ap, -1)
    bp = p - b
    d3, d4 = np.sum(ab * bp, -1), np.sum(ac * bp, -1)
    cp = p - c
    d5, d6 = np.sum(ab * cp, -1), np.sum(ac * cp, -1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        result = a + ab * v[..., None] + ac * w[..., None]  # inside the face
        # edge regions
        t_ab = np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0)
        t_ac = np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0)
        t_bc = np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0)
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    result = np.where(on_bc[..., None], b + (c - b) * t_bc[..., None], result)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    result = np.where(on_ac[..., None], a + ac * t_ac[..., None], result)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    result = np.where(on_ab[..., None], a + ab * t_ab[..., None], result)
    # vertex regions (checked last so they win, as in the sequential algorithm)
    result = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, result)
    result = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, result)
    result = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, result)
    return result


def surface_distance(keypoints: Any, vertices: Any, triangles: Any) -> np.ndarray:
    """Distance from each keypoint to the mesh surface: keypoints (K, 3) -> (K,) float64 (unsigned)."""
    return point_triangle_distance(as_points(keypoints, "keypoints"), vertices, triangles)


def fit_mirror_permutation(keypoints: Any, mirrored_keypoints: Any) -> np.ndarray:
    """The fixed keypoint permutation that best matches keypoints to those of the mirrored shapes.

    Parameters
    ----------
    keypoints : (S, K, 3), keypoints of S shapes.
    mirrored_keypoints : (S, K, 3), ``mirrored_keypoints[s]`` = keypoints predicted on the mirror image of shape s,
        mirrored back into the shape's frame.

    Returns
    -------
    permutation : (K,) int64; keypoint k of a shape corresponds to keypoint ``permutation[k]`` of its mirror image.
        Found by the Hungarian method on the distances summed over the shapes.
    """
    kp = _keypoint_sets(keypoints, "keypoints")
    mk = _keypoint_sets(mirrored_keypoints, "mirrored_keypoints")
    if kp.shape != mk.shape:
        raise InputError(f"keypoints and mirrored_keypoints must have the same shape; got {kp.shape} and {mk.shape}")
    cost = np.linalg.norm(kp[:, :, None, :] - mk[:, None, :, :], axis=3).sum(axis=0)  # (K, K)
    rows, cols = linear_sum_assignment(cost)
    permutation = np.empty(kp.shape[1], dtype=np.int64)
    permutation[rows] = cols
    return permutation


def mirror_consistency(keypoints: Any, mirrored_keypoints: Any, permutation: Any) -> float:
    """Mean distance between keypoints and the permuted keypoints of the mirrored shapes (lower is better).

    Parameters
    ----------
    keypoints, mirrored_keypoints : (S, K, 3), as for :func:`fit_mirror_permutation`.
    permutation : (K,) int, from :func:`fit_mirror_permutation` (fitted on other shapes, e.g. the train split).
    """
    kp = _keypoint_sets(keypoints, "keypoints")
    mk = _keypoint_sets(mirrored_keypoints, "mirrored_keypoints")
    perm = np.asarray(permutation, dtype=np.int64)
    if kp.shape != mk.shape:
        raise InputError(f"keypoints and mirrored_keypoints must have the same shape; got {kp.shape} and {mk.shape}")
    if perm.shape != (kp.shape[1],) or sorted(perm.tolist()) != list(range(kp.shape[1])):
        raise InputError(f"permutation must be a permutation of range({kp.shape[1]}); got {perm.tolist()}")
    return float(np.linalg.norm(kp - mk[:, perm], axis=2).mean())


def alignment_chamfer(deformed: Any, target: Any) -> float:
    """Chamfer distance between a deformed source and its target (docs/method.md §6; = kpd.geometry.chamfer)."""
    return chamfer(deformed, target)
