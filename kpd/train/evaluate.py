"""Evaluation of trained runs: pairwise alignment (the paper's Fig. 7) and label-free keypoint quality.

Both read the run's ``record.json`` to rebuild its data split (``data_root`` overrides the folder) and use the sample
settings stored in its checkpoint, so they see the same kind of samples and cages as training did.
"""

from __future__ import annotations

import json
import logging
import os
from typing import Callable, NamedTuple
from pathlib import Path

import numpy as np

from kpd.annotations import alignment_pairs, pair_notes
from kpd.data import PreparedData, SampleSettings, ShapeSamples, Skipped, discover, prepare
from kpd.errors import InputError, KpdError
from kpd.metrics import (alignment_chamfer, fit_mirror_permutation, keypoint_stability, mirror_consistency,
                         surface_distance)
from kpd.train.predictor import CheckpointPredictor

__all__ = ["run_data", "fixed_pairs", "evaluate_alignment", "evaluate_keypoints", "GalleryPairs"]

log = logging.getLogger(__name__)


def _record(run: str | os.PathLike) -> dict:
    path = Path(run)
    path = path if path.is_dir() else path.parent
    file = path / "record.json"
    if not file.is_file():
        raise InputError(f"run folder {path} has no record.json")
    return json.loads(file.read_text())


def run_data(predictor: CheckpointPredictor, run: str | os.PathLike, *, splits: tuple[str, ...] = ("test",),
             data_root: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None,
             processes: int = 2, progress: bool = True) -> PreparedData:
    """The run's data (same discovery options and sample settings), for the given splits."""
    options = _record(run)["data"]["discover"]
    settings = SampleSettings.from_dict(predictor.sample_settings)
    return prepare(data_root or options["root"], options["category"], settings=settings, cache_dir=cache_dir,
                   split_file=options["split_file"], val_fraction=options["val_fraction"], seed=options["seed"],
                   splits=splits, processes=processes, progress=progress)


def fixed_pairs(n: int, count: int, seed: int = 0) -> np.ndarray:
    """Up to ``count`` seeded distinct (source, target) index pairs, source != target:
    :func:`kpd.annotations.alignment_pairs`."""
    if n < 2:
        raise InputError(f"alignment needs at least 2 shapes; got {n}")
    return alignment_pairs(n, count, seed)


def _align_all(predictor: CheckpointPredictor, test: ShapeSamples, pairs: np.ndarray, batch: int = 16):
    deformed, kp_src, kp_tgt = [], [], []
    for s in range(0, len(pairs), batch):
        src, tgt = pairs[s:s + batch, 0], pairs[s:s + batch, 1]
        d, ks, kt = predictor.align(test.points[src, 0], test.points[tgt, 0], test.cage_vertices[src, 0],
                                    test.weights[src, 0])
        deformed.append(d)
        kp_src.append(ks)
        kp_tgt.append(kt)
    return np.concatenate(deformed), np.concatenate(kp_src), np.concatenate(kp_tgt)


def _summary(values: np.ndarray) -> dict:
    return {"mean": float(values.mean()), "median": float(np.median(values)), "std": float(values.std()),
            "min": float(values.min()), "max": float(values.max())}


class GalleryPairs(NamedTuple):
    """The first pairs of an alignment evaluation, for a picture: P pairs of N points, K keypoints."""

    sources: np.ndarray  # (P, N, 3)
    targets: np.ndarray  # (P, N, 3)
    deformed: dict  # run name -> (P, N, 3), each source deformed to its target
    keypoints: dict  # run name -> ((P, K, 3) source keypoints, (P, K, 3) target keypoints)
    titles: list  # P captions
    scores: dict  # method name -> (P,) alignment chamfer x1e3


