"""Does a shape sit in the model's frame, and is it of the model's category? (the check behind ``kpd keypoints``,
``deform``, ``align``, ``view`` and ``render`` without ``--scan``).

A model predicts keypoints in the frame its training shapes shared (ModelNet: z up, backs toward +y). A chair given
lying on its back or with y up still gets keypoints, but wrong ones (a third of its size off). The check runs the
scan aligner (:class:`kpd.scan.ScanAligner`, the orientation search of ``--scan``) against the bundle's template
and compares two of its scores, trimmed RMS distances in the template's [-1, 1] box:

* the pose **as given**: the shape fitted to the template with its rotation held fixed (only the per-axis scale and
  the translation fitted, as the aligner's ICP does), or the best refined hypothesis within ``NEAR_ANGLE`` degrees
  of it, and
* the **best** rotation the search finds.

When the best is more than ``TURN_ANGLE`` degrees away and its score is better than the given pose's by more than
``TURN_MARGIN`` (relative, the aligner's ambiguity margin), the shape is **turned**: the message names ``--scan``,
and ``--scan --up AXIS`` with the input's axis that the best rotation turns up.

Whether the shape is of the category at all is judged in its best pose by two fits, each against a limit calibrated
at export on training shapes (:func:`calibrate`, the bundle's ``frame_check`` entry): the aligner's best score (how
well the template's shape can be laid over it) and the **keypoint fit**, the mean distance from the model's
keypoints to the shape's points (the model puts a chair's keypoints on its surface; on other shapes they float
off it). A shape beyond either limit fits no pose of the category as well as its training shapes do and is flagged
**foreign** (probably not a chair). Measured rates: ``benchmarks/bench_frame.py``.
"""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np

from kpd.geometry import as_rng

__all__ = ["FrameCheck", "check_frame", "calibrate", "keypoint_fit", "frame_warnings", "ScanFrame", "ScanRig",
           "bind_shape", "settle_orientation", "ambiguity_advice", "TURN_MARGIN", "TURN_ANGLE", "NEAR_ANGLE",
           "LIMIT_QUANTILE", "SETTLE_POINTS"]

log = logging.getLogger(__name__)

TURN_MARGIN = 0.15  # relative score margin for "another pose fits clearly better" (kpd.scan's ambiguity margin)
TURN_ANGLE = 30.0  # degrees: the best rotation must be this far from the given pose
NEAR_ANGLE = 15.0  # degrees: refined hypotheses this close to the given pose count as the given pose
LIMIT_QUANTILE = 0.99  # the score limit: this quantile of the training shapes' best scores, times LIMIT_FACTOR
LIMIT_FACTOR = 1.25
# a lighter search than kpd scan's (no FPFH candidates, smaller subsets, fewer refined hypotheses): the check runs on
# every command without --scan, on the point_count points the model sees; a few times faster, same decisions on the
# shapes measured in bench_frame.py. On one thread: on two, its small fits wait on each other for the GIL (more CPU
# for no less time), and in the commands it runs beside the binding, which has the cores' work to do
SEARCH = {"fpfh_runs": 0, "n_points": 500, "coarse_points": 200, "refine_top": 3, "iterations": 15, "threads": 1}
_AXES = ("x", "y", "z")


class FrameCheck(NamedTuple):
    """Result of :func:`check_frame`.

    given_score : the aligner's score of the pose as given (template box units; lower fits better).
    best_score : the score of the best rotation found.
    best_rotation : (3, 3) float64, the best rotation (the input's frame -> the model's).
    angle : degrees between the given pose and the best rotation.
    turned : another pose fits clearly better than the given one.
    up : the input's axis (``'y'``, ``'-x'``...) that the best rotation turns to the model's up axis, or None.
    keypoint_fit : mean distance from the model's keypoints to the shape's points in its best pose (box units).
    score_limit, keypoint_limit : the bundle's calibrated limits of ``best_score`` and ``keypoint_fit``, or None.
    foreign : beyond a limit: probably not a shape of the category.
    """

    given_score: float
    best_score: float
    best_rotation: np.ndarray
    angle: float
    turned: bool
    up: str | None
    keypoint_fit: float
    score_limit: float | None
    keypoint_limit: float | None
    foreign: bool

    def warnings(self, category: str, name: str = "the input") -> list[str]:
        """One line per finding, for the command line (empty when the shape sits in the model's frame)."""
        out = []
        if self.foreign:
            out.append(f"{name} fits no pose of a {category} as well as the {category} training shapes do (shape "
                       f"score {self.best_score:.3f}, limit {_text(self.score_limit)}; keypoint fit "
                       f"{self.keypoint_fit:.3f}, limit {_text(self.keypoint_limit)}): probably not a {category}")
        elif self.turned:
            up = f" (or --scan --up {self.up})" if self.up else " (or --scan --up AXIS)"
            out.append(f"{name} fits the {category} model's frame clearly better turned by {self.angle:.0f} degrees "
                       f"(score {self.best_score:.3f} vs {self.given_score:.3f} as given), so its keypoints are "
                       f"likely wrong: pass --scan to orient it first{up}")
        return out

    def to_dict(self) -> dict:
        return {"given_score": self.given_score, "best_score": self.best_score, "angle": self.angle,
                "turned": self.turned, "up": self.up, "keypoint_fit": self.keypoint_fit,
                "score_limit": self.score_limit, "keypoint_limit": self.keypoint_limit, "foreign": self.foreign,
                "best_rotation": self.best_rotation.tolist()}


