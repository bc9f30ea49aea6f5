"""kpd eval: score trained runs (alignment chamfer, label-free keypoint quality)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from kpd.commands import check_output
from kpd.errors import InputError

HELP = "evaluate trained runs: alignment chamfer (paper Fig. 7) and label-free keypoint quality"
EXAMPLE = "kpd eval alignment runs/chair --baseline runs/chair-fps --out chair_alignment.json --gallery chair.png"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="task", metavar="TASK", required=True)

    a = sub.add_parser("alignment", help="deform test sources onto test targets; chamfer x1e3 vs baselines",
                       description="The paper's Fig. 7 protocol: seeded pairs of distinct test shapes; chamfer "
                                   "(REFERENCE §6, [-1, 1] frame, x1e3) of the deformed source to the target, next "
                                   "to no deformation and an optional baseline run.")
    a.add_argument("run", help="run folder (or checkpoint) from kpd train")
    a.add_argument("--baseline", help="a second run to compare, e.g. trained with --keypoint-source fps")
    a.add_argument("--pairs", type=int, default=200, help="number of pairs (default 200)")
    a.add_argument("--gallery", help="PNG with source / keypoints / deformed / target for the first pairs")
    a.add_argument("--gallery-pairs", type=int, default=8, help="pairs in the gallery (default 8)")
    _common(a)

    k = sub.add_parser("keypoints", help="stability, distance to the surface and mirror consistency of keypoints",
                       description="Label-free keypoint quality on the test split; distances in the [-1, 1] frame.")
    k.add_argument("run", help="run folder (or checkpoint) from kpd train")
    k.add_argument("--samples", type=int, default=5, help="independent point samples per shape (default 5)")
    k.add_argument("--mirror-axis", choices=("x", "y", "z", "none"), default="x",
                   help="mirror plane normal in the data's frame (ModelNet chairs and tables: x)")
    k.add_argument("--max-train", type=int, default=200, help="train shapes used to fit the mirror permutation")
    k.add_argument("--max-test", type=int, default=None, help="evaluate at most this many test shapes")
    _common(k)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="JSON result")
    p.add_argument("--data", help="dataset folder, if it moved since training (default: the run's record)")
    p.add_argument("--cache", help="sample cache folder (default $KPD_CACHE or ~/.cache/kpd)")
    p.add_argument("--seed", type=int, default=0, help="seed of the pairs / samples (default 0)")
    p.add_argument("--force", action="store_true", help="replace existing outputs")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _write_json(path: Path, data: dict) -> None:
    from kpd.train.trainer import _write_json as write

    write(path, data)


def run(args: argparse.Namespace) -> int:
    out = check_output(args.out, force=args.force)
    if not Path(args.run).exists():
        raise InputError(f"run {args.run} does not exist")
    from kpd.train import evaluate

    if args.task == "alignment":
        if args.gallery:
            check_output(args.gallery, force=args.force)
        if args.pairs < 1:
            raise InputError(f"--pairs must be at least 1; got {args.pairs}")
        result = evaluate.evaluate_alignment(args.run, args.baseline, pairs=args.pairs, seed=args.seed,
                                             data_root=args.data, cache_dir=args.cache, gallery=args.gallery,
                                             gallery_pairs=args.gallery_pairs, progress=not args.quiet)
        _write_json(out, result)
        scores = result["chamfer_x1e3"]
        print(f"{result['category']}: {result['pairs']} pairs of {result['test_shapes']} test shapes, chamfer x1e3 "
              + ", ".join(f"{name} {s['mean']:.3f}" for name, s in scores.items()))
    else:
        axis = None if args.mirror_axis == "none" else "xyz".index(args.mirror_axis)
        result = evaluate.evaluate_keypoints(args.run, samples=args.samples, seed=args.seed, mirror_axis=axis,
                                             data_root=args.data, cache_dir=args.cache, max_train=args.max_train,
                                             max_test=args.max_test, progress=not args.quiet)
        _write_json(out, result)
        line = (f"{result['category']}: stability {result['stability']['mean']:.4f}, surface distance "
                f"{result['surface_distance']['mean']:.4f}")
        if "mirror" in result:
            line += f", mirror consistency {result['mirror']['consistency']:.4f}"
        print(line)
    print(f"wrote {out}")
    return 0
