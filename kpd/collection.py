"""Bring a collection of scans of one category into one shared frame, without a hand-picked reference.

Groupwise alignment (:func:`align_collection`), reusing the orientation search of :class:`kpd.scan.ScanAligner`:

1. the first template is the collection's **medoid** by a rotation-invariant descriptor (:func:`shape_descriptor`:
   the distribution of point-pair distances and the principal extents of each shape at unit RMS radius), so no
   rotation search is needed to choose it, and the collection frame is that shape's own frame;
2. every shape is oriented to the template (the full rotation search, or the turns about ``up`` when it is known),
   with its score, runner-up and ambiguity flag;
3. a flagged shape is settled by its decided look-alikes when they clearly prefer one of its candidate rotations
   (:func:`_neighbour_vote`: a ballet flat is judged by other flats, not by the template sneaker);
4. the template is **re-estimated** as the medoid, by chamfer distance in the shared frame, of the shapes just
   aligned and not flagged, and step 2 is repeated, until the template no longer changes or no shape turns by
   more than 10 degrees between rounds (or ``rounds``);
5. without a known up axis, the collection is **stood on its floor** (:func:`floor_up`, :func:`stand_collection`):
   objects are scanned standing, so the shared frame's up axis is the direction in which the decided shapes rest on
   a flat contact (a sole, the tips of four legs) and each decided shape is turned by the small tilt that stands it
   on its own support plane (:func:`kpd.scan.support_plane`). A template fit tilts shapes of other proportions (a
   ballet flat fitted to a sneaker); the floor under each shape does not. Nothing is stood when no direction is a
   clear floor for the collection.

A shape flagged ambiguous (two rotations more than ``distinct_angle`` apart fit within the ambiguity margin) is
reported as such, never silently counted as aligned. Every result is kept in a JSON state file after each shape,
so a killed run continues where it stopped (``state``). Everything is numpy, scipy and Open3D; no torch.
"""

from __future__ import annotations

import json
import logging
import math
import os
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np
from scipy.spatial import cKDTree

from kpd.errors import DataError, InputError
from kpd.geometry import as_points, as_rng, sample_surface
from kpd.scan import (DEFAULT_AMBIGUITY_MARGIN, ScanAligner, _dense_subset, _rotation_between, parse_axis,
                      hull_faces, rotation_angle, support_plane)

__all__ = [
    "CollectionShape",
    "CollectionAlignment",
    "find_shapes",
    "collection_points",
    "shape_descriptor",
    "descriptor_medoid",
    "chamfer_medoid",
    "floor_up",
    "stand_collection",
    "align_collection",
    "pairwise_rotation_errors",
    "rms_unit",
]

log = logging.getLogger(__name__)

STATE_VERSION = 1


class CollectionShape(NamedTuple):
    """One shape's result in :class:`CollectionAlignment`.

    - name : the shape's name ; rotation : (3, 3) float64, turns the shape into the shared frame (``x @ rotation.T``)
    - score : trimmed RMS distance to the template after refinement (template's [-1, 1] units)
    - runner_up_score / runner_up_angle : the best rotation more than ``distinct_angle`` degrees away, and its angle
    - margin : ``runner_up_score / score - 1`` ; ambiguous : margin under the threshold (not decided)
    - template : True for the shape that served as the final template (its rotation is the reference's)
    - decided_by : ``"template"`` (its fit to the template), ``"neighbours"`` (flagged there, settled by its decided
      look-alikes) or ``"undecided"``
    """

    name: str
    rotation: np.ndarray
    score: float
    runner_up_score: float
    runner_up_angle: float
    margin: float
    ambiguous: bool
    template: bool = False
    decided_by: str = "template"
    tilt: float = math.nan

    def to_dict(self) -> dict:
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        transform = np.eye(4)
        transform[:3, :3] = self.rotation
        return {"name": self.name, "transform": transform.tolist(), "score": num(self.score),
                "runner_up_score": num(self.runner_up_score), "runner_up_angle": num(self.runner_up_angle),
                "margin": num(self.margin), "ambiguous": bool(self.ambiguous), "template": bool(self.template),
                "decided_by": self.decided_by, "tilt": None if not np.isfinite(self.tilt) else float(self.tilt)}

    @classmethod
    def from_dict(cls, data: dict) -> "CollectionShape":
        def num(x: Any) -> float:
            return math.inf if x is None else float(x)

        return cls(str(data["name"]), np.asarray(data["transform"], dtype=np.float64)[:3, :3], num(data["score"]),
                   num(data["runner_up_score"]), math.nan if data["runner_up_angle"] is None
                   else float(data["runner_up_angle"]), num(data["margin"]), bool(data["ambiguous"]),
                   bool(data.get("template", False)),
                   "undecided" if data["ambiguous"] else str(data.get("decided_by", "template")),
                   math.nan if data.get("tilt") is None else float(data["tilt"]))


