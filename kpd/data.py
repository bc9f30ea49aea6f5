"""Datasets for training: find a category's meshes, split them, and sample them once into a cache.

Layouts (``discover``):

- **ModelNet**: ``ROOT/<class>/{train,test}/*.off|ply`` (the folder split is used).
- **ShapeNet v1**: ``ROOT/<synset>/<id>/model.obj``; **ShapeNet v2**:
  ``ROOT/<synset>/<id>/models/model_normalized.obj``.
  The category is a synset id or a common name (``chair``). The split comes from the official ``all.csv``
  (``--split-file``, or ``ROOT/all.csv`` when present).
- **Flat folder**: mesh files in ``ROOT/<category>/`` (or ``ROOT`` itself), with an optional split file;
  ``train.txt`` / ``val.txt`` / ``test.txt`` beside the meshes are used as the split when no split file is given.

Split files: the ShapeNet csv (columns ``modelId`` and ``split``),
JSON ``{"train": [names], "val": [...], "test": [...]}``,
a folder with ``train.txt`` / ``val.txt`` / ``test.txt`` (one name per line; KeypointNet's ``<synset>-<id>`` works;
one of those files given by itself stands for its folder),
or text lines ``name split``. Shapes are named by model id (ShapeNet) or file stem. When there is no validation split it
is carved from train with a seed (``val_fraction``); a layout with no split at all also has its test split carved.

The sample cache (``ingest``): every mesh is read once, normalised to the [-1, 1] box by a
:class:`kpd.geometry.Normalizer` fitted on its **mesh vertices** (those referenced by triangles; docs/method.md §7), and
sampled ``samples`` times independently (``points`` surface points with normals, area-weighted). For each sample the
cache also holds what needs no gradient and costs time to compute: the cage fitted to the sample's points (authors'
rule, docs/method.md §4) and the MVC weights of the sample's points with respect to that cage (float32). Files are
``.npz`` (no pickle) named ``<sha256 of the file>_<settings key>.npz`` under ``CACHE/samples``; the cache folder
defaults to ``$KPD_CACHE`` or ``~/.cache/kpd``. Meshes that cannot be read are listed with the reason and skipped.
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kpd.errors import DataError, InputError, KpdError
from kpd.io import MESH_FORMATS

__all__ = [
    "MESH_SUFFIXES",
    "SHAPENET_SYNSETS",
    "ShapeFile",
    "Category",
    "discover",
    "read_split_file",
    "SampleSettings",
    "Skipped",
    "ShapeSamples",
    "default_cache_dir",
    "file_digest",
    "sample_mesh",
    "ingest",
    "load_samples",
    "PreparedData",
    "prepare",
]

log = logging.getLogger(__name__)

MESH_SUFFIXES = MESH_FORMATS  # the formats kpd.io reads; the old name, kept importable
CACHE_VERSION = 1

# Common ShapeNetCore category names (taxonomy.json) -> synset id.
SHAPENET_SYNSETS = {
    "airplane": "02691156", "bag": "02773838", "bathtub": "02808440", "bed": "02818832", "bench": "02828884",
    "bookshelf": "02871439", "bottle": "02876657", "bowl": "02880940", "bus": "02924116", "cabinet": "02933112",
    "camera": "02942699", "can": "02946921", "cap": "02954340", "car": "02958343", "chair": "03001627",
    "clock": "03046257", "display": "03211117", "earphone": "03261776", "guitar": "03467517",
    "helmet": "03513137", "knife": "03624134", "lamp": "03636649", "laptop": "03642806", "loudspeaker": "03691459",
    "motorbike": "03790512", "mug": "03797390", "pistol": "03948459", "rifle": "04090263", "rocket": "04099429",
    "skateboard": "04225987", "sofa": "04256520", "table": "04379243", "telephone": "04401088", "vessel": "04530566",
}
SPLITS = ("train", "val", "test")
_SPLIT_ALIASES = {"train": "train", "training": "train", "val": "val", "valid": "val", "validation": "val",
                  "test": "test", "testing": "test"}


class ShapeFile(NamedTuple):
    """One mesh of the category: ``name`` (model id or file stem) and ``path``."""

    name: str
    path: Path


@dataclass
class Category:
    """The meshes of one category, split into ``train`` / ``val`` / ``test`` lists of :class:`ShapeFile`."""

    root: Path
    layout: str
    category: str
    splits: dict[str, list[ShapeFile]] = field(default_factory=dict)
    split_source: str = ""

    def to_dict(self) -> dict:
        return {"root": str(self.root), "layout": self.layout, "category": self.category,
                "split_source": self.split_source, "counts": {s: len(self.splits.get(s, [])) for s in SPLITS}}


def _mesh_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)


def _is_name_list(path: Path) -> bool:
    """A list of names, one per line (not the two-column 'name split' format)."""
    try:
        lines = [s.replace(",", " ").split() for s in path.read_text().splitlines() if s.strip()]
    except (OSError, UnicodeDecodeError):
        return False
    return all(len(parts) == 1 for parts in lines)


def _split_lists(folder: Path) -> bool:
    return any((folder / f"{s}.txt").is_file() for s in SPLITS)


def read_split_file(path: str | os.PathLike) -> dict[str, str]:
    """Read a split description: name -> ``train`` / ``val`` / ``test`` (formats in the module docstring).

    A ``train.txt``, ``val.txt`` or ``test.txt`` given by itself (one name per line) stands for the lists of its
    folder: its siblings among those three are read with it.
    """
    path = Path(path)
    result: dict[str, str] = {}
    if path.is_file() and path.name.lower() in {f"{s}.txt" for s in SPLITS} and _is_name_list(path):
        path = path.parent

    def put(name: str, split: str) -> None:
        key = _SPLIT_ALIASES.get(split.strip().lower())
        if key is None:
            raise DataError(f"split file {path}: unknown split {split!r} for {name!r}; expected one of {SPLITS}")
        name = name.strip()
        if "-" in name and name.split("-", 1)[0].isdigit() and len(name.split("-", 1)[0]) == 8:
            name = name.split("-", 1)[1]  # KeypointNet's <synset>-<id>
        result[name] = key

    if path.is_dir():
        found = False
        for split in SPLITS:
            f = path / f"{split}.txt"
            if f.is_file():
                found = True
                for line in f.read_text().splitlines():
                    if line.strip():
                        put(line, split)
        if not found:
            raise DataError(f"split folder {path} has none of train.txt, val.txt, test.txt")
        return result
    if not path.is_file():
        raise DataError(f"split file {path} does not exist")
    text = path.read_text()
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataError(f"split file {path} is not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise DataError(f"split file {path} must hold an object {{split: [names]}}; got {type(data).__name__}")
        for split, names in data.items():
            for name in names:
                put(str(name), split)
        return result
    if path.suffix.lower() == ".csv":
        rows = list(csv.DictReader(text.splitlines()))
        if not rows or "split" not in rows[0] or "modelId" not in rows[0]:
            raise DataError(f"split csv {path} needs the columns 'modelId' and 'split'")
        for row in rows:
            put(row["modelId"], row["split"])
        return result
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.replace(",", " ").split()
        if not parts:
            continue
        if len(parts) != 2:
            raise DataError(f"split file {path} line {number}: expected 'name split'; got {line!r}")
        put(parts[0], parts[1])
    return result


def _carve(files: list[ShapeFile], fraction: float,
           rng: np.random.Generator) -> tuple[list[ShapeFile], list[ShapeFile]]:
    """Split off ``round(fraction * len)`` files (at least one when fraction > 0 and there are two or more)."""
    if fraction <= 0 or len(files) < 2:
        return files, []
    count = min(len(files) - 1, max(1, int(round(fraction * len(files)))))
    order = rng.permutation(len(files))
    picked = set(order[:count].tolist())
    keep = [f for i, f in enumerate(files) if i not in picked]
    carved = [f for i, f in enumerate(files) if i in picked]
    return keep, carved


def discover(root: str | os.PathLike, category: str | None = None, *, split_file: str | os.PathLike | None = None,
             val_fraction: float = 0.1, test_fraction: float = 0.1, seed: int = 0) -> Category:
    """Find a category's meshes and split them.

    Parameters
    ----------
    root : the dataset folder.
    category : ModelNet class, ShapeNet synset id or name, or a sub-folder of a flat dataset; None uses ``root``.
    split_file : overrides the layout's split (see :func:`read_split_file`).
    val_fraction : share of train carved into the validation split when the split has none.
    test_fraction : share carved into test when nothing defines a test split.
    seed : for the carving.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"data folder {root} does not exist")
    rng = np.random.default_rng([int(seed), 7])
    splits: dict[str, list[ShapeFile]] = {s: [] for s in SPLITS}
    pool: list[ShapeFile] = []
    split_source = ""
    name = category or root.name
    folder = root / category if category else root

    if (folder / "train").is_dir() or (folder / "test").is_dir():
        layout = "modelnet"
        for split in ("train", "test"):
            if (folder / split).is_dir():
                splits[split] = [ShapeFile(p.stem, p) for p in _mesh_files(folder / split)]
        split_source = "folders"
    else:
        synset = SHAPENET_SYNSETS.get(category.lower(), category) if category else None
        shapenet_dir = root / synset if synset else None
        layout = ""
        if shapenet_dir is not None and shapenet_dir.is_dir():
            models = sorted(p for p in shapenet_dir.iterdir() if p.is_dir())
            v1 = [ShapeFile(p.name, p / "model.obj") for p in models if (p / "model.obj").is_file()]
            v2 = [ShapeFile(p.name, p / "models" / "model_normalized.obj") for p in models
                  if (p / "models" / "model_normalized.obj").is_file()]
            if v1 or v2:
                layout = "shapenet-v1" if len(v1) >= len(v2) else "shapenet-v2"
                pool = v1 if layout == "shapenet-v1" else v2
                folder = shapenet_dir
                if split_file is None and (root / "all.csv").is_file():
                    split_file = root / "all.csv"
        if not layout:
            if not folder.is_dir():
                raise DataError(f"category {category!r} not found in {root}: no folder {folder}, no ShapeNet synset "
                                f"folder, and no ModelNet train/test folders")
            layout = "flat"
            pool = [ShapeFile(p.stem, p) for p in _mesh_files(folder)]
            if split_file is None and _split_lists(folder):  # train.txt / val.txt / test.txt beside the meshes
                split_file = folder

    if split_file is not None:
        assignment = read_split_file(split_file)
        everything = pool or [f for s in SPLITS for f in splits[s]]
        splits = {s: [] for s in SPLITS}
        unassigned = 0
        for f in everything:
            split = assignment.get(f.name)
            if split is None:
                unassigned += 1
            else:
                splits[split].append(f)
        if unassigned:
            log.info("%d of %d shapes are not in the split file %s and are left out", unassigned, len(everything),
                     split_file)
        split_source = str(split_file)
    elif pool:
        splits["train"], splits["test"] = _carve(pool, test_fraction, rng)
        split_source = f"carved (test {test_fraction:g}, seed {seed})"

    if not splits["val"] and splits["train"]:
        splits["train"], splits["val"] = _carve(splits["train"], val_fraction, rng)
        split_source += f"; val carved from train ({val_fraction:g}, seed {seed})"
    total = sum(len(v) for v in splits.values())
    if total == 0:
        raise DataError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) found for category {name!r} in {root}")
    return Category(root=root, layout=layout, category=name, splits=splits, split_source=split_source)


