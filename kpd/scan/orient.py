"""Orienting a scan to a reference: a global search over rotations, each hypothesis refined by a trimmed, symmetric ICP
with a scale per axis, scored, and an ambiguous result flagged rather than silently chosen (:class:`ScanAligner`)."""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from kpd.errors import InputError, NotFittedError
from kpd.geometry import Normalizer, as_rng
from kpd.scan.clean import _pcd
from kpd.scan.rotations import (
    _about,
    _principal_frame,
    _rotation_between,
    icosahedral_rotations,
    parse_axis,
    proper_signed_permutations,
    rotation_angle,
)
from kpd.scan.shapes import _shape_points
from kpd.scan.support import _dense_subset, support_plane

__all__ = ["DEFAULT_AMBIGUITY_MARGIN", "MESH_ORIENT_SAMPLES", "Hypothesis", "Orientation", "ScanAligner", "orient"]

log = logging.getLogger("kpd.scan")


# A relative margin (runner-up score / best score - 1) below this is flagged ambiguous. Calibrated on ModelNet10
# *train* chairs and tables (60 each, outside the reference's pool, clean and corrupted, with and without a known up):
# the smallest threshold of the sweep at which the unflagged results are right >= 95% of the time on clean scans and
# >= 90% on corrupted ones, in both settings (benchmarks/results/scan_calibration.json: 97.6% / 92.3% without up,
# 98.3% / 92.5% with it). benchmarks/bench_scan.py measures it on the test split.
DEFAULT_AMBIGUITY_MARGIN = 0.15


# Surface points a mesh scan is oriented by (area-weighted, so independent of how the mesh spends its vertices).
MESH_ORIENT_SAMPLES = 20000


class Hypothesis(NamedTuple):
    """One refined rotation hypothesis; ``source`` names its start: ``pca:i`` (principal axes under signed
    permutation i), ``grid:i`` (icosahedral rotation i), ``fpfh:i`` (RANSAC run i), ``yaw:i`` / ``pca-yaw:i`` (with
    an up axis); ``+turnk`` for the best turned by k quarter turns about the reference's up axis; ``+support`` when
    the hypothesis was stood on its support plane (see :func:`support_plane`)."""

    rotation: np.ndarray
    score: float
    source: str


