"""Synthetic clouds the scan tests share (the real sneaker and chair are fixtures in conftest.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def rotation(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


def cylinder(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1, 1, n)
    return np.c_[0.4 * np.cos(theta), 0.4 * np.sin(theta), z]


def sphere(n: int, seed: int, center=(0.0, 0.0, 0.0), radius=1.0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def floor(n: int, seed: int, half: float, z: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-half, half, (n, 2)), np.full(n, z) + rng.normal(0, 1e-3, n)]


def lumpy(n: int, seed: int) -> np.ndarray:
    """An asymmetric blob: an ellipsoid with a bump and a tail (no rotational symmetry)."""
    x = sphere(n, seed) * [1.0, 0.6, 0.35]
    bump = sphere(n // 4, seed + 1, center=(0.7, 0.3, 0.2), radius=0.25)
    tail = np.c_[np.linspace(-1.6, -1.0, n // 8), np.zeros(n // 8), np.linspace(0.0, 0.4, n // 8)]
    return np.concatenate([x, bump, tail])


def table(n: int, seed: int) -> np.ndarray:
    """A table standing on z = 0: a top at z = 1 and four legs."""
    rng = np.random.default_rng(seed)
    top = np.c_[rng.uniform(-1.0, 1.0, n), rng.uniform(-0.6, 0.6, n), rng.uniform(1.0, 1.05, n)]
    legs = [np.c_[rng.normal(x, 0.02, n // 8), rng.normal(y, 0.02, n // 8), rng.uniform(0.0, 1.0, n // 8)]
            for x, y in ((-0.9, -0.5), (-0.9, 0.5), (0.9, -0.5), (0.9, 0.5))]
    return np.concatenate([top, *legs])
