"""kpd deform: move keypoints and write the deformed mesh."""

from __future__ import annotations

import argparse

import numpy as np

from kpd.commands import integer, shipped_names
from kpd.commands._shared import load_rig, parse_move, parse_moves, warn_moves  # noqa: F401  (importable as before)
from kpd.errors import InputError

HELP = "move keypoints of a shape and write the deformed mesh (same topology, UVs and colours)"
EXAMPLE = ("kpd deform chair my_chair.obj --move 8:0,0,5 --move 9:0,0,5 --out taller_back.obj    "
           "(8 and 9: the top corners of the backrest; with --prior, moving one leg moves its partner: "
           "kpd deform chair my_chair.obj --move 1:-3,0,0 --prior --out wider.obj)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_scan_arguments

    parser.add_argument("model", metavar="MODEL", nargs="?", default=None,
                        help=f"a bundle (.kpd folder or .zip) or a shipped name ({shipped_names()}); not with --rig")
    parser.add_argument("shape", metavar="SHAPE", nargs="?", default=None, help="the mesh to deform (with MODEL)")
    parser.add_argument("--rig", default=None, help="instead of MODEL SHAPE: a rig (.npz from kpd) or a folder in the "
                                                    "authors' demo format")
    parser.add_argument(
        "--move", action="append", default=[], metavar="I:DX,DY,DZ",
        help="move keypoint I by (DX, DY, DZ) in the shape's own units; repeat for several keypoints",
    )
    parser.add_argument("--prior", action="store_true",
                        help="move the other keypoints as the model's category prior says (e.g. a leg's partner)")
    parser.add_argument("--out", required=True, help="deformed mesh to write (.obj .ply .off .stl .gltf .glb)")
    parser.add_argument("--seed", type=integer(0), default=0, help="surface-sampling seed (with MODEL)")
    parser.add_argument("--threads", type=integer(1), default=None, help="onnxruntime intra-op threads (with MODEL)")
    add_scan_arguments(parser)
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    from kpd.io import MESH_FORMATS, Outputs, mesh_companions, write_mesh

    with_model = args.model is not None or args.shape is not None
    if with_model == (args.rig is not None):
        raise InputError("give either MODEL SHAPE or --rig RIG")
    if with_model and (args.model is None or args.shape is None):
        raise InputError("give both MODEL and SHAPE "
                         "(for example: kpd deform chair chair.obj --move 0:0,0,1 --out o.obj)")
    if args.rig is not None and (args.prior or args.scan):
        raise InputError("--prior and --scan need MODEL SHAPE, not --rig")
    moves = parse_moves(args.move)
    with Outputs(force=args.force, inputs=(args.rig, args.shape)) as outputs:
        out = outputs.file(args.out, "--out", formats=MESH_FORMATS, what="mesh")
        if args.rig is not None:
            rig = load_rig(args.rig)
            warn_moves(moves, rig.mesh.vertices)
            mesh = rig.deformed_mesh(rig.moved(moves))
        else:
            mesh = deform_with_model(args, moves, check=lambda m: outputs.companions(out, mesh_companions(out, m)))
        outputs.companions(out, mesh_companions(out, mesh))
        write_mesh(outputs.stage(out), mesh)
    print(f"wrote {out} ({len(mesh.vertices)} vertices, {len(moves)} keypoint(s) moved"
          f"{', others by the prior' if args.prior else ''})")
    return 0


def deform_with_model(args: argparse.Namespace, moves: dict[int, np.ndarray], check=None):
    """The deformed mesh of ``kpd deform MODEL SHAPE``: rig the mesh, move keypoints (through the prior if asked).
    ``check(mesh)`` runs on the input mesh before the work (the output's companion files)."""
    from kpd.commands._shared import load_model, model_beside_read, rig_checked, scan_frame

    def load():
        model = load_model(args)
        k = model.num_keypoints
        for index in moves:
            if not 0 <= index < k:
                raise InputError(f"--move keypoint index must lie in [0, {k}) for this {k}-keypoint model; got "
                                 f"{index}")
        if args.prior and model.prior is None:
            raise InputError(f"{args.model}: this bundle has no category prior; drop --prior")
        return model

    model, mesh = model_beside_read(load, args.shape)
    if check is not None:
        check(mesh)
    warn_moves(moves, mesh.vertices)
    scan = None
    if args.scan:
        # orient with the scan pipeline, but rig the whole input mesh (topology kept) in the model's orientation
        scan = scan_frame(args, model, mesh)
        moves = {i: scan.vector_to_aligned(d) for i, d in moves.items()}
        work = mesh.with_vertices(scan.to_aligned(mesh.vertices))
        rig = model.rig(work, seed=args.seed)
    else:
        work = mesh
        rig = rig_checked(model, mesh, args.seed, args.shape)
    targets = rig.moved(moves)
    if args.prior and moves:
        targets = model.sync(rig, {i: targets[i] for i in moves})
    vertices = rig.deform(targets)
    if scan is not None:
        # map the vertex offsets back (not the positions), so an edit that moves nothing changes nothing exactly
        vertices = mesh.vertices + scan.vector_to_original(vertices - work.vertices)
    return mesh.with_vertices(vertices)
