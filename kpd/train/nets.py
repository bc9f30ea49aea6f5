"""The two networks of KeypointDeformer and the module that holds them (docs/method.md §2, §3, §16).

Φ (``keypoint_predictor``) maps a point cloud to K keypoints; Γ (``influence_predictor``) maps the source cloud to the
instance-specific influence offset W_I; ``influence_param`` is the category-shared W_C. Module names mirror the
authors' checkpoints, so ``KeypointDeformer.state_dict()`` has the keys of docs/method.md §16::

    influence_param                                    (K, C)      W_C, zero-initialised
    template_vertices                                  (1, 3, C)   the cage template, channel-first (buffer)
    template_faces                                     (1, F, 3)   its triangles, int64 (buffer)
    keypoint_predictor.0.0.conv{1,2,3}.conv.{weight,bias}          PointNet 3-64-128-256 (ReLU, ReLU, none), max-pool
    keypoint_predictor.0.1.linear.*                    256 -> 256  LeakyReLU(0.1)
    keypoint_predictor.1.layers.{0,1,2}.linear.*       256 -> 512 -> 256 -> 3K (LReLU, LReLU, none)
    influence_predictor.0.0.conv{1,2,3}.conv.*         PointNet 3-64-128-KC, max-pool
    influence_predictor.0.1.linear.*, .1.0.linear.*, .1.1.linear.*   KC -> KC (LReLU, LReLU, none)

With ``keypoint_source="fps"`` (the farthest-point baseline) there is no ``keypoint_predictor``.

Unlike the authors' code the networks take row-major points ``(B, N, 3)``; the 1x1 convolutions keep their
``(out, in, 1)`` weights but run as matrix products over the last axis, which is the same function and about twice as
fast on a CPU. The keypoint head's flat 3K output is ordered [all x, all y, all z] as in the authors' code.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ModelConfig", "Deformation", "PointConv", "PointNetFeatures", "LinearBlock", "MLPHead",
           "KeypointPredictor", "InfluencePredictor", "KeypointDeformer", "count_parameters"]

LEAKY_SLOPE = 0.1


class Deformation(NamedTuple):
    """deformed (B, N, 3), new_cage (B, C, 3), influence (B, K, C) masked W, offset (B, K, C) unmasked W_I."""

    deformed: torch.Tensor
    new_cage: torch.Tensor
    influence: torch.Tensor
    offset: torch.Tensor


@dataclass(frozen=True)
class ModelConfig:
    """What fixes the shapes of a model.

    keypoints : K.
    cage_vertices : C, the template cage's vertex count (42 for the level-1 icosphere).
    cage_faces : F.
    m : influence locality, the number of nearest cage vertices each keypoint moves.
    keypoint_source : "learned" (Φ) or "fps" (farthest-point keypoints, the baseline of the paper's §4.3).
    clamp : clamp Φ's output to [-1, 1] (authors' code).
    """

    keypoints: int
    cage_vertices: int
    cage_faces: int
    m: int
    keypoint_source: str = "learned"
    clamp: bool = True

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})


class PointConv(nn.Module):
    """A shared per-point linear layer stored as ``Conv1d(k=1)`` (weight ``(out, in, 1)``), applied to
    ``(B, N, in)``."""

    def __init__(self, in_channels: int, out_channels: int, activation: str | None) -> None:
        super().__init__()
        self.conv = nn.Conv1d(in_channels, out_channels, 1)
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.linear(x, self.conv.weight.squeeze(-1), self.conv.bias)  # (B, N, out)
        return F.relu(y) if self.activation == "relu" else y


class PointNetFeatures(nn.Module):
    """PointNet encoder 3 -> 64 -> 128 -> ``bottleneck`` (ReLU, ReLU, none), max over points: (B, N, 3) -> (B, D).

    The last layer has no activation, so its bias is added after the max-pool (``max_i(x_i W + b) = max_i(x_i W) + b``
    exactly, as rounding is monotone), which spares a (B, N, D) pass forward and backward.
    """

    def __init__(self, bottleneck: int) -> None:
        super().__init__()
        self.conv1 = PointConv(3, 64, "relu")
        self.conv2 = PointConv(64, 128, "relu")
        self.conv3 = PointConv(128, bottleneck, None)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        h = self.conv2(self.conv1(points))  # (B, N, 128)
        last = self.conv3.conv
        return torch.matmul(h, last.weight.squeeze(-1).T).max(dim=1).values + last.bias  # (B, D)


class LinearBlock(nn.Module):
    """``Linear`` followed by LeakyReLU(0.1), or by nothing when ``activation`` is False."""

    def __init__(self, in_features: int, out_features: int, activation: bool = True) -> None:
        super().__init__()
        self.linear = nn.Linear(in_features, out_features)
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.linear(x)
        return F.leaky_relu(y, LEAKY_SLOPE) if self.activation else y


class MLPHead(nn.Module):
    """The keypoint head: 256 -> 512 -> 256 -> 3K (LReLU, LReLU, none)."""

    def __init__(self, keypoints: int) -> None:
        super().__init__()
        self.layers = nn.ModuleList(
            [LinearBlock(256, 512), LinearBlock(512, 256), LinearBlock(256, 3 * keypoints, activation=False)]
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = layer(x)
        return x


class KeypointPredictor(nn.Sequential):
    """Φ: points (B, N, 3) -> keypoints (B, K, 3), unclamped. 376,472 parameters for K=8; 379,556 for K=12."""

    def __init__(self, keypoints: int) -> None:
        super().__init__(nn.Sequential(PointNetFeatures(256), LinearBlock(256, 256)), MLPHead(keypoints))
        self.keypoints = keypoints

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        flat = super().forward(points)  # (B, 3K) ordered [x..., y..., z...]
        return flat.reshape(-1, 3, self.keypoints).transpose(1, 2)


class InfluencePredictor(nn.Sequential):
    """Γ: source points (B, N, 3) -> W_I (B, K, C). 391,616 parameters for K=8, C=42; 837,152 for K=12."""

    def __init__(self, keypoints: int, cage_vertices: int) -> None:
        kc = keypoints * cage_vertices
        super().__init__(
            nn.Sequential(PointNetFeatures(kc), LinearBlock(kc, kc)),
            nn.Sequential(LinearBlock(kc, kc), LinearBlock(kc, kc, activation=False)),
        )
        self.keypoints, self.cage_vertices = keypoints, cage_vertices

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return super().forward(points).reshape(-1, self.keypoints, self.cage_vertices)


def xavier_init(module: nn.Module, generator: torch.Generator | None = None) -> None:
    """The authors' ``weights_init``: Xavier-uniform weights and zero biases for every Conv1d / Linear."""
    for sub in module.modules():
        if isinstance(sub, (nn.Conv1d, nn.Linear)):
            nn.init.xavier_uniform_(sub.weight, generator=generator)
            nn.init.zeros_(sub.bias)


