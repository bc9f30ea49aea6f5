"""Plausible variants of a bound shape: what ``kpd amplify`` and :class:`kpd.augment.Augmenter` draw.

A variant is a keypoint set drawn from the category prior around the shape's own keypoints, and the shape deformed
to it. Two measures say whether people would keep it:

- **typical**: every prior coefficient of its keypoints within ``TYPICAL_SIGMA`` standard deviations
  (``sigma = max_m |c_m| / sqrt(λ_m)``). Draws are made inside that range
  (:meth:`kpd.prior.KeypointPrior.sample` with ``limit``): a source beyond it is first brought to its edge, so an
  unusual source's variants are the nearest typical ones;
- **flat**: at most ``FOLDED_LIMIT`` of its triangles turned over against the source's normals (a fold of the
  surface, which a large move of a thin part can make).

A draw that folds too much is drawn again with its next attempt's generator (:func:`attempt_sequence`), up to
``ATTEMPTS`` draws; when none is flat enough, the least folded one's offset from the (typical) source is halved until
it is. Every step depends on the variant's seed alone, so the same variant is the same numbers in any process.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

__all__ = ["ATTEMPTS", "FOLDED_LIMIT", "SIGMA_ROUNDING", "TYPICAL_SIGMA", "Folds", "Plausible", "attempt_sequence",
           "draw_plausible", "typical"]

TYPICAL_SIGMA = 3.0  # a variant is in the prior's typical range when every coefficient is within 3 deviations
FOLDED_LIMIT = 0.005  # at most 0.5% of a variant's triangles may turn over
SIGMA_ROUNDING = 1e-9  # a coefficient brought to the range's edge may come back a rounding beyond it
ATTEMPTS = 8  # draws of a variant before its least folded one is moved less
_SMALLEST_SHRINK = 1.0 / 64


def typical(sigma: float | np.ndarray) -> bool | np.ndarray:
    """Whether a variant's ``sigma`` is within the typical range (up to the rounding of a coefficient at its edge)."""
    return np.asarray(sigma) <= TYPICAL_SIGMA + SIGMA_ROUNDING


class Folds:
    """Counts a deformed mesh's folded triangles against the source's (its normals computed once).

    Parameters
    ----------
    vertices : (V, 3) float64, the source; triangles : (T, 3) int.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        from kpd.triangles import cross

        normals = cross(np.asarray(vertices, dtype=np.float64), triangles)  # (T, 3)
        length = np.linalg.norm(normals, axis=1)
        valid = length > 1e-12 * max(float(length.max(initial=0.0)), 1e-300)  # degenerate ones have no side
        self.triangles = np.asarray(triangles)[valid]  # (T', 3)
        self.normals = normals[valid]  # (T', 3) float64

    @classmethod
    def kept(cls, triangles: np.ndarray, normals: np.ndarray) -> Folds:
        """The counter whose :attr:`triangles` and :attr:`normals` were kept (an augmenter's cache maps them)."""
        folds = cls.__new__(cls)
        folds.triangles, folds.normals = triangles, normals
        return folds

    def fraction(self, vertices: np.ndarray) -> float:
        """The fraction of the source's non-degenerate triangles whose normal points against its own before the edit
        (0 for a mesh without any)."""
        if not len(self.triangles):
            return 0.0
        from kpd.triangles import turned_over

        return turned_over(vertices, self.triangles, self.normals) / len(self.triangles)


def attempt_sequence(entropy: int | list[int], attempt: int) -> np.random.SeedSequence:
    """The seed sequence of draw ``attempt`` of a variant seeded by ``entropy``: attempt 0 is ``entropy``'s own
    sequence (``default_rng(entropy)``); the others are its children by spawn key, independent of it and of any
    other variant's."""
    return np.random.SeedSequence(entropy, spawn_key=(attempt,) if attempt else ())


class Plausible(NamedTuple):
    """A drawn variant (:func:`draw_plausible`).

    keypoints : (K, 3) float64 in the model frame; coefficients : (M,) their prior coefficients;
    sigma : ``max |c_m| / sqrt(λ_m)``; folded : the fraction of triangles turned over;
    deformed : what ``deform`` returned for them; attempt : the accepted draw's number (0: the variant's own seed);
    shrink : the factor its offset from the typical source was scaled by (1: none).
    """

    keypoints: np.ndarray
    coefficients: np.ndarray
    sigma: float
    folded: float
    deformed: Any
    attempt: int
    shrink: float


def draw_plausible(prior: Any, base: np.ndarray, scale: float, entropy: int | list[int],
                   deform: Callable[[np.ndarray], tuple[Any, float]]) -> Plausible:
    """A plausible variant of the shape whose keypoints (model frame, (K, 3)) are ``base`` (see the module notes).

    Parameters
    ----------
    prior : the model's :class:`kpd.prior.KeypointPrior`.
    scale : standard deviations of the prior's components in a draw.
    entropy : the variant's seed (an integer or a list of them, as ``numpy.random.default_rng`` takes).
    deform : ``deform(keypoints)`` with model-frame keypoints (K, 3) -> ``(deformed, folded fraction)``.
    """
    sd = np.sqrt(prior.explained_variance_)  # (M,)

    def make(keypoints: np.ndarray, attempt: int, shrink: float) -> Plausible:
        deformed, folded = deform(keypoints)
        coefficients = prior.coefficients(keypoints)
        return Plausible(keypoints, coefficients, float(np.abs(coefficients / sd).max()), float(folded), deformed,
                         attempt, shrink)

    best = None
    for attempt in range(ATTEMPTS):
        rng = np.random.default_rng(attempt_sequence(entropy, attempt))
        variant = make(prior.sample(1, seed=rng, scale=scale, base=base, limit=TYPICAL_SIGMA)[0], attempt, 1.0)
        if variant.folded <= FOLDED_LIMIT:
            return variant
        if best is None or variant.folded < best.folded:
            best = variant
    centre = prior.typical_base(base, TYPICAL_SIGMA)  # (K, 3)
    variant, shrink = best, 1.0
    while variant.folded > FOLDED_LIMIT and shrink > _SMALLEST_SHRINK:
        shrink /= 2
        variant = make(centre + shrink * (best.keypoints - centre), best.attempt, shrink)
    if variant.folded > FOLDED_LIMIT:  # the typical source itself (a source brought into range may fold)
        variant = make(centre, best.attempt, 0.0)
    return variant
