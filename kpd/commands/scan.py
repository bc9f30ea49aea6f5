"""kpd scan: clean a real scan, orient it to a reference shape or a model's template, normalise it."""

from __future__ import annotations

import argparse

from kpd.commands import integer

HELP = ("clean a real scan, turn it into a reference's or a model's frame and normalise it to [-1, 1] (with a "
        "report); or bring a folder of scans into one frame")
EXAMPLE = ("kpd scan my_sneaker.ply --reference sneaker_template.ply --out aligned.ply --report report.json --up z "
           "--picture check.png\n  kpd scan ../shared/data/gso_shoes --out shoes_aligned   "
           "# a folder: groupwise, no reference; kpd train shoes_aligned reads the result")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scan", metavar="SCAN", help="the scan: a mesh (.obj .ply .off .stl .gltf .glb) or points "
                                                      "(.ply .pcd .xyz .pts .npy .npz); or a folder of them (or of "
                                                      "sub-folders with one each): collection mode")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--reference", metavar="REF", default=None,
                        help="a shape in the frame to turn the scan into (mesh or points)")
    source.add_argument("--model", metavar="MODEL", default=None,
                        help="a bundle (.kpd folder, .zip, or a shipped name: chair): orient to its template shape")
    parser.add_argument("--out", required=True, help="the cleaned, oriented, normalised scan (a mesh scan needs a "
                                                     "mesh format; a point scan a point format); collection mode: "
                                                     "the aligned folder to create")
    parser.add_argument("--report", default=None, help="JSON report: the cleaning counts, the orientation scores "
                                                       "and the 4x4 transforms to the aligned frame and back "
                                                       "(required for one scan; collection mode: OUT/alignment.json)")
    parser.add_argument("--up", default=None, metavar="AXIS",
                        help="the scan's known up axis (x, y, z, -z, ...): only rotations about it are searched, "
                             "and a ground plane below the scan may be removed")
    parser.add_argument("--reference-up", default=None, metavar="AXIS",
                        help="the reference's up axis (default: the model's recorded up axis, else --up); without "
                             "--up it still helps: each hypothesis is stood on the scan's own support plane")
    parser.add_argument("--no-outliers", action="store_true", help="keep statistical outliers (point scans)")
    parser.add_argument("--no-ground", action="store_true", help="never remove a ground plane")
    parser.add_argument("--ground", action="store_true",
                        help="look for a ground plane even without --up (may take a table top for a floor)")
    parser.add_argument("--no-pieces", action="store_true", help="keep small disconnected pieces (mesh scans)")
    parser.add_argument("--reference-points", type=integer(10), default=5000,
                        help="points sampled on a mesh reference (default 5000)")
    parser.add_argument("--picture", metavar="PNG", default=None,
                        help="also draw the scan as given, and over the reference as the best and the runner-up "
                             "rotation, to check by eye")
    parser.add_argument("--seed", type=integer(0), default=0, help="seed of sampling, RANSAC and subsets (default 0)")
    parser.add_argument("--force", action="store_true", help="replace --out and --report if they exist")
    g = parser.add_argument_group("collection mode (SCAN is a folder)")
    g.add_argument("--rounds", type=int, default=3,
                   help="at most this many registrations of the collection to a re-estimated template (default 3)")
    g.add_argument("--processes", type=int, default=1,
                   help="worker processes orienting shapes (default 1; each uses one core)")
    g.add_argument("--points", type=int, default=5000, help="surface points sampled per shape (default 5000)")
    g.add_argument("--no-stand", action="store_true",
                   help="without --up, do not stand the aligned shapes on the floor they share (kpd.collection."
                        "floor_up; default: the shared frame's up axis is found from the decided shapes' flat "
                        "contact and each is turned onto its own support plane)")
    g.add_argument("--all-surface", action="store_true",
                   help="sample every face, also those inside the shape (default: the outer surface only)")