def _text(limit: float | None) -> str:
    return "none" if limit is None else f"{limit:.3f}"


def _aligner(template: np.ndarray, up: str | None, seed: int = 0):
    from kpd.scan import ScanAligner

    return ScanAligner(reference_up=up, seed=seed, **SEARCH).fit(template)


def _given_score(aligner: Any, points: np.ndarray, iterations: int = 20) -> float:
    """The aligner's score of ``points`` with their rotation held fixed (per-axis scale and translation fitted by
    the same trimmed symmetric matching as its ICP), in the reference's box units."""
    scan = aligner._cloud(points, as_rng(aligner.seed + 1))
    ref = aligner.reference_
    low, high = aligner._SCALE_RANGE
    a, t = np.ones(3), np.zeros(3)
    kept_s = max(3, int(aligner.trim * len(scan.points)))
    kept_r = max(3, int(aligner.trim * len(ref.points)))
    for _ in range(iterations):
        d1, i1 = ref.tree3.query(scan.points * a + t)
        d2, i2 = scan.tree3.query((ref.points - t) / a)
        o1 = np.argpartition(d1, kept_s - 1)[:kept_s]
        o2 = np.argpartition(d2, kept_r - 1)[:kept_r]
        x = np.concatenate([scan.points[o1], scan.points[i2[o2]]])  # (k, 3)
        y = np.concatenate([ref.points[i1[o1]], ref.points[o2]])  # (k, 3)
        xc, yc = x - x.mean(axis=0), y - y.mean(axis=0)
        a_new = np.clip((xc * yc).sum(axis=0) / np.maximum((xc * xc).sum(axis=0), 1e-12), low, high)
        t_new = y.mean(axis=0) - a_new * x.mean(axis=0)
        done = np.abs(a_new - a).max() < 1e-5 and np.abs(t_new - t).max() < 1e-5
        a, t = a_new, t_new
        if done:
            break
    unit = ref.radius / aligner.reference_box_scale_
    return float(aligner._score(scan, a, np.eye(3), t) * unit)


def _axis_name(vector: np.ndarray) -> str:
    i = int(np.argmax(np.abs(vector)))
    return ("-" if vector[i] < 0 else "") + _AXES[i]


def keypoint_fit(keypoints_of: Any, points: np.ndarray) -> float:
    """Mean distance from the keypoints ``keypoints_of(points)`` (K, 3) to the nearest of ``points`` (N, 3), both in
    the model's [-1, 1] frame."""
    from scipy.spatial import cKDTree

    keypoints = np.asarray(keypoints_of(points), dtype=np.float64)
    return float(cKDTree(points).query(keypoints)[0].mean())


def _check(aligner: Any, keypoints_of: Any, points: np.ndarray, model_up: str | None,
           limits: dict) -> FrameCheck:
    from kpd.geometry import Normalizer
    from kpd.scan import parse_axis, rotation_angle

    orientation = aligner.orient(points)
    given = _given_score(aligner, points)
    near = [h.score for h in orientation.hypotheses if rotation_angle(h.rotation) < NEAR_ANGLE]
    given = min([given, *near])
    best = float(orientation.score)
    rotation = orientation.rotation
    angle = rotation_angle(rotation)
    turned = bool(angle > TURN_ANGLE and given > best * (1.0 + TURN_MARGIN))
    up = None
    if turned and model_up is not None:
        up = _axis_name(rotation.T @ parse_axis(model_up))
    posed = points @ rotation.T if turned else points  # the shape in its best pose, back in the [-1, 1] box
    posed = Normalizer().fit(posed).apply(posed)
    fit = keypoint_fit(keypoints_of, posed)
    score_limit, keypoint_limit = limits.get("score_limit"), limits.get("keypoint_limit")
    foreign = bool((score_limit is not None and best > score_limit)
                   or (keypoint_limit is not None and fit > keypoint_limit))
    return FrameCheck(float(given), best, rotation, float(angle), turned, up, fit,
                      None if score_limit is None else float(score_limit),
                      None if keypoint_limit is None else float(keypoint_limit), foreign)


