"""Straightening of sliver triangles: the smallest smooth correction of a rig's edit basis that keeps them from
turning over in edits (:func:`straighten_basis`), with its slow twin (:func:`straighten_basis_reference`).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

from kpd.errors import InputError
from kpd.geometry import as_points
from kpd.grouping import first_occurrence_groups, merge_coincident, same_corners
from kpd.straighten_kernels import (  # noqa: F401  (the kernels, importable from here as before)
    _graph_pattern, _corners, _entry, _sliver_weight, _sliver_terms, _row, _submatrix, _region_parts, _rings,
    _beyond_rim, _held_rhs, _has_outside, _rows_times, _sliver_steps, _sliver_seeds, has_sliver,
    _triangle_shapes)

__all__ = ["straighten_basis", "straighten_basis_reference", "StraightenSystem", "merged_system", "straighten_system",
           "has_sliver", "STRAIGHTEN_THINNESS", "STRAIGHTEN_REACH", "STRAIGHTEN_TOLERANCE"]

log = logging.getLogger(__name__)

STRAIGHTEN_THINNESS = 0.1  # a triangle is a sliver when its height is below this share of its longest edge
STRAIGHTEN_REACH = 0.1  # how far a sliver's straightening spreads over the surface, [-1, 1] box units
STRAIGHTEN_TOLERANCE = 1e-6  # the straightening is solved where it changes the basis by more than this (0: everywhere)
_STRAIGHTEN_ENDS = 20.0  # how much more firmly the ends of straight runs (never a sliver's third corner) are held
_STRAIGHTEN_CAP = 1e8  # largest weight of one sliver's straightness (a collinear triangle's weight is infinite)


def straighten_basis(
    basis: Any,
    vertices: Any,
    triangles: Any,
    *,
    thinness: float = STRAIGHTEN_THINNESS,
    reach: float = STRAIGHTEN_REACH,
    tolerance: float = STRAIGHTEN_TOLERANCE,
) -> np.ndarray:
    """The smallest smooth correction of an edit basis that keeps the mesh's sliver triangles from turning over.

    CAD meshes are full of slivers: long triangles whose third corner lies within a fraction of a percent of the
    long edge (strips along a table's edges and legs, fans across lattice panels, collinear runs of vertices). A
    cage deformation is smooth, so it bends a long edge slightly; the mesh draws the edge straight between its two
    ends while the third corner follows the bend, and a bend larger than the sliver's height carries that corner
    across the edge: the triangle turns over and shows as a dark crease. This solves, once per rig, for a
    correction ``D`` of the (V, K) basis (each keypoint's column alike) that makes every sliver's third corner
    move as the linear interpolation of its long edge's ends, spread smoothly over the surface::

        min_D  sum_slivers min((L/h)^2, cap) |B_c + D_c - (1-s)(B_a + D_a) - s(B_b + D_b)|^2
             + sum_edges |D_i - D_j|^2 / l_ij^2  +  sum_v e_v (a_v / mean a) |D_v|^2 / reach^2

    with ``a, b`` the ends of a sliver's longest edge (length ``L``), ``c`` its third corner at height ``h`` and
    projected at ``s`` along it, ``l_ij`` the mesh's edge lengths and ``a_v`` the vertices' areas. The edge term
    keeps small details moving with their neighbours (a correction of the corners alone folds the small triangles
    around them); the last term keeps the correction within about ``reach`` of the slivers, so that a keypoint's
    move reaches no farther than before. ``e_v`` is 20 for the vertices that are never a sliver's third corner (the
    ends of straight runs: a leg's foot, a panel's corner) and 1 otherwise, so that a run is straightened by moving
    its middle rather than its ends: a chair's feet stay on the floor when its back is raised. Straight features
    (a table's top edge, a lattice's slats, a leg) stay straight.
    A translation is kept exactly; any other affine motion (which turns nothing over) changes by no more than a
    sliver's height times its gradient across the sliver: the straightness asks a sliver to keep its thickness.
    (Asking instead for the smooth field's own change across each sliver needs one more MVC evaluation per sliver,
    about as many as vertices on a CAD mesh, for the same folds and leakage.)

    The system is solved on the mesh with coincident vertices merged (CAD meshes store one vertex per corner), so
    the corrected mesh has no cracks. ``thinness`` (0.1), ``reach`` (0.1) and the ends' 20 were chosen on ModelNet10
    training chairs and tables (docs/results.md, edit quality): 20 is the smallest end weight that keeps a chair's
    feet within 1% of a raise of its back.

    The system is solved where it matters, not over every vertex: around the slivers whose own term alone would
    move one of their corners by more than ``tolerance`` (a vertex offset per unit keypoint offset; one Jacobi
    step: the straightness times the sliver's weight over the corner's diagonal entry), or move the third corner
    across the sliver's height in a move of half the model box of every keypoint, grown until the correction just
    outside is below ``tolerance`` (:class:`StraightenSystem`). On a native mesh a thin sliver's weight is most of
    its corners' diagonal, and that step is its straightness itself. On a real scan only a few percent of the
    triangles are slivers, so only a small part of the points is solved; the result differs from the solve over
    every piece with a sliver (``tolerance=0``) by the many slivers left out, each moving the correction by less
    than ``tolerance``, and by the region's growth solved as patches with the rest held (the tests bound it by
    1e-4). A CAD mesh subdivided to a scan's size keeps a sliver in every triangle of a sliver, but the edges
    around each one grow stiffer with each subdivision, and their many small terms add up to a smooth correction
    that turns no triangle over: there a larger part of the points is solved, and no more triangles turn over in
    single moves than with the solve over every piece.

    Parameters
    ----------
    basis : (V, K) float64, vertex offset per unit keypoint offset (:attr:`Rig.basis`).
    vertices : (V, 3) float64, rest vertices in the model frame.
    triangles : (T, 3) int, the mesh's triangles.
    thinness : a triangle is a sliver when its height is below ``thinness`` times its longest edge (0 < t <= 1).
    reach : (> 0) spread of the correction, in the units of ``vertices``.
    tolerance : (>= 0) the correction is solved for where it exceeds this; 0 solves every connected piece that has
        a sliver, exactly.

    Returns
    -------
    (V, K) float64, the corrected basis (``basis`` itself, not a copy, when the mesh has no sliver).
    """
    basis, vertices, triangles = _check_straighten(basis, vertices, triangles, thinness, reach)
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise InputError(f"the straightening's tolerance must be a number >= 0; got {tolerance!r}")
    if not len(triangles) or not has_sliver(np.ascontiguousarray(vertices), triangles, float(thinness)):
        return basis  # no sliver (the cheap test first: merging below does not make new ones)
    points, inverse = _distinct_in_order(vertices)  # in the mesh's order, as Rig.bind
    first = np.zeros(len(points), dtype=np.int64)
    first[inverse[::-1]] = np.arange(len(vertices))[::-1]  # one vertex per merged point
    merged = np.ascontiguousarray(basis[first])  # coincident vertices have the same basis rows
    changed = _straighten_merged(merged, points, inverse[triangles], thinness, reach, tolerance)
    return merged[inverse] if changed else basis


def _straighten_merged(basis: np.ndarray, points: np.ndarray, triangles: np.ndarray, thinness: float, reach: float,
                       tolerance: float) -> bool:
    """:func:`straighten_basis` of the (n, K) basis of distinct ``points`` (n, 3), ``triangles`` indexing them, in
    place: only the rows of the points solved change. Returns whether there was a sliver to straighten."""
    return straighten_system(StraightenSystem(points, triangles, thinness, reach), basis, tolerance)


def merged_system(points: np.ndarray, triangles: np.ndarray, inverse: np.ndarray | None) -> "StraightenSystem":
    """The straightening's system, with the default thinness and reach, of a mesh's ``triangles`` (T, 3) int64 on
    its distinct ``points`` (n, 3): ``inverse`` (V,) maps each vertex to its point (None when no two vertices
    coincide). It does not depend on the basis, so it can be made while the basis is computed."""
    return StraightenSystem(points, triangles, STRAIGHTEN_THINNESS, STRAIGHTEN_REACH, point_of=inverse)


def straighten_system(system: "StraightenSystem", basis: np.ndarray, tolerance: float) -> bool:
    """Add the straightening's correction to ``basis`` (n, K) float64 of the system's points, in place: only the rows
    of the points solved change (:meth:`StraightenSystem.solve` with ``tolerance``). Returns whether there was a
    sliver to straighten."""
    if system.slivers == 0:
        return False
    correction = system.solve(basis, float(tolerance))
    basis[correction.rows] += correction.values
    return True


class _Correction:
    """The straightening's correction of the points solved so far, zero elsewhere: ``values`` (m, K), the rows of
    the points ``rows`` (m,), and each point's row in ``slot`` (n,) (-1: not solved). On a scan the region is a few
    percent of the points: an (n, K) array, faulted in page by page where the region's points fall and then added
    whole, takes longer than the region's solve."""

    def __init__(self, n: int, k: int) -> None:
        self.slot = np.full(n, -1, dtype=np.int64)
        self.rows = np.zeros(0, dtype=np.int64)
        self.values = np.zeros((0, k))

    def reserve(self, points: np.ndarray) -> None:
        """Rows for those of ``points`` (p,) int64 that have none, zero until set (before threads set them)."""
        new = points[self.slot[points] < 0]
        if len(new):
            self.slot[new] = np.arange(len(self.rows), len(self.rows) + len(new))
            self.rows = np.concatenate([self.rows, new])
            self.values = np.concatenate([self.values, np.zeros((len(new), self.values.shape[1]))])

    def set(self, points: np.ndarray, values: np.ndarray) -> None:
        """The correction of ``points`` (p,) int64 is ``values`` (p, K) (rows reserved for them already, or now)."""
        self.reserve(points)
        self.values[self.slot[points]] = values


