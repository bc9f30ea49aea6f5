"""Φ and Γ of a trained :class:`kpd.train.nets.KeypointDeformer` -> two ONNX graphs (names in kpd.onnx_contract).

The graphs are written with the torch.export-based exporter (``dynamo=True``) and named dynamic axes for the batch
and the point count, then stamped with the contract's metadata entries and checked with ``onnx.checker``.
:func:`parity` runs the graphs through onnxruntime next to torch on the same inputs.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import tempfile
import warnings
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from kpd import onnx_contract as contract
from kpd.errors import InputError
from kpd.train.nets import KeypointDeformer

__all__ = ["KeypointsGraph", "InfluenceGraph", "Graphs", "Parity", "export_graphs", "parity", "torch_outputs"]

log = logging.getLogger(__name__)


class KeypointsGraph(nn.Module):
    """points (B, N, 3) -> keypoints (B, K, 3): Φ with the clamp to [-1, 1] (when the model was trained with it)."""

    def __init__(self, model: KeypointDeformer) -> None:
        super().__init__()
        self.model = model

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.model.keypoints(points)


class InfluenceGraph(nn.Module):
    """points (B, N, 3) -> influence (B, K, C): Γ, the instance offset W_I (W_C lives in the manifest)."""

    def __init__(self, model: KeypointDeformer) -> None:
        super().__init__()
        self.model = model

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.model.influence_offset(points)


class Graphs(NamedTuple):
    """Serialised ONNX models."""

    keypoints: bytes
    influence: bytes


def export_graphs(model: KeypointDeformer, *, category: str = "") -> Graphs:
    """Export Φ and Γ to ONNX bytes with dynamic batch and point axes.

    Parameters
    ----------
    model : a KeypointDeformer with a learned keypoint predictor (put in eval mode here).
    category : recorded in the graphs' metadata.
    """
    if model.keypoint_predictor is None:
        raise InputError("this model uses farthest-point keypoints (the FPS baseline); only a learned keypoint "
                         "predictor can be exported")
    model = model.eval().float().cpu()
    meta = {
        contract.META_FORMAT: contract.FORMAT_NAME,
        contract.META_FORMAT_VERSION: str(contract.FORMAT_VERSION),
        contract.META_KEYPOINTS: str(model.config.keypoints),
        contract.META_CAGE_VERTICES: str(model.config.cage_vertices),
        contract.META_CATEGORY: category,
    }
    out = []
    for spec, module in ((contract.KEYPOINTS_GRAPH, KeypointsGraph(model)),
                         (contract.INFLUENCE_GRAPH, InfluenceGraph(model))):
        out.append(_export_one(module.eval(), spec, {**meta, contract.META_GRAPH: spec.key}))
    return Graphs(*out)


def _export_one(module: nn.Module, spec: contract.GraphSpec, meta: dict[str, str]) -> bytes:
    import onnx

    example = torch.zeros(2, 64, 3).uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
    dynamic = {contract.INPUT_NAME: {0: torch.export.Dim(contract.BATCH_AXIS),
                                     1: torch.export.Dim(contract.POINTS_AXIS)}}
    with tempfile.TemporaryDirectory(prefix="kpd-onnx-") as tmp:
        path = os.path.join(tmp, spec.file)
        # the exporter prints progress lines and warnings of its own; keep them out of the user's terminal
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), \
                _quiet("torch.onnx", "onnx_ir", "onnxscript"):
            warnings.simplefilter("ignore")
            torch.onnx.export(
                module, (example,), path, input_names=[contract.INPUT_NAME], output_names=[spec.output],
                dynamo=True, dynamic_shapes=dynamic, opset_version=contract.OPSET, external_data=False,
                verbose=False,
            )
        graph = onnx.load(path)
    _rename_axes(graph, spec)
    del graph.metadata_props[:]
    for key, value in sorted(meta.items()):
        entry = graph.metadata_props.add()
        entry.key, entry.value = key, value
    graph.producer_name = "kpd.export"
    onnx.checker.check_model(graph, full_check=True)
    return graph.SerializeToString()


@contextlib.contextmanager
def _quiet(*names: str):
    """Raise loggers' levels to ERROR for the duration (the exporter and its optimiser log every pass)."""
    loggers = [logging.getLogger(name) for name in names]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def _rename_axes(graph, spec: contract.GraphSpec) -> None:
    """Make sure the dynamic axes carry the contract's names (the exporter takes them from the Dim names)."""
    value = graph.graph.input[0]
    dims = value.type.tensor_type.shape.dim
    for dim, name in zip(dims, (contract.BATCH_AXIS, contract.POINTS_AXIS)):
        dim.dim_param = name
    out_dims = graph.graph.output[0].type.tensor_type.shape.dim
    out_dims[0].dim_param = contract.BATCH_AXIS


@torch.no_grad()
def torch_outputs(model: KeypointDeformer, points: np.ndarray, batch: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Φ (clamped) and Γ in torch: points (S, N, 3) float32 -> keypoints (S, K, 3), influence (S, K, C) float32."""
    model = model.eval()
    keypoints, influence = [], []
    for start in range(0, len(points), batch):
        x = torch.from_numpy(np.ascontiguousarray(points[start:start + batch], dtype=np.float32))
        keypoints.append(model.keypoints(x).numpy())
        influence.append(model.influence_offset(x).numpy())
    return np.concatenate(keypoints), np.concatenate(influence)


class Parity(NamedTuple):
    """Largest absolute difference between onnxruntime and torch over the checked shapes."""

    keypoints: float
    influence: float
    shapes: int


def parity(model: KeypointDeformer, graphs: Graphs, points: np.ndarray) -> Parity:
    """Run both graphs in onnxruntime and the model in torch on ``points`` (S, N, 3) float32; max abs differences.

    Batches of one and of several shapes are both run, so the dynamic batch axis is exercised.
    """
    import onnxruntime as ort

    points = np.ascontiguousarray(points, dtype=np.float32)
    want_k, want_w = torch_outputs(model, points)
    options = ort.SessionOptions()
    options.log_severity_level = 3
    worst = []
    for data, want in ((graphs.keypoints, want_k), (graphs.influence, want_w)):
        session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
        name = session.get_inputs()[0].name
        together = session.run(None, {name: points})[0]
        one = np.concatenate([session.run(None, {name: points[i:i + 1]})[0] for i in range(min(len(points), 2))])
        worst.append(max(float(np.abs(together - want).max()), float(np.abs(one - want[: len(one)]).max())))
    return Parity(worst[0], worst[1], len(points))
