"""The camera: where it stands for a view of a shape, its view and projection matrices, and picking (points to
pixels, pixels to rays, rays to planes)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

import numba
import numpy as np

from kpd.viewer.settings import ViewSettings, up_axis

__all__ = ["Camera", "camera_pose", "box", "look_at_matrix", "perspective_matrix", "project", "pixel_ray", "plane_hit"]


@dataclass(frozen=True)
class Camera:
    """A look-at camera: ``center`` looked at from ``eye`` with ``up``; vertical ``fov`` in degrees."""

    center: np.ndarray
    eye: np.ndarray
    up: np.ndarray
    fov: float
    near: float
    far: float


def camera_pose(vertices: Any, settings: ViewSettings, *, margin: float = 0.9) -> Camera:
    """The camera of a view: orbiting the bounding-box centre of ``vertices`` (V, 3) at the settings' azimuth and
    elevation around the up axis, as close as lets every vertex into the view with ``margin`` (a fraction of the
    view's half-width and half-height) to spare; ``settings.zoom`` > 1 moves it closer.

    ``vertices`` may be a list of (N, 3) arrays (a shape and its keypoints, several frames), framed together without
    joining them. Each array is read twice by a compiled pass (a few milliseconds for a million vertices).

    The front view (azimuth 0) looks along the horizontal axis that follows the up axis (x -> y -> z -> x) in the
    positive direction, i.e. from ``-that axis``: for ModelNet (z up, chair backs towards +y) that is the view from
    the front of a chair.
    """
    parts = [np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
             for p in (vertices if isinstance(vertices, (list, tuple)) else [vertices])]
    return camera_pose_over(lambda: parts, settings, margin=margin)


def camera_pose_over(parts: Callable[[], Iterable[np.ndarray]], settings: ViewSettings, *, margin: float = 0.9,
                     bounds: tuple[np.ndarray, np.ndarray] | None = None) -> Camera:
    """:func:`camera_pose` of points that come in parts: ``parts()`` gives them, (N, 3) float64 arrays, and is
    called twice (the bounding box, then how far back every point fits; once when ``bounds``, their :func:`box`, is
    given), so that the parts need not all be held at once (a shape's variants, deformed as they are asked for); the
    same camera as of the parts joined."""
    def parts_now() -> Iterator[np.ndarray]:
        for part in parts():
            part = np.ascontiguousarray(part, dtype=np.float64).reshape(-1, 3)
            if len(part):
                yield part

    lo, hi = box(parts_now()) if bounds is None else bounds
    center = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-9)
    up = up_axis(settings.up)
    a = int(np.flatnonzero(up)[0])
    front = np.zeros(3)
    front[(a + 1) % 3] = -1.0  # from the front: the camera sits on the negative side of the next axis
    side = np.cross(up, front)
    az, el = math.radians(settings.azimuth), math.radians(settings.elevation)
    direction = math.cos(el) * (math.cos(az) * front + math.sin(az) * side) + math.sin(el) * up
    # as close as the view lets every vertex in, with ``margin`` of the half-width and half-height to spare
    forward = -direction
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    upward = np.cross(right, forward)
    tan_v = math.tan(math.radians(settings.fov) / 2)
    tan_h = tan_v * settings.width / settings.height
    axes = np.stack([right, upward, direction])  # (3, 3)
    distance = max((_reach(p, center, axes, margin * tan_h, margin * tan_v) for p in parts_now()), default=1.0)
    distance = max(distance, 1e-3 * radius) / settings.zoom
    eye = center + distance * direction
    return Camera(center=center, eye=eye, up=up, fov=float(settings.fov), near=max(distance - 3 * radius, distance / 100),
                  far=distance + 3 * radius)


def box(parts: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(3,) lowest and (3,) highest coordinates of the points of (N, 3) float64 arrays (zeros without points)."""
    boxes = [_box(p) for p in parts if len(p)]
    if not boxes:
        return np.zeros(3), np.zeros(3)
    return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


@numba.njit(cache=True, nogil=True)
def _box(points):  # pragma: no cover - compiled
    lo = points[0].copy()
    hi = points[0].copy()
    for i in range(1, points.shape[0]):
        for k in range(3):
            x = points[i, k]
            if x < lo[k]:
                lo[k] = x
            elif x > hi[k]:
                hi[k] = x
    return lo, hi


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _reach(points, center, axes, half_width, half_height):  # pragma: no cover - compiled
    """The largest distance back along ``axes[2]`` from ``center`` that sees every point within the view's half-width
    and half-height (tangents, times the margin)."""
    best = -np.inf
    for i in range(points.shape[0]):
        ox, oy, oz = points[i, 0] - center[0], points[i, 1] - center[1], points[i, 2] - center[2]
        x = abs(ox * axes[0, 0] + oy * axes[0, 1] + oz * axes[0, 2])
        y = abs(ox * axes[1, 0] + oy * axes[1, 1] + oz * axes[1, 2])
        z = ox * axes[2, 0] + oy * axes[2, 1] + oz * axes[2, 2]
        best = max(best, z + max(x / half_width, y / half_height))
    return best


def look_at_matrix(camera: Camera) -> np.ndarray:
    """(4, 4) world -> camera (OpenGL: camera looks down -z)."""
    f = camera.center - camera.eye
    f = f / np.linalg.norm(f)
    s = np.cross(f, camera.up)
    if np.linalg.norm(s) < 1e-9:  # looking straight along up
        s = np.cross(f, np.roll(camera.up, 1))
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ camera.eye
    return m


def perspective_matrix(fov: float, aspect: float, near: float, far: float) -> np.ndarray:
    """(4, 4) OpenGL perspective projection, vertical ``fov`` in degrees."""
    t = 1.0 / math.tan(math.radians(fov) / 2)
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = t / aspect, t
    m[2, 2], m[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def project(points: Any, view: Any, projection: Any, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Screen positions of world points.

    Parameters
    ----------
    points : (N, 3) float64, world coordinates.
    view, projection : (4, 4) camera matrices (OpenGL conventions, as Open3D's ``Camera`` returns them).
    width, height : the viewport in pixels.

    Returns
    -------
    pixels : (N, 2) float64, x to the right and y down from the top-left corner of the viewport.
    depth : (N,) float64, distance in front of the camera along its axis (negative behind it).
    """
    points = np.asarray(points, dtype=np.float64)
    homogeneous = np.hstack([points, np.ones((len(points), 1))])  # (N, 4)
    eye = homogeneous @ np.asarray(view, dtype=np.float64).T  # (N, 4)
    clip = eye @ np.asarray(projection, dtype=np.float64).T
    w = np.where(np.abs(clip[:, 3]) < 1e-12, 1e-12, clip[:, 3])
    ndc = clip[:, :2] / w[:, None]
    pixels = np.column_stack([(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height])
    return pixels, -eye[:, 2]


def pixel_ray(x: float, y: float, view: Any, projection: Any, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """The world ray through pixel (x, y) of a perspective camera: origin (3,) at the eye and unit direction (3,).

    Works for any near and far planes, including the infinite far plane of Open3D's window cameras (unprojecting
    the far plane there divides by zero).
    """
    view = np.asarray(view, dtype=np.float64)
    projection = np.asarray(projection, dtype=np.float64)
    ndc_x, ndc_y = 2 * x / width - 1, 1 - 2 * y / height
    # eye space, on the plane z_e = -1: clip = P @ (x_e, y_e, -1, 1) with w = 1
    x_e = (ndc_x + projection[0, 2]) / projection[0, 0]
    y_e = (ndc_y + projection[1, 2]) / projection[1, 1]
    rotation, translation = view[:3, :3], view[:3, 3]
    origin = -rotation.T @ translation
    direction = rotation.T @ np.array([x_e, y_e, -1.0])
    return origin, direction / np.linalg.norm(direction)


def plane_hit(origin: np.ndarray, direction: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """Where a ray meets the plane through ``point`` with ``normal``; None when parallel."""
    denominator = float(direction @ normal)
    if abs(denominator) < 1e-12:
        return None
    t = float((point - origin) @ normal) / denominator
    return origin + t * direction
