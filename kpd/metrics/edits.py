"""Edit quality: locality, detail preservation, semantic edits, the prior's response, sample plausibility.

Every measure compares a mesh before and after an edit (same triangles), in whatever frame it is given;
benchmarks/bench_edits.py runs them in the model's [-1, 1] frame, where moves are fractions of the box.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from kpd.errors import InputError
from kpd.geometry import as_points
from kpd.triangles import areas as triangle_areas
from kpd.triangles import cross as triangle_cross
from kpd.metrics.labelfree import _closest_on_triangles, _keypoint_sets
__all__ = [
    "vertex_areas", "far_side_leakage", "folded_share", "folded_area_share", "EditDistortion", "edit_distortion",
    "keypoint_roles", "semantic_edits", "PriorResponse", "prior_response", "triangle_distance",
    "new_self_intersections", "keypoint_set_distance",
]

def _mesh_pair(rest: Any, deformed: Any, triangles: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v0 = as_points(rest, "rest vertices")
    v1 = as_points(deformed, "deformed vertices")
    if v0.shape != v1.shape:
        raise InputError(f"rest and deformed vertices must have the same shape; got {v0.shape} and {v1.shape}")
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
        raise InputError(f"triangles must have shape (T, 3) with T >= 1; got {tri.shape}")
    if tri.min() < 0 or tri.max() >= len(v0):
        raise InputError(f"triangle indices must lie in [0, {len(v0)}); got [{tri.min()}, {tri.max()}]")
    return v0, v1, tri


def vertex_areas(vertices: Any, triangles: Any) -> np.ndarray:
    """(V,) float64: the surface area each vertex stands for (a third of each triangle it is a corner of).

    Weights for measures over a mesh's vertices, so that densely tessellated details do not count more than large
    flat faces (CAD meshes are tessellated very unevenly).
    """
    v = as_points(vertices, "vertices")
    tri = np.asarray(triangles, dtype=np.int64)
    area = triangle_areas(v, tri)  # (T,)
    out = np.zeros(len(v))
    for i in range(3):
        np.add.at(out, tri[:, i], area / 3.0)
    return out


def far_side_leakage(rest: Any, deformed: Any, keypoint: Any, move: float, weights: Any = None) -> float:
    """Locality of a single-keypoint edit: how much the half of the shape farthest from the moved keypoint moved.

    Parameters
    ----------
    rest, deformed : (V, 3) float64, mesh vertices before and after moving one keypoint.
    keypoint : (3,) float64, the moved keypoint's rest position.
    move : length of the keypoint's move (> 0).
    weights : (V,) float64 or None, vertex weights (e.g. :func:`vertex_areas`); None weighs vertices alike.

    Returns
    -------
    leakage : the (weighted) mean displacement of the vertices farther from the keypoint than the (weighted) median
        distance, divided by ``move``: 0 for a perfectly local edit, 1 when the far half moved as far as the keypoint.
    """
    v0 = as_points(rest, "rest vertices")
    v1 = as_points(deformed, "deformed vertices")
    if v0.shape != v1.shape:
        raise InputError(f"rest and deformed vertices must have the same shape; got {v0.shape} and {v1.shape}")
    p = np.asarray(keypoint, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise InputError(f"keypoint must be 3 finite numbers; got {np.shape(keypoint)}")
    if not (np.isfinite(move) and move > 0):
        raise InputError(f"move must be a positive length; got {move!r}")
    w = np.ones(len(v0)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(v0),) or not np.isfinite(w).all() or (w < 0).any() or not w.sum() > 0:
        raise InputError(f"weights must be {len(v0)} non-negative finite numbers, not all zero")
    distance = np.linalg.norm(v0 - p, axis=1)  # (V,)
    order = np.argsort(distance)
    cumulative = np.cumsum(w[order])
    far = order[cumulative > 0.5 * cumulative[-1]]  # the farther half of the weight
    displacement = np.linalg.norm(v1[far] - v0[far], axis=1)
    return float(np.average(displacement, weights=w[far]) / move) if w[far].sum() > 0 else 0.0


def folded_share(rest: Any, deformed: Any, triangles: Any) -> float:
    """Share of the (non-degenerate) triangles whose normal turned by more than 90 degrees in an edit (folded)."""
    v0, v1, tri = _mesh_pair(rest, deformed, triangles)
    return _fold_share(triangle_cross(v0, tri), triangle_cross(v1, tri))


def folded_area_share(rest: Any, deformed: Any, triangles: Any) -> float:
    """Share of the surface *area* (at rest) on triangles whose normal turned by more than 90 degrees in an edit.

    :func:`folded_share` counts triangles; on CAD meshes one long sliver triangle (a strip along a table leg or a
    seat edge, a thousandth of the area) counts as much as a large face, and slivers are what fold first when a
    long flat face bends slightly. This weighs each by its area, so it reads as the share of the visible surface.
    """
    v0, v1, tri = _mesh_pair(rest, deformed, triangles)
    n0, n1 = triangle_cross(v0, tri), triangle_cross(v1, tri)
    size = np.linalg.norm(n0, axis=1)
    if not size.sum() > 0:
        return 0.0
    return float(size[_turned(n0, n1)].sum() / size.sum())


def _turned(n0: np.ndarray, n1: np.ndarray) -> np.ndarray:
    """(T,) bool: the triangles whose normal turned by more than 90 degrees (normals before and after, (T, 3))."""
    return np.einsum("ij,ij->i", n0, n1) < 0.0


def _fold_share(n0: np.ndarray, n1: np.ndarray) -> float:
    """Share of the non-degenerate triangles (rest normals n0, deformed n1) that turned over."""
    size = np.linalg.norm(n0, axis=1)
    valid = size > 1e-12 * max(float(size.max()), 1e-300)
    if not valid.any():
        return 0.0
    return float(np.mean(_turned(n0[valid], n1[valid])))


class EditDistortion(NamedTuple):
    """Detail preservation of an edit (:func:`edit_distortion`).

    folded : share of triangles whose normal turned by more than 90 degrees.
    edge : mean relative change of the edge lengths, mean ``|l' / l - 1|`` over the mesh's edges.
    dihedral : mean change of the dihedral angles, in degrees, over the edges shared by exactly two triangles.
    """

    folded: float
    edge: float
    dihedral: float


def edit_distortion(rest: Any, deformed: Any, triangles: Any) -> EditDistortion:
    """How much an edit distorts a mesh locally (see :class:`EditDistortion`); 0, 0, 0 for a rigid motion.

    Parameters
    ----------
    rest, deformed : (V, 3) float64, vertices before and after the edit.
    triangles : (T, 3) int, the mesh's triangles (degenerate ones and zero-length edges are ignored).
    """
    v0, v1, tri = _mesh_pair(rest, deformed, triangles)
    n0, n1 = triangle_cross(v0, tri), triangle_cross(v1, tri)
    size0, size1 = np.linalg.norm(n0, axis=1), np.linalg.norm(n1, axis=1)
    valid = size0 > 1e-12 * max(float(size0.max()), 1e-300)
    folded = _fold_share(n0, n1)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)  # (3T, 2)
    unique, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    l0 = np.linalg.norm(v0[unique[:, 0]] - v0[unique[:, 1]], axis=1)
    l1 = np.linalg.norm(v1[unique[:, 0]] - v1[unique[:, 1]], axis=1)
    long = l0 > 1e-9 * max(float(l0.max()), 1e-300)
    edge = float(np.mean(np.abs(l1[long] / l0[long] - 1.0))) if long.any() else 0.0
    # dihedral angles across the edges of exactly two valid triangles (angle between the two normals)
    inverse = inverse.ravel()
    face = np.tile(np.arange(len(tri)), 3)  # (3T,) the triangle of each edge copy
    keep = valid[face] & (counts[inverse] == 2)
    order = np.argsort(inverse[keep], kind="stable")
    pairs = face[keep][order].reshape(-1, 2) if keep.sum() % 2 == 0 else np.empty((0, 2), dtype=np.int64)
    if len(pairs):
        same = inverse[keep][order].reshape(-1, 2)
        pairs = pairs[same[:, 0] == same[:, 1]]
    dihedral = 0.0
    if len(pairs):
        u0 = n0 / np.maximum(size0, 1e-300)[:, None]
        u1 = n1 / np.maximum(size1, 1e-300)[:, None]

        def angle(u: np.ndarray) -> np.ndarray:
            a, b = u[pairs[:, 0]], u[pairs[:, 1]]
            return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b)))

        dihedral = float(np.mean(np.abs(angle(u1) - angle(u0))))
    return EditDistortion(folded, edge, dihedral)


def keypoint_roles(mean_keypoints: Any, *, up: int = 2, side: int = 0, gap: float = 0.2) -> dict[str, np.ndarray]:
    """Roles of a model's keypoints, found from their mean positions on the training shapes (no hand-picked indices).

    The keypoints are grouped by height (single linkage along ``up``: a new group starts where consecutive heights
    differ by more than ``gap``, in [-1, 1] box units).

    Parameters
    ----------
    mean_keypoints : (K, 3) float64, the mean keypoint set over the training shapes (``KeypointPrior.mean_``).
    up, side : axis indices of the up and the left/right (mirror) directions.
    gap : height difference that separates two groups.

    Returns
    -------
    roles : ``{"top": the highest group (a chair's top of the back, a table's top), "bottom": the lowest (feet),
        "above_bottom": the group just above the lowest (a chair's seat), "sides": (K,) float64 sign of each
        keypoint's side coordinate, 0 for those within 0.1 of the mirror plane}``; index arrays are int64, sorted.
    """
    mean = as_points(mean_keypoints, "mean_keypoints")
    if len(mean) < 2:
        raise InputError(f"roles need at least 2 keypoints; got {len(mean)}")
    height = mean[:, up]
    order = np.argsort(height)
    breaks = np.flatnonzero(np.diff(height[order]) > gap) + 1
    groups = [np.sort(g) for g in np.split(order, breaks)]
    side_sign = np.where(np.abs(mean[:, side]) > 0.1, np.sign(mean[:, side]), 0.0)
    return {
        "top": groups[-1].astype(np.int64),
        "bottom": groups[0].astype(np.int64),
        "above_bottom": (groups[1] if len(groups) > 2 else groups[-1]).astype(np.int64),
        "sides": side_sign,
    }


# the edits of issue #14, by category: (name, role, direction) with direction "up", "down" or "out" (away from the
# mirror plane along the side axis)
_SEMANTIC = {
    "chair": [("taller_back", "top", "up"), ("longer_legs", "bottom", "down"), ("wider_seat", "above_bottom", "out")],
    "table": [("taller", "top", "up"), ("wider_top", "top", "out")],
}


def semantic_edits(roles: dict, category: str, step: float, *, up: int = 2, side: int = 0) -> dict[str, dict]:
    """Part edits built from :func:`keypoint_roles`: ``{name: {keypoint index: (3,) offset}}``.

    Chairs: ``taller_back`` (the top group up), ``longer_legs`` (the bottom group down), ``wider_seat`` (the group
    above the feet outward along the side axis); tables: ``taller`` (the top up), ``wider_top`` (the top outward).
    ``step`` is the length of each keypoint's offset. Keypoints on the mirror plane do not move outward.
    """
    if category not in _SEMANTIC:
        raise InputError(f"semantic edits are defined for {sorted(_SEMANTIC)}; got {category!r}")
    out = {}
    for name, role, direction in _SEMANTIC[category]:
        edit = {}
        for index in roles[role].tolist():
            offset = np.zeros(3)
            if direction == "out":
                offset[side] = step * roles["sides"][index]
            else:
                offset[up] = step if direction == "up" else -step
            if offset.any():
                edit[int(index)] = offset
        out[name] = edit
    return out


class PriorResponse(NamedTuple):
    """How a synchronised edit of one keypoint moved the others (:func:`prior_response`).

    - partner : the mirror partner's displacement along the mirrored move, relative to the move (1 = mirrored exactly).
    - others : mean displacement length of the other keypoints (neither the moved one nor its partner), relative to the
      move (0 = they stay).
    """

    partner: float
    others: float


def prior_response(before: Any, after: Any, index: int, partner: int, move: Any, *,
                   mirror_axis: int = 0) -> PriorResponse:
    """Response of the keypoints to a synchronised single-keypoint move.

    Parameters
    ----------
    before, after : (K, 3) float64, keypoints before and after ``KeypointPrior.sync`` of the move.
    index : the moved keypoint; ``partner`` its mirror partner (``KeypointPrior.mirror_permutation_[index]``, which
        must differ from ``index``).
    move : (3,) float64, the move given to ``index``.
    mirror_axis : the mirror's axis (0 = x).
    """
    kp0, kp1 = as_points(before, "before"), as_points(after, "after")
    if kp0.shape != kp1.shape:
        raise InputError(f"before and after must have the same shape; got {kp0.shape} and {kp1.shape}")
    k = len(kp0)
    if not (0 <= index < k and 0 <= partner < k and index != partner):
        raise InputError(f"index and partner must be two different keypoints of {k}; got {index} and {partner}")
    d = np.asarray(move, dtype=np.float64)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.linalg.norm(d) > 0:
        raise InputError(f"move must be 3 finite numbers, not all zero; got {np.shape(move)}")
    mirrored = d.copy()
    mirrored[mirror_axis] *= -1.0
    delta = kp1 - kp0  # (K, 3)
    others = np.delete(np.linalg.norm(delta, axis=1), [index, partner])
    size = float(np.linalg.norm(d))
    return PriorResponse(float(delta[partner] @ mirrored / size**2),
                         float(others.mean() / size) if len(others) else 0.0)


def _segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """(n,) distances between segments p1-q1 and p2-q2, each (n, 3) (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2)
    f, c, b = np.einsum("ij,ij->i", d2, r), np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d1, d2)
    tiny = 1e-30
    denom = a * e - b * b
    s = np.where(denom > tiny, np.clip((b * f - c * e) / np.maximum(denom, tiny), 0.0, 1.0), 0.0)
    t = np.where(e > tiny, (b * s + f) / np.maximum(e, tiny), 0.0)
    s = np.where(t < 0.0, np.clip(-c / np.maximum(a, tiny), 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / np.maximum(
        a, tiny), 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p1 + d1 * s[:, None] - (p2 + d2 * t[:, None]), axis=1)


def triangle_distance(a: Any, b: Any) -> np.ndarray:
    """(n,) float64: distance between the disjoint triangles ``a[i]`` and ``b[i]``, each (n, 3, 3).

    The distance of two disjoint triangles is attained between a vertex and the other triangle or between two
    edges, the cases computed here (for intersecting triangles the result is not 0 in general: test intersection
    first).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    best = np.full(len(a), np.inf)
    for x, y in ((a, b), (b, a)):
        for i in range(3):
            q = _closest_on_triangles(x[:, i], y[:, 0], y[:, 1], y[:, 2])  # (n, 3)
            np.minimum(best, np.linalg.norm(q - x[:, i], axis=1), out=best)
    for i in range(3):
        for j in range(3):
            d = _segment_distance(a[:, i], a[:, (i + 1) % 3], b[:, j], b[:, (j + 1) % 3])
            np.minimum(best, d, out=best)
    return best


def new_self_intersections(rest: Any, deformed: Any, triangles: Any, *, separation: float = 0.05) -> int:
    """Pairs of triangles that intersect after an edit but were apart before (Open3D's triangle-triangle test).

    CAD meshes intersect themselves as given (parts pushed into each other) and many parts only touch, so moving
    them creates contacts that break nothing. A pair counts only if it did not intersect in the rest shape and its
    triangles were more than ``separation`` apart there (exact triangle distance, in the mesh's units; 0.05 = 2.5%
    of the [-1, 1] box): a positive count means the edit pushed one part of the surface through another.
    """
    import open3d as o3d

    v0, v1, tri = _mesh_pair(rest, deformed, triangles)

    def pairs(vertices: np.ndarray) -> set:
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tri))
        found = np.sort(np.asarray(mesh.get_self_intersecting_triangles()), axis=1)
        return set(map(tuple, found.tolist()))

    new = np.array(sorted(pairs(v1) - pairs(v0)), dtype=np.int64).reshape(-1, 2)
    if not len(new):
        return 0
    apart = triangle_distance(v0[tri[new[:, 0]]], v0[tri[new[:, 1]]]) > separation
    return int(apart.sum())


def keypoint_set_distance(sets: Any, reference_sets: Any) -> np.ndarray:
    """(S,) float64: for each keypoint set, the mean keypoint distance to the nearest reference set.

    With the training shapes' keypoint sets as the reference this says how far sampled keypoint sets stray from the
    category's distribution (compare held-out shapes' own keypoints, which are real shapes).
    """
    a = _keypoint_sets(sets, "sets")
    b = _keypoint_sets(reference_sets, "reference_sets")
    if a.shape[1:] != b.shape[1:]:
        raise InputError(f"sets and reference_sets must have the same K; got {a.shape} and {b.shape}")
    out = np.empty(len(a))
    for i, s in enumerate(a):
        out[i] = np.linalg.norm(b - s, axis=2).mean(axis=1).min()
    return out
