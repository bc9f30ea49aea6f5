"""Evaluation metrics (numpy, torch-free).

Label-free keypoint quality: stability over independent point samples, distance to the surface, mirror consistency;
and the alignment chamfer of the paper's Fig. 7 (REFERENCE §6, on [-1, 1]-normalised shapes).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from kpd.errors import InputError
from kpd.geometry import as_points, chamfer
from kpd.triangles import areas as triangle_areas
from kpd.triangles import cross as triangle_cross

__all__ = [
    "keypoint_stability",
    "surface_distance",
    "point_triangle_distance",
    "fit_mirror_permutation",
    "mirror_consistency",
    "alignment_chamfer",
]


def _keypoint_sets(x: Any, name: str) -> np.ndarray:
    array = np.asarray(x, dtype=np.float64)
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1 or array.shape[1] < 1:
        raise InputError(f"{name} must have shape (S, K, 3) with S, K >= 1; got {array.shape}")
    if not np.isfinite(array).all():
        raise InputError(f"{name} must be finite; got NaN or inf")
    return array


def keypoint_stability(keypoint_sets: Any) -> float:
    """Spread of keypoints predicted from S independent point samples of one shape.

    Parameters
    ----------
    keypoint_sets : (S, K, 3) float64, keypoints of the same shape from S samples.

    Returns
    -------
    spread : mean over keypoints of the mean distance to that keypoint's centroid over the samples.
    """
    sets = _keypoint_sets(keypoint_sets, "keypoint_sets")
    centroid = sets.mean(axis=0)  # (K, 3)
    return float(np.linalg.norm(sets - centroid, axis=2).mean())


def point_triangle_distance(points: Any, vertices: Any, triangles: Any, chunk: int = 4096) -> np.ndarray:
    """Unsigned distance from each point to the nearest triangle (exact closest point on each triangle).

    Parameters
    ----------
    points : (P, 3) float64
    vertices : (V, 3) float64
    triangles : (T, 3) int
    chunk : triangles per block.

    Returns
    -------
    distance : (P,) float64
    """
    p = as_points(points, "points")
    v = as_points(vertices, "vertices")
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
        raise InputError(f"triangles must have shape (T, 3) with T >= 1; got {tri.shape}")
    if tri.min() < 0 or tri.max() >= len(v):
        raise InputError(f"triangle indices must lie in [0, {len(v)}); got [{tri.min()}, {tri.max()}]")
    best = np.full(len(p), np.inf)
    for s in range(0, len(tri), chunk):
        t = tri[s:s + chunk]
        a, b, c = v[t[:, 0]][None], v[t[:, 1]][None], v[t[:, 2]][None]  # (1, T, 3)
        q = _closest_on_triangles(p[:, None, :], a, b, c)  # (P, T, 3)
        d = np.sqrt(np.sum((q - p[:, None, :]) ** 2, axis=2)).min(axis=1)
        np.minimum(best, d, out=best)
    return best


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to p (Ericson, Real-Time Collision Detection §5.1.5), broadcast."""
    p, a, b, c = np.broadcast_arrays(p, a, b, c)
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.sum(ab * ap, -1), np.sum(ac * ap, -1)
    bp = p - b
    d3, d4 = np.sum(ab * bp, -1), np.sum(ac * bp, -1)
    cp = p - c
    d5, d6 = np.sum(ab * cp, -1), np.sum(ac * cp, -1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        result = a + ab * v[..., None] + ac * w[..., None]  # inside the face
        # edge regions
        t_ab = np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0)
        t_ac = np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0)
        t_bc = np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0)
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    result = np.where(on_bc[..., None], b + (c - b) * t_bc[..., None], result)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    result = np.where(on_ac[..., None], a + ac * t_ac[..., None], result)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    result = np.where(on_ab[..., None], a + ab * t_ab[..., None], result)
    # vertex regions (checked last so they win, as in the sequential algorithm)
    result = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, result)
    result = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, result)
    result = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, result)
    return result


def surface_distance(keypoints: Any, vertices: Any, triangles: Any) -> np.ndarray:
    """Distance from each keypoint to the mesh surface: keypoints (K, 3) -> (K,) float64 (unsigned)."""
    return point_triangle_distance(as_points(keypoints, "keypoints"), vertices, triangles)


