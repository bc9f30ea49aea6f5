"""Write a model bundle from a trained network, validate it, and only then put it in place.

Steps: export Φ and Γ to ONNX (:mod:`kpd.export.onnx`); run Φ over the training shapes to fit the category prior
(:class:`kpd.prior.KeypointPrior`) and pick a representative training shape as the template cloud; write the bundle
to a temporary sibling of the output; open it with the torch-free runtime (:class:`kpd.runtime.Model`, which checks
format, hashes and shapes) and compare its outputs with torch on real shapes; rename it onto the output only when the
largest difference is within ``tolerance``. A bundle that fails is removed and the error names the difference.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import numpy as np
import torch

from kpd.bundle import build_manifest, write_bundle
from kpd.cage import Cage
from kpd.errors import BundleError, DataError, InputError
from kpd.io import Outputs
from kpd.export.onnx import Parity, export_graphs, parity, torch_outputs
from kpd.prior import KeypointPrior
from kpd.train.nets import KeypointDeformer, ModelConfig

__all__ = ["ExportResult", "TrainingShapes", "export_model", "export_checkpoint", "export_authors",
           "load_training_shapes", "model_from_checkpoint", "PARITY_TOLERANCE"]

log = logging.getLogger(__name__)

PARITY_TOLERANCE = 1e-5
PARITY_SHAPES = 8


class TrainingShapes(NamedTuple):
    """Cached samples of a category's training shapes, in the model frame.

    names : one per shape.
    points : (S, R, N, 3) float32, R independent samples of N surface points per shape.
    source : where they came from (for the manifest).
    """

    names: list[str]
    points: np.ndarray
    source: dict


class ExportResult(NamedTuple):
    """What :func:`export_model` wrote: the bundle path, the measured parity, the manifest."""

    path: Path
    parity: Parity
    manifest: dict


def export_model(
    model: KeypointDeformer,
    out: str | os.PathLike,
    *,
    category: str,
    point_count: int,
    shapes: TrainingShapes | None = None,
    parity_points: np.ndarray | None = None,
    fit_prior: bool = True,
    n_components: int = 8,
    cage_fit: Mapping | None = None,
    up: str | None = None,
    training: Mapping | None = None,
    force: bool = False,
    tolerance: float = PARITY_TOLERANCE,
    rig_cage_distance: float | None = None,
) -> ExportResult:
    """Export a network into a validated bundle (folder, or zip when ``out`` ends in ``.zip``).

    Parameters
    ----------
    model : the trained network (learned keypoints).
    out : bundle path.
    category : the category name recorded in the bundle.
    point_count : N the model was trained with (the runtime samples this many points).
    shapes : training shapes: the prior is fitted on Φ's keypoints of every shape (averaged over its samples), the
        shape nearest the mean keypoints becomes the template cloud, and the first shapes are the parity check.
        Without shapes the bundle has no prior and no template.
    parity_points : (S, N, 3) float32 model-frame clouds for the parity check when ``shapes`` is None.
    fit_prior : fit the prior when shapes are given.
    n_components : prior components (8 in the paper).
    cage_fit : the cage-fitting settings used in training (``distance``, ``iterations``, ``step``).
    up : the training frame's up axis, if known ("+z" for ModelNet).
    training : the training record (data, command, seed, iterations, metrics).
    force : replace an existing ``out``.
    tolerance : largest accepted ``|onnxruntime - torch|`` over keypoints and influence.
    rig_cage_distance : the stop distance of the cage fitted for each rig at run time, if not the training one
        (a tighter cage keeps edits more local; measured in benchmarks/bench_edits.py).
    """
    out = Path(out)
    if out.exists() and not force:
        raise InputError(f"{out} exists; pass --force to replace it")
    if not out.parent.is_dir():
        raise InputError(f"output folder {out.parent} does not exist")
    model = model.eval().float().cpu()
    cfg = model.config
    prior = template = template_source = frame_check = None
    if shapes is not None:
        checks = shapes.points[:PARITY_SHAPES, 0]
        mean_keypoints = _shape_keypoints(model, shapes.points)  # (S, K, 3)
        if fit_prior:
            m = min(n_components, len(mean_keypoints) - 1, 3 * cfg.keypoints)
            if m < n_components:
                log.warning("only %d training shapes: the prior keeps %d components instead of %d",
                            len(mean_keypoints), m, n_components)
            # the mirror images of the training shapes (about x, the left/right axis of ModelNet and ShapeNet)
            # make the prior mirror-symmetric: moving one keypoint moves its mirror partner (kpd.prior)
            flip = np.array([-1.0, 1.0, 1.0])
            mirrored = _shape_keypoints(model, shapes.points * flip.astype(shapes.points.dtype)) * flip
            try:
                prior = KeypointPrior(n_components=m).fit(mean_keypoints, mirrored)
            except InputError as exc:
                log.warning("prior without a mirror: %s", exc)
                prior = KeypointPrior(n_components=m).fit(mean_keypoints)
        centre = prior.mean_ if prior is not None else mean_keypoints.mean(axis=0)
        pick = int(np.argmin(((mean_keypoints - centre) ** 2).sum(axis=(1, 2))))
        template = shapes.points[pick].reshape(-1, 3)
        template_source = shapes.names[pick]
        frame_check = _calibrate_frame_check(model, template, up, shapes.points, pick)
    elif parity_points is not None:
        checks = np.asarray(parity_points, dtype=np.float32)
    else:
        raise InputError("export needs shapes (training data) or parity_points for the parity check")
    if checks.ndim != 3 or checks.shape[2] != 3 or len(checks) < 1:
        raise InputError(f"parity points must have shape (S, N, 3); got {checks.shape}")

    graphs = export_graphs(model, category=category)
    measured = parity(model, graphs, checks)
    log.info("parity onnxruntime vs torch on %d shapes: keypoints %.2e, influence %.2e", measured.shapes,
             measured.keypoints, measured.influence)
    _check_parity(measured, tolerance, "the exported graphs")

    record = dict(training or {})
    record["export"] = {
        "parity_max_abs": {"keypoints": measured.keypoints, "influence": measured.influence},
        "parity_shapes": measured.shapes,
        "parity_source": "training shapes" if shapes is not None else "given clouds",
        "tolerance": tolerance,
        "torch": torch.__version__,
    }
    if shapes is not None:
        record["export"]["prior_source"] = shapes.source
    template_vertices = model.template_vertices[0].T.double().numpy()  # (C, 3)
    template_faces = model.template_faces[0].numpy()
    manifest, files = build_manifest(
        category=category, keypoints_onnx=graphs.keypoints, influence_onnx=graphs.influence,
        cage=Cage(template_vertices, template_faces), shared_influence=model.influence_param.detach().double().numpy(),
        m=cfg.m, point_count=point_count, cage_fit=cage_fit, prior=prior, template_points=template,
        template_source=template_source, up=up, training=_json_safe(record), clamp=cfg.clamp,
        frame_check=frame_check,
        rig_fit=None if rig_cage_distance is None else {"distance": float(rig_cage_distance)},
    )
    with Outputs(force=force) as outputs:  # validated where it is written, placed only when it passes
        target = outputs.file(out, None) if out.suffix == ".zip" else outputs.folder(out, None)
        staged = write_bundle(outputs.stage(target), files)
        _validate(staged, model, checks, tolerance)
    return ExportResult(out, measured, manifest)


def _validate(path: Path, model: KeypointDeformer, checks: np.ndarray, tolerance: float) -> None:
    """Open the written bundle with the torch-free runtime and compare its outputs with torch."""
    from kpd.runtime import Model

    runtime = Model.load(path)
    want_k, want_w = torch_outputs(model, checks)
    got_k, got_w = runtime.run(checks)
    measured = Parity(float(np.abs(got_k - want_k).max()), float(np.abs(got_w - want_w).max()), len(checks))
    _check_parity(measured, tolerance, f"the written bundle {path.name}")


def _check_parity(measured: Parity, tolerance: float, what: str) -> None:
    worst = max(measured.keypoints, measured.influence)
    if not worst <= tolerance:
        raise BundleError(f"{what} differ from torch by {worst:.3g} (keypoints {measured.keypoints:.3g}, influence "
                          f"{measured.influence:.3g}) on {measured.shapes} shapes; tolerance {tolerance:g}; "
                          "nothing was written")


FRAME_CHECK_SHAPES = 100  # training shapes the frame and category check is calibrated on


def _calibrate_frame_check(model: KeypointDeformer, template: np.ndarray, up: str | None, points: np.ndarray,
                           template_index: int) -> dict:
    """kpd.frame's limits from up to FRAME_CHECK_SHAPES training shapes other than the template's (one sample each)."""
    from kpd.frame import calibrate

    others = np.delete(np.arange(len(points)), template_index)
    chosen = others[:: max(1, len(others) // FRAME_CHECK_SHAPES)][:FRAME_CHECK_SHAPES]

    def keypoints_of(p: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model.keypoints(torch.from_numpy(np.asarray(p, dtype=np.float32)[None])).numpy()[0]

    entry = calibrate(template, up, points[chosen, 0].astype(np.float64), keypoints_of)
    log.info("frame check calibrated on %d training shapes: score limit %.4f, keypoint limit %.4f", entry["shapes"],
             entry["score_limit"], entry["keypoint_limit"])
    return entry


@torch.no_grad()
def _shape_keypoints(model: KeypointDeformer, points: np.ndarray) -> np.ndarray:
    """(S, K, 3) float64: Φ's keypoints of each shape, averaged over its R samples."""
    s, r, n, _ = points.shape
    flat = points.reshape(s * r, n, 3)
    out = []
    for start in range(0, len(flat), 64):
        x = torch.from_numpy(np.ascontiguousarray(flat[start:start + 64], dtype=np.float32))
        out.append(model.keypoints(x).numpy())
    return np.concatenate(out).reshape(s, r, -1, 3).astype(np.float64).mean(axis=1)


