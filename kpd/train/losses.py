"""The three loss terms of KeypointDeformer (docs/method.md §6). Each returns a scalar tensor (batch mean)."""

from __future__ import annotations

import torch

from kpd.train.ops import chamfer

__all__ = ["similarity_loss", "keypoint_loss", "influence_loss"]


def similarity_loss(deformed: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_sim: chamfer between deformed source (B, N, 3) and target (B, M, 3), mean over the batch."""
    return chamfer(deformed, target).mean()


def keypoint_loss(keypoints: torch.Tensor, fps_points: torch.Tensor) -> torch.Tensor:
    """L_kpt: chamfer between keypoints (B, K, 3) and farthest points (B, J, 3) of the same clouds, batch mean."""
    return chamfer(keypoints, fps_points).mean()


def influence_loss(offset: torch.Tensor, form: str = "code") -> torch.Tensor:
    """L_inf on W_I (B, K, C).

    ``form="code"``: ``mean(W_I²)`` over all B·K·C entries (the authors' code, weighted 1e6 there).
    ``form="paper"``: the Frobenius norm ``‖W_I‖_F`` of each shape's matrix, averaged over the batch (weighted 1e-6).
    """
    if form == "code":
        return offset.square().mean()
    if form == "paper":
        return offset.flatten(1).norm(dim=1).mean()
    raise ValueError(f"influence loss form must be 'code' or 'paper'; got {form!r}")