def run(args: argparse.Namespace) -> int:
    import json
    import sys
    from pathlib import Path

    from kpd.frame import ambiguity_advice
    from kpd.errors import InputError
    from kpd.geometry import sample_surface
    from kpd.io import MESH_FORMATS, POINT_FORMATS, Mesh, Outputs, mesh_companions, read_shape, write_mesh, write_points
    from kpd.scan import parse_axis, preprocess

    if Path(args.scan).is_dir():
        return run_collection(args)
    if args.report is None:
        raise InputError("--report is required for one scan (the transforms that map results back onto it)")
    if args.ground and args.no_ground:
        raise InputError("--ground and --no-ground contradict each other; give one")
    for name in ("up", "reference_up"):
        if getattr(args, name) is not None:
            parse_axis(getattr(args, name), "--" + name.replace("_", "-"))
    out_suffix = Path(args.out).suffix.lower()
    outputs = Outputs(force=args.force, inputs=(args.scan, args.reference, args.model))
    out = outputs.file(args.out, "--out", formats=MESH_FORMATS + POINT_FORMATS, what="mesh or point")
    report_path = outputs.file(args.report, "--report", formats=(".json",), what="report (JSON)")
    picture = None
    if args.picture is not None:
        if args.reference is None and args.model is None:
            raise InputError("--picture shows the orientation: give --reference or --model")
        picture = outputs.file(args.picture, "--picture", formats=(".png",), what="picture (PNG)")

    scan = read_shape(args.scan)
    is_mesh = isinstance(scan, Mesh)
    formats = MESH_FORMATS if is_mesh else POINT_FORMATS
    if out_suffix not in formats:
        kind = "mesh" if is_mesh else "point cloud"
        raise InputError(f"--out {args.out}: the scan is a {kind}, so --out must end in one of {' '.join(formats)}")
    if is_mesh:
        outputs.companions(out, mesh_companions(out, scan))

    reference_up = args.reference_up
    if args.model is not None:
        from kpd.bundle import read_bundle
        from kpd.errors import BundleError

        bundle = read_bundle(args.model)
        reference = bundle.template_points
        if reference is None:
            raise BundleError(f"{args.model}: the bundle has no template shape to orient scans to; give --reference")
        reference_name = f"model {args.model} template ({bundle.manifest.get('template', {}).get('source')})"
        if reference_up is None:  # the model's frame records its up axis; it turns on the support prior
            reference_up = bundle.manifest.get("input", {}).get("up")
    elif args.reference is not None:
        shape = read_shape(args.reference)
        if isinstance(shape, Mesh):
            reference = sample_surface(shape.vertices, shape.triangles, args.reference_points, args.seed).points
        else:
            reference = shape.points
        reference_name = str(args.reference)
    else:
        reference, reference_name = None, None

    clean_params = {"outliers": not args.no_outliers, "pieces": not args.no_pieces, "seed": args.seed,
                    "ground": False if args.no_ground else (True if args.ground else None), "up": args.up}
    orient_params = {"seed": args.seed}
    if args.up is not None:
        orient_params["up"] = args.up
    if reference_up is not None:
        orient_params["reference_up"] = reference_up
    result = preprocess(scan, reference, clean_params=clean_params, **orient_params)

    record = {
        "scan": str(args.scan),
        "reference": reference_name,
        "up": args.up,
        "reference_up": reference_up,
        "output": str(out),
        "frame": "aligned = transform @ [x, y, z, 1] of the cleaned scan; inverse maps back (original units)",
        **result.to_dict(),
    }
    with outputs:
        if picture is not None:
            from kpd.viewer.figures import alignment_picture

            alignment_picture(result, reference, outputs.stage(picture), up=reference_up or args.up or "z",
                              seed=args.seed)
        if is_mesh:
            write_mesh(outputs.stage(out), result.shape)
        else:
            write_points(outputs.stage(out), result.shape)
        outputs.stage(report_path).write_text(json.dumps(record, indent=1) + "\n")

    c = result.clean
    removed = ", ".join(f"{name} {value}" for name, value in (("outliers", c.outliers_removed),
                                                               ("ground", c.ground_removed),
                                                               ("small-piece vertices", c.pieces_vertices_removed))
                        if value)
    print(f"cleaned: {c.input_count} -> {c.output_count} points ({removed or 'nothing removed'})")
    o = result.orientation
    if o is None:
        print("not oriented (no --reference or --model): cleaned and normalised only")
    else:
        runner = "none" if o.runner_up_rotation is None else f"{o.runner_up_score:.4f} at {o.runner_up_angle:.0f} deg"
        print(f"oriented: score {o.score:.4f}, runner-up {runner}, margin {o.margin:.3f}")
        if o.ambiguous:
            print(f"warning: {ambiguity_advice(args.up is not None, o, reference_up)}", file=sys.stderr)
    print(f"wrote {out} and {report_path}" + (f" and {picture}" if picture is not None else ""))
    return 0


