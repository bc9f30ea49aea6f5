"""kpd align: deform a source mesh so that its keypoints move to a target's."""

from __future__ import annotations

import argparse
import sys

HELP = "deform a source mesh to a target shape through their keypoints (source topology, UVs and colours kept)"
EXAMPLE = "kpd align chair source_chair.obj target_chair.ply --out source_like_target.obj"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_model_arguments, add_scan_arguments

    add_model_arguments(parser)
    parser.add_argument("source", metavar="SOURCE", help="the mesh to deform")
    parser.add_argument("target", metavar="TARGET", help="the shape to align to (mesh or point cloud)")
    add_scan_arguments(parser)
    parser.add_argument("--out", required=True, help="deformed source mesh (.obj .ply .off .stl .gltf .glb)")
    parser.add_argument("--keypoints", default=None, metavar="JSON",
                        help="also write the source's and the target's keypoints (in the source's frame) here")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    import json
    from concurrent.futures import ThreadPoolExecutor

    from kpd.commands._shared import frame_lines, load_model, rig_checked, scan_frame
    from kpd.frame import ScanRig
    from kpd.io import MESH_FORMATS, Outputs, mesh_companions, read_mesh, read_shape, write_mesh

    with Outputs(force=args.force, inputs=(args.source, args.target)) as outputs:
        out = outputs.file(args.out, "--out", formats=MESH_FORMATS, what="mesh")
        extra = None
        if args.keypoints is not None:
            extra = outputs.file(args.keypoints, "--keypoints", formats=(".json",), what="keypoint")
        model = load_model(args)
        source = read_mesh(args.source)
        outputs.companions(out, mesh_companions(out, source))
        target = read_shape(args.target)
        if args.scan:
            # both oriented into the model's frame (--up, when given, is both shapes' up axis); the source is deformed
            # there and written in its own frame (a ScanRig)
            source_scan = scan_frame(args, model, source, path=args.source)
            target_scan = scan_frame(args, model, target, path=args.target)
            aligned = source.with_vertices(source_scan.to_aligned(source.vertices))
            rig = ScanRig(model.rig(aligned, seed=args.seed), source, source_scan)
            prediction = model.predict(target_scan.result.shape, seed=args.seed)
        else:
            prediction = model.predict(target, seed=args.seed)
            # the frame checks beside the binding, each from its shape's one surface sample (rig_checked: the source's
            # on a thread of its own, its warnings first), as the other commands that bind do
            with ThreadPoolExecutor(1, thread_name_prefix="kpd-target-check") as pool:
                target_check = pool.submit(frame_lines, model, target, args.seed, args.target, prediction=prediction)
                rig = rig_checked(model, source, args.seed, args.source)
                target_warnings = target_check.result()
            for line in target_warnings:
                print(f"warning: {line}", file=sys.stderr)
        target_keypoints = rig.normalizer.invert(prediction.keypoints)  # target's shape, source's frame
        write_mesh(outputs.stage(out), rig.deformed_mesh(target_keypoints))
        if extra is not None:
            text = json.dumps({"source_keypoints": rig.keypoints.tolist(),
                               "target_keypoints": target_keypoints.tolist(), "frame": "source",
                               "model": str(args.model), "scan": bool(args.scan)}, indent=2)
            outputs.stage(extra).write_text(text + "\n")
    print(f"wrote {out} ({len(source.vertices)} vertices, source deformed to the target's {model.num_keypoints} "
          "keypoints)" + (f" and {extra}" if extra is not None else ""))
    return 0
