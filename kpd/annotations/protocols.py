"""The evaluation protocols: PCK by regression, part correspondence, the dual alignment score, coverage and inclusivity,
and the alignment chamfer over seeded pairs."""

from __future__ import annotations

import logging
import os
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from kpd.annotations.keypointnet import KeypointNet
from kpd.annotations.shapenetpart import ShapeNetPart
from kpd.annotations.shapes import (
    Skipped,
    keypointnet_shapes,
    point_cloud_shapes,
    shapenetpart_shapes,
)
from kpd.annotations.sources import _predict
from kpd.errors import DataError, InputError

__all__ = [
    "pck_protocol", "parts_protocol", "das_protocol", "coverage_protocol", "alignment_pairs", "chamfer_protocol",
]

log = logging.getLogger("kpd.annotations")


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
    the target's sample by :func:`kpd.metrics.alignment_chamfer` (docs/method.md §6), x1e3, next to no deformation.
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
                      "docs/method.md §6) to the target's sample in the [-1, 1] frame, x1e3",
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
