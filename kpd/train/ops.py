"""Batched torch kernels for training: chamfer, farthest point sampling, the M-nearest mask, the cage deformation and
mean value coordinates. Each has a numpy twin in kpd.geometry / kpd.cage / kpd.mvc that the tests compare against.

All arrays are row-major: points ``(B, N, 3)``, cages ``(B, C, 3)``, influence ``(B, K, C)``.
"""

from __future__ import annotations

import math
from contextlib import contextmanager

import torch

# nearest() computes distance blocks of about this many elements (4 MB of float32).
_BLOCK_ELEMENTS = 1 << 20

__all__ = [
    "serial",
    "squared_distances",
    "nearest",
    "chamfer",
    "farthest_point_sampling",
    "gather_points",
    "fps_keypoints",
    "influence_mask",
    "deform_cage",
    "mvc_weights",
]


@contextmanager
def serial(device: torch.device):
    """Run the enclosed CPU ops on one thread.

    The kernels here are sequences of many small ops; with several threads each op ends at a barrier that stalls for a
    scheduler time slice whenever another process holds a core, which made them ~10x slower on a shared 2-core
    machine. Serial they cost about the same on an idle machine. No effect on other devices.
    """
    if device.type != "cpu" or torch.get_num_threads() == 1:
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def squared_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """All squared distances ``|a_i - b_j|^2``: (B, N, 3), (B, M, 3) -> (B, N, M), clamped at 0."""
    a2 = a.square().sum(-1)  # (B, N)
    b2 = b.square().sum(-1)  # (B, M)
    d = torch.baddbmm(b2.unsqueeze(1), a, b.transpose(1, 2), alpha=-2.0)  # (B, N, M)
    return d.add_(a2.unsqueeze(2)).clamp_min_(0.0)


