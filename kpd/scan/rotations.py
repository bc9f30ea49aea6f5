"""Rotation helpers of scan orientation: axis names, angles between rotations, the candidate rotation sets (the 24
proper signed axis permutations, the 60 icosahedral rotations) and principal frames."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from kpd.errors import InputError


__all__ = ["AXES", "parse_axis", "rotation_angle", "proper_signed_permutations", "icosahedral_rotations"]

log = logging.getLogger("kpd.scan")


AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


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