def check_frame(model: Any, shape: Any, *, seed: int = 0) -> FrameCheck | None:
    """Compare a shape's own pose with the model's frame, and its fit with the category's (module docstring).

    Parameters
    ----------
    model : kpd.runtime.Model (its bundle's template cloud, up axis and ``frame_check`` calibration are used).
    shape : Mesh, PointSet or (N, 3) points in the input's own frame and units.
    seed : the surface-sampling seed (the points the model itself sees are checked).

    Returns
    -------
    FrameCheck, or None when the bundle has no template cloud to compare with.
    """
    template = model.template_points
    if template is None:
        return None
    _, points = model.sample(shape, seed=seed)
    cache = getattr(model, "_frame_aligner", None)
    if cache is None:
        cache = _aligner(template, model.up)
        model._frame_aligner = cache
    limits = model.bundle.manifest.get("frame_check") or {}
    result = _check(cache, lambda p: model.run(p)[0], points, model.up, limits)
    log.info("frame check: given %.4f, best %.4f at %.0f deg%s%s", result.given_score, result.best_score,
             result.angle, " (turned)" if result.turned else "", " (foreign)" if result.foreign else "")
    return result


def calibrate(template: Any, up: str | None, training_points: Any, keypoints_of: Any) -> dict:
    """The bundle's ``frame_check`` entry: the limits of a category shape's fits, from training shapes.

    Parameters
    ----------
    template : (P, 3) float64, the bundle's template cloud (model frame).
    up : the model's up axis.
    training_points : (S, N, 3) float64, model-frame point samples of training shapes (N = the model's point count).
    keypoints_of : the model's keypoints of model-frame points, (N, 3) -> (K, 3).

    Returns
    -------
    ``{"score_limit", "keypoint_limit"}``: LIMIT_FACTOR x the LIMIT_QUANTILE quantile of the training shapes' best
    scores and keypoint fits, with ``"quantile"``, ``"factor"``, ``"shapes"`` and the medians.
    """
    aligner = _aligner(np.asarray(template, dtype=np.float64), up)
    scores, fits = [], []
    for p in training_points:
        p = np.asarray(p, dtype=np.float64)
        scores.append(aligner.orient(p).score)
        fits.append(keypoint_fit(keypoints_of, p))
    return {"score_limit": float(LIMIT_FACTOR * np.quantile(scores, LIMIT_QUANTILE)),
            "keypoint_limit": float(LIMIT_FACTOR * np.quantile(fits, LIMIT_QUANTILE)),
            "quantile": LIMIT_QUANTILE, "factor": LIMIT_FACTOR, "shapes": int(len(scores)),
            "median_score": float(np.median(scores)), "median_keypoint_fit": float(np.median(fits))}


def frame_warnings(model: Any, shape: Any, *, seed: int = 0, name: str = "the shape") -> list[str]:
    """The lines to show when ``shape`` sits turned in the model's frame or is probably not of its category
    (:func:`check_frame`; the check behind the commands without ``--scan``); empty when all is well."""
    result = check_frame(model, shape, seed=seed)
    return [] if result is None else result.warnings(model.category, name)


# --- scans in the model's frame (--scan) ----------------------------------------------------------------------


