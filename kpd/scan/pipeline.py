"""The one-call pipeline: clean, orient and normalise a scan into the model's [-1, 1] frame, keeping the similarity
transform both ways (:func:`preprocess`, :class:`ScanResult`); other rotations of an ambiguous result
(:func:`candidate_rotations`, :func:`reorient`)."""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np

from kpd.errors import InputError
from kpd.geometry import Normalizer, as_points, sample_surface
from kpd.scan.clean import CleanReport, clean
from kpd.scan.orient import DEFAULT_AMBIGUITY_MARGIN, MESH_ORIENT_SAMPLES, Orientation, ScanAligner
from kpd.scan.rotations import rotation_angle
from kpd.scan.shapes import _is_mesh, _shape_points, _with_points

__all__ = [
    "NormalizeResult", "normalize", "ScanResult", "similarity_matrices", "preprocess", "candidate_rotations",
    "reorient",
]

log = logging.getLogger("kpd.scan")


class NormalizeResult(NamedTuple):
    points: np.ndarray
    normalizer: Normalizer


def normalize(points: Any) -> NormalizeResult:
    """``points`` (N, 3) into the [-1, 1] box (docs/method.md §7) with the fitted :class:`~kpd.geometry.Normalizer`."""
    normalizer = Normalizer().fit(points)
    return NormalizeResult(normalizer.apply(points), normalizer)


class ScanResult(NamedTuple):
    """Result of :func:`preprocess`.

    shape : the cleaned scan, rotated into the reference's frame and normalised into [-1, 1] (same type as the input)
    points : (N, 3) float64, its points (mesh vertices)
    transform : (4, 4) float64, the similarity taking cleaned-scan coordinates to ``points``
    inverse : (4, 4) float64, its exact inverse: results in the aligned frame map back onto the original scan
    rotation : (3, 3) float64 ; normalizer : Normalizer of the rotated scan (``points = normalizer.apply(x @ R.T)``)
    orientation : Orientation (None when no reference was given) ; clean : CleanReport
    """

    shape: Any
    points: np.ndarray
    transform: np.ndarray
    inverse: np.ndarray
    rotation: np.ndarray
    normalizer: Normalizer
    orientation: Orientation | None
    clean: CleanReport

    def to_original(self, points: Any) -> np.ndarray:
        """(N, 3) points of the aligned frame mapped back onto the original scan."""
        points = as_points(points, min_count=0)
        return points @ self.inverse[:3, :3].T + self.inverse[:3, 3]

    def to_aligned(self, points: Any) -> np.ndarray:
        """(N, 3) points of the original scan mapped into the aligned frame."""
        points = as_points(points, min_count=0)
        return points @ self.transform[:3, :3].T + self.transform[:3, 3]

    def to_dict(self) -> dict:
        return {
            "transform": self.transform.tolist(),
            "inverse": self.inverse.tolist(),
            "rotation": self.rotation.tolist(),
            "normalizer": self.normalizer.to_dict(),
            "orientation": None if self.orientation is None else self.orientation.to_dict(),
            "clean": self.clean.to_dict(),
            "count": len(self.points),
        }


def similarity_matrices(rotation: np.ndarray, normalizer: Normalizer) -> tuple[np.ndarray, np.ndarray]:
    """The (4, 4) map ``x -> (R x - c) / s`` of a rotation then a normaliser, and its inverse ``y -> R^T (s y + c)``."""
    c, s = normalizer.center_, normalizer.scale_
    forward = np.eye(4)
    forward[:3, :3] = rotation / s
    forward[:3, 3] = -c / s
    inverse = np.eye(4)
    inverse[:3, :3] = rotation.T * s
    inverse[:3, 3] = rotation.T @ c
    return forward, inverse