@dataclass(frozen=True)
class SampleSettings:
    """What a cached sample depends on, besides the mesh file.

    - points : N, surface points per sample.
    - samples : independent samples per mesh.
    - cage_level / cage_radius : the icosphere template (level 1 = 42 vertices).
    - cage_distance / cage_iterations / cage_step / enclose : :func:`kpd.cage.fit_cage` settings (docs/method.md §4).
    - weights : also store the MVC weights of the sample points (else training computes them once with torch).
    - outer : sample the outer surface only (:func:`kpd.geometry.sample_surface` with ``outer=True``): drop points on
      faces inside the shape, where overlapping or touching pieces meet (convex decompositions, CAD parts).
    """

    points: int = 1024
    samples: int = 4
    cage_level: int = 1
    cage_radius: float = 1.4
    cage_distance: float = 0.4
    cage_iterations: int = 100
    cage_step: float = 0.01
    enclose: bool = False
    weights: bool = True
    outer: bool = False

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "SampleSettings":
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})

    def key(self) -> str:
        values = self.to_dict()
        if not values["outer"]:  # the key of every setting that predates the option stays the same
            del values["outer"]
        text = json.dumps({"version": CACHE_VERSION, **values}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


class Skipped(NamedTuple):
    """A mesh left out of the data, and why."""

    path: str
    reason: str


def default_cache_dir() -> Path:
    """``$KPD_CACHE`` or ``~/.cache/kpd``."""
    env = os.environ.get("KPD_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "kpd"


def file_digest(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sample_mesh(path: str | os.PathLike, settings: SampleSettings, digest: str, *,
                threads: int | None = None) -> dict[str, np.ndarray]:
    """Read, normalise and sample one mesh, fit a cage per sample and compute MVC weights (the cache content).

    The randomness is seeded by the file's digest, so a cache entry is a function of its key.

    Returns
    -------
    arrays : ``points`` (R, N, 3) float32, ``normals`` (R, N, 3) float32, ``cage_vertices`` (R, C, 3) float64,
        ``cage_faces`` (F, 3) int64, ``weights`` (R, N, C) float32 (only when ``settings.weights``), ``center`` (3,),
        ``scale`` (), ``vertex_count``, ``triangle_count``.
    """
    from kpd.cage import fit_cage, icosphere
    from kpd.geometry import Normalizer, sample_surface
    from kpd.io import read_mesh
    from kpd.mvc import mvc_weights

    mesh = read_mesh(path)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    if len(triangles) == 0:
        raise InputError(f"{path} has no triangles")
    used = np.unique(triangles)
    normalizer = Normalizer().fit(mesh.vertices[used])
    vertices = normalizer.apply(mesh.vertices)
    template = icosphere(settings.cage_level, settings.cage_radius)
    rng = np.random.default_rng([int(digest[:15], 16), CACHE_VERSION])
    points, normals, cages, weights = [], [], [], []
    for _ in range(settings.samples):
        sample = sample_surface(vertices, triangles, settings.points, seed=rng, outer=settings.outer)
        cage = fit_cage(sample.points, template=template, distance=settings.cage_distance,
                        iterations=settings.cage_iterations, step=settings.cage_step, enclose=settings.enclose)
        points.append(sample.points)
        normals.append(sample.normals)
        cages.append(cage.vertices)
        if settings.weights:
            weights.append(mvc_weights(sample.points, cage.vertices, cage.faces, threads=threads))
    arrays = {
        "points": np.asarray(points, dtype=np.float32),
        "normals": np.asarray(normals, dtype=np.float32),
        "cage_vertices": np.asarray(cages, dtype=np.float64),
        "cage_faces": np.asarray(template.faces, dtype=np.int64),
        "center": normalizer.center_,
        "scale": np.float64(normalizer.scale_),
        "vertex_count": np.int64(len(mesh.vertices)),
        "triangle_count": np.int64(len(triangles)),
    }
    if settings.weights:
        arrays["weights"] = np.asarray(weights, dtype=np.float32)
    return arrays


def _cache_file(cache_dir: Path, digest: str, settings: SampleSettings) -> Path:
    return cache_dir / "samples" / f"{digest}_{settings.key()}.npz"


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a cache entry with kpd's one atomic writer (a full disk is one :class:`~kpd.errors.WriteError`, a
    killed worker's temporary is removed by the next run)."""
    from kpd.io import atomic_output

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        from kpd.errors import WriteError
        from kpd.io.atomic import describe_os_error

        raise WriteError(describe_os_error(exc, path.parent)) from exc
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def _ingest_one(job: tuple[str, str, dict, str, int | None]) -> str | None:
    """Worker: sample one mesh into the cache; returns the reason when the mesh is unusable."""
    path, digest, settings_dict, target, threads = job
    settings = SampleSettings.from_dict(settings_dict)
    try:
        arrays = sample_mesh(path, settings, digest, threads=threads)
    except KpdError as exc:
        return str(exc)
    arrays["settings"] = np.asarray(json.dumps(settings.to_dict(), sort_keys=True))
    arrays["source"] = np.asarray(str(path))
    arrays["sha256"] = np.asarray(digest)
    _write_npz(Path(target), arrays)
    return None


class Ingested(NamedTuple):
    """Result of :func:`ingest`: usable ``(file, cache path)`` pairs in input order, and the skipped meshes."""

    entries: list[tuple[ShapeFile, Path]]
    skipped: list[Skipped]


def ingest(files: list[ShapeFile], settings: SampleSettings = SampleSettings(),
           cache_dir: str | os.PathLike | None = None,
           *, processes: int = 2, progress: bool = True, desc: str = "sampling") -> Ingested:
    """Make sure every mesh has a cache entry; list the ones that cannot be used.

    Parameters
    ----------
    files : the meshes.
    settings : sampling and cage settings (part of the cache key).
    cache_dir : default :func:`default_cache_dir`.
    processes : worker processes for meshes not yet cached (1 = in this process).
    progress : show a tqdm bar.
    """
    from tqdm import tqdm

    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    skipped: list[Skipped] = []
    targets: list[Path | None] = []
    jobs: list[tuple[int, tuple]] = []
    parallel = processes > 1
    for i, f in enumerate(files):
        try:
            if f.path.stat().st_size == 0:
                raise OSError("the file is empty")
            digest = file_digest(f.path)
        except OSError as exc:
            skipped.append(Skipped(str(f.path), f"cannot read the file: {exc}"))
            targets.append(None)
            continue
        target = _cache_file(cache_dir, digest, settings)
        targets.append(target)
        if not target.is_file():
            jobs.append((i, (str(f.path), digest, settings.to_dict(), str(target), 1 if parallel else None)))
    if jobs:
        log.info("sampling %d of %d meshes into %s", len(jobs), len(files), cache_dir)
        bar = tqdm(total=len(jobs), desc=desc, unit="mesh", disable=not progress)
        try:
            if parallel and len(jobs) > 1:
                with ProcessPoolExecutor(max_workers=processes, mp_context=get_context("spawn")) as pool:
                    reasons = []
                    for reason in pool.map(_ingest_one, [job for _, job in jobs], chunksize=4):
                        reasons.append(reason)
                        bar.update()
            else:
                reasons = []
                for _, job in jobs:
                    reasons.append(_ingest_one(job))
                    bar.update()
        finally:
            bar.close()
        for (i, _), reason in zip(jobs, reasons):
            if reason is not None:
                skipped.append(Skipped(str(files[i].path), reason))
                targets[i] = None
    for s in skipped:
        log.warning("skipped %s: %s", s.path, s.reason)
    entries = [(f, t) for f, t in zip(files, targets) if t is not None]
    return Ingested(entries, skipped)


@dataclass
class ShapeSamples:
    """The cached samples of several shapes, stacked (numpy; kpd.train turns them into tensors without copying).

    names : one per shape; paths : the mesh files.
    points, normals : (n_shapes, R, N, 3) float32, in each shape's [-1, 1] frame.
    cage_vertices : (n_shapes, R, C, 3) float32, the cage fitted to each sample.
    cage_faces : (F, 3) int64, shared by all cages.
    weights : (n_shapes, R, N, C) float32 MVC weights of each sample's points w.r.t. its cage, or None.
    centers : (n_shapes, 3) float64 and scales : (n_shapes,) float64, the normalisers (original = x * scale + center).
    """

    names: list[str]
    paths: list[str]
    points: np.ndarray
    normals: np.ndarray
    cage_vertices: np.ndarray
    cage_faces: np.ndarray
    weights: np.ndarray | None
    centers: np.ndarray
    scales: np.ndarray

    def __len__(self) -> int:
        return len(self.names)


def load_samples(entries: list[tuple[ShapeFile, Path]], settings: SampleSettings) -> ShapeSamples:
    """Stack cache entries (from :func:`ingest`) into one :class:`ShapeSamples`."""
    if not entries:
        raise DataError("no usable shapes to load")
    count = len(entries)
    n, r = settings.points, settings.samples
    points = np.empty((count, r, n, 3), np.float32)
    normals = np.empty((count, r, n, 3), np.float32)
    cages = None
    weights = None
    faces = None
    centers = np.empty((count, 3))
    scales = np.empty(count)
    for i, (_, path) in enumerate(entries):
        with np.load(path, allow_pickle=False) as z:
            if z["points"].shape != (r, n, 3):
                raise DataError(f"cache file {path} holds points of shape {z['points'].shape}; expected {(r, n, 3)}")
            points[i], normals[i] = z["points"], z["normals"]
            if cages is None:
                c = z["cage_vertices"].shape[1]
                cages = np.empty((count, r, c, 3), np.float32)
                faces = z["cage_faces"]
                if settings.weights:
                    weights = np.empty((count, r, n, c), np.float32)
            cages[i] = z["cage_vertices"]
            if weights is not None:
                weights[i] = z["weights"]
            centers[i], scales[i] = z["center"], z["scale"]
    return ShapeSamples(names=[f.name for f, _ in entries], paths=[str(f.path) for f, _ in entries], points=points,
                        normals=normals, cage_vertices=cages, cage_faces=faces, weights=weights, centers=centers,
                        scales=scales)


@dataclass
class PreparedData:
    """A category ready for training or evaluation: the split, the loaded samples per split, the skipped meshes."""

    category: Category
    settings: SampleSettings
    cache_dir: Path
    samples: dict[str, ShapeSamples]
    skipped: list[Skipped]
    options: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-safe summary; ``discover`` holds the arguments that rebuild the same split."""
        return {**self.category.to_dict(), "cache": str(self.cache_dir), "settings": self.settings.to_dict(),
                "discover": self.options, "usable": {s: len(v) for s, v in self.samples.items()},
                "skipped": [s._asdict() for s in self.skipped]}


def prepare(root: str | os.PathLike, category: str | None = None, *, settings: SampleSettings = SampleSettings(),
            cache_dir: str | os.PathLike | None = None, split_file: str | os.PathLike | None = None,
            val_fraction: float = 0.1, seed: int = 0, splits: tuple[str, ...] = ("train", "val"),
            processes: int = 2, progress: bool = True, min_shapes: int = 2) -> PreparedData:
    """Discover, ingest and load the requested splits.

    DataError when the first split has fewer than ``min_shapes`` usable shapes; a later split with none is left out of
    ``samples`` (with a warning), so training runs without validation rather than failing.
    """
    cat = discover(root, category, split_file=split_file, val_fraction=val_fraction, seed=seed)
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    from kpd.io import remove_stale_temporaries

    remove_stale_temporaries(cache_dir / "samples")  # left by sampling workers that were killed
    new_folders = [f for f in (cache_dir / "samples", cache_dir) if not f.exists()]
    try:
        return _prepare(cat, root, category, settings, cache_dir, split_file, val_fraction, seed, splits, processes,
                        progress, min_shapes)
    except BaseException:
        for folder in new_folders:  # a failed first run (a full disk) leaves no empty cache folders
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        raise


def _prepare(cat, root, category, settings, cache_dir, split_file, val_fraction, seed, splits, processes, progress,
             min_shapes) -> PreparedData:
    samples: dict[str, ShapeSamples] = {}
    skipped: list[Skipped] = []
    for i, split in enumerate(splits):
        files = cat.splits.get(split, [])
        done = ingest(files, settings, cache_dir, processes=processes, progress=progress,
                      desc=f"sampling {cat.category} {split}")
        skipped.extend(done.skipped)
        if i == 0 and len(done.entries) < min_shapes:
            raise DataError(f"category {cat.category!r} ({cat.layout} at {cat.root}): the {split} split has "
                            f"{len(done.entries)} usable shape(s) of {len(files)}; need at least {min_shapes}")
        if not done.entries:
            log.warning("the %s split of %r has no usable shapes; it is left out", split, cat.category)
            continue
        samples[split] = load_samples(done.entries, settings)
    options = {"root": str(Path(root).resolve()), "category": category,
               "split_file": None if split_file is None else str(Path(split_file).resolve()),
               "val_fraction": val_fraction, "seed": seed}
    return PreparedData(category=cat, settings=settings, cache_dir=cache_dir, samples=samples, skipped=skipped,
                        options=options)