class CollectionAlignment(NamedTuple):
    """Result of :func:`align_collection`.

    - shapes : one :class:`CollectionShape` per input, in input order (the last round's results)
    - rotations : (S, 3, 3) float64, the same rotations stacked
    - templates : the template's name in each round (the first is the descriptor medoid)
    - changed : per round after the first, how many shapes turned by more than 10 degrees against the round before
    - converged : the re-estimated template was the one just used, or no shape turned by more than 10 degrees in the
      last round (another round would change nothing that matters)
    - seconds : (S,) float64, each shape's orientation time summed over the rounds (as measured when it was done,
      also in an earlier, resumed run)
    - floor : what :func:`floor_up` found (the up axis in the shared frame, the flat-contact share of every candidate
      direction, how many shapes were stood and by how much), or None when the up axis was given or standing off
    """

    shapes: list
    rotations: np.ndarray
    templates: list
    changed: list
    converged: bool
    seconds: np.ndarray
    floor: dict | None = None

    @property
    def ambiguous(self) -> np.ndarray:
        """(S,) bool: the flagged shapes."""
        return np.array([s.ambiguous for s in self.shapes], dtype=bool)

    def to_dict(self) -> dict:
        return {"templates": list(self.templates), "changed": list(self.changed), "converged": self.converged,
                "rounds": len(self.templates), "count": len(self.shapes),
                "seconds_per_shape": float(self.seconds.mean()),
                "ambiguous": int(self.ambiguous.sum()), "floor": self.floor,
                "shapes": [s.to_dict() for s in self.shapes]}


# --------------------------------------------------------------------------------------------------------------------
# the collection on disk


def find_shapes(folder: str | os.PathLike) -> list[tuple[str, Path]]:
    """The shapes of a collection folder: mesh or point files in it (named by their stem) and sub-folders holding
    exactly one such file (named by the sub-folder, as ``gso_shoes/<name>/model.obj``), sorted by name.

    Returns
    -------
    shapes : list of (name, path); DataError when there are none or two share a name.
    """
    from kpd.io import MESH_FORMATS, POINT_FORMATS

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    suffixes = set(MESH_FORMATS) | set(POINT_FORMATS)

    def shape_files(where: Path) -> list[Path]:
        return sorted(p for p in where.iterdir() if p.is_file() and p.suffix.lower() in suffixes
                      and not p.name.startswith("."))

    found: dict[str, Path] = {}
    for path in shape_files(folder):
        found.setdefault(path.stem, path)
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        files = shape_files(sub)
        if len(files) == 1:
            if sub.name in found:
                raise DataError(f"{folder}: two shapes are named {sub.name!r} ({found[sub.name]} and {files[0]})")
            found[sub.name] = files[0]
    if not found:
        raise DataError(f"no shapes (mesh or point files, or sub-folders with one each) in {folder}")
    return sorted(found.items())


