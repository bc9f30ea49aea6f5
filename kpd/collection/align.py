"""The groupwise alignment: every shape oriented to the template in rounds (in parallel, resumable from a state file),
ambiguous ones settled by a vote of their decided look-alikes."""

from __future__ import annotations

import json
import logging
import math
import os
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy.spatial import cKDTree

from kpd.collection.floor import floor_up, stand_collection
from kpd.collection.results import CollectionAlignment, CollectionShape
from kpd.collection.templates import chamfer_medoid, rms_unit, shape_descriptor
from kpd.errors import InputError
from kpd.geometry import as_points
from kpd.scan import (
    DEFAULT_AMBIGUITY_MARGIN,
    ScanAligner,
    parse_axis,
    rotation_angle,
)

__all__ = ["align_collection", "pairwise_rotation_errors"]

log = logging.getLogger("kpd.collection")


STATE_VERSION = 1


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