def evaluate_alignment(run: str | os.PathLike, baseline: str | os.PathLike | None = None, *, pairs: int = 200,
                       seed: int = 0, data_root: str | os.PathLike | None = None,
                       cache_dir: str | os.PathLike | None = None,
                       gallery: Callable[["GalleryPairs"], None] | None = None,
                       gallery_pairs: int = 8, processes: int = 2, progress: bool = True) -> dict:
    """Pairwise alignment on the test split (the paper's Fig. 7 protocol).

    ``pairs`` seeded source/target pairs of distinct test shapes (cached sample 0 of each); the source is deformed
    by the model and compared with the target by the chamfer distance of docs/method.md §6 in the [-1, 1] frame,
    reported ×10³, next to no deformation and, when given, a baseline run (e.g. ``--keypoint-source fps``).

    ``gallery``, when given, is called once with the first ``gallery_pairs`` pairs (:class:`GalleryPairs`) to draw
    them (``kpd eval alignment --gallery`` passes :func:`kpd.viewer.figures.alignment_gallery`).

    Returns
    -------
    result : JSON-safe dict; ``chamfer_x1e3`` holds mean / median / std per method.
    """
    models = {"model": CheckpointPredictor.load(run)}
    if baseline is not None:
        models["baseline"] = CheckpointPredictor.load(baseline)
    data = {name: run_data(p, run if name == "model" else baseline, data_root=data_root, cache_dir=cache_dir,
                           processes=processes, progress=progress) for name, p in models.items()}
    test = data["model"].samples["test"]
    for name, d in data.items():
        if d.samples["test"].names != test.names:
            raise InputError(f"the {name} run sees other test shapes than the model run; compare runs on one dataset")
    index = fixed_pairs(len(test), pairs, seed)
    scores = {"no_deformation": np.array([alignment_chamfer(test.points[s, 0], test.points[t, 0]) for s, t in index])}
    outputs = {}
    for name, predictor in models.items():
        deformed, kp_src, kp_tgt = _align_all(predictor, data[name].samples["test"], index)
        outputs[name] = (deformed, kp_src, kp_tgt)
        # every run is scored against the same targets, the model run's samples: a baseline sampled otherwise (say
        # without --outer-surface) sees its own samples but is not scored against a different point set
        targets = test.points[index[:, 1], 0]
        scores[name] = np.array([alignment_chamfer(d, t) for d, t in zip(deformed, targets)])
    none = scores["no_deformation"].mean()
    result = {
        "protocol": "Fig. 7: seeded pairs of distinct test shapes, sample 0, chamfer (squared, mean, both directions) "
                    "in the [-1, 1] frame, x1e3",
        "category": data["model"].category.category,
        "test_shapes": len(test),
        "test_names": list(test.names),
        "pairs": int(len(index)),
        "requested_pairs": int(pairs),
        "notes": pair_notes(len(test), pairs, len(index), data["model"].category.split_source),
        "seed": int(seed),
        "runs": {name: str(p.path) for name, p in models.items()},
        "targets": "sample 0 of each target as the model run samples it (also for the baseline)",
        "keypoint_source": {name: p.keypoint_source for name, p in models.items()},
        "chamfer_x1e3": {name: _summary(1e3 * v) for name, v in scores.items()},
        "ratio_to_no_deformation": {name: float(v.mean() / none) for name, v in scores.items()},
        "skipped": [s._asdict() for s in data["model"].skipped],
        "per_pair": [
            {"source": test.names[s], "target": test.names[t], **{n: float(1e3 * scores[n][i]) for n in scores}}
            for i, (s, t) in enumerate(index)
        ],
    }
    if "baseline" in scores:
        result["wins_vs_baseline"] = float(np.mean(scores["model"] < scores["baseline"]))
    if gallery is not None:
        count = min(gallery_pairs, len(index))
        gallery(GalleryPairs(
            sources=test.points[index[:count, 0], 0], targets=test.points[index[:count, 1], 0],
            deformed={name: out[0][:count] for name, out in outputs.items()},
            keypoints={name: (out[1][:count], out[2][:count]) for name, out in outputs.items()},
            titles=[f"{test.names[s]} -> {test.names[t]}" for s, t in index[:count]],
            scores={name: 1e3 * v[:count] for name, v in scores.items()}))
    return result


def _mirror(points: np.ndarray, axis: int) -> np.ndarray:
    out = np.array(points, copy=True)
    out[..., axis] *= -1.0
    return out