def ambiguity_advice(up_given: bool, orientation: Any = None, model_up: str | None = None) -> str:
    """The warning for an ambiguous orientation: what it means, the alternatives and what to do.

    ``orientation`` (a :class:`kpd.scan.Orientation`) and ``model_up``: the alternatives are named, the input's axis
    each turns up (``--up`` picks one of them) or, for a turn about the chosen up axis (a shoe's toe and heel
    swapped, a table turned about its legs), that no ``--up`` settles it.
    """
    check = "kpd scan --picture draws the candidates"
    if orientation is not None and model_up is not None:
        from kpd.scan import candidate_rotations, parse_axis, rotation_angle

        up = parse_axis(model_up)
        candidates = candidate_rotations(orientation)
        chosen = _axis_name(candidates[0][0].T @ up)
        ups = sorted({_axis_name(r.T @ up) for r, _ in candidates[1:]} - {chosen})
        turns = sorted({round(rotation_angle(r, candidates[0][0]) / 5) * 5 for r, _ in candidates[1:]
                        if _axis_name(r.T @ up) == chosen})
        parts = []
        if ups:
            parts.append(f"another up axis fits almost as well ({' or '.join(ups)} instead of {chosen}); if one of "
                         f"them is the shape's up, pass --up with it")
        half = [t for t in turns if t >= 135]
        if half:
            parts.append(f"a half turn about the up axis ({chosen}) fits almost as well, the shape's two ends swapped "
                         "(a shoe's toe and heel, a table's sides), which no --up settles: look at which end the "
                         "keypoints mark")
        if len(half) < len(turns):
            parts.append(f"a turn of {' or '.join(f'{t:.0f}' for t in turns if t < 135)} degrees about the up axis "
                         f"({chosen}) fits almost as well, which no --up settles: look at the result")
        if parts:
            return f"the orientation is ambiguous: {'; '.join(parts)} ({check})"
    if up_given:
        return ("the orientation is ambiguous: a turn about the up axis far from the chosen one fits almost as well "
                f"(a symmetric object, such as a table turned 180 degrees, gives the same shape either way); check "
                f"the result ({check})")
    return ("the orientation is ambiguous: a rotation far from the chosen one fits almost as well (symmetric or "
            f"round object?); check the result ({check}), or pass --up with the shape's up axis (x, y, z, -x...)")


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
    holds what was decided (None: nothing settled) and ``rigid`` the result of the best rigid fit alone.

    Nothing is printed: ``warnings`` holds the lines a user should see (an ambiguous orientation), ``notes`` what was
    decided for them (a settled one); the commands print them."""

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
        self._model, self._shape = model, shape
        self.result = preprocess(shape, reference, outer=model.outer_surface, **params)
        self.rigid = self.result  # the best rigid fit, before any settling
        self.settled = None
        if settle:
            self.result, self.settled = settle_orientation(model, self.result, seed=seed)
        self.warnings: list[str] = []
        self.notes: list[str] = []
        orientation = self.result.orientation
        if orientation is not None and orientation.ambiguous:
            if self.settled is None:
                self.warnings.append(ambiguity_advice(up is not None, orientation, model.up))
            else:
                s = self.settled
                self.notes.append(
                    f"the orientation was ambiguous by shape alone ({len(s['candidates'])} candidate "
                    f"rotations); settled by the model (the scan deformed onto the template fits it best, "
                    f"{s['margin']:.0%} better than the next; the candidate "
                    f"{s['candidates'][s['chosen']]['angle_deg']:.0f} degrees from the best rigid fit)")

    def category_warnings(self, *, seed: int = 0, name: str = "the shape") -> list[str]:
        """The category check that runs without ``--scan`` (:func:`check_frame`'s ``foreign``, on the shape as given:
        the check searches its poses itself), kept with it: one line when the shape is probably not of the model's
        category, else none."""
        result = check_frame(self._model, self._shape, seed=seed)
        if result is None or not result.foreign:
            return []
        return result._replace(turned=False).warnings(self._model.category, name)

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


def bind_shape(model: Any, mesh: Any, *, scan: bool = False, up: str | None = None, path: Any = None,
               seed: int = 0) -> Any:
    """A shape's rig in its own frame, as the commands bind it: as it is, or with ``scan`` (``--scan``) oriented into
    the model's frame first (:class:`ScanFrame`; ``up`` as ``--up``, else the file's own up axis when ``path`` names
    a glTF), bound there and seen back in the scan's own frame and units (:class:`ScanRig`)."""
    if not scan:
        return model.rig(mesh, seed=seed)
    if up is None and path is not None:
        from kpd.io import file_up

        up = file_up(path)
    frame = ScanFrame(model, mesh, up, seed=seed)
    aligned = model.rig(mesh.with_vertices(frame.to_aligned(mesh.vertices)), seed=seed)
    return ScanRig(aligned, mesh, frame)


