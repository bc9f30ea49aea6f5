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
REFERENCE §8, which is also ShapeNetPart's frame), then into the [-1, 1] box of its geometry by a
:class:`kpd.geometry.Normalizer` (REFERENCE §7: the authors normalise KeypointNet keypoints with the unit box of the
KeypointNet point cloud). Thresholds such as PCK@0.05 are in these units. A model trained on ModelNet (z up) sees the
shape rotated into its own frame (``MODELNET_TO_REFERENCE``) and its keypoints are rotated back.

Protocols
---------
:func:`pck_protocol` (paper Fig. 4), :func:`parts_protocol` (paper Table 1), :func:`das_protocol` (Skeleton Merger),
:func:`coverage_protocol` (SC3K), :func:`chamfer_protocol` (paper Fig. 7 on a bundle). Each returns a JSON-safe dict
with the protocol, its definition, the data used and the numbers; the metrics themselves are in :mod:`kpd.metrics`.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, NamedTuple, Sequence

import numpy as np
from scipy.spatial import cKDTree

from kpd.errors import DataError, InputError
from kpd.geometry import Normalizer, as_points, sample_surface
from kpd.io import Mesh, PointSet

__all__ = [
    "KEYPOINTNET_CATEGORIES",
    "KEYPOINTNET_TO_REFERENCE",
    "MODELNET_TO_REFERENCE",
    "FIT_CANDIDATES",
    "Similarity",
    "FrameFit",
    "fit_annotation_frame",
    "AnnotatedModel",
    "KeypointNet",
    "PartShape",
    "ShapeNetPart",
    "EvalShape",
    "Skipped",
    "keypointnet_shapes",
    "shapenetpart_shapes",
    "point_cloud_shapes",
    "ModelKeypoints",
    "FileKeypoints",
    "pck_protocol",
    "parts_protocol",
    "das_protocol",
    "coverage_protocol",
    "chamfer_protocol",
    "alignment_pairs",
]

log = logging.getLogger(__name__)

# KeypointNet's 16 categories: annotation file name -> ShapeNet synset.
KEYPOINTNET_CATEGORIES = {
    "airplane": "02691156", "bathtub": "02808440", "bed": "02818832", "bottle": "02876657", "cap": "02954340",
    "car": "02958343", "chair": "03001627", "guitar": "03467517", "helmet": "03513137", "knife": "03624134",
    "laptop": "03642806", "motorcycle": "03790512", "mug": "03797390", "skateboard": "04225987",
    "table": "04379243", "vessel": "04530566",
}
_ALIASES = {"motorbike": "motorcycle", "plane": "airplane", "boat": "vessel"}

# Row-vector convention everywhere: x_new = x @ M.T.
# The authors' axis fix of KeypointNet coordinates, (x, y, z) -> (-z, y, x) (REFERENCE §8): a rotation about y.
KEYPOINTNET_TO_REFERENCE = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
# ModelNet (z up, chair backs towards +y) -> reference (y up, backs towards -x): (x, y, z) -> (-y, z, -x).
MODELNET_TO_REFERENCE = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
_MIRROR_LAST = np.diag([1.0, 1.0, -1.0])
# Orthogonal maps tried when registering KeypointNet annotations to a mesh of unknown frame (y up in both):
# the authors' axis fix, the same with the last axis mirrored (ambiguous for mirror-symmetric shapes, SOURCES.md),
# and the ShapeNet v2 frame itself (with either sign of x).
FIT_CANDIDATES = {
    "keypointnet-to-reference": KEYPOINTNET_TO_REFERENCE,
    "keypointnet-to-reference-mirrored": _MIRROR_LAST @ KEYPOINTNET_TO_REFERENCE,
    "identity": np.eye(3),
    "identity-mirrored": np.diag([-1.0, 1.0, 1.0]),
}
SPLITS = ("train", "val", "test")


# --- frames ------------------------------------------------------------------------------------------------------


