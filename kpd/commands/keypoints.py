"""kpd keypoints: predict a shape's keypoints with a model bundle."""

from __future__ import annotations

import argparse
import json
import sys

from kpd.commands import add_check, integer

HELP = "predict the keypoints of a mesh or point cloud (written in the input's own frame and units)"
EXAMPLE = "kpd keypoints chair my_chair.obj --out my_chair_keypoints.json"


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """MODEL, the seed and the onnxruntime threads (shared by the commands that run a model)."""
    parser.add_argument("model", metavar="MODEL", help="a bundle (.kpd folder or .zip) or a shipped name: chair, table")
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


def ambiguity_advice(up_given: bool) -> str:
    """The warning for an ambiguous orientation: what it means and what to do."""
    if up_given:
        return ("the orientation is ambiguous: a turn about the up axis far from the chosen one fits almost as well "
                "(a symmetric object, such as a table turned 180 degrees, gives the same shape either way); check "
                "the result (kpd scan --picture draws both)")
    return ("the orientation is ambiguous: a rotation far from the chosen one fits almost as well (symmetric or "
            "round object?); check the result (kpd scan --picture draws both), or pass --up")


def warn_frame(model, shape, seed: int, name: str) -> None:
    """Without --scan: one warning line if the shape sits turned in the model's frame or is probably not of the
    category (kpd.frame.check_frame)."""
    from kpd.frame import check_frame

    result = check_frame(model, shape, seed=seed)
    for line in [] if result is None else result.warnings(model.category, name):
        print(f"warning: {line}", file=sys.stderr)


def load_model(args: argparse.Namespace):
    from kpd.runtime import Model

    return Model.load(args.model, threads=args.threads)


def check_suffix(path: str, formats: tuple, what: str, option: str = "--out") -> None:
    from pathlib import Path

    from kpd.errors import InputError

    if Path(path).suffix.lower() not in formats:
        raise InputError(f"{option} {path}: a {what} file must end in one of {' '.join(formats)}")


SETTLE_POINTS = 2048  # surface points of the deformed scan compared with the template


def settle_orientation(model, result, *, seed: int = 0):
    """An ambiguous orientation settled by the model: the candidate rotation whose scan, deformed by the model onto
    the template's keypoints, fits the template best.

    The shape alone cannot tell them apart (a ballet flat fits the template about as well back to front), but the
    model knows the category: for each distinct rotation within the ambiguity margin
    (:func:`kpd.scan.candidate_rotations`) the scan is turned that way, its keypoints are predicted, its rig
    (cage, influence) deforms it so that its keypoints go where the template's are (``kpd align``, the paper's
    §4.2), and the chamfer distance (the training loss) between the deformed scan and the template is taken. A
    correctly turned scan deforms into the template; a turned-around one keeps its heel where the template has its
    toe. Off by default (``ScanFrame(settle=True)`` turns it on): on 30 training shoes under 4 random poses each it
    picked the right rotation in 46 of 58 ambiguous poses, as often as the rigid fit alone (benchmarks/bench_settle.py,
    results/settle.json).

    Returns
    -------
    result : the :class:`kpd.scan.ScanResult` of the chosen rotation (``result`` itself when it stays)
    record : None when there was nothing to settle (not ambiguous, one candidate, a point scan: a rig needs a
        mesh), else {"candidates": [{"angle_deg", "score", "fit"}...], "chosen": index, "margin": the runner-up's
        fit / the chosen one's - 1}
    """
    import numpy as np

    from kpd.geometry import Normalizer, chamfer, sample_surface
    from kpd.scan import candidate_rotations, reorient, rotation_angle

    orientation = result.orientation
    if orientation is None or not orientation.ambiguous or model.template_points is None:
        return result, None
    shape = result.shape
    if not (hasattr(shape, "triangles") and len(shape.triangles)):
        return result, None
    candidates = candidate_rotations(orientation)
    if len(candidates) < 2:
        return result, None
    template = model.template_points
    target = Normalizer().fit(template).apply(template)
    target_keypoints = model.predict(template, seed=seed).keypoints  # the template's, in its model frame
    fits, turned = [], []
    for rotation, _ in candidates:
        alt = result if rotation is orientation.rotation else reorient(result, rotation)
        prediction = model.predict(alt.shape, seed=seed)
        rig = model.rig(alt.shape, prediction=prediction, enclose=False)
        deformed = alt.shape.with_vertices(rig.deform(rig.normalizer.invert(target_keypoints)))
        points = sample_surface(deformed.vertices, deformed.triangles, SETTLE_POINTS, seed=seed,
                                outer=model.outer_surface).points
        fits.append(chamfer(Normalizer().fit(points).apply(points), target))
        turned.append(alt)
    order = np.argsort(fits)
    chosen = int(order[0])
    best = fits[chosen]
    record = {"candidates": [{"angle_deg": rotation_angle(r, orientation.rotation), "score": float(score),
                              "fit": float(fit)} for (r, score), fit in zip(candidates, fits)],
              "chosen": chosen, "margin": float(fits[int(order[1])] / best - 1.0) if best > 0 else float("inf")}
    return turned[chosen], record


class ScanFrame:
    """A scan oriented into the model's frame: ``shape`` there, and the maps to and from the scan's own frame.

    With ``settle``, an orientation the shape alone leaves ambiguous is settled by the model
    (:func:`settle_orientation`; off by default, it is no better than the rigid fit on training shoes); ``settled``
    holds what was decided (None: nothing settled) and ``rigid`` the result of the best rigid fit alone."""

    def __init__(self, model, shape, up: str | None, *, settle: bool = False, seed: int = 0) -> None:
        from kpd.errors import BundleError
        from kpd.scan import preprocess

        reference = model.template_points
        if reference is None:
            raise BundleError(f"{model.bundle.path}: the bundle has no template cloud, so --scan cannot orient "
                              "scans to it; re-export it with its training data")
        params = {}
        if up is not None:
            params["up"] = up
        if model.up is not None:  # as kpd scan --model: the model's up axis turns on the support prior
            params["reference_up"] = model.up
        self.result = preprocess(shape, reference, outer=model.outer_surface, **params)
        self.rigid = self.result  # the best rigid fit, before any settling
        self.settled = None
        if settle:
            self.result, self.settled = settle_orientation(model, self.result, seed=seed)
        orientation = self.result.orientation
        if orientation is not None and orientation.ambiguous:
            if self.settled is None:
                print(f"warning: {ambiguity_advice(up is not None)}", file=sys.stderr)
            else:
                s = self.settled
                print(f"note: the orientation was ambiguous by shape alone ({len(s['candidates'])} candidate "
                      f"rotations); settled by the model (the scan deformed onto the template fits it best, "
                      f"{s['margin']:.0%} better than the next; the candidate "
                      f"{s['candidates'][s['chosen']]['angle_deg']:.0f} degrees from the best rigid fit)",
                      file=sys.stderr)

    def to_aligned(self, points):
        return self.result.to_aligned(points)

    def to_original(self, points):
        return self.result.to_original(points)

    def vector_to_aligned(self, vector):
        """(3,) offset in the scan's units -> the aligned frame (rotation and scale only)."""
        return self.result.transform[:3, :3] @ vector

    def vector_to_original(self, vectors):
        """(N, 3) offsets in the aligned frame -> the scan's units."""
        return vectors @ self.result.inverse[:3, :3].T

    def report(self) -> dict:
        return {**self.result.to_dict(), "settled": self.settled}


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
            scan = ScanFrame(model, shape, args.up, seed=args.seed)
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
