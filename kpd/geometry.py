"""Point-set geometry: input checks, the [-1, 1] box normaliser, surface sampling, farthest point sampling, chamfer.

Everything is numpy (float64) and works on row-major ``(N, 3)`` arrays.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from kpd._compiled import compiled_on_first_call
from kpd.errors import InputError, NotFittedError
from kpd.triangles import cross as triangle_cross
from kpd.triangles import unit_normals

__all__ = [
    "as_points",
    "bounds",
    "as_rng",
    "Normalizer",
    "SurfaceSample",
    "sample_surface",
    "mesh_pieces",
    "interior_mask",
    "farthest_point_sampling",
    "farthest_point_sampling_naive",
    "chamfer",
    "chamfer_naive",
]

# Above this many pairs the chamfer distance uses KD-trees instead of a dense distance matrix.
_DENSE_CHAMFER_PAIRS = 4_000_000


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(D,) lowest and (D,) highest coordinates of (N, D) points, N >= 1: ``points.min(axis=0), points.max(axis=0)``
    reduced a column at a time, which numpy does about ten times faster on an (N, 3) array; the same values, NaN
    included."""
    columns = range(points.shape[1])
    return (np.array([points[:, k].min() for k in columns], dtype=points.dtype),
            np.array([points[:, k].max() for k in columns], dtype=points.dtype))


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
    """Maps shapes into the [-1, 1] box and back (docs/method.md §7).

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
        lo, hi = bounds(points)
        center = (lo + hi) / 2.0
        # max |p - center| over the points, as rounded: p - center rounds monotonically, so the extremes decide it
        scale = float(np.maximum(np.abs(lo - center), np.abs(hi - center)).max())
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
        out = as_points(points, min_count=0) - self.center_
        out /= self.scale_  # in place: the same numbers, without a second (N, 3) array to fault in
        return out

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


def _check_mesh(vertices: Any, triangles: Any) -> tuple[np.ndarray, np.ndarray]:
    vertices = as_points(vertices, "vertices")
    triangles = np.asarray(triangles)
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
        raise InputError(f"triangles must have shape (T, 3) with T >= 1; got {triangles.shape}")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputError(f"triangle indices must lie in [0, {len(vertices)}); "
                         f"got [{triangles.min()}, {triangles.max()}]")
    return vertices, triangles.astype(np.int64, copy=False)


def _draw(vertices: np.ndarray, triangles: np.ndarray, area2: np.ndarray, total: float, n: int,
          rng: np.random.Generator) -> SurfaceSample:
    """``n`` points drawn by area (``total`` is ``area2.sum()``): the triangles first, then the corners and cross
    products of those alone."""
    faces = np.empty(n, dtype=np.int64)
    uniform = rng.random(n)
    # the numbers in ascending order, by numpy (a sort compiled in the kernel cost a second of a first run); ties
    # get the same triangle in either order
    _picks_by_area(area2, total, uniform, np.argsort(uniform), faces)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    u, v = 1.0 - s, s * (1.0 - r2)  # barycentric weights of a and b
    picked = triangles[faces]  # (n, 3)
    a, b, c = (vertices[picked[:, i]] for i in range(3))  # (n, 3) each
    points = u[:, None] * a + v[:, None] * b + (1.0 - u - v)[:, None] * c
    normals = triangle_cross(vertices, picked) / area2[faces, None]
    return SurfaceSample(points, normals, faces)


@compiled_on_first_call
def _picks_by_area(area2, total, uniform, order, out):  # pragma: no cover - compiled
    """``out[j]``: the triangle that ``Generator.choice(len(area2), p=area2 / total)`` picks for its uniform number
    ``uniform[j]``, to the bit (numpy takes the cumulative sum of ``p``, divides it by its last value and finds each
    number in it with ``searchsorted(side="right")``), in two passes over the areas and without the (T,) arrays of
    ``p`` and its cumulative sum (fresh memory, and most of the time of a sample of a scan-sized mesh). ``order``:
    ``uniform``'s numbers in ascending order (``numpy.argsort``), found in one pass along the sums."""
    t = area2.shape[0]
    last = 0.0
    for i in range(t):
        last += area2[i] / total
    m = uniform.shape[0]
    j = 0
    running = 0.0
    for i in range(t):
        if j == m:
            break
        running += area2[i] / total
        value = running / last
        while j < m and uniform[order[j]] < value:
            out[order[j]] = i
            j += 1
    while j < m:  # at or past the last value (not for numbers below 1)
        out[order[j]] = t
        j += 1