class Similarity(NamedTuple):
    """``x -> scale * x @ matrix.T + translation`` on (N, 3) rows; ``matrix`` is orthogonal (a mirror is allowed).

    scale : float; matrix : (3, 3) float64; translation : (3,) float64.
    """

    scale: float
    matrix: np.ndarray
    translation: np.ndarray

    @classmethod
    def identity(cls) -> "Similarity":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def linear(cls, matrix: Any) -> "Similarity":
        return cls(1.0, np.asarray(matrix, dtype=np.float64), np.zeros(3))

    def apply(self, points: Any) -> np.ndarray:
        """(N, 3) -> (N, 3)."""
        return self.scale * (as_points(points, min_count=0) @ self.matrix.T) + self.translation

    def inverse(self) -> "Similarity":
        return Similarity(1.0 / self.scale, self.matrix.T, -(self.translation @ self.matrix) / self.scale)

    def then(self, other: "Similarity") -> "Similarity":
        """The map ``other(self(x))``."""
        return Similarity(other.scale * self.scale, other.matrix @ self.matrix,
                          other.scale * (self.translation @ other.matrix.T) + other.translation)

    def to_dict(self) -> dict:
        return {"scale": float(self.scale), "matrix": self.matrix.tolist(), "translation": self.translation.tolist()}


class FrameFit(NamedTuple):
    """Result of :func:`fit_annotation_frame`.

    transform : Similarity, KeypointNet coordinates -> the geometry's coordinates.
    candidate : name of the orthogonal map chosen (a key of :data:`FIT_CANDIDATES`).
    distances : (J,) float64, distance of each mapped keypoint to the nearest surface point (geometry units).
    residuals : {candidate: mean distance} for every candidate tried.
    """

    transform: Similarity
    candidate: str
    distances: np.ndarray
    residuals: dict