def fit_mirror_permutation(keypoints: Any, mirrored_keypoints: Any) -> np.ndarray:
    """The fixed keypoint permutation that best matches keypoints to those of the mirrored shapes.

    Parameters
    ----------
    keypoints : (S, K, 3), keypoints of S shapes.
    mirrored_keypoints : (S, K, 3), ``mirrored_keypoints[s]`` = keypoints predicted on the mirror image of shape s,
        mirrored back into the shape's frame.

    Returns
    -------
    permutation : (K,) int64; keypoint k of a shape corresponds to keypoint ``permutation[k]`` of its mirror image.
        Found by the Hungarian method on the distances summed over the shapes.
    """
    kp = _keypoint_sets(keypoints, "keypoints")
    mk = _keypoint_sets(mirrored_keypoints, "mirrored_keypoints")
    if kp.shape != mk.shape:
        raise InputError(f"keypoints and mirrored_keypoints must have the same shape; got {kp.shape} and {mk.shape}")
    cost = np.linalg.norm(kp[:, :, None, :] - mk[:, None, :, :], axis=3).sum(axis=0)  # (K, K)
    rows, cols = linear_sum_assignment(cost)
    permutation = np.empty(kp.shape[1], dtype=np.int64)
    permutation[rows] = cols
    return permutation


def mirror_consistency(keypoints: Any, mirrored_keypoints: Any, permutation: Any) -> float:
    """Mean distance between keypoints and the permuted keypoints of the mirrored shapes (lower is better).

    Parameters
    ----------
    keypoints, mirrored_keypoints : (S, K, 3), as for :func:`fit_mirror_permutation`.
    permutation : (K,) int, from :func:`fit_mirror_permutation` (fitted on other shapes, e.g. the train split).
    """
    kp = _keypoint_sets(keypoints, "keypoints")
    mk = _keypoint_sets(mirrored_keypoints, "mirrored_keypoints")
    perm = np.asarray(permutation, dtype=np.int64)
    if kp.shape != mk.shape:
        raise InputError(f"keypoints and mirrored_keypoints must have the same shape; got {kp.shape} and {mk.shape}")
    if perm.shape != (kp.shape[1],) or sorted(perm.tolist()) != list(range(kp.shape[1])):
        raise InputError(f"permutation must be a permutation of range({kp.shape[1]}); got {perm.tolist()}")
    return float(np.linalg.norm(kp - mk[:, perm], axis=2).mean())


def alignment_chamfer(deformed: Any, target: Any) -> float:
    """Chamfer distance between a deformed source and its target (REFERENCE §6; = kpd.geometry.chamfer)."""
    return chamfer(deformed, target)


# --- Protocols on annotated data (helper "eval"): PCK by regression, part correspondence, DAS, coverage -------------
#
# Every function below works in whatever frame it is given; kpd.annotations puts keypoints, annotations and points
# into the evaluation frame (the [-1, 1] box of REFERENCE §7/§8) before calling them, so thresholds such as 0.05 are
# in those units.

from typing import NamedTuple  # noqa: E402  (imports of this section, kept beside it)

from scipy.spatial import cKDTree  # noqa: E402

