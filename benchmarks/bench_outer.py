"""Share of surface samples inside the shape (interior faces of overlapping or touching pieces), before and after
outer-surface sampling, on the GSO shoes and the ModelNet10 chairs; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_outer.py --out benchmarks/results/outer.json

"Before": ``sample_surface(..., outer=False)`` (what kpd sampled until now), the share of its points that
:func:`kpd.geometry.interior_mask` finds inside another piece. "After": the same test on ``outer=True`` samples
(zero by construction) and, as an independent check, the share of the *before* points that are farther than 1% of
the diagonal from every *after* point of a dense outer sample (points of interior faces lie away from the outer
surface; points of the outer surface do not).

With ``--chamfer DATA``: what outer-surface *training* does to the learned alignment chamfer (paper Fig. 7), two or
more bundles on the same held-out shapes, the same seeded pairs and the same target point sets::

    .venv/bin/python benchmarks/bench_outer.py --chamfer runs/data/shoe \
        --split-file benchmarks/results/shoe_split_shipped.txt \
        --model outer-0=shoe --model plain-0=runs/shoe-plain/shoe-plain.kpd \
        --model outer-1=runs/shoe-plain/seeds/outer-1/outer-1.kpd \
        --model plain-1=runs/shoe-plain/seeds/plain-1/plain-1.kpd \
        --model outer-2=runs/shoe-plain/seeds/outer-2/outer-2.kpd \
        --model plain-2=runs/shoe-plain/seeds/plain-2/plain-2.kpd \
        --out benchmarks/results/outer_training.json

(``shoe`` is the shipped bundle, trained with ``--outer-surface``; the others are ``kpd train runs/data/shoe
--split-file benchmarks/results/shoe_split_shipped.txt --keypoints 12 [--outer-surface] --seed S --out ...`` and
``kpd export RUN --out RUN/NAME.kpd --up +y``; the split file is the shipped model's 150/17/18 split.) Models named
``ARM-SEED`` are also summarised per arm ("by_arm"): each arm over its seeds, and the arms seed by seed, so that the
difference between arms can be read against the spread between training seeds of one arm.

Each model sees each test mesh as it was trained to (:meth:`kpd.runtime.Model.predict`: outer-surface samples for a
bundle trained with ``--outer-surface``, every face otherwise) and rigs it (:meth:`kpd.runtime.Model.rig`, the cage
fitted to what it saw, grown to enclose the mesh); the source is deformed through its rig to the target's keypoints,
as ``kpd eval chamfer`` does. The deformation is then applied to *scoring* samples that are the same for every model:
an outer-surface sample ("outer", the honest target: interior faces are not the shoe's surface) and an every-face
sample ("all"), drawn with their own seed so that no model is scored against the very points it saw. "native" is
``kpd eval chamfer``'s figure (each model's own input points, deformed, against the target's input points), which
differs between models in what it measures. No deformation and the resampling floor (the chamfer between two
independent samples of one shape, what a perfect alignment would still score) are given per scoring set.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from kpd.geometry import Normalizer, interior_mask, mesh_pieces, sample_surface  # noqa: E402
from kpd.io import read_mesh  # noqa: E402
from kpd.benchmark import write_json  # noqa: E402


def measure(path: str, n: int, seed: int) -> dict:
    mesh = read_mesh(path)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    vertices = Normalizer().fit(mesh.vertices[np.unique(triangles)]).apply(mesh.vertices)
    started = time.perf_counter()
    before = sample_surface(vertices, triangles, n, seed=seed)
    plain = time.perf_counter() - started
    inside = interior_mask(vertices, triangles, before.points, before.faces)
    started = time.perf_counter()
    after = sample_surface(vertices, triangles, n, seed=seed, outer=True)
    outer_seconds = time.perf_counter() - started
    after_inside = interior_mask(vertices, triangles, after.points, after.faces)
    dense = sample_surface(vertices, triangles, 8 * n, seed=seed + 1, outer=True).points
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    far = cKDTree(dense).query(before.points)[0] > 0.01 * diagonal
    return {"name": Path(path).parent.name if Path(path).name == "model.obj" else Path(path).stem,
            "pieces": int(mesh_pieces(triangles).max() + 1), "interior_before": float(inside.mean()),
            "interior_after": float(after_inside.mean()), "far_from_outer_before": float(far.mean()),
            "far_from_outer_of_interior": float(far[inside].mean()) if inside.any() else None,
            "seconds_plain": plain, "seconds_outer": outer_seconds}


def summary(rows: list[dict]) -> dict:
    before = np.array([r["interior_before"] for r in rows])
    after = np.array([r["interior_after"] for r in rows])
    far = np.array([r["far_from_outer_before"] for r in rows])
    return {"shapes": len(rows), "interior_before_mean": float(before.mean()),
            "interior_before_median": float(np.median(before)), "shapes_with_interior": int((before > 0.001).sum()),
            "interior_after_mean": float(after.mean()), "far_from_outer_before_mean": float(far.mean()),
            "seconds_outer_median": float(np.median([r["seconds_outer"] for r in rows])),
            "seconds_plain_median": float(np.median([r["seconds_plain"] for r in rows]))}


SCORING = (("outer", True), ("all", False))


def _stats(values: np.ndarray) -> dict:
    return {"mean": float(values.mean()), "median": float(np.median(values)), "std": float(values.std()),
            "min": float(values.min()), "max": float(values.max())}


def _paired(a: np.ndarray, b: np.ndarray, sources: np.ndarray) -> dict:
    """Model a against model b on the same pairs (lower is better)."""
    from scipy.stats import binomtest

    per_source = [(a[sources == s].mean(), b[sources == s].mean()) for s in np.unique(sources)]
    wins = int(sum(x < y for x, y in per_source))
    return {"share_of_pairs_a_better": float(np.mean(a < b)), "median_ratio_a_over_b": float(np.median(a / b)),
            "ratio_of_means_a_over_b": float(a.mean() / b.mean()), "mean_difference_x1e3": float(1e3 * (a - b).mean()),
            "share_of_sources_a_better": wins / len(per_source), "sources": len(per_source),
            # pairs share their shapes, so they are not independent; the source shapes' means are closer to it
            "sign_test_p_sources": float(binomtest(wins, len(per_source)).pvalue)}


def chamfer_comparison(root: str, models: dict[str, str], *, pairs: int, seed: int, score_seed: int,
                       score_points: int, split_file: str | None = None) -> dict:
    """Alignment chamfer x1e3 of each bundle in ``models`` (name -> bundle) on the test split of ``root``."""
    from kpd.annotations import alignment_pairs
    from kpd.data import discover
    from kpd.metrics import alignment_chamfer
    from kpd.mvc import mvc_weights
    from kpd.runtime import Model

    data = discover(root, split_file=split_file)
    test = data.splits["test"]
    index = alignment_pairs(len(test), pairs, seed)
    loaded = {name: Model.load(path, threads=1) for name, path in models.items()}
    used = sorted(set(index.ravel().tolist()))
    views = {name: {} for name in loaded}  # name -> shape -> (prediction, cage vertices, cage faces, influence)
    scoring = {mode: {} for mode, _ in SCORING}
    floor = {mode: [] for mode, _ in SCORING}
    started = time.perf_counter()
    for i in used:
        mesh = read_mesh(test[i].path)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        for name, model in loaded.items():
            prediction = model.predict(mesh, seed=seed)
            rig = model.rig(mesh, seed=seed, prediction=prediction)
            views[name][i] = (prediction, rig.cage.vertices, rig.cage.faces, rig.influence)
        vertices = Normalizer().fit(mesh.vertices[np.unique(triangles)]).apply(mesh.vertices)  # = every model's frame
        for name in loaded:
            if not np.allclose(views[name][i][0].normalizer.apply(mesh.vertices), vertices):
                raise RuntimeError(f"{name} normalises {test[i].name} differently")
        for mode, outer in SCORING:
            scoring[mode][i] = sample_surface(vertices, triangles, score_points, seed=score_seed, outer=outer).points
            again = sample_surface(vertices, triangles, score_points, seed=score_seed + 1, outer=outer).points
            floor[mode].append(alignment_chamfer(scoring[mode][i], again))
    weights = {}

    def deform(name: str, points_of, s: int, t: int, key: str) -> np.ndarray:
        prediction, cage, faces, influence = views[name][s]
        if (name, key, s) not in weights:
            weights[name, key, s] = mvc_weights(points_of(s), cage, faces)
        offsets = views[name][t][0].keypoints - prediction.keypoints  # (K, 3), model frame
        return weights[name, key, s] @ (cage + influence.T @ offsets)

    scores = {mode: {"no_deformation": [], **{name: [] for name in loaded}} for mode, _ in SCORING}
    scores["native"] = {name: [] for name in loaded}
    native_none = {name: [] for name in loaded}
    for s, t in index:
        for mode, _ in SCORING:
            target = scoring[mode][t]
            scores[mode]["no_deformation"].append(alignment_chamfer(scoring[mode][s], target))
            for name in loaded:
                scores[mode][name].append(alignment_chamfer(deform(name, scoring[mode].__getitem__, s, t, mode),
                                                            target))
        for name in loaded:
            own = views[name]
            deformed = deform(name, lambda i: own[i][0].points, s, t, "native")
            scores["native"][name].append(alignment_chamfer(deformed, own[t][0].points))
            native_none[name].append(alignment_chamfer(own[s][0].points, own[t][0].points))
    seconds = time.perf_counter() - started
    scores = {mode: {name: np.array(v) for name, v in per.items()} for mode, per in scores.items()}
    names = list(loaded)
    result = {"data": {"root": str(root), "layout": data.layout, "split_source": data.split_source,
                       "counts": {k: len(v) for k, v in data.splits.items()}, "test_names": [f.name for f in test]},
              "pairs": int(len(index)), "requested_pairs": int(pairs), "seed": seed, "score_seed": score_seed,
              "score_points": score_points,
              "models": {name: {"bundle": str(m.bundle.path), "outer_surface": m.outer_surface,
                                "points": m.point_count, "keypoints": m.num_keypoints,
                                "training": _training(m)} for name, m in loaded.items()},
              "chamfer_x1e3": {}, "ratio_to_no_deformation": {}, "paired": {}, "seconds": seconds}
    for mode, per in scores.items():
        result["chamfer_x1e3"][mode] = {name: _stats(1e3 * v) for name, v in per.items()}
        if mode == "native":
            result["chamfer_x1e3"][mode].update({f"no_deformation ({name}'s input)": _stats(1e3 * np.array(v))
                                                 for name, v in native_none.items()})
            continue
        result["chamfer_x1e3"][mode]["resample_floor"] = _stats(1e3 * np.array(floor[mode]))
        result["ratio_to_no_deformation"][mode] = {name: float(per[name].mean() / per["no_deformation"].mean())
                                                   for name in names}
        result["paired"][mode] = {f"{a} vs {b}": _paired(per[a], per[b], index[:, 0])
                                  for k, a in enumerate(names) for b in names[k + 1:]}
    result["by_arm"] = _by_arm(names, scores)
    result["per_pair"] = [{"source": test[s].name, "target": test[t].name,
                           **{f"{mode}/{name}": float(1e3 * per[name][i]) for mode, per in scores.items()
                              for name in per}} for i, (s, t) in enumerate(index)]
    return result


def _by_arm(names: list[str], scores: dict) -> dict | None:
    """Models named ``ARM-SEED`` (e.g. outer-0, plain-0, outer-1, ...): each arm's mean chamfer over its training seeds,
    and the first arm against each other one seed by seed (same seed, same pairs), which sets the difference between
    arms beside the spread between seeds of one arm."""
    arms: dict[str, dict[str, str]] = {}
    for name in names:
        arm, sep, seed = name.rpartition("-")
        if not sep or not arm:
            return None
        arms.setdefault(arm, {})[seed] = name
    if len(arms) < 2:
        return None
    first, *others = arms
    out = {}
    for mode in (m for m, _ in SCORING):
        per = scores[mode]
        entry = {arm: {"seeds": list(members), "means_x1e3": [float(1e3 * per[n].mean()) for n in members.values()]}
                 for arm, members in arms.items()}
        for arm in entry.values():
            arm["mean_of_means_x1e3"] = float(np.mean(arm["means_x1e3"]))
            arm["spread_x1e3"] = float(np.ptp(arm["means_x1e3"]))
        for other in others:
            seeds = [seed for seed in arms[first] if seed in arms[other]]
            a = [per[arms[first][seed]] for seed in seeds]
            b = [per[arms[other][seed]] for seed in seeds]
            entry[f"{first} vs {other}, same seed"] = {
                "seeds": seeds, "ratio_of_means": [float(x.mean() / y.mean()) for x, y in zip(a, b)],
                "share_of_pairs_better": [float(np.mean(x < y)) for x, y in zip(a, b)],
                "pooled_share_of_pairs_better": float(np.mean(np.concatenate(a) < np.concatenate(b))),
                "seeds_better": int(sum(x.mean() < y.mean() for x, y in zip(a, b)))}
        out[mode] = entry
    return out


def _training(model) -> dict:
    record = model.bundle.manifest.get("training") or {}
    counts = (record.get("data") or {}).get("counts") or {}
    seconds = record.get("train_seconds")
    return {"command": record.get("command"), "iterations": record.get("iterations"), "counts": counts,
            "train_seconds": seconds, "run_seconds": record.get("run_seconds"),
            "train_seconds_per_train_shape": seconds / counts["train"] if seconds and counts.get("train") else None,
            "val_chamfer": (record.get("metrics") or {}).get("val_chamfer")}


def _summary_lines(result: dict) -> dict:
    out = {mode: {name: round(s["mean"], 3) for name, s in per.items()} for mode, per in result["chamfer_x1e3"].items()}
    if result.get("by_arm"):
        return {"chamfer_x1e3_mean": out, "by_arm": result["by_arm"]}
    return {"chamfer_x1e3_mean": out, "paired": result["paired"],
            "ratio_to_no_deformation": result["ratio_to_no_deformation"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=os.environ.get("KPD_DATA", str(REPO.parent / "shared" / "data")))
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chairs", default="test", help="ModelNet10 chair split measured (default test)")
    parser.add_argument("--out", default=None)
    g = parser.add_argument_group("--chamfer: alignment chamfer of bundles trained with and without outer sampling")
    g.add_argument("--chamfer", metavar="DATA", default=None,
                   help="dataset the bundles were trained on (its seeded test split is scored), e.g. runs/data/shoe")
    g.add_argument("--split-file", default=None,
                   help="split the bundles were trained with (default: the folder's seeded carving, as kpd train)")
    g.add_argument("--model", action="append", default=[], metavar="NAME=BUNDLE",
                   help="a bundle to score (repeat; paired statistics compare them in the given order)")
    g.add_argument("--pairs", type=int, default=200, help="seeded pairs of distinct test shapes (default 200)")
    g.add_argument("--score-points", type=int, default=1024, help="points of each scoring sample (default 1024)")
    g.add_argument("--score-seed", type=int, default=100, help="seed of the scoring samples (default 100)")
    args = parser.parse_args()
    if args.chamfer is not None:
        models = dict(m.split("=", 1) if "=" in m else (m, m) for m in args.model)
        if len(models) < 1:
            parser.error("--chamfer needs at least one --model NAME=BUNDLE")
        result = {"benchmark": "outer_training", "machine": platform.machine(), "cpus": os.cpu_count(),
                  "load": os.getloadavg()[0],
                  **chamfer_comparison(args.chamfer, models, pairs=args.pairs, seed=args.seed,
                                       score_seed=args.score_seed, score_points=args.score_points,
                                       split_file=args.split_file)}
        if args.out:
            write_json(args.out, result, indent=1)
        print(json.dumps(_summary_lines(result), indent=1))
        return
    data = Path(args.data)
    sets = {"gso_shoes": sorted(glob.glob(str(data / "gso_shoes" / "*" / "model.obj"))),
            f"modelnet10_chair_{args.chairs}": sorted(glob.glob(str(data / "modelnet10" / "chair" / args.chairs /
                                                                   "*.ply")))}
    result = {"benchmark": "outer", "points": args.points, "seed": args.seed, "machine": platform.machine(),
              "cpus": os.cpu_count(), "load": os.getloadavg()[0], "sets": {}}
    for name, files in sets.items():
        rows = [measure(f, args.points, args.seed) for f in files]
        result["sets"][name] = {"summary": summary(rows), "shapes": rows}
    if args.out:
        write_json(args.out, result, indent=1)
    print(json.dumps({k: v["summary"] for k, v in result["sets"].items()}, indent=1))


if __name__ == "__main__":
    main()