def _factorised(system: Any) -> Callable[[np.ndarray], np.ndarray]:
    """``solve(rhs)`` for ``system``, a symmetric positive definite sparse matrix (CSC, both triangles): ``rhs`` (n, K)
    to (n, K), by QDLDL's LDLᵀ factorisation in an approximate minimum-degree order (which lets go of the GIL).
    Half the time of SuperLU's LU in its symmetric mode on the straightening's systems, to the same solution
    within rounding."""
    import qdldl

    factor = qdldl.Solver(system)

    def solve(rhs: np.ndarray) -> np.ndarray:
        out = np.empty(rhs.shape)
        for k in range(rhs.shape[1]):
            out[:, k] = factor.solve(np.ascontiguousarray(rhs[:, k]))
        return out

    return solve


def _check_straighten(basis: Any, vertices: Any, triangles: Any, thinness: float, reach: float) -> tuple:
    basis = np.asarray(basis, dtype=np.float64)
    vertices = as_points(vertices, "vertices")
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if basis.ndim != 2 or len(basis) != len(vertices):
        raise InputError(f"basis must be (V, K) for {len(vertices)} vertices; got {basis.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or (len(triangles) and (triangles.min() < 0 or
                                                                                triangles.max() >= len(vertices))):
        raise InputError(f"triangles must be (T, 3) indices into {len(vertices)} vertices")
    if not (np.isfinite(thinness) and 0 < thinness <= 1 and np.isfinite(reach) and reach > 0):
        raise InputError(f"straightening needs 0 < thinness <= 1 and reach > 0; got {thinness!r}, {reach!r}")
    return basis, vertices, triangles