__all__ += [
    "KeypointRegressor",
    "fit_keypoint_regressor",
    "pck",
    "RegressionPCK",
    "regression_pck",
    "part_association",
    "PartCorrespondence",
    "part_correspondence",
    "DualAlignment",
    "dual_alignment_score",
    "keypoint_coverage",
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


# --- Edit quality: locality, detail preservation, semantic edits, the prior's response, sample plausibility --------
#
# Every measure compares a mesh before and after an edit (same triangles), in whatever frame it is given;
# benchmarks/bench_edits.py runs them in the model's [-1, 1] frame, where moves are fractions of the box.

__all__ += [
    "vertex_areas",
    "far_side_leakage",
    "folded_share",
    "folded_area_share",
    "EditDistortion",
    "edit_distortion",
    "keypoint_roles",
    "semantic_edits",
    "PriorResponse",
    "prior_response",
    "triangle_distance",
    "new_self_intersections",
    "keypoint_set_distance",
]


def _mesh_pair(rest: Any, deformed: Any, triangles: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v0 = as_points(rest, "rest vertices")
    v1 = as_points(deformed, "deformed vertices")
    if v0.shape != v1.shape:
        raise InputError(f"rest and deformed vertices must have the same shape; got {v0.shape} and {v1.shape}")
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
        raise InputError(f"triangles must have shape (T, 3) with T >= 1; got {tri.shape}")
    if tri.min() < 0 or tri.max() >= len(v0):
        raise InputError(f"triangle indices must lie in [0, {len(v0)}); got [{tri.min()}, {tri.max()}]")
    return v0, v1, tri


def vertex_areas(vertices: Any, triangles: Any) -> np.ndarray:
    """(V,) float64: the surface area each vertex stands for (a third of each triangle it is a corner of).

    Weights for measures over a mesh's vertices, so that densely tessellated details do not count more than large
    flat faces (CAD meshes are tessellated very unevenly).
    """
    v = as_points(vertices, "vertices")
    tri = np.asarray(triangles, dtype=np.int64)
    area = triangle_areas(v, tri)  # (T,)
    out = np.zeros(len(v))
    for i in range(3):
        np.add.at(out, tri[:, i], area / 3.0)
    return out


def far_side_leakage(rest: Any, deformed: Any, keypoint: Any, move: float, weights: Any = None) -> float:
    """Locality of a single-keypoint edit: how much the half of the shape farthest from the moved keypoint moved.

    Parameters
    ----------
    rest, deformed : (V, 3) float64, mesh vertices before and after moving one keypoint.
    keypoint : (3,) float64, the moved keypoint's rest position.
    move : length of the keypoint's move (> 0).
    weights : (V,) float64 or None, vertex weights (e.g. :func:`vertex_areas`); None weighs vertices alike.

    Returns
    -------
    leakage : the (weighted) mean displacement of the vertices farther from the keypoint than the (weighted) median
        distance, divided by ``move``: 0 for a perfectly local edit, 1 when the far half moved as far as the keypoint.
    """
    v0 = as_points(rest, "rest vertices")
    v1 = as_points(deformed, "deformed vertices")
    if v0.shape != v1.shape:
        raise InputError(f"rest and deformed vertices must have the same shape; got {v0.shape} and {v1.shape}")
    p = np.asarray(keypoint, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise InputError(f"keypoint must be 3 finite numbers; got {np.shape(keypoint)}")
    if not (np.isfinite(move) and move > 0):
        raise InputError(f"move must be a positive length; got {move!r}")
    w = np.ones(len(v0)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(v0),) or not np.isfinite(w).all() or (w < 0).any() or not w.sum() > 0:
        raise InputError(f"weights must be {len(v0)} non-negative finite numbers, not all zero")
    distance = np.linalg.norm(v0 - p, axis=1)  # (V,)
    order = np.argsort(distance)
    cumulative = np.cumsum(w[order])
    far = order[cumulative > 0.5 * cumulative[-1]]  # the farther half of the weight
    displacement = np.linalg.norm(v1[far] - v0[far], axis=1)
    return float(np.average(displacement, weights=w[far]) / move) if w[far].sum() > 0 else 0.0


def folded_share(rest: Any, deformed: Any, triangles: Any) -> float:
    """Share of the (non-degenerate) triangles whose normal turned by more than 90 degrees in an edit (folded)."""
    v0, v1, tri = _mesh_pair(rest, deformed, triangles)
    return _fold_share(triangle_cross(v0, tri), triangle_cross(v1, tri))


def folded_area_share(rest: Any, deformed: Any, triangles: Any) -> float:
    """Share of the surface *area* (at rest) on triangles whose normal turned by more than 90 degrees in an edit.

    :func:`folded_share` counts triangles; on CAD meshes one long sliver triangle (a strip along a table leg or a
    seat edge, a thousandth of the area) counts as much as a large face, and slivers are what fold first when a
    long flat face bends slightly. This weighs each by its area, so it reads as the share of the visible surface.
    """
    v0, v1, tri = _mesh_pair(rest, deformed, triangles)
    n0, n1 = triangle_cross(v0, tri), triangle_cross(v1, tri)
    size = np.linalg.norm(n0, axis=1)
    if not size.sum() > 0:
        return 0.0
    return float(size[_turned(n0, n1)].sum() / size.sum())


def _turned(n0: np.ndarray, n1: np.ndarray) -> np.ndarray:
    """(T,) bool: the triangles whose normal turned by more than 90 degrees (normals before and after, (T, 3))."""
    return np.einsum("ij,ij->i", n0, n1) < 0.0


def _fold_share(n0: np.ndarray, n1: np.ndarray) -> float:
    """Share of the non-degenerate triangles (rest normals n0, deformed n1) that turned over."""
    size = np.linalg.norm(n0, axis=1)
    valid = size > 1e-12 * max(float(size.max()), 1e-300)
    if not valid.any():
        return 0.0
    return float(np.mean(_turned(n0[valid], n1[valid])))


class EditDistortion(NamedTuple):
    """Detail preservation of an edit (:func:`edit_distortion`).

    folded : share of triangles whose normal turned by more than 90 degrees.
    edge : mean relative change of the edge lengths, mean ``|l' / l - 1|`` over the mesh's edges.
    dihedral : mean change of the dihedral angles, in degrees, over the edges shared by exactly two triangles.
    """

    folded: float
    edge: float
    dihedral: float


def edit_distortion(rest: Any, deformed: Any, triangles: Any) -> EditDistortion:
    """How much an edit distorts a mesh locally (see :class:`EditDistortion`); 0, 0, 0 for a rigid motion.

    Parameters
    ----------
    rest, deformed : (V, 3) float64, vertices before and after the edit.
    triangles : (T, 3) int, the mesh's triangles (degenerate ones and zero-length edges are ignored).
    """
    v0, v1, tri = _mesh_pair(rest, deformed, triangles)
    n0, n1 = triangle_cross(v0, tri), triangle_cross(v1, tri)
    size0, size1 = np.linalg.norm(n0, axis=1), np.linalg.norm(n1, axis=1)
    valid = size0 > 1e-12 * max(float(size0.max()), 1e-300)
    folded = _fold_share(n0, n1)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)  # (3T, 2)
    unique, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    l0 = np.linalg.norm(v0[unique[:, 0]] - v0[unique[:, 1]], axis=1)
    l1 = np.linalg.norm(v1[unique[:, 0]] - v1[unique[:, 1]], axis=1)
    long = l0 > 1e-9 * max(float(l0.max()), 1e-300)
    edge = float(np.mean(np.abs(l1[long] / l0[long] - 1.0))) if long.any() else 0.0
    # dihedral angles across the edges of exactly two valid triangles (angle between the two normals)
    inverse = inverse.ravel()
    face = np.tile(np.arange(len(tri)), 3)  # (3T,) the triangle of each edge copy
    keep = valid[face] & (counts[inverse] == 2)
    order = np.argsort(inverse[keep], kind="stable")
    pairs = face[keep][order].reshape(-1, 2) if keep.sum() % 2 == 0 else np.empty((0, 2), dtype=np.int64)
    if len(pairs):
        same = inverse[keep][order].reshape(-1, 2)
        pairs = pairs[same[:, 0] == same[:, 1]]
    dihedral = 0.0
    if len(pairs):
        u0 = n0 / np.maximum(size0, 1e-300)[:, None]
        u1 = n1 / np.maximum(size1, 1e-300)[:, None]

        def angle(u: np.ndarray) -> np.ndarray:
            a, b = u[pairs[:, 0]], u[pairs[:, 1]]
            return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b)))

        dihedral = float(np.mean(np.abs(angle(u1) - angle(u0))))
    return EditDistortion(folded, edge, dihedral)


