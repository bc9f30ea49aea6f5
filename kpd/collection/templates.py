"""Templates of a collection: a rotation-invariant shape descriptor, the descriptor medoid that starts the alignment and
the chamfer medoid each round re-estimates."""

from __future__ import annotations

import logging
import math
from typing import Any, Sequence

import numpy as np
from scipy.spatial import cKDTree

from kpd.errors import InputError
from kpd.geometry import as_points, as_rng

__all__ = ["rms_unit", "shape_descriptor", "descriptor_medoid", "chamfer_medoid"]

log = logging.getLogger("kpd.collection")


def rms_unit(points: np.ndarray) -> np.ndarray:
    """(N, 3) ``points`` centred and scaled to unit root-mean-square radius."""
    centred = points - points.mean(axis=0)
    radius = math.sqrt(float((centred**2).sum(axis=1).mean()))
    if not radius > 0:
        raise InputError(f"a shape of {len(points)} points has zero extent")
    return centred / radius


def shape_descriptor(points: Any, *, pairs: int = 20000, bins: int = 32, seed: int = 0) -> np.ndarray:
    """A rotation-invariant summary of a shape at unit RMS radius: the histogram of distances between random point
    pairs (Osada et al.'s D2) followed by the square roots of the principal variances.

    Returns
    -------
    descriptor : (bins + 3,) float64
    """
    unit = rms_unit(as_points(points, min_count=10))
    rng = as_rng(seed)
    i, j = rng.integers(len(unit), size=(2, pairs))
    d = np.linalg.norm(unit[i] - unit[j], axis=1)  # (pairs,)
    hist = np.histogram(d, bins=bins, range=(0.0, 4.0))[0] / pairs
    extents = np.sqrt(np.maximum(np.linalg.eigvalsh(unit.T @ unit / len(unit)), 0.0))  # ascending
    return np.concatenate([hist, extents])


def descriptor_medoid(clouds: Sequence[np.ndarray], *, seed: int = 0) -> int:
    """Index of the shape whose :func:`shape_descriptor` has the least total L1 distance to the others'."""
    if len(clouds) == 0:
        raise InputError("no shapes to choose a template from")
    desc = np.stack([shape_descriptor(c, seed=seed) for c in clouds])  # (S, D)
    total = np.abs(desc[:, None, :] - desc[None, :, :]).sum(axis=(1, 2))  # (S,)
    return int(np.argmin(total))


def chamfer_medoid(clouds: Sequence[np.ndarray], rotations: np.ndarray, candidates: Sequence[int], *,
                   points: int = 512, others: int = 64, seed: int = 0) -> int:
    """Index (among ``candidates``) of the shape nearest, by mean symmetric chamfer distance at unit RMS radius in
    the shared frame, to a seeded sample of ``others`` of the candidates."""
    candidates = list(candidates)
    if not candidates:
        raise InputError("no shapes to choose a template from")
    rng = as_rng(seed)
    turned = {}
    for i in candidates:
        c = clouds[i]
        sub = c if len(c) <= points else c[rng.choice(len(c), points, replace=False)]
        turned[i] = rms_unit(sub @ rotations[i].T)
    trees = {i: cKDTree(p) for i, p in turned.items()}
    pool = candidates if len(candidates) <= others else list(rng.choice(candidates, others, replace=False))
    best, best_cost = candidates[0], math.inf
    for i in candidates:
        cost = 0.0
        for j in pool:
            if j != i:
                cost += float((trees[j].query(turned[i])[0] ** 2).mean() + (trees[i].query(turned[j])[0] ** 2).mean())
        if cost < best_cost:
            best, best_cost = i, cost
    return int(best)
