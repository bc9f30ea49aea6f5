"""ShapeNetPart: its point clouds with per-point part labels and its official splits."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kpd.annotations.frames import SPLITS
from kpd.errors import DataError, InputError

__all__ = ["PartShape", "ShapeNetPart"]

log = logging.getLogger("kpd.annotations")


class PartShape(NamedTuple):
    """One ShapeNetPart shape: points (N, 3) float64 in the file's frame, labels (N,) int64, path of the points."""

    synset: str
    model_id: str
    points: np.ndarray
    labels: np.ndarray
    path: Path


class ShapeNetPart:
    """A ShapeNetPart folder (Yi et al., SIGGRAPH Asia 2016; ``shapenetcore_partanno_segmentation_benchmark_v0``).

    Parameters
    ----------
    root : the folder holding ``synsetoffset2category.txt`` and one folder per synset.
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        index = self.root / "synsetoffset2category.txt"
        if not index.is_file():
            raise DataError(f"{self.root} is not a ShapeNetPart folder: no synsetoffset2category.txt")
        self.categories: dict[str, str] = {}
        for number, line in enumerate(index.read_text(encoding="utf-8").splitlines(), 1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) != 2:
                raise DataError(f"{index}: line {number} must be '<name> <synset>'; got {line!r}")
            self.categories[fields[0].lower()] = fields[1]
        split_dir = self.root / "train_test_split"
        self.split_files = {s: split_dir / f"shuffled_{s}_file_list.json" for s in SPLITS
                            if (split_dir / f"shuffled_{s}_file_list.json").is_file()}

    def __repr__(self) -> str:
        return f"ShapeNetPart({str(self.root)!r}, {len(self.categories)} categories)"

    def synset(self, category: str) -> str:
        """Synset of a category name (``Chair``, ``chair``) or synset."""
        key = category.lower()
        if key in self.categories:
            return self.categories[key]
        if category in self.categories.values():
            return category
        raise DataError(f"category {category!r} is not in {self.root / 'synsetoffset2category.txt'} (known: "
                        f"{', '.join(sorted(self.categories))})")

    def name(self, synset: str) -> str:
        return {s: n for n, s in self.categories.items()}.get(synset, synset)

    def ids(self, category: str, split: str = "all") -> list[str]:
        """Sorted ids of a category with both points and labels, restricted to a split's file list."""
        synset = self.synset(category)
        folder = self.root / synset / "points"
        if not folder.is_dir():
            raise DataError(f"no points folder {folder} for category {category!r}")
        ids = sorted(p.stem for p in folder.glob("*.pts")
                     if (self.root / synset / "points_label" / f"{p.stem}.seg").is_file())
        if split == "all":
            return ids
        if split not in SPLITS:
            raise InputError(f"split must be one of train, val, test, all; got {split!r}")
        if split not in self.split_files:
            raise DataError(f"{self.root} has no train_test_split/shuffled_{split}_file_list.json; use split 'all'"
                            + (f" or one of {', '.join(self.split_files)}" if self.split_files else ""))
        try:
            listed = json.loads(self.split_files[split].read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DataError(f"{self.split_files[split]}: not valid JSON ({exc})") from exc
        wanted = {Path(str(e)).name for e in listed if Path(str(e)).parent.name == synset}
        return [i for i in ids if i in wanted]

    def load(self, category: str, model_id: str) -> PartShape:
        from kpd.io import read_points

        synset = self.synset(category)
        path = self.root / synset / "points" / f"{model_id}.pts"
        seg = self.root / synset / "points_label" / f"{model_id}.seg"
        if not path.is_file() or not seg.is_file():
            raise DataError(f"shape {model_id} of {category!r} needs {path} and {seg}")
        points = read_points(path).points
        try:
            labels = np.loadtxt(seg, dtype=np.int64, ndmin=1)
        except ValueError as exc:
            raise DataError(f"{seg}: part labels must be one integer per line ({exc})") from exc
        if labels.shape != (len(points),):
            raise DataError(f"{seg}: {labels.size} labels for the {len(points)} points of {path}")
        return PartShape(synset, model_id, points, labels, path)
