"""Import a checkpoint written by the authors' trainer (``net_final.pth``, docs/method.md §16).

Their checkpoint is ``{"states": state_dict}`` with the module names of their ``CageSkinning`` network. This project's
:class:`kpd.train.nets.KeypointDeformer` uses the same names and weight shapes (1x1 convolutions keep their
``(out, in, 1)`` weights; the keypoint head's flat 3K output is [all x, all y, all z] in both), so importing is:
take the keys of §16, check every shape against K and C read from ``influence_param``, load. Optimiser states and
other modules in the file are ignored. Only the input layout differs -- theirs is channel-first ``(B, 3, N)``, ours
``(B, N, 3)`` -- which is the same function of the same weights.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Mapping, NamedTuple

import torch

from kpd.errors import InputError
from kpd.train.nets import KeypointDeformer, ModelConfig

__all__ = ["AuthorsModel", "expected_shapes", "load_authors_checkpoint", "model_from_authors_state"]

log = logging.getLogger(__name__)


class AuthorsModel(NamedTuple):
    """An imported model and what was learned about the file.

    model : the network with the authors' weights.
    ignored : keys of the file that are not part of the model (optimiser states, other modules).
    """

    model: KeypointDeformer
    ignored: list[str]


def expected_shapes(k: int, c: int, f: int) -> dict[str, tuple[int, ...]]:
    """Every key of docs/method.md §16 and its shape for K keypoints, a C-vertex cage with F faces."""
    kc = k * c
    shapes: dict[str, tuple[int, ...]] = {
        "influence_param": (k, c),
        "template_vertices": (1, 3, c),
        "template_faces": (1, f, 3),
    }
    for net, last in (("keypoint_predictor", 256), ("influence_predictor", kc)):
        for i, (n_in, n_out) in enumerate(((3, 64), (64, 128), (128, last)), 1):
            shapes[f"{net}.0.0.conv{i}.conv.weight"] = (n_out, n_in, 1)
            shapes[f"{net}.0.0.conv{i}.conv.bias"] = (n_out,)
    linears = {
        "keypoint_predictor.0.1": (256, 256),
        "keypoint_predictor.1.layers.0": (512, 256),
        "keypoint_predictor.1.layers.1": (256, 512),
        "keypoint_predictor.1.layers.2": (3 * k, 256),
        "influence_predictor.0.1": (kc, kc),
        "influence_predictor.1.0": (kc, kc),
        "influence_predictor.1.1": (kc, kc),
    }
    for prefix, (n_out, n_in) in linears.items():
        shapes[f"{prefix}.linear.weight"] = (n_out, n_in)
        shapes[f"{prefix}.linear.bias"] = (n_out,)
    return shapes


def load_authors_checkpoint(path: str | os.PathLike) -> AuthorsModel:
    """Read an authors' checkpoint (``torch.load(weights_only=True)``, no pickle of code) into a model.

    Raises
    ------
    InputError naming the file, and any missing or mis-shaped key with its expected shape.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such checkpoint file")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several kinds (pickle, zip, runtime) for damaged or foreign files
        from kpd.io.integrity import checkpoint_failure

        raise InputError(f"{path}: cannot load the authors' checkpoint: {checkpoint_failure(path, exc)}") from exc
    if not isinstance(data, Mapping):
        raise InputError(f"{path}: expected a dict {{'states': state_dict}}; got {type(data).__name__}")
    if "states" in data:
        states = data["states"]
    elif "influence_param" in data:
        states = data  # a bare state dict
    else:
        raise InputError(f"{path}: expected the authors' layout {{'states': state_dict}}; top-level keys: "
                         f"{sorted(map(str, data))[:8]}")
    if not isinstance(states, Mapping):
        raise InputError(f"{path}: 'states' must be a state dict; got {type(states).__name__}")
    try:
        return model_from_authors_state(states)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from exc


def model_from_authors_state(states: Mapping[str, torch.Tensor]) -> AuthorsModel:
    """A :class:`KeypointDeformer` holding the weights of an authors' state dict (docs/method.md §16)."""
    from kpd.cage import default_m

    for key in ("influence_param", "template_faces"):
        if key not in states:
            raise InputError(f"checkpoint lacks {key!r} (docs/method.md §16 layout)")
    influence = states["influence_param"]
    faces = states["template_faces"]
    if not isinstance(influence, torch.Tensor) or influence.ndim != 2:
        raise InputError(f"'influence_param' must have shape (K, C); got {_shape(influence)}")
    if not isinstance(faces, torch.Tensor) or faces.ndim != 3 or faces.shape[0] != 1 or faces.shape[2] != 3:
        raise InputError(f"'template_faces' must have shape (1, F, 3); got {_shape(faces)}")
    k, c = influence.shape
    f = faces.shape[1]
    wanted = expected_shapes(k, c, f)
    missing = [key for key in wanted if key not in states]
    if missing:
        raise InputError(f"checkpoint lacks {len(missing)} key(s) of the docs/method.md §16 layout, first "
                         f"{missing[0]!r} (expected shape {wanted[missing[0]]})")
    for key, shape in wanted.items():
        value = states[key]
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape:
            raise InputError(f"key {key!r} has shape {_shape(value)}; expected {shape} for K={k}, C={c}")
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise InputError(f"key {key!r} holds NaN or inf")
    config = ModelConfig(keypoints=k, cage_vertices=c, cage_faces=f, m=default_m(c, k))
    template = states["template_vertices"][0].T.double()  # (C, 3)
    model = KeypointDeformer(config, template, faces[0].long())
    own = model.state_dict()
    if set(own) != set(wanted):  # the two layouts are one by construction; say so loudly if that ever changes
        raise InputError("internal: network keys differ from docs/method.md §16: "
                         f"{sorted(set(own) ^ set(wanted))[:4]}")
    model.load_state_dict({key: states[key].to(own[key].dtype) for key in wanted}, strict=True)
    ignored = sorted(str(key) for key in states if key not in wanted)
    if ignored:
        log.info("ignored %d key(s) that are not part of the model, e.g. %s", len(ignored), ignored[0])
    return AuthorsModel(model.eval(), ignored)


def _shape(value) -> str:
    return str(tuple(value.shape)) if isinstance(value, torch.Tensor) else type(value).__name__
