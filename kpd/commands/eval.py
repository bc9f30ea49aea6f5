"""kpd eval: score trained runs (alignment chamfer, label-free keypoint quality)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from kpd.commands import existing, folder, integer, number, require_train_extra
from kpd.errors import InputError

HELP = "evaluate trained runs: alignment chamfer (paper Fig. 7) and label-free keypoint quality"
EXAMPLE = "kpd eval alignment runs/chair --baseline runs/chair-fps --out chair_alignment.json --gallery chair.png"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="task", metavar="TASK", required=True)

    a = sub.add_parser("alignment", help="deform test sources onto test targets; chamfer x1e3 vs baselines",
                       description="The paper's Fig. 7 protocol: seeded pairs of distinct test shapes; chamfer "
                                   "(docs/method.md §6, [-1, 1] frame, x1e3) of the deformed source to the target, "
                                   "next to no deformation and an optional baseline run.",
                       epilog="example:\n  kpd eval alignment runs/chair --baseline runs/chair-fps --pairs 200 "
                              "--out chair_alignment.json --gallery chair_alignment.png",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("run", type=existing, help="run folder (or checkpoint) from kpd train")
    a.add_argument("--baseline", type=existing, help="a second run to compare, e.g. trained with --keypoint-source fps")
    a.add_argument("--pairs", type=integer(1), default=200, help="number of pairs (default 200)")
    a.add_argument("--gallery", help="PNG with source / keypoints / deformed / target for the first pairs")
    a.add_argument("--gallery-pairs", type=integer(1), default=8, help="pairs in the gallery (default 8)")
    _common(a)

    k = sub.add_parser("keypoints", help="stability, distance to the surface and mirror consistency of keypoints",
                       description="Label-free keypoint quality on the test split; distances in the [-1, 1] frame.",
                       epilog="example:\n  kpd eval keypoints runs/chair --samples 5 --mirror-axis x "
                              "--out chair_keypoints.json",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    k.add_argument("run", type=existing, help="run folder (or checkpoint) from kpd train")
    k.add_argument("--samples", type=integer(1), default=5, help="independent point samples per shape (default 5)")
    k.add_argument("--mirror-axis", choices=("x", "y", "z", "none"), default="x",
                   help="mirror plane normal in the data's frame (ModelNet chairs and tables: x)")
    k.add_argument("--max-train", type=integer(1), default=200, help="train shapes used to fit the mirror permutation")
    k.add_argument("--max-test", type=integer(1), default=None, help="evaluate at most this many test shapes")
    _common(k)
    _add_protocol_parsers(sub)  # pck, parts, das, coverage, chamfer (bottom of this file)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="JSON result")
    p.add_argument("--data", type=folder, help="dataset folder, if it moved since training (default: the run's record)")
    p.add_argument("--cache", help="sample cache folder (default $KPD_CACHE or ~/.cache/kpd)")
    p.add_argument("--seed", type=integer(0), default=0, help="seed of the pairs / samples (default 0)")
    p.add_argument("--force", action="store_true", help="replace existing outputs")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def run(args: argparse.Namespace) -> int:
    from kpd.io import Outputs

    if args.task in _PROTOCOLS:
        return _run_protocol(args)
    require_train_extra("torch")  # a run's checkpoint (the protocols and `eval chamfer` take a bundle, torch-free)
    inputs = (args.run, getattr(args, "baseline", None), args.data, args.cache)
    with Outputs(force=args.force, inputs=inputs) as outputs:
        out = outputs.file(args.out, "--out", formats=(".json",), what="result (JSON)")
        _run_run(args, outputs, out)
    print(f"wrote {out}")
    return 0


def _run_run(args: argparse.Namespace, outputs, out: Path) -> None:
    from kpd.train import evaluate

    if args.task == "alignment":
        gallery = draw = None
        if args.gallery:
            gallery = outputs.file(args.gallery, "--gallery", formats=(".png",), what="gallery (PNG)")

            def draw(pairs) -> None:  # the library hands over the pairs; the viewer draws them
                from kpd.viewer.figures import alignment_gallery

                alignment_gallery(outputs.stage(gallery), pairs.sources, pairs.targets, pairs.deformed,
                                  pairs.keypoints, titles=pairs.titles, scores=pairs.scores)

        result = evaluate.evaluate_alignment(args.run, args.baseline, pairs=args.pairs, seed=args.seed,
                                             data_root=args.data, cache_dir=args.cache, gallery=draw,
                                             gallery_pairs=args.gallery_pairs, progress=not args.quiet)
        if gallery is not None:
            result["gallery"] = str(gallery)
        _write_json(outputs.stage(out), result)
        scores = result["chamfer_x1e3"]
        print(f"{result['category']}: {result['pairs']} pairs of {result['test_shapes']} test shapes, chamfer x1e3 "
              + ", ".join(f"{name} {s['mean']:.3f}" for name, s in scores.items()))
        print("test shapes: " + _names(result["test_names"], "the run's test split"))
        for note in result["notes"]:
            print(f"warning: {note}", file=sys.stderr)
    else:
        axis = None if args.mirror_axis == "none" else "xyz".index(args.mirror_axis)
        result = evaluate.evaluate_keypoints(args.run, samples=args.samples, seed=args.seed, mirror_axis=axis,
                                             data_root=args.data, cache_dir=args.cache, max_train=args.max_train,
                                             max_test=args.max_test, progress=not args.quiet)
        _write_json(outputs.stage(out), result)
        line = (f"{result['category']}: stability {result['stability']['mean']:.4f}, surface distance "
                f"{result['surface_distance']['mean']:.4f}")
        if "mirror" in result:
            line += f", mirror consistency {result['mirror']['consistency']:.4f}"
        print(line)


# --- Protocols on annotated datasets (helper "eval"): pck, parts, das, coverage, and chamfer on a bundle ------------
# Keypoints come from a bundle (--model) or from files (--keypoints DIR), so any method's output is scored the same
# way. The work is in kpd.annotations (data, frames, protocols) and kpd.metrics (the numbers).

HELP += "; scores on annotated data: pck, parts, das, coverage; chamfer of a bundle"

_PROTOCOLS = ("pck", "parts", "das", "coverage", "chamfer")


def _add_protocol_parsers(sub) -> None:
    p = sub.add_parser(
        "pck", help="PCK@0.05 of annotated keypoints regressed from the keypoints (paper Fig. 4), KeypointNet",
        description="The paper's Fig. 4 protocol (after Thewlis et al. 2017): a linear map (ridge-regularised least "
                    "squares) from the flattened keypoints to the annotated ones (the semantic ids present in 80%% "
                    "of models) is fitted on the train split and scored on test: PCK at 0.05 of the [-1, 1] box of "
                    "the KeypointNet cloud (authors' axis fix). Only models with geometry can be scored.",
        epilog="example:\n  kpd eval pck ../shared/data/keypointnet --category chair --model chair "
               "--geometry ../shared/data/shapenetpart_sample --out chair_pck.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=folder, help="KeypointNet folder (annotations/, splits/, pcds/ and optionally models/)")
    _source_arguments(p)
    _geometry_argument(p)
    p.add_argument("--threshold", type=number(positive=True), default=0.05,
                   help="PCK distance in the [-1, 1] box (default 0.05)")
    p.add_argument("--ridge", type=number(0), default=1e-3,
                   help="relative ridge strength of the regressor (default 1e-3; 0: least squares)")
    p.add_argument("--min-fraction", type=number(0, 1), default=0.8,
                   help="keep the semantic ids present together in more than this share of models (default 0.8)")
    p.add_argument("--fit-split", default="train", choices=("train", "val", "test", "all"),
                   help="split the regressor is fitted on (default train)")
    p.add_argument("--test-split", default="test", choices=("train", "val", "test", "all"),
                   help="split it is scored on (default test)")
    _protocol_common(p)

    p = sub.add_parser(
        "parts", help="semantic part correspondence of the keypoints (paper Table 1), ShapeNetPart",
        description="The paper's Table 1 protocol: keypoint k of a shape is associated with every part that has a "
                    "labelled point within 0.05 of it ([-1, 1] box); frequency[k, p] = share of shapes in which k is "
                    "associated with p; score = mean over keypoints of the best part's frequency; part score (the "
                    "reverse reduction) = mean over parts of the best keypoint's frequency.",
        epilog="example:\n  kpd eval parts ../shared/data/shapenetpart_sample --category chair --split all "
               "--model chair --out chair_parts.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=folder,
                   help="ShapeNetPart folder (synsetoffset2category.txt, <synset>/points, points_label)")
    _source_arguments(p)
    p.add_argument("--split", default="test", choices=("train", "val", "test", "all"), help="split (default test)")
    p.add_argument("--radius", type=number(positive=True), default=0.05, help="association distance in the [-1, 1] box")
    _protocol_common(p)

    p = sub.add_parser(
        "das", help="Dual Alignment Score of Skeleton Merger (Shi et al. 2021), KeypointNet",
        description="DAS as in Skeleton Merger's eval_keypointnet.py: mean of the forward score (do the keypoints "
                    "of all pairs of shapes take the same nearest annotated semantic id?) and the backward score "
                    "(do the annotations of one semantic id take the same nearest keypoint?).",
        epilog="example:\n  kpd eval das ../shared/data/keypointnet --category chair --model chair "
               "--out chair_das.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=folder, help="KeypointNet folder")
    _source_arguments(p)
    _geometry_argument(p)
    p.add_argument("--split", default="all", choices=("train", "val", "test", "all"),
                   help="split (default all, as Skeleton Merger)")
    _protocol_common(p)

    p = sub.add_parser(
        "coverage", help="coverage and inclusivity of SC3K (Zohaib and Del Bue 2023), on point clouds",
        description="SC3K's metrics on each cloud (centred on its centroid, unit largest radius): coverage = "
                    "1 - |bbox diagonal of the cloud - bbox diagonal of the keypoints| / cloud diagonal (at least 0); "
                    "inclusivity = share of keypoints closer than 0.05 to the cloud.",
        epilog="example:\n  kpd eval coverage ../shared/data/keypointnet --category chair --model chair "
               "--out chair_coverage.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=folder, help="KeypointNet folder (its pcds/) or ShapeNetPart folder")
    _source_arguments(p)
    p.add_argument("--split", default="all", choices=("train", "val", "test", "all"), help="split (default all)")
    p.add_argument("--threshold", type=number(positive=True), default=0.05,
                   help="inclusivity distance (default 0.05, as SC3K)")
    _protocol_common(p)

    p = sub.add_parser(
        "chamfer", help="alignment chamfer of a bundle (paper Fig. 7), like 'kpd eval alignment' for a run",
        description="Seeded pairs of distinct test meshes; the source's point sample deformed by the bundle's rig to "
                    "the target's keypoints; chamfer (docs/method.md §6) to the target's sample in the [-1, 1] frame, "
                    "x1e3, next to no deformation.",
        epilog="example:\n  kpd eval chamfer ../shared/data/modelnet10 --category chair --model chair "
               "--out chair_chamfer.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=folder, help="dataset folder (ModelNet, ShapeNet, or a flat folder; see kpd train)")
    p.add_argument("--model", required=True, help="bundle: a .kpd folder or zip, or a shipped name (chair)")
    p.add_argument("--pairs", type=integer(1), default=200, help="number of pairs (default 200)")
    p.add_argument("--split-file", type=existing, help="split file overriding the layout's")
    p.add_argument("--category", help="category of the dataset (ModelNet class, ShapeNet synset or name)")
    p.add_argument("--gallery", help="PNG with source / deformed / target meshes and keypoints for the first pairs")
    p.add_argument("--gallery-pairs", type=integer(1, 50), default=4, help="pairs in the gallery (default 4)")
    _protocol_common(p)


def _source_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--category", required=True, help="category name (chair) or synset")
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--model", help="bundle predicting the keypoints: a .kpd folder or zip, or a shipped name")
    group.add_argument("--keypoints", metavar="DIR",
                       help="folder of keypoint files, one per shape: <id>.json or <id>.txt (another method's output)")
    p.add_argument("--keypoints-frame", choices=("file", "unit"), default="file",
                   help="frame of --keypoints files: 'file' = coordinates of the shape's geometry file (default), "
                        "'unit' = the evaluation frame ([-1, 1] box, reference axes)")
    p.add_argument("--up", choices=("auto", "+y", "+z"), default="auto",
                   help="frame the --model was trained in: +z for ModelNet, +y for ShapeNet/KeypointNet as the "
                        "authors use them (default: the bundle's record)")


def _geometry_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--geometry", action="append", default=[], metavar="DIR",
                   help="more folders with geometry of annotated models (<synset>/points/<id>.pts as in "
                        "ShapeNetPart, <synset>/<id>.<ext>, or meshes under <synset>/<id>/); registered to the "
                        "annotations (repeatable)")


def _protocol_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="JSON result")
    p.add_argument("--seed", type=integer(0), default=0, help="seed of the model's point sampling (default 0)")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _keypoint_source(args: argparse.Namespace):
    from kpd import annotations

    if args.keypoints is not None:
        return annotations.FileKeypoints(args.keypoints, frame=args.keypoints_frame)
    from kpd.runtime import Model

    return annotations.ModelKeypoints(Model.load(args.model), up=None if args.up == "auto" else args.up,
                                      seed=args.seed)


def _run_protocol(args: argparse.Namespace) -> int:
    from kpd import annotations

    from kpd.io import Outputs

    inputs = (args.data, getattr(args, "model", None), getattr(args, "keypoints", None),
              getattr(args, "split_file", None), *getattr(args, "geometry", []))
    outputs = Outputs(force=args.force, inputs=inputs)
    out = outputs.file(args.out, "--out", formats=(".json",), what="result (JSON)")
    gallery = None
    if getattr(args, "gallery", None):
        gallery = outputs.file(args.gallery, "--gallery", formats=(".png",), what="gallery (PNG)")
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        def progress(items):
            return tqdm(items, desc="shapes", unit="shape", leave=False)

    if args.task == "pck":
        dataset = annotations.KeypointNet(args.data, args.category)
        result = annotations.pck_protocol(dataset, _keypoint_source(args), geometry_dirs=args.geometry,
                                          threshold=args.threshold, ridge=args.ridge, min_fraction=args.min_fraction,
                                          fit_split=args.fit_split, test_split=args.test_split, progress=progress)
        r = result["results"]
        rows = [(f"PCK@{args.threshold:g}", f"{r['pck']:.3f}"),
                ("mean error", f"{r['error']['mean']:.4f}"),
                ("fit / test shapes", f"{r['fit_shapes']} / {r['test_shapes']}"),
                ("keypoints -> annotated", f"{r['unsupervised_keypoints']} -> {r['annotated_keypoints']}")]
    elif args.task == "parts":
        dataset = annotations.ShapeNetPart(args.data)
        result = annotations.parts_protocol(dataset, args.category, _keypoint_source(args), split=args.split,
                                            radius=args.radius, progress=progress)
        r = result["results"]
        rows = [("part correspondence (per keypoint)", f"{r['score']:.3f}"),
                ("reverse reduction (per part)", f"{r['part_score']:.3f}"),
                ("shapes / keypoints / parts", f"{r['shapes']} / {r['keypoints']} / {len(r['parts'])}")]
    elif args.task == "das":
        dataset = annotations.KeypointNet(args.data, args.category)
        result = annotations.das_protocol(dataset, _keypoint_source(args), split=args.split,
                                          geometry_dirs=args.geometry, progress=progress)
        r = result["results"]
        rows = [("DAS", f"{r['das']:.3f}"), ("forward", f"{r['forward']:.3f}"), ("backward", f"{r['backward']:.3f}"),
                ("shapes / keypoints", f"{r['shapes']} / {r['keypoints']}")]
    elif args.task == "coverage":
        result = annotations.coverage_protocol(args.data, args.category, _keypoint_source(args), split=args.split,
                                               threshold=args.threshold, progress=progress)
        r = result["results"]
        rows = [("coverage", f"{r['coverage']:.3f}"), (f"inclusivity@{args.threshold:g}", f"{r['inclusivity']:.3f}"),
                ("shapes / keypoints", f"{r['shapes']} / {r['keypoints']}")]
    else:
        if args.pairs < 1:
            raise InputError(f"--pairs must be at least 1; got {args.pairs}")
        from kpd.runtime import Model

        model = Model.load(args.model)
        result = annotations.chamfer_protocol(model, args.data, args.category, pairs=args.pairs,
                                              seed=args.seed, split_file=args.split_file, progress=progress)
        r = result["results"]
        if gallery is not None:
            _chamfer_gallery(model, args, result, outputs.stage(gallery))
            result["gallery"] = str(gallery)
        rows = [("chamfer x1e3, model", f"{r['chamfer_x1e3']['model']['mean']:.3f}"),
                ("chamfer x1e3, no deformation", f"{r['chamfer_x1e3']['no_deformation']['mean']:.3f}"),
                ("ratio to no deformation", f"{r['ratio_to_no_deformation']:.3f}"),
                ("pairs / test shapes", f"{result['settings']['pairs']} / {result['data']['test_shapes']}"),
                ("test shapes", _names(result["data"]["test_names"], result["data"]["split_source"]))]
    from kpd import __version__

    result["arguments"] = {k: v for k, v in sorted(vars(args).items()) if not k.startswith("_")}
    result["kpd_version"] = __version__
    with outputs:
        _write_protocol_json(outputs.stage(out), result)
    skipped = result["data"].get("skipped", {"count": 0})
    if skipped["count"]:
        reasons = ", ".join(f"{reason}: {n}" for reason, n in skipped["reasons"].items())
        rows.append(("shapes left out", f"{skipped['count']} ({reasons})"))
    width = max(len(name) for name, _ in rows)
    print(f"{args.task}: {result['data'].get('category', '')} from {args.data}")
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    for note in result.get("notes", []):
        print(f"  note: {note}")
        if args.task == "chamfer":
            print(f"warning: {note}", file=sys.stderr)
    print(f"wrote {out}")
    return 0


def _chamfer_gallery(model, args: argparse.Namespace, result: dict, path: Path) -> None:
    """The first ``--gallery-pairs`` pairs of a chamfer protocol as meshes (source, deformed, target)."""
    from kpd.data import discover
    from kpd.io import read_mesh
    from kpd.viewer.pictures import alignment_sheet

    test = {f.name: f.path for f in discover(args.data, args.category, split_file=args.split_file).splits["test"]}
    chosen = result["results"]["per_pair"][:args.gallery_pairs]
    pairs = [(read_mesh(test[p["source"]]), read_mesh(test[p["target"]])) for p in chosen]
    alignment_sheet(model, pairs, path, titles=[f"{p['source']} -> {p['target']}" for p in chosen],
                    scores=[p["model"] for p in chosen], seed=args.seed)


def _names(names: list, source: str, shown: int = 8) -> str:
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return f"{', '.join(names[:shown])}{more} ({source})"


def _write_protocol_json(path: Path, data: dict) -> None:
    text = json.dumps(data, indent=1, allow_nan=False)
    path.write_text(text + "\n", encoding="utf-8")
