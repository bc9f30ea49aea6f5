"""Shapes in the evaluation frame: annotated models and point clouds mapped into the [-1, 1] box the metrics work in,
with what was skipped and why."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, NamedTuple, Sequence

import numpy as np

from kpd.annotations.frames import (
    KEYPOINTNET_TO_REFERENCE,
    Similarity,
    fit_annotation_frame,
)
from kpd.annotations.keypointnet import KeypointNet
from kpd.annotations.shapenetpart import ShapeNetPart
from kpd.errors import DataError
from kpd.geometry import Normalizer, sample_surface
from kpd.io import Mesh, PointSet

__all__ = ["Skipped", "EvalShape", "keypointnet_shapes", "shapenetpart_shapes", "point_cloud_shapes"]

log = logging.getLogger("kpd.annotations")


class Skipped(NamedTuple):
    """A shape left out of a protocol, and why."""

    model_id: str
    reason: str


@dataclass
class EvalShape:
    """One shape, ready to score.

    Attributes
    ----------
    model_id, synset, split : identity (split None when unknown).
    geometry : Mesh or (N, 3) float64 points, in the reference frame (original scale); what a model is run on.
    normalizer : reference frame -> evaluation frame ([-1, 1] box of the geometry).
    file_to_reference : coordinates of the geometry file -> reference frame.
    points : (N, 3) float64, surface points in the evaluation frame (the cloud itself, or mesh samples).
    keypoints : (J, 3) float64 annotated keypoints in the evaluation frame, or None.
    semantic_ids : (J,) int64 or None.
    labels : (N,) int64 part labels of ``points``, or None.
    path : the geometry file; frame : how its frame is known ("keypointnet", "shapenetpart", "fitted:<map>").
    fit_distance : for a fitted frame, the largest keypoint-to-surface distance after the fit (evaluation units).
    """

    model_id: str
    synset: str
    split: str | None
    geometry: Any
    normalizer: Normalizer
    file_to_reference: Similarity
    points: np.ndarray
    path: Path
    frame: str
    keypoints: np.ndarray | None = None
    semantic_ids: np.ndarray | None = None
    labels: np.ndarray | None = None
    fit_distance: float | None = None

    def to_eval(self, reference_points: Any) -> np.ndarray:
        """Reference-frame (N, 3) -> evaluation frame."""
        return self.normalizer.apply(reference_points)

    def describe(self) -> dict:
        d = {"id": self.model_id, "split": self.split, "geometry": str(self.path), "frame": self.frame}
        if self.fit_distance is not None:
            d["fit_max_distance"] = round(float(self.fit_distance), 6)
        return d


def _read_geometry(path: Path):
    """A mesh with triangles, or the (N, 3) points of a point file (or of a mesh file without triangles)."""
    from kpd.io import read_shape

    shape = read_shape(path)
    if isinstance(shape, Mesh) and len(shape.triangles):
        return shape
    return shape.points if isinstance(shape, PointSet) else shape.vertices


def _map_geometry(raw, transform: Similarity, *, surface_samples: int, seed: int):
    """Geometry mapped by ``transform``: (geometry, surface points, the points a normaliser is fitted on)."""
    if isinstance(raw, Mesh):
        mesh = raw.with_vertices(transform.apply(raw.vertices))
        used = mesh.vertices[np.unique(mesh.triangles)]
        samples = sample_surface(mesh.vertices, mesh.triangles, surface_samples, seed=seed).points
        return mesh, samples, used
    points = transform.apply(raw)
    return points, points, points


def keypointnet_shapes(dataset: KeypointNet, split: str = "all", *, ids: Sequence[str] | None = None,
                       geometry_dirs: Sequence[str | os.PathLike] = (),
                       surface_samples: int = 2048, fit_samples: int = 50_000, seed: int = 0,
                       max_fit_distance: float = 0.05,
                       progress: Callable[[Iterable], Iterable] | None = None
                       ) -> tuple[list[EvalShape], list[Skipped]]:
    """The annotated models of a split that have geometry, with their annotations in the evaluation frame.

    Geometry in the annotations' frame (the KeypointNet cloud or a ShapeNet v2 mesh) is mapped by the authors' axis
    fix; any other copy is registered with :func:`fit_annotation_frame` on ``fit_samples`` surface points and left
    out when a keypoint stays farther than ``max_fit_distance`` (evaluation units) from its surface. Models without
    geometry are returned as :class:`Skipped`.

    Parameters
    ----------
    ids : only these models (of the split).
    surface_samples : points sampled on a mesh for :attr:`EvalShape.points` (a cloud is used as it is).
    seed : seed of the surface samples.
    progress : optional wrapper of an iterable (a progress bar).
    """
    shapes: list[EvalShape] = []
    skipped: list[Skipped] = []
    wanted = dataset.ids(split)
    if ids is not None:
        wanted = [i for i in wanted if i in set(ids)]
    found = [(i, dataset.geometry_file(i, geometry_dirs)) for i in wanted]
    missing = [i for i, f in found if f is None]
    skipped += [Skipped(i, "no geometry") for i in missing]
    todo = [(i, f) for i, f in found if f is not None]
    for model_id, (path, kind) in (progress(todo) if progress else todo):
        model = dataset.get(model_id)
        fit_distance = None
        raw = _read_geometry(path)
        if kind == "keypointnet":
            to_reference = Similarity.linear(KEYPOINTNET_TO_REFERENCE)
            frame = "keypointnet"
        else:
            if isinstance(raw, Mesh):
                dense = sample_surface(raw.vertices, raw.triangles, fit_samples, seed=seed).points
            else:
                dense = raw
            fit = fit_annotation_frame(model.keypoints, dense)
            # geometry -> KeypointNet -> reference
            to_reference = fit.transform.inverse().then(Similarity.linear(KEYPOINTNET_TO_REFERENCE))
            frame = f"fitted:{fit.candidate}"
            fit_distance = float(fit.distances.max())
        geometry, points, used = _map_geometry(raw, to_reference, surface_samples=surface_samples, seed=seed)
        normalizer = Normalizer().fit(used)
        keypoints = normalizer.apply(model.keypoints @ KEYPOINTNET_TO_REFERENCE.T)
        if fit_distance is not None:
            if isinstance(geometry, Mesh):  # exact distance to the triangles
                from kpd.metrics import point_triangle_distance

                fit_distance = float(point_triangle_distance(keypoints, normalizer.apply(geometry.vertices),
                                                             geometry.triangles).max())
            else:
                fit_distance *= to_reference.scale / normalizer.scale_
            if fit_distance > max_fit_distance:
                skipped.append(Skipped(model_id, f"annotations do not fit {path} (a keypoint {fit_distance:.3f} "
                                                 f"from the surface > {max_fit_distance})"))
                continue
        shapes.append(EvalShape(model_id, dataset.synset, model.split, geometry, normalizer, to_reference,
                                normalizer.apply(points), path, frame, keypoints, model.semantic_ids,
                                fit_distance=fit_distance))
    return shapes, skipped


def shapenetpart_shapes(dataset: ShapeNetPart, category: str, split: str = "all", *,
                        progress: Callable[[Iterable], Iterable] | None = None) -> list[EvalShape]:
    """Part-labelled shapes of a category in the evaluation frame (ShapeNetPart's frame is the reference frame)."""
    ids = dataset.ids(category, split)
    if not ids:
        raise DataError(f"no {category!r} shapes in split {split!r} of {dataset.root}")
    shapes = []
    for model_id in (progress(ids) if progress else ids):
        part = dataset.load(category, model_id)
        normalizer = Normalizer().fit(part.points)
        shapes.append(EvalShape(model_id, part.synset, split if split != "all" else None, part.points, normalizer,
                                Similarity.identity(), normalizer.apply(part.points), part.path, "shapenetpart",
                                labels=part.labels))
    return shapes


def point_cloud_shapes(root: str | os.PathLike, category: str, split: str = "all", *,
                       progress: Callable[[Iterable], Iterable] | None = None) -> tuple[list[EvalShape], str]:
    """Point clouds for the label-free SC3K metrics: a KeypointNet folder (its clouds, annotations unused beyond the
    list of models) or a ShapeNetPart folder. Returns the shapes and the dataset kind."""
    root = Path(root)
    if (root / "annotations").is_dir():
        dataset = KeypointNet(root, category)
        with_cloud = [i for i in dataset.ids(split) if (root / "pcds" / dataset.synset / f"{i}.pcd").is_file()]
        clouds, _ = keypointnet_shapes(dataset, split, ids=with_cloud, progress=progress)
        if not clouds:
            raise DataError(f"no KeypointNet point clouds (pcds/{dataset.synset}/*.pcd) for split {split!r} in {root}")
        return clouds, "keypointnet"
    if (root / "synsetoffset2category.txt").is_file():
        return shapenetpart_shapes(ShapeNetPart(root), category, split, progress=progress), "shapenetpart"
    raise DataError(f"{root} is neither a KeypointNet folder (annotations/) nor a ShapeNetPart folder "
                    "(synsetoffset2category.txt)")
