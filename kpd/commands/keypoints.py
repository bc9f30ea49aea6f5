"""kpd keypoints: predict a shape's keypoints with a model bundle."""

from __future__ import annotations

import argparse
import json

from kpd.commands._shared import (  # noqa: F401  (importable from here as before)
    add_model_arguments, add_scan_arguments, check_scan_arguments, check_suffix, frame_lines, load_model,
    model_beside_read, rig_checked, scan_frame, warn_frame,
)

HELP = "predict the keypoints of a mesh or point cloud (written in the input's own frame and units)"
EXAMPLE = "kpd keypoints chair my_chair.obj --out my_chair_keypoints.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_model_arguments(parser)
    parser.add_argument("shape", metavar="SHAPE", help="mesh or point cloud (.obj .ply .off .stl .gltf .glb .pcd "
                                                        ".xyz .pts .npy .npz)")
    parser.add_argument("--out", default=None, help="keypoints file to write (.json, or .txt as the authors' "
                                                    "'%%03d x y z' rows); printed as JSON when omitted")
    add_scan_arguments(parser)
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    from kpd.io import KEYPOINT_FORMATS, Outputs, read_shape, write_keypoints

    with Outputs(force=args.force, inputs=(args.shape,)) as outputs:
        out = None
        if args.out is not None:
            out = outputs.file(args.out, "--out", formats=KEYPOINT_FORMATS, what="keypoint")
        model, shape = model_beside_read(lambda: load_model(args), args.shape, read_shape)
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
