"""What several commands share: the model's arguments and its load beside the shape's read, ``--scan``/``--up``
and the frame check, a shape or a rig to show (``kpd view``, ``kpd render``), ``--move``, contact sheets.

Commands import these from here and never from each other. Like the command modules, this one imports only light
things at the top.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd.commands import add_check, integer, shipped_names
from kpd.errors import InputError

_MOVE = re.compile(r"^\s*(\d+)\s*:\s*([^,]+),([^,]+),([^,]+)\s*$")


# --- a model and a shape -------------------------------------------------------------------------------------


def add_model_arguments(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    """MODEL, the seed and the onnxruntime threads (shared by the commands that run a model); ``default``: MODEL
    may be left out for this shipped one."""
    if default is None:
        parser.add_argument("model", metavar="MODEL",
                            help=f"a bundle (.kpd folder or .zip) or a shipped name: {shipped_names()}")
    else:
        parser.add_argument("model", metavar="MODEL", nargs="?", default=default,
                            help=f"a bundle (.kpd folder or .zip) or a shipped name: {shipped_names()} (default "
                                 f"{default})")
    parser.add_argument("--seed", type=integer(0), default=0,
                        help="surface-sampling seed (default 0: same result every run)")
    parser.add_argument("--threads", type=integer(1), default=None,
                        help="onnxruntime intra-op threads (default: its own)")


def add_scan_arguments(parser: argparse.ArgumentParser) -> None:
    """``--scan`` and ``--up`` (which needs ``--scan``, checked alike for every command that has them)."""
    add_check(parser, check_scan_arguments)
    parser.add_argument("--scan", action="store_true",
                        help="treat the input as a real scan: clean it and orient it to the model's template first "
                             "(kpd.scan); results are mapped back onto the scan")
    parser.add_argument("--up", default=None, metavar="AXIS",
                        help="with --scan: the scan's known up axis (x, y, z, -z...), "
                             "restricting the orientation search")


def check_scan_arguments(args: argparse.Namespace) -> None:
    if args.up is not None:
        from kpd.scan import parse_axis  # here: kpd.scan (scipy) is slow to import and most runs need none of it

        if not args.scan:
            raise InputError("--up goes with --scan (the scan's known up axis); add --scan or drop --up")
        parse_axis(args.up, "--up")


def load_model(args: argparse.Namespace):
    from kpd.runtime import Model

    return Model.load(args.model, threads=args.threads)


_READ_FIRST = 0.05  # s the model's load waits for the read: a bad shape fails at once, a good one costs at most this


def model_beside_read(load, path, read=None):
    """``(load(), read(path))`` (``read``: :func:`kpd.io.read_mesh` unless given): the shape is read on a worker thread
    (a large file's read and its fresh memory wait mostly outside the interpreter's lock) while this one loads the
    model (``load``, which checks it too), and a third gets the compiled kernels' machinery ready with a first small
    kernel call (numba's start, mostly outside the lock too), work the binding or the sampling would otherwise do
    after the read. A shape whose read fails at once (a missing file, a header that declares what it cannot hold) is
    reported at once, before the model is loaded; otherwise the model's errors come first."""
    from concurrent.futures import ThreadPoolExecutor, wait

    from kpd.geometry import sample_surface
    from kpd.io import read_mesh

    with ThreadPoolExecutor(1, thread_name_prefix="kpd-read") as reader, \
            ThreadPoolExecutor(1, thread_name_prefix="kpd-numba-start") as starter:
        reading = reader.submit(read or read_mesh, path)
        # the first kernel call: numba's start
        starting = starter.submit(sample_surface, np.eye(3), np.array([[0, 1, 2]]), 1, seed=0)
        wait([reading], timeout=_READ_FIRST)
        if reading.done() and reading.exception() is not None:
            raise reading.exception()
        try:
            model = load()
        except BaseException:
            reading.cancel()
            raise
        starting.result()
        return model, reading.result()


def warn_frame(model, shape, seed: int, name: str, *, prediction=None) -> None:
    """Without --scan: one warning line if the shape sits turned in the model's frame or is probably not of the
    category (:func:`kpd.frame.frame_warnings`). ``prediction``: the model's :meth:`~kpd.runtime.Model.predict` of
    ``shape`` with ``seed``, whose surface sample the check then uses instead of drawing the same points again (a
    scan-sized mesh takes a second or more to sample)."""
    for line in frame_lines(model, shape, seed, name, prediction=prediction):
        print(f"warning: {line}", file=sys.stderr)


def frame_lines(model, shape, seed: int, name: str, *, prediction=None) -> list[str]:
    """The lines :func:`warn_frame` prints (for a command that checks the frame while it binds, and prints after)."""
    from kpd.frame import frame_warnings

    return frame_warnings(model if prediction is None else _Sampled(model, prediction), shape, seed=seed, name=name)


def rig_checked(model, mesh, seed: int, name: str, *, check_memory: bool = True):
    """``model.rig(mesh)`` with the frame check of :func:`warn_frame`, both from one surface sample: the check runs
    on a worker thread while the mesh is bound (it needs the networks and one core, the binding mostly the other) and
    its warnings are printed when both are done. A mesh too large for the memory ends before any work
    (``check_memory=False``: the caller checked it)."""
    from concurrent.futures import ThreadPoolExecutor

    from kpd.rig import check_bind_memory

    if check_memory:
        check_bind_memory(len(mesh.vertices), len(mesh.triangles), model.num_keypoints)
    prediction = model.predict(mesh, seed=seed)
    with ThreadPoolExecutor(1, thread_name_prefix="kpd-frame-check") as pool:
        lines = pool.submit(frame_lines, model, mesh, seed, name, prediction=prediction)
        rig = model.rig(mesh, seed=seed, prediction=prediction, check_memory=False)  # checked above
        for line in lines.result():
            print(f"warning: {line}", file=sys.stderr)
    return rig


class _Sampled:
    """``model`` with the surface sample of one shape already drawn: :meth:`sample` returns the normaliser and the
    points of its prediction (what ``model.sample`` of that shape and seed returns), anything else is the model's."""

    def __init__(self, model, prediction) -> None:
        self._model, self._prediction = model, prediction

    def sample(self, shape, *, seed: int = 0):
        return self._prediction.normalizer, self._prediction.points

    def __getattr__(self, name: str):
        return getattr(self._model, name)


def scan_frame(args: argparse.Namespace, model, shape, path: str | None = None, **kwargs):
    """``--scan``: the shape oriented into the model's frame (:class:`kpd.frame.ScanFrame`), searched with ``--up``
    or, for glTF, the file's y up; what it decided is printed (stderr), with the category check that runs without
    ``--scan`` (:meth:`kpd.frame.ScanFrame.category_warnings`). ``path``: the shape's file (default ``args.shape``)."""
    from kpd.frame import ScanFrame
    from kpd.io import file_up

    path = args.shape if path is None else path
    scan = ScanFrame(model, shape, args.up or file_up(path), **kwargs)
    for line in scan.warnings + scan.category_warnings(seed=getattr(args, "seed", 0), name=str(path)):
        print(f"warning: {line}", file=sys.stderr)
    for line in scan.notes:
        print(f"note: {line}", file=sys.stderr)
    return scan


def check_suffix(path: str, formats: tuple, what: str, option: str = "--out") -> None:
    if Path(path).suffix.lower() not in formats:
        raise InputError(f"{option} {path}: a {what} file must end in one of {' '.join(formats)}")


# --- keypoint moves and rigs ---------------------------------------------------------------------------------


def parse_move(text: str) -> tuple[int, np.ndarray]:
    """``"I:DX,DY,DZ"`` -> (I, (3,) offset)."""
    match = _MOVE.match(text)
    if match is None:
        raise InputError(f"--move must look like I:DX,DY,DZ (for example 3:0,0.05,0); got {text!r}")
    try:
        delta = np.array([float(match.group(i)) for i in (2, 3, 4)])
    except ValueError as exc:
        raise InputError(f"--move offsets must be numbers; got {text!r}") from exc
    if not np.isfinite(delta).all():
        raise InputError(f"--move offsets must be finite; got {text!r}")
    return int(match.group(1)), delta


def parse_moves(texts: list[str]) -> dict[int, np.ndarray]:
    moves: dict[int, np.ndarray] = {}
    for text in texts:
        index, delta = parse_move(text)
        moves[index] = moves.get(index, 0.0) + delta
    return moves


def warn_moves(moves: dict[int, np.ndarray], vertices: np.ndarray) -> None:
    """One warning line per ``--move`` longer than the shape (its largest extent, from ``vertices`` (V, 3)): the
    offsets are in the shape's own units, and an offset meant for a ModelNet chair (``--move 8:0,0,5``) stretches a
    ShapeNet chair of size 0.6 to many times its height."""
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    size = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    for index, delta in sorted(moves.items()):
        length = float(np.linalg.norm(delta))
        if length > size:
            print(f"warning: --move {index} moves it by {length:.3g}, more than the shape's size ({size:.3g}, its "
                  "largest extent): offsets are in the shape's own units", file=sys.stderr)


def load_rig(path: str):
    from kpd.rig import Rig

    return Rig.from_demo(path) if Path(path).is_dir() else Rig.load(path)


# --- a shape or a rig to show (kpd view, kpd render) ------------------------------------------------------------


def add_source_arguments(parser: argparse.ArgumentParser) -> None:
    """MODEL SHAPE | --rig, with --scan/--up, --seed, --threads (shared by ``kpd view`` and ``kpd render``)."""
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
    parser.add_argument("--azimuth", type=float, default=None,
                        help="camera degrees around the up axis, from the front (default: 30, or 60 for a category "
                             "long front to back such as shoes, so that its side shows)")
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


def view_settings(args: argparse.Namespace, up: str | None = None, front: str | None = None,
                  azimuth: float | None = None, **extra: Any):
    """The view options; the camera's up axis is ``--view-up`` when given, else ``up`` (the source's, see
    :attr:`Source.up`), else +z; its front is ``front`` (the source's) unless ``--view-up`` is given; its azimuth
    ``--azimuth`` when given, else ``azimuth`` (the category's, see :func:`category_azimuth`), else 30."""
    from kpd.viewer.render import ViewSettings

    width, height = parse_size(args.size)
    return ViewSettings(width=width, height=height, up=args.view_up or up or "+z",
                        front=None if args.view_up else front,
                        azimuth=args.azimuth if args.azimuth is not None else azimuth if azimuth is not None else 30.0,
                        elevation=args.elevation, zoom=args.zoom, show_cage=args.cage, show_ghost=args.ghost,
                        show_labels=not args.no_labels, **extra)


class Source:
    """The rig to show and, when a model is known, its category prior; ``up`` and ``front`` are the shape's up axis
    and the axis it is seen from at azimuth 0 when known (:func:`shape_view`), else None; ``azimuth`` the category's
    default azimuth (:func:`category_azimuth`), None without a model."""

    def __init__(self, rig: Any, prior: Any, name: str, up: str | None = None, front: str | None = None,
                 azimuth: float | None = None) -> None:
        self.rig, self.prior, self.name, self.up = rig, prior, name, up
        self.front, self.azimuth = front, azimuth


def _axis_text(vector: np.ndarray) -> str:
    i = int(np.argmax(np.abs(vector)))
    return ("-" if vector[i] < 0 else "+") + "xyz"[i]


def scan_up(scan: Any, model_up: str | None) -> str | None:
    """The input's axis (``'+y'``, ``'-x'``...) that ``scan`` (a ScanFrame) turns to the model's up axis."""
    from kpd.scan import parse_axis

    if model_up is None:
        return None
    return _axis_text(scan.vector_to_original(parse_axis(model_up)[None, :])[0])  # (3,) in the input's frame


def shape_view(model: Any, path: str | None = None, scan: Any = None) -> tuple[str | None, str | None]:
    """``(up, front)``: the shape's up axis and the axis its pictures, rigs and editors see it from at azimuth 0.

    With ``scan`` (a ScanFrame): the input's axes nearest to the ones the scan's recovered frame turns to the model's
    up axis and to the model's front (:func:`kpd.viewer.settings.front_axis` of its up), so that a y-up chair is seen
    from the side a z-up one is. Without: the file's own up axis (glTF: +y) or the model's, front by the same rule
    (None)."""
    from kpd.io import file_up

    if scan is None or model.up is None:
        return (file_up(path) if path is not None else None) or model.up, None
    from kpd.viewer.settings import front_axis, up_axis

    up = scan_up(scan, model.up)
    front = scan.vector_to_original(front_axis(model.up)[None, :])[0]  # (3,) in the input's frame
    front[up_axis(up) != 0] = 0.0  # across the up axis
    return up, _axis_text(front)


def category_azimuth(model: Any) -> float:
    """The default azimuth for ``model``'s category: 30 degrees from the front, or 60 (mostly from the side) when
    the category's template is long front to back (a shoe, whose heel or toe would face the camera end-on)."""
    template = getattr(model, "template_points", None)
    if template is None or model.up is None:
        return 30.0
    from kpd.viewer.settings import front_axis, up_axis

    front = front_axis(model.up)
    side = np.cross(up_axis(model.up), front)
    return 60.0 if np.ptp(template @ front) > 1.3 * np.ptp(template @ side) else 30.0


def load_source(args: argparse.Namespace, *, need_prior: bool = False, later: bool = False) -> Source:
    """Resolve ``MODEL SHAPE`` (with ``--scan``) or ``--rig`` (with ``--model``) into a rig and an optional prior,
    as ``kpd deform`` does. Bad combinations and a model of another keypoint count end in :class:`InputError`.

    ``later``: with ``MODEL SHAPE``, the source's rig is a :class:`kpd.viewer.app.Binding` (the mesh, read and
    checked, and the binding still to run), so that the editor shows the mesh at once and binds it on a worker
    thread; a mesh too large for the memory ends here all the same."""
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
        prior, azimuth = None, None
        if args.prior_model is not None:
            model = Model.load(args.prior_model, threads=args.threads)
            if model.num_keypoints != rig.num_keypoints:
                raise InputError(f"the model {args.prior_model} has {model.num_keypoints} keypoints; the rig "
                                 f"{args.rig} has {rig.num_keypoints}")
            prior, azimuth = model.prior, category_azimuth(model)
        if need_prior and prior is None:
            raise InputError("--prior needs a category prior: pass --model MODEL with --rig")
        return Source(rig, prior, Path(args.rig).name, azimuth=azimuth)
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
    if later:
        from kpd.rig import check_bind_memory

        check_bind_memory(len(mesh.vertices), len(mesh.triangles), model.num_keypoints)
    if args.scan:
        scan = scan_frame(args, model, mesh)

        def bind():
            aligned = model.rig(mesh.with_vertices(scan.to_aligned(mesh.vertices)), seed=args.seed,
                                check_memory=not later)  # checked above when later
            return ScanRig(aligned, mesh, scan)

        up, front = shape_view(model, args.shape, scan)
        return Source(_later(mesh, model, bind) if later else bind(), model.prior, Path(args.shape).name,
                      up or args.up, front, category_azimuth(model))

    def bind():
        return rig_checked(model, mesh, args.seed, args.shape, check_memory=not later)

    # without --scan the mesh is taken in the model's frame, so the model's up axis is the shape's (unless the
    # file's format defines one)
    up, front = shape_view(model, args.shape)
    return Source(_later(mesh, model, bind) if later else bind(), model.prior, Path(args.shape).name, up, front,
                  category_azimuth(model))


def _later(mesh: Any, model: Any, bind: Any) -> Any:
    from kpd.viewer.app import PendingRig

    return PendingRig(mesh, model.num_keypoints, bind)


# --- what a command writes --------------------------------------------------------------------------------------


def morph_rig(rig: Any, prior: Any, meta: dict):
    """The :class:`kpd.morph.MorphRig` of a rig, in the user's frame: a rig made on an aligned scan (``kpd view``'s
    ``ScanRig``, which keeps the scan's own mesh and its alignment) gives its targets in the scan's frame."""
    from kpd.morph import MorphRig

    if hasattr(rig, "aligned"):
        return MorphRig.from_rig(rig.aligned, prior, mesh=rig.mesh, frame=rig.scan.result.transform, meta=meta)
    return MorphRig.from_rig(rig, prior, meta=meta)


def render_sheet(meshes: Sequence[Any], path: str | Path, **options: Any) -> None:
    """A contact sheet of meshes (see :func:`kpd.viewer.pictures.render_sheet`: the editor's OpenGL drawing path)."""
    from kpd.viewer.pictures import render_sheet as draw

    draw(meshes, path, **options)