def _json_safe(value: Any) -> Any:
    """Plain JSON types for the manifest: numpy values become numbers or lists, NaN and inf become None, anything
    else unknown becomes its string."""
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


# --- from a kpd training run ---------------------------------------------------------------------------------------

def model_from_checkpoint(checkpoint: Mapping) -> KeypointDeformer:
    """The network of a kpd checkpoint (``kpd.train.trainer.load_checkpoint``)."""
    try:
        config = ModelConfig.from_dict(checkpoint["model_config"])
        states = checkpoint["states"]
        model = KeypointDeformer(config, states["template_vertices"][0].T, states["template_faces"][0])
        model.load_state_dict(states)
    except (KeyError, TypeError, RuntimeError) as exc:
        raise InputError(f"the checkpoint's weights do not fit its model config: {exc}") from exc
    return model.eval()


def load_training_shapes(root: str | os.PathLike, category: str, settings_dict: Mapping, *,
                         cache_dir: str | os.PathLike | None = None, seed: int = 0, split_file: str | None = None,
                         val_fraction: float = 0.1, progress: bool = True) -> TrainingShapes:
    """The cached training samples of a category (sampled into the cache first if needed)."""
    from kpd.data import SampleSettings, prepare

    settings = SampleSettings.from_dict(dict(settings_dict))
    prepared = prepare(root, category, settings=settings, cache_dir=cache_dir, seed=seed, splits=("train",),
                       split_file=split_file, val_fraction=val_fraction, progress=progress)
    samples = prepared.samples["train"]
    source = {"root": str(prepared.category.root), "category": prepared.category.category, "split": "train",
              "shapes": len(samples), "samples_per_shape": int(samples.points.shape[1]),
              "points": int(samples.points.shape[2])}
    return TrainingShapes(list(samples.names), samples.points, source)


