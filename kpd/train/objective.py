"""One iteration's forward pass and losses as a module call, the unit DistributedDataParallel wraps."""

from __future__ import annotations

import torch
from torch import nn

from kpd.train.config import TrainConfig
from kpd.train.losses import influence_loss, keypoint_loss, similarity_loss
from kpd.train.nets import KeypointDeformer
from kpd.train.ops import (
    farthest_point_sampling,
    gather_points,
)

__all__ = ["Objective"]


class Objective(nn.Module):
    """One iteration's forward pass and losses as a module call, the unit DistributedDataParallel wraps.

    The warm-up objective (``warm=True``: the keypoint regulariser alone) holds Φ only and the full one the whole
    model, so each holds exactly the parameters its loss reaches and DDP never meets an unused one.

    Parameters
    ----------
    model : the networks (shared, not copied).
    config : the recipe (K, J factor, loss weights).
    warm : the warm-up objective.
    """

    def __init__(self, model: KeypointDeformer, config: TrainConfig, warm: bool) -> None:
        super().__init__()
        self.config, self.warm, self.clamp = config, warm, model.config.clamp
        self.keypoint_predictor = model.keypoint_predictor  # Φ, None for farthest-point keypoints
        self.model = None if warm else model

    def forward(self, points: torch.Tensor, cage: torch.Tensor, weights: torch.Tensor, fps_start: torch.Tensor,
                fps_keypoints: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Losses of ``b`` pairs.

        Parameters
        ----------
        points : (2b, N, 3) the sources, then the targets.
        cage : (b, C, 3) the sources' cages; weights : (b, N, C) their MVC weights.
        fps_start : (2b,) int64 first farthest point of each cloud (keypoint regulariser).
        fps_keypoints : (2b, K, 3) the keypoints of the farthest-point baseline; None for Φ's.

        Returns
        -------
        out : ``loss`` (what is backpropagated) and the terms ``sim``, ``kpt``, ``inf`` it has (scalars); the full
            objective also gives ``deformed``, ``new_cage`` (b, ...) and its inputs ``cage``, ``weights``.
        """
        cfg = self.config
        b = len(points) // 2
        out: dict[str, torch.Tensor] = {}
        if fps_keypoints is None:
            keypoints = self.keypoint_predictor(points)  # (2b, K, 3); as KeypointDeformer.keypoints
            if self.clamp:
                keypoints = keypoints.clamp(-1.0, 1.0)
            fps = farthest_point_sampling(points, cfg.fps_factor * cfg.keypoints, fps_start)
            out["kpt"] = keypoint_loss(keypoints, gather_points(points, fps))
        else:
            keypoints = fps_keypoints
        if self.warm:
            out["loss"] = cfg.alpha_kpt * out["kpt"]
            return out
        result = self.model.deform(points[:b], cage, weights, keypoints[:b], keypoints[b:])
        out["sim"] = similarity_loss(result.deformed, points[b:])
        out["inf"] = influence_loss(result.offset, cfg.inf_reg)
        loss = out["sim"] + cfg.alpha_inf * out["inf"]
        if fps_keypoints is None:
            loss = loss + cfg.alpha_kpt * out["kpt"]
        out["loss"] = loss
        out["deformed"], out["new_cage"], out["cage"], out["weights"] = result.deformed, result.new_cage, cage, weights
        return out
