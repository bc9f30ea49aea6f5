"""The contract between the exporter (``kpd.export``, torch) and the runtime (``kpd.runtime``, onnxruntime).

Both sides import these names, so a bundle written by one is read by the other without guessing. Nothing here
imports torch or onnxruntime.

A bundle (directory ``name.kpd/`` or a zip of the same files) holds:

================== ==========================================================================================
``manifest.json``  format name and version, shapes (K, C, F, M), category, point count, normalisation, cage
                   template, W_C, the PCA prior (or null), the template point cloud's description, training
                   record, sha256 of every other file, and a checksum of the manifest itself
``keypoints.onnx`` ``points`` (B, N, 3) float32 -> ``keypoints`` (B, K, 3) float32, clamped to [-1, 1]
``influence.onnx`` ``points`` (B, N, 3) float32 -> ``influence`` (B, K, C) float32, the instance offset W_I
``template.npy``   (optional) (P, 3) float32 surface points of a representative training shape, model frame
================== ==========================================================================================

Points are in the model's [-1, 1] frame (``kpd.geometry.Normalizer``, docs/method.md §7). ``B`` and ``N`` are dynamic
axes named :data:`BATCH_AXIS` and :data:`POINTS_AXIS`.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MANIFEST_FILE",
    "TEMPLATE_FILE",
    "INPUT_NAME",
    "BATCH_AXIS",
    "POINTS_AXIS",
    "OPSET",
    "NORMALIZATION",
    "GraphSpec",
    "KEYPOINTS_GRAPH",
    "INFLUENCE_GRAPH",
    "GRAPHS",
    "META_FORMAT",
    "META_FORMAT_VERSION",
    "META_GRAPH",
    "META_KEYPOINTS",
    "META_CAGE_VERTICES",
    "META_CATEGORY",
]

FORMAT_NAME = "kpd-bundle"
FORMAT_VERSION = 1

MANIFEST_FILE = "manifest.json"
TEMPLATE_FILE = "template.npy"

INPUT_NAME = "points"
BATCH_AXIS = "batch"
POINTS_AXIS = "points"
OPSET = 20

# How shapes are mapped into the model frame; the runtime refuses a bundle that says anything else.
NORMALIZATION = "bbox-center-max-abs"


class GraphSpec(NamedTuple):
    """One ONNX graph of a bundle.

    key : name of the graph in the manifest and in the ``kpd.graph`` metadata entry.
    file : file name inside the bundle.
    output : name of the single output.
    output_axes : symbolic output shape; "K" and "C" are fixed per model, ``BATCH_AXIS`` is dynamic.
    """

    key: str
    file: str
    output: str
    output_axes: tuple[str, ...]


KEYPOINTS_GRAPH = GraphSpec("keypoints", "keypoints.onnx", "keypoints", (BATCH_AXIS, "K", "3"))
INFLUENCE_GRAPH = GraphSpec("influence", "influence.onnx", "influence", (BATCH_AXIS, "K", "C"))
GRAPHS = (KEYPOINTS_GRAPH, INFLUENCE_GRAPH)

# Keys of the ONNX models' metadata_props (values are strings).
META_FORMAT = "kpd.format"
META_FORMAT_VERSION = "kpd.format_version"
META_GRAPH = "kpd.graph"
META_KEYPOINTS = "kpd.keypoints"
META_CAGE_VERTICES = "kpd.cage_vertices"
META_CATEGORY = "kpd.category"