def nearest(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Index of each point's nearest neighbour in the other cloud, without gradient: (B, N, 3), (B, M, 3) -> (B, N).

    Squared distances come from one matrix product of augmented coordinates, ``[-2a, 1, |a|²] · [b, |b|², 1]``, and
    the rows go in blocks of about 4 MB so each block of the distance matrix stays in cache; only row minima are taken
    (torch's reduction along the middle axis is slow). The distances themselves are recomputed exactly by the caller.
    """
    with torch.no_grad(), serial(a.device):
        a2 = a.square().sum(-1, keepdim=True)  # (B, N, 1)
        b2 = b.square().sum(-1, keepdim=True)  # (B, M, 1)
        left = torch.cat([-2.0 * a, torch.ones_like(a2), a2], dim=-1)  # (B, N, 5)
        right = torch.cat([b, b2, torch.ones_like(b2)], dim=-1).transpose(1, 2).contiguous()  # (B, 5, M)
        rows = max(1, _BLOCK_ELEMENTS // (a.shape[0] * b.shape[1]))
        if rows >= a.shape[1]:
            return torch.bmm(left, right).min(dim=2).indices
        return torch.cat([torch.bmm(left[:, s:s + rows], right).min(dim=2).indices
                          for s in range(0, a.shape[1], rows)], dim=1)


def gather_points(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``points[b, index[b, j]]``: (B, N, D), (B, J) int64 -> (B, J, D)."""
    return torch.gather(points, 1, index.unsqueeze(-1).expand(-1, -1, points.shape[-1]))


def chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Chamfer distance per pair, as pytorch3d's with squared distances and mean reduction (docs/method.md §6).

    ``mean_i min_j |a_i - b_j|^2 + mean_j min_i |a_i - b_j|^2``. Nearest neighbours are found without gradient; the
    distances to them are then recomputed exactly, which gives the same gradient as differentiating the minimum.

    Parameters
    ----------
    a : (B, N, 3)
    b : (B, M, 3)

    Returns
    -------
    distance : (B,)
    """
    nn_ab = nearest(a.detach(), b.detach())  # (B, N)
    nn_ba = nearest(b.detach(), a.detach())  # (B, M)
    with serial(a.device):
        d_ab = (a - gather_points(b, nn_ab)).square().sum(-1).mean(1)
        d_ba = (b - gather_points(a, nn_ba)).square().sum(-1).mean(1)
        return d_ab + d_ba


def farthest_point_sampling(points: torch.Tensor, k: int, start: torch.Tensor) -> torch.Tensor:
    """Greedy farthest point sampling from given first points, as kpd.geometry.farthest_point_sampling.

    Parameters
    ----------
    points : (B, N, 3)
    k : how many points per cloud.
    start : (B,) int64, index of each cloud's first point.

    Returns
    -------
    indices : (B, k) int64
    """
    with torch.no_grad(), serial(points.device):
        batch = torch.arange(points.shape[0], device=points.device)
        indices = torch.empty(points.shape[0], k, dtype=torch.int64, device=points.device)
        current = start.to(device=points.device, dtype=torch.int64)
        indices[:, 0] = current
        dist = (points - points[batch, current].unsqueeze(1)).square().sum(-1)  # (B, N)
        for i in range(1, k):
            current = dist.argmax(dim=1)
            indices[:, i] = current
            torch.minimum(dist, (points - points[batch, current].unsqueeze(1)).square().sum(-1), out=dist)
    return indices


def fps_keypoints(points: torch.Tensor, k: int) -> torch.Tensor:
    """The farthest-point keypoint baseline: FPS starting from the point farthest from the origin (the bbox centre).

    Deterministic, so one shape always gets the same keypoints in the same order. (B, N, 3) -> (B, k, 3).
    """
    start = points.square().sum(-1).argmax(dim=1)
    return gather_points(points, farthest_point_sampling(points, k, start))


def influence_mask(keypoints: torch.Tensor, cage: torch.Tensor, m: int) -> torch.Tensor:
    """True where a cage vertex is among the ``m`` nearest to a keypoint, ties kept (docs/method.md §3).

    Parameters
    ----------
    keypoints : (B, K, 3)
    cage : (B, C, 3)
    m : 1 <= m <= C.

    Returns
    -------
    mask : (B, K, C) bool
    """
    with torch.no_grad(), serial(keypoints.device):
        d = squared_distances(keypoints, cage)  # (B, K, C)
        kth = d.kthvalue(m, dim=2, keepdim=True).values  # (B, K, 1)
        return d <= kth


def deform_cage(cage: torch.Tensor, influence: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """``c* = c + Wᵀ Δp``: cage (B, C, 3), influence (B, K, C) masked W, offsets (B, K, 3) -> (B, C, 3)."""
    return cage + torch.bmm(influence.transpose(1, 2), offsets)


def mvc_weights(points: torch.Tensor, cage: torch.Tensor, faces: torch.Tensor, *, chunk: int = 4096,
                eps: float = 1e-10) -> torch.Tensor:
    """Mean value coordinates of points w.r.t. closed triangle cages (Ju et al. 2005; docs/method.md §5), without
    gradient.

    Computed in float64 and returned in the dtype of ``points``. Used when a sample cache holds no weights.

    Parameters
    ----------
    points : (B, N, 3)
    cage : (B, C, 3)
    faces : (F, 3) int64, outward-oriented.
    chunk : points per block, to bound memory (B * chunk * F * 9 doubles).
    eps : the clamps of docs/method.md §5. The authors use 1e-5 in float32, which costs ~5e-5 of linear precision; in
        float64 1e-10 keeps it at ~1e-13 and agrees with kpd.mvc.

    Returns
    -------
    weights : (B, N, C), rows sum to one.
    """
    out = []
    with torch.no_grad():
        for s in range(0, points.shape[1], chunk):
            out.append(_mvc_block(points[:, s:s + chunk].double(), cage.double(), faces.long(), eps))
    return torch.cat(out, dim=1).to(points.dtype)


def _mvc_block(x: torch.Tensor, cage: torch.Tensor, faces: torch.Tensor, eps: float) -> torch.Tensor:
    b, n, _ = x.shape
    c = cage.shape[1]
    vec = cage.unsqueeze(1) - x.unsqueeze(2)  # (B, N, C, 3)
    dist = vec.norm(dim=-1)  # (B, N, C)
    unit = vec / dist.clamp_min(1e-12).unsqueeze(-1)
    u = unit[:, :, faces]  # (B, N, F, 3 corners, 3)
    d = dist[:, :, faces]  # (B, N, F, 3)
    nxt = [1, 2, 0]
    prv = [2, 0, 1]
    length = (u[:, :, :, nxt] - u[:, :, :, prv]).norm(dim=-1)  # (B, N, F, 3)
    length = length.clamp_max(2.0 - 2.0 * eps)
    theta = 2.0 * torch.asin(length / 2.0)  # (B, N, F, 3)
    h = theta.sum(-1) / 2.0  # (B, N, F)
    sin_t = torch.sin(theta)
    cos_c = (2.0 * torch.sin(h).unsqueeze(-1) * torch.sin(h.unsqueeze(-1) - theta) / (sin_t[..., nxt] * sin_t[..., prv])
             - 1.0)
    cos_c = cos_c.clamp(-1.0 + eps, 1.0 - eps)
    sign = torch.sign(torch.linalg.det(u))  # (B, N, F)
    s = sign.unsqueeze(-1) * torch.sqrt(1.0 - cos_c.square())  # (B, N, F, 3)
    w = ((theta - cos_c[..., nxt] * theta[..., prv] - cos_c[..., prv] * theta[..., nxt])
         / (d * sin_t[..., nxt] * s[..., prv]))
    w = torch.where((s.abs() <= eps).any(-1, keepdim=True), torch.zeros_like(w), w)
    on_face = (math.pi - h) < 1e-4  # (B, N, F)
    on_any = on_face.any(-1, keepdim=True)  # (B, N, 1)
    w_face = sin_t * d[..., prv] * d[..., nxt]  # barycentric-like weights on the touching face
    w = torch.where(on_any.unsqueeze(-1), torch.where(on_face.unsqueeze(-1), w_face, torch.zeros_like(w)), w)
    weights = torch.zeros(b, n, c, dtype=x.dtype, device=x.device)
    weights.index_add_(2, faces.reshape(-1), w.reshape(b, n, -1))
    on_vertex = dist < 1e-8  # (B, N, C)
    hit = on_vertex.any(-1, keepdim=True)
    weights = torch.where(hit, on_vertex.to(x.dtype), weights)
    total = weights.sum(-1, keepdim=True)
    total = torch.where(total == 0, torch.ones_like(total), total)
    return weights / total
