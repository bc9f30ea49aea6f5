"""Protocols on annotated data: PCK by regression, part correspondence, the dual alignment score, SC3K coverage and
inclusivity.

Every function works in whatever frame it is given; :mod:`kpd.annotations` puts keypoints, annotations and points into
the evaluation frame (the [-1, 1] box of docs/method.md §7/§8) before calling them, so thresholds such as 0.05 are
in those units.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from kpd.errors import InputError
from kpd.geometry import as_points
from kpd.metrics.labelfree import _keypoint_sets
__all__ = [
    "KeypointRegressor", "fit_keypoint_regressor", "pck", "RegressionPCK", "regression_pck", "part_association",
    "PartCorrespondence", "part_correspondence", "DualAlignment", "dual_alignment_score", "keypoint_coverage",
    "keypoint_inclusivity",
]

class KeypointRegressor(NamedTuple):
    """Affine map from one shape's K flattened keypoints to its J annotated keypoints.

    weights : (3K, 3J) float64; bias : (3J,) float64. ``predict(keypoints (S, K, 3)) -> (S, J, 3)``.
    """

    weights: np.ndarray
    bias: np.ndarray

    def predict(self, keypoints: Any) -> np.ndarray:
        """(S, K, 3) unsupervised keypoints -> (S, J, 3) regressed annotated keypoints."""
        kp = _keypoint_sets(keypoints, "keypoints")
        if kp.shape[1] * 3 != self.weights.shape[0]:
            raise InputError(f"keypoints must have {self.weights.shape[0] // 3} keypoints per shape; got "
                             f"{kp.shape[1]}")
        out = kp.reshape(len(kp), -1) @ self.weights + self.bias  # (S, 3J)
        return out.reshape(len(kp), -1, 3)


def fit_keypoint_regressor(keypoints: Any, annotated: Any, *, ridge: float = 1e-3) -> KeypointRegressor:
    """Fit the linear regressor of Thewlis et al. (ICCV 2017) from unsupervised to annotated keypoints.

    Each shape's keypoints are flattened to a 3K vector (x1, y1, z1, x2, ...) and mapped to the flattened 3J annotated
    keypoints by ``y = x @ weights + bias``, fitted by ridge-regularised least squares on the training shapes. The
    bias is not penalised (the data are centred), and the penalty is relative: ``lambda = ridge * trace(Xc^T Xc) / 3K``,
    so the fit, and the PCK built on it, do not change when one rigid motion is applied to every keypoint, nor when the
    keypoints are listed in another order. ``ridge = 0`` gives the minimum-norm least-squares solution.

    Parameters
    ----------
    keypoints : (S, K, 3) float64, unsupervised keypoints of S training shapes.
    annotated : (S, J, 3) float64, their annotated keypoints (same shapes, same order).
    ridge : relative ridge strength, >= 0.

    Returns
    -------
    KeypointRegressor
    """
    kp = _keypoint_sets(keypoints, "keypoints")
    ann = _keypoint_sets(annotated, "annotated")
    if len(kp) != len(ann):
        raise InputError(f"keypoints and annotated must cover the same shapes; got {len(kp)} and {len(ann)}")
    if not np.isfinite(ridge) or ridge < 0:
        raise InputError(f"ridge must be a finite number >= 0; got {ridge}")
    x = kp.reshape(len(kp), -1)  # (S, 3K)
    y = ann.reshape(len(ann), -1)  # (S, 3J)
    x_mean, y_mean = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - x_mean, y - y_mean
    gram = xc.T @ xc  # (3K, 3K)
    strength = ridge * np.trace(gram) / gram.shape[0]
    if strength > 0:
        weights = np.linalg.solve(gram + strength * np.eye(gram.shape[0]), xc.T @ yc)
    else:
        weights = np.linalg.lstsq(xc, yc, rcond=None)[0]
    return KeypointRegressor(weights, y_mean - x_mean @ weights)


def pck(predicted: Any, annotated: Any, threshold: float = 0.05) -> float:
    """Percentage of correct keypoints: the fraction of predicted keypoints within ``threshold`` of their annotation.

    Parameters
    ----------
    predicted, annotated : (S, J, 3) float64, corresponding keypoints.
    threshold : Euclidean distance (inclusive), in the units of the frame (0.05 of the [-1, 1] box in the paper).

    Returns
    -------
    pck : in [0, 1], over all S * J keypoints.
    """
    pred = _keypoint_sets(predicted, "predicted")
    ann = _keypoint_sets(annotated, "annotated")
    if pred.shape != ann.shape:
        raise InputError(f"predicted and annotated must have the same shape; got {pred.shape} and {ann.shape}")
    return float(np.mean(np.linalg.norm(pred - ann, axis=2) <= threshold))


class RegressionPCK(NamedTuple):
    """Result of :func:`regression_pck`.

    pck : float, over all test keypoints; per_keypoint : (J,) float64, per annotated keypoint;
    errors : (S, J) float64, distances of the regressed keypoints on the S test shapes; regressor : the fitted map.
    """

    pck: float
    per_keypoint: np.ndarray
    errors: np.ndarray
    regressor: KeypointRegressor


def regression_pck(train_keypoints: Any, train_annotated: Any, test_keypoints: Any, test_annotated: Any, *,
                   threshold: float = 0.05, ridge: float = 1e-3) -> RegressionPCK:
    """PCK of annotated keypoints regressed from unsupervised ones (KeypointDeformer, Jakab et al. CVPR 2021, Fig. 4).

    Protocol of Thewlis et al., "Unsupervised learning of object landmarks by factorized spatial embeddings" (ICCV
    2017), as used by the paper on KeypointNet: a linear regressor (:func:`fit_keypoint_regressor`) is fitted on the
    training shapes from the unsupervised keypoints to the annotated ones; on the test shapes a regressed keypoint is
    correct when it lies within ``threshold`` (0.05 of the [-1, 1] box) of its annotation; PCK is the fraction of
    correct keypoints over all test shapes and annotated keypoints.

    Parameters
    ----------
    train_keypoints : (S, K, 3), train_annotated : (S, J, 3)
    test_keypoints : (S', K, 3), test_annotated : (S', J, 3)
    threshold, ridge : as in :func:`pck` and :func:`fit_keypoint_regressor`.
    """
    regressor = fit_keypoint_regressor(train_keypoints, train_annotated, ridge=ridge)
    predicted = regressor.predict(test_keypoints)
    ann = _keypoint_sets(test_annotated, "test_annotated")
    if predicted.shape != ann.shape:
        raise InputError(f"test_annotated must have shape {predicted.shape} (as many shapes as test_keypoints and "
                         f"as many keypoints as train_annotated); got {ann.shape}")
    errors = np.linalg.norm(predicted - ann, axis=2)  # (S', J)
    correct = errors <= threshold
    return RegressionPCK(float(correct.mean()), correct.mean(axis=0), errors, regressor)


def _labelled_points(points: Any, labels: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    pts = as_points(points, f"{where} points")
    lab = np.asarray(labels)
    if lab.shape != (len(pts),) or lab.dtype.kind not in "iu":
        raise InputError(f"{where} labels must be ({len(pts)},) integers; got {lab.dtype} array of shape {lab.shape}")
    return pts, lab.astype(np.int64)


def part_association(keypoints: Any, points: Any, labels: Any, parts: Any, radius: float = 0.05) -> np.ndarray:
    """Which parts each keypoint is associated with: those with a labelled point within ``radius`` (inclusive).

    Parameters
    ----------
    keypoints : (K, 3) float64
    points : (N, 3) float64, part-labelled points of the shape.
    labels : (N,) int, the part label of each point.
    parts : (P,) int, the part labels to report (a part absent from this shape is never associated).
    radius : association distance (0.05 of the [-1, 1] box in the paper).

    Returns
    -------
    associated : (K, P) bool
    """
    kp = as_points(keypoints, "keypoints")
    pts, lab = _labelled_points(points, labels, "part")
    parts = np.asarray(parts, dtype=np.int64).reshape(-1)
    out = np.zeros((len(kp), len(parts)), dtype=bool)
    for j, part in enumerate(parts):
        member = pts[lab == part]
        if len(member):
            d2 = np.min(np.sum((kp[:, None, :] - member[None, :, :]) ** 2, axis=2), axis=1)  # (K,)
            out[:, j] = d2 <= radius * radius
    return out


class PartCorrespondence(NamedTuple):
    """Result of :func:`part_correspondence`.

    - score : float, the paper's metric: mean over keypoints of the frequency with the keypoint's best part.
    - part_score : float, the reverse (part-wise) reduction: mean over parts of the frequency with the part's best
      keypoint.
    - frequency : (K, P) float64, fraction of shapes in which keypoint k is associated with part p.
    - parts : (P,) int64, the part labels of the columns.
    - best_part : (K,) int64, each keypoint's most frequent part label.
    - associated : (K,) float64, fraction of shapes in which keypoint k is associated with any part.
    """

    score: float
    part_score: float
    frequency: np.ndarray
    parts: np.ndarray
    best_part: np.ndarray
    associated: np.ndarray


def _per_shape_keypoints(function: str, keypoints: Sequence[Any], **per_shape: Sequence[Any]) -> list[np.ndarray]:
    """Checked (K, 3) keypoint arrays, one per shape, with the same K, and as many shapes as each ``per_shape``."""
    keypoint_list = [as_points(k, "keypoints") for k in keypoints]
    if not keypoint_list:
        raise InputError(f"{function} needs at least one shape; got none")
    if any(len(v) != len(keypoint_list) for v in per_shape.values()):
        names = " and ".join(per_shape)
        sizes = " and ".join(str(len(v)) for v in per_shape.values())
        raise InputError(f"keypoints, {names} must cover the same shapes; got {len(keypoint_list)}, {sizes}")
    counts = {len(k) for k in keypoint_list}
    if len(counts) != 1:
        raise InputError(f"every shape must have the same number of keypoints; got {sorted(counts)}")
    return keypoint_list


def part_correspondence(keypoints: Any, points: Any, labels: Any, *, radius: float = 0.05,
                        parts: Any = None) -> PartCorrespondence:
    """Semantic part correspondence of keypoints (KeypointDeformer, Jakab et al. CVPR 2021, Table 1, supp. Fig. 12).

    The paper modifies the protocol of Fernandez-Labrador et al. (ECCV 2020) and Chen et al. (CVPR 2020): keypoint k
    of shape s is associated with every part that has a labelled point within ``radius`` of it (0.05 in the [-1, 1]
    box), so it may be associated with several parts or none. The paper does not define "correlation" further; its
    supplementary Fig. 12 tabulates "the frequency of each keypoint being associated with a given object part", which
    is what this function computes:

        frequency[k, p] = (1 / S) * #{shapes s : keypoint k of s is within radius of part p of s}

    over all S shapes (a shape lacking part p counts as not associated). The paper's score is the keypoint-wise
    reduction ``mean_k max_p frequency[k, p]``; ``part_score`` is the reverse, part-wise reduction
    ``mean_p max_k frequency[k, p]`` over the parts that occur, reported by some later work. Both are 1 when every
    keypoint always lies on the same part, do not depend on the label values (relabelling parts permutes columns),
    and do not change under a rigid motion applied to keypoints and points together.

    Parameters
    ----------
    keypoints : (S, K, 3) or a sequence of S (K, 3) arrays.
    points : sequence of S (N_s, 3) arrays, part-labelled points.
    labels : sequence of S (N_s,) int arrays.
    radius : association distance.
    parts : (P,) int, the part labels to consider; default: every label that occurs.
    """
    keypoint_list = _per_shape_keypoints("part_correspondence", keypoints, points=points, labels=labels)
    if not np.isfinite(radius) or radius < 0:
        raise InputError(f"radius must be a finite number >= 0; got {radius}")
    pairs = [_labelled_points(p, lab, f"shape {s}") for s, (p, lab) in enumerate(zip(points, labels))]
    if parts is None:
        parts = np.unique(np.concatenate([lab for _, lab in pairs]))
    parts = np.asarray(parts, dtype=np.int64).reshape(-1)
    if len(parts) == 0:
        raise InputError("part_correspondence needs at least one part label; got none")
    hits = np.zeros((len(keypoint_list[0]), len(parts)))
    associated = np.zeros(len(hits))
    present = np.zeros(len(parts), dtype=bool)
    for kp, (pts, lab) in zip(keypoint_list, pairs):
        a = part_association(kp, pts, lab, parts, radius)  # (K, P)
        hits += a
        associated += a.any(axis=1)
        present |= np.isin(parts, lab)
    frequency = hits / len(keypoint_list)
    return PartCorrespondence(
        score=float(frequency.max(axis=1).mean()),
        part_score=float(frequency[:, present].max(axis=0).mean()),
        frequency=frequency,
        parts=parts,
        best_part=parts[np.argmax(frequency, axis=1)],
        associated=associated / len(keypoint_list),
    )


class DualAlignment(NamedTuple):
    """Result of :func:`dual_alignment_score`: ``score`` = (``forward`` + ``backward``) / 2, each in [0, 1]."""

    score: float
    forward: float
    backward: float


def dual_alignment_score(keypoints: Any, annotated: Any, semantic_ids: Any) -> DualAlignment:
    """Dual Alignment Score (DAS) of Skeleton Merger (Shi et al., CVPR 2021).

    As implemented in the authors' ``eval_keypointnet.py`` (github.com/eliphatfs/SkeletonMerger): with
    nearest neighbours by Euclidean distance (first index on ties),

    - forward: each predicted keypoint k of shape s takes the semantic id of the nearest annotated keypoint of s,
      ``label[s, k]``; forward = mean over all ordered pairs of shapes (a, b), a = b included, of the fraction of k
      with ``label[a, k] == label[b, k]``;
    - backward: each annotated keypoint takes the index of the nearest predicted keypoint; for each semantic id c,
      the fraction of ordered pairs of its occurrences (self-pairs included) that took the same index; backward =
      mean over the semantic ids that occur;
    - DAS = (forward + backward) / 2 (the released script prints the two; later work reports their mean as DAS, e.g.
      the KeypointDETR authors in github.com/bibi547/KeypointDETR issue 2).

    The score is 1 for keypoints equal to the annotations (when every shape has the same semantic ids), and does not
    change under a rigid motion of everything or a fixed reordering of the predicted keypoints. Fractions, not
    percentages (the papers print x100).

    Parameters
    ----------
    keypoints : (S, K, 3) or a sequence of S (K, 3) arrays, predicted keypoints.
    annotated : sequence of S (J_s, 3) arrays, every annotated keypoint of each shape.
    semantic_ids : sequence of S (J_s,) int arrays.
    """
    keypoint_list = _per_shape_keypoints("dual_alignment_score", keypoints, annotated=annotated,
                                         semantic_ids=semantic_ids)
    K = len(keypoint_list[0])
    forward_labels = np.empty((len(keypoint_list), K), dtype=np.int64)
    backward: dict[int, list[np.ndarray]] = {}
    for s, (kp, ann, ids) in enumerate(zip(keypoint_list, annotated, semantic_ids)):
        ann, ids = _labelled_points(ann, ids, f"shape {s} annotated")
        d2 = np.sum((kp[:, None, :] - ann[None, :, :]) ** 2, axis=2)  # (K, J)
        forward_labels[s] = ids[np.argmin(d2, axis=1)]
        nearest = np.argmin(d2, axis=0)  # (J,)
        for c in np.unique(ids):
            backward.setdefault(int(c), []).append(nearest[ids == c])
    S = len(keypoint_list)
    agree = 0.0
    for k in range(K):
        _, n = np.unique(forward_labels[:, k], return_counts=True)
        agree += float(np.sum(n.astype(np.float64) ** 2))
    forward = agree / (S * S * K)
    scores = []
    for chosen in backward.values():
        chosen = np.concatenate(chosen)
        _, n = np.unique(chosen, return_counts=True)
        scores.append(float(np.sum(n.astype(np.float64) ** 2)) / len(chosen) ** 2)
    backward_score = float(np.mean(scores))
    return DualAlignment((forward + backward_score) / 2, forward, backward_score)


def keypoint_coverage(keypoints: Any, points: Any) -> float:
    """Coverage of SC3K (Zohaib and Del Bue, ICCV 2023; ``coverage`` in github.com/IIT-PAVIS/SC3K ``metrics.py``).

    With ``d(X)`` the length of the diagonal of the axis-aligned bounding box of X,
    coverage = ``max(0, 1 - |d(points) - d(keypoints)| / d(points))``: 1 when the keypoints span the shape's bounding
    box diagonal. SC3K averages it over test shapes and prints x100. Invariant to translation and scale of both.

    Parameters
    ----------
    keypoints : (K, 3) float64; points : (N, 3) float64, the shape's point cloud.
    """
    kp = as_points(keypoints, "keypoints")
    pts = as_points(points, "points")
    d_points = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    if d_points == 0:
        raise InputError("points must not all coincide (zero bounding box)")
    d_keypoints = float(np.linalg.norm(kp.max(axis=0) - kp.min(axis=0)))
    return max(0.0, 1.0 - abs(d_points - d_keypoints) / d_points)


def keypoint_inclusivity(keypoints: Any, points: Any, threshold: float = 0.05) -> float:
    """Inclusivity of SC3K (Zohaib and Del Bue, ICCV 2023; ``inclusivity`` in github.com/IIT-PAVIS/SC3K
    ``metrics.py``): the fraction of keypoints whose nearest point of the shape's point cloud is closer than
    ``threshold`` (strictly). SC3K's test script uses 0.05 on point clouds centred on their centroid and scaled to
    a maximum radius of 1, averages over test shapes and prints x100.

    Parameters
    ----------
    keypoints : (K, 3) float64; points : (N, 3) float64; threshold : distance in the points' units.
    """
    kp = as_points(keypoints, "keypoints")
    pts = as_points(points, "points")
    nearest, _ = cKDTree(pts).query(kp)
    return float(np.mean(nearest < threshold))