_SOLVE_BATCH = 1 << 17  # merged points per sparse factorisation: small connected pieces are solved together
_MAX_SOLVE_THREADS = 2
_SEEDS_ON_TWO_THREADS = 200_000  # slivers: fewer are judged on one thread
_FOLD_MOVE = 1.0  # a sliver that a move this large (half the model box) of every keypoint would turn over: straightened
_WHOLE_PIECE = 0.5  # a connected piece whose points the region covers more than this share of is solved whole
_FIRST_RINGS = 2  # the region first reaches this many edges from the slivers to straighten
_GROW_RINGS = 2  # then grows by this many edges where the correction just outside it is above the tolerance
_MAX_GROW_RINGS = 8  # and twice as many each further step, up to this many
_PATCH_RINGS = 4  # a growth is solved with the region's points this many edges around it, the rest held


class StraightenSystem:
    """The straightening's sparse system (:func:`straighten_basis`) on the merged points, solved where it matters.

    The system's pattern is the mesh's edge graph with its diagonal (a sliver's three corners are a triangle, so its
    straightness couples only neighbours); compiled kernels find the edges, add the slivers' part ``SᵀWS`` into that
    pattern and each point's anchor in one pass over the triangles, and make the rest of a row (the edges'
    stiffness) only when the row is solved.

    :meth:`solve` solves on a region (:func:`straighten_basis`): the points within two edges of the slivers whose
    own term moves a corner by more than ``tolerance`` (one Jacobi step from no correction) or that a large edit
    would turn over, with no correction beyond it; where the points just outside would still move by more than
    ``tolerance`` (one Jacobi step from the region's correction), the region grows from them by two edges (twice
    as far each further step, up to eight), and a patch of the region four edges around the growth is solved with
    the correction elsewhere held (a block Gauss-Seidel step: the growth moves the points farther inside by less
    than the tolerance), until nothing beyond the rim is above it. The first region's connected parts are
    factorised on their own, packed into batches (at least one per thread, the largest parts first), two batches at
    a time (:func:`_factorised`: an LDLᵀ factorisation in an approximate minimum-degree order, which does not
    depend on how the points are numbered); a connected piece of the mesh that the first region covers more than
    half of is taken whole.
    """

    def __init__(self, points: np.ndarray, tri: np.ndarray, thinness: float, reach: float,
                 point_of: np.ndarray | None = None) -> None:
        """``points`` (n, 3) distinct, ``tri`` (T, 3) int64 indexing them (repeated corners allowed: skipped); or
        indexing a mesh's vertices, each vertex ``v`` at point ``point_of[v]`` (the triangles are not renumbered
        into a copy: the kernels look the points up)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        self.reach = float(reach)
        n = self.n = len(points)
        tri = np.ascontiguousarray(tri, dtype=np.int64)
        point_of = np.zeros(0, np.int64) if point_of is None else np.ascontiguousarray(point_of, dtype=np.int64)
        # a triangle stored again over the same corners (ShapeNet's meshes store every face twice, once each way
        # round) is counted with its first copy: the same system in half the passes
        same = np.empty(len(tri), dtype=np.int64)
        same_corners(tri, point_of if len(point_of) else np.arange(n, dtype=np.int64), n, True, same)
        # (n + 1,), (n + 2E,): each row's neighbours and itself, sorted
        indptr, indices = _graph_pattern(tri, point_of, same, n)
        self.indptr, self.indices, self.points = indptr, indices, points
        self.sliver_values, self.anchor = np.zeros(len(indices)), np.empty(n)  # the rest of a row: _row
        ends, along, height = np.empty((len(tri), 3), dtype=np.int32), np.empty(len(tri)), np.empty(len(tri))
        self.label = np.empty(n, dtype=np.int64)  # connected pieces
        self.slivers, longest = _sliver_terms(points, tri, point_of, same, indptr, indices, float(thinness),
                                              1.0 / reach**2, _STRAIGHTEN_ENDS, _STRAIGHTEN_CAP, self.sliver_values,
                                              self.anchor, ends, along, height, self.label)
        self.floor = 1e-6 * max(longest, 1e-300)  # edge lengths floored at 1e-6 of the longest
        del tri, same
        if self.slivers == 0:
            return
        s = self.slivers
        self.ends, self.along, self.height = ends[:s].copy(), along[:s].copy(), height[:s].copy()  # per sliver
        del ends, along, height
        self.pieces = int(self.label.max()) + 1
        # what the region's seeds need of the system, made here beside the MVC basis, not after it
        self.step = _sliver_steps(points, indptr, indices, self.sliver_values, self.anchor, self.floor, self.ends,
                                  self.along, self.height, _STRAIGHTEN_CAP)

    def solve(self, basis: np.ndarray, tolerance: float) -> _Correction:
        """The correction of the merged points (0 where it is below ``tolerance``; ``tolerance`` 0: every connected
        piece with a sliver, exactly)."""
        merged = np.ascontiguousarray(basis)
        correction = _Correction(self.n, merged.shape[1])
        if tolerance <= 0:
            inside = np.zeros(self.pieces, dtype=bool)
            inside[self.label[self.ends[:, 0]]] = True
            self._solve_region(inside[self.label], inside[self.label], merged, correction)
            return correction
        seeds = np.flatnonzero(self._seeds(merged, float(tolerance)))
        inside = np.zeros(self.n, dtype=bool)
        piece_size = np.bincount(self.label, minlength=self.pieces)
        frontier, rings, first = seeds, _FIRST_RINGS, True
        while len(frontier):
            reached = _rings(self.indptr, self.indices, frontier, rings)
            if first:
                # a piece the region covers mostly is taken whole: solving it whole costs little more than solving
                # that part, and a rim there could make the part grow
                covered = np.bincount(self.label, weights=reached, minlength=self.pieces)
                reached |= (covered > _WHOLE_PIECE * piece_size)[self.label]
                inside |= reached
                del reached
                rim = self._solve_region(inside, inside, merged, correction)
            else:
                # the region grows by a few points: solve a patch around them, holding the correction elsewhere (a
                # block Gauss-Seidel step; the growth's effect on points farther inside is below the tolerance)
                added = reached & ~inside
                inside |= reached
                patch = _rings(self.indptr, self.indices, np.flatnonzero(added), _PATCH_RINGS) & inside
                del reached, added
                rim = self._solve_patch(patch, inside, merged, correction)
            # cut off too soon where the points just outside would move by more than the tolerance (one Jacobi step
            # from the region's correction): grow from there
            frontier = _beyond_rim(self.indptr, self.indices, self.points, self.sliver_values, self.anchor, self.floor,
                                   rim, inside, correction.slot, correction.values, float(tolerance))
            log.debug("straightening: %d seed points, %d rings: %d of %d points solved, %d beyond the rim above %.3g",
                      len(seeds), rings, inside.sum(), self.n, len(frontier), tolerance)
            # a region that keeps growing (along a strip, a few points a step) grows twice as far each step
            rings, first = (_GROW_RINGS if first else min(2 * rings, _MAX_GROW_RINGS)), False
        return correction

    def _seeds(self, merged: np.ndarray, tolerance: float) -> np.ndarray:
        """(n,) bool: :func:`_sliver_seeds` of every sliver, in two halves on two threads when there are many."""
        seed = np.zeros(self.n, dtype=np.bool_)
        args = (merged, self.ends, self.along, self.height, self.step, tolerance, _FOLD_MOVE, seed)
        s = self.slivers
        if s < _SEEDS_ON_TWO_THREADS or (os.cpu_count() or 1) < 2:
            _sliver_seeds(0, s, *args)
            return seed
        with ThreadPoolExecutor(1, thread_name_prefix="kpd-seeds") as pool:
            other = pool.submit(_sliver_seeds, s // 2, s, *args)
            _sliver_seeds(0, s // 2, *args)
            other.result()
        return seed

    def _solve_patch(self, patch: np.ndarray, inside: np.ndarray, basis: np.ndarray,
                     correction: _Correction) -> np.ndarray:
        """Solve, into ``correction``, the points ``patch`` (n,) bool of the region ``inside`` with the
        correction of every other point held as it is. Returns the region's rim within the patch."""
        import scipy.sparse as sparse

        members = np.flatnonzero(patch)
        local = np.full(self.n, -1, dtype=np.int64)
        local[members] = np.arange(len(members))
        ptr, idx, val = _submatrix(self.indptr, self.indices, members, local, self.points, self.sliver_values,
                                   self.anchor, self.floor)
        system = sparse.csc_matrix((val, idx, ptr), shape=(len(members),) * 2)
        solve = _factorised(system)
        rhs = _held_rhs(self.indptr, self.indices, self.points, self.sliver_values, self.anchor, self.floor, members,
                        patch, basis, correction.slot, correction.values)
        correction.set(members, solve(rhs))
        return members[_has_outside(self.indptr, self.indices, members, inside)]

    def _solve_region(self, inside: np.ndarray, added: np.ndarray, basis: np.ndarray,
                      correction: _Correction) -> np.ndarray:
        """Solve, into ``correction``, the connected parts of the region ``inside`` (n,) bool that hold an
        ``added`` (n,) point, with no correction outside the region; the other parts keep theirs. Returns the
        region's rim: its points next to points outside it."""
        import scipy.sparse as sparse

        part, rim = _region_parts(self.indptr, self.indices, inside)  # (n,) -1 outside; (n,) bool
        parts = int(part.max()) + 1 if len(part) else 0
        changed = np.zeros(parts + 1, dtype=bool)
        changed[part[added]] = True
        part = np.where(changed[part], part, -1)  # only the parts with an added point are solved (again)
        sizes = np.bincount(part[part >= 0], minlength=parts)
        # the parts packed into batches of about _SOLVE_BATCH points, and at least one per thread: the largest first,
        # each into the batch with the fewest points so far (a part is never split: fill-in does not cross parts)
        threads = min(_MAX_SOLVE_THREADS, os.cpu_count() or 1)
        total, nonempty = int(sizes.sum()), int(np.count_nonzero(sizes))
        batches = min(max(-(-total // _SOLVE_BATCH), threads), nonempty)
        batch_of_part = np.zeros(parts, dtype=np.int64)
        filled = [0] * batches
        for p in np.argsort(-sizes, kind="stable")[:nonempty].tolist():
            b = min(range(batches), key=filled.__getitem__)
            batch_of_part[p] = b
            filled[b] += int(sizes[p])
        point_batch = np.where(part >= 0, batch_of_part[np.maximum(part, 0)], -1)
        order = np.argsort(point_batch, kind="stable")  # each batch's points in ascending order
        bounds = np.searchsorted(point_batch[order], np.arange(batches + 1))
        local = np.full(self.n, -1, dtype=np.int64)

        def solve_batch(b: int) -> None:
            # each batch numbers its own points (a point's neighbours in the region are in its part, so its batch)
            members = order[bounds[b]:bounds[b + 1]]
            local[members] = np.arange(len(members))
            ptr, idx, val = _submatrix(self.indptr, self.indices, members, local, self.points, self.sliver_values,
                                       self.anchor, self.floor)
            system = sparse.csc_matrix((val, idx, ptr), shape=(len(members),) * 2)  # symmetric: CSR rows = columns
            solve = _factorised(system)
            rhs = _rows_times(self.indptr, self.indices, self.sliver_values, members, basis)  # -Sᵀ W S B
            correction.values[correction.slot[members]] = solve(rhs)  # rows of their own: no lock

        correction.reserve(order[bounds[0]:bounds[batches]] if batches else order[:0])
        # QDLDL lets go of the GIL: two batches at a time on two cores, the largest first
        largest_first = sorted(range(batches), key=lambda b: bounds[b] - bounds[b + 1])
        threads = min(threads, batches)
        if threads <= 1:
            for b in largest_first:
                solve_batch(b)
        else:
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(solve_batch, largest_first))
        return np.flatnonzero(rim)


def straighten_basis_reference(basis: Any, vertices: Any, triangles: Any, *, thinness: float = STRAIGHTEN_THINNESS,
                               reach: float = STRAIGHTEN_REACH) -> np.ndarray:
    """:func:`straighten_basis` as one sparse LU over every merged point (the slow twin tests compare with)."""
    import scipy.sparse as sparse
    from scipy.sparse.linalg import splu

    basis, vertices, triangles = _check_straighten(basis, vertices, triangles, thinness, reach)
    if not len(triangles) or not _thin_triangles(vertices, triangles, thinness)[0].any():
        return basis  # no sliver (the cheap test first: merging below does not make new ones)
    points, inverse = merge_coincident(vertices)
    tri = inverse[triangles]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])]
    if not len(tri):
        return basis
    n = len(points)
    thin, apex, longest, height, twice_area = _thin_triangles(points, tri, thinness)
    sliver = np.flatnonzero(thin)
    if not len(sliver):
        return basis
    corner = tri[sliver, apex[sliver]]
    start, end = tri[sliver, (apex[sliver] + 1) % 3], tri[sliver, (apex[sliver] + 2) % 3]
    edge = points[end] - points[start]
    s = np.clip(np.einsum("ij,ij->i", points[corner] - points[start], edge) / np.einsum("ij,ij->i", edge, edge), 0, 1)
    weight = (longest[sliver] / np.maximum(height[sliver], longest[sliver] / np.sqrt(_STRAIGHTEN_CAP))) ** 2
    count = len(sliver)
    straight = sparse.csr_matrix(
        (np.stack([np.ones(count), s - 1.0, -s], axis=1).ravel(),
         (np.repeat(np.arange(count), 3), np.stack([corner, start, end], axis=1).ravel())), shape=(count, n))
    first = np.zeros(n, dtype=np.int64)
    first[inverse[::-1]] = np.arange(len(vertices))[::-1]  # one original vertex per merged point
    merged = basis[first]  # (n, K): coincident vertices have the same basis rows
    residual = straight @ merged  # (count, K)
    pairs = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)  # (3T, 2)
    keys = np.unique(pairs[:, 0] * n + pairs[:, 1])
    edges = np.stack([keys // n, keys % n], axis=1)  # (E, 2) each edge once
    length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    length = np.maximum(length, 1e-6 * max(float(length.max()), 1e-300))
    difference = sparse.csr_matrix(
        (np.tile([1.0, -1.0], len(edges)), (np.repeat(np.arange(len(edges)), 2), edges.ravel())),
        shape=(len(edges), n))
    area = np.zeros(n)
    for i in range(3):
        np.add.at(area, tri[:, i], twice_area / 6.0)
    ends = np.ones(n, dtype=bool)
    ends[corner] = False  # never a sliver's third corner: a leg's foot, a panel's corner, a run's end
    anchor = (area / max(float(area.mean()), 1e-300) + 1e-6) * np.where(ends, _STRAIGHTEN_ENDS, 1.0) / reach**2
    system = (sparse.diags(anchor) + difference.T @ sparse.diags(1.0 / length**2) @ difference
              + straight.T @ sparse.diags(weight) @ straight).tocsc()
    correction = splu(system).solve(-(straight.T @ (weight[:, None] * residual)))  # (n, K)
    return basis + correction[inverse]


def _thin_triangles(points: np.ndarray, tri: np.ndarray, thinness: float) -> tuple[np.ndarray, ...]:
    """Per triangle: sliver or not, the corner opposite the longest edge, that edge's length, the height over it
    and twice the area, all (T,)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    tri = np.ascontiguousarray(tri, dtype=np.int64)
    apex = np.empty(len(tri), dtype=np.int64)
    longest, twice_area = np.empty(len(tri)), np.empty(len(tri))
    _triangle_shapes(points, tri, apex, longest, twice_area)
    height = twice_area / np.maximum(longest, 1e-300)
    return height < thinness * longest, apex, longest, height, twice_area


def _distinct_in_order(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct positions (n, 3) in order of first occurrence and, per vertex, the index of its position (V,);
    ``vertices`` itself and ``arange(V)`` when no two coincide."""
    first, index = first_occurrence_groups(vertices)
    return (vertices if len(first) == len(vertices) else vertices[first]), index