@compiled_on_first_call
def _double_areas_kernel(vertices, triangles, out):  # pragma: no cover - compiled
    for t in range(len(triangles)):
        i, j, k = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ux, uy, uz = vertices[j, 0] - vertices[i, 0], vertices[j, 1] - vertices[i, 1], vertices[j, 2] - vertices[i, 2]
        vx, vy, vz = vertices[k, 0] - vertices[i, 0], vertices[k, 1] - vertices[i, 1], vertices[k, 2] - vertices[i, 2]
        # as numpy.cross and numpy.linalg.norm round them: products, then differences; (x² + y²) + z²
        cx = uy * vz - uz * vy
        cy = uz * vx - ux * vz
        cz = ux * vy - uy * vx
        out[t] = np.sqrt((cx * cx + cy * cy) + cz * cz)


def _double_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) float64: twice each triangle's area, ``numpy.linalg.norm(kpd.triangles.cross(...), axis=1)`` to the bit,
    in one compiled pass (without the (T, 3) corners and cross products).

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, checked indices into ``vertices``
    """
    out = np.empty(len(triangles))
    _double_areas_kernel(np.ascontiguousarray(vertices), np.ascontiguousarray(triangles), out)
    return out


def sample_surface(
    vertices: Any, triangles: Any, n: int, seed: None | int | np.random.Generator = None, *, outer: bool = False
) -> SurfaceSample:
    """Draw ``n`` points uniformly by area on a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int
    n : number of points.
    seed : seed or Generator; the same seed gives the same sample.
    outer : draw from the outer surface only: points that lie inside another closed piece of the same mesh (the
        interior faces of overlapping parts, as in convex decompositions or CAD models built from intersecting solids;
        see :func:`interior_mask`) are rejected and drawn again, so the result stays uniform on what is left.
    """
    vertices, triangles = _check_mesh(vertices, triangles)
    if n < 1:
        raise InputError(f"the number of samples must be at least 1; got {n}")
    rng = as_rng(seed)
    area2 = _double_areas(vertices, triangles)  # (T,)
    total = float(area2.sum())
    if not total > 0:
        raise InputError("cannot sample a mesh whose triangles all have zero area")
    if not np.isfinite(total):
        raise InputError("cannot sample a mesh this large: its triangles' areas overflow (scale it down)")
    if not outer:
        return _draw(vertices, triangles, area2, total, n, rng)
    inside = _InteriorTest(vertices, triangles)
    if not inside.containers:
        return _draw(vertices, triangles, area2, total, n, rng)
    kept: list[SurfaceSample] = []
    count, drawn, accepted = 0, 0, 0
    for _ in range(_OUTER_ROUNDS):
        share = max(accepted / drawn, 0.05) if drawn else 1.0
        batch = _draw(vertices, triangles, area2, total, int(np.ceil(1.1 * (n - count) / share)) + 16, rng)
        keep = ~inside(batch.points, batch.normals, batch.faces)
        drawn, accepted = drawn + len(keep), accepted + int(keep.sum())
        kept.append(SurfaceSample(batch.points[keep], batch.normals[keep], batch.faces[keep]))
        count += int(keep.sum())
        if count >= n:
            break
    if count < n:
        raise InputError(f"the outer surface of this mesh is too small to sample: {accepted} of {drawn} points drawn "
                         f"lie outside the other pieces")
    return SurfaceSample(*(np.concatenate(parts)[:n] for parts in zip(*kept)))


# Rejection rounds of an outer-surface sample before giving up (each round draws what the accepted share asks for).
_OUTER_ROUNDS = 20


def mesh_pieces(triangles: Any) -> np.ndarray:
    """Label each triangle with its connected piece (triangles sharing a vertex index are connected).

    Parameters
    ----------
    triangles : (T, 3) int

    Returns
    -------
    labels : (T,) int64 in [0, number of pieces), pieces numbered by their first triangle.
    """
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise InputError(f"triangles must have shape (T, 3); got {triangles.shape}")
    if len(triangles) == 0:
        return np.zeros(0, dtype=np.int64)
    if triangles.min() < 0:
        raise InputError("triangles must index vertices (>= 0)")
    return _triangle_pieces(triangles, int(triangles.max()) + 1)


@compiled_on_first_call
def _triangle_pieces(triangles, count):  # pragma: no cover - compiled
    """Union-find over the vertices that the triangles join; each triangle labelled by its piece, numbered in order
    of the pieces' first triangles."""
    parent = np.arange(count)

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]  # path halving
            i = parent[i]
        return i

    for t in range(triangles.shape[0]):
        a = root(triangles[t, 0])
        for k in range(1, 3):
            b = root(triangles[t, k])
            if a != b:
                if b < a:
                    a, b = b, a
                parent[b] = a
    number = np.full(count, -1, dtype=np.int64)
    labels = np.empty(triangles.shape[0], dtype=np.int64)
    pieces = 0
    for t in range(triangles.shape[0]):
        r = root(triangles[t, 0])
        if number[r] < 0:
            number[r] = pieces
            pieces += 1
        labels[t] = number[r]
    return labels


