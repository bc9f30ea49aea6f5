"""Point-set geometry: input checks, the [-1, 1] box normaliser, surface sampling, farthest point sampling, chamfer.

Everything is numpy (float64) and works on row-major ``(N, 3)`` arrays.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from kpd.errors import InputError, NotFittedError

__all__ = [
    "as_points",
    "as_rng",
    "Normalizer",
    "SurfaceSample",
    "sample_surface",
    "farthest_point_sampling",
    "farthest_point_sampling_naive",
    "chamfer",
    "chamfer_naive",
]

# Above this many pairs the chamfer distance uses KD-trees instead of a dense distance matrix.
_DENSE_CHAMFER_PAIRS = 4_000_000


def as_points(x: Any, name: str = "points", *, min_count: int = 1) -> np.ndarray:
    """Check and convert an array of 3D points.

    Parameters
    ----------
    x : (N, 3) array-like
    name : what the array is, for error messages.
    min_count : the fewest points accepted.

    Returns
    -------
    points : (N, 3) float64, C-contiguous (a copy only when needed).
    """
    try:
        points = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric with shape (N, 3); got {type(x).__name__}") from exc
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3); got {points.shape}")
    if points.shape[0] < min_count:
        raise InputError(f"{name} must have at least {min_count} point(s); got {points.shape[0]}")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise InputError(f"{name} must be finite; got {bad} point(s) with NaN or inf coordinates")
    return points


def as_rng(seed: None | int | np.random.Generator = None) -> np.random.Generator:
    """A numpy Generator from a seed, or the Generator itself."""
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(seed)


class Normalizer:
    """Maps shapes into the [-1, 1] box and back (REFERENCE §7).

    The bounding-box centre goes to the origin and the largest absolute coordinate over all axes becomes 1, so the
    longest axis spans [-1, 1] and the aspect ratio is kept.

    Attributes
    ----------
    center_ : (3,) float64
    scale_ : float
    """

    def __init__(self) -> None:
        pass

    def fit(self, points: Any) -> "Normalizer":
        points = as_points(points)
        lo, hi = points.min(axis=0), points.max(axis=0)
        center = (lo + hi) / 2.0
        scale = float(np.abs(points - center).max())
        if not scale > 0.0:
            raise InputError(f"cannot normalise a shape with zero extent (all {len(points)} points coincide)")
        self.center_ = center
        self.scale_ = scale
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "scale_"):
            raise NotFittedError("this Normalizer is not fitted yet; call fit(points) first")

    def apply(self, points: Any) -> np.ndarray:
        """``(points - center_) / scale_`` for ``points : (N, 3)``."""
        self._check_fitted()
        return (as_points(points, min_count=0) - self.center_) / self.scale_

    def invert(self, points: Any) -> np.ndarray:
        """``points * scale_ + center_``, the inverse of :meth:`apply`."""
        self._check_fitted()
        return as_points(points, min_count=0) * self.scale_ + self.center_

    def apply_vectors(self, vectors: Any) -> np.ndarray:
        """Offsets ``(N, 3)`` into the normalised frame (scale only)."""
        self._check_fitted()
        return as_points(vectors, "offsets", min_count=0) / self.scale_

    def invert_vectors(self, vectors: Any) -> np.ndarray:
        """Offsets ``(N, 3)`` back to the original frame (scale only)."""
        self._check_fitted()
        return as_points(vectors, "offsets", min_count=0) * self.scale_

    def to_dict(self) -> dict:
        self._check_fitted()
        return {"center": [float(c) for c in self.center_], "scale": self.scale_}

    @classmethod
    def from_dict(cls, data: dict) -> "Normalizer":
        try:
            center = np.asarray(data["center"], dtype=np.float64)
            scale = float(data["scale"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"a normaliser needs 'center' (3 numbers) and 'scale'; got {data!r}") from exc
        if center.shape != (3,) or not np.isfinite(center).all() or not (np.isfinite(scale) and scale > 0):
            raise InputError(f"invalid normaliser: center {center.tolist()}, scale {scale}")
        normalizer = cls()
        normalizer.center_, normalizer.scale_ = center, scale
        return normalizer

    def __repr__(self) -> str:
        if not hasattr(self, "scale_"):
            return "Normalizer()"
        return f"Normalizer(center={np.round(self.center_, 6).tolist()}, scale={self.scale_:.6g})"


class SurfaceSample(NamedTuple):
    """Points drawn on a triangle mesh.

    points : (n, 3) float64
    normals : (n, 3) float64, unit normals of the triangles they lie on
    faces : (n,) int64, index of each point's triangle
    """

    points: np.ndarray
    normals: np.ndarray
    faces: np.ndarray


def sample_surface(
    vertices: Any, triangles: Any, n: int, seed: None | int | np.random.Generator = None
) -> SurfaceSample:
    """Draw ``n`` points uniformly by area on a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int
    n : number of points.
    seed : seed or Generator; the same seed gives the same sample.
    """
    vertices = as_points(vertices, "vertices")
    triangles = np.asarray(triangles)
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
        raise InputError(f"triangles must have shape (T, 3) with T >= 1; got {triangles.shape}")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputError(f"triangle indices must lie in [0, {len(vertices)}); got [{triangles.min()}, {triangles.max()}]")
    if n < 1:
        raise InputError(f"the number of samples must be at least 1; got {n}")
    rng = as_rng(seed)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))  # (T, 3) each
    cross = np.cross(b - a, c - a)  # (T, 3)
    area2 = np.linalg.norm(cross, axis=1)  # (T,)
    total = area2.sum()
    if not total > 0:
        raise InputError("cannot sample a mesh whose triangles all have zero area")
    faces = rng.choice(len(triangles), size=n, p=area2 / total).astype(np.int64)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    u, v = 1.0 - s, s * (1.0 - r2)  # barycentric weights of a and b
    points = u[:, None] * a[faces] + v[:, None] * b[faces] + (1.0 - u - v)[:, None] * c[faces]
    normals = cross[faces] / area2[faces, None]
    return SurfaceSample(points, normals, faces)


def farthest_point_sampling(
    points: Any, k: int, seed: None | int | np.random.Generator = None, start: int | None = None
) -> np.ndarray:
    """Indices of ``k`` points chosen greedily, each the farthest from those already chosen.

    Parameters
    ----------
    points : (N, 3) float64
    k : how many to choose, 1 <= k <= N.
    seed : picks the random first point (as the authors' code); ignored when ``start`` is given.
    start : index of the first point.

    Returns
    -------
    indices : (k,) int64, distinct.
    """
    points = as_points(points)
    n = len(points)
    if not 1 <= k <= n:
        raise InputError(f"k must lie in [1, {n}] for {n} points; got {k}")
    first = int(as_rng(seed).integers(n)) if start is None else int(start)
    indices = np.empty(k, dtype=np.int64)
    indices[0] = first
    dist = np.sum((points - points[first]) ** 2, axis=1)  # (N,)
    for i in range(1, k):
        nxt = int(np.argmax(dist))
        indices[i] = nxt
        np.minimum(dist, np.sum((points - points[nxt]) ** 2, axis=1), out=dist)
    return indices


def farthest_point_sampling_naive(
    points: Any, k: int, seed: None | int | np.random.Generator = None, start: int | None = None
) -> np.ndarray:
    """Slow reference for :func:`farthest_point_sampling`: recomputes every distance from scratch."""
    points = as_points(points)
    first = int(as_rng(seed).integers(len(points))) if start is None else int(start)
    chosen = [first]
    while len(chosen) < k:
        best, best_d = -1, -1.0
        for j in range(len(points)):
            d = min(float(np.sum((points[j] - points[c]) ** 2)) for c in chosen)
            if d > best_d:
                best, best_d = j, d
        chosen.append(best)
    return np.asarray(chosen, dtype=np.int64)


def chamfer(a: Any, b: Any) -> float:
    """Chamfer distance as the authors' training loss (REFERENCE §6).

    ``mean_i min_j |a_i - b_j|^2 + mean_j min_i |a_i - b_j|^2``: squared distances, a mean per cloud, both directions
    summed. Dense for small clouds, KD-trees for large ones.

    Parameters
    ----------
    a : (N, 3) float64
    b : (M, 3) float64
    """
    a, b = as_points(a, "a"), as_points(b, "b")
    if len(a) * len(b) <= _DENSE_CHAMFER_PAIRS:
        d = np.sum(a * a, 1)[:, None] + np.sum(b * b, 1)[None, :] - 2.0 * a @ b.T  # (N, M)
        np.maximum(d, 0.0, out=d)
        return float(d.min(axis=1).mean() + d.min(axis=0).mean())
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(np.mean(d_ab**2) + np.mean(d_ba**2))


def chamfer_naive(a: Any, b: Any) -> float:
    """Slow reference for :func:`chamfer` with explicit differences."""
    a, b = as_points(a, "a"), as_points(b, "b")
    d = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)  # (N, M)
    return float(d.min(axis=1).mean() + d.min(axis=0).mean())
