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


def rig_checked(model, mesh, seed: int, name: str):
    """``model.rig(mesh)`` with the frame check of :func:`warn_frame`, both from one surface sample: the check runs
    on a worker thread while the mesh is bound (it needs the networks and one core, the binding mostly the other) and
    its warnings are printed when both are done. A mesh too large for the memory ends before any work."""
    from concurrent.futures import ThreadPoolExecutor

    from kpd.rig import check_bind_memory

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


def model_beside_read(load, path, read=None):
    """``(load(), read(path))`` (``read``: :func:`kpd.io.read_mesh` unless given): the shape is read on a worker thread
    (a large file's read and its fresh memory wait mostly outside the interpreter's lock) while this one loads the
    model (``load``, which checks it too), and a third gets the compiled kernels' machinery ready with a first small
    kernel call (numba's start: 0.3-0.4 s in a fresh process, mostly outside the lock too: beside the model's load,
    0.2-0.3 s sooner than after it), work the binding or the sampling would otherwise do after the read. The model's
    errors come first, as before."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    from kpd.geometry import sample_surface
    from kpd.io import read_mesh

    with ThreadPoolExecutor(1, thread_name_prefix="kpd-read") as reader, \
            ThreadPoolExecutor(1, thread_name_prefix="kpd-numba-start") as starter:
        reading = reader.submit(read or read_mesh, path)
        # the first kernel call: numba's start
        starting = starter.submit(sample_surface, np.eye(3), np.array([[0, 1, 2]]), 1, seed=0)
        try:
            model = load()
        except BaseException:
            reading.cancel()
            raise
        starting.result()
        return model, reading.result()


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