def _is_closed(triangles: np.ndarray) -> bool:
    """Every edge of the piece is shared by exactly two of its triangles (a watertight, edge-manifold surface)."""
    if len(triangles) < 4:
        return False
    first = triangles.ravel()
    second = triangles[:, [1, 2, 0]].ravel()
    count = int(max(first.max(), second.max())) + 1
    keys = np.sort(np.minimum(first, second) * count + np.maximum(first, second))  # each edge as one integer
    runs = np.diff(np.flatnonzero(np.diff(keys, prepend=-1, append=-1)))  # how often each edge occurs
    return bool((runs == 2).all())


@compiled_on_first_call
def _closed_pieces(triangles, labels, pieces, count):  # pragma: no cover - compiled
    """(pieces,) bool: :func:`_is_closed` of every piece at once (``labels`` from :func:`mesh_pieces`; an edge
    belongs to one piece). The edges are bucketed by their smaller corner, a counting sort, so this is one linear
    pass instead of a sort per piece."""
    start = np.zeros(count + 1, dtype=np.int64)
    for t in range(triangles.shape[0]):
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            start[min(a, b) + 1] += 1
    for i in range(count):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    other = np.empty(start[count], dtype=np.int64)
    for t in range(triangles.shape[0]):
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            low = min(a, b)
            other[fill[low]] = max(a, b)
            fill[low] += 1
    closed = np.ones(pieces, dtype=np.bool_)
    size = np.zeros(pieces, dtype=np.int64)
    for t in range(triangles.shape[0]):
        size[labels[t]] += 1
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        if a == b or b == c or c == a:
            closed[labels[t]] = False  # a repeated corner: an edge from a point to itself, never shared by two
    owner = np.full(count, -1, dtype=np.int64)  # each vertex's piece
    for t in range(triangles.shape[0]):
        for k in range(3):
            owner[triangles[t, k]] = labels[t]
    for i in range(count):
        lo, hi = start[i], start[i + 1]
        if hi - lo > 64:  # a fan's centre: a real sort
            other[lo:hi].sort()  # in place: assigning a sorted copy makes numba's first compile far longer
        for j in range(lo + 1, hi):  # insertion sort: rows are short (a no-op after the sort)
            value = other[j]
            k = j - 1
            while k >= lo and other[k] > value:
                other[k + 1] = other[k]
                k -= 1
            other[k + 1] = value
        run = 1
        for j in range(lo + 1, hi + 1):
            if j < hi and other[j] == other[j - 1]:
                run += 1
            else:
                if run != 2:
                    closed[owner[i]] = False
                run = 1
    for p in range(pieces):
        if size[p] < 4:
            closed[p] = False
    return closed


