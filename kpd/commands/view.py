"""kpd view: open the keypoint editor (an Open3D window) on a shape or a rig."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from kpd.commands import integer
from kpd.commands._shared import (  # noqa: F401  (importable from here as before)
    Source, add_source_arguments, add_view_arguments, load_source, morph_rig, parse_size, scan_up, view_settings,
)
from kpd.errors import InputError

HELP = "edit a shape in a window: pick keypoints, drag them, watch the mesh deform; save the mesh and the session"
EXAMPLE = ("kpd view chair my_chair.obj --out my_chair_edited.obj    "
           "(or: kpd view --rig chair_rig.npz --model chair --events log.jsonl)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_source_arguments(parser)
    add_view_arguments(parser)
    parser.add_argument("--out", default=None, help="where 'save mesh' (S) writes the deformed mesh "
                                                    "(.obj .ply .off .stl .gltf .glb)")
    parser.add_argument("--session", default=None, help="where 'save session' (J) writes and 'load session' (L) "
                                                        "reads the edit session (JSON); default kpd_session.json")
    parser.add_argument("--load-session", default=None, metavar="JSON", help="apply a saved edit session at start")
    parser.add_argument("--screenshot", default="kpd_view.png",
                        help="screenshot file name; P writes NAME_001.png, NAME_002.png, ... (default kpd_view.png)")
    parser.add_argument("--prior", action="store_true", help="start with the prior toggle on")
    parser.add_argument("--step", type=float, default=0.01, help="arrow-key nudge step, as a fraction of the shape's "
                                                                  "diagonal (default 0.01)")
    parser.add_argument("--events", default=None, metavar="JSONL",
                        help="append one JSON line per editor event (selection, keypoints, camera) to this file")
    parser.add_argument("--force", action="store_true", help="let 'save mesh' and 'save session' replace existing "
                                                             "files")
    parser.add_argument("--browser", action="store_true",
                        help="instead of a window: serve the editor as a page for your own browser (three.js, drawn on "
                             "your GPU; works through an SSH port forward); prints the URL")
    parser.add_argument("--host", default="127.0.0.1", help="with --browser: the address to listen on (default "
                                                            "127.0.0.1, this machine only)")
    parser.add_argument("--port", type=integer(0, 65535), default=8765,
                        help="with --browser: the port (default 8765; 0 picks a free one)")


def run(args: argparse.Namespace) -> int:
    import os

    if args.browser:
        return browse(args)

    from kpd.commands import check_output
    from kpd.commands._shared import check_suffix
    from kpd.io import MESH_FORMATS

    if args.out is not None:
        check_suffix(args.out, MESH_FORMATS, "mesh")
        check_output(args.out, force=args.force, inputs=(args.rig, args.shape))
    if args.session is not None:
        if Path(args.session).suffix.lower() != ".json":
            raise InputError(f"--session {args.session}: an edit session is a .json file")
        if args.load_session is None or Path(args.load_session).resolve() != Path(args.session).resolve():
            check_output(args.session, force=args.force, inputs=(args.load_session,))
    if args.load_session is not None and not Path(args.load_session).is_file():
        raise InputError(f"{args.load_session}: no such session file")
    if not (args.step > 0 and np.isfinite(args.step)):
        raise InputError(f"--step must be a positive number; got {args.step}")
    view_settings(args)  # bad --size or --view-up ends here, before any work
    source = load_source(args, need_prior=args.prior, later=True)  # bound on the editor's worker thread
    if args.out is not None:  # 'save mesh' adds the companions of --out (an OBJ's .mtl and maps): checked now
        from kpd.io import Outputs, mesh_companions

        Outputs(force=args.force, inputs=(args.rig, args.shape)).companions(
            Path(args.out), mesh_companions(args.out, source.rig.mesh))
    settings = view_settings(args, source.up, source.front, source.azimuth, prior=bool(args.prior),
                             nudge_step=float(args.step))
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise InputError("kpd view needs a display ($DISPLAY is not set); for images without one use kpd render, "
                         "or run it under xvfb-run")
    from kpd.viewer.app import EditorApp

    app = EditorApp(source.rig, prior=source.prior, settings=settings, out=args.out, session_path=args.session,
                    screenshot_path=args.screenshot, events=args.events, title=f"kpd view - {source.name}",
                    initial_session=args.load_session)
    return app.run()


def browse(args: argparse.Namespace) -> int:
    """``kpd view ... --browser``: the editor as a page served from this machine (:mod:`kpd.viewer.browser`)."""
    from kpd.commands import check_output
    from kpd.io import MESH_FORMATS
    from kpd.morph import up_rotation
    from kpd.viewer.browser import BrowserEditor

    window_only = [option for option, value in (("--session", args.session), ("--load-session", args.load_session),
                                                ("--events", args.events), ("--cage", args.cage or None),
                                                ("--ghost", args.ghost or None), ("--size", args.size))
                   if value is not None]
    if window_only:
        raise InputError(f"{window_only[0]} belongs to the window editor; the browser page has none (drop it or "
                         "--browser)")
    inputs = (args.rig, args.shape)
    if args.out is not None:
        check_output(args.out, force=args.force, inputs=inputs, formats=MESH_FORMATS, what="mesh")
    if args.view_up is not None:
        up_rotation(args.view_up)
    editor = BrowserEditor(out=args.out, force=args.force, inputs=inputs, host=args.host, port=args.port)
    try:
        source = load_source(args, need_prior=args.prior)
        model = args.model or args.prior_model
        meta = {**({"model": str(model)} if model is not None else {}), "shape": source.name, "scan": bool(args.scan)}
        settings = view_settings(args, source.up, source.front, source.azimuth)
        editor.show(morph_rig(source.rig, source.prior, meta), name=Path(source.name).stem, up=settings.up,
                    prior=args.prior, azimuth=page_azimuth(settings), elevation=settings.elevation)
        port = editor.server.server_address[1]
        if editor.exposed:
            print(f"warning: --host {args.host} is not a loopback address: anyone who can reach port {port} and has "
                  "the address printed next can use this editor and its save", file=sys.stderr, flush=True)
        print(f"kpd view: the editor is at {editor.url} (from another machine: ssh -L {port}:localhost:{port} "
              f"THIS_HOST, then open http://localhost:{port}/{editor.secret}/); Ctrl+C stops it", flush=True)
        editor.serve_forever()
    except KeyboardInterrupt:
        print("kpd view: stopped", flush=True)
    finally:
        editor.server.server_close()
        editor.close()
    return 0


def page_azimuth(settings) -> float:
    """The browser page's azimuth for the view of ``settings``: the page looks from the axis that the glTF file's up
    rotation turns to +Z (:func:`kpd.viewer.settings.front_axis`), so a front turned from it (a scan's recovered
    frame) adds its turn about the up axis; the page then sees the side the pictures and the window see."""
    from kpd.viewer.settings import front_axis, up_axis

    if settings.front is None:
        return float(settings.azimuth)
    up, default, front = up_axis(settings.up), front_axis(settings.up), up_axis(settings.front)
    turn = np.degrees(np.arctan2(np.cross(default, front) @ up, default @ front))
    return float((settings.azimuth + turn + 180.0) % 360.0 - 180.0)


def __getattr__(name: str):  # ScanRig moved to kpd.frame; importable from here as before, without importing it early
    if name == "ScanRig":
        from kpd.frame import ScanRig

        return ScanRig
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