def collection_points(shape: Any, n: int = 5000, *, seed: int = 0, outer: bool = True) -> np.ndarray:
    """(n, 3) float64 points a shape is aligned by: area-weighted surface samples of a mesh (its outer surface by
    default, :func:`kpd.geometry.sample_surface`), or at most ``n`` of a point set's points."""
    triangles = np.asarray(getattr(shape, "triangles", np.zeros((0, 3))))
    if hasattr(shape, "vertices") and len(triangles):
        return sample_surface(shape.vertices, triangles, n, seed=seed, outer=outer).points
    points = as_points(shape.points if hasattr(shape, "points") else shape, "shape", min_count=10)
    if len(points) > n:
        points = points[np.sort(as_rng(seed).choice(len(points), n, replace=False))]
    return points


# --------------------------------------------------------------------------------------------------------------------
# templates


def rms_unit(points: np.ndarray) -> np.ndarray:
    """(N, 3) ``points`` centred and scaled to unit root-mean-square radius."""
    centred = points - points.mean(axis=0)
    radius = math.sqrt(float((centred**2).sum(axis=1).mean()))
    if not radius > 0:
        raise InputError(f"a shape of {len(points)} points has zero extent")
    return centred / radius


def shape_descriptor(points: Any, *, pairs: int = 20000, bins: int = 32, seed: int = 0) -> np.ndarray:
    """A rotation-invariant summary of a shape at unit RMS radius: the histogram of distances between random point
    pairs (Osada et al.'s D2) followed by the square roots of the principal variances.

    Returns
    -------
    descriptor : (bins + 3,) float64
    """
    unit = rms_unit(as_points(points, min_count=10))
    rng = as_rng(seed)
    i, j = rng.integers(len(unit), size=(2, pairs))
    d = np.linalg.norm(unit[i] - unit[j], axis=1)  # (pairs,)
    hist = np.histogram(d, bins=bins, range=(0.0, 4.0))[0] / pairs
    extents = np.sqrt(np.maximum(np.linalg.eigvalsh(unit.T @ unit / len(unit)), 0.0))  # ascending
    return np.concatenate([hist, extents])


def descriptor_medoid(clouds: Sequence[np.ndarray], *, seed: int = 0) -> int:
    """Index of the shape whose :func:`shape_descriptor` has the least total L1 distance to the others'."""
    if len(clouds) == 0:
        raise InputError("no shapes to choose a template from")
    desc = np.stack([shape_descriptor(c, seed=seed) for c in clouds])  # (S, D)
    total = np.abs(desc[:, None, :] - desc[None, :, :]).sum(axis=(1, 2))  # (S,)
    return int(np.argmin(total))


def chamfer_medoid(clouds: Sequence[np.ndarray], rotations: np.ndarray, candidates: Sequence[int], *,
                   points: int = 512, others: int = 64, seed: int = 0) -> int:
    """Index (among ``candidates``) of the shape nearest, by mean symmetric chamfer distance at unit RMS radius in
    the shared frame, to a seeded sample of ``others`` of the candidates."""
    candidates = list(candidates)
    if not candidates:
        raise InputError("no shapes to choose a template from")
    rng = as_rng(seed)
    turned = {}
    for i in candidates:
        c = clouds[i]
        sub = c if len(c) <= points else c[rng.choice(len(c), points, replace=False)]
        turned[i] = rms_unit(sub @ rotations[i].T)
    trees = {i: cKDTree(p) for i, p in turned.items()}
    pool = candidates if len(candidates) <= others else list(rng.choice(candidates, others, replace=False))
    best, best_cost = candidates[0], math.inf
    for i in candidates:
        cost = 0.0
        for j in pool:
            if j != i:
                cost += float((trees[j].query(turned[i])[0] ** 2).mean() + (trees[i].query(turned[j])[0] ** 2).mean())
        if cost < best_cost:
            best, best_cost = i, cost
    return int(best)