class _InteriorTest:
    """Which points of a mesh's surface are covered by another closed piece of it (Open3D ray casting, per piece).

    A point of piece i is covered when the point a little off the surface on its outer side (``offset`` times the
    mesh's diagonal along the outward normal; both sides for an open piece, whose outside is unknown) lies inside a
    closed piece j != i: then it is inside j, or on a face where i and j touch.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, offset: float = 2e-3) -> None:
        self.labels = mesh_pieces(triangles)
        lo, hi = bounds(vertices)
        self.offset = offset * float(np.linalg.norm(hi - lo))
        self.containers = []  # (piece label, scene, box low, box high) of the closed pieces
        self.outward = np.zeros(len(triangles))  # per triangle: +1 / -1 to turn its normal outward, 0 if unknown
        pieces = np.arange(int(self.labels.max()) + 1 if len(self.labels) else 0)  # numbered 0.. by mesh_pieces
        if len(pieces) < 2:
            return
        closed = _closed_pieces(triangles, self.labels, len(pieces), int(triangles.max()) + 1)
        order = np.argsort(self.labels, kind="stable")  # each piece's triangles together: no pass per piece
        start = np.concatenate([[0], np.cumsum(np.bincount(self.labels, minlength=len(pieces)))])
        for at, label in enumerate(pieces):
            if not closed[label]:
                continue
            mask = order[start[at]:start[at + 1]]
            tri = triangles[mask]
            a, b, c = (vertices[tri[:, i]] for i in range(3))
            volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum())  # 6x the signed volume
            if volume == 0.0:
                continue
            self.outward[mask] = np.sign(volume)
            import open3d as o3d  # only for a closed piece: a scan of open pieces reads and binds without Open3D

            scene = o3d.t.geometry.RaycastingScene()
            used, local = np.unique(tri, return_inverse=True)
            scene.add_triangles(o3d.core.Tensor(vertices[used].astype(np.float32)),
                                o3d.core.Tensor(local.reshape(-1, 3).astype(np.uint32)))
            lo, hi = bounds(vertices[used])
            self.containers.append((int(label), scene, lo - self.offset, hi + self.offset))

    def _inside_others(self, points: np.ndarray, own: np.ndarray) -> np.ndarray:
        import open3d as o3d

        inside = np.zeros(len(points), dtype=bool)
        for label, scene, lo, hi in self.containers:
            candidate = np.flatnonzero((own != label) & ~inside & (points >= lo).all(axis=1)
                                       & (points <= hi).all(axis=1))
            if len(candidate):
                query = o3d.core.Tensor(points[candidate].astype(np.float32))
                inside[candidate[scene.compute_occupancy(query, nthreads=1, nsamples=3).numpy() > 0.5]] = True
        return inside

    def __call__(self, points: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> np.ndarray:
        own = self.labels[faces]  # (n,)
        sign = self.outward[faces]  # (n,)
        known = sign != 0
        step = self.offset * normals * np.where(known, sign, 1.0)[:, None]  # (n, 3)
        covered = self._inside_others(points + step, own)
        if (~known).any():  # an open piece: covered only when both sides are
            covered &= known | self._inside_others(points - step, own)
        return covered


def interior_mask(vertices: Any, triangles: Any, points: Any, faces: Any, *, offset: float = 2e-3) -> np.ndarray:
    """Which surface points are inside the shape: covered by another piece of the same mesh.

    A mesh made of overlapping or touching parts (a convex decomposition, a CAD chair whose legs go into its seat)
    has faces inside its volume that no scanner could see. The pieces are the connected components of the mesh
    (:func:`mesh_pieces`); each closed one (every edge shared by two of its triangles) is a container. A point is
    interior when the point ``offset`` times the mesh's diagonal off the surface on its piece's outer side (along
    the outward normal of a closed piece; on both sides for an open piece) lies inside a container other than its
    own piece (Open3D's ``RaycastingScene.compute_occupancy``, majority of 3 rays): it is then inside that piece or
    on a face where the two touch. A mesh of open surfaces has no containers and so no interior points.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int
    points : (n, 3) float64, points on the surface
    faces : (n,) int, the triangle each point lies on (``SurfaceSample.faces``)

    Returns
    -------
    interior : (n,) bool
    """
    vertices, triangles = _check_mesh(vertices, triangles)
    points = as_points(points, min_count=0)
    faces = np.asarray(faces, dtype=np.int64)
    if faces.shape != (len(points),) or (len(faces) and (faces.min() < 0 or faces.max() >= len(triangles))):
        raise InputError(f"faces must be {len(points)} triangle indices in [0, {len(triangles)}); got shape "
                         f"{faces.shape}")
    test = _InteriorTest(vertices, triangles, offset)
    if not test.containers:
        return np.zeros(len(points), dtype=bool)
    return test(points, unit_normals(vertices, triangles[faces]), faces)


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
    dist[first] = -1.0  # a chosen point is never chosen again, even where squared distances underflow to 0
    for i in range(1, k):
        nxt = int(np.argmax(dist))
        indices[i] = nxt
        np.minimum(dist, np.sum((points - points[nxt]) ** 2, axis=1), out=dist)
        dist[nxt] = -1.0
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
            if j in chosen:
                continue
            d = min(float(np.sum((points[j] - points[c]) ** 2)) for c in chosen)
            if d > best_d:
                best, best_d = j, d
        chosen.append(best)
    return np.asarray(chosen, dtype=np.int64)


def chamfer(a: Any, b: Any) -> float:
    """Chamfer distance as the authors' training loss (docs/method.md §6).

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
    from scipy.spatial import cKDTree  # here: importing scipy.spatial takes 0.3 s, most commands' start needs none

    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(np.mean(d_ab**2) + np.mean(d_ba**2))


def chamfer_naive(a: Any, b: Any) -> float:
    """Slow reference for :func:`chamfer` with explicit differences."""
    a, b = as_points(a, "a"), as_points(b, "b")
    d = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)  # (N, M)
    return float(d.min(axis=1).mean() + d.min(axis=0).mean())
