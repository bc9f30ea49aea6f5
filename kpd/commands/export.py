"""kpd export: turn a training run (or an authors' checkpoint) into a torch-free model bundle."""

from __future__ import annotations

import argparse

from kpd.commands import folder, integer, require_train_extra

HELP = "export a trained model to a bundle (ONNX graphs + manifest) that runs without torch"
EXAMPLE = ("kpd export runs/chair --out chair.kpd    "
           "(or: kpd export --from-authors net_final.pth --category airplane --out airplane.kpd; "
           "or a bundle with other rig settings: kpd export chair.kpd --rig-cage-distance 0.3 --out chair-03.kpd)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", metavar="RUN_OR_CHECKPOINT", nargs="?", default=None,
                        help="a kpd training run folder or its checkpoint.pt; or a bundle (.kpd folder or .zip), "
                             "written again with the rig settings given (no torch needed)")
    parser.add_argument("--from-authors", metavar="PTH", default=None,
                        help="instead: a checkpoint of the authors' trainer (net_final.pth, {'states': ...})")
    parser.add_argument("--out", required=True, help="bundle to write: a .kpd folder, or a .zip of the same files")
    parser.add_argument("--category", default=None, help="category name (required with --from-authors; "
                                                         "default: the run's)")
    parser.add_argument("--data", type=folder, default=None, metavar="DIR",
                        help="training data for the prior and the template cloud (default: the run's own data; "
                             "with --from-authors the bundle has no prior unless given)")
    parser.add_argument("--cache", default=None, metavar="DIR", help="sample cache folder (default: the run's)")
    parser.add_argument("--no-prior", action="store_true", help="do not fit the category prior")
    parser.add_argument("--points", type=integer(1), default=1024,
                        help="with --from-authors: points per shape the model was trained on (default 1024)")
    parser.add_argument("--up", default=None, metavar="AXIS",
                        help="the training frame's up axis to record (+z for ModelNet, +y for ShapeNet)")
    parser.add_argument("--rig-cage-distance", type=float, default=None, metavar="D",
                        help="stop distance of the cage fitted for each rig at run time, the learned influence "
                             "transferred to it (default: the training cage, 0.4; the shipped chair and table use "
                             "0.2: more local edits); 0 with a bundle: rig with the training cage again")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from kpd.commands import check_output
    from kpd.errors import InputError

    if (args.checkpoint is None) == (args.from_authors is None):
        raise InputError("give either RUN_OR_CHECKPOINT or --from-authors PTH")
    source = args.checkpoint or args.from_authors
    if args.checkpoint is not None and not Path(source).exists():
        from kpd.bundle import resolve_bundle
        from kpd.errors import BundleError

        try:  # a shipped bundle by name (kpd export chair --rig-cage-distance 0 --out loose.kpd)
            source = str(resolve_bundle(source))
        except BundleError:
            pass  # refused just below, as a missing run
    if not Path(source).exists():
        raise InputError(f"{source}: no such run folder or checkpoint")
    is_bundle = args.checkpoint is not None and (
        (Path(source) / "manifest.json").is_file() or (Path(source).suffix == ".zip" and Path(source).is_file()))
    if args.rig_cage_distance is not None and not (0 < args.rig_cage_distance < 1.4 or
                                                   (is_bundle and args.rig_cage_distance == 0)):
        raise InputError(f"--rig-cage-distance must lie in (0, 1.4) (the [-1, 1] box); got {args.rig_cage_distance}")
    if is_bundle:
        return _rewrite_bundle(args, source)
    require_train_extra()  # a bundle is written again without torch; a checkpoint needs torch and the exporter
    if args.up is not None and args.up.strip().lower().lstrip("+-") not in ("x", "y", "z"):
        raise InputError(f"--up must be one of x, y, z, +x, -y...; got {args.up!r}")
    out = check_output(args.out, force=args.force, inputs=(source, args.data, args.cache),
                       kind="file" if Path(args.out).suffix == ".zip" else "folder")
    from kpd.export.build import export_authors, export_checkpoint  # imports torch

    up = None if args.up is None else ("+" + args.up.lstrip("+") if not args.up.startswith("-") else args.up)
    if args.from_authors is not None:
        result = export_authors(args.from_authors, out, category=args.category, data=args.data,
                                point_count=args.points, fit_prior=not args.no_prior, up=up, force=args.force)
    else:
        result = export_checkpoint(args.checkpoint, out, category=args.category, data=args.data,
                                   cache_dir=args.cache, fit_prior=not args.no_prior, up=up, force=args.force,
                                   rig_cage_distance=args.rig_cage_distance)
    manifest = result.manifest
    prior = manifest["prior"]
    size = _size(result.path)
    print(f"wrote {result.path} ({size / 1e6:.1f} MB): {manifest['category']}, K={manifest['model']['keypoints']}, "
          f"C={manifest['model']['cage_vertices']}, prior: "
          f"{'%d components' % prior['n_components'] if prior else 'none'}; onnxruntime vs torch max |diff| "
          f"{max(result.parity.keypoints, result.parity.influence):.1e} on {result.parity.shapes} shapes")
    return 0


def _rewrite_bundle(args: argparse.Namespace, source: str) -> int:
    """A bundle written again with other rig settings (the graphs, prior and record unchanged)."""
    from kpd.bundle import read_bundle, with_rig_fit, write_bundle
    from kpd.commands import check_output
    from kpd.errors import InputError

    given = [flag for flag, value in (("--from-authors", args.from_authors), ("--category", args.category),
                                      ("--data", args.data), ("--cache", args.cache), ("--no-prior", args.no_prior),
                                      ("--up", args.up)) if value]
    if given:
        raise InputError(f"{source} is a bundle: only --rig-cage-distance, --out and --force apply to it "
                         f"(not {', '.join(given)})")
    if args.rig_cage_distance is None:
        raise InputError(f"{source} is a bundle: give --rig-cage-distance D (0: the training cage) to write it "
                         "with other rig settings")
    bundle = read_bundle(source)
    out = check_output(args.out, force=args.force, inputs=(source,),
                       kind="file" if args.out.endswith(".zip") else "folder")
    fit = bundle.manifest["cage"].get("fit") or {}
    rig = {"distance": args.rig_cage_distance} if args.rig_cage_distance else None
    note = (f"rigs fit their cage at {args.rig_cage_distance} (training: {fit.get('distance', 0.4)}) and transfer "
            "the learned influence to it (kpd.rig.transfer_influence)") if rig else None
    manifest, files = with_rig_fit(bundle, rig, note)
    path = write_bundle(out, files, force=args.force)
    print(f"wrote {path}: {manifest['category']}, rig cage "
          f"{'at %g, influence transferred' % args.rig_cage_distance if rig else 'as in training'}")
    return 0


def _size(path) -> int:
    from pathlib import Path

    path = Path(path)
    return sum(p.stat().st_size for p in path.iterdir()) if path.is_dir() else path.stat().st_size