# --------------------------------------------------------------------------------------------------------------------
# the floor: the shared frame's up axis and each shape stood on its support plane

FLOOR_NEAR = 0.05  # a point within this height (unit RMS radius) of the support plane is on the floor contact
FLOOR_CLEAR = 1.5  # the best direction must have this many times the flat-contact share of the next one


def _floor_samples(clouds: Sequence[np.ndarray], rotations: np.ndarray, indices: Sequence[int], points: int,
                   seed: int) -> dict[int, np.ndarray]:
    """Each shape's dense points (stray ones out), at unit RMS radius in the shared frame."""
    out = {}
    for i in indices:
        c = clouds[i]
        sub = c if len(c) <= points else c[np.random.default_rng([seed, i]).choice(len(c), points, replace=False)]
        out[i] = _dense_subset(rms_unit(sub @ rotations[i].T))
    return out


def _contact(points: np.ndarray, up: np.ndarray, snap: float) -> tuple[float, np.ndarray | None]:
    """The share of ``points`` within FLOOR_NEAR of their support plane with ``up`` up, and its normal (None when
    there is no stable support that way)."""
    found = support_plane(points, up, max_angle=snap)
    if not found.count or not found.stability > 0:
        return 0.0, None
    height = points @ found.normal
    return float(np.mean(height - height.min() < FLOOR_NEAR)), found.normal


