"""kpd view: open the keypoint editor (an Open3D window) on a shape or a rig."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from kpd.commands import integer, shipped_names
from kpd.errors import InputError

HELP = "edit a shape in a window: pick keypoints, drag them, watch the mesh deform; save the mesh and the session"
EXAMPLE = ("kpd view chair my_chair.obj --out my_chair_edited.obj    "
           "(or: kpd view --rig chair_rig.npz --model chair --events log.jsonl)")


def add_source_arguments(parser: argparse.ArgumentParser) -> None:
    """MODEL SHAPE | --rig, with --scan/--up, --seed, --threads (shared by ``kpd view`` and ``kpd render``)."""
    from kpd.commands.keypoints import add_scan_arguments

    parser.add_argument("model", metavar="MODEL", nargs="?", default=None,
                        help=f"a bundle (.kpd folder or .zip) or a shipped name ({shipped_names()})")
    parser.add_argument("shape", metavar="SHAPE", nargs="?", default=None, help="the mesh to edit (with MODEL)")
    parser.add_argument("--rig", default=None, help="instead of MODEL SHAPE: a rig (.npz from kpd) or a folder in "
                                                    "the authors' demo format")
    parser.add_argument("--model", dest="prior_model", default=None, metavar="MODEL",
                        help="with --rig: a model whose category prior drives the prior toggle and the sliders")
    parser.add_argument("--seed", type=int, default=0, help="surface-sampling seed (with MODEL)")
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (with MODEL)")
    add_scan_arguments(parser)


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """What to show and from where (shared by ``kpd view`` and ``kpd render``)."""
    parser.add_argument("--size", default=None, metavar="WxH", help="size of the 3D view in pixels (default 960x720)")
    parser.add_argument("--view-up", default=None, metavar="AXIS",
                        help="the shape's up axis for the camera (default: the axis --scan decided or --up gave, "
                             "+y for .gltf/.glb files as glTF defines, else the model's: +z for chair, +y for shoe)")
    parser.add_argument("--azimuth", type=float, default=30.0, help="camera degrees around the up axis (default 30)")
    parser.add_argument("--elevation", type=float, default=20.0, help="camera degrees above the horizon (default 20)")
    parser.add_argument("--zoom", type=float, default=1.0, help="> 1 moves the camera closer")
    parser.add_argument("--cage", action="store_true", help="show the cage as a wireframe")
    parser.add_argument("--ghost", action="store_true", help="show the original shape as a ghost")
    parser.add_argument("--no-labels", action="store_true", help="hide the keypoint numbers")


def parse_size(text: str | None) -> tuple[int, int]:
    if text is None:
        return 960, 720
    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError as exc:
        raise InputError(f"--size must look like 960x720; got {text!r}") from exc
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise InputError(f"--size must be between 16x16 and 8192x8192; got {text!r}")
    return width, height


def view_settings(args: argparse.Namespace, up: str | None = None, **extra: Any):
    """The view options; the camera's up axis is ``--view-up`` when given, else ``up`` (the source's, see
    :attr:`Source.up`), else +z."""
    from kpd.viewer.render import ViewSettings

    width, height = parse_size(args.size)
    return ViewSettings(width=width, height=height, up=args.view_up or up or "+z", azimuth=args.azimuth, elevation=args.elevation,
                        zoom=args.zoom, show_cage=args.cage, show_ghost=args.ghost, show_labels=not args.no_labels,
                        **extra)


class Source:
    """The rig to show and, when a model is known, its category prior; ``up`` is the shape's up axis when known
    (the one ``--scan`` decided or ``--up`` gave, +y for glTF, else the model's own), else None."""

    def __init__(self, rig: Any, prior: Any, name: str, up: str | None = None) -> None:
        self.rig, self.prior, self.name, self.up = rig, prior, name, up


def scan_up(scan: Any, model_up: str | None) -> str | None:
    """The input's axis (``'+y'``, ``'-x'``...) that ``scan`` (a ScanFrame) turns to the model's up axis."""
    from kpd.scan import parse_axis

    if model_up is None:
        return None
    vector = scan.vector_to_original(parse_axis(model_up)[None, :])[0]  # (3,) in the input's frame
    i = int(np.argmax(np.abs(vector)))
    return ("-" if vector[i] < 0 else "+") + "xyz"[i]


def load_source(args: argparse.Namespace, *, need_prior: bool = False, later: bool = False) -> Source:
    """Resolve ``MODEL SHAPE`` (with ``--scan``) or ``--rig`` (with ``--model``) into a rig and an optional prior,
    as ``kpd deform`` does. Bad combinations and a model of another keypoint count end in :class:`InputError`.

    ``later``: with ``MODEL SHAPE``, the source's rig is a :class:`kpd.viewer.app.Binding` (the mesh, read and
    checked, and the binding still to run), so that the editor shows the mesh at once and binds it on a worker
    thread; a mesh too large for the memory ends here all the same."""
    from kpd.commands.deform import load_rig
    from kpd.commands.keypoints import model_beside_read, scan_frame
    from kpd.frame import ScanRig
    from kpd.runtime import Model

    with_model = args.model is not None or args.shape is not None
    if with_model == (args.rig is not None):
        raise InputError("give either MODEL SHAPE or --rig RIG")
    if with_model and (args.model is None or args.shape is None):
        raise InputError("give both MODEL and SHAPE (for example: kpd view chair chair.obj)")
    if args.rig is not None and args.scan:
        raise InputError("--scan needs MODEL SHAPE, not --rig")
    if with_model and args.prior_model is not None:
        raise InputError("--model goes with --rig; with MODEL SHAPE the prior comes from MODEL")
    if args.up is not None and not args.scan:
        raise InputError("--up goes with --scan (the camera's up axis is --view-up)")
    if args.rig is not None:
        if not Path(args.rig).exists():
            raise InputError(f"{args.rig}: no such rig file or folder")
        rig = load_rig(args.rig)
        prior = None
        if args.prior_model is not None:
            model = Model.load(args.prior_model, threads=args.threads)
            if model.num_keypoints != rig.num_keypoints:
                raise InputError(f"the model {args.prior_model} has {model.num_keypoints} keypoints; the rig "
                                 f"{args.rig} has {rig.num_keypoints}")
            prior = model.prior
        if need_prior and prior is None:
            raise InputError("--prior needs a category prior: pass --model MODEL with --rig")
        return Source(rig, prior, Path(args.rig).name)
    if Path(args.shape).is_dir():
        raise InputError(f"{args.shape}: is a folder, not a mesh file (give one of the mesh files in it)")
    if not Path(args.shape).is_file():
        raise InputError(f"{args.shape}: no such file")

    def load():
        model = Model.load(args.model, threads=args.threads)
        if need_prior and model.prior is None:
            raise InputError(f"{args.model}: this bundle has no category prior; drop --prior")
        return model

    model, mesh = model_beside_read(load, args.shape)
    from kpd.io import file_up

    if later:
        from kpd.rig import check_bind_memory

        check_bind_memory(len(mesh.vertices), len(mesh.triangles), model.num_keypoints)
    if args.scan:
        scan = scan_frame(args, model, mesh)

        def bind():
            aligned = model.rig(mesh.with_vertices(scan.to_aligned(mesh.vertices)), seed=args.seed)
            return ScanRig(aligned, mesh, scan)

        return Source(_later(mesh, model, bind) if later else bind(), model.prior, Path(args.shape).name,
                      scan_up(scan, model.up) or args.up)
    from kpd.commands.keypoints import rig_checked  # kpd view and kpd render: the frame and category check

    def bind():
        return rig_checked(model, mesh, args.seed, args.shape)

    # without --scan the mesh is taken in the model's frame, so the model's up axis is the shape's (unless the
    # file's format defines one)
    return Source(_later(mesh, model, bind) if later else bind(), model.prior, Path(args.shape).name,
                  file_up(args.shape) or model.up)


def _later(mesh: Any, model: Any, bind: Any) -> Any:
    from kpd.viewer.app import Binding

    return Binding(mesh, model.num_keypoints, bind)


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
        from kpd.commands.rig import browse

        return browse(args)

    from kpd.commands import check_output
    from kpd.commands.keypoints import check_suffix
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
    settings = view_settings(args, source.up, prior=bool(args.prior), nudge_step=float(args.step))
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise InputError("kpd view needs a display ($DISPLAY is not set); for images without one use kpd render, "
                         "or run it under xvfb-run")
    from kpd.viewer.app import EditorApp

    app = EditorApp(source.rig, prior=source.prior, settings=settings, out=args.out, session_path=args.session,
                    screenshot_path=args.screenshot, events=args.events, title=f"kpd view - {source.name}",
                    initial_session=args.load_session)
    return app.run()


def __getattr__(name: str):  # ScanRig moved to kpd.frame; importable from here as before, without importing it early
    if name == "ScanRig":
        from kpd.frame import ScanRig

        return ScanRig
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
