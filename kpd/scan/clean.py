"""Cleaning a scan: statistical outlier removal (point sets), a dominant ground plane found by RANSAC, and small
disconnected pieces (meshes); every step switchable and reported."""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple

import numpy as np
import open3d as o3d
from scipy.spatial import ConvexHull

from kpd._compiled import compiled_on_first_call
from kpd.errors import InputError
from kpd.geometry import _double_areas, bounds
from kpd.scan.rotations import parse_axis
from kpd.scan.shapes import _is_mesh, _shape_points, _shape_points_raw, _take_points, _take_triangles

__all__ = ["CleanReport", "CleanResult", "clean"]

log = logging.getLogger("kpd.scan")


class CleanReport(NamedTuple):
    """What :func:`clean` did; counts are points for point sets and vertices for meshes.

    input_count, output_count : int
    outliers_removed : int, or None when the step was off or does not apply (meshes)
    ground_removed : int, or None when the step was off
    ground_plane : (a, b, c, d) with ax + by + cz + d = 0 of the removed plane, or None
    ground_note : why a plane was or was not taken as the ground
    pieces_removed : number of small disconnected pieces dropped (meshes), or None
    pieces_vertices_removed : vertices dropped with them, or None
    """

    input_count: int
    output_count: int
    outliers_removed: int | None
    ground_removed: int | None
    ground_plane: tuple[float, float, float, float] | None
    ground_note: str
    pieces_removed: int | None
    pieces_vertices_removed: int | None

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self._asdict().items()}


class CleanResult(NamedTuple):
    shape: Any
    report: CleanReport