def evaluate_keypoints(run: str | os.PathLike, *, samples: int = 5, seed: int = 0, mirror_axis: int | None = 0,
                       data_root: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None,
                       max_train: int = 200, max_test: int | None = None, processes: int = 2,
                       progress: bool = True) -> dict:
    """Label-free keypoint quality on the test split.

    - stability: keypoints from ``samples`` independent surface samples of each test mesh; mean distance to the
      per-keypoint centroid (:func:`kpd.metrics.keypoint_stability`), averaged over shapes;
    - surface distance: keypoints (of every sample) to the normalised mesh surface;
    - mirror consistency (``mirror_axis`` 0/1/2 = x/y/z; None skips): keypoints of the mirrored shape (an
      independent sample of it, so that a method that merely commutes with reflecting its input cloud, like FPS, is
      not scored 0 by construction), mirrored back, against the keypoints of the shape, after the best fixed
      permutation fitted on (up to ``max_train``) train shapes.
      Also reported: each axis's mirror asymmetry of the test shapes (chamfer of a sample and its mirror image) next
      to the chamfer between two samples of the same shape, which shows which plane is a symmetry plane.

    All distances are in the [-1, 1] frame of each shape.
    """
    from tqdm import tqdm

    from kpd.geometry import Normalizer, chamfer, sample_surface
    from kpd.io import read_mesh

    predictor = CheckpointPredictor.load(run)
    options = _record(run)["data"]["discover"]
    category = discover(data_root or options["root"], options["category"], split_file=options["split_file"],
                        val_fraction=options["val_fraction"], seed=options["seed"])
    n_points = int(predictor.sample_settings.get("points", 1024))
    outer = bool(predictor.sample_settings.get("outer", False))  # sampled as the model was trained
    files = category.splits["test"][:max_test] if max_test else category.splits["test"]
    if not files:
        raise InputError(f"category {category.category!r} has no test split to evaluate")
    stability, surface, kps, mirrored, skipped = [], [], [], [], []
    asym = {axis: [] for axis in "xyz"}
    same = []
    for i, f in enumerate(tqdm(files, desc="keypoints", unit="shape", disable=not progress)):
        try:
            mesh = read_mesh(f.path)
            triangles = np.asarray(mesh.triangles, dtype=np.int64)
            normalizer = Normalizer().fit(mesh.vertices[np.unique(triangles)])
            vertices = normalizer.apply(mesh.vertices)
            rng = np.random.default_rng([seed, 5, i])
            clouds = np.stack([sample_surface(vertices, triangles, n_points, seed=rng, outer=outer).points
                               for _ in range(samples)])
        except KpdError as exc:
            skipped.append(Skipped(str(f.path), str(exc)))
            continue
        kp = predictor.keypoints(clouds.astype(np.float32)).astype(np.float64)  # (S, K, 3)
        stability.append(keypoint_stability(kp))
        surface.append(surface_distance(kp.reshape(-1, 3), vertices, triangles))
        kps.append(kp[0])
        if mirror_axis is not None:  # the mirrored shape, seen through another independent sample
            other = clouds[1:2] if samples >= 2 else clouds[:1]
            mk = predictor.keypoints(_mirror(other, mirror_axis).astype(np.float32)).astype(np.float64)[0]
            mirrored.append(_mirror(mk, mirror_axis))
        if samples >= 2:
            same.append(chamfer(clouds[0], clouds[1]))
        for a, name in enumerate("xyz"):
            asym[name].append(chamfer(clouds[0], _mirror(clouds[0], a)))
    if not kps:
        raise InputError(f"no test mesh of {category.category!r} could be read")
    surface_all = np.concatenate(surface)
    result = {
        "category": category.category,
        "run": str(predictor.path),
        "keypoint_source": predictor.keypoint_source,
        "keypoints": predictor.K,
        "test_shapes": len(kps),
        "samples_per_shape": samples,
        "points": n_points,
        "stability": {"mean": float(np.mean(stability)), "median": float(np.median(stability))},
        "surface_distance": {"mean": float(surface_all.mean()), "median": float(np.median(surface_all)),
                             "within_0.05": float(np.mean(surface_all <= 0.05))},
        "mirror_asymmetry_x1e3": {name: float(1e3 * np.mean(v)) for name, v in asym.items()},
        "resample_chamfer_x1e3": float(1e3 * np.mean(same)) if same else None,
        "skipped": [s._asdict() for s in skipped],
        "units": "[-1, 1] frame of each shape (bbox centre, max |coordinate| = 1)",
    }
    if mirror_axis is not None:
        data = run_data(predictor, run, splits=("train",), data_root=data_root, cache_dir=cache_dir,
                        processes=processes, progress=progress)
        train = data.samples["train"]
        pick = np.random.default_rng([seed, 6]).permutation(len(train))[:max_train]
        clouds = train.points[pick, 0]
        others = train.points[pick, 1 if train.points.shape[1] > 1 else 0]
        kp_train = np.concatenate([predictor.keypoints(clouds[s:s + 32]) for s in range(0, len(clouds), 32)])
        mk_train = np.concatenate([predictor.keypoints(_mirror(others[s:s + 32], mirror_axis))
                                   for s in range(0, len(clouds), 32)])
        permutation = fit_mirror_permutation(kp_train.astype(np.float64), _mirror(mk_train, mirror_axis))
        result["mirror"] = {
            "axis": "xyz"[mirror_axis],
            "permutation": permutation.tolist(),
            "train_shapes": len(pick),
            "consistency": mirror_consistency(np.stack(kps), np.stack(mirrored), permutation),
            "consistency_identity": mirror_consistency(np.stack(kps), np.stack(mirrored),
                                                       np.arange(predictor.K)),
            "self_symmetric_keypoints": int(np.sum(permutation == np.arange(predictor.K))),
        }
    return result


def __getattr__(attr: str):
    if attr == "alignment_gallery":  # drawing is the viewer's: the core never imports it
        raise AttributeError(f"{__name__}.alignment_gallery moved to kpd.viewer.figures.alignment_gallery")
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
