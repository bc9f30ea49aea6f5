"""The training recipe (:class:`TrainConfig`: the authors' defaults, every paper value of docs/method.md §11 an
option) and the device it runs on."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from kpd.errors import InputError

__all__ = ["TrainConfig", "resolve_device"]


@dataclass(frozen=True)
class TrainConfig:
    """The training recipe. Defaults are the authors' code (docs/method.md §11 lists the paper's values).

    - keypoints : K.
    - iterations : optimisation steps.
    - batch : source/target pairs per step.
    - seed : everything random (initial weights, pairs, samples, FPS starts) derives from it.
    - lr : Adam learning rate of Φ and of Γ.
    - wc_lr : learning rate of W_C (code 1e-2; paper: same as Γ, 1e-3).
    - alpha_kpt : weight of the FPS keypoint regulariser (code 2.0; paper 1.0).
    - alpha_inf, inf_reg : influence regulariser, ``code`` = alpha_inf * mean(W_I²) with 1e6, ``paper`` =
      alpha_inf * ‖W_I‖_F with 1e-6.
    - fps_factor : J = fps_factor * K farthest points for the regulariser.
    - warmup : keypoint-only iterations at the start (code 200; paper 0).
    - clamp : clamp keypoints to [-1, 1] (code; the paper has no clamp).
    - paper_m : M = ⌊C/K⌋ (paper) instead of max(5, ⌊C/K⌋) (code); ``m`` overrides both.
    - keypoint_source : ``learned`` (Φ) or ``fps`` (farthest-point keypoints of each shape; only the deformer trains,
      from the first iteration: ``warmup`` and the keypoint regulariser do not apply).
    - save_every : checkpoint (and validation) interval in iterations.
    - val_pairs : fixed validation pairs scored at every checkpoint.
    """

    keypoints: int = 12
    iterations: int = 2000
    batch: int = 16
    seed: int = 0
    lr: float = 1e-3
    wc_lr: float = 1e-2
    alpha_kpt: float = 2.0
    alpha_inf: float = 1e6
    inf_reg: str = "code"
    fps_factor: int = 2
    warmup: int = 200
    clamp: bool = True
    paper_m: bool = False
    m: int | None = None
    keypoint_source: str = "learned"
    save_every: int = 200
    val_pairs: int = 64

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})

    def check(self) -> None:
        for name in ("keypoints", "iterations", "batch", "fps_factor", "save_every"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} must be at least 1; got {getattr(self, name)}")
        if self.warmup < 0 or self.val_pairs < 0:
            raise InputError(f"warmup and val_pairs must be >= 0; got {self.warmup}, {self.val_pairs}")
        if self.inf_reg not in ("code", "paper"):
            raise InputError(f"inf_reg must be 'code' or 'paper'; got {self.inf_reg!r}")
        if self.keypoint_source not in ("learned", "fps"):
            raise InputError(f"keypoint_source must be 'learned' or 'fps'; got {self.keypoint_source!r}")
        for name in ("lr", "wc_lr", "alpha_kpt", "alpha_inf"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be a finite number >= 0; got {value}")


def resolve_device(device: str = "auto") -> torch.device:
    """``auto`` -> cuda when available, else cpu; otherwise the named device (checked)."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        raise InputError(f"unknown device {device!r}; expected auto, cpu, cuda or cuda:N") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {device!r} requested but CUDA is not available")
    return dev