def _pcd(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


def _hull_area(points2d: np.ndarray) -> float:
    if len(points2d) < 3:
        return 0.0
    try:
        return float(ConvexHull(points2d).volume)  # the "volume" of a 2D hull is its area
    except Exception as exc:  # noqa: BLE001 - qhull raises its own QhullError for flat or degenerate input
        if type(exc).__name__ != "QhullError":
            raise
        return 0.0


def _find_ground(
    points: np.ndarray, *, distance: float, up: np.ndarray | None, min_share: float, one_side: float,
    area_ratio: float, iterations: int, seed: int,
) -> tuple[np.ndarray | None, tuple | None, str]:
    """Inlier mask of a ground plane, the plane, and a note. The dominant RANSAC plane is the ground only if it holds
    ``min_share`` of the points, nearly all the other points lie on one side of it (the object rests on it), its
    in-plane extent is ``area_ratio`` times the footprint of the rest (it reaches beyond the object), and, when ``up``
    is known, it faces up with the object above it."""
    if len(points) < 50:
        return None, None, f"too few points ({len(points)}) to look for a ground plane"
    o3d.utility.random.seed(seed)
    model, inliers = _pcd(points).segment_plane(distance, 3, iterations)
    normal, offset = np.asarray(model[:3], dtype=np.float64), float(model[3])
    norm = np.linalg.norm(normal)
    if not norm > 0:
        return None, None, "no plane found"
    normal, offset = normal / norm, offset / norm
    mask = np.zeros(len(points), dtype=bool)
    mask[np.asarray(inliers, dtype=np.int64)] = True
    share = mask.mean()
    plane = tuple(float(v) for v in (*normal, offset))
    if share < min_share:
        return None, plane, f"dominant plane holds {share:.1%} of the points (< {min_share:.0%}): not a ground"
    rest = points[~mask]
    if len(rest) < 10:
        if up is not None and abs(float(np.dot(normal, up))) < math.cos(math.radians(30.0)):
            return None, plane, "the scan is (almost) only a plane, and not a horizontal one: not removed"
        return np.ones(len(points), dtype=bool), plane, "the scan is (almost) only a ground plane: all removed"
    signed = rest @ normal + offset  # (N',)
    above = float((signed > 0).mean())
    if above < 0.5:
        normal, offset, signed, above = -normal, -offset, -signed, 1.0 - above
        plane = tuple(float(v) for v in (*normal, offset))
    if above < one_side:
        return None, plane, f"only {above:.1%} of the other points lie on one side of the dominant plane: not a ground"
    if up is not None:
        tilt = float(np.degrees(np.arccos(np.clip(np.dot(normal, up), -1.0, 1.0))))
        if tilt > 30.0:
            return None, plane, (f"the dominant plane is {tilt:.0f} degrees from the up axis with the object above: "
                                 "not a ground")
    basis = np.linalg.svd(normal[None, :])[2][1:]  # (2, 3) in-plane axes
    ground_area = _hull_area(points[mask] @ basis.T)
    footprint = _hull_area(rest @ basis.T)
    if ground_area < area_ratio * footprint:
        return None, plane, (f"the dominant plane covers {ground_area / max(footprint, 1e-300):.2f} x the footprint of "
                             f"the rest (< {area_ratio}): a part of the object, not a ground")
    # take also the points just below the plane (sensor noise under the floor) that the distance threshold missed
    below = points @ normal + offset < distance
    return mask | below, plane, f"ground plane with {int((mask | below).sum())} points removed"


def _triangle_pieces(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected pieces of a mesh, (T,) piece label per triangle and the number of pieces. Vertices at the same
    position are welded first, so that the copies a scanner makes along texture seams do not split a surface."""
    if len(triangles) == 0:
        return np.zeros(0, dtype=np.int64), 0
    from kpd.geometry import mesh_pieces
    from kpd.grouping import coincident_first

    extent = float(max(vertices.max(), -vertices.min())) or 1.0
    keys = np.round(vertices / (1e-9 * extent))  # integers below 2**53: exact as float64
    welded = coincident_first(keys)  # (V,) the first vertex at each position
    labels = mesh_pieces(welded[triangles])  # a compiled union-find, one pass
    return labels, int(labels.max()) + 1


def _scene(vertices: np.ndarray, triangles: np.ndarray) -> Any:
    """Open3D's raycasting scene of the given triangles, for exact distances to their surface (:func:`_distances`)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene


def _distances(scene: Any, queries: np.ndarray) -> np.ndarray:
    """(Q,) exact distance from each query point (Q, 3) to the scene's surface."""
    return scene.compute_distance(o3d.core.Tensor(queries.astype(np.float32))).numpy().astype(np.float64)


_GRID_CELLS = 256  # at most this many cells along an axis in _near_triangles


def _near_triangles(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray, gap: float) -> np.ndarray:
    """(T,) bool: the triangles that may come within ``gap`` of one of ``points`` (Q, 3), so that the distances up to
    ``gap`` over them alone are those over all: their search structure costs less to build (about half the
    triangles of a dense CAD mesh's parts).

    On a grid of cells a little wider than ``gap`` (so that float32 rounding of a distance within ``gap`` stays within
    a cell), a point of a triangle within ``gap`` of a query point lies in the query point's cell or one next to it;
    a triangle is kept when its bounding box meets such a cell. Cells are widened to keep the grid within
    :data:`_GRID_CELLS` along each axis (the property holds for any width above ``gap``)."""
    lo = np.minimum(points.min(axis=0), vertices.min(axis=0))
    hi = np.maximum(points.max(axis=0), vertices.max(axis=0))
    cell = max(1.001 * gap, float((hi - lo).max()) / _GRID_CELLS, 1e-300)
    shape = (np.floor((hi - lo) / cell).astype(np.int64) + 3)  # a border of one cell on each side
    near = np.zeros(tuple(shape), dtype=np.bool_)
    index = np.floor((points - lo) / cell).astype(np.int64) + 1
    for dx in (-1, 0, 1):  # the points' cells and their neighbours
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                near[index[:, 0] + dx, index[:, 1] + dy, index[:, 2] + dz] = True
    keep = np.empty(len(triangles), dtype=np.bool_)
    _boxes_meet(vertices, np.ascontiguousarray(triangles, dtype=np.int64), lo, 1.0 / cell, near, keep)
    return keep


@compiled_on_first_call
def _boxes_meet(vertices, triangles, lo, inverse_cell, near, keep):  # pragma: no cover - compiled
    """``keep[t]``: whether triangle t's bounding box meets a cell of ``near`` (cells of 1 / ``inverse_cell`` from
    ``lo``, with a border of one cell)."""
    nx, ny, nz = near.shape
    for t in range(triangles.shape[0]):
        a0 = a1 = b0 = b1 = c0 = c1 = 0
        for k in range(3):
            v = triangles[t, k]
            i = int(np.floor((vertices[v, 0] - lo[0]) * inverse_cell)) + 1
            j = int(np.floor((vertices[v, 1] - lo[1]) * inverse_cell)) + 1
            m = int(np.floor((vertices[v, 2] - lo[2]) * inverse_cell)) + 1
            if k == 0:
                a0, a1, b0, b1, c0, c1 = i, i, j, j, m, m
            else:
                a0, a1, b0, b1, c0, c1 = min(a0, i), max(a1, i), min(b0, j), max(b1, j), min(c0, m), max(c1, m)
        found = False
        for i in range(max(a0, 0), min(a1, nx - 1) + 1):
            for j in range(max(b0, 0), min(b1, ny - 1) + 1):
                for m in range(max(c0, 0), min(c1, nz - 1) + 1):
                    found |= near[i, j, m]
        keep[t] = found


_PROBES = 256  # vertices of each piece looked at first (evenly through its vertices)


def _touching(scene: Any, points: np.ndarray, piece: np.ndarray, gap: float) -> np.ndarray:
    """The pieces (sorted, distinct) with a point within ``gap`` of the scene's triangles: ``points`` (Q, 3), each
    of piece ``piece`` (Q,). Up to :data:`_PROBES` points of each piece are looked at first, then every point of the
    pieces not found touching so: the same pieces as looking at every point, for a few thousand distances where
    most pieces touch."""
    order = np.argsort(piece, kind="stable")
    sorted_piece = piece[order]
    starts = np.flatnonzero(np.r_[True, sorted_piece[1:] != sorted_piece[:-1]])  # each piece's first position
    counts = np.diff(np.r_[starts, len(order)])
    rank = np.arange(len(order)) - np.repeat(starts, counts)  # each point's place among its piece's points
    step = np.repeat(np.maximum(counts // _PROBES, 1), counts)
    probe = order[rank % step == 0]
    found = np.unique(piece[probe][_distances(scene, points[probe]) <= gap])
    rest = ~np.isin(piece, found)
    if rest.any():
        found = np.union1d(found, piece[rest][_distances(scene, points[rest]) <= gap])
    return found


def _small_pieces(
    vertices: np.ndarray, triangles: np.ndarray, min_piece: float, max_gap: float,
) -> tuple[np.ndarray, int]:
    """(T,) bool mask of the triangles of stray pieces, and how many there are.

    A piece is stray when its area is below ``min_piece`` times the largest piece's and it does not come within
    ``max_gap`` (a fraction of the bounding-box diagonal) of the kept surface, which grows from the large pieces by
    every small piece that touches it. Scan debris floats apart from the object; the parts of a CAD model (a chair's
    feet, bolts, stretchers), modelled as separate pieces, touch the rest and are kept."""
    labels, count = _triangle_pieces(vertices, triangles)
    if count == 0:
        return np.zeros(0, dtype=bool), 0
    area = 0.5 * _double_areas(vertices, triangles)  # (T,): kpd.triangles.areas to the bit, in one compiled pass
    piece_area = np.bincount(labels, weights=area, minlength=count)  # (pieces,)
    small = piece_area < min_piece * piece_area.max()
    if small.any() and max_gap > 0:
        lo, hi = bounds(vertices)
        gap = max_gap * float(np.linalg.norm(hi - lo))
        # the vertices of some triangle (np.unique's, in order, without its sort or hash of 3T indices), and the
        # piece each belongs to
        in_use = np.zeros(len(vertices), dtype=bool)
        in_use[triangles.reshape(-1)] = True
        used = np.flatnonzero(in_use)
        used_piece = np.empty(len(vertices), dtype=np.int64)
        used_piece[triangles.reshape(-1)] = np.repeat(labels, 3)
        used_piece = used_piece[used]
        while small.any():
            query = small[used_piece]  # vertices of the small pieces not yet kept
            points = vertices[used[query]]
            surface = triangles[~small[labels]]
            surface = surface[_near_triangles(vertices, surface, points, gap)]
            if not len(surface):
                break
            touching = _touching(_scene(vertices, surface), points, used_piece[query], gap)
            if len(touching) == 0:
                break
            small[touching] = False
    return small[labels], int(small.sum())


def clean(
    shape: Any,
    *,
    outliers: bool = True,
    neighbors: int = 20,
    std_ratio: float = 2.0,
    ground: bool | None = None,
    ground_distance: float = 0.01,
    ground_min_share: float = 0.05,
    ground_area_ratio: float = 1.3,
    up: Any = None,
    pieces: bool = True,
    min_piece: float = 0.05,
    piece_gap: float = 0.05,
    min_points: int = 10,
    seed: int = 0,
) -> CleanResult:
    """Clean a scan; each step is switchable and reported.

    Parameters
    ----------
    shape : (N, 3) array, ``kpd.io.PointSet`` or ``kpd.io.Mesh``; the result has the same type.
    outliers : statistical outlier removal of point sets (Open3D ``remove_statistical_outlier``): a point goes when its
        mean distance to its ``neighbors`` nearest points exceeds the average by ``std_ratio`` standard deviations.
        Not applied to mesh vertices, whose spacing follows the tessellation; meshes lose small pieces instead.
    ground : remove a dominant plane found by RANSAC if it looks like a ground (see ``_find_ground``). None (the
        default) searches only when ``up`` is known: without it a table top or a seat cannot be told from a floor.
    ground_distance : RANSAC inlier distance as a fraction of the scan's bounding-box diagonal.
    ground_min_share, ground_area_ratio : thresholds of the ground test.
    up : the scan's up axis if known (``'z'``, ``'-y'``, three numbers): the ground must then face up.
    pieces : drop stray pieces of a mesh: connected pieces whose area is below ``min_piece`` times the largest
        piece's and that stay more than ``piece_gap`` (a fraction of the bounding-box diagonal) away from the rest.
        Pieces that touch the object, like the separately modelled parts of a CAD chair, are kept.
    min_points : fewer points (mesh vertices) left than this is an error.
    seed : seeds the RANSAC plane search.

    Returns
    -------
    CleanResult(shape, report)

    Raises
    ------
    InputError
        For points that are not (N, 3) or not finite, and for a scan with fewer than ``min_points`` left.
    """
    points = _shape_points(shape)
    up_vector = None if up is None else parse_axis(up)
    n_in = len(points)
    outliers_removed = ground_removed = pieces_removed = pieces_vertices = None
    plane, note = None, "step off"
    mesh = _is_mesh(shape)

    if mesh and pieces:
        small, pieces_removed = _small_pieces(points, np.asarray(shape.triangles, dtype=np.int64), min_piece,
                                              piece_gap)
        pieces_vertices = 0
        if pieces_removed:
            shape = _take_triangles(shape, ~small)
            pieces_vertices = n_in - len(shape.vertices)
    elif not mesh and outliers:
        if len(points) > neighbors:
            _, kept = _pcd(points).remove_statistical_outlier(neighbors, std_ratio)
            keep = np.zeros(len(points), dtype=bool)
            keep[np.asarray(kept, dtype=np.int64)] = True
            outliers_removed = int((~keep).sum())
            shape = _take_points(shape, keep)
        else:
            outliers_removed = 0

    if ground is None and up_vector is None:
        note = "not searched: the up axis is unknown (give up=..., or ground=True to search anyway)"
    elif ground is not False:
        points = _shape_points_raw(shape)
        if len(points) == 0:
            ground_removed, note = 0, "nothing left to search"
        else:
            lo, hi = bounds(points)
            diagonal = float(np.linalg.norm(hi - lo))
            mask, plane, note = _find_ground(
                points, distance=ground_distance * diagonal, up=up_vector, min_share=ground_min_share,
                one_side=0.98, area_ratio=ground_area_ratio, iterations=1000, seed=seed)
            ground_removed = 0 if mask is None else int(mask.sum())
            if mask is not None:
                if mesh:
                    triangles = np.asarray(shape.triangles, dtype=np.int64)
                    shape = _take_triangles(shape, ~mask[triangles].all(axis=1))
                    ground_removed = len(points) - len(shape.vertices)
                else:
                    shape = _take_points(shape, ~mask)
        log.info("ground: %s", note)

    n_out = len(_shape_points_raw(shape))
    if n_out < min_points:
        raise InputError(f"the scan is (nearly) empty after cleaning: {n_in} point(s) in, {n_out} left, at least "
                         f"{min_points} needed (removed: outliers {outliers_removed}, ground {ground_removed}, "
                         f"small pieces {pieces_vertices}); switch a step off or check the scan")
    report = CleanReport(n_in, n_out, outliers_removed, ground_removed, plane, note, pieces_removed, pieces_vertices)
    log.info("clean: %s", report)
    return CleanResult(shape, report)
