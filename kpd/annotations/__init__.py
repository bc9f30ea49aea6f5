"""Annotated datasets (KeypointNet, ShapeNetPart) and the protocols that score keypoints on them.

Readers
-------
- :class:`KeypointNet`: ``ROOT/annotations/<category>.json`` (``model_id``, ``keypoints[].xyz``, ``semantic_id``,
  ``pcd_info.point_index``), ``ROOT/splits/{train,val,test}.txt`` (lines ``<synset>-<model id>``) and the geometry
  ``ROOT/pcds/<synset>/<id>.pcd`` (KeypointNet's own cloud, the frame of the annotations), or a ShapeNet v2 mesh
  ``ROOT/models/<synset>/<id>[/models]/model_normalized.obj`` (same frame), or any other mesh of the model (another
  frame, registered by :func:`fit_annotation_frame`).
- :class:`ShapeNetPart`: ``ROOT/<synset>/points/<id>.pts`` + ``points_label/<id>.seg``, ``synsetoffset2category.txt``
  and, when present, ``train_test_split/shuffled_{train,val,test}_file_list.json``.

Frames
------
Everything is scored in one *evaluation frame* per shape: the shape is first put into the *reference frame* (y up,
the axes of the KeypointDeformer authors' data: KeypointNet coordinates mapped by ``(x, y, z) -> (-z, y, x)``,
docs/method.md §8, which is also ShapeNetPart's frame), then into the [-1, 1] box of its geometry by a
:class:`kpd.geometry.Normalizer` (docs/method.md §7: the authors normalise KeypointNet keypoints with the unit box of
the KeypointNet point cloud). Thresholds such as PCK@0.05 are in these units. A model trained on ModelNet (z up) sees
the shape rotated into its own frame (``MODELNET_TO_REFERENCE``) and its keypoints are rotated back.

Protocols
---------
:func:`pck_protocol` (paper Fig. 4), :func:`parts_protocol` (paper Table 1), :func:`das_protocol` (Skeleton Merger),
:func:`coverage_protocol` (SC3K), :func:`chamfer_protocol` (paper Fig. 7 on a bundle). Each returns a JSON-safe dict
with the protocol, its definition, the data used and the numbers; the metrics themselves are in :mod:`kpd.metrics`.

The package's modules, one topic each: kpd.annotations.frames, keypointnet, shapenetpart, shapes, sources and
protocols; every name is importable from kpd.annotations itself.
"""

from __future__ import annotations

from kpd.annotations.frames import (
                                    FIT_CANDIDATES,
                                    KEYPOINTNET_TO_REFERENCE,
                                    MODELNET_TO_REFERENCE,
                                    SPLITS,
                                    FrameFit,
                                    Similarity,
                                    fit_annotation_frame,
)
from kpd.annotations.keypointnet import (
                                    KEYPOINTNET_CATEGORIES,
                                    AnnotatedModel,
                                    KeypointNet,
)
from kpd.annotations.protocols import (
                                    FEW_TEST_SHAPES,
                                    alignment_pairs,
                                    chamfer_protocol,
                                    coverage_protocol,
                                    das_protocol,
                                    pair_notes,
                                    parts_protocol,
                                    pck_protocol,
)
from kpd.annotations.shapenetpart import PartShape, ShapeNetPart
from kpd.annotations.shapes import (
                                    EvalShape,
                                    Skipped,
                                    keypointnet_shapes,
                                    point_cloud_shapes,
                                    shapenetpart_shapes,
)
from kpd.annotations.sources import FileKeypoints, ModelKeypoints

__all__ = [
    "KEYPOINTNET_CATEGORIES", "KEYPOINTNET_TO_REFERENCE", "MODELNET_TO_REFERENCE", "FIT_CANDIDATES", "Similarity",
    "FrameFit", "fit_annotation_frame", "AnnotatedModel", "KeypointNet", "PartShape", "ShapeNetPart", "EvalShape",
    "Skipped", "keypointnet_shapes", "shapenetpart_shapes", "point_cloud_shapes", "ModelKeypoints", "FileKeypoints",
    "pck_protocol", "parts_protocol", "das_protocol", "coverage_protocol", "chamfer_protocol", "alignment_pairs",
    "pair_notes", "FEW_TEST_SHAPES", "SPLITS",
]
