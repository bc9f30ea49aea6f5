"""kpd render: draw a shape with its keypoints (optionally moved) to a PNG, without a window."""

from __future__ import annotations

import argparse

from kpd.errors import InputError

HELP = "draw a shape, its numbered keypoints (moved with --move) and optionally the cage to a PNG, off-screen"
EXAMPLE = ("kpd render chair my_chair.obj --move 0:0,0,-5 --prior --out view.png    "
           "(or: kpd render --rig chair_rig.npz --cage --out rig.png)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_source_arguments, add_view_arguments

    add_source_arguments(parser)
    add_view_arguments(parser)
    parser.add_argument("--move", action="append", default=[], metavar="I:DX,DY,DZ",
                        help="move keypoint I by (DX, DY, DZ) in the shape's own units; repeat for several")
    parser.add_argument("--prior", action="store_true", help="the other keypoints follow the category prior")
    parser.add_argument("--select", default=None, metavar="I,J", help="keypoints drawn as selected")
    parser.add_argument("--backend", default="auto", choices=("auto", "egl", "xvfb", "window"),
                        help="auto (default) = egl: OpenGL without any display (headless EGL, fast in software); "
                             "xvfb: OpenGL on a private Xvfb server; window: on the current $DISPLAY")
    parser.add_argument("--out", required=True, help="PNG file to write")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):  # small products: threads only wait for a busy core
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from kpd.commands._shared import load_source, parse_moves, view_settings, warn_moves
    from kpd.io import Outputs
    from kpd.viewer.render import render_rig, write_png
    from kpd.viewer.session import propose

    if not args.out.lower().endswith(".png"):
        raise InputError(f"--out {args.out}: kpd render writes PNG images (.png)")
    outputs = Outputs(force=args.force, inputs=(args.rig, args.shape))
    out = outputs.file(args.out, "--out")
    moves = parse_moves(args.move)
    selection = []
    if args.select:
        try:
            selection = [int(s) for s in args.select.split(",") if s.strip()]
        except ValueError as exc:
            raise InputError(f"--select must be keypoint numbers like 0,3; got {args.select!r}") from exc
    view_settings(args)  # bad --size or --view-up ends here, before any work
    source = load_source(args, need_prior=args.prior, later=True)
    settings = view_settings(args, source.up, source.front, source.azimuth)
    k = source.rig.num_keypoints
    for index in list(moves) + selection:  # before the binding
        if not 0 <= index < k:
            raise InputError(f"keypoint index must lie in [0, {k}) for this {k}-keypoint rig; got {index}")
    warn_moves(moves, source.rig.mesh.vertices)
    rig, shaded = bind_beside_drawing(source.rig, settings)
    keypoints = rig.moved(moves)
    if args.prior and moves:
        keypoints = propose(rig.keypoints, {i: keypoints[i] for i in moves}, prior=source.prior,
                            normalizer=rig.normalizer)
    image = render_rig(rig, keypoints, settings=settings, selection=selection, backend=args.backend, shaded=shaded)
    with outputs:
        write_png(outputs.stage(out), image)
    print(f"wrote {out} ({image.shape[1]}x{image.shape[0]}, {len(moves)} keypoint(s) moved"
          f"{', others by the prior' if args.prior and moves else ''})")
    return 0


def bind_beside_drawing(rig, settings):
    """``(rig, shaded)``: a :class:`kpd.viewer.app.Binding` bound on this thread while a worker thread gets its mesh
    ready to draw (:class:`kpd.viewer.gl.ShadedMesh`: positions grouped, each triangle once, the normals' lists; a
    second or more for millions of triangles); a rig already made is returned as it is, with None."""
    from concurrent.futures import ThreadPoolExecutor

    from kpd.viewer.app import PendingRig

    if not isinstance(rig, PendingRig):
        return rig, None
    from kpd.viewer.gl import ShadedMesh

    with ThreadPoolExecutor(1, thread_name_prefix="kpd-render-mesh") as pool:
        shaded = pool.submit(ShadedMesh, rig.mesh, settings.mesh_color, once=True)  # one picture
        bound = rig.bind()
        return bound, shaded.result()