def export_checkpoint(
    checkpoint: str | os.PathLike,
    out: str | os.PathLike,
    *,
    category: str | None = None,
    data: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    fit_prior: bool = True,
    up: str | None = None,
    force: bool = False,
    progress: bool = True,
    rig_cage_distance: float | None = None,
) -> ExportResult:
    """Export a kpd training run (its folder or its ``checkpoint.pt``) into a bundle.

    The training data (for the prior, the template cloud and the parity check) is the run's own, read from its
    ``record.json``, unless ``data`` names another folder.
    """
    from kpd.train.trainer import CHECKPOINT_NAME, load_checkpoint

    path = Path(checkpoint)
    ckpt = load_checkpoint(path)
    run_dir = path if path.is_dir() else path.parent
    record: dict = {}
    if (run_dir / "record.json").is_file():
        try:
            record = json.loads((run_dir / "record.json").read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"{run_dir / 'record.json'}: unreadable training record ({exc})") from exc
    else:
        log.warning("%s has no record.json; the bundle's training record holds only the checkpoint's settings",
                    run_dir)
    model = model_from_checkpoint(ckpt)
    recorded = record.get("data") or {}
    category = category or recorded.get("category")
    if not category:
        raise InputError("the category is not in the run's record; pass --category")
    root = data if data is not None else recorded.get("root")
    if root is None:
        raise InputError("the training data folder is not in the run's record; pass --data")
    settings = ckpt["sample_settings"]
    discover = recorded.get("discover") or {}
    if data is not None:
        split_file, val_fraction = None, 0.1
    elif discover:
        split_file, val_fraction = discover.get("split_file"), float(discover.get("val_fraction", 0.1))
    else:
        split_file, val_fraction = _recorded_split(recorded.get("split_source", ""))
    seed = int(discover.get("seed", record.get("seed", 0)))
    try:
        # the category as the run discovered it (None for a flat folder, whose name is the category)
        found_as = discover["category"] if data is None and "category" in discover else category
        shapes = load_training_shapes(root, found_as, settings, seed=seed,
                                      cache_dir=cache_dir or recorded.get("cache"), split_file=split_file,
                                      val_fraction=val_fraction, progress=progress)
    except DataError as exc:
        raise InputError(f"cannot read the training shapes for the prior ({exc}); pass --data") from exc
    usable = (recorded.get("usable") or {}).get("train")
    if usable is not None and usable != len(shapes.names):
        log.warning("the run trained on %d shapes; the prior is fitted on %d (the split could not be reproduced "
                    "exactly)", usable, len(shapes.names))
    training = {key: value for key, value in record.items() if key != "skipped"}
    training["skipped_shapes"] = len(record.get("skipped", []))
    training["checkpoint"] = {"file": str(path if path.is_file() else path / CHECKPOINT_NAME),
                              "iteration": int(ckpt["iteration"]), "model_config": ckpt["model_config"],
                              "train_config": ckpt.get("train_config"), "sample_settings": settings}
    cage_fit = {"distance": settings.get("cage_distance", 0.4), "iterations": settings.get("cage_iterations", 100),
                "step": settings.get("cage_step", 0.01)}
    if up is None and recorded.get("layout") == "modelnet":
        up = "+z"
    return export_model(model, out, category=category, point_count=int(settings.get("points", 1024)), shapes=shapes,
                        fit_prior=fit_prior, cage_fit=cage_fit, up=up, training=training, force=force,
                        rig_cage_distance=rig_cage_distance)


