"""The shared reference frame of annotated datasets: the fixed maps of KeypointNet and ModelNet into it, similarity
transforms, and the registration that fits a dataset's annotation frame to a shape's surface."""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from kpd.errors import InputError
from kpd.geometry import as_points

__all__ = [
    "KEYPOINTNET_TO_REFERENCE", "MODELNET_TO_REFERENCE", "FIT_CANDIDATES", "Similarity", "FrameFit",
    "fit_annotation_frame",
]

log = logging.getLogger("kpd.annotations")


# Row-vector convention everywhere: x_new = x @ M.T.
# The authors' axis fix of KeypointNet coordinates, (x, y, z) -> (-z, y, x) (docs/method.md §8): a rotation about y.
KEYPOINTNET_TO_REFERENCE = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


# ModelNet (z up, chair backs towards +y) -> reference (y up, backs towards -x): (x, y, z) -> (-y, z, -x).
MODELNET_TO_REFERENCE = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])


_MIRROR_LAST = np.diag([1.0, 1.0, -1.0])


# Orthogonal maps tried when registering KeypointNet annotations to a mesh of unknown frame (y up in both):
# the authors' axis fix, the same with the last axis mirrored (ambiguous for mirror-symmetric shapes, SOURCES.md),
# and the ShapeNet v2 frame itself (with either sign of x).
FIT_CANDIDATES = {
    "keypointnet-to-reference": KEYPOINTNET_TO_REFERENCE,
    "keypointnet-to-reference-mirrored": _MIRROR_LAST @ KEYPOINTNET_TO_REFERENCE,
    "identity": np.eye(3),
    "identity-mirrored": np.diag([-1.0, 1.0, 1.0]),
}


SPLITS = ("train", "val", "test")


class Similarity(NamedTuple):
    """``x -> scale * x @ matrix.T + translation`` on (N, 3) rows; ``matrix`` is orthogonal (a mirror is allowed).

    scale : float; matrix : (3, 3) float64; translation : (3,) float64.
    """

    scale: float
    matrix: np.ndarray
    translation: np.ndarray

    @classmethod
    def identity(cls) -> "Similarity":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def linear(cls, matrix: Any) -> "Similarity":
        return cls(1.0, np.asarray(matrix, dtype=np.float64), np.zeros(3))

    def apply(self, points: Any) -> np.ndarray:
        """(N, 3) -> (N, 3)."""
        return self.scale * (as_points(points, min_count=0) @ self.matrix.T) + self.translation

    def inverse(self) -> "Similarity":
        return Similarity(1.0 / self.scale, self.matrix.T, -(self.translation @ self.matrix) / self.scale)

    def then(self, other: "Similarity") -> "Similarity":
        """The map ``other(self(x))``."""
        return Similarity(other.scale * self.scale, other.matrix @ self.matrix,
                          other.scale * (self.translation @ other.matrix.T) + other.translation)

    def to_dict(self) -> dict:
        return {"scale": float(self.scale), "matrix": self.matrix.tolist(), "translation": self.translation.tolist()}


class FrameFit(NamedTuple):
    """Result of :func:`fit_annotation_frame`.

    transform : Similarity, KeypointNet coordinates -> the geometry's coordinates.
    candidate : name of the orthogonal map chosen (a key of :data:`FIT_CANDIDATES`).
    distances : (J,) float64, distance of each mapped keypoint to the nearest surface point (geometry units).
    residuals : {candidate: mean distance} for every candidate tried.
    """

    transform: Similarity
    candidate: str
    distances: np.ndarray
    residuals: dict


def fit_annotation_frame(keypoints: Any, surface: Any, *, candidates: dict | None = None,
                         source_diagonal: float = 1.0, prefer_first: float = 0.1, shift: float = 0.1,
                         iterations: int = 50) -> FrameFit:
    """Register KeypointNet annotations to another copy of the model (a mesh re-normalised elsewhere).

    KeypointNet models are ShapeNet v2 models, normalised to a unit bounding-box diagonal; a copy of the same model
    normalised elsewhere differs by an axis change, a scale and a translation. For each orthogonal map Q of
    ``candidates`` the keypoints are rotated by Q, scaled by ``diagonal(surface) / source_diagonal`` and translated:
    starting from matching bounding-box centres (and 26 shifts of ``shift`` times the diagonal around it), the
    translation is refined by closest-point iterations (ICP, translation only) towards the surface points. The
    candidate with the lowest mean distance wins; the first candidate is kept unless another one is better by more
    than ``prefer_first`` (relative), because mirror-symmetric shapes fit a mirrored map almost as well (SOURCES.md).

    Parameters
    ----------
    keypoints : (J, 3) float64, KeypointNet coordinates (J >= 3).
    surface : (N, 3) float64, dense points on the other copy's surface (e.g. 20,000 area-weighted samples).
    candidates : {name: (3, 3) orthogonal}, default :data:`FIT_CANDIDATES`.
    source_diagonal : bounding-box diagonal of the KeypointNet model (1 for ShapeNet v2).

    Returns
    -------
    FrameFit
    """
    kp = as_points(keypoints, "keypoints", min_count=3)
    pts = as_points(surface, "surface", min_count=4)
    candidates = FIT_CANDIDATES if candidates is None else candidates
    if not candidates:
        raise InputError("fit_annotation_frame needs at least one candidate map")
    tree = cKDTree(pts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = float(np.linalg.norm(hi - lo)) / source_diagonal
    grid = np.stack(np.meshgrid(*[[-shift, 0.0, shift]] * 3, indexing="ij"), axis=-1).reshape(-1, 3) * scale
    fits = {}
    for name, matrix in candidates.items():
        q = np.asarray(matrix, dtype=np.float64)
        y = scale * (kp @ q.T)  # (J, 3)
        start = (lo + hi) / 2 - (y.min(axis=0) + y.max(axis=0)) / 2
        best = None
        for offset in grid:
            t = start + offset
            for _ in range(iterations):
                _, nearest = tree.query(y + t)
                t_new = (pts[nearest] - y).mean(axis=0)
                done = np.abs(t_new - t).max() < 1e-10 * scale
                t = t_new
                if done:
                    break
            d, _ = tree.query(y + t)
            if best is None or d.mean() < best[0]:
                best = (float(d.mean()), t, d)
        fits[name] = (best[0], Similarity(scale, q, best[1]), best[2])
    names = list(fits)
    chosen = min(names, key=lambda n: fits[n][0])
    if fits[names[0]][0] <= (1.0 + prefer_first) * fits[chosen][0]:
        chosen = names[0]
    return FrameFit(fits[chosen][1], chosen, fits[chosen][2], {n: f[0] for n, f in fits.items()})
