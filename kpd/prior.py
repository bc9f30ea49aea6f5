"""The category prior: PCA over the keypoints a model predicts on its training set (paper §3.4, docs/method.md §10).

The paper keeps 8 principal components of the 3K-dimensional keypoint vectors and uses them for two things the
authors never released:

* **synchronised editing** -- the user moves a few keypoints; the others follow as the category's shapes say (move one
  chair leg and its partner moves too), and
* **sampling** -- new keypoint sets drawn from the component distribution, used to deform a shape into variants.

Synchronisation works on *offsets*, so a shape keeps what makes it itself: with the edited keypoints ``E`` moved by
``d``, every keypoint moves by the conditional mean of a Gaussian over keypoint sets given that move,

    Δ = Σ[:, E] Σ[E, E]⁻¹ d,        Σ = Σ_m λ_m c_m c_mᵀ + ρ·P + ridge·I                  (3K × 3K)

and the edited ones are then set exactly to their targets. ``c_m``, ``λ_m`` are the principal components and their
variances; ``ridge`` is an isotropic noise (by default probabilistic PCA's maximum-likelihood noise variance, the
mean variance of the discarded directions, scikit-learn's ``noise_variance_``). A zero edit moves nothing.

Fitted with the mirror images of the training sets (``fit(sets, mirrored_sets)``: the keypoints a model predicts on
each mirrored training shape, mirrored back), the prior is **mirror-symmetric**: the permutation that pairs each
keypoint with its mirror partner is found as for the mirror-consistency metric
(:func:`kpd.metrics.fit_mirror_permutation`), the sets are augmented with their mirror images, and the components are
the principal directions of the symmetric part of that covariance (shapes of the category are mirror-symmetric; the
network's own left/right placement noise is not shape variation). ``P = (I + R) / 2`` projects onto mirror-symmetric
offsets (``R`` mirrors a keypoint set and permutes it), so ``ρ·P`` says that a keypoint and its mirror partner may
also vary together on their own, independently of the others, with variance ``ρ = part_variance × mean(λ)`` per
coordinate. Under this Gaussian, moving one keypoint moves its partner by the mirrored move (a chair's other back
corner, the partner leg) and the rest of the category only as much as its components explain beyond that part's
own variation (measured in ``benchmarks/bench_edits.py``). Without mirrored sets (``ρ = 0``) the sync is the plain
probabilistic-PCA conditional mean of earlier bundles.

The keypoints live in each shape's own [-1, 1] box, so the prior knows proportions, not sizes: an edit far outside
what the category shows (several standard deviations, say, raising a chair's top above the box) is explained by
moving everything else a lot; ``scale`` in :meth:`KeypointPrior.sample` and modest edits stay in range.
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

import numpy as np

from kpd.errors import InputError, NotFittedError
from kpd.geometry import as_rng

__all__ = ["KeypointPrior"]

log = logging.getLogger(__name__)


class KeypointPrior:
    """PCA of a category's keypoint sets (the paper's shape prior), with synchronised edits and sampling.

    Parameters
    ----------
    n_components : M, principal components kept (8 in the paper).
    ridge : noise variance of an edit, in squared model-frame units ([-1, 1] box): how closely the
        component model must reproduce the edited keypoints before they are set exactly. Smaller follows the
        edit more literally with more component energy; larger keeps the other keypoints closer to where they were.
        None (default) uses the fitted ``noise_variance_``.
    part_variance : with a mirror (``fit`` given mirrored sets): the variance of a keypoint pair's own symmetric
        variation, in units of the mean component variance; larger keeps the other keypoints stiller in a
        synchronised edit.
    mirror_axis : the mirror's axis (0 = x, the left/right axis of ModelNet and ShapeNet shapes).

    Attributes
    ----------
    mean_ : (K, 3) float64, mean keypoint set.
    components_ : (M, K, 3) float64, orthonormal principal directions (as flat 3K vectors), by decreasing variance.
    explained_variance_ : (M,) float64, variance of the training keypoint sets along each component.
    explained_variance_ratio_ : (M,) float64, share of the total variance.
    noise_variance_ : float, mean variance of the discarded directions (probabilistic PCA's noise), floored at
        1e-9 of the total variance.
    n_samples_ : int, keypoint sets the prior was fitted on.
    mirror_permutation_ : (K,) int64 or None; keypoint k's mirror partner is ``mirror_permutation_[k]`` (itself for a
        keypoint on the mirror plane). None when fitted without mirrored sets.
    """

    def __init__(self, *, n_components: int = 8, ridge: float | None = None, part_variance: float = 2.0,
                 mirror_axis: int = 0) -> None:
        self.n_components = n_components
        self.ridge = ridge
        self.part_variance = part_variance
        self.mirror_axis = mirror_axis

    # --- fitting ----------------------------------------------------------------------------------------------

    def fit(self, keypoint_sets: Any, mirrored_sets: Any = None) -> "KeypointPrior":
        """Fit the components to keypoint sets.

        Parameters
        ----------
        keypoint_sets : (S, K, 3) float, one keypoint set per training shape, in the model frame.
        mirrored_sets : (S, K, 3) float or None; ``mirrored_sets[s]`` = the keypoints predicted on the mirror image
            of shape s (about ``mirror_axis``), mirrored back into the shape's frame. Given, the prior is
            mirror-symmetric (module docstring).

        Returns
        -------
        self
        """
        sets = _as_sets(keypoint_sets, "keypoint_sets")
        s, k, _ = sets.shape
        m = self._check_params()
        permutation = None
        if mirrored_sets is not None:
            from kpd.metrics import fit_mirror_permutation

            mirrored = _as_sets(mirrored_sets, "mirrored_sets")
            if mirrored.shape != sets.shape:
                raise InputError(f"mirrored_sets must have the shape of keypoint_sets {sets.shape}; got "
                                 f"{mirrored.shape}")
            permutation = fit_mirror_permutation(sets, mirrored)
            if not (permutation[permutation] == np.arange(k)).all():
                raise InputError(f"the keypoints do not pair up under the mirror (best permutation "
                                 f"{permutation.tolist()} is not its own inverse); fit without mirrored_sets")
            sets = np.concatenate([sets, self._mirror(sets, permutation)])  # the mirror images are shapes too
        if m > min(s - 1, 3 * k):
            raise InputError(
                f"n_components must be at most min(S - 1, 3K) = {min(s - 1, 3 * k)} for S={s} keypoint sets of "
                f"K={k}; got {m}"
            )
        flat = sets.reshape(len(sets), 3 * k)  # (S, 3K)
        mean = flat.mean(axis=0)
        centred = flat - mean
        if permutation is None:
            _, singular, vt = np.linalg.svd(centred, full_matrices=False)
            variance = singular**2 / (len(sets) - 1)  # (min(S, 3K),)
            components = vt[:m]
            rest = 3 * k - m
        else:
            # principal directions of the mirror-symmetric part of the covariance
            sym = self._symmetric_projector(permutation)  # (3K, 3K)
            covariance = sym @ (centred.T @ centred / (len(sets) - 1)) @ sym
            variance, vectors = np.linalg.eigh(covariance)
            order = np.argsort(variance)[::-1]
            variance, components = np.clip(variance[order], 0.0, None), vectors[:, order].T[:m]
            rest = int(round(np.trace(sym))) - m
            if rest < 0:
                raise InputError(f"n_components={m} exceeds the {m + rest} mirror-symmetric directions of K={k} "
                                 "keypoints; lower n_components")
        components = _fix_signs(components)  # (M, 3K)
        if not variance[m - 1] > 0.0:
            raise InputError(f"the keypoint sets span fewer than n_components={m} directions; lower n_components")
        self.mean_ = mean.reshape(k, 3)
        self.components_ = components.reshape(m, k, 3)
        self.explained_variance_ = variance[:m].copy()
        total = float(variance.sum())
        self.explained_variance_ratio_ = variance[:m] / total
        self.noise_variance_ = max(float(variance[m:m + rest].sum()) / rest if rest > 0 else 0.0, 1e-9 * total)
        self.n_samples_ = s
        self.mirror_permutation_ = permutation
        log.info("prior: %d components explain %.1f%% of the keypoint variance over %d sets%s",
                 m, 100 * self.explained_variance_ratio_.sum(), s, "" if permutation is None else
                 f" and their mirror images (mirror pairs {_pairs(permutation)})")
        return self

    def _mirror(self, sets: np.ndarray, permutation: np.ndarray) -> np.ndarray:
        """(S, K, 3): the mirror images of keypoint sets, permuted into the keypoint order (``R`` of the docstring)."""
        flip = np.ones(3)
        flip[self.mirror_axis] = -1.0
        return sets[:, permutation] * flip

    def _symmetric_projector(self, permutation: np.ndarray) -> np.ndarray:
        """(3K, 3K) ``P = (I + R) / 2``, the projector onto mirror-symmetric keypoint offsets."""
        k = len(permutation)
        mirror = np.zeros((3 * k, 3 * k))
        for i, j in enumerate(permutation):
            for a in range(3):
                mirror[3 * i + a, 3 * int(j) + a] = -1.0 if a == self.mirror_axis else 1.0
        return 0.5 * (np.eye(3 * k) + mirror)

    def _check_params(self) -> int:
        m = self.n_components
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise InputError(f"n_components must be a positive integer; got {m!r}")
        ridge = self.ridge
        if ridge is not None and not (isinstance(ridge, (int, float, np.floating)) and not isinstance(ridge, bool)
                                      and np.isfinite(ridge) and ridge > 0):
            raise InputError(f"ridge must be a positive number or None; got {ridge!r}")
        part = self.part_variance
        if isinstance(part, bool) or not isinstance(part, (int, float, np.floating)) or not (np.isfinite(part)
                                                                                                and part >= 0):
            raise InputError(f"part_variance must be a non-negative number; got {part!r}")
        if self.mirror_axis not in (0, 1, 2):
            raise InputError(f"mirror_axis must be 0, 1 or 2; got {self.mirror_axis!r}")
        return int(m)

    @property
    def ridge_(self) -> float:
        """The ridge in use: ``ridge``, or the fitted ``noise_variance_`` when ``ridge`` is None."""
        self._check_fitted()
        return float(self.noise_variance_ if self.ridge is None else self.ridge)

    def _check_fitted(self) -> None:
        if not hasattr(self, "components_"):
            raise NotFittedError("this KeypointPrior is not fitted yet; call fit(keypoint_sets) or from_dict first")

    @property
    def part_variance_(self) -> float:
        """``ρ``: the per-coordinate variance of a mirror pair's own variation (0 without a mirror)."""
        self._check_fitted()
        if self.mirror_permutation_ is None:
            return 0.0
        return float(self.part_variance * self.explained_variance_.mean())

    def covariance(self) -> np.ndarray:
        """(3K, 3K) float64: the Gaussian ``Σ`` of the synchronised edit (module docstring), over flat keypoints."""
        self._check_fitted()
        flat = self.components_.reshape(len(self.components_), -1)  # (M, 3K)
        sigma = (flat.T * self.explained_variance_) @ flat + self.ridge_ * np.eye(flat.shape[1])
        if self.mirror_permutation_ is not None:
            sigma += self.part_variance_ * self._symmetric_projector(self.mirror_permutation_)
        return sigma

    @property
    def num_keypoints(self) -> int:
        self._check_fitted()
        return len(self.mean_)

    def _as_keypoints(self, keypoints: Any, name: str = "keypoints") -> np.ndarray:
        k = self.num_keypoints
        array = np.asarray(keypoints, dtype=np.float64)
        if array.shape != (k, 3):
            raise InputError(f"{name} must have shape (K, 3) = ({k}, 3) for this prior; got {array.shape}")
        if not np.isfinite(array).all():
            raise InputError(f"{name} must be finite")
        return array

    # --- coefficients -----------------------------------------------------------------------------------------

    def coefficients(self, keypoints: Any) -> np.ndarray:
        """(M,) float64: the component coefficients of a keypoint set (its projection, relative to the mean)."""
        keypoints = self._as_keypoints(keypoints)
        return np.tensordot(self.components_, keypoints - self.mean_, axes=([1, 2], [0, 1]))

    def synthesize(self, coefficients: Any, base: Any = None) -> np.ndarray:
        """(K, 3) float64: ``base + Σ_m coefficients[m] · components_[m]`` (``base`` defaults to ``mean_``)."""
        self._check_fitted()
        z = np.asarray(coefficients, dtype=np.float64)
        m = len(self.components_)
        if z.shape != (m,) or not np.isfinite(z).all():
            raise InputError(f"coefficients must be {m} finite numbers; got shape {z.shape}")
        base = self.mean_ if base is None else self._as_keypoints(base, "base")
        return base + np.tensordot(z, self.components_, axes=1)

    # --- editing ----------------------------------------------------------------------------------------------

    def sync(self, keypoints: Any, edits: Mapping[int, Any]) -> np.ndarray:
        """Move the edited keypoints to their new positions and the others as the prior says.

        Parameters
        ----------
        keypoints : (K, 3) float64, the current keypoints, in the model frame.
        edits : {index: (3,) new position} in the model frame.

        Returns
        -------
        keypoints : (K, 3) float64; ``keypoints[i] == edits[i]`` exactly for every edited ``i``.
        """
        keypoints = self._as_keypoints(keypoints)
        k = len(keypoints)
        indices, targets = [], []
        for index, position in edits.items():
            if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < k:
                raise InputError(f"edited keypoint index must be an integer in [0, {k}); got {index!r}")
            position = np.asarray(position, dtype=np.float64)
            if position.shape != (3,) or not np.isfinite(position).all():
                raise InputError(f"edit of keypoint {index} must be 3 finite numbers; got {position.tolist()}")
            indices.append(int(index))
            targets.append(position)
        result = keypoints.copy()
        if not indices:
            return result
        self._check_params()
        targets = np.stack(targets)  # (E, 3)
        offsets = (targets - keypoints[indices]).ravel()  # (3E,)
        sigma = self.covariance()  # (3K, 3K)
        observed = (3 * np.asarray(indices)[:, None] + np.arange(3)).ravel()  # (3E,)
        shift = sigma[:, observed] @ np.linalg.solve(sigma[np.ix_(observed, observed)], offsets)  # (3K,)
        result += shift.reshape(k, 3)
        result[indices] = targets
        return result

    def sample(self, n: int, seed: None | int | np.random.Generator = None, scale: float = 1.0, *,
               base: Any = None, limit: float | None = None) -> np.ndarray:
        """Draw keypoint sets from the prior.

        Parameters
        ----------
        n : number of sets.
        seed : seed or Generator; the same seed gives the same sets.
        scale : multiplies the standard deviation of every component (0 gives ``base`` n times).
        base : (K, 3) float64 keypoints to vary around (a given shape's own keypoints); ``mean_`` when None.
        limit : None, or keep every set in the prior's typical range: each coefficient within ``limit`` standard
            deviations ``sqrt(λ_m)`` of the mean (see :meth:`typical_base`). A base beyond it is first brought to its
            edge; then each ``z_m`` is drawn from its normal truncated to the range, by redrawing the components that
            leave it (an exact truncated normal; a set already inside is the unbounded draw, number for number).

        Returns
        -------
        keypoint_sets : (n, K, 3) float64, ``base + z · components_`` with ``z_m ~ N(0, scale² λ_m)``.
        """
        self._check_fitted()
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise InputError(f"n must be a non-negative integer; got {n!r}")
        if not (np.isfinite(scale) and scale >= 0):
            raise InputError(f"scale must be a non-negative number; got {scale!r}")
        base = self.mean_ if base is None else self._as_keypoints(base, "base")
        rng = as_rng(seed)
        sd = np.sqrt(self.explained_variance_)  # (M,)
        z = rng.standard_normal((int(n), len(self.components_))) * sd * scale  # (n, M)
        if limit is not None:
            base = self.typical_base(base, limit)
            z = self._truncate(z, self.coefficients(base), sd * limit, sd * scale, rng)
        return base[None] + np.tensordot(z, self.components_, axes=1)

    def typical_base(self, keypoints: Any, limit: float) -> np.ndarray:
        """(K, 3) float64: ``keypoints`` moved along the components just enough that every coefficient lies within
        ``limit`` standard deviations (unchanged when they already do; the part outside the components is kept).
        The components are orthonormal, so the shift is ``(clip(c) - c) · components_``."""
        if not (isinstance(limit, (int, float, np.floating)) and np.isfinite(limit) and limit > 0):
            raise InputError(f"limit must be a positive number; got {limit!r}")
        keypoints = self._as_keypoints(keypoints)
        bound = np.sqrt(self.explained_variance_) * float(limit)  # (M,)
        c = self.coefficients(keypoints)
        shift = np.clip(c, -bound, bound) - c
        return keypoints + np.tensordot(shift, self.components_, axes=1) if shift.any() else keypoints

    @staticmethod
    def _truncate(z: np.ndarray, centre: np.ndarray, bound: np.ndarray, sd: np.ndarray, rng: np.random.Generator,
                  tries: int = 64) -> np.ndarray:
        """``z`` (n, M) with every ``centre + z`` inside ``[-bound, bound]``: the components outside are drawn again
        from ``N(0, sd²)``, in order, until inside. The base is inside, so a component lands inside with
        probability at least one half per draw (64 misses: 2^-64); the rare rest is clipped."""
        z = z.copy()
        for _ in range(tries):
            outside = np.abs(centre + z) > bound  # (n, M)
            if not outside.any():
                return z
            z[outside] = rng.standard_normal(int(outside.sum())) * np.broadcast_to(sd, z.shape)[outside]
        return np.clip(centre + z, -bound, bound) - centre

    # --- serialisation ----------------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """A JSON-safe dict (floats kept exactly by ``json``)."""
        self._check_fitted()
        return {
            "n_components": int(self.n_components),
            "ridge": None if self.ridge is None else float(self.ridge),
            "noise_variance": float(self.noise_variance_),
            "n_samples": int(self.n_samples_),
            "mean": self.mean_.tolist(),
            "components": self.components_.tolist(),
            "explained_variance": self.explained_variance_.tolist(),
            "explained_variance_ratio": self.explained_variance_ratio_.tolist(),
            "part_variance": float(self.part_variance),
            "mirror_axis": int(self.mirror_axis),
            "mirror_permutation": None if self.mirror_permutation_ is None else self.mirror_permutation_.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> "KeypointPrior":
        """The prior written by :meth:`to_dict`; :class:`InputError` names a missing or mis-shaped entry."""
        if not isinstance(data, Mapping):
            raise InputError(f"a prior must be a dict; got {type(data).__name__}")
        try:
            ridge = data["ridge"]
            prior = cls(n_components=int(data["n_components"]), ridge=None if ridge is None else float(ridge),
                        part_variance=float(data.get("part_variance", 2.0)),
                        mirror_axis=int(data.get("mirror_axis", 0)))
            permutation = data.get("mirror_permutation")
            permutation = None if permutation is None else np.asarray(permutation)
            noise = float(data["noise_variance"])
            mean = np.asarray(data["mean"], dtype=np.float64)
            components = np.asarray(data["components"], dtype=np.float64)
            variance = np.asarray(data["explained_variance"], dtype=np.float64)
            ratio = np.asarray(data.get("explained_variance_ratio", variance / variance.sum()), dtype=np.float64)
            n_samples = int(data["n_samples"])
        except KeyError as exc:
            raise InputError(f"prior lacks {exc.args[0]!r}") from exc
        except (TypeError, ValueError) as exc:
            raise InputError(f"prior holds a non-numeric or ragged entry: {exc}") from exc
        m = prior._check_params()
        if mean.ndim != 2 or mean.shape[1] != 3:
            raise InputError(f"prior mean must have shape (K, 3); got {mean.shape}")
        k = len(mean)
        if components.shape != (m, k, 3):
            raise InputError(f"prior components must have shape (M, K, 3) = ({m}, {k}, 3); got {components.shape}")
        if variance.shape != (m,) or ratio.shape != (m,):
            raise InputError(f"prior explained_variance must have shape ({m},); got {variance.shape}")
        if not all(np.isfinite(a).all() for a in (mean, components, variance, ratio)) or not (variance > 0).all():
            raise InputError("prior arrays must be finite and its variances positive")
        if not (np.isfinite(noise) and noise > 0):
            raise InputError(f"prior noise_variance must be a positive number; got {noise}")
        if permutation is not None and (permutation.shape != (k,) or permutation.dtype.kind not in "iu"
                                        or sorted(permutation.tolist()) != list(range(k))
                                        or not (permutation[permutation] == np.arange(k)).all()):
            raise InputError(f"prior mirror_permutation must pair the {k} keypoints (a permutation that is its own "
                             f"inverse); got {permutation.tolist()}")
        prior.mirror_permutation_ = None if permutation is None else permutation.astype(np.int64)
        prior.noise_variance_ = noise
        prior.mean_, prior.components_, prior.explained_variance_ = mean, components, variance
        prior.explained_variance_ratio_, prior.n_samples_ = ratio, n_samples
        return prior

    def __repr__(self) -> str:
        fitted = f", K={len(self.mean_)}, fitted on {self.n_samples_}" if hasattr(self, "mean_") else ""
        ridge = "None" if self.ridge is None else f"{self.ridge:g}"
        return f"KeypointPrior(n_components={self.n_components}, ridge={ridge}{fitted})"


def _as_sets(x: Any, name: str) -> np.ndarray:
    sets = np.asarray(x, dtype=np.float64)
    if sets.ndim != 3 or sets.shape[2] != 3:
        raise InputError(f"{name} must have shape (S, K, 3); got {sets.shape}")
    if not np.isfinite(sets).all():
        raise InputError(f"{name} must be finite")
    return sets


def _pairs(permutation: np.ndarray) -> str:
    return ", ".join(f"{i}-{j}" for i, j in enumerate(permutation.tolist()) if i < j) or "none"


def _fix_signs(components: np.ndarray) -> np.ndarray:
    """Make each component's largest-magnitude entry positive, so a fit is reproducible across LAPACK builds."""
    signs = np.sign(components[np.arange(len(components)), np.abs(components).argmax(axis=1)])
    return components * np.where(signs == 0, 1.0, signs)[:, None]