def fit_annotation_frame(keypoints: Any, surface: Any, *, candidates: dict | None = None,
                         source_diagonal: float = 1.0, prefer_first: float = 0.1, shift: float = 0.1,
                         iterations: int = 50) -> FrameFit:
    """Register KeypointNet annotations to another copy of the model (a mesh re-normalised elsewhere).

    KeypointNet models are ShapeNet v2 models, normalised to a unit bounding-box diagonal; a copy of the same model
    normalised elsewhere differs by an axis change, a scale and a translation. For each orthogonal map Q of
    ``candidates`` the keypoints are rotated by Q, scaled by ``diagonal(surface) / source_diagonal`` and translated:
    starting from matching bounding-box centres (and 26 shifts of ``shift`` times the diagonal around it), the
    translation is refined by closest-point iterations (ICP, translation only) towards the surface points. The
    candidate with the lowest mean distance wins; the first candidate is kept unless another one is better by more
    than ``prefer_first`` (relative), because mirror-symmetric shapes fit a mirrored map almost as well (SOURCES.md).

    Parameters
    ----------
    keypoints : (J, 3) float64, KeypointNet coordinates (J >= 3).
    surface : (N, 3) float64, dense points on the other copy's surface (e.g. 20,000 area-weighted samples).
    candidates : {name: (3, 3) orthogonal}, default :data:`FIT_CANDIDATES`.
    source_diagonal : bounding-box diagonal of the KeypointNet model (1 for ShapeNet v2).

    Returns
    -------
    FrameFit
    """
    kp = as_points(keypoints, "keypoints", min_count=3)
    pts = as_points(surface, "surface", min_count=4)
    candidates = FIT_CANDIDATES if candidates is None else candidates
    if not candidates:
        raise InputError("fit_annotation_frame needs at least one candidate map")
    tree = cKDTree(pts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = float(np.linalg.norm(hi - lo)) / source_diagonal
    grid = np.stack(np.meshgrid(*[[-shift, 0.0, shift]] * 3, indexing="ij"), axis=-1).reshape(-1, 3) * scale
    fits = {}
    for name, matrix in candidates.items():
        q = np.asarray(matrix, dtype=np.float64)
        y = scale * (kp @ q.T)  # (J, 3)
        start = (lo + hi) / 2 - (y.min(axis=0) + y.max(axis=0)) / 2
        best = None
        for offset in grid:
            t = start + offset
            for _ in range(iterations):
                _, nearest = tree.query(y + t)
                t_new = (pts[nearest] - y).mean(axis=0)
                done = np.abs(t_new - t).max() < 1e-10 * scale
                t = t_new
                if done:
                    break
            d, _ = tree.query(y + t)
            if best is None or d.mean() < best[0]:
                best = (float(d.mean()), t, d)
        fits[name] = (best[0], Similarity(scale, q, best[1]), best[2])
    names = list(fits)
    chosen = min(names, key=lambda n: fits[n][0])
    if fits[names[0]][0] <= (1.0 + prefer_first) * fits[chosen][0]:
        chosen = names[0]
    return FrameFit(fits[chosen][1], chosen, fits[chosen][2], {n: f[0] for n, f in fits.items()})


# --- KeypointNet ---------------------------------------------------------------------------------------------------


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
        """The semantic ids the paper evaluates: "keypoints contained in at least 80% of models" (REFERENCE §8).

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


# --- ShapeNetPart ----------------------------------------------------------------------------------------------------


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


# --- shapes in the evaluation frame ---------------------------------------------------------------------------------


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


# --- keypoint sources -------------------------------------------------------------------------------------------------


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
        raise DataError(f"every shape needs the same number of keypoints; got "
                        + ", ".join(f"{n} ({first[n]})" for n in sorted(counts)))
    return [s for s, _ in kept], np.stack([k for _, k in kept]), skipped


# --- protocols ------------------------------------------------------------------------------------------------------


def _skipped_json(skipped: list[Skipped]) -> dict:
    reasons: dict[str, int] = {}
    for s in skipped:
        key = "no geometry" if s.reason == "no geometry" else s.reason.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    return {"count": len(skipped), "reasons": reasons, "shapes": [s._asdict() for s in skipped]}


def _few_shapes(n: int, enough: int = 20) -> list[str]:
    """A note for the result when a protocol ran on too few shapes to mean much."""
    return [f"only {n} scored shape{'s' if n != 1 else ''}: this checks the protocol, it is not a benchmark number"] \
        if n < enough else []


def _stats(values: np.ndarray) -> dict:
    values = np.asarray(values, dtype=np.float64)
    return {"mean": float(values.mean()), "median": float(np.median(values)), "std": float(values.std()),
            "min": float(values.min()), "max": float(values.max())}


def pck_protocol(dataset: KeypointNet, source, *, geometry_dirs: Sequence[str | os.PathLike] = (),
                 threshold: float = 0.05, ridge: float = 1e-3, min_fraction: float = 0.8,
                 fit_split: str = "train", test_split: str = "test",
                 progress: Callable[[Iterable], Iterable] | None = None) -> dict:
    """PCK@``threshold`` of annotated keypoints regressed from unsupervised ones (paper Fig. 4;
    :func:`kpd.metrics.regression_pck`), on a KeypointNet category.

    The annotated keypoints are the category's common semantic ids (:meth:`KeypointNet.common_semantic_ids`); models
    lacking one of them are left out. The regressor is fitted on ``fit_split`` and scored on ``test_split``
    (KeypointNet's own splits; the paper re-sampled them to follow ShapeNet's, which were not released).
    """
    from kpd.metrics import regression_pck

    common = dataset.common_semantic_ids(min_fraction=min_fraction)
    sets: dict[str, tuple] = {}
    skipped_all: list[Skipped] = []
    for split in (fit_split, test_split):
        shapes, skipped = keypointnet_shapes(dataset, split, geometry_dirs=geometry_dirs, progress=progress)
        complete = []
        for s in shapes:
            have = set(s.semantic_ids.tolist())
            if set(common.tolist()) <= have:
                complete.append(s)
            else:
                skipped.append(Skipped(s.model_id, f"lacks semantic ids {sorted(set(common.tolist()) - have)}"))
        skipped_all += skipped
        if not complete:
            raise DataError(f"no {split} model of {dataset.category!r} has geometry and all common semantic ids "
                            f"({len(skipped)} left out; {_skipped_json(skipped)['reasons']})")
        kept, keypoints, missing = _predict(source, complete)
        skipped_all += missing
        annotated = np.stack([s.keypoints[[int(np.flatnonzero(s.semantic_ids == c)[0]) for c in common]]
                              for s in kept])
        sets[split] = (kept, keypoints, annotated)
    skipped_all = list(dict.fromkeys(skipped_all))  # once each when the two splits overlap
    train, test = sets[fit_split], sets[test_split]
    if train[1].shape[1] != test[1].shape[1]:
        raise DataError(f"the source gave {train[1].shape[1]} keypoints on {fit_split} and {test[1].shape[1]} on "
                        f"{test_split}")
    result = regression_pck(train[1], train[2], test[1], test[2], threshold=threshold, ridge=ridge)
    notes = []
    overlap = {s.model_id for s in train[0]} & {s.model_id for s in test[0]}
    if overlap:
        notes.append(f"{len(overlap)} test shapes are also fit shapes: the score is optimistic")
    if len(train[0]) <= 3 * train[1].shape[1]:
        notes.append(f"{len(train[0])} fit shapes for {3 * train[1].shape[1] + 1} regressor inputs: the map is "
                     f"underdetermined and the score says little about the keypoints")
    notes += _few_shapes(len(test[0]))
    for note in notes:
        log.info("pck: %s", note)
    return {
        "protocol": "pck",
        "definition": f"PCK@{threshold:g} by linear regression (KeypointDeformer Fig. 4, after Thewlis et al. 2017): "
                      f"a ridge-regularised affine map (relative ridge {ridge:g}) from the flattened unsupervised "
                      f"keypoints to the annotated ones, fitted on {fit_split}; a regressed keypoint on {test_split} "
                      f"is correct within {threshold:g} (Euclidean) in the [-1, 1] box of the KeypointNet cloud, after "
                      f"the authors' axis fix",
        "data": {
            "dataset": "KeypointNet", "root": str(dataset.root), "category": dataset.category,
            "synset": dataset.synset, "annotations": str(dataset.annotation_path),
            "annotated_models": len(dataset), "common_semantic_ids": common.tolist(),
            "min_fraction": min_fraction,
            "fit": {"split": fit_split, "shapes": [s.describe() for s in train[0]]},
            "test": {"split": test_split, "shapes": [s.describe() for s in test[0]]},
            "skipped": _skipped_json(skipped_all),
        },
        "keypoints": source.describe(),
        "settings": {"threshold": threshold, "ridge": ridge},
        "results": {
            "pck": result.pck,
            "fit_shapes": len(train[0]),
            "test_shapes": len(test[0]),
            "unsupervised_keypoints": int(train[1].shape[1]),
            "annotated_keypoints": int(len(common)),
            "per_semantic_id": {str(c): float(v) for c, v in zip(common, result.per_keypoint)},
            "error": _stats(result.errors),
            "per_shape": [{"id": s.model_id, "pck": float(np.mean(e <= threshold)), "mean_error": float(e.mean())}
                          for s, e in zip(test[0], result.errors)],
        },
        "notes": notes,
    }


def parts_protocol(dataset: ShapeNetPart, category: str, source, *, split: str = "test", radius: float = 0.05,
                   progress: Callable[[Iterable], Iterable] | None = None) -> dict:
    """Semantic part correspondence (paper Table 1, supp. Fig. 12; :func:`kpd.metrics.part_correspondence`) on a
    ShapeNetPart category."""
    from kpd.metrics import part_correspondence

    shapes = shapenetpart_shapes(dataset, category, split, progress=progress)
    kept, keypoints, missing = _predict(source, shapes)
    result = part_correspondence(keypoints, [s.points for s in kept], [s.labels for s in kept], radius=radius)
    parts = [str(p) for p in result.parts]
    return {
        "protocol": "parts",
        "definition": f"semantic part correspondence (KeypointDeformer Table 1): keypoint k of a shape is associated "
                      f"with every part having a labelled point within {radius:g} in the shape's [-1, 1] box; "
                      f"frequency[k, p] = fraction of shapes in which k is associated with p; score = mean over "
                      f"keypoints of max over parts (the paper's); part_score = mean over parts of max over keypoints "
                      f"(the reverse reduction)",
        "data": {"dataset": "ShapeNetPart", "root": str(dataset.root),
                 "category": dataset.name(dataset.synset(category)), "synset": dataset.synset(category), "split": split,
                 "shapes": [s.describe() for s in kept], "skipped": _skipped_json(missing)},
        "keypoints": source.describe(),
        "settings": {"radius": radius},
        "results": {
            "score": result.score,
            "part_score": result.part_score,
            "shapes": len(kept),
            "keypoints": int(keypoints.shape[1]),
            "parts": parts,
            "frequency": [[float(v) for v in row] for row in result.frequency],
            "best_part": [int(p) for p in result.best_part],
            "associated": [float(v) for v in result.associated],
        },
        "notes": _few_shapes(len(kept)),
    }


def das_protocol(dataset: KeypointNet, source, *, split: str = "all", geometry_dirs: Sequence[str | os.PathLike] = (),
                 progress: Callable[[Iterable], Iterable] | None = None) -> dict:
    """Dual Alignment Score of Skeleton Merger (:func:`kpd.metrics.dual_alignment_score`) on a KeypointNet category,
    with every annotated keypoint of each model (the authors' script scores all models of the annotation file:
    ``split="all"``)."""
    from kpd.metrics import dual_alignment_score

    shapes, skipped = keypointnet_shapes(dataset, split, geometry_dirs=geometry_dirs, progress=progress)
    if not shapes:
        raise DataError(f"no {split} model of {dataset.category!r} has geometry ({len(skipped)} left out)")
    kept, keypoints, missing = _predict(source, shapes)
    result = dual_alignment_score(keypoints, [s.keypoints for s in kept], [s.semantic_ids for s in kept])
    return {
        "protocol": "das",
        "definition": "Dual Alignment Score (Skeleton Merger, Shi et al. CVPR 2021, eval_keypointnet.py): forward = "
                      "agreement over all ordered pairs of shapes of the semantic id of the annotation nearest to "
                      "each predicted keypoint; backward = per semantic id, agreement over pairs of its annotations of "
                      "the index of the nearest predicted keypoint, averaged over ids; DAS = their mean",
        "data": {"dataset": "KeypointNet", "root": str(dataset.root), "category": dataset.category,
                 "synset": dataset.synset, "annotations": str(dataset.annotation_path), "split": split,
                 "shapes": [s.describe() for s in kept], "skipped": _skipped_json(skipped + missing)},
        "keypoints": source.describe(),
        "settings": {},
        "results": {"das": result.score, "forward": result.forward, "backward": result.backward,
                    "shapes": len(kept), "keypoints": int(keypoints.shape[1])},
        "notes": _few_shapes(len(kept)),
    }


def _unit_sphere(points: np.ndarray, keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SC3K's ``normalize_pc``: centre on the centroid, divide by the largest radius (applied to both)."""
    center = points.mean(axis=0)
    radius = float(np.linalg.norm(points - center, axis=1).max())
    return (points - center) / radius, (keypoints - center) / radius


def coverage_protocol(root: str | os.PathLike, category: str, source, *, split: str = "all",
                      threshold: float = 0.05,
                      progress: Callable[[Iterable], Iterable] | None = None) -> dict:
    """Coverage and inclusivity of SC3K (:func:`kpd.metrics.keypoint_coverage`,
    :func:`kpd.metrics.keypoint_inclusivity`) on the point clouds of a KeypointNet or ShapeNetPart category, each
    cloud and its keypoints normalised as SC3K does (centroid, unit largest radius)."""
    from kpd.metrics import keypoint_coverage, keypoint_inclusivity

    shapes, kind = point_cloud_shapes(root, category, split, progress=progress)
    kept, keypoints, missing = _predict(source, shapes)
    cov, inc = [], []
    for s, k in zip(kept, keypoints):
        pts, kp = _unit_sphere(s.points, k)
        cov.append(keypoint_coverage(kp, pts))
        inc.append(keypoint_inclusivity(kp, pts, threshold))
    return {
        "protocol": "coverage",
        "definition": f"SC3K (Zohaib and Del Bue, ICCV 2023, metrics.py): per shape, cloud and keypoints centred on "
                      f"the cloud's centroid and scaled to unit largest radius; coverage = max(0, 1 - |d(cloud) - "
                      f"d(keypoints)| / d(cloud)) with d the bounding-box diagonal; inclusivity = fraction of "
                      f"keypoints closer than {threshold:g} to the cloud; both averaged over shapes (SC3K prints x100)",
        "data": {"dataset": kind, "root": str(root), "category": category, "split": split,
                 "shapes": [s.describe() for s in kept], "skipped": _skipped_json(missing)},
        "keypoints": source.describe(),
        "settings": {"threshold": threshold},
        "results": {"coverage": float(np.mean(cov)), "inclusivity": float(np.mean(inc)), "shapes": len(kept),
                    "keypoints": int(keypoints.shape[1]),
                    "per_shape": [{"id": s.model_id, "coverage": c, "inclusivity": i}
                                  for s, c, i in zip(kept, cov, inc)]},
        "notes": _few_shapes(len(kept)),
    }


def alignment_pairs(n: int, count: int, seed: int = 0) -> np.ndarray:
    """Up to ``count`` seeded, distinct (source, target) index pairs over ``n`` shapes, source != target:
    (P, 2) int64 with P = min(count, n (n - 1)).

    No pair appears twice (a small test split cannot pass a few pairs off as many): the seeded draws are the same as
    before duplicates were dropped, so a draw without repeats is unchanged; repeats are replaced by further draws of
    the same generator, and when ``count`` exceeds the n (n - 1) ordered pairs every pair is used once (callers
    report the shortfall). The same pairs as the training evaluation (``kpd.train.evaluate.fixed_pairs``), without
    importing torch.
    """
    if n < 2:
        raise DataError(f"alignment needs at least 2 shapes; got {n}")
    total = n * (n - 1)
    want = min(int(count), total)
    rng = np.random.default_rng([seed, 3])
    chosen: dict[tuple[int, int], None] = {}
    size = int(count)
    while len(chosen) < want:
        source = rng.integers(n, size=size)
        target = (source + rng.integers(1, n, size=size)) % n
        for pair in zip(source.tolist(), target.tolist()):
            chosen.setdefault(pair)
            if len(chosen) == want:
                break
        size = max(16, want - len(chosen))
        if len(chosen) < want and want == total and len(chosen) > 0.9 * total:  # the last few: take them in order
            for pair in ((s, t) for s in range(n) for t in range(n) if s != t):
                chosen.setdefault(pair)
    return np.array(list(chosen)[:want], dtype=np.int64).reshape(-1, 2)


# fewer test shapes than this make a score that says little; it is flagged in the result and on the console
FEW_TEST_SHAPES = 10


def pair_notes(n: int, requested: int, used: int, split_source: str) -> list[str]:
    """Loud notes for an alignment score over few shapes or fewer distinct pairs than asked for."""
    notes = []
    if used < requested:
        notes.append(f"only {used} distinct pairs exist among {n} test shapes; {requested} were asked for, each pair "
                     "is scored once")
    if n < FEW_TEST_SHAPES:
        notes.append(f"only {n} test shapes ({split_source}): the score says little about the category")
    return notes


def chamfer_protocol(model: Any, root: str | os.PathLike, category: str | None = None, *, pairs: int = 200,
                     seed: int = 0, split_file: str | os.PathLike | None = None,
                     progress: Callable[[Iterable], Iterable] | None = None) -> dict:
    """The paper's Fig. 7 alignment protocol on a bundle, reported like ``kpd eval alignment`` does for a run.

    Test shapes come from :func:`kpd.data.discover` (ModelNet, ShapeNet or a flat folder); ``pairs`` seeded pairs
    (:func:`alignment_pairs`) of distinct test shapes. For each shape the model sees its seeded point sample in its
    own [-1, 1] frame (:meth:`kpd.runtime.Model.predict`); the source's sample points are deformed through the
    source's rig (cage, masked influence W, MVC: ``x* = MVC(x; c) (c + W^T (p_target - p_source))``) and compared with
    the target's sample by :func:`kpd.metrics.alignment_chamfer` (REFERENCE §6), x1e3, next to no deformation.
    """
    from kpd.data import discover
    from kpd.io import read_mesh
    from kpd.metrics import alignment_chamfer
    from kpd.mvc import mvc_weights

    data = discover(root, category, split_file=split_file)
    test = data.splits["test"]
    if len(test) < 2:
        raise DataError(f"alignment needs at least 2 test shapes in {root}; got {len(test)}")
    index = alignment_pairs(len(test), pairs, seed)
    used = sorted(set(index.ravel().tolist()))
    meshes, predictions, skipped = {}, {}, []
    for i in (progress(used) if progress else used):
        try:
            meshes[i] = read_mesh(test[i].path)
            predictions[i] = model.predict(meshes[i], seed=seed)
        except InputError as exc:
            skipped.append(Skipped(test[i].name, str(exc)))
    if skipped:
        raise DataError(f"{len(skipped)} test meshes cannot be used (first: {skipped[0].model_id}: "
                        f"{skipped[0].reason})")
    deformers = {}
    none, scores = [], []
    for s, t in index:
        if s not in deformers:
            rig = model.rig(meshes[s], seed=seed, prediction=predictions[s], straighten=False)  # cage and W only
            weights = mvc_weights(predictions[s].points, rig.cage.vertices, rig.cage.faces)  # (N, C)
            deformers[s] = (weights, rig.cage.vertices, rig.influence)
        weights, cage, influence = deformers[s]
        offsets = predictions[t].keypoints - predictions[s].keypoints  # (K, 3), model frame
        deformed = weights @ (cage + influence.T @ offsets)
        none.append(alignment_chamfer(predictions[s].points, predictions[t].points))
        scores.append(alignment_chamfer(deformed, predictions[t].points))
    none, scores = np.array(none), np.array(scores)
    notes = pair_notes(len(test), pairs, len(index), data.split_source)
    return {
        "protocol": "chamfer",
        "notes": notes,
        "definition": "Fig. 7: seeded pairs of distinct test shapes; the model's point sample of the source deformed "
                      "by the bundle's rig to the target's keypoints; chamfer (squared, mean, both directions, "
                      "REFERENCE §6) to the target's sample in the [-1, 1] frame, x1e3",
        "data": {"root": str(root), "layout": data.layout, "category": data.category, "split_source": data.split_source,
                 "test_shapes": len(test), "test_names": [f.name for f in test]},
        "keypoints": {"source": "model", "bundle": str(model.bundle.path), "category": model.category,
                      "keypoints": model.num_keypoints, "seed": seed},
        "settings": {"pairs": int(len(index)), "requested_pairs": int(pairs), "seed": int(seed),
                     "points": model.point_count},
        "results": {
            "chamfer_x1e3": {"model": _stats(1e3 * scores), "no_deformation": _stats(1e3 * none)},
            "ratio_to_no_deformation": float(scores.mean() / none.mean()),
            "per_pair": [{"source": test[s].name, "target": test[t].name, "model": float(1e3 * a),
                          "no_deformation": float(1e3 * b)} for (s, t), a, b in zip(index, scores, none)],
        },
    }
