"""kpd keypoints: predict a shape's keypoints with a model bundle."""

from __future__ import annotations

import argparse
import json
import sys

from kpd.commands import add_check, integer, shipped_names

HELP = "predict the keypoints of a mesh or point cloud (written in the input's own frame and units)"
EXAMPLE = "kpd keypoints chair my_chair.obj --out my_chair_keypoints.json"


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """MODEL, the seed and the onnxruntime threads (shared by the commands that run a model)."""
    parser.add_argument("model", metavar="MODEL",
                        help=f"a bundle (.kpd folder or .zip) or a shipped name: {shipped_names()}")
    parser.add_argument("--seed", type=integer(0), default=0,
                        help="surface-sampling seed (default 0: same result every run)")
    parser.add_argument("--threads", type=integer(1), default=None, help="onnxruntime intra-op threads (default: its own)")


def add_scan_arguments(parser: argparse.ArgumentParser) -> None:
    """``--scan`` and ``--up`` (which needs ``--scan``, checked alike for every command that has them)."""
    add_check(parser, check_scan_arguments)
    parser.add_argument("--scan", action="store_true",
                        help="treat the input as a real scan: clean it and orient it to the model's template first "
                             "(kpd.scan); results are mapped back onto the scan")
    parser.add_argument("--up", default=None, metavar="AXIS",
                        help="with --scan: the scan's known up axis (x, y, z, -z...), restricting the orientation search")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_model_arguments(parser)
    parser.add_argument("shape", metavar="SHAPE", help="mesh or point cloud (.obj .ply .off .stl .gltf .glb .pcd "
                                                        ".xyz .pts .npy .npz)")
    parser.add_argument("--out", default=None, help="keypoints file to write (.json, or .txt as the authors' "
                                                    "'%%03d x y z' rows); printed as JSON when omitted")
    add_scan_arguments(parser)
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def check_scan_arguments(args: argparse.Namespace) -> None:
    from kpd.errors import InputError

    if args.up is not None:
        from kpd.scan import parse_axis  # here: kpd.scan (scipy) is slow to import and most runs need none of it

        if not args.scan:
            raise InputError("--up goes with --scan (the scan's known up axis); add --scan or drop --up")
        parse_axis(args.up, "--up")


def warn_frame(model, shape, seed: int, name: str) -> None:
    """Without --scan: one warning line if the shape sits turned in the model's frame or is probably not of the
    category (:func:`kpd.frame.frame_warnings`)."""
    from kpd.frame import frame_warnings

    for line in frame_warnings(model, shape, seed=seed, name=name):
        print(f"warning: {line}", file=sys.stderr)


def scan_frame(args: argparse.Namespace, model, shape, **kwargs):
    """``--scan``: the shape oriented into the model's frame (:class:`kpd.frame.ScanFrame`), searched with ``--up``
    or, for glTF, the file's y up; what it decided is printed (stderr)."""
    from kpd.frame import ScanFrame
    from kpd.io import file_up

    scan = ScanFrame(model, shape, args.up or file_up(args.shape), **kwargs)
    for line in scan.warnings:
        print(f"warning: {line}", file=sys.stderr)
    for line in scan.notes:
        print(f"note: {line}", file=sys.stderr)
    return scan


def load_model(args: argparse.Namespace):
    from kpd.runtime import Model

    return Model.load(args.model, threads=args.threads)


def check_suffix(path: str, formats: tuple, what: str, option: str = "--out") -> None:
    from pathlib import Path

    from kpd.errors import InputError

    if Path(path).suffix.lower() not in formats:
        raise InputError(f"{option} {path}: a {what} file must end in one of {' '.join(formats)}")


def run(args: argparse.Namespace) -> int:
    from kpd.io import KEYPOINT_FORMATS, Outputs, read_shape, write_keypoints

    with Outputs(force=args.force, inputs=(args.shape,)) as outputs:
        out = None
        if args.out is not None:
            out = outputs.file(args.out, "--out", formats=KEYPOINT_FORMATS, what="keypoint")
        model = load_model(args)
        shape = read_shape(args.shape)
        meta = {"model": str(args.model), "category": model.category, "shape": str(args.shape), "frame": "input",
                "seed": args.seed}
        if args.scan:
            scan = scan_frame(args, model, shape, seed=args.seed)
            keypoints = scan.to_original(model.keypoints(scan.result.shape, seed=args.seed))
            meta["scan"] = scan.report()
        else:
            warn_frame(model, shape, args.seed, args.shape)
            keypoints = model.keypoints(shape, seed=args.seed)
        if out is None:
            print(json.dumps({"keypoints": keypoints.tolist(), **meta}, indent=2))
            return 0
        if out.suffix.lower() == ".txt":
            write_keypoints(outputs.stage(out), keypoints)
        else:
            write_keypoints(outputs.stage(out), keypoints, **meta)
    print(f"wrote {out} ({len(keypoints)} keypoints)")
    return 0


_MOVED = ("ScanFrame", "settle_orientation", "ambiguity_advice", "SETTLE_POINTS")


def __getattr__(name: str):  # moved to kpd.frame; importable from here as before, without importing it early
    if name in _MOVED:
        import kpd.frame

        return getattr(kpd.frame, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