class Orientation(NamedTuple):
    """Result of :meth:`ScanAligner.orient`.

    rotation : (3, 3) float64, proper rotation turning the scan into the reference's frame
    translation : (3,) float64 and scale : (3,) float64 (one per reference axis; equal unless ``scaling='axes'``), so
        that ``(points @ rotation.T) * scale + translation`` lies on the reference (in the reference's units)
    score : the best hypothesis' trimmed symmetric RMS nearest-neighbour distance after ICP (the ``score_trim``
        nearest share of the distances each way), in units of the reference's [-1, 1] box
    runner_up_score : the best score of a rotation more than ``distinct_angle`` degrees from the best (inf if none)
    runner_up_rotation : (3, 3) float64 or None
    runner_up_angle : angle in degrees between best and runner-up rotations (nan if none)
    margin : runner_up_score / score - 1 (relative; inf if no runner-up)
    ambiguous : margin below the aligner's threshold: two genuinely different rotations fit about equally well
    hypotheses : every refined hypothesis, best first
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: np.ndarray
    score: float
    runner_up_score: float
    runner_up_rotation: np.ndarray | None
    runner_up_angle: float
    margin: float
    ambiguous: bool
    hypotheses: list

    def to_dict(self) -> dict:
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "scale": self.scale.tolist(),
            "score": num(self.score),
            "runner_up_score": num(self.runner_up_score),
            "runner_up_rotation": None if self.runner_up_rotation is None else self.runner_up_rotation.tolist(),
            "runner_up_angle": num(self.runner_up_angle),
            "margin": num(self.margin),
            "ambiguous": self.ambiguous,
            "hypotheses": [{"source": h.source, "score": num(h.score), "rotation": h.rotation.tolist()}
                           for h in self.hypotheses],
        }


class _Cloud(NamedTuple):
    """A shape in its working frame: centred on its centroid, unit RMS radius."""

    points: np.ndarray  # (n, 3) working-frame sample, in random order
    normals: np.ndarray  # (n, 3) unoriented unit normals
    tree: cKDTree  # over _features(points, normals): matching
    tree3: cKDTree  # over points: scoring
    center: np.ndarray  # (3,) centroid in original units
    radius: float  # RMS distance to the centroid, original units


def _axial(normals: np.ndarray) -> np.ndarray:
    """(n, 6) the unique entries of n n^T (sign-free), scaled so that distances match the Frobenius norm."""
    x, y, z = normals.T
    r2 = math.sqrt(2.0)
    return np.stack([x * x, y * y, z * z, r2 * x * y, r2 * x * z, r2 * y * z], axis=1)


def _umeyama(
    x: np.ndarray, y: np.ndarray, *, axis: np.ndarray | None, with_scale: bool
) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |s R x + t - y|^2; R restricted to rotations about ``axis`` if given."""
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my  # (n, 3)
    if axis is None:
        u, sig, vt = np.linalg.svd(yc.T @ xc)
        d = np.ones(3)
        d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
        rot = (u * d) @ vt
        trace = float((sig * d).sum())
    else:
        # rotation about the axis: angle from the components orthogonal to it
        basis = np.linalg.svd(axis[None, :])[2][1:]  # (2, 3)
        a, b = xc @ basis.T, yc @ basis.T  # (n, 2)
        angle = math.atan2(float((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()), float((a * b).sum()))
        e1, e2 = basis
        sign = np.sign(np.dot(np.cross(e1, e2), axis)) or 1.0
        rot = _about(axis, sign * angle)
        trace = float(np.einsum("ij,ij->", yc, xc @ rot.T))
    var = float((xc**2).sum())
    scale = trace / var if with_scale and var > 0 else 1.0
    return scale, rot, my - scale * rot @ mx


def _umeyama_rotations(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(H, 3, 3): the rotation of :func:`_umeyama` (no axis) of each pair ``x[h]``, ``y[h]`` ((H, n, 3) each)."""
    xc, yc = x - x.mean(axis=1)[:, None], y - y.mean(axis=1)[:, None]
    u, _, vt = np.linalg.svd(yc.transpose(0, 2, 1) @ xc)
    d = np.ones((len(x), 3))
    sign = np.sign(np.linalg.det(u @ vt))
    d[:, 2] = np.where(sign == 0, 1.0, sign)
    return (u * d[:, None, :]) @ vt


def _at_a_time(function: Any, items: Any, threads: int) -> list:
    """``[function(item) for item in items]`` on ``threads`` threads: the orientation hypotheses are independent, and
    their nearest-neighbour queries (scipy's cKDTree) release the GIL."""
    if threads == 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(function, items))


class ScanAligner:
    """Orients scans into the frame of a reference shape by a global rotation search.

    ``ScanAligner(**params).fit(reference_points)`` then ``orient(points)`` for each scan; :func:`orient` is the
    one-call form. Estimator-style: ``__init__`` stores parameters, ``fit`` returns ``self``.

    Parameters
    ----------
    up : the scan's up axis if known (``'z'``, ``'-y'`` or three numbers). The search is then restricted to the
        rotations that take it to ``reference_up`` followed by any rotation about ``reference_up``.
    reference_up : the reference's up axis (a property of the model's frame); defaults to ``up``. Given without
        ``up``, the search still covers all rotations but uses the support prior (``support``).
    support : with ``reference_up`` known and ``up`` not: objects are scanned standing, so each refined hypothesis is
        stood on the scan's support plane (:func:`support_plane` with the hypothesis' up as the guess) turned onto
        the reference's support plane, and then only its turn about the up axis is refined. A support plane is used
        only if hull faces within ``snap_angle`` degrees of the hypothesis' down direction exist and the centroid lies
        over their contact polygon (a cut-away leg leaves an unstable contact, which is not trusted). This fixes the
        tilt of the up axis by the floor contact (leg tips, a sole) rather than by the fit of two shapes of different
        proportions, which on ModelNet10 chairs left it 10 to 15 degrees off in about one case in ten.
    snap_angle : see ``support``.
    n_points : points of each shape used in the search: a random subset of the shape thinned on a ``voxel`` grid
        (``voxel`` in units of the shape's RMS radius), so that dense and sparse regions weigh alike.
    coarse_points, coarse_iterations : the cheap first ICP (positions only) run from every starting rotation.
    refine_top : how many distinct hypotheses get the full ICP (``iterations``).
    trim : share of nearest-neighbour pairs kept in each direction by ICP (robust to outliers and missing parts).
    scaling : what ICP may adjust besides the rotation: ``'axes'`` a scale per reference axis (shapes of a category
        differ in proportions), ``'uniform'`` one scale, ``'none'`` nothing (both start at unit RMS radius).
    normal_weight : weight of the (unoriented) normal direction in ICP's nearest-neighbour matching; 0 for positions
        only. Without ``up`` the hypotheses are refined and compared on positions only (normals of a noisy scan
        mislead the comparison) and only the winner is polished with normals.
    score_trim : share of nearest-neighbour distances kept in each direction by the score, a trimmed RMS distance.
    fpfh_runs : FPFH + RANSAC candidates added to the search (0 to turn them off).
    distinct_angle : the runner-up must differ from the best by more than this many degrees.
    ambiguity_margin : relative margin (runner-up score / best score - 1) below which the result is flagged ambiguous.
    seed : seeds the subsets and RANSAC.
    threads : refined hypotheses fitted at a time (the same result whatever the number; the coarse stage fits all
        its starts at once, see :meth:`_icp_together`, unless ``up`` is given or ``scaling`` is not ``'axes'``). Two
        suit ``kpd scan``'s full search; the frame check's light search is held by the GIL for most of its time, and
        one thread does it for less CPU in the same time.
    """

    def __init__(
        self,
        *,
        up: Any = None,
        reference_up: Any = None,
        n_points: int = 1000,
        voxel: float = 0.02,
        coarse_points: int = 300,
        coarse_iterations: int = 8,
        iterations: int = 30,
        refine_top: int = 6,
        trim: float = 0.8,
        scaling: str = "axes",
        normal_weight: float = 0.5,
        score_trim: float = 0.95,
        fpfh_runs: int = 2,
        distinct_angle: float = 30.0,
        ambiguity_margin: float = DEFAULT_AMBIGUITY_MARGIN,
        support: bool = True,
        snap_angle: float = 25.0,
        seed: int = 0,
        threads: int = 2,
    ) -> None:
        self.up = up
        self.reference_up = reference_up
        self.n_points = n_points
        self.voxel = voxel
        self.coarse_points = coarse_points
        self.coarse_iterations = coarse_iterations
        self.iterations = iterations
        self.refine_top = refine_top
        self.trim = trim
        self.scaling = scaling
        self.normal_weight = normal_weight
        self.score_trim = score_trim
        self.fpfh_runs = fpfh_runs
        self.distinct_angle = distinct_angle
        self.ambiguity_margin = ambiguity_margin
        self.support = support
        self.snap_angle = snap_angle
        self.seed = seed
        self.threads = threads

    # -- set-up -------------------------------------------------------------------------------------------------------

    def _check_params(self) -> None:
        for name in ("trim", "score_trim"):
            if not 0.1 <= getattr(self, name) <= 1.0:
                raise InputError(f"{name} must lie in [0.1, 1]; got {getattr(self, name)}")
        if self.scaling not in ("axes", "uniform", "none"):
            raise InputError(f"scaling must be 'axes', 'uniform' or 'none'; got {self.scaling!r}")
        if not (self.voxel > 0 and self.normal_weight >= 0 and self.ambiguity_margin >= 0):
            raise InputError(f"voxel must be > 0, normal_weight and ambiguity_margin >= 0; got {self.voxel}, "
                             f"{self.normal_weight}, {self.ambiguity_margin}")
        for name in ("n_points", "coarse_points", "iterations", "refine_top", "threads"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be at least 1; got {getattr(self, name)}")
        if self.fpfh_runs < 0 or self.coarse_iterations < 0:
            raise InputError(f"fpfh_runs and coarse_iterations must be >= 0; got {self.fpfh_runs}, "
                             f"{self.coarse_iterations}")
        if not 0.0 <= self.snap_angle < 90.0:
            raise InputError(f"snap_angle must lie in [0, 90) degrees; got {self.snap_angle}")
        if not 0.0 < self.distinct_angle < 180.0:
            raise InputError(f"distinct_angle must lie in (0, 180) degrees; got {self.distinct_angle}")

    def _features(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n, 9) positions and weighted axial normals: nearest neighbours must agree in place and surface direction."""
        return np.concatenate([points, self.normal_weight * _axial(normals)], axis=1)

    def _cloud(self, points: np.ndarray, rng: np.random.Generator) -> _Cloud:
        center = points.mean(axis=0)
        radius = float(np.sqrt(((points - center) ** 2).sum(axis=1).mean()))
        if not radius > 0:
            raise InputError(f"cannot orient a shape whose {len(points)} points all coincide")
        pcd = _pcd((points - center) / radius).voxel_down_sample(self.voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        thinned, normals = np.asarray(pcd.points), np.asarray(pcd.normals)
        # a random order, so that any prefix is a random subset (the coarse stage uses one)
        order = rng.permutation(len(thinned))[: self.n_points]
        thinned, normals = thinned[order], normals[order]
        return _Cloud(thinned, normals, cKDTree(self._features(thinned, normals)), cKDTree(thinned), center, radius)

    def fit(self, reference: Any) -> "ScanAligner":
        """Prepare the reference: (N, 3) points, a PointSet or a Mesh (its vertices; sample a mesh's surface first for
        an even density), in the frame the scans should be turned into."""
        self._check_params()
        points = _shape_points(reference, "reference")
        if len(points) < 10:
            raise InputError(f"the reference needs at least 10 points; got {len(points)}")
        self.up_ = None if self.up is None else parse_axis(self.up)
        ref_up = self.reference_up if self.reference_up is not None else self.up
        self.reference_up_ = None if ref_up is None else parse_axis(ref_up, "reference_up")
        self.reference_ = self._cloud(points, as_rng(self.seed))
        self.reference_box_scale_ = Normalizer().fit(points).scale_
        self.reference_support_ = None
        if self._uses_support():
            ref = self.reference_
            work = _dense_subset(self._working_sample((points - ref.center) / ref.radius, as_rng(self.seed)))
            self.reference_support_ = support_plane(work, self.reference_up_)
        self._reference_fpfh = self._fpfh(self.reference_.points) if self.fpfh_runs else None
        return self

    def _uses_support(self) -> bool:
        """The support prior applies when the reference's up axis is known and the scan's is not."""
        return bool(self.support) and self.up_ is None and self.reference_up_ is not None

    _SUPPORT_POINTS = 6000  # points of a shape used to find its support plane

    def _working_sample(self, work: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if len(work) > self._SUPPORT_POINTS:
            work = work[rng.choice(len(work), self._SUPPORT_POINTS, replace=False)]
        return work

    def _check_fitted(self) -> None:
        if not hasattr(self, "reference_"):
            raise NotFittedError("this ScanAligner has no reference yet; call fit(reference_points) first")

    # -- the search ---------------------------------------------------------------------------------------------------

    _SCALE_RANGE = (0.5, 2.0)  # bounds of the ICP scales (both shapes start at unit RMS radius)
    _VOXEL = 0.08  # FPFH voxel in units of the RMS radius

    def _fpfh(self, work: np.ndarray) -> tuple[o3d.geometry.PointCloud, Any]:
        voxel = self._VOXEL
        pcd = _pcd(work).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return pcd, fpfh

    def _fpfh_candidates(self, work: np.ndarray) -> list[np.ndarray]:
        reg = o3d.pipelines.registration
        source, source_fpfh = self._fpfh(work)
        target, target_fpfh = self._reference_fpfh
        distance = 1.5 * self._VOXEL
        out = []
        for run in range(self.fpfh_runs):
            o3d.utility.random.seed(self.seed + run)
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # "too few correspondences"
                result = reg.registration_ransac_based_on_feature_matching(
                    source, target, source_fpfh, target_fpfh, True, distance,
                    reg.TransformationEstimationPointToPoint(False), 3,
                    [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                     reg.CorrespondenceCheckerBasedOnDistance(distance)],
                    reg.RANSACConvergenceCriteria(20000, 0.999))
            rot = np.asarray(result.transformation)[:3, :3].copy()
            if np.isfinite(rot).all() and abs(np.linalg.det(rot) - 1.0) < 1e-6:
                out.append(rot)
        return out

    def _initial(self, scan: _Cloud) -> list[tuple[np.ndarray, str]]:
        """Starting rotations (working frame of the scan -> working frame of the reference)."""
        ref = self.reference_
        starts: list[tuple[np.ndarray, str]] = []
        if self.up_ is None:
            frame_s, frame_r = _principal_frame(scan.points), _principal_frame(ref.points)
            for i, perm in enumerate(proper_signed_permutations()):
                starts.append((frame_r @ perm @ frame_s.T, f"pca:{i}"))
            for i, rot in enumerate(icosahedral_rotations()):
                starts.append((rot, f"grid:{i}"))
        else:
            tilt = _rotation_between(self.up_, self.reference_up_)
            axis = self.reference_up_
            for i in range(24):
                starts.append((_about(axis, 2 * np.pi * i / 24) @ tilt, f"yaw:{i}"))
            # principal horizontal axes matched both ways and both signs
            basis = np.linalg.svd(axis[None, :])[2][1:]  # (2, 3)

            def horizontal_angle(points: np.ndarray) -> float:
                flat = (points - points.mean(axis=0)) @ basis.T  # (n, 2)
                _, v = np.linalg.eigh(flat.T @ flat)
                return math.atan2(v[1, -1], v[0, -1])

            a_s = horizontal_angle(scan.points @ tilt.T)
            a_r = horizontal_angle(ref.points)
            sign = np.sign(np.dot(np.cross(basis[0], basis[1]), axis)) or 1.0
            for k in range(4):
                starts.append((_about(axis, sign * (a_r - a_s + k * np.pi / 2)) @ tilt, f"pca-yaw:{k}"))
        if self.fpfh_runs:
            for i, rot in enumerate(self._fpfh_candidates(scan.points)):
                if self.up_ is not None:
                    rot = self._project_to_up(rot)
                starts.append((rot, f"fpfh:{i}"))
        return starts

    def _project_to_up(self, rot: np.ndarray) -> np.ndarray:
        """The allowed rotation (tilt to reference_up, then about it) nearest to ``rot``."""
        tilt = _rotation_between(self.up_, self.reference_up_)
        rest = rot @ tilt.T  # ideally a rotation about reference_up
        axis = self.reference_up_
        basis = np.linalg.svd(axis[None, :])[2][1:]
        m = basis @ rest @ basis.T  # (2, 2)
        angle = math.atan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1])
        sign = np.sign(np.dot(np.cross(basis[0], basis[1]), axis)) or 1.0
        return _about(axis, sign * angle) @ tilt

    def _icp(self, scan: _Cloud, rot: np.ndarray, iterations: int, n: int | None = None, *, normals: bool = True,
             ups: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Trimmed symmetric ICP in the working frames from the rotation ``rot``.

        The transform is ``x -> a * (R x) + t`` with ``a`` (3,) a scale per reference axis (``scaling='axes'``), one
        scale (``'uniform'``) or none (``'none'``). Nearest neighbours are found both ways among points whose
        positions and (weighted) normal directions agree. ``ups`` (scan up, reference up) restricts R to the turns
        that take the one to the other (default: ``up`` and ``reference_up`` when ``up`` is given). Returns
        (a, R, t, score), the score of :meth:`_score`.
        """
        ref = self.reference_
        ref_points, ref_normals = ref.points[:n], ref.normals[:n]  # random order: a prefix is a random subset
        scan_points, scan_normals = scan.points[:n], scan.normals[:n]
        if ups is None and self.up_ is not None:
            ups = (self.up_, self.reference_up_)
        axis = None if ups is None else ups[1]
        tilt = None if ups is None else _rotation_between(*ups)
        a, r, t = np.ones(3), rot, np.zeros(3)
        kept_s = max(3, int(self.trim * len(scan_points)))
        kept_r = max(3, int(self.trim * len(ref_points)))

        def match(a: np.ndarray, r: np.ndarray, t: np.ndarray):
            moved = (scan_points @ r.T) * a + t
            back = ((ref_points - t) / a) @ r  # the reference in the scan's working frame
            if normals and self.normal_weight > 0:
                d1, i1 = ref.tree.query(self._features(moved, scan_normals @ r.T))
                d2, i2 = scan.tree.query(self._features(back, ref_normals @ r))
            else:
                d1, i1 = ref.tree3.query(moved)
                d2, i2 = scan.tree3.query(back)
            return d1, i1, d2, i2

        for _ in range(iterations):
            d1, i1, d2, i2 = match(a, r, t)
            o1 = np.argpartition(d1, kept_s - 1)[:kept_s]
            o2 = np.argpartition(d2, kept_r - 1)[:kept_r]
            x = np.concatenate([scan_points[o1], scan.points[i2[o2]]])  # (k, 3) scan working frame
            y = np.concatenate([ref.points[i1[o1]], ref_points[o2]])  # (k, 3) their partners on the reference
            if axis is not None:
                x = x @ tilt.T  # then only a turn about the reference's up axis is left to find
            if self.scaling == "axes":
                _, r_new, _ = _umeyama(x, (y - t) / a, axis=axis, with_scale=False)
                turned = x @ r_new.T
                tc, yc = turned - turned.mean(axis=0), y - y.mean(axis=0)
                a_new = np.clip((tc * yc).sum(axis=0) / np.maximum((tc * tc).sum(axis=0), 1e-12), *self._SCALE_RANGE)
                t_new = y.mean(axis=0) - a_new * turned.mean(axis=0)
            else:
                s_new, r_new, t_new = _umeyama(x, y, axis=axis, with_scale=self.scaling == "uniform")
                a_new = np.full(3, float(np.clip(s_new, *self._SCALE_RANGE)))
                t_new = y.mean(axis=0) - a_new * (x.mean(axis=0) @ r_new.T)
            if axis is not None:
                r_new = r_new @ tilt
            done = (rotation_angle(r_new, r) < 0.01 and np.abs(a_new - a).max() < 1e-5
                    and np.abs(t_new - t).max() < 1e-5)
            a, r, t = a_new, r_new, t_new
            if done:
                break
        return a, r, t, self._score(scan, a, r, t, n)

    def _coarse(self, scan: _Cloud, starts: list[tuple[np.ndarray, str]]) -> list[tuple[float, np.ndarray, str]]:
        """``(score, R, source)`` of the coarse ICP (:meth:`_icp` on positions, ``coarse_points`` of each shape,
        ``coarse_iterations``) from each start: all at once (:meth:`_icp_together`) where the search is over every
        rotation with a scale per axis, else one by one."""
        if self.up_ is None and self.scaling == "axes" and starts:
            fits = self._icp_together(scan, np.stack([r for r, _ in starts]), self.coarse_iterations,
                                      self.coarse_points)
            return [(score, r, source) for (_, r, _, score), (_, source) in zip(fits, starts)]

        def first_fit(start: tuple) -> tuple[float, np.ndarray, str]:
            _, r, _, score = self._icp(scan, start[0], self.coarse_iterations, self.coarse_points, normals=False)
            return score, r, start[1]

        return _at_a_time(first_fit, starts, self.threads)

    def _icp_together(self, scan: _Cloud, rotations: np.ndarray, iterations: int, n: int) -> list[tuple]:
        """:meth:`_icp` on positions from each of ``rotations`` (H, 3, 3), without an up axis, with a scale per axis:
        the same steps on the hypotheses' arrays stacked, one nearest-neighbour query a step for all the hypotheses
        still moving (one by one, the frame check spent two thirds of its time calling the queries and numpy on a
        few hundred points at a time). The same results as :meth:`_icp`, each hypothesis stopping at the step it
        would stop at alone (tested). Returns the (a, R, t, score) of each."""
        ref = self.reference_
        ref_points, scan_points = ref.points[:n], scan.points[:n]
        count = len(rotations)
        a, r, t = np.ones((count, 3)), np.array(rotations, dtype=np.float64), np.zeros((count, 3))
        kept_s = max(3, int(self.trim * len(scan_points)))
        kept_r = max(3, int(self.trim * len(ref_points)))
        moving = np.arange(count)
        for _ in range(iterations):
            if not len(moving):
                break
            am, rm, tm = a[moving], r[moving], t[moving]  # (m, 3), (m, 3, 3), (m, 3)
            m = len(moving)
            moved = (scan_points @ rm.transpose(0, 2, 1)) * am[:, None] + tm[:, None]  # (m, ns, 3)
            back = ((ref_points - tm[:, None]) / am[:, None]) @ rm  # (m, nr, 3): the reference in the scan's frame
            d1, i1 = ref.tree3.query(moved.reshape(-1, 3))
            d2, i2 = scan.tree3.query(back.reshape(-1, 3))
            d1, i1, d2, i2 = d1.reshape(m, -1), i1.reshape(m, -1), d2.reshape(m, -1), i2.reshape(m, -1)
            o1 = np.argpartition(d1, kept_s - 1, axis=1)[:, :kept_s]
            o2 = np.argpartition(d2, kept_r - 1, axis=1)[:, :kept_r]
            x = np.concatenate([scan_points[o1], scan.points[np.take_along_axis(i2, o2, axis=1)]], axis=1)  # (m, k, 3)
            y = np.concatenate([ref.points[np.take_along_axis(i1, o1, axis=1)], ref_points[o2]], axis=1)
            r_new = _umeyama_rotations(x, (y - tm[:, None]) / am[:, None])
            turned = x @ r_new.transpose(0, 2, 1)
            turned_mean, y_mean = turned.mean(axis=1), y.mean(axis=1)  # (m, 3)
            tc, yc = turned - turned_mean[:, None], y - y_mean[:, None]
            a_new = np.clip((tc * yc).sum(axis=1) / np.maximum((tc * tc).sum(axis=1), 1e-12), *self._SCALE_RANGE)
            t_new = y_mean - a_new * turned_mean
            cosine = (np.trace(r_new @ rm.transpose(0, 2, 1), axis1=1, axis2=2) - 1.0) / 2.0
            done = ((np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))) < 0.01)
                    & (np.abs(a_new - am).max(axis=1) < 1e-5) & (np.abs(t_new - tm).max(axis=1) < 1e-5))
            a[moving], r[moving], t[moving] = a_new, r_new, t_new
            moving = moving[~done]
        return [(a[h], r[h], t[h], score) for h, score in enumerate(self._scores(scan, a, r, t, n))]

    def _scores(self, scan: _Cloud, a: np.ndarray, r: np.ndarray, t: np.ndarray, n: int) -> list[float]:
        """:meth:`_score` of each hypothesis ((H, 3), (H, 3, 3), (H, 3)), with one query each way for all."""
        ref = self.reference_
        ref_points, scan_points = ref.points[:n], scan.points[:n]
        count = len(a)
        d1, _ = ref.tree3.query(((scan_points @ r.transpose(0, 2, 1)) * a[:, None] + t[:, None]).reshape(-1, 3))
        _, i2 = scan.tree3.query((((ref_points - t[:, None]) / a[:, None]) @ r).reshape(-1, 3))
        matched = scan.points[i2.reshape(count, -1)]  # (H, m, 3)
        d2 = np.linalg.norm((matched @ r.transpose(0, 2, 1)) * a[:, None] + t[:, None] - ref_points, axis=2)
        d1 = d1.reshape(count, -1)

        def trimmed(d: np.ndarray) -> np.ndarray:
            k = max(1, int(self.score_trim * d.shape[1]))
            return (np.partition(d, k - 1, axis=1)[:, :k] ** 2).mean(axis=1)

        return [math.sqrt(0.5 * (u + v)) for u, v in zip(trimmed(d1).tolist(), trimmed(d2).tolist())]

    def _score(self, scan: _Cloud, a: np.ndarray, r: np.ndarray, t: np.ndarray, n: int | None = None) -> float:
        """Trimmed symmetric RMS distance between positions (working units) of the first ``n`` points of each shape:
        each way the ``score_trim`` nearest share of the nearest-neighbour distances counts (robust to outliers and
        missing parts)."""
        ref = self.reference_
        ref_points, scan_points = ref.points[:n], scan.points[:n]
        d1, _ = ref.tree3.query((scan_points @ r.T) * a + t)  # (n,)
        _, i2 = scan.tree3.query(((ref_points - t) / a) @ r)
        d2 = np.linalg.norm((scan.points[i2] @ r.T) * a + t - ref_points, axis=1)  # (m,)

        def trimmed(d: np.ndarray) -> float:
            k = max(1, int(self.score_trim * len(d)))
            return float((np.partition(d, k - 1)[:k] ** 2).mean())

        return math.sqrt(0.5 * (trimmed(d1) + trimmed(d2)))

    def orient(self, points: Any) -> Orientation:
        """Find the rotation of ``points`` (N, 3) (or a PointSet / Mesh) into the reference's frame."""
        self._check_fitted()
        points = _shape_points(points, "scan")
        if len(points) < 10:
            raise InputError(f"the scan needs at least 10 points to be oriented; got {len(points)}")
        rng = as_rng(self.seed + 1)
        scan = self._cloud(points, rng)
        standing = None  # the scan's dense points (working frame), to find its support plane
        if self._uses_support():
            standing = _dense_subset(self._working_sample((points - scan.center) / scan.radius, rng))
        starts = self._initial(scan)

        # coarse: a short ICP (positions only) on a small subset for every start; keep the best of each cluster
        coarse = self._coarse(scan, starts)
        coarse.sort(key=lambda c: c[0])
        chosen: list[tuple[float, np.ndarray, str]] = []
        for score, r, source in coarse:
            if all(rotation_angle(r, c[1]) > 10.0 for c in chosen):
                chosen.append((score, r, source))
            if len(chosen) >= self.refine_top:
                break

        # Without an up axis, hypotheses are refined and compared on positions only: normals estimated on a noisy
        # scan (noise of 1% of the size is several voxels) mislead the matching and favour wrong rotations (re-scoring
        # the hypotheses of 40 noisy ModelNet10 chair scans: 17 right / 12 wrong decided with normals, 25 / 0
        # without). The winner is polished with normals afterwards. With an up axis the search is narrow and normals
        # help it.
        search_normals = self.up_ is not None

        def refine(r0: np.ndarray, source: str) -> tuple:
            a, r, t, score = self._icp(scan, r0, self.iterations, normals=search_normals)
            ups = None
            if standing is not None:
                # the support prior: stand the scan on its own support plane (the hull faces under it with the
                # hypothesis' up pointing up, within snap_angle) and turn that plane onto the reference's, then
                # refine only the turn about the up axis
                guess = r.T @ self.reference_up_
                found = support_plane(standing, guess, max_angle=self.snap_angle)
                if found.count and found.stability > 0:  # an unstable support is not one (a cut-away leg)
                    ups = (found.normal, self.reference_support_.normal)
                    a, r, t, score = self._icp(scan, r, self.iterations, normals=search_normals, ups=ups)
                    source += "+support"
            return score, a, r, t, source, ups

        refined = sorted(_at_a_time(lambda c: refine(c[1], c[2]), chosen, self.threads), key=lambda c: c[0])
        if standing is not None:
            # With the up axis settled by the support, the quarter turns of the best about it are searched too:
            # many objects (tables, boxes) look alike after such a turn, and a runner-up found there is a genuine
            # alternative that the starts may have missed (it may also win: then it is the better fit)
            _, _, r_best, _, source_best, ups_best = refined[0]

            def turn(k: int) -> tuple:
                turned = _about(self.reference_up_, k * np.pi / 2) @ r_best
                source = f"{source_best.split('+')[0]}+turn{k}"
                if ups_best is None:
                    return refine(turned, source)
                # already standing on its support: only the turn about the up axis is refined
                a, r, t, score = self._icp(scan, turned, self.iterations, normals=search_normals, ups=ups_best)
                return score, a, r, t, source + "+support", ups_best

            refined += _at_a_time(turn, (1, 2, 3), self.threads)
            refined.sort(key=lambda c: c[0])
        unit = self.reference_.radius / self.reference_box_scale_  # working units -> reference box units
        best_score, s, r, t, _, best_ups = refined[0]
        runner = next((c for c in refined[1:] if rotation_angle(c[2], r) > self.distinct_angle), None)
        # the coarse stage may know a distinct rotation that the fine stage did not keep
        if runner is None:
            for _, r_c, source in coarse:
                if rotation_angle(r_c, r) > self.distinct_angle:
                    candidate = refine(r_c, source)
                    if rotation_angle(candidate[2], r) > self.distinct_angle:
                        runner = candidate
                        refined.append(runner)
                        break
        if not search_normals and self.normal_weight > 0:
            # polish the winner with normals (same constraint); its score stays the one it was chosen by
            s, r, t, _ = self._icp(scan, r, self.iterations, ups=best_ups)
            refined[0] = (best_score, s, r, t, refined[0][4], best_ups)
        # back to original units: y = c_ref + r_ref * (a * R (x - c_scan) / r_scan + t), centres c, RMS radii r
        ref = self.reference_
        scale = s * ref.radius / scan.radius  # (3,)
        translation = ref.center + ref.radius * t - scale * (r @ scan.center)
        if runner is None:
            runner_score, runner_rot, runner_angle, margin = math.inf, None, math.nan, math.inf
        else:
            runner_score, runner_rot = runner[0] * unit, runner[2]
            runner_angle = rotation_angle(runner_rot, r)
            margin = runner[0] / best_score - 1.0 if best_score > 0 else math.inf
        hypotheses = [Hypothesis(c[2], c[0] * unit, c[4]) for c in sorted(refined, key=lambda c: c[0])]
        ambiguous = bool(margin < self.ambiguity_margin)
        result = Orientation(r, translation, scale, best_score * unit, runner_score, runner_rot, runner_angle,
                             float(margin), ambiguous, hypotheses)
        log.info("orient: score %.4f, runner-up %.4f at %.0f deg, margin %.3f%s", result.score, runner_score,
                 runner_angle, margin, " (ambiguous)" if ambiguous else "")
        return result


def orient(points: Any, reference: Any, **params: Any) -> Orientation:
    """One call of ``ScanAligner(**params).fit(reference).orient(points)``; see :class:`ScanAligner`."""
    return ScanAligner(**params).fit(reference).orient(points)