def _sphere_directions(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit vectors (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    a = np.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)


def _contact_shares(points: np.ndarray, directions: np.ndarray, snap: float) -> np.ndarray:
    """(D,) for each candidate up direction: the share of ``points`` within FLOOR_NEAR of the support plane under
    them (the area-weighted mean plane of the hull faces within ``snap`` degrees of facing down; 0 without)."""
    faces = hull_faces(points)
    if faces is None:
        return np.zeros(len(directions))
    outward, area, _ = faces  # (F, 3), (F,)
    below = (outward @ -directions.T) >= math.cos(math.radians(snap))  # (F, D)
    normals = -(below * area[:, None]).T @ outward  # (D, 3)
    length = np.linalg.norm(normals, axis=1)
    found = length > 0
    normals[found] /= length[found, None]
    height = points @ normals.T  # (N, D)
    shares = np.mean(height - height.min(axis=0) < FLOOR_NEAR, axis=0)
    return np.where(found, shares, 0.0)


FLOOR_DIRECTIONS = 200  # candidate up directions (about 14 degrees apart, within the 25 degree snap of any axis)
FLOOR_APART = 45.0  # a rival floor lies more than this many degrees from the best


def floor_up(clouds: Sequence[np.ndarray], rotations: np.ndarray, decided: Sequence[int], *, snap: float = 25.0,
             points: int = 2000, seed: int = 0) -> tuple[np.ndarray | None, dict]:
    """The up axis of a collection's shared frame, from the floor its shapes stand on.

    Objects are scanned standing on something, and what they stand on is flat: a shoe's sole, a box's base, the
    plane through a chair's leg tips. For each of FLOOR_DIRECTIONS candidate up directions of the shared frame,
    every decided shape is stood on its support plane with that direction up (the hull faces within ``snap``
    degrees of facing down, as :func:`kpd.scan.support_plane`) and the share of its points within FLOOR_NEAR (unit
    RMS radius) of that plane is taken: large for a flat contact, small for a curved side. The direction with the
    highest median share is the floor when that median is FLOOR_CLEAR times the best one FLOOR_APART degrees or
    more away; the up axis is then the mean support normal of the decided shapes with that direction up.

    Returns
    -------
    up : (3,) unit vector in the shared frame, or None when no direction is a clear floor
    info : {"share": the best direction's median share, "rival_share": the best rival's, "up": ...}
    """
    decided = [int(i) for i in decided]
    info: dict = {"share": None, "rival_share": None, "up": None}
    if len(decided) < 2:
        info["note"] = "fewer than 2 decided shapes"
        return None, info
    work = _floor_samples(clouds, rotations, decided, points, seed)
    directions = _sphere_directions(FLOOR_DIRECTIONS)
    shares = np.median(np.stack([_contact_shares(work[i], directions, snap) for i in decided]), axis=0)  # (D,)
    best = int(np.argmax(shares))
    apart = directions @ directions[best] < math.cos(math.radians(FLOOR_APART))
    rival = float(shares[apart].max()) if apart.any() else 0.0
    info.update(share=float(shares[best]), rival_share=rival)
    if not shares[best] > 0 or shares[best] < FLOOR_CLEAR * rival:
        info["note"] = "no direction is a clear floor"
        return None, info
    up = directions[best]
    for _ in range(2):  # the mean support normal, then once more from it
        normals = [n for n in (_contact(work[i], up, snap)[1] for i in decided) if n is not None]
        if not normals:
            break
        mean = np.mean(normals, axis=0)
        up = mean / np.linalg.norm(mean)
    info["up"] = up.tolist()
    return up, info


def stand_collection(clouds: Sequence[np.ndarray], rotations: np.ndarray, indices: Sequence[int], up: Any, *,
                     snap: float = 25.0, points: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Stand shapes on their support planes in the shared frame.

    Each shape of ``indices`` (turned into the shared frame by ``rotations``) is found its support plane with
    ``up`` (3,) up (:func:`kpd.scan.support_plane`, hull faces within ``snap`` degrees, a stable support only) and
    turned by the smallest rotation taking that plane's normal to ``up``; its turn about ``up`` is kept.

    Returns
    -------
    rotations : (S, 3, 3) float64, the stood rotations (others unchanged)
    tilts : (S,) float64, degrees each shape was turned (nan: not stood)
    """
    up = parse_axis(up)
    out = np.array(rotations, dtype=np.float64, copy=True)
    tilts = np.full(len(out), math.nan)
    work = _floor_samples(clouds, out, indices, points, seed)
    for i, pts in work.items():
        normal = _contact(pts, up, snap)[1]
        if normal is None:
            continue
        turn = _rotation_between(normal, up)
        out[i] = turn @ out[i]
        tilts[i] = rotation_angle(turn)
    return out, tilts


# --------------------------------------------------------------------------------------------------------------------
# the alignment

_WORKER: dict = {}


def _worker_fit(template: np.ndarray, params: dict) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER["aligner"] = ScanAligner(**params).fit(template)


def _worker_orient(item: tuple[str, np.ndarray]) -> dict:
    import time

    name, points = item
    started = time.perf_counter()
    aligner = _WORKER["aligner"]
    o = aligner.orient(points)
    candidates: list[dict] = []  # distinct hypotheses, best first: what the neighbour vote chooses among
    for h in o.hypotheses:
        if len(candidates) == _CANDIDATES:
            break
        if all(rotation_angle(h.rotation, np.asarray(c["rotation"])) > aligner.distinct_angle for c in candidates):
            candidates.append({"rotation": h.rotation.tolist(), "score": float(h.score), "source": h.source})
    return {**CollectionShape(name, o.rotation, o.score, o.runner_up_score, o.runner_up_angle, o.margin,
                              o.ambiguous).to_dict(), "seconds": time.perf_counter() - started,
            "candidates": candidates}


_CANDIDATES = 4  # distinct hypotheses kept per shape for the neighbour vote


def _neighbour_vote(clouds: Sequence[np.ndarray], rotations: np.ndarray, results: list[dict],
                    descriptors: np.ndarray, *, neighbours: int, margin: float, points: int = 500,
                    seed: int = 0) -> list[dict]:
    """Settle flagged shapes by their decided look-alikes: each candidate rotation of a flagged shape is scored by
    its mean RMS chamfer distance (unit RMS radius, shared frame) to the ``neighbours`` decided shapes nearest by
    descriptor (a ballet flat is compared with other flats, not with the template sneaker); a candidate that beats
    the others by ``margin`` (relative, as the template's ambiguity margin) decides the shape."""
    decided = [i for i, r in enumerate(results) if not r["ambiguous"]]
    out = [dict(r) for r in results]
    if len(decided) < 2:
        return out

    def unit_sample(i: int, rotation: np.ndarray) -> np.ndarray:
        c = clouds[i]
        sub = c if len(c) <= points else c[np.random.default_rng([seed, i]).choice(len(c), points, replace=False)]
        return rms_unit(sub @ rotation.T)

    trees: dict[int, tuple[cKDTree, np.ndarray]] = {}
    for i, r in enumerate(results):
        candidates = r.get("candidates") or []
        if not r["ambiguous"] or len(candidates) < 2:
            continue
        order = np.argsort(np.abs(descriptors[decided] - descriptors[i]).sum(axis=1))[:neighbours]
        near = [decided[j] for j in order if decided[j] != i]
        costs = []
        for c in candidates:
            turned = unit_sample(i, np.asarray(c["rotation"]))
            total = 0.0
            for j in near:
                if j not in trees:
                    pts = unit_sample(j, rotations[j])
                    trees[j] = (cKDTree(pts), pts)
                tree, pts = trees[j]
                total += float((tree.query(turned)[0] ** 2).mean() + (cKDTree(turned).query(pts)[0] ** 2).mean())
            costs.append(math.sqrt(total / max(1, len(near))))
        ranked = np.argsort(costs)
        vote_margin = costs[ranked[1]] / costs[ranked[0]] - 1.0 if costs[ranked[0]] > 0 else math.inf
        out[i]["neighbour_margin"] = float(vote_margin)
        if vote_margin >= margin:
            best = candidates[int(ranked[0])]
            out[i].update(ambiguous=False, decided_by="neighbours",
                          transform=np.block([[np.asarray(best["rotation"]), np.zeros((3, 1))],
                                              [np.zeros((1, 3)), np.ones((1, 1))]]).tolist())
    return out


def _load_state(path: Path | None, names: list[str], settings: dict) -> dict:
    if path is None or not path.is_file():
        return {"version": STATE_VERSION, "names": names, "settings": settings, "rounds": []}
    try:
        state = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable alignment state ({exc}); delete it to start over") from exc
    if state.get("version") != STATE_VERSION or state.get("names") != names or state.get("settings") != settings:
        raise InputError(f"{path}: the alignment state is of other shapes or settings; delete it to start over")
    return state


def _save_state(path: Path | None, state: dict) -> None:
    if path is None:
        return
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(state))
    os.replace(tmp, path)


def align_collection(
    clouds: Sequence[Any],
    names: Sequence[str] | None = None,
    *,
    up: Any = None,
    rounds: int = 3,
    processes: int = 1,
    state: str | os.PathLike | None = None,
    progress: bool = False,
    seed: int = 0,
    neighbours: int = 8,
    stand: bool = True,
    **aligner_params: Any,
) -> CollectionAlignment:
    """Groupwise alignment of a collection (see the module docstring).

    Parameters
    ----------
    clouds : S >= 2 arrays (N_i, 3), the shapes' points (e.g. :func:`collection_points`), each in its own pose.
    names : S distinct names (default ``"0"``, ``"1"``, ...).
    up : the up axis shared by every shape, if known (``'y'``, ``'-z'``, three numbers): only turns about it are
        searched, and the shared frame keeps it.
    rounds : at most this many registrations of the whole collection (>= 1); stops earlier when the re-estimated
        template is the one just used.
    processes : worker processes orienting shapes (1 = in this process).
    state : a JSON file that keeps every result as it is found; a run given the same file (same shapes and
        settings) continues where the previous one stopped.
    seed : seeds the descriptor, the medoids and the aligner.
    neighbours : after each round, a flagged shape is settled by its ``neighbours`` nearest decided look-alikes
        (by descriptor) when one of its distinct candidate rotations fits them better than the others by the
        ambiguity margin (0 turns this off); such shapes are reported with ``decided_by: neighbours``.
    stand : without ``up``, after the rounds: find the shared frame's up axis from the floor the decided shapes
        stand on (:func:`floor_up`) and stand each decided shape on its own support plane (:func:`stand_collection`;
        the shapes' ``tilt``, the alignment's ``floor``). Not part of the resumable state: it is recomputed.
    aligner_params : further :class:`kpd.scan.ScanAligner` parameters (``ambiguity_margin``, ``n_points``, ...).

    Returns
    -------
    CollectionAlignment
    """
    clouds = [as_points(c, f"shape {i}", min_count=10) for i, c in enumerate(clouds)]
    if len(clouds) < 2:
        raise InputError(f"a collection needs at least 2 shapes; got {len(clouds)}")
    names = [str(i) for i in range(len(clouds))] if names is None else [str(n) for n in names]
    if len(names) != len(clouds) or len(set(names)) != len(names):
        raise InputError(f"names must be {len(clouds)} distinct strings; got {len(names)} ({len(set(names))} distinct)")
    if int(rounds) < 1 or int(processes) < 1:
        raise InputError(f"rounds and processes must be at least 1; got {rounds}, {processes}")
    if up is not None:
        parse_axis(up)
    params = {"seed": seed, **aligner_params}
    if up is not None:
        params.update(up=up, reference_up=up)
    ScanAligner(**params)._check_params()
    state_path = None if state is None else Path(state)
    settings = {"up": None if up is None else str(up), "seed": seed,
                "aligner": {k: v for k, v in sorted(aligner_params.items())}}
    saved = _load_state(state_path, names, settings)
    index = {n: i for i, n in enumerate(names)}
    rotations = np.repeat(np.eye(3)[None], len(clouds), axis=0)
    templates: list[str] = []
    changed: list[int] = []
    results: dict[str, dict] = {}
    seconds = np.zeros(len(clouds))
    converged = False
    descriptors = np.stack([shape_descriptor(c, seed=seed) for c in clouds])  # (S, D)
    template = int(np.argmin(np.abs(descriptors[:, None, :] - descriptors[None, :, :]).sum(axis=(1, 2))))
    margin = float(params.get("ambiguity_margin", DEFAULT_AMBIGUITY_MARGIN))
    for k in range(int(rounds)):
        name = names[template]
        if k < len(saved["rounds"]):
            record = saved["rounds"][k]
            if record["template"] != name:
                raise InputError(f"{state_path}: round {k + 1} used template {record['template']!r}, this run chose "
                                 f"{name!r}; delete the state to start over")
        else:
            record = {"template": name, "results": {}}
            saved["rounds"].append(record)
            _save_state(state_path, saved)
        templates.append(name)
        reference = clouds[template] @ rotations[template].T  # in the shared frame
        todo = [(n, clouds[index[n]]) for n in names if n not in record["results"]]
        if todo:
            log.info("round %d: orienting %d of %d shapes to template %s", k + 1, len(todo), len(names), name)
            from tqdm import tqdm

            bar = tqdm(total=len(names), initial=len(names) - len(todo), desc=f"aligning, round {k + 1}",
                       unit="shape", disable=not progress)
            try:
                if processes > 1 and len(todo) > 1:
                    with ProcessPoolExecutor(max_workers=int(processes), mp_context=get_context("spawn"),
                                             initializer=_worker_fit, initargs=(reference, params)) as pool:
                        for result in pool.map(_worker_orient, todo, chunksize=1):
                            record["results"][result["name"]] = result
                            _save_state(state_path, saved)
                            bar.update()
                else:
                    _worker_fit(reference, params)
                    for item in todo:
                        result = _worker_orient(item)
                        record["results"][result["name"]] = result
                        _save_state(state_path, saved)
                        bar.update()
            finally:
                bar.close()
                _WORKER.clear()
        previous = rotations.copy()
        results = record["results"]
        for n in names:
            rotations[index[n]] = np.asarray(results[n]["transform"])[:3, :3]
            seconds[index[n]] += float(results[n].get("seconds", math.nan))
        if neighbours:  # the flagged shapes settled by their decided look-alikes (recomputed from the state)
            voted = _neighbour_vote(clouds, rotations, [results[n] for n in names], descriptors,
                                    neighbours=neighbours, margin=margin, seed=seed)
            results = {n: v for n, v in zip(names, voted)}
            for n in names:
                rotations[index[n]] = np.asarray(results[n]["transform"])[:3, :3]
        if k > 0:
            changed.append(int(sum(rotation_angle(rotations[i], previous[i]) > 10.0 for i in range(len(names)))))
        if k > 0 and changed[-1] == 0:  # no shape turned: another template would change nothing that matters
            converged = True
            break
        decided = [i for i, n in enumerate(names) if not results[n]["ambiguous"]] or list(range(len(names)))
        following = chamfer_medoid(clouds, rotations, decided, seed=seed)
        if following == template:
            converged = True
            break
        template = following
    tilts = np.full(len(names), math.nan)
    floor = None
    if stand and up is None:
        decided = [i for i, n in enumerate(names) if not results[n]["ambiguous"]]
        floor_axis, floor = floor_up(clouds, rotations, decided, seed=seed)
        if floor_axis is not None:
            rotations, tilts = stand_collection(clouds, rotations, decided, floor_axis, seed=seed)
            stood = tilts[np.isfinite(tilts)]
            floor.update(stood=int(len(stood)), tilt_median_deg=float(np.median(stood)) if len(stood) else None,
                         tilt_max_deg=float(stood.max()) if len(stood) else None)
            log.info("floor: up %s in the shared frame, %d shapes stood (median tilt %.1f deg)",
                     np.round(floor_axis, 3).tolist(), len(stood), floor["tilt_median_deg"] or 0.0)
    shapes = []
    for i, n in enumerate(names):
        transform = np.eye(4)
        transform[:3, :3] = rotations[i]
        shapes.append(CollectionShape.from_dict({**results[n], "template": n == templates[-1],
                                                 "transform": transform.tolist(),
                                                 "tilt": None if not np.isfinite(tilts[i]) else float(tilts[i])}))
    return CollectionAlignment(shapes, rotations, templates, changed, converged, seconds, floor)


def pairwise_rotation_errors(estimated: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Angles (degrees) of ``(E_i T_i)(E_j T_j)^T`` over pairs i < j: 0 when shapes i and j, turned by the known
    rotations ``truth`` (S, 3, 3) and back by the estimated ``estimated`` (S, 3, 3), end up in one frame.

    Parameters
    ----------
    mask : (S,) bool, the shapes to pair (default all).

    Returns
    -------
    errors : (S', S') float64, symmetric with a zero diagonal, over the masked shapes.
    """
    estimated, truth = np.asarray(estimated, float), np.asarray(truth, float)
    if estimated.shape != truth.shape or estimated.ndim != 3 or estimated.shape[1:] != (3, 3):
        raise InputError(f"estimated and truth must both be (S, 3, 3); got {estimated.shape} and {truth.shape}")
    keep = np.ones(len(truth), bool) if mask is None else np.asarray(mask, bool)
    net = np.einsum("sij,sjk->sik", estimated[keep], truth[keep])  # (S', 3, 3)
    relative = np.einsum("aij,bkj->abik", net, net)  # (S', S', 3, 3): net_a @ net_b.T
    cos = (np.trace(relative, axis1=2, axis2=3) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
