"""Keypoint sources for the protocols: a model bundle run on each shape, or keypoint files written by another method, in
the evaluation frame."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kpd.annotations.frames import MODELNET_TO_REFERENCE
from kpd.annotations.shapes import EvalShape, Skipped
from kpd.errors import DataError, InputError
from kpd.io import Mesh

__all__ = ["ModelKeypoints", "FileKeypoints"]

log = logging.getLogger("kpd.annotations")


_UP_TO_REFERENCE = {"+y": np.eye(3), "+z": MODELNET_TO_REFERENCE}


class ModelKeypoints:
    """Keypoints predicted by a bundle (:class:`kpd.runtime.Model`).

    Parameters
    ----------
    model : a loaded Model.
    up : the frame the model was trained in: ``"+z"`` (ModelNet: the shape is rotated by the inverse of
        :data:`MODELNET_TO_REFERENCE` before prediction and the keypoints back) or ``"+y"`` (the reference frame,
        ShapeNet/KeypointNet as the authors use it); ``None`` reads the bundle's record (an error when it has none:
        a wrong frame would give meaningless scores).
    seed : sampling seed passed to the model.
    """

    def __init__(self, model: Any, *, up: str | None = None, seed: int = 0) -> None:
        self.model = model
        self.up = up or model.up
        if self.up is None:
            raise InputError(f"the bundle {model.bundle.path} does not record the frame it was trained in; say it "
                             "with up='+z' (ModelNet) or up='+y' (ShapeNet / KeypointNet), --up on the command line")
        if self.up not in _UP_TO_REFERENCE:
            raise InputError(f"up must be '+y' or '+z'; got {self.up!r}")
        self.to_reference = _UP_TO_REFERENCE[self.up]
        self.seed = seed

    @property
    def num_keypoints(self) -> int:
        return self.model.num_keypoints

    def describe(self) -> dict:
        bundle = self.model.bundle
        return {"source": "model", "bundle": str(bundle.path), "category": self.model.category,
                "keypoints": self.model.num_keypoints, "up": self.up, "seed": self.seed}

    def __call__(self, shapes: Sequence[EvalShape]) -> tuple[list[np.ndarray | None], list[Skipped]]:
        """Keypoints of each shape in its evaluation frame (the same K for all)."""
        inputs = []
        for s in shapes:
            g = s.geometry
            to_model = self.to_reference.T  # reference -> model frame (rows: x @ to_model.T)
            if isinstance(g, Mesh):
                inputs.append(g.with_vertices(g.vertices @ to_model.T))
            else:
                inputs.append(np.asarray(g) @ to_model.T)
        predicted = self.model.keypoints_batch(inputs, seed=self.seed)  # (S, K, 3), model frame, each shape's units
        return [s.to_eval(k @ self.to_reference.T) for s, k in zip(shapes, predicted)], []


class FileKeypoints:
    """Keypoints read from files, one per shape, so that any method's output can be scored.

    Parameters
    ----------
    folder : holds ``<id>.json`` or ``<id>.txt`` (:func:`kpd.io.read_keypoints` formats), also accepted as
        ``<synset>-<id>.*`` or ``<synset>/<id>.*``.
    frame : ``"file"`` (default): coordinates of the geometry file the shape is scored on (the KeypointNet ``.pcd``,
        the ShapeNetPart ``.pts``, or the mesh); ``"unit"``: already in the evaluation frame.
    """

    def __init__(self, folder: str | os.PathLike, *, frame: str = "file") -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise InputError(f"keypoints folder {self.folder} does not exist")
        if frame not in ("file", "unit"):
            raise InputError(f"frame must be 'file' or 'unit'; got {frame!r}")
        self.frame = frame

    def describe(self) -> dict:
        return {"source": "files", "folder": str(self.folder), "frame": self.frame}

    def path(self, shape: EvalShape) -> Path | None:
        names = (shape.model_id, f"{shape.synset}-{shape.model_id}", f"{shape.synset}/{shape.model_id}")
        for name in names:
            for suffix in (".json", ".txt"):
                p = self.folder / f"{name}{suffix}"
                if p.is_file():
                    return p
        return None

    def __call__(self, shapes: Sequence[EvalShape]) -> tuple[list[np.ndarray | None], list[Skipped]]:
        from kpd.io import read_keypoints

        out: list[np.ndarray | None] = []
        skipped = []
        for s in shapes:
            p = self.path(s)
            if p is None:
                out.append(None)
                skipped.append(Skipped(s.model_id, f"no keypoint file {s.model_id}.json|.txt in {self.folder}"))
                continue
            k = read_keypoints(p)
            out.append(k if self.frame == "unit" else s.to_eval(s.file_to_reference.apply(k)))
        return out, skipped


def _predict(source, shapes: list[EvalShape]) -> tuple[list[EvalShape], np.ndarray, list[Skipped]]:
    """Run a keypoint source; keep the shapes it covers; check one K for all."""
    keypoints, skipped = source(shapes)
    kept = [(s, k) for s, k in zip(shapes, keypoints) if k is not None]
    if not kept:
        raise DataError("the keypoint source gave keypoints for none of the shapes"
                        + (f" (first: {skipped[0].reason})" if skipped else ""))
    counts = {len(k) for _, k in kept}
    if len(counts) != 1:
        first = {len(k): s.model_id for s, k in kept}
        raise DataError("every shape needs the same number of keypoints; got "
                        + ", ".join(f"{n} ({first[n]})" for n in sorted(counts)))
    return [s for s, _ in kept], np.stack([k for _, k in kept]), skipped
