"""Real-scan preprocessing: clean a scan, orient it to a reference shape, normalise it into the model's [-1, 1] frame.

KeypointDeformer assumes that the shapes of a category share one orientation. Real scans arrive in any pose, in any
unit, with noise, stray points, a ground plane and holes. This module

1. cleans a scan (:func:`clean`): statistical outlier removal (point sets), removal of a dominant ground plane found
   by RANSAC, and removal of small disconnected pieces (meshes); every step is switchable and reported;
2. orients it (:class:`ScanAligner`, :func:`orient`): a global search over rotations (principal axes under all 24
   proper signed axis permutations, the 60 rotations of the icosahedral group, and FPFH + RANSAC candidates), every
   hypothesis refined by a trimmed, symmetric ICP (with a scale per axis, since shapes of a category differ in
   proportions) and scored by a trimmed symmetric RMS distance on scale-normalised shapes; when the reference's up
   axis is known, each hypothesis is stood on the scan's own support plane (:func:`support_plane`: the hull faces
   under its lowest points, e.g. between the leg tips) turned onto the reference's, and only its turn about the up
   axis is refined; the best, the runner-up (a rotation more than ``distinct_angle`` degrees away) and the margin
   between them are reported, and a small margin is flagged as ambiguous rather than silently chosen;
3. normalises the rotated scan with :class:`kpd.geometry.Normalizer` (REFERENCE §7) and keeps the full similarity
   transform and its inverse (:func:`preprocess`, :class:`ScanResult`), so that results map back onto the scan.

Everything is numpy (float64) plus Open3D; no torch.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, NamedTuple

import numpy as np
import open3d as o3d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.transform import Rotation

from kpd.errors import InputError, NotFittedError
from kpd.geometry import Normalizer, as_points, as_rng, sample_surface
from kpd.triangles import areas as triangle_areas

__all__ = [
    "AXES",
    "CleanReport",
    "CleanResult",
    "Hypothesis",
    "Orientation",
    "ScanAligner",
    "ScanResult",
    "clean",
    "orient",
    "normalize",
    "preprocess",
    "parse_axis",
    "rotation_angle",
    "proper_signed_permutations",
    "icosahedral_rotations",
    "Support",
    "support_plane",
    "hull_faces",
    "candidate_rotations",
    "reorient",
]

log = logging.getLogger(__name__)

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}

# A relative margin (runner-up score / best score - 1) below this is flagged ambiguous. Calibrated on ModelNet10
# *train* chairs and tables (60 each, outside the reference's pool, clean and corrupted, with and without a known up):
# the smallest threshold of the sweep at which the unflagged results are right >= 95% of the time on clean scans and
# >= 90% on corrupted ones, in both settings (benchmarks/results/scan_calibration.json: 97.6% / 92.3% without up,
# 98.3% / 92.5% with it). benchmarks/bench_scan.py measures it on the test split.
DEFAULT_AMBIGUITY_MARGIN = 0.15

# Surface points a mesh scan is oriented by (area-weighted, so independent of how the mesh spends its vertices).
MESH_ORIENT_SAMPLES = 20000


# --------------------------------------------------------------------------------------------------------------------
# small rotation helpers


def parse_axis(axis: Any, name: str = "up") -> np.ndarray:
    """An axis as a unit (3,) float64 vector from ``'x'``, ``'-z'``, ``'+y'`` or three numbers."""
    if isinstance(axis, str):
        text = axis.strip().lower()
        sign = -1.0 if text.startswith("-") else 1.0
        key = text.lstrip("+-")
        if key not in AXES:
            raise InputError(f"{name} must be one of x, y, z, -x, -y, -z or three numbers; got {axis!r}")
        return sign * np.asarray(AXES[key])
    try:
        vector = np.asarray(axis, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be an axis name or three numbers; got {axis!r}") from exc
    if vector.shape != (3,) or not np.isfinite(vector).all() or not np.linalg.norm(vector) > 0:
        raise InputError(f"{name} must be a non-zero finite 3-vector; got {vector.tolist()}")
    return vector / np.linalg.norm(vector)


def rotation_angle(a: np.ndarray, b: np.ndarray | None = None) -> float:
    """Angle in degrees of the rotation ``a`` (or of ``a @ b.T``, the rotation taking ``b`` to ``a``)."""
    m = a if b is None else a @ b.T
    c = (np.trace(m) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``u`` to unit vector ``v``."""
    axis = np.cross(u, v)
    s, c = np.linalg.norm(axis), float(np.dot(u, v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perpendicular = np.cross(u, [1.0, 0.0, 0.0])
        if np.linalg.norm(perpendicular) < 1e-6:
            perpendicular = np.cross(u, [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(np.pi * perpendicular / np.linalg.norm(perpendicular)).as_matrix()
    return Rotation.from_rotvec(axis / s * math.atan2(s, c)).as_matrix()


def _about(axis: np.ndarray, angle: float) -> np.ndarray:
    return Rotation.from_rotvec(axis * angle).as_matrix()


def proper_signed_permutations() -> np.ndarray:
    """The 24 signed permutation matrices with determinant +1 (the rotation group of the cube), (24, 3, 3)."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            for row, (col, sign) in enumerate(zip(perm, signs)):
                m[row, col] = -1.0 if sign else 1.0
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.stack(out)


def icosahedral_rotations() -> np.ndarray:
    """The 60 rotations of the icosahedral group, (60, 3, 3): a near-uniform coarse grid of SO(3)."""
    phi = (1.0 + 5.0**0.5) / 2.0
    generators = [Rotation.from_rotvec(np.array([0.0, 1.0, phi]) / np.linalg.norm([0.0, 1.0, phi]) * 2 * np.pi / 5),
                  Rotation.from_rotvec(np.array([1.0, 1.0, 1.0]) / 3**0.5 * 2 * np.pi / 3)]
    group = [np.eye(3)]
    frontier = [np.eye(3)]
    while frontier:
        fresh = []
        for g in frontier:
            for h in generators:
                m = h.as_matrix() @ g
                if all(np.abs(m - k).max() > 1e-6 for k in group):
                    group.append(m)
                    fresh.append(m)
        frontier = fresh
    return np.stack(group)


def _principal_frame(points: np.ndarray) -> np.ndarray:
    """Columns: principal axes of centred ``points`` (descending variance), a proper rotation."""
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    frame = vectors[:, ::-1].copy()
    if np.linalg.det(frame) < 0:
        frame[:, 2] *= -1.0
    return frame


def _dense_subset(points: np.ndarray, *, k: int = 8, factor: float = 2.5) -> np.ndarray:
    """The points (N, 3) whose distance to their ``k``-th nearest neighbour is at most ``factor`` times the median
    one: surface points, without the isolated stray points that would otherwise decide which point is lowest."""
    if len(points) <= k + 1:
        return points
    d, _ = cKDTree(points).query(points, k + 1)
    reach = d[:, -1]  # (N,)
    return points[reach <= factor * np.median(reach)]


class Support(NamedTuple):
    """The plane an object would rest on when turned so that ``up`` points up (see :func:`support_plane`).

    normal : (3,) float64, unit up-facing normal of the plane under the lowest points
    stability : signed distance from the centroid's projection to the edge of the contact polygon, in units of the
        points' RMS radius (> 0: the centroid lies over the contact polygon and the pose is statically stable)
    count : number of contact points
    """

    normal: np.ndarray
    stability: float
    count: int


def hull_faces(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The faces of the convex hull of ``points`` (N, 3): (F, 3) unit outward normals, (F,) areas and (F, 3) vertex
    indices; None when the points are flat or degenerate (qhull refuses them)."""
    try:
        hull = ConvexHull(points)
    except Exception as exc:  # noqa: BLE001 - qhull raises its own QhullError for flat or degenerate input
        if type(exc).__name__ != "QhullError":
            raise
        return None
    a, b, c = (points[hull.simplices[:, i]] for i in range(3))
    return hull.equations[:, :3], 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1), hull.simplices


def support_plane(points: Any, up: Any, *, max_angle: float = 25.0) -> Support:
    """The support plane of ``points`` (N, 3) standing roughly with ``up`` (3,) up: where the object touches the floor.

    Objects are scanned standing on something, and a model's frame is that of a standing object, so the plane under
    an object (under its leg tips, its sole, its flat underside) fixes its up axis more precisely than a global fit
    of two shapes that differ in proportions. A rigid object rests on a face of its convex hull: the plane is the
    area-weighted mean plane of the hull's faces whose outward normals lie within ``max_angle`` degrees of ``-up``
    (for a chair, the two large triangles between its four leg tips dominate the small faces around each tip).
    Without such faces ``up`` is returned with ``count`` 0. Isolated stray points should be removed first (they
    would make hull faces of their own).
    """
    points = as_points(points, min_count=4)
    guess = parse_axis(up)
    center = points.mean(axis=0)
    radius = float(np.sqrt(((points - center) ** 2).sum(axis=1).mean())) or 1.0
    faces = hull_faces(points)
    if faces is None:
        return Support(guess, -math.inf, 0)
    outward, area, simplices = faces
    below = outward @ -guess >= math.cos(math.radians(max_angle))  # (F,) faces that face down
    if not below.any() or not area[below].sum() > 0:
        return Support(guess, -math.inf, 0)
    normal = -(outward[below] * area[below, None]).sum(axis=0)
    normal /= np.linalg.norm(normal)
    contact = points[np.unique(simplices[below])]  # (n, 3)
    basis = np.linalg.svd(normal[None, :])[2][1:]  # (2, 3) in-plane axes
    flat, middle = contact @ basis.T, center @ basis.T  # (n, 2), (2,)
    try:
        polygon = ConvexHull(flat)
        stability = float(-(polygon.equations[:, :2] @ middle + polygon.equations[:, 2]).max())
    except Exception as exc:  # noqa: BLE001 - collinear or too few contact points
        if type(exc).__name__ != "QhullError":
            raise
        stability = -float(np.min(np.linalg.norm(flat - middle, axis=1)))
    return Support(normal, stability / radius, len(contact))


# --------------------------------------------------------------------------------------------------------------------
# shapes: arrays, kpd.io.PointSet and kpd.io.Mesh (duck-typed so this module depends only on their fields)


def _is_mesh(shape: Any) -> bool:
    return hasattr(shape, "triangles") and hasattr(shape, "vertices")


def _is_pointset(shape: Any) -> bool:
    return hasattr(shape, "points") and not _is_mesh(shape)


def _shape_points(shape: Any, name: str = "scan") -> np.ndarray:
    if _is_mesh(shape):
        return as_points(shape.vertices, f"{name} vertices")
    if _is_pointset(shape):
        return as_points(shape.points, f"{name} points")
    return as_points(shape, name)


def _take_points(shape: Any, keep: np.ndarray) -> Any:
    """A point shape (array or PointSet) restricted to the boolean mask ``keep`` (N,)."""
    if isinstance(shape, np.ndarray):
        return shape[keep]
    changes = {"points": np.asarray(shape.points)[keep]}
    for field in ("normals", "colors"):
        value = getattr(shape, field, None)
        if value is not None:
            changes[field] = np.asarray(value)[keep]
    return dataclasses.replace(shape, **changes)


def _take_triangles(mesh: Any, keep: np.ndarray) -> Any:
    """A mesh restricted to the triangles in the boolean mask ``keep`` (T,), without unreferenced vertices."""
    triangles = np.asarray(mesh.triangles, dtype=np.int64)[keep]  # (T', 3)
    used = np.zeros(len(mesh.vertices), dtype=bool)
    used[triangles.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    changes: dict[str, Any] = {"vertices": np.asarray(mesh.vertices)[used], "triangles": remap[triangles]}
    for field in ("vertex_normals", "vertex_colors"):
        value = getattr(mesh, field, None)
        if value is not None:
            changes[field] = np.asarray(value)[used]
    uvs = getattr(mesh, "triangle_uvs", None)
    if uvs is not None and len(uvs) == 3 * len(keep):
        changes["triangle_uvs"] = np.asarray(uvs).reshape(-1, 3, 2)[keep].reshape(-1, 2)
    for field in ("triangle_material_ids", "triangle_uv_mask"):
        value = getattr(mesh, field, None)
        if value is not None and len(value) == len(keep):
            changes[field] = np.asarray(value)[keep]
    return dataclasses.replace(mesh, **changes)


def _with_points(shape: Any, points: np.ndarray, linear: np.ndarray) -> Any:
    """``shape`` with its points replaced (topology, colours, UVs kept); normals turned by ``linear`` (3, 3)."""
    if isinstance(shape, np.ndarray):
        return points
    if hasattr(shape, "with_vertices"):
        return shape.with_vertices(points)  # kpd.io.Mesh: same topology, UVs, colours; normals recomputed
    if _is_mesh(shape):
        changes: dict[str, Any] = {"vertices": points}
        field = "vertex_normals"
    else:
        changes = {"points": points}
        field = "normals"
    normals = getattr(shape, field, None)
    if normals is not None and len(normals):
        # normals transform by the inverse transpose: n' = L^-T n, as rows n @ L^-1
        turned = np.asarray(normals, dtype=np.float64) @ np.linalg.inv(linear)
        length = np.linalg.norm(turned, axis=1, keepdims=True)
        changes[field] = np.divide(turned, length, out=np.zeros_like(turned), where=length > 0)
    return dataclasses.replace(shape, **changes)


# --------------------------------------------------------------------------------------------------------------------
# clean


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
    extent = float(np.abs(vertices).max()) or 1.0
    keys = np.round(vertices / (1e-9 * extent)).astype(np.int64)
    _, welded = np.unique(keys, axis=0, return_inverse=True)
    welded = welded.reshape(-1)
    t = welded[triangles]  # (T, 3)
    n = int(welded.max()) + 1
    rows = np.concatenate([t[:, 0], t[:, 1]])
    cols = np.concatenate([t[:, 1], t[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return labels[t[:, 0]], count


def _distance_to_triangles(vertices: np.ndarray, triangles: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """(Q,) exact distance from each query point to the surface of the given triangles (Open3D raycasting scene)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(queries.astype(np.float32))).numpy().astype(np.float64)


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
    area = triangle_areas(vertices, triangles)  # (T,)
    piece_area = np.bincount(labels, weights=area, minlength=count)  # (pieces,)
    small = piece_area < min_piece * piece_area.max()
    if small.any() and max_gap > 0:
        gap = max_gap * float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        used = np.unique(triangles)  # vertices of some triangle, and the piece each belongs to
        used_piece = np.empty(len(vertices), dtype=np.int64)
        used_piece[triangles.reshape(-1)] = np.repeat(labels, 3)
        used_piece = used_piece[used]
        while small.any():
            query = small[used_piece]  # vertices of the small pieces not yet kept
            near = _distance_to_triangles(vertices, triangles[~small[labels]], vertices[used[query]])
            touching = np.unique(used_piece[query][near <= gap])
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
            diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
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


def _shape_points_raw(shape: Any) -> np.ndarray:
    if _is_mesh(shape):
        return np.asarray(shape.vertices)
    if _is_pointset(shape):
        return np.asarray(shape.points)
    return np.asarray(shape)


# --------------------------------------------------------------------------------------------------------------------
# orient


class Hypothesis(NamedTuple):
    """One refined rotation hypothesis; ``source`` names its start: ``pca:i`` (principal axes under signed
    permutation i), ``grid:i`` (icosahedral rotation i), ``fpfh:i`` (RANSAC run i), ``yaw:i`` / ``pca-yaw:i`` (with
    an up axis); ``+turnk`` for the best turned by k quarter turns about the reference's up axis; ``+support`` when
    the hypothesis was stood on its support plane (see :func:`support_plane`)."""

    rotation: np.ndarray
    score: float
    source: str


class Orientation(NamedTuple):
    """Result of :meth:`ScanAligner.orient`.

    rotation : (3, 3) float64, proper rotation turning the scan into the reference's frame
    translation : (3,) float64 and scale : (3,) float64 (one per reference axis; equal unless ``scaling='axes'``), so
        that ``(points @ rotation.T) * scale + translation`` lies on the reference (in the reference's units)
    score : the best hypothesis' trimmed symmetric RMS nearest-neighbour distance after ICP (the ``score_trim``
        nearest share of the distances each way), in units of the reference's [-1, 1] box
    runner_up_score : the best score of a rotation more than ``distinct_angle`` degrees from the best (inf if none)
    runner_up_rotation : (3, 3) float64 or None
    runner_up_angle : angle in degrees between best and runner-up rotations (nan if none)
    margin : runner_up_score / score - 1 (relative; inf if no runner-up)
    ambiguous : margin below the aligner's threshold: two genuinely different rotations fit about equally well
    hypotheses : every refined hypothesis, best first
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: np.ndarray
    score: float
    runner_up_score: float
    runner_up_rotation: np.ndarray | None
    runner_up_angle: float
    margin: float
    ambiguous: bool
    hypotheses: list

    def to_dict(self) -> dict:
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "scale": self.scale.tolist(),
            "score": num(self.score),
            "runner_up_score": num(self.runner_up_score),
            "runner_up_rotation": None if self.runner_up_rotation is None else self.runner_up_rotation.tolist(),
            "runner_up_angle": num(self.runner_up_angle),
            "margin": num(self.margin),
            "ambiguous": self.ambiguous,
            "hypotheses": [{"source": h.source, "score": num(h.score), "rotation": h.rotation.tolist()}
                           for h in self.hypotheses],
        }


class _Cloud(NamedTuple):
    """A shape in its working frame: centred on its centroid, unit RMS radius."""

    points: np.ndarray  # (n, 3) working-frame sample, in random order
    normals: np.ndarray  # (n, 3) unoriented unit normals
    tree: cKDTree  # over _features(points, normals): matching
    tree3: cKDTree  # over points: scoring
    center: np.ndarray  # (3,) centroid in original units
    radius: float  # RMS distance to the centroid, original units


def _axial(normals: np.ndarray) -> np.ndarray:
    """(n, 6) the unique entries of n n^T (sign-free), scaled so that distances match the Frobenius norm."""
    x, y, z = normals.T
    r2 = math.sqrt(2.0)
    return np.stack([x * x, y * y, z * z, r2 * x * y, r2 * x * z, r2 * y * z], axis=1)


def _umeyama(
    x: np.ndarray, y: np.ndarray, *, axis: np.ndarray | None, with_scale: bool
) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |s R x + t - y|^2; R restricted to rotations about ``axis`` if given."""
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my  # (n, 3)
    if axis is None:
        u, sig, vt = np.linalg.svd(yc.T @ xc)
        d = np.ones(3)
        d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
        rot = (u * d) @ vt
        trace = float((sig * d).sum())
    else:
        # rotation about the axis: angle from the components orthogonal to it
        basis = np.linalg.svd(axis[None, :])[2][1:]  # (2, 3)
        a, b = xc @ basis.T, yc @ basis.T  # (n, 2)
        angle = math.atan2(float((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()), float((a * b).sum()))
        e1, e2 = basis
        sign = np.sign(np.dot(np.cross(e1, e2), axis)) or 1.0
        rot = _about(axis, sign * angle)
        trace = float(np.einsum("ij,ij->", yc, xc @ rot.T))
    var = float((xc**2).sum())
    scale = trace / var if with_scale and var > 0 else 1.0
    return scale, rot, my - scale * rot @ mx


class ScanAligner:
    """Orients scans into the frame of a reference shape by a global rotation search.

    ``ScanAligner(**params).fit(reference_points)`` then ``orient(points)`` for each scan; :func:`orient` is the
    one-call form. Estimator-style: ``__init__`` stores parameters, ``fit`` returns ``self``.

    Parameters
    ----------
    up : the scan's up axis if known (``'z'``, ``'-y'`` or three numbers). The search is then restricted to the
        rotations that take it to ``reference_up`` followed by any rotation about ``reference_up``.
    reference_up : the reference's up axis (a property of the model's frame); defaults to ``up``. Given without
        ``up``, the search still covers all rotations but uses the support prior (``support``).
    support : with ``reference_up`` known and ``up`` not: objects are scanned standing, so each refined hypothesis is
        stood on the scan's support plane (:func:`support_plane` with the hypothesis' up as the guess) turned onto
        the reference's support plane, and then only its turn about the up axis is refined. A support plane is used
        only if hull faces within ``snap_angle`` degrees of the hypothesis' down direction exist and the centroid lies
        over their contact polygon (a cut-away leg leaves an unstable contact, which is not trusted). This fixes the
        tilt of the up axis by the floor contact (leg tips, a sole) rather than by the fit of two shapes of different
        proportions, which on ModelNet10 chairs left it 10 to 15 degrees off in about one case in ten.
    snap_angle : see ``support``.
    n_points : points of each shape used in the search: a random subset of the shape thinned on a ``voxel`` grid
        (``voxel`` in units of the shape's RMS radius), so that dense and sparse regions weigh alike.
    coarse_points, coarse_iterations : the cheap first ICP (positions only) run from every starting rotation.
    refine_top : how many distinct hypotheses get the full ICP (``iterations``).
    trim : share of nearest-neighbour pairs kept in each direction by ICP (robust to outliers and missing parts).
    scaling : what ICP may adjust besides the rotation: ``'axes'`` a scale per reference axis (shapes of a category
        differ in proportions), ``'uniform'`` one scale, ``'none'`` nothing (both start at unit RMS radius).
    normal_weight : weight of the (unoriented) normal direction in ICP's nearest-neighbour matching; 0 for positions
        only. Without ``up`` the hypotheses are refined and compared on positions only (normals of a noisy scan
        mislead the comparison) and only the winner is polished with normals.
    score_trim : share of nearest-neighbour distances kept in each direction by the score, a trimmed RMS distance.
    fpfh_runs : FPFH + RANSAC candidates added to the search (0 to turn them off).
    distinct_angle : the runner-up must differ from the best by more than this many degrees.
    ambiguity_margin : relative margin (runner-up score / best score - 1) below which the result is flagged ambiguous.
    seed : seeds the subsets and RANSAC.
    """

    def __init__(
        self,
        *,
        up: Any = None,
        reference_up: Any = None,
        n_points: int = 1000,
        voxel: float = 0.02,
        coarse_points: int = 300,
        coarse_iterations: int = 8,
        iterations: int = 30,
        refine_top: int = 6,
        trim: float = 0.8,
        scaling: str = "axes",
        normal_weight: float = 0.5,
        score_trim: float = 0.95,
        fpfh_runs: int = 2,
        distinct_angle: float = 30.0,
        ambiguity_margin: float = DEFAULT_AMBIGUITY_MARGIN,
        support: bool = True,
        snap_angle: float = 25.0,
        seed: int = 0,
    ) -> None:
        self.up = up
        self.reference_up = reference_up
        self.n_points = n_points
        self.voxel = voxel
        self.coarse_points = coarse_points
        self.coarse_iterations = coarse_iterations
        self.iterations = iterations
        self.refine_top = refine_top
        self.trim = trim
        self.scaling = scaling
        self.normal_weight = normal_weight
        self.score_trim = score_trim
        self.fpfh_runs = fpfh_runs
        self.distinct_angle = distinct_angle
        self.ambiguity_margin = ambiguity_margin
        self.support = support
        self.snap_angle = snap_angle
        self.seed = seed

    # -- set-up -------------------------------------------------------------------------------------------------------

    def _check_params(self) -> None:
        for name in ("trim", "score_trim"):
            if not 0.1 <= getattr(self, name) <= 1.0:
                raise InputError(f"{name} must lie in [0.1, 1]; got {getattr(self, name)}")
        if self.scaling not in ("axes", "uniform", "none"):
            raise InputError(f"scaling must be 'axes', 'uniform' or 'none'; got {self.scaling!r}")
        if not (self.voxel > 0 and self.normal_weight >= 0 and self.ambiguity_margin >= 0):
            raise InputError(f"voxel must be > 0, normal_weight and ambiguity_margin >= 0; got {self.voxel}, "
                             f"{self.normal_weight}, {self.ambiguity_margin}")
        for name in ("n_points", "coarse_points", "iterations", "refine_top"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be at least 1; got {getattr(self, name)}")
        if self.fpfh_runs < 0 or self.coarse_iterations < 0:
            raise InputError(f"fpfh_runs and coarse_iterations must be >= 0; got {self.fpfh_runs}, "
                             f"{self.coarse_iterations}")
        if not 0.0 <= self.snap_angle < 90.0:
            raise InputError(f"snap_angle must lie in [0, 90) degrees; got {self.snap_angle}")
        if not 0.0 < self.distinct_angle < 180.0:
            raise InputError(f"distinct_angle must lie in (0, 180) degrees; got {self.distinct_angle}")

    def _features(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n, 9) positions and weighted axial normals: nearest neighbours must agree in place and surface direction."""
        return np.concatenate([points, self.normal_weight * _axial(normals)], axis=1)

    def _cloud(self, points: np.ndarray, rng: np.random.Generator) -> _Cloud:
        center = points.mean(axis=0)
        radius = float(np.sqrt(((points - center) ** 2).sum(axis=1).mean()))
        if not radius > 0:
            raise InputError(f"cannot orient a shape whose {len(points)} points all coincide")
        pcd = _pcd((points - center) / radius).voxel_down_sample(self.voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        thinned, normals = np.asarray(pcd.points), np.asarray(pcd.normals)
        # a random order, so that any prefix is a random subset (the coarse stage uses one)
        order = rng.permutation(len(thinned))[: self.n_points]
        thinned, normals = thinned[order], normals[order]
        return _Cloud(thinned, normals, cKDTree(self._features(thinned, normals)), cKDTree(thinned), center, radius)

    def fit(self, reference: Any) -> "ScanAligner":
        """Prepare the reference: (N, 3) points, a PointSet or a Mesh (its vertices; sample a mesh's surface first for
        an even density), in the frame the scans should be turned into."""
        self._check_params()
        points = _shape_points(reference, "reference")
        if len(points) < 10:
            raise InputError(f"the reference needs at least 10 points; got {len(points)}")
        self.up_ = None if self.up is None else parse_axis(self.up)
        ref_up = self.reference_up if self.reference_up is not None else self.up
        self.reference_up_ = None if ref_up is None else parse_axis(ref_up, "reference_up")
        self.reference_ = self._cloud(points, as_rng(self.seed))
        self.reference_box_scale_ = Normalizer().fit(points).scale_
        self.reference_support_ = None
        if self._uses_support():
            ref = self.reference_
            work = _dense_subset(self._working_sample((points - ref.center) / ref.radius, as_rng(self.seed)))
            self.reference_support_ = support_plane(work, self.reference_up_)
        self._reference_fpfh = self._fpfh(self.reference_.points) if self.fpfh_runs else None
        return self

    def _uses_support(self) -> bool:
        """The support prior applies when the reference's up axis is known and the scan's is not."""
        return bool(self.support) and self.up_ is None and self.reference_up_ is not None

    _SUPPORT_POINTS = 6000  # points of a shape used to find its support plane

    def _working_sample(self, work: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if len(work) > self._SUPPORT_POINTS:
            work = work[rng.choice(len(work), self._SUPPORT_POINTS, replace=False)]
        return work

    def _check_fitted(self) -> None:
        if not hasattr(self, "reference_"):
            raise NotFittedError("this ScanAligner has no reference yet; call fit(reference_points) first")

    # -- the search ---------------------------------------------------------------------------------------------------

    _SCALE_RANGE = (0.5, 2.0)  # bounds of the ICP scales (both shapes start at unit RMS radius)
    _VOXEL = 0.08  # FPFH voxel in units of the RMS radius

    def _fpfh(self, work: np.ndarray) -> tuple[o3d.geometry.PointCloud, Any]:
        voxel = self._VOXEL
        pcd = _pcd(work).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return pcd, fpfh

    def _fpfh_candidates(self, work: np.ndarray) -> list[np.ndarray]:
        reg = o3d.pipelines.registration
        source, source_fpfh = self._fpfh(work)
        target, target_fpfh = self._reference_fpfh
        distance = 1.5 * self._VOXEL
        out = []
        for run in range(self.fpfh_runs):
            o3d.utility.random.seed(self.seed + run)
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # "too few correspondences"
                result = reg.registration_ransac_based_on_feature_matching(
                    source, target, source_fpfh, target_fpfh, True, distance,
                    reg.TransformationEstimationPointToPoint(False), 3,
                    [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                     reg.CorrespondenceCheckerBasedOnDistance(distance)],
                    reg.RANSACConvergenceCriteria(20000, 0.999))
            rot = np.asarray(result.transformation)[:3, :3].copy()
            if np.isfinite(rot).all() and abs(np.linalg.det(rot) - 1.0) < 1e-6:
                out.append(rot)
        return out

    def _initial(self, scan: _Cloud) -> list[tuple[np.ndarray, str]]:
        """Starting rotations (working frame of the scan -> working frame of the reference)."""
        ref = self.reference_
        starts: list[tuple[np.ndarray, str]] = []
        if self.up_ is None:
            frame_s, frame_r = _principal_frame(scan.points), _principal_frame(ref.points)
            for i, perm in enumerate(proper_signed_permutations()):
                starts.append((frame_r @ perm @ frame_s.T, f"pca:{i}"))
            for i, rot in enumerate(icosahedral_rotations()):
                starts.append((rot, f"grid:{i}"))
        else:
            tilt = _rotation_between(self.up_, self.reference_up_)
            axis = self.reference_up_
            for i in range(24):
                starts.append((_about(axis, 2 * np.pi * i / 24) @ tilt, f"yaw:{i}"))
            # principal horizontal axes matched both ways and both signs
            basis = np.linalg.svd(axis[None, :])[2][1:]  # (2, 3)

            def horizontal_angle(points: np.ndarray) -> float:
                flat = (points - points.mean(axis=0)) @ basis.T  # (n, 2)
                _, v = np.linalg.eigh(flat.T @ flat)
                return math.atan2(v[1, -1], v[0, -1])

            a_s = horizontal_angle(scan.points @ tilt.T)
            a_r = horizontal_angle(ref.points)
            sign = np.sign(np.dot(np.cross(basis[0], basis[1]), axis)) or 1.0
            for k in range(4):
                starts.append((_about(axis, sign * (a_r - a_s + k * np.pi / 2)) @ tilt, f"pca-yaw:{k}"))
        if self.fpfh_runs:
            for i, rot in enumerate(self._fpfh_candidates(scan.points)):
                if self.up_ is not None:
                    rot = self._project_to_up(rot)
                starts.append((rot, f"fpfh:{i}"))
        return starts

    def _project_to_up(self, rot: np.ndarray) -> np.ndarray:
        """The allowed rotation (tilt to reference_up, then about it) nearest to ``rot``."""
        tilt = _rotation_between(self.up_, self.reference_up_)
        rest = rot @ tilt.T  # ideally a rotation about reference_up
        axis = self.reference_up_
        basis = np.linalg.svd(axis[None, :])[2][1:]
        m = basis @ rest @ basis.T  # (2, 2)
        angle = math.atan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1])
        sign = np.sign(np.dot(np.cross(basis[0], basis[1]), axis)) or 1.0
        return _about(axis, sign * angle) @ tilt

    def _icp(self, scan: _Cloud, rot: np.ndarray, iterations: int, n: int | None = None, *, normals: bool = True,
             ups: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Trimmed symmetric ICP in the working frames from the rotation ``rot``.

        The transform is ``x -> a * (R x) + t`` with ``a`` (3,) a scale per reference axis (``scaling='axes'``), one
        scale (``'uniform'``) or none (``'none'``). Nearest neighbours are found both ways among points whose
        positions and (weighted) normal directions agree. ``ups`` (scan up, reference up) restricts R to the turns
        that take the one to the other (default: ``up`` and ``reference_up`` when ``up`` is given). Returns
        (a, R, t, score), the score of :meth:`_score`.
        """
        ref = self.reference_
        ref_points, ref_normals = ref.points[:n], ref.normals[:n]  # random order: a prefix is a random subset
        scan_points, scan_normals = scan.points[:n], scan.normals[:n]
        if ups is None and self.up_ is not None:
            ups = (self.up_, self.reference_up_)
        axis = None if ups is None else ups[1]
        tilt = None if ups is None else _rotation_between(*ups)
        a, r, t = np.ones(3), rot, np.zeros(3)
        kept_s = max(3, int(self.trim * len(scan_points)))
        kept_r = max(3, int(self.trim * len(ref_points)))

        def match(a: np.ndarray, r: np.ndarray, t: np.ndarray):
            moved = (scan_points @ r.T) * a + t
            back = ((ref_points - t) / a) @ r  # the reference in the scan's working frame
            if normals and self.normal_weight > 0:
                d1, i1 = ref.tree.query(self._features(moved, scan_normals @ r.T))
                d2, i2 = scan.tree.query(self._features(back, ref_normals @ r))
            else:
                d1, i1 = ref.tree3.query(moved)
                d2, i2 = scan.tree3.query(back)
            return d1, i1, d2, i2

        for _ in range(iterations):
            d1, i1, d2, i2 = match(a, r, t)
            o1 = np.argpartition(d1, kept_s - 1)[:kept_s]
            o2 = np.argpartition(d2, kept_r - 1)[:kept_r]
            x = np.concatenate([scan_points[o1], scan.points[i2[o2]]])  # (k, 3) scan working frame
            y = np.concatenate([ref.points[i1[o1]], ref_points[o2]])  # (k, 3) their partners on the reference
            if axis is not None:
                x = x @ tilt.T  # then only a turn about the reference's up axis is left to find
            if self.scaling == "axes":
                _, r_new, _ = _umeyama(x, (y - t) / a, axis=axis, with_scale=False)
                turned = x @ r_new.T
                tc, yc = turned - turned.mean(axis=0), y - y.mean(axis=0)
                a_new = np.clip((tc * yc).sum(axis=0) / np.maximum((tc * tc).sum(axis=0), 1e-12), *self._SCALE_RANGE)
                t_new = y.mean(axis=0) - a_new * turned.mean(axis=0)
            else:
                s_new, r_new, t_new = _umeyama(x, y, axis=axis, with_scale=self.scaling == "uniform")
                a_new = np.full(3, float(np.clip(s_new, *self._SCALE_RANGE)))
                t_new = y.mean(axis=0) - a_new * (x.mean(axis=0) @ r_new.T)
            if axis is not None:
                r_new = r_new @ tilt
            done = (rotation_angle(r_new, r) < 0.01 and np.abs(a_new - a).max() < 1e-5
                    and np.abs(t_new - t).max() < 1e-5)
            a, r, t = a_new, r_new, t_new
            if done:
                break
        return a, r, t, self._score(scan, a, r, t, n)

    def _score(self, scan: _Cloud, a: np.ndarray, r: np.ndarray, t: np.ndarray, n: int | None = None) -> float:
        """Trimmed symmetric RMS distance between positions (working units) of the first ``n`` points of each shape:
        each way the ``score_trim`` nearest share of the nearest-neighbour distances counts (robust to outliers and
        missing parts)."""
        ref = self.reference_
        ref_points, scan_points = ref.points[:n], scan.points[:n]
        d1, _ = ref.tree3.query((scan_points @ r.T) * a + t)  # (n,)
        _, i2 = scan.tree3.query(((ref_points - t) / a) @ r)
        d2 = np.linalg.norm((scan.points[i2] @ r.T) * a + t - ref_points, axis=1)  # (m,)

        def trimmed(d: np.ndarray) -> float:
            k = max(1, int(self.score_trim * len(d)))
            return float((np.partition(d, k - 1)[:k] ** 2).mean())

        return math.sqrt(0.5 * (trimmed(d1) + trimmed(d2)))

    def orient(self, points: Any) -> Orientation:
        """Find the rotation of ``points`` (N, 3) (or a PointSet / Mesh) into the reference's frame."""
        self._check_fitted()
        points = _shape_points(points, "scan")
        if len(points) < 10:
            raise InputError(f"the scan needs at least 10 points to be oriented; got {len(points)}")
        rng = as_rng(self.seed + 1)
        scan = self._cloud(points, rng)
        standing = None  # the scan's dense points (working frame), to find its support plane
        if self._uses_support():
            standing = _dense_subset(self._working_sample((points - scan.center) / scan.radius, rng))
        starts = self._initial(scan)

        # coarse: a short ICP (positions only) on a small subset for every start; keep the best of each cluster
        coarse = []
        for rot, source in starts:
            _, r, _, score = self._icp(scan, rot, self.coarse_iterations, self.coarse_points, normals=False)
            coarse.append((score, r, source))
        coarse.sort(key=lambda c: c[0])
        chosen: list[tuple[float, np.ndarray, str]] = []
        for score, r, source in coarse:
            if all(rotation_angle(r, c[1]) > 10.0 for c in chosen):
                chosen.append((score, r, source))
            if len(chosen) >= self.refine_top:
                break

        # Without an up axis, hypotheses are refined and compared on positions only: normals estimated on a noisy
        # scan (noise of 1% of the size is several voxels) mislead the matching and favour wrong rotations (re-scoring
        # the hypotheses of 40 noisy ModelNet10 chair scans: 17 right / 12 wrong decided with normals, 25 / 0
        # without). The winner is polished with normals afterwards. With an up axis the search is narrow and normals
        # help it.
        search_normals = self.up_ is not None

        def refine(r0: np.ndarray, source: str) -> tuple:
            a, r, t, score = self._icp(scan, r0, self.iterations, normals=search_normals)
            ups = None
            if standing is not None:
                # the support prior: stand the scan on its own support plane (the hull faces under it with the
                # hypothesis' up pointing up, within snap_angle) and turn that plane onto the reference's, then
                # refine only the turn about the up axis
                guess = r.T @ self.reference_up_
                found = support_plane(standing, guess, max_angle=self.snap_angle)
                if found.count and found.stability > 0:  # an unstable support is not one (a cut-away leg)
                    ups = (found.normal, self.reference_support_.normal)
                    a, r, t, score = self._icp(scan, r, self.iterations, normals=search_normals, ups=ups)
                    source += "+support"
            return score, a, r, t, source, ups

        refined = sorted((refine(r0, source) for _, r0, source in chosen), key=lambda c: c[0])
        if standing is not None:
            # With the up axis settled by the support, the quarter turns of the best about it are searched too:
            # many objects (tables, boxes) look alike after such a turn, and a runner-up found there is a genuine
            # alternative that the starts may have missed (it may also win: then it is the better fit)
            _, _, r_best, _, source_best, ups_best = refined[0]
            for k in (1, 2, 3):
                turned = _about(self.reference_up_, k * np.pi / 2) @ r_best
                source = f"{source_best.split('+')[0]}+turn{k}"
                if ups_best is None:
                    refined.append(refine(turned, source))
                else:  # already standing on its support: only the turn about the up axis is refined
                    a, r, t, score = self._icp(scan, turned, self.iterations, normals=search_normals, ups=ups_best)
                    refined.append((score, a, r, t, source + "+support", ups_best))
            refined.sort(key=lambda c: c[0])
        unit = self.reference_.radius / self.reference_box_scale_  # working units -> reference box units
        best_score, s, r, t, _, best_ups = refined[0]
        runner = next((c for c in refined[1:] if rotation_angle(c[2], r) > self.distinct_angle), None)
        # the coarse stage may know a distinct rotation that the fine stage did not keep
        if runner is None:
            for _, r_c, source in coarse:
                if rotation_angle(r_c, r) > self.distinct_angle:
                    candidate = refine(r_c, source)
                    if rotation_angle(candidate[2], r) > self.distinct_angle:
                        runner = candidate
                        refined.append(runner)
                        break
        if not search_normals and self.normal_weight > 0:
            # polish the winner with normals (same constraint); its score stays the one it was chosen by
            s, r, t, _ = self._icp(scan, r, self.iterations, ups=best_ups)
            refined[0] = (best_score, s, r, t, refined[0][4], best_ups)
        # back to original units: y = c_ref + r_ref * (a * R (x - c_scan) / r_scan + t), centres c, RMS radii r
        ref = self.reference_
        scale = s * ref.radius / scan.radius  # (3,)
        translation = ref.center + ref.radius * t - scale * (r @ scan.center)
        if runner is None:
            runner_score, runner_rot, runner_angle, margin = math.inf, None, math.nan, math.inf
        else:
            runner_score, runner_rot = runner[0] * unit, runner[2]
            runner_angle = rotation_angle(runner_rot, r)
            margin = runner[0] / best_score - 1.0 if best_score > 0 else math.inf
        hypotheses = [Hypothesis(c[2], c[0] * unit, c[4]) for c in sorted(refined, key=lambda c: c[0])]
        ambiguous = bool(margin < self.ambiguity_margin)
        result = Orientation(r, translation, scale, best_score * unit, runner_score, runner_rot, runner_angle,
                             float(margin), ambiguous, hypotheses)
        log.info("orient: score %.4f, runner-up %.4f at %.0f deg, margin %.3f%s", result.score, runner_score,
                 runner_angle, margin, " (ambiguous)" if ambiguous else "")
        return result


def orient(points: Any, reference: Any, **params: Any) -> Orientation:
    """One call of ``ScanAligner(**params).fit(reference).orient(points)``; see :class:`ScanAligner`."""
    return ScanAligner(**params).fit(reference).orient(points)


# --------------------------------------------------------------------------------------------------------------------
# normalise and the one-call pipeline


class NormalizeResult(NamedTuple):
    points: np.ndarray
    normalizer: Normalizer


def normalize(points: Any) -> NormalizeResult:
    """``points`` (N, 3) into the [-1, 1] box (REFERENCE §7) with the fitted :class:`~kpd.geometry.Normalizer`."""
    normalizer = Normalizer().fit(points)
    return NormalizeResult(normalizer.apply(points), normalizer)


class ScanResult(NamedTuple):
    """Result of :func:`preprocess`.

    shape : the cleaned scan, rotated into the reference's frame and normalised into [-1, 1] (same type as the input)
    points : (N, 3) float64, its points (mesh vertices)
    transform : (4, 4) float64, the similarity taking cleaned-scan coordinates to ``points``
    inverse : (4, 4) float64, its exact inverse: results in the aligned frame map back onto the original scan
    rotation : (3, 3) float64 ; normalizer : Normalizer of the rotated scan (``points = normalizer.apply(x @ R.T)``)
    orientation : Orientation (None when no reference was given) ; clean : CleanReport
    """

    shape: Any
    points: np.ndarray
    transform: np.ndarray
    inverse: np.ndarray
    rotation: np.ndarray
    normalizer: Normalizer
    orientation: Orientation | None
    clean: CleanReport

    def to_original(self, points: Any) -> np.ndarray:
        """(N, 3) points of the aligned frame mapped back onto the original scan."""
        points = as_points(points, min_count=0)
        return points @ self.inverse[:3, :3].T + self.inverse[:3, 3]

    def to_aligned(self, points: Any) -> np.ndarray:
        """(N, 3) points of the original scan mapped into the aligned frame."""
        points = as_points(points, min_count=0)
        return points @ self.transform[:3, :3].T + self.transform[:3, 3]

    def to_dict(self) -> dict:
        return {
            "transform": self.transform.tolist(),
            "inverse": self.inverse.tolist(),
            "rotation": self.rotation.tolist(),
            "normalizer": self.normalizer.to_dict(),
            "orientation": None if self.orientation is None else self.orientation.to_dict(),
            "clean": self.clean.to_dict(),
            "count": len(self.points),
        }


def similarity_matrices(rotation: np.ndarray, normalizer: Normalizer) -> tuple[np.ndarray, np.ndarray]:
    """The (4, 4) map ``x -> (R x - c) / s`` of a rotation then a normaliser, and its inverse ``y -> R^T (s y + c)``."""
    c, s = normalizer.center_, normalizer.scale_
    forward = np.eye(4)
    forward[:3, :3] = rotation / s
    forward[:3, 3] = -c / s
    inverse = np.eye(4)
    inverse[:3, :3] = rotation.T * s
    inverse[:3, 3] = rotation.T @ c
    return forward, inverse


def preprocess(
    shape: Any,
    reference: Any = None,
    *,
    clean_params: dict | None = None,
    aligner: ScanAligner | None = None,
    outer: bool = False,
    **orient_params: Any,
) -> ScanResult:
    """Clean, orient and normalise a scan in one call.

    Parameters
    ----------
    shape : (N, 3) array, PointSet or Mesh (the scan).
    reference : (M, 3) points (or a PointSet / Mesh) in the model's frame, or None to skip orientation (the scan is
        then only cleaned and normalised).
    clean_params : keyword arguments of :func:`clean` (``up`` is passed on from ``orient_params`` if not given).
    aligner : an already fitted :class:`ScanAligner` (then ``reference`` and ``orient_params`` are not used).
    outer : orient a mesh by samples of its outer surface only (:func:`kpd.geometry.sample_surface`): for meshes
        made of overlapping pieces, as the models trained with ``kpd train --outer-surface`` see them.
    orient_params : keyword arguments of :class:`ScanAligner`.

    Returns
    -------
    ScanResult; ``result.inverse`` maps ``result.points`` back onto the cleaned scan exactly (float64 round-off).
    """
    clean_params = dict(clean_params or {})
    if "up" in orient_params and "up" not in clean_params:
        clean_params["up"] = orient_params["up"]
    _shape_points(shape)  # checks the input before any work
    cleaned, report = clean(shape, **clean_params)
    points = _shape_points(cleaned)
    if aligner is None and reference is not None:
        aligner = ScanAligner(**orient_params).fit(reference)
    if aligner is not None:
        # a mesh is oriented by its surface, not its vertices (CAD meshes crowd vertices on curved details)
        triangles = np.asarray(getattr(cleaned, "triangles", np.zeros((0, 3))))
        seen = (sample_surface(points, triangles, MESH_ORIENT_SAMPLES, aligner.seed, outer=outer).points
                if _is_mesh(cleaned) and len(triangles) else points)
        orientation = aligner.orient(seen)
    else:
        orientation = None
    rotation = np.eye(3) if orientation is None else orientation.rotation
    normalizer, forward, inverse, aligned = _aligned_frame(points, rotation)
    return ScanResult(_with_points(cleaned, aligned, forward[:3, :3]), aligned, forward, inverse, rotation,
                      normalizer, orientation, report)


def _aligned_frame(points: np.ndarray, rotation: np.ndarray) -> tuple[Normalizer, np.ndarray, np.ndarray, np.ndarray]:
    """The scan's points turned by ``rotation`` and normalised: the normaliser, the 4x4 maps to the aligned frame and
    back, and the aligned points."""
    normalizer = Normalizer().fit(points @ rotation.T)
    forward, inverse = similarity_matrices(rotation, normalizer)
    return normalizer, forward, inverse, points @ forward[:3, :3].T + forward[:3, 3]


def candidate_rotations(orientation: Orientation, margin: float | None = None,
                        distinct_angle: float = 30.0) -> list[tuple[np.ndarray, float]]:
    """The distinct rotations an ambiguous orientation hesitates between: (rotation, score) pairs, best first.

    The first is the chosen rotation; then every refined hypothesis whose score is within ``margin`` (relative, as
    :attr:`Orientation.margin`; default the aligner's :data:`DEFAULT_AMBIGUITY_MARGIN`) of the best and that lies
    more than ``distinct_angle`` degrees from every rotation listed before it. A shape that is not ambiguous (or has
    no such hypothesis) gives the chosen rotation alone. What settles the choice is up to the caller: a model's
    keypoint prior (``kpd keypoints --scan``), the shape's look-alikes (``kpd scan FOLDER``).
    """
    margin = DEFAULT_AMBIGUITY_MARGIN if margin is None else float(margin)
    out = [(orientation.rotation, float(orientation.score))]
    if not orientation.ambiguous or not np.isfinite(orientation.score):
        return out
    for h in orientation.hypotheses:
        if h.score > orientation.score * (1.0 + margin):
            break  # hypotheses are sorted best first
        if all(rotation_angle(h.rotation, r) > distinct_angle for r, _ in out):
            out.append((h.rotation, float(h.score)))
    return out


def reorient(result: ScanResult, rotation: np.ndarray) -> ScanResult:
    """``result``'s cleaned scan turned by another ``rotation`` (3, 3) (a runner-up hypothesis, say) and normalised
    again: the :class:`ScanResult` :func:`preprocess` would have returned had it chosen that rotation."""
    rotation = np.asarray(rotation, dtype=np.float64)
    if rotation.shape != (3, 3) or not np.isfinite(rotation).all() or abs(np.linalg.det(rotation) - 1.0) > 1e-6:
        raise InputError(f"a rotation must be a proper (3, 3) rotation matrix; got shape {rotation.shape}")
    points = result.to_original(result.points)  # the cleaned scan
    normalizer, forward, inverse, aligned = _aligned_frame(points, rotation)
    linear = forward[:3, :3] @ result.inverse[:3, :3]  # old aligned frame -> new aligned frame
    return ScanResult(_with_points(result.shape, aligned, linear), aligned, forward, inverse, rotation, normalizer,
                      result.orientation, result.clean)
