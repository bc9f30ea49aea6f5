"""Real-scan preprocessing: clean a scan, orient it to a reference shape, normalise it into the model's [-1, 1] frame.

KeypointDeformer assumes that the shapes of a category share one orientation. Real scans arrive in any pose, in any
unit, with noise, stray points, a ground plane and holes. This module

1. cleans a scan (:func:`clean`): statistical outlier removal (point sets), removal of a dominant ground plane found
   by RANSAC, and removal of small disconnected pieces (meshes); every step is switchable and reported;
2. orients it (:class:`ScanAligner`, :func:`orient`): a global search over rotations (principal axes under all 24
   proper signed axis permutations, the 60 rotations of the icosahedral group, and FPFH + RANSAC candidates), every
   hypothesis refined by a trimmed, symmetric ICP (with a scale per axis, since shapes of a category differ in
   proportions) and scored by a trimmed symmetric RMS distance on scale-normalised shapes; when the reference's up
   axis is known, each hypothesis is stood on the scan's own support plane (:func:`support_plane`: the hull faces
   under its lowest points, e.g. between the leg tips) turned onto the reference's, and only its turn about the up
   axis is refined; the best, the runner-up (a rotation more than ``distinct_angle`` degrees away) and the margin
   between them are reported, and a small margin is flagged as ambiguous rather than silently chosen;
3. normalises the rotated scan with :class:`kpd.geometry.Normalizer` (docs/method.md §7) and keeps the full similarity
   transform and its inverse (:func:`preprocess`, :class:`ScanResult`), so that results map back onto the scan.

Everything is numpy (float64) plus Open3D; no torch.

The package's modules, one topic each: :mod:`kpd.scan.clean`, :mod:`kpd.scan.orient`, :mod:`kpd.scan.pipeline`,
:mod:`kpd.scan.rotations`, :mod:`kpd.scan.support` and :mod:`kpd.scan.shapes`; every name is importable from
``kpd.scan`` itself.
"""

from __future__ import annotations

from kpd.scan.clean import CleanReport, CleanResult, clean
from kpd.scan.orient import DEFAULT_AMBIGUITY_MARGIN, MESH_ORIENT_SAMPLES, Hypothesis, Orientation, ScanAligner, orient
from kpd.scan.pipeline import (NormalizeResult, ScanResult, candidate_rotations, normalize, preprocess, reorient,
                               similarity_matrices)
from kpd.scan.rotations import (AXES, _rotation_between, icosahedral_rotations, parse_axis,  # noqa: F401
                                proper_signed_permutations, rotation_angle)
from kpd.scan.support import Support, _dense_subset, hull_faces, support_plane  # noqa: F401

__all__ = [
    "AXES", "CleanReport", "CleanResult", "Hypothesis", "Orientation", "ScanAligner", "ScanResult", "NormalizeResult",
    "clean", "orient", "normalize", "preprocess", "parse_axis", "rotation_angle", "proper_signed_permutations",
    "icosahedral_rotations", "Support", "support_plane", "hull_faces", "candidate_rotations", "reorient",
    "DEFAULT_AMBIGUITY_MARGIN", "MESH_ORIENT_SAMPLES", "similarity_matrices",
]


def __getattr__(attr: str):
    if attr == "alignment_picture":  # drawing is the viewer's: the core never imports it
        raise AttributeError(f"{__name__}.alignment_picture moved to kpd.viewer.figures.alignment_picture")
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