class _ScanFrameNormalizer:
    """The scan's own frame -> the model frame: the scan alignment, then the aligned rig's normaliser."""

    def __init__(self, scan: Any, normalizer: Any) -> None:
        self.scan, self.normalizer = scan, normalizer
        self._linear = np.asarray(scan.result.transform, dtype=np.float64)[:3, :3]  # (3, 3) original -> aligned
        self._inverse = np.linalg.inv(self._linear)

    def apply(self, x: Any) -> np.ndarray:
        return self.normalizer.apply(self.scan.to_aligned(np.asarray(x, dtype=np.float64)))

    def invert(self, y: Any) -> np.ndarray:
        return self.scan.to_original(self.normalizer.invert(np.asarray(y, dtype=np.float64)))

    def apply_vectors(self, d: Any) -> np.ndarray:
        return self.normalizer.apply_vectors(np.asarray(d, dtype=np.float64) @ self._linear.T)

    def invert_vectors(self, d: Any) -> np.ndarray:
        return self.normalizer.invert_vectors(np.asarray(d, dtype=np.float64)) @ self._inverse.T


class ScanRig:
    """A rig made in the model's orientation (``--scan``) shown and saved in the scan's own frame and units.

    It offers what the editor and the renderer use of :class:`kpd.rig.Rig`: ``mesh``, ``keypoints``, ``cage``,
    ``normalizer``, ``num_keypoints``, ``deform``, ``deform_cage``, ``deformed_mesh``, ``moved``.

    Parameters
    ----------
    aligned : kpd.rig.Rig of the scan turned into the model's frame
    mesh : kpd.mesh.Mesh, the scan in its own frame and units
    scan : ScanFrame that turned it
    """

    def __init__(self, aligned: Any, mesh: Any, scan: Any) -> None:
        self.aligned, self.mesh, self.scan = aligned, mesh, scan
        self.cage = aligned.cage
        self.normalizer = _ScanFrameNormalizer(scan, aligned.normalizer)
        self._rest = scan.to_original(aligned.keypoints)
        self._aligned_out: np.ndarray | None = None  # (V, 3) deform(rows=)'s rows in the aligned frame

    @property
    def num_keypoints(self) -> int:
        return self.aligned.num_keypoints

    @property
    def keypoints(self) -> np.ndarray:
        return self._rest.copy()

    def deform(self, keypoints: Any, *, out: np.ndarray | None = None, rows: Any = None) -> np.ndarray:
        """(V, 3) the scan's vertices, in its own frame, with the keypoints (K, 3) moved to ``keypoints``.

        ``out``: a (V, 3) float64 array to write into. ``rows``: (P,) vertex indices, as for
        :meth:`kpd.rig.Rig.deform`: only these rows of ``out`` are computed and written (the editor's coarse
        stand-in of a large scan needs only its own vertices).
        """
        from kpd.errors import InputError

        keypoints = np.asarray(keypoints, dtype=np.float64)
        if keypoints.shape != self._rest.shape:
            raise InputError(f"keypoints must have shape ({self.num_keypoints}, 3); got {keypoints.shape}")
        if rows is None:
            offsets = self.aligned.deform(self.scan.to_aligned(keypoints)) - self.aligned.mesh.vertices  # (V, 3)
            result = self.mesh.vertices + self.scan.vector_to_original(offsets)
            if out is not None:
                out[...] = result
                return out
            return result
        if self._aligned_out is None:
            self._aligned_out = np.empty_like(self.aligned.mesh.vertices)
        self.aligned.deform(self.scan.to_aligned(keypoints), out=self._aligned_out, rows=rows)  # checks rows
        rows = np.asarray(rows)
        offsets = self._aligned_out[rows] - self.aligned.mesh.vertices[rows]  # (P, 3)
        out = np.empty_like(self.mesh.vertices) if out is None else out
        out[rows] = self.mesh.vertices[rows] + self.scan.vector_to_original(offsets)
        return out

    def deform_cage(self, keypoints: Any) -> np.ndarray:
        return self.scan.to_original(self.aligned.deform_cage(self.scan.to_aligned(np.asarray(keypoints))))

    def deformed_mesh(self, keypoints: Any) -> Any:
        return self.mesh.with_vertices(self.deform(keypoints))

    def moved(self, moves: dict) -> np.ndarray:
        """(K, 3) keypoints with ``{index: (dx, dy, dz)}`` offsets (the scan's units) added to the rest keypoints;
        checked as :meth:`kpd.rig.Rig.moved` checks them."""
        from kpd.rig import Rig

        return Rig.moved(self, moves)
