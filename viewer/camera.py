"""The camera: where it stands for a view of a shape, its view and projection matrices, and picking (points to
pixels, pixels to rays, rays to planes)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from kpd._compiled import njit
from kpd.viewer.settings import ViewSettings, front_axis, up_axis

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


def camera_pose(vertices: Any, settings: ViewSettings, *, margin: float = 0.9, closest: bool = True) -> Camera:
    """The camera of a view: looking at ``vertices`` (V, 3) from the settings' azimuth and elevation around the up
    axis, as close as lets every vertex into the view with ``margin`` (a fraction of the view's half-width and
    half-height) to spare, and aimed so that the picture of the vertices is centred (in perspective the near side of
    a shape looks larger, so its bounding box's centre is not the picture's: a shoe seen from behind sat low and to
    one side); ``settings.zoom`` > 1 moves it closer. With ``closest`` False the camera stays as far as a view aimed at
    the bounding box's centre needs (the editor's home view: drawn larger, a million-vertex mesh takes longer to draw
    in software), still centred.

    ``vertices`` may be a list of (N, 3) arrays (a shape and its keypoints, several frames), framed together without
    joining them. Each array is read twice by a compiled pass.

    The front view (azimuth 0) looks from ``settings.front``, by default the axis that a glTF file with the same up
    axis turns to glTF's front (:func:`kpd.viewer.settings.front_axis`: -y for z up, a ModelNet chair's front; +z
    for y up), as the browser page does; positive azimuths turn the camera towards ``up x front``.
    """
    parts = [np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
             for p in (vertices if isinstance(vertices, (list, tuple)) else [vertices])]
    return camera_pose_over(lambda: parts, settings, margin=margin, closest=closest)


def camera_pose_over(parts: Callable[[], Iterable[np.ndarray]], settings: ViewSettings, *, margin: float = 0.9,
                     bounds: tuple[np.ndarray, np.ndarray] | None = None, closest: bool = True) -> Camera:
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
    front = front_axis(settings.up) if settings.front is None else up_axis(settings.front)
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
    # A point at x, y across and w towards the camera from the centre, seen from distance D with the aim moved across
    # by (sx, sy), is in the view when |x - sx| <= t (D - w) and |y - sy| <= t' (D - w), t and t' the tangents of
    # the margin. The nearest D that fits across is (A(t) - B(t)) / 2t, A(t) = max(x + t w), B(t) = min(x - t w),
    # at sx = (A(t) + B(t)) / 2, where the shape touches both sides (and so upwards). The tighter way sets D and its
    # aim; the other way's aim is where its shape touches both sides of a narrower view, t* with (A - B) / 2t* = D:
    # A and B are known on a grid of tangents (_extents) and between them taken as straight.
    kh, kv = margin * tan_h, margin * tan_v
    steps = np.arange(_STEPS + 1) / _STEPS
    tangents = np.stack([kh * steps, kv * steps])  # (2, S + 1)
    ends = np.empty((2, 2, _STEPS + 1))
    ends[:, 0], ends[:, 1] = -np.inf, np.inf
    for p in parts_now():
        _extents(p, center, axes, tangents, ends)
    if np.isfinite(ends).all():
        fits = (ends[:, 0, -1] - ends[:, 1, -1]) / (2 * tangents[:, -1])  # (2,) the distance each way needs
        # aimed at the centre, a point needs w + |x| / t: max(A(t), -B(t)) / t
        distance = float(fits.max()) if closest else float(
            (np.maximum(ends[:, 0, -1], -ends[:, 1, -1]) / tangents[:, -1]).max())
        shifts = [_aim(ends[a, 0], ends[a, 1], tangents[a], distance) for a in range(2)]
        center = center + shifts[0] * right + shifts[1] * upward
    else:
        distance = 1.0
    distance = max(distance, 1e-3 * radius) / settings.zoom
    eye = center + distance * direction
    return Camera(center=center, eye=eye, up=up, fov=float(settings.fov),
                  near=max(distance - 3 * radius, distance / 100),
                  far=distance + 3 * radius)


def box(parts: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(3,) lowest and (3,) highest coordinates of the points of (N, 3) float64 arrays (zeros without points)."""
    boxes = [_box(p) for p in parts if len(p)]
    if not boxes:
        return np.zeros(3), np.zeros(3)
    return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


@njit(nogil=True)
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


_STEPS = 8  # tangents from 0 to the margin's at which the shape's extents are found, each way


def _aim(high: np.ndarray, low: np.ndarray, tangents: np.ndarray, distance: float) -> float:
    """Where to aim across one way: the middle of the shape's extents ``high`` (A) and ``low`` (B) at the tangent t*
    with (A(t*) - B(t*)) / 2t* = ``distance`` (the last tangent, the margin's, when that way is the tighter one), A
    and B straight between the grid's ``tangents``."""
    need = 2 * distance * tangents  # (S + 1,): A - B >= need at the tangents not above t*
    room = (high - low) - need
    j = int(np.flatnonzero(room >= 0)[-1]) if (room >= 0).any() else 0
    if j == len(tangents) - 1:
        return float(high[j] + low[j]) / 2
    # on [t_j, t_j+1]: (A_j - B_j) + (a - b) u = 2 D (t_j + u), a and b the slopes
    dt = tangents[j + 1] - tangents[j]
    slope = ((high[j + 1] - high[j]) - (low[j + 1] - low[j])) / dt
    denominator = 2 * distance - slope
    u = min(max(room[j] / denominator, 0.0), dt) if denominator > 0 else 0.0
    return float((high[j] + low[j]) + ((high[j + 1] - high[j]) + (low[j + 1] - low[j])) * u / dt) / 2


@njit(nogil=True, error_model="numpy")
def _extents(points, center, axes, tangents, ends):  # pragma: no cover - compiled
    """``ends`` (2, 2, S + 1) widened to max(x + t w) and min(x - t w) over ``points`` for each of
    ``tangents[0]``, and of y for ``tangents[1]``, with x, y, w their offsets from ``center`` along ``axes`` (right,
    up, towards the camera); 256 points at a time, their offsets first."""
    n = tangents.shape[1]
    x = np.empty(256)
    y = np.empty(256)
    w = np.empty(256)
    for start in range(0, points.shape[0], 256):
        m = min(256, points.shape[0] - start)
        for i in range(m):
            ox = points[start + i, 0] - center[0]
            oy = points[start + i, 1] - center[1]
            oz = points[start + i, 2] - center[2]
            x[i] = ox * axes[0, 0] + oy * axes[0, 1] + oz * axes[0, 2]
            y[i] = ox * axes[1, 0] + oy * axes[1, 1] + oz * axes[1, 2]
            w[i] = ox * axes[2, 0] + oy * axes[2, 1] + oz * axes[2, 2]
        for j in range(n):
            th = tangents[0, j]
            tv = tangents[1, j]
            a0, b0, a1, b1 = ends[0, 0, j], ends[0, 1, j], ends[1, 0, j], ends[1, 1, j]
            for i in range(m):
                a0 = max(a0, x[i] + th * w[i])
                b0 = min(b0, x[i] - th * w[i])
                a1 = max(a1, y[i] + tv * w[i])
                b1 = min(b1, y[i] - tv * w[i])
            ends[0, 0, j], ends[0, 1, j], ends[1, 0, j], ends[1, 1, j] = a0, b0, a1, b1


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


def pixel_ray(x: float, y: float, view: Any, projection: Any, width: float,
              height: float) -> tuple[np.ndarray, np.ndarray]:
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
