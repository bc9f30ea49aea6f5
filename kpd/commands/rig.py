"""kpd rig: a shape's rig, as glTF morph targets (Blender, engines, the browser) or as kpd's own ``.npz``."""

from __future__ import annotations

import argparse
from pathlib import Path

from kpd.commands._shared import morph_rig  # noqa: F401  (importable from here as before)
from kpd.errors import InputError

HELP = ("rig a shape for editing anywhere: glTF morph targets (.glb, .gltf: Blender shape keys, three.js, game "
        "engines) or kpd's own rig (.npz)")
EXAMPLE = ("kpd rig chair my_chair.obj --out my_chair.glb    (then Blender's File > Import > glTF 2.0: the shape keys "
           "keypoint_<i>_x|y|z move keypoint i by their value in the shape's units, prior_<i>_x|y|z with the others "
           "following the category prior, pca_<c> by standard deviations of the prior; docs/rigs.md)")

RIG_FORMATS = (".glb", ".gltf", ".npz")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_model_arguments, add_scan_arguments

    add_model_arguments(parser)
    parser.add_argument("shape", metavar="SHAPE", help="the mesh to rig (.obj .ply .off .stl .gltf .glb)")
    parser.add_argument("--out", required=True, help="the rig to write: .glb (one file), .gltf (with a .bin beside "
                                                     "it) or .npz (kpd's rig, for kpd deform/view/render --rig)")
    parser.add_argument("--view-up", default=None, metavar="AXIS",
                        help="the shape's up axis (default: the one --scan recovered, else +y for .gltf/.glb input, "
                             "else the model's: +z for chair and table, +y for shoe); glTF files turn it to glTF's +Y "
                             "with a root node, so that Blender and web viewers show the shape upright")
    parser.add_argument("--targets", default="keypoint,prior,pca", metavar="KINDS",
                        help="glTF files: the kinds of morph targets to write, of keypoint, prior, pca (default all; "
                             "'keypoint' alone is 45%% of the size and spans every edit as sums)")
    add_scan_arguments(parser)
    parser.add_argument("--force", action="store_true", help="replace --out (and a .gltf's .bin) if it exists")


def run(args: argparse.Namespace) -> int:
    from kpd.commands._shared import load_model, model_beside_read, rig_checked, scan_frame, shape_view
    from kpd.io import Outputs
    from kpd.morph import MorphRig, up_rotation, write_gltf

    with Outputs(force=args.force, inputs=(args.shape,)) as outputs:
        out = outputs.file(args.out, "--out", formats=RIG_FORMATS, what="rig")
        ext = out.suffix.lower()
        if ext == ".npz" and args.scan:
            raise InputError(f"--out {out}: kpd's .npz rig holds no scan frame; with --scan write .glb or .gltf "
                             "(in the scan's own frame)")
        if ext == ".gltf":
            outputs.companions(out, [out.stem + ".bin"])
        if args.view_up is not None:
            up_rotation(args.view_up)  # a bad axis ends here, before any work
        kinds = [k.strip() for k in args.targets.split(",") if k.strip()]
        unknown = sorted(set(kinds) - {"keypoint", "prior", "pca"})
        if unknown or not kinds:
            raise InputError(f"--targets must name some of keypoint, prior, pca; got {args.targets!r}")
        model, mesh = model_beside_read(lambda: load_model(args), args.shape)
        frame, scan = None, None
        if args.scan:
            # orient with the scan pipeline, rig the whole mesh there, write the targets in the scan's own frame
            scan = scan_frame(args, model, mesh)
            rig = model.rig(mesh.with_vertices(scan.to_aligned(mesh.vertices)), seed=args.seed)
            frame = scan.result.transform
        else:
            rig = rig_checked(model, mesh, args.seed, args.shape)
        if ext == ".npz":
            rig.save(outputs.stage(out))
            what = f"{rig.num_keypoints} keypoints"
        else:
            meta = {"model": str(args.model), "category": model.category, "shape": Path(args.shape).name,
                    "seed": args.seed, "scan": bool(args.scan)}
            morph = MorphRig.from_rig(rig, model.prior, mesh=mesh if frame is not None else None, frame=frame,
                                      meta=meta)
            chosen = [n for n in morph.names if n.split("_", 1)[0] in kinds]
            if not chosen:
                raise InputError(f"--targets {args.targets}: this bundle has no category prior, so only keypoint "
                                 "targets can be written")
            from tqdm import tqdm

            with tqdm(desc="morph targets written", unit="B", unit_scale=True, leave=False) as bar:  # GBs at scan sizes

                def progress(written: int, total: int) -> None:
                    bar.total = total
                    bar.update(written - bar.n)

                up = args.view_up or shape_view(model, args.shape, scan)[0] or "+z"
                write_gltf(outputs.stage(out), morph, name=Path(args.shape).stem, up=up, targets=chosen,
                           progress=progress)
            what = f"{len(chosen)} morph targets"
    companion = f" and {out.with_suffix('.bin').name}" if ext == ".gltf" else ""
    prior_note = "" if ext == ".npz" or model.prior is not None else " (the bundle has no prior: keypoint targets only)"
    print(f"wrote {out}{companion} ({len(mesh.vertices)} vertices, {what}{prior_note})")
    return 0
