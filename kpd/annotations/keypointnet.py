"""KeypointNet: its annotation files read per category, with each model's keypoints and semantic ids, and the shape
files beside them found."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from kpd.annotations.frames import SPLITS
from kpd.errors import DataError, InputError

__all__ = ["KEYPOINTNET_CATEGORIES", "AnnotatedModel", "KeypointNet"]

log = logging.getLogger("kpd.annotations")


# KeypointNet's 16 categories: annotation file name -> ShapeNet synset.
KEYPOINTNET_CATEGORIES = {
    "airplane": "02691156", "bathtub": "02808440", "bed": "02818832", "bottle": "02876657", "cap": "02954340",
    "car": "02958343", "chair": "03001627", "guitar": "03467517", "helmet": "03513137", "knife": "03624134",
    "laptop": "03642806", "motorcycle": "03790512", "mug": "03797390", "skateboard": "04225987",
    "table": "04379243", "vessel": "04530566",
}


_ALIASES = {"motorbike": "motorcycle", "plane": "airplane", "boat": "vessel"}


class AnnotatedModel(NamedTuple):
    """One model of a KeypointNet annotation file.

    model_id : str; split : "train" | "val" | "test" | None (not in a split file);
    keypoints : (J, 3) float64, KeypointNet coordinates; semantic_ids : (J,) int64;
    pcd_index : (J,) int64 or None, indices into the model's KeypointNet point cloud.
    """

    model_id: str
    split: str | None
    keypoints: np.ndarray
    semantic_ids: np.ndarray
    pcd_index: np.ndarray | None


def _category_name(category: str) -> str:
    name = _ALIASES.get(category.lower(), category.lower())
    by_synset = {s: n for n, s in KEYPOINTNET_CATEGORIES.items()}
    return by_synset.get(name, name)


class KeypointNet:
    """A KeypointNet folder, one category (You et al., CVPR 2020; github.com/qq456cvb/KeypointNet).

    Parameters
    ----------
    root : the folder holding ``annotations/``, ``splits/`` and ``pcds/``.
    category : a KeypointNet category name (``chair``) or synset (``03001627``).

    Attributes
    ----------
    root, category, synset, annotation_path, models (list of :class:`AnnotatedModel`, in file order),
    split_source (the split folder, or None).
    """

    def __init__(self, root: str | os.PathLike, category: str) -> None:
        self.root = Path(root)
        if not (self.root / "annotations").is_dir():
            raise DataError(f"{self.root} is not a KeypointNet folder: no annotations/ folder")
        self.category = _category_name(str(category))
        self.annotation_path = self.root / "annotations" / f"{self.category}.json"
        if not self.annotation_path.is_file():
            available = sorted(p.stem for p in (self.root / "annotations").glob("*.json"))
            raise DataError(f"no KeypointNet annotations for {category!r}: {self.annotation_path} does not exist "
                            f"(available: {', '.join(available) or 'none'})")
        try:
            entries = json.loads(self.annotation_path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DataError(f"{self.annotation_path}: not valid JSON ({exc})") from exc
        if not isinstance(entries, list) or not entries:
            raise DataError(f"{self.annotation_path}: expected a non-empty list of models; got "
                            f"{type(entries).__name__}")
        self.synset = KEYPOINTNET_CATEGORIES.get(self.category) or str(entries[0].get("class_id", ""))
        self.split_source = self.root / "splits" if (self.root / "splits").is_dir() else None
        splits = self._read_splits()
        self.models: list[AnnotatedModel] = []
        for i, entry in enumerate(entries):
            self.models.append(self._parse(entry, i, splits))
        self._by_id = {m.model_id: m for m in self.models}

    def _read_splits(self) -> dict[str, str]:
        assignment: dict[str, str] = {}
        if self.split_source is None:
            return assignment
        for split in SPLITS:
            path = self.split_source / f"{split}.txt"
            if not path.is_file():
                continue
            for line in path.read_text(encoding="utf-8").splitlines():
                line = line.strip()
                if not line:
                    continue
                synset, _, model_id = line.partition("-")
                if model_id and synset == self.synset:
                    assignment[model_id] = split
        return assignment

    def _parse(self, entry: Any, i: int, splits: dict[str, str]) -> AnnotatedModel:
        where = f"{self.annotation_path}: model {i}"
        try:
            model_id = str(entry["model_id"])
            where += f" ({model_id})"
            rows = entry["keypoints"]
            xyz = np.array([k["xyz"] for k in rows], dtype=np.float64)
            ids = np.array([k["semantic_id"] for k in rows], dtype=np.int64)
            index = [k.get("pcd_info", {}).get("point_index") for k in rows]
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{where}: malformed annotation ({type(exc).__name__}: {exc})") from exc
        if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0 or not np.isfinite(xyz).all():
            raise DataError(f"{where}: keypoints must be finite (J, 3) with J >= 1; got shape {xyz.shape}")
        pcd_index = np.array(index, dtype=np.int64) if all(v is not None for v in index) else None
        return AnnotatedModel(model_id, splits.get(model_id), xyz, ids, pcd_index)

    def __len__(self) -> int:
        return len(self.models)

    def __repr__(self) -> str:
        return f"KeypointNet({str(self.root)!r}, {self.category!r}, {len(self)} models)"

    def get(self, model_id: str) -> AnnotatedModel:
        if model_id not in self._by_id:
            raise DataError(f"model {model_id} is not annotated in {self.annotation_path}")
        return self._by_id[model_id]

    def ids(self, split: str = "all") -> list[str]:
        """Model ids of a split (``"train"``, ``"val"``, ``"test"``) or ``"all"``, in file order."""
        if split == "all":
            return [m.model_id for m in self.models]
        if split not in SPLITS:
            raise InputError(f"split must be one of train, val, test, all; got {split!r}")
        if self.split_source is None:
            raise DataError(f"{self.root} has no splits/ folder; use split 'all'")
        return [m.model_id for m in self.models if m.split == split]

    def common_semantic_ids(self, min_fraction: float = 0.8, min_count: int = 7) -> np.ndarray:
        """The semantic ids the paper evaluates: "keypoints contained in at least 80% of models" (docs/method.md §8).

        The authors' rule: for n from the number of semantic ids down to ``min_count``, take the n most frequent ids
        (ties by smaller id) and keep the first n for which the models holding all of them are more than
        ``min_fraction`` of the annotated models.

        Returns
        -------
        ids : (n,) int64, sorted.
        """
        counts: dict[int, int] = {}
        for m in self.models:
            for c in set(m.semantic_ids.tolist()):
                counts[c] = counts.get(c, 0) + 1
        ranked = sorted(counts, key=lambda c: (-counts[c], c))
        sets = [set(m.semantic_ids.tolist()) for m in self.models]
        for n in range(len(ranked), min_count - 1, -1):
            chosen = set(ranked[:n])
            kept = sum(chosen <= s for s in sets) / len(sets)
            if kept > min_fraction:
                return np.array(sorted(chosen), dtype=np.int64)
        raise DataError(f"{self.annotation_path}: no {min_count} or more semantic ids are all present in more than "
                        f"{min_fraction:.0%} of the {len(sets)} models")

    def geometry_file(self, model_id: str, extra: Sequence[str | os.PathLike] = ()) -> tuple[Path, str] | None:
        """The geometry of a model and its frame: ``(path, "keypointnet")`` for the KeypointNet cloud or a ShapeNet v2
        mesh (the annotations' own frame), ``(path, "fitted")`` for another copy (registered by
        :func:`fit_annotation_frame`), or None. ``extra`` folders are searched for ``<synset>/points/<id>.pts``
        (ShapeNetPart), ``<synset>/<id>.<ext>`` and meshes under ``<synset>/<id>/``."""
        pcd = self.root / "pcds" / self.synset / f"{model_id}.pcd"
        if pcd.is_file():
            return pcd, "keypointnet"
        folders = [self.root / "models" / self.synset / model_id]
        for folder in folders:
            for v2 in (folder / "models" / "model_normalized.obj", folder / "model_normalized.obj"):
                if v2.is_file():
                    return v2, "keypointnet"
        for base in [self.root / "models", *map(Path, extra)]:
            found = _find_model_file(base / self.synset, model_id)
            if found is not None:
                return found, "fitted"
        return None


_GEOMETRY_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf", ".pcd", ".pts", ".xyz", ".npy", ".npz")


def _find_model_file(folder: Path, model_id: str) -> Path | None:
    for candidate in (folder / "points" / f"{model_id}.pts", *(folder / f"{model_id}{s}" for s in _GEOMETRY_SUFFIXES)):
        if candidate.is_file():
            return candidate
    sub = folder / model_id
    if sub.is_dir():
        meshes = sorted(p for p in sub.rglob("*") if p.suffix.lower() in _GEOMETRY_SUFFIXES[:6] and p.is_file())
        if meshes:
            return meshes[0]
    return None
