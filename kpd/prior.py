"""The category prior: PCA over the keypoints a model predicts on its training set (paper §3.4, REFERENCE §10).

The paper keeps 8 principal components of the 3K-dimensional keypoint vectors and uses them for two things the
authors never released:

* **synchronised editing** -- the user moves a few keypoints; the others follow as the category's shapes say (move one
  chair leg and its partner moves too), and
* **sampling** -- new keypoint sets drawn from the component distribution, used to deform a shape into variants.

Synchronisation works on *offsets*, so a shape keeps what makes it itself: with the edited keypoints ``E`` moved from
``p_E`` to ``q_E``, the component coefficients ``z`` solve the regularised least-squares problem

    minimise  ‖A z − (q_E − p_E)‖² / ridge + Σ_m z_m² / λ_m,        A = components restricted to E

(a Gaussian MAP estimate: the edit is met up to noise of variance ``ridge`` and the coefficients have the variances
``λ`` the training set showed). This is the conditional mean of probabilistic PCA (Tipping & Bishop 1999) given the
edited coordinates, and the default ``ridge`` is its maximum-likelihood noise variance, the mean variance of the
discarded directions (scikit-learn's ``noise_variance_``). All keypoints move by ``z · components``; the edited ones
are then set exactly to their targets. A zero edit moves nothing.

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

    Attributes
    ----------
    mean_ : (K, 3) float64, mean keypoint set.
    components_ : (M, K, 3) float64, orthonormal principal directions (as flat 3K vectors), by decreasing variance.
    explained_variance_ : (M,) float64, variance of the training keypoint sets along each component.
    explained_variance_ratio_ : (M,) float64, share of the total variance.
    noise_variance_ : float, mean variance of the discarded directions (probabilistic PCA's noise), floored at
        1e-9 of the total variance.
    n_samples_ : int, keypoint sets the prior was fitted on.
    """

    def __init__(self, *, n_components: int = 8, ridge: float | None = None) -> None:
        self.n_components = n_components
        self.ridge = ridge

    # --- fitting ----------------------------------------------------------------------------------------------

    def fit(self, keypoint_sets: Any) -> "KeypointPrior":
        """Fit the components to keypoint sets.

        Parameters
        ----------
        keypoint_sets : (S, K, 3) float, one keypoint set per training shape, in the model frame.

        Returns
        -------
        self
        """
        sets = np.asarray(keypoint_sets, dtype=np.float64)
        if sets.ndim != 3 or sets.shape[2] != 3:
            raise InputError(f"keypoint_sets must have shape (S, K, 3); got {sets.shape}")
        if not np.isfinite(sets).all():
            raise InputError("keypoint_sets must be finite")
        s, k, _ = sets.shape
        m = self._check_params()
        if m > min(s - 1, 3 * k):
            raise InputError(
                f"n_components must be at most min(S - 1, 3K) = {min(s - 1, 3 * k)} for S={s} keypoint sets of "
                f"K={k}; got {m}"
            )
        flat = sets.reshape(s, 3 * k)  # (S, 3K)
        mean = flat.mean(axis=0)
        _, singular, vt = np.linalg.svd(flat - mean, full_matrices=False)
        variance = singular**2 / (s - 1)  # (min(S, 3K),)
        components = _fix_signs(vt[:m])  # (M, 3K)
        if not variance[m - 1] > 0.0:
            raise InputError(f"the keypoint sets span fewer than n_components={m} directions; lower n_components")
        self.mean_ = mean.reshape(k, 3)
        self.components_ = components.reshape(m, k, 3)
        self.explained_variance_ = variance[:m].copy()
        total = variance.sum()
        self.explained_variance_ratio_ = variance[:m] / total
        rest = 3 * k - m
        self.noise_variance_ = max(float(variance[m:].sum()) / rest if rest else 0.0, 1e-9 * float(total))
        self.n_samples_ = s
        log.info("prior: %d components explain %.1f%% of the keypoint variance over %d sets",
                 m, 100 * self.explained_variance_ratio_.sum(), s)
        return self

    def _check_params(self) -> int:
        m = self.n_components
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise InputError(f"n_components must be a positive integer; got {m!r}")
        ridge = self.ridge
        if ridge is not None and not (isinstance(ridge, (int, float, np.floating)) and not isinstance(ridge, bool)
                                      and np.isfinite(ridge) and ridge > 0):
            raise InputError(f"ridge must be a positive number or None; got {ridge!r}")
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
        basis = self.components_[:, indices, :].reshape(len(self.components_), -1).T  # (3E, M)
        normal = basis.T @ basis + self.ridge_ * np.diag(1.0 / self.explained_variance_)  # (M, M)
        z = np.linalg.solve(normal, basis.T @ offsets)  # (M,)
        result += np.tensordot(z, self.components_, axes=1)
        result[indices] = targets
        return result

    def sample(self, n: int, seed: None | int | np.random.Generator = None, scale: float = 1.0, *,
               base: Any = None) -> np.ndarray:
        """Draw keypoint sets from the prior.

        Parameters
        ----------
        n : number of sets.
        seed : seed or Generator; the same seed gives the same sets.
        scale : multiplies the standard deviation of every component (0 gives ``base`` n times).
        base : (K, 3) float64 keypoints to vary around (a given shape's own keypoints); ``mean_`` when None.

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
        z = rng.standard_normal((int(n), len(self.components_))) * np.sqrt(self.explained_variance_) * scale  # (n, M)
        return base[None] + np.tensordot(z, self.components_, axes=1)

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
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> "KeypointPrior":
        """The prior written by :meth:`to_dict`; :class:`InputError` names a missing or mis-shaped entry."""
        if not isinstance(data, Mapping):
            raise InputError(f"a prior must be a dict; got {type(data).__name__}")
        try:
            ridge = data["ridge"]
            prior = cls(n_components=int(data["n_components"]), ridge=None if ridge is None else float(ridge))
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
        prior.noise_variance_ = noise
        prior.mean_, prior.components_, prior.explained_variance_ = mean, components, variance
        prior.explained_variance_ratio_, prior.n_samples_ = ratio, n_samples
        return prior

    def __repr__(self) -> str:
        fitted = f", K={len(self.mean_)}, fitted on {self.n_samples_}" if hasattr(self, "mean_") else ""
        ridge = "None" if self.ridge is None else f"{self.ridge:g}"
        return f"KeypointPrior(n_components={self.n_components}, ridge={ridge}{fitted})"


def _fix_signs(components: np.ndarray) -> np.ndarray:
    """Make each component's largest-magnitude entry positive, so a fit is reproducible across LAPACK builds."""
    signs = np.sign(components[np.arange(len(components)), np.abs(components).argmax(axis=1)])
    return components * np.where(signs == 0, 1.0, signs)[:, None]