def preprocess(
    shape: Any,
    reference: Any = None,
    *,
    clean_params: dict | None = None,
    aligner: ScanAligner | None = None,
    outer: bool = False,
    **orient_params: Any,
) -> ScanResult:
    """Clean, orient and normalise a scan in one call.

    Parameters
    ----------
    shape : (N, 3) array, PointSet or Mesh (the scan).
    reference : (M, 3) points (or a PointSet / Mesh) in the model's frame, or None to skip orientation (the scan is
        then only cleaned and normalised).
    clean_params : keyword arguments of :func:`clean` (``up`` is passed on from ``orient_params`` if not given).
    aligner : an already fitted :class:`ScanAligner` (then ``reference`` and ``orient_params`` are not used).
    outer : orient a mesh by samples of its outer surface only (:func:`kpd.geometry.sample_surface`): for meshes
        made of overlapping pieces, as the models trained with ``kpd train --outer-surface`` see them.
    orient_params : keyword arguments of :class:`ScanAligner`.

    Returns
    -------
    ScanResult; ``result.inverse`` maps ``result.points`` back onto the cleaned scan exactly (float64 round-off).
    """
    clean_params = dict(clean_params or {})
    if "up" in orient_params and "up" not in clean_params:
        clean_params["up"] = orient_params["up"]
    _shape_points(shape)  # checks the input before any work
    cleaned, report = clean(shape, **clean_params)
    points = _shape_points(cleaned)
    if aligner is None and reference is not None:
        aligner = ScanAligner(**orient_params).fit(reference)
    if aligner is not None:
        # a mesh is oriented by its surface, not its vertices (CAD meshes crowd vertices on curved details)
        triangles = np.asarray(getattr(cleaned, "triangles", np.zeros((0, 3))))
        seen = (sample_surface(points, triangles, MESH_ORIENT_SAMPLES, aligner.seed, outer=outer).points
                if _is_mesh(cleaned) and len(triangles) else points)
        orientation = aligner.orient(seen)
    else:
        orientation = None
    rotation = np.eye(3) if orientation is None else orientation.rotation
    normalizer, forward, inverse, aligned = _aligned_frame(points, rotation)
    return ScanResult(_with_points(cleaned, aligned, forward[:3, :3]), aligned, forward, inverse, rotation,
                      normalizer, orientation, report)


def _aligned_frame(points: np.ndarray, rotation: np.ndarray) -> tuple[Normalizer, np.ndarray, np.ndarray, np.ndarray]:
    """The scan's points turned by ``rotation`` and normalised: the normaliser, the 4x4 maps to the aligned frame and
    back, and the aligned points."""
    normalizer = Normalizer().fit(points @ rotation.T)
    forward, inverse = similarity_matrices(rotation, normalizer)
    return normalizer, forward, inverse, points @ forward[:3, :3].T + forward[:3, 3]


def candidate_rotations(orientation: Orientation, margin: float | None = None,
                        distinct_angle: float = 30.0) -> list[tuple[np.ndarray, float]]:
    """The distinct rotations an ambiguous orientation hesitates between: (rotation, score) pairs, best first.

    The first is the chosen rotation; then every refined hypothesis whose score is within ``margin`` (relative, as
    :attr:`Orientation.margin`; default the aligner's :data:`DEFAULT_AMBIGUITY_MARGIN`) of the best and that lies
    more than ``distinct_angle`` degrees from every rotation listed before it. A shape that is not ambiguous (or has
    no such hypothesis) gives the chosen rotation alone. What settles the choice is up to the caller: a model's
    keypoint prior (``kpd keypoints --scan``), the shape's look-alikes (``kpd scan FOLDER``).
    """
    margin = DEFAULT_AMBIGUITY_MARGIN if margin is None else float(margin)
    out = [(orientation.rotation, float(orientation.score))]
    if not orientation.ambiguous or not np.isfinite(orientation.score):
        return out
    for h in orientation.hypotheses:
        if h.score > orientation.score * (1.0 + margin):
            break  # hypotheses are sorted best first
        if all(rotation_angle(h.rotation, r) > distinct_angle for r, _ in out):
            out.append((h.rotation, float(h.score)))
    return out


def reorient(result: ScanResult, rotation: np.ndarray) -> ScanResult:
    """``result``'s cleaned scan turned by another ``rotation`` (3, 3) (a runner-up hypothesis, say) and normalised
    again: the :class:`ScanResult` :func:`preprocess` would have returned had it chosen that rotation."""
    rotation = np.asarray(rotation, dtype=np.float64)
    if rotation.shape != (3, 3) or not np.isfinite(rotation).all() or abs(np.linalg.det(rotation) - 1.0) > 1e-6:
        raise InputError(f"a rotation must be a proper (3, 3) rotation matrix; got shape {rotation.shape}")
    points = result.to_original(result.points)  # the cleaned scan
    normalizer, forward, inverse, aligned = _aligned_frame(points, rotation)
    linear = forward[:3, :3] @ result.inverse[:3, :3]  # old aligned frame -> new aligned frame
    return ScanResult(_with_points(result.shape, aligned, linear), aligned, forward, inverse, rotation, normalizer,
                      result.orientation, result.clean)