def keypoint_roles(mean_keypoints: Any, *, up: int = 2, side: int = 0, gap: float = 0.2) -> dict[str, np.ndarray]:
    """Roles of a model's keypoints, found from their mean positions on the training shapes (no hand-picked indices).

    The keypoints are grouped by height (single linkage along ``up``: a new group starts where consecutive heights
    differ by more than ``gap``, in [-1, 1] box units).

    Parameters
    ----------
    mean_keypoints : (K, 3) float64, the mean keypoint set over the training shapes (``KeypointPrior.mean_``).
    up, side : axis indices of the up and the left/right (mirror) directions.
    gap : height difference that separates two groups.

    Returns
    -------
    roles : ``{"top": the highest group (a chair's top of the back, a table's top), "bottom": the lowest (feet),
        "above_bottom": the group just above the lowest (a chair's seat), "sides": (K,) float64 sign of each
        keypoint's side coordinate, 0 for those within 0.1 of the mirror plane}``; index arrays are int64, sorted.
    """
    mean = as_points(mean_keypoints, "mean_keypoints")
    if len(mean) < 2:
        raise InputError(f"roles need at least 2 keypoints; got {len(mean)}")
    height = mean[:, up]
    order = np.argsort(height)
    breaks = np.flatnonzero(np.diff(height[order]) > gap) + 1
    groups = [np.sort(g) for g in np.split(order, breaks)]
    side_sign = np.where(np.abs(mean[:, side]) > 0.1, np.sign(mean[:, side]), 0.0)
    return {
        "top": groups[-1].astype(np.int64),
        "bottom": groups[0].astype(np.int64),
        "above_bottom": (groups[1] if len(groups) > 2 else groups[-1]).astype(np.int64),
        "sides": side_sign,
    }


