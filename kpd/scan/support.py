"""The support plane a shape stands on: the convex hull faces under its lowest points (between the leg tips of a chair,
under the sole of a shoe)."""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from kpd.geometry import as_points
from kpd.scan.rotations import parse_axis

__all__ = ["Support", "hull_faces", "support_plane"]

log = logging.getLogger("kpd.scan")


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

    - normal : (3,) float64, unit up-facing normal of the plane under the lowest points
    - stability : signed distance from the centroid's projection to the edge of the contact polygon, in units of the
      points' RMS radius (> 0: the centroid lies over the contact polygon and the pose is statically stable)
    - count : number of contact points
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