def run_collection(args: argparse.Namespace) -> int:
    """``kpd scan FOLDER --out ALIGNED``: groupwise alignment of a collection (kpd.collection).

    The aligned folder holds one file per decided shape (the input turned into the shared frame, same format and
    units), ``ambiguous/`` with the flagged ones (turned by their best rotation), ``alignment.json`` (the report) and
    ``contact_sheet.png``. It is built in a hidden sibling folder that keeps the state of the run, so a killed run
    started again with the same arguments continues where it stopped; the folder appears at ``--out`` when complete.
    """
    import json
    import os
    import shutil
    import time
    from pathlib import Path

    import numpy as np

    from kpd.collection import align_collection, collection_points, find_shapes
    from kpd.errors import InputError, KpdError
    from kpd.io import Mesh, Outputs, read_shape, write_mesh, write_points
    from kpd.scan import parse_axis
    from kpd.viewer.figures import contact_sheet

    if args.reference is not None or args.model is not None:
        raise InputError("collection mode (SCAN is a folder) needs no --reference or --model: the collection's "
                         "medoid is the template")
    if args.up is not None:
        parse_axis(args.up, "--up")
    for name in ("rounds", "processes"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name} must be at least 1; got {getattr(args, name)}")
    if args.points < 100:
        raise InputError(f"--points must be at least 100; got {args.points}")
    out = Path(args.out)
    source = Path(args.scan).resolve()
    if out.resolve() == source or source in out.resolve().parents:
        raise InputError(f"--out {out} lies inside the collection {args.scan}; choose another folder")
    outputs = Outputs(force=args.force, inputs=(args.scan,))
    out = outputs.folder(out, "--out")
    extra = {name: outputs.file(value, option, formats=(suffix,), what=what)
             for option, value, suffix, what, name in (
                 ("--report", args.report, ".json", "JSON", "alignment.json"),
                 ("--picture", args.picture, ".png", "PNG", "contact_sheet.png")) if value is not None}
    shapes = find_shapes(args.scan)
    staging = out.parent / f".{out.name}.partial"  # the run's work and state: a run stopped there continues
    staging.mkdir(exist_ok=True)
    (staging / "ambiguous").mkdir(exist_ok=True)
    print(f"{len(shapes)} shapes in {args.scan}; working in {staging} (a run stopped there continues)")

    started = time.perf_counter()
    from tqdm import tqdm

    loaded, clouds = [], []
    for _, path in tqdm(shapes, desc="reading", unit="shape"):
        try:
            shape = read_shape(path)
            clouds.append(collection_points(shape, args.points, seed=args.seed, outer=not args.all_surface))
        except KpdError as exc:
            raise InputError(f"{path}: {exc}") from exc
        loaded.append(shape)
    read_seconds = time.perf_counter() - started
    started = time.perf_counter()
    result = align_collection(clouds, [n for n, _ in shapes], up=args.up, rounds=args.rounds,
                              processes=args.processes, state=staging / "state.json", progress=True,
                              seed=args.seed, stand=not args.no_stand)
    align_seconds = time.perf_counter() - started

    rows = []
    for (name, path), shape, item in zip(shapes, loaded, result.shapes):
        where = staging / ("ambiguous" if item.ambiguous else "") / (name + path.suffix.lower())
        rotation = item.rotation
        if isinstance(shape, Mesh):
            write_mesh(where, shape.with_vertices(shape.vertices @ rotation.T))
        else:
            write_points(where, shape.points @ rotation.T,
                         None if shape.normals is None else shape.normals @ rotation.T, shape.colors)
        rows.append({**item.to_dict(), "source": str(path), "output": str(out / where.relative_to(staging))})
    report = {"collection": str(args.scan), "output": str(out), "up": args.up, "seed": args.seed,
              "surface": "all" if args.all_surface else "outer", "points": args.points,
              "frame": "output = transform @ [x, y, z, 1] of the input (a rotation: the input's units and origin)",
              "seconds": {"reading": read_seconds, "aligning_this_run": align_seconds,
                          "per_shape": float(result.seconds.mean())},
              **{k: v for k, v in result.to_dict().items() if k != "shapes"}, "shapes": rows}
    (staging / "alignment.json").write_text(json.dumps(report, indent=1) + "\n")
    floor_up = (result.floor or {}).get("up")
    contact_sheet(clouds, result, staging / "contact_sheet.png", up=args.up or floor_up, seed=args.seed)
    (staging / "state.json").unlink()
    with outputs:  # the finished folder and the copies placed by the one writer, all together or none
        shutil.copytree(staging, outputs.stage(out), copy_function=os.link)  # hard links: no second copy on disk
        for name, path in extra.items():
            shutil.copyfile(staging / name, outputs.stage(path))
    shutil.rmtree(staging)
    flagged = int(result.ambiguous.sum())
    print(f"aligned {len(shapes) - flagged} shapes, {flagged} flagged ambiguous (in {out / 'ambiguous'}); "
          f"{len(result.templates)} round(s), templates {', '.join(result.templates)}; "
          f"{result.seconds.mean():.2f} s per shape")
    if floor_up is not None:
        print(f"stood {result.floor['stood']} shapes on the floor they share (up {np.round(floor_up, 3).tolist()} in "
              f"the shared frame; median tilt {result.floor['tilt_median_deg']:.1f} degrees)")
    print(f"wrote {out} (alignment.json, contact_sheet.png)")
    return 0