# the edits of issue #14, by category: (name, role, direction) with direction "up", "down" or "out" (away from the
# mirror plane along the side axis)
_SEMANTIC = {
    "chair": [("taller_back", "top", "up"), ("longer_legs", "bottom", "down"), ("wider_seat", "above_bottom", "out")],
    "table": [("taller", "top", "up"), ("wider_top", "top", "out")],
}


def semantic_edits(roles: dict, category: str, step: float, *, up: int = 2, side: int = 0) -> dict[str, dict]:
    """Part edits built from :func:`keypoint_roles`: ``{name: {keypoint index: (3,) offset}}``.

    Chairs: ``taller_back`` (the top group up), ``longer_legs`` (the bottom group down), ``wider_seat`` (the group
    above the feet outward along the side axis); tables: ``taller`` (the top up), ``wider_top`` (the top outward).
    ``step`` is the length of each keypoint's offset. Keypoints on the mirror plane do not move outward.
    """
    if category not in _SEMANTIC:
        raise InputError(f"semantic edits are defined for {sorted(_SEMANTIC)}; got {category!r}")
    out = {}
    for name, role, direction in _SEMANTIC[category]:
        edit = {}
        for index in roles[role].tolist():
            offset = np.zeros(3)
            if direction == "out":
                offset[side] = step * roles["sides"][index]
            else:
                offset[up] = step if direction == "up" else -step
            if offset.any():
                edit[int(index)] = offset
        out[name] = edit
    return out


class PriorResponse(NamedTuple):
    """How a synchronised edit of one keypoint moved the others (:func:`prior_response`).

    - partner : the mirror partner's displacement along the mirrored move, relative to the move (1 = mirrored exactly).
    - others : mean displacement length of the other keypoints (neither the moved one nor its partner), relative to the
      move (0 = they stay).
    """

    partner: float
    others: float


def prior_response(before: Any, after: Any, index: int, partner: int, move: Any, *,
                   mirror_axis: int = 0) -> PriorResponse:
    """Response of the keypoints to a synchronised single-keypoint move.

    Parameters
    ----------
    before, after : (K, 3) float64, keypoints before and after ``KeypointPrior.sync`` of the move.
    index : the moved keypoint; ``partner`` its mirror partner (``KeypointPrior.mirror_permutation_[index]``, which
        must differ from ``index``).
    move : (3,) float64, the move given to ``index``.
    mirror_axis : the mirror's axis (0 = x).
    """
    kp0, kp1 = as_points(before, "before"), as_points(after, "after")
    if kp0.shape != kp1.shape:
        raise InputError(f"before and after must have the same shape; got {kp0.shape} and {kp1.shape}")
    k = len(kp0)
    if not (0 <= index < k and 0 <= partner < k and index != partner):
        raise InputError(f"index and partner must be two different keypoints of {k}; got {index} and {partner}")
    d = np.asarray(move, dtype=np.float64)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.linalg.norm(d) > 0:
        raise InputError(f"move must be 3 finite numbers, not all zero; got {np.shape(move)}")
    mirrored = d.copy()
    mirrored[mirror_axis] *= -1.0
    delta = kp1 - kp0  # (K, 3)
    others = np.delete(np.linalg.norm(delta, axis=1), [index, partner])
    size = float(np.linalg.norm(d))
    return PriorResponse(float(delta[partner] @ mirrored / size**2), float(others.mean() / size) if len(others) else 0.0)


