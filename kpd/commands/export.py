"""kpd export: turn a training run (or an authors' checkpoint) into a torch-free model bundle."""

from __future__ import annotations

import argparse

from kpd.commands import folder, integer

HELP = "export a trained model to a bundle (ONNX graphs + manifest) that runs without torch"
EXAMPLE = ("kpd export runs/chair --out chair.kpd    "
           "(or: kpd export --from-authors net_final.pth --category airplane --out airplane.kpd)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", metavar="RUN_OR_CHECKPOINT", nargs="?", default=None,
                        help="a kpd training run folder or its checkpoint.pt")
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
                        help="stop distance of the cage fitted for each rig at run time (default: the training "
                             "one, 0.4; the shipped bundles use 0.2: more local edits)")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from kpd.commands import check_output
    from kpd.errors import InputError

    if (args.checkpoint is None) == (args.from_authors is None):
        raise InputError("give either RUN_OR_CHECKPOINT or --from-authors PTH")
    source = args.checkpoint or args.from_authors
    if not Path(source).exists():
        raise InputError(f"{source}: no such run folder or checkpoint")
    if args.rig_cage_distance is not None and not 0 < args.rig_cage_distance < 1.4:
        raise InputError(f"--rig-cage-distance must lie in (0, 1.4) (the [-1, 1] box); got {args.rig_cage_distance}")
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


def _size(path) -> int:
    from pathlib import Path

    path = Path(path)
    return sum(p.stat().st_size for p in path.iterdir()) if path.is_dir() else path.stat().st_size