def _recorded_split(source: str) -> tuple[str | None, float]:
    """The split file and validation share of a run, from its record's ``split_source`` text
    (``"<file or folders>[; val carved from train (<fraction>, seed <seed>)]"``)."""
    import re

    first = source.split(";")[0].strip()
    split_file = first if first and Path(first).is_file() else None
    match = re.search(r"val carved from train \(([0-9.eE+-]+)", source)
    return split_file, float(match.group(1)) if match else 0.1


# --- from the authors' code -----------------------------------------------------------------------------------------

def export_authors(
    checkpoint: str | os.PathLike,
    out: str | os.PathLike,
    *,
    category: str,
    data: str | os.PathLike | None = None,
    point_count: int = 1024,
    fit_prior: bool = True,
    up: str | None = None,
    force: bool = False,
    progress: bool = True,
) -> ExportResult:
    """Export a checkpoint of the authors' trainer (docs/method.md §16) into a bundle.

    With ``data`` (a folder :func:`kpd.data.discover` understands) the prior and template cloud are fitted on its
    training split, in this project's normalisation. Without it the bundle has neither, and the parity check runs on
    seeded synthetic clouds (points on the surfaces of random boxes and spheres in the [-1, 1] frame).
    """
    from kpd.export.authors import load_authors_checkpoint

    if not category:
        raise InputError("--category is required with --from-authors (their checkpoints do not record it)")
    imported = load_authors_checkpoint(checkpoint)
    model = imported.model
    training = {
        "source": "authors' trainer (tomasjakab/keypoint_deformer)",
        "checkpoint": {"file": str(checkpoint), "ignored_keys": len(imported.ignored),
                       "model_config": model.config.to_dict()},
        "data": None if data is None else str(data),
        "note": "imported; the training data, command, seed and metrics are not stored in the authors' checkpoints",
    }
    cage_fit = {"distance": 0.4, "iterations": 100, "step": 0.01}
    shapes = None
    parity_points = None
    if data is not None:
        try:
            shapes = load_training_shapes(data, category, {"points": point_count}, progress=progress)
        except DataError as exc:
            raise InputError(f"cannot read --data for the prior: {exc}") from exc
    else:
        parity_points = synthetic_clouds(PARITY_SHAPES, point_count, seed=0)
        log.warning("no --data: the bundle has no prior and no template cloud")
    return export_model(model, out, category=category, point_count=point_count, shapes=shapes,
                        parity_points=parity_points, fit_prior=fit_prior, cage_fit=cage_fit, up=up,
                        training=training, force=force)


def synthetic_clouds(count: int, n: int, seed: int = 0) -> np.ndarray:
    """(count, n, 3) float32 seeded clouds in the [-1, 1] frame: surfaces of random boxes and ellipsoids."""
    rng = np.random.default_rng(seed)
    clouds = np.empty((count, n, 3), dtype=np.float32)
    for i in range(count):
        half = rng.uniform(0.3, 1.0, 3)
        half /= half.max()
        direction = rng.standard_normal((n, 3))
        if i % 2:
            surface = direction / np.linalg.norm(direction, axis=1, keepdims=True)
        else:
            surface = direction / np.abs(direction).max(axis=1, keepdims=True)
        clouds[i] = surface * half
    return clouds