def _segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """(n,) distances between segments p1-q1 and p2-q2, each (n, 3) (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2)
    f, c, b = np.einsum("ij,ij->i", d2, r), np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d1, d2)
    tiny = 1e-30
    denom = a * e - b * b
    s = np.where(denom > tiny, np.clip((b * f - c * e) / np.maximum(denom, tiny), 0.0, 1.0), 0.0)
    t = np.where(e > tiny, (b * s + f) / np.maximum(e, tiny), 0.0)
    s = np.where(t < 0.0, np.clip(-c / np.maximum(a, tiny), 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / np.maximum(
        a, tiny), 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p1 + d1 * s[:, None] - (p2 + d2 * t[:, None]), axis=1)


def triangle_distance(a: Any, b: Any) -> np.ndarray:
    """(n,) float64: distance between the disjoint triangles ``a[i]`` and ``b[i]``, each (n, 3, 3).

    The distance of two disjoint triangles is attained between a vertex and the other triangle or between two
    edges, the cases computed here (for intersecting triangles the result is not 0 in general: test intersection
    first).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    best = np.full(len(a), np.inf)
    for x, y in ((a, b), (b, a)):
        for i in range(3):
            q = _closest_on_triangles(x[:, i], y[:, 0], y[:, 1], y[:, 2])  # (n, 3)
            np.minimum(best, np.linalg.norm(q - x[:, i], axis=1), out=best)
    for i in range(3):
        for j in range(3):
            d = _segment_distance(a[:, i], a[:, (i + 1) % 3], b[:, j], b[:, (j + 1) % 3])
            np.minimum(best, d, out=best)
    return best


def new_self_intersections(rest: Any, deformed: Any, triangles: Any, *, separation: float = 0.05) -> int:
    """Pairs of triangles that intersect after an edit but were apart before (Open3D's triangle-triangle test).

    CAD meshes intersect themselves as given (parts pushed into each other) and many parts only touch, so moving
    them creates contacts that break nothing. A pair counts only if it did not intersect in the rest shape and its
    triangles were more than ``separation`` apart there (exact triangle distance, in the mesh's units; 0.05 = 2.5%
    of the [-1, 1] box): a positive count means the edit pushed one part of the surface through another.
    """
    import open3d as o3d

    v0, v1, tri = _mesh_pair(rest, deformed, triangles)

    def pairs(vertices: np.ndarray) -> set:
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tri))
        found = np.sort(np.asarray(mesh.get_self_intersecting_triangles()), axis=1)
        return set(map(tuple, found.tolist()))

    new = np.array(sorted(pairs(v1) - pairs(v0)), dtype=np.int64).reshape(-1, 2)
    if not len(new):
        return 0
    apart = triangle_distance(v0[tri[new[:, 0]]], v0[tri[new[:, 1]]]) > separation
    return int(apart.sum())


def keypoint_set_distance(sets: Any, reference_sets: Any) -> np.ndarray:
    """(S,) float64: for each keypoint set, the mean keypoint distance to the nearest reference set.

    With the training shapes' keypoint sets as the reference this says how far sampled keypoint sets stray from the
    category's distribution (compare held-out shapes' own keypoints, which are real shapes).
    """
    a = _keypoint_sets(sets, "sets")
    b = _keypoint_sets(reference_sets, "reference_sets")
    if a.shape[1:] != b.shape[1:]:
        raise InputError(f"sets and reference_sets must have the same K; got {a.shape} and {b.shape}")
    out = np.empty(len(a))
    for i, s in enumerate(a):
        out[i] = np.linalg.norm(b - s, axis=2).mean(axis=1).min()
    return out
