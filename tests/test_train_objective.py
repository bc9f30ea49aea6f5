"""kpd.train.objective: the warm-up objective holds and trains Φ alone; the full one adds the deformation losses with
the recipe's weights."""

from __future__ import annotations

import torch

from kpd.cage import icosphere
from kpd.train.config import TrainConfig
from kpd.train.nets import KeypointDeformer, ModelConfig
from kpd.train.objective import Objective

ICO = icosphere(1, 1.4)


def _inputs(b: int = 2, n: int = 128, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(2 * b, n, 3, generator=g, dtype=torch.float32) * 1.6 - 0.8
    cage = torch.from_numpy(ICO.vertices).float().expand(b, -1, -1).contiguous()
    weights = torch.rand(b, n, len(ICO.vertices), generator=g)
    weights = weights / weights.sum(dim=2, keepdim=True)
    return points, cage, weights, torch.zeros(2 * b, dtype=torch.int64)


def test_warm_and_full_objectives():
    config = TrainConfig(keypoints=4, alpha_kpt=2.0, alpha_inf=1e6)
    model = KeypointDeformer(ModelConfig(keypoints=4, cage_vertices=42, cage_faces=80, m=5),
                             torch.from_numpy(ICO.vertices), torch.from_numpy(ICO.faces), seed=0)
    warm, full = Objective(model, config, warm=True), Objective(model, config, warm=False)
    phi = {id(p) for p in model.keypoint_predictor.parameters()}
    assert {id(p) for p in warm.parameters()} == phi  # DDP sees only what the warm-up loss reaches
    assert {id(p) for p in full.parameters()} == {id(p) for p in model.parameters()} != phi
    inputs = _inputs()
    out = warm(*inputs)
    assert set(out) == {"kpt", "loss"} and torch.equal(out["loss"], 2.0 * out["kpt"])
    out["loss"].backward()
    assert all(p.grad is None for p in model.parameters() if id(p) not in phi)
    model.zero_grad()
    out = full(*inputs)
    assert {"sim", "inf", "kpt", "loss", "deformed", "new_cage"} <= set(out)
    torch.testing.assert_close(out["loss"], out["sim"] + 1e6 * out["inf"] + 2.0 * out["kpt"])
    assert out["deformed"].shape == (2, 128, 3) and out["new_cage"].shape == (2, 42, 3)
    out["loss"].backward()
    assert all(p.grad is not None for p in model.parameters())