class KeypointDeformer(nn.Module):
    """Φ, Γ, W_C and the cage template of one trained model.

    Parameters
    ----------
    config : the model's shapes and keypoint source.
    template_vertices : (C, 3) float, the cage template (radius-1.4 icosphere by default).
    template_faces : (F, 3) int64.
    seed : seeds the Xavier initialisation, so the same seed gives the same starting weights.
    """

    def __init__(self, config: ModelConfig, template_vertices: torch.Tensor, template_faces: torch.Tensor,
                 seed: int = 0) -> None:
        super().__init__()
        self.config = config
        k, c = config.keypoints, config.cage_vertices
        generator = torch.Generator().manual_seed(int(seed))
        if config.keypoint_source == "learned":
            self.keypoint_predictor = KeypointPredictor(k)
            xavier_init(self.keypoint_predictor, generator)
        else:
            self.keypoint_predictor = None
        self.influence_predictor = InfluencePredictor(k, c)
        xavier_init(self.influence_predictor, generator)
        self.influence_param = nn.Parameter(torch.zeros(k, c))
        self.register_buffer("template_vertices",
                             torch.as_tensor(template_vertices, dtype=torch.float32).T[None].clone())
        self.register_buffer("template_faces", torch.as_tensor(template_faces, dtype=torch.int64)[None].clone())

    def keypoints(self, points: torch.Tensor) -> torch.Tensor:
        """Φ(points), clamped to [-1, 1] unless the config says otherwise: (B, N, 3) -> (B, K, 3).

        For the farthest-point baseline (``keypoint_source="fps"``): :func:`kpd.train.ops.fps_keypoints`.
        """
        if self.keypoint_predictor is None:
            from kpd.train.ops import fps_keypoints

            return fps_keypoints(points, self.config.keypoints)
        keypoints = self.keypoint_predictor(points)
        return keypoints.clamp(-1.0, 1.0) if self.config.clamp else keypoints

    def influence_offset(self, points: torch.Tensor) -> torch.Tensor:
        """W_I = Γ(points): (B, N, 3) -> (B, K, C)."""
        return self.influence_predictor(points)

    def deform(self, source: torch.Tensor, cage: torch.Tensor, weights: torch.Tensor, source_keypoints: torch.Tensor,
               target_keypoints: torch.Tensor) -> "Deformation":
        """Move the source's cage with the keypoint offsets and carry its points along (docs/method.md §1 steps 5-8).

        Parameters
        ----------
        source : (B, N, 3) source points (input of Γ).
        cage : (B, C, 3) the source's fitted cage (no gradient).
        weights : (B, N, C) MVC weights of ``source`` w.r.t. ``cage`` (no gradient).
        source_keypoints, target_keypoints : (B, K, 3).
        """
        from kpd.train.ops import deform_cage, influence_mask

        offset = self.influence_offset(source)  # (B, K, C) W_I
        mask = influence_mask(source_keypoints, cage, self.config.m)  # (B, K, C)
        influence = (self.influence_param + offset) * mask
        new_cage = deform_cage(cage, influence, target_keypoints - source_keypoints)  # (B, C, 3)
        return Deformation(torch.bmm(weights, new_cage), new_cage, influence, offset)

    def phi_parameters(self) -> list[nn.Parameter]:
        return [] if self.keypoint_predictor is None else list(self.keypoint_predictor.parameters())


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
