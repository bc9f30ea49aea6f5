"""The floor a collection stands on: the shared frame's up axis found from flat contacts, and each shape stood on its
support plane."""

from __future__ import annotations

import logging
import math
from typing import Any, Sequence

import numpy as np

from kpd.collection.templates import rms_unit
from kpd.scan import (
    _dense_subset,
    _rotation_between,
    hull_faces,
    parse_axis,
    rotation_angle,
    support_plane,
)

__all__ = ["floor_up", "stand_collection"]

log = logging.getLogger("kpd.collection")


FLOOR_NEAR = 0.05  # a point within this height (unit RMS radius) of the support plane is on the floor contact


FLOOR_CLEAR = 1.5  # the best direction must have this many times the flat-contact share of the next one


def _floor_samples(clouds: Sequence[np.ndarray], rotations: np.ndarray, indices: Sequence[int], points: int,
                   seed: int) -> dict[int, np.ndarray]:
    """Each shape's dense points (stray ones out), at unit RMS radius in the shared frame."""
    out = {}
    for i in indices:
        c = clouds[i]
        sub = c if len(c) <= points else c[np.random.default_rng([seed, i]).choice(len(c), points, replace=False)]
        out[i] = _dense_subset(rms_unit(sub @ rotations[i].T))
    return out


def _contact(points: np.ndarray, up: np.ndarray, snap: float) -> tuple[float, np.ndarray | None]:
    """The share of ``points`` within FLOOR_NEAR of their support plane with ``up`` up, and its normal (None when
    there is no stable support that way)."""
    found = support_plane(points, up, max_angle=snap)
    if not found.count or not found.stability > 0:
        return 0.0, None
    height = points @ found.normal
    return float(np.mean(height - height.min() < FLOOR_NEAR)), found.normal


def _sphere_directions(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit vectors (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    a = np.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)


def _contact_shares(points: np.ndarray, directions: np.ndarray, snap: float) -> np.ndarray:
    """(D,) for each candidate up direction: the share of ``points`` within FLOOR_NEAR of the support plane under
    them (the area-weighted mean plane of the hull faces within ``snap`` degrees of facing down; 0 without)."""
    faces = hull_faces(points)
    if faces is None:
        return np.zeros(len(directions))
    outward, area, _ = faces  # (F, 3), (F,)
    below = (outward @ -directions.T) >= math.cos(math.radians(snap))  # (F, D)
    normals = -(below * area[:, None]).T @ outward  # (D, 3)
    length = np.linalg.norm(normals, axis=1)
    found = length > 0
    normals[found] /= length[found, None]
    height = points @ normals.T  # (N, D)
    shares = np.mean(height - height.min(axis=0) < FLOOR_NEAR, axis=0)
    return np.where(found, shares, 0.0)


FLOOR_DIRECTIONS = 200  # candidate up directions (about 14 degrees apart, within the 25 degree snap of any axis)


FLOOR_APART = 45.0  # a rival floor lies more than this many degrees from the best


def floor_up(clouds: Sequence[np.ndarray], rotations: np.ndarray, decided: Sequence[int], *, snap: float = 25.0,
             points: int = 2000, seed: int = 0) -> tuple[np.ndarray | None, dict]:
    """The up axis of a collection's shared frame, from the floor its shapes stand on.

    Objects are scanned standing on something, and what they stand on is flat: a shoe's sole, a box's base, the
    plane through a chair's leg tips. For each of FLOOR_DIRECTIONS candidate up directions of the shared frame,
    every decided shape is stood on its support plane with that direction up (the hull faces within ``snap``
    degrees of facing down, as :func:`kpd.scan.support_plane`) and the share of its points within FLOOR_NEAR (unit
    RMS radius) of that plane is taken: large for a flat contact, small for a curved side. The direction with the
    highest median share is the floor when that median is FLOOR_CLEAR times the best one FLOOR_APART degrees or
    more away; the up axis is then the mean support normal of the decided shapes with that direction up.

    Returns
    -------
    up : (3,) unit vector in the shared frame, or None when no direction is a clear floor
    info : {"share": the best direction's median share, "rival_share": the best rival's, "up": ...}
    """
    decided = [int(i) for i in decided]
    info: dict = {"share": None, "rival_share": None, "up": None}
    if len(decided) < 2:
        info["note"] = "fewer than 2 decided shapes"
        return None, info
    work = _floor_samples(clouds, rotations, decided, points, seed)
    directions = _sphere_directions(FLOOR_DIRECTIONS)
    shares = np.median(np.stack([_contact_shares(work[i], directions, snap) for i in decided]), axis=0)  # (D,)
    best = int(np.argmax(shares))
    apart = directions @ directions[best] < math.cos(math.radians(FLOOR_APART))
    rival = float(shares[apart].max()) if apart.any() else 0.0
    info.update(share=float(shares[best]), rival_share=rival)
    if not shares[best] > 0 or shares[best] < FLOOR_CLEAR * rival:
        info["note"] = "no direction is a clear floor"
        return None, info
    up = directions[best]
    for _ in range(2):  # the mean support normal, then once more from it
        normals = [n for n in (_contact(work[i], up, snap)[1] for i in decided) if n is not None]
        if not normals:
            break
        mean = np.mean(normals, axis=0)
        up = mean / np.linalg.norm(mean)
    info["up"] = up.tolist()
    return up, info


def stand_collection(clouds: Sequence[np.ndarray], rotations: np.ndarray, indices: Sequence[int], up: Any, *,
                     snap: float = 25.0, points: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Stand shapes on their support planes in the shared frame.

    Each shape of ``indices`` (turned into the shared frame by ``rotations``) is found its support plane with
    ``up`` (3,) up (:func:`kpd.scan.support_plane`, hull faces within ``snap`` degrees, a stable support only) and
    turned by the smallest rotation taking that plane's normal to ``up``; its turn about ``up`` is kept.

    Returns
    -------
    rotations : (S, 3, 3) float64, the stood rotations (others unchanged)
    tilts : (S,) float64, degrees each shape was turned (nan: not stood)
    """
    up = parse_axis(up)
    out = np.array(rotations, dtype=np.float64, copy=True)
    tilts = np.full(len(out), math.nan)
    work = _floor_samples(clouds, out, indices, points, seed)
    for i, pts in work.items():
        normal = _contact(pts, up, snap)[1]
        if normal is None:
            continue
        turn = _rotation_between(normal, up)
        out[i] = turn @ out[i]
        tilts[i] = rotation_angle(turn)
    return out, tilts
