"""Use a trained checkpoint: keypoints, influence and alignment with torch (the exporter builds ONNX from the same)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from kpd.errors import InputError
from kpd.train.nets import KeypointDeformer, ModelConfig
from kpd.train.trainer import TrainConfig, load_checkpoint

__all__ = ["CheckpointPredictor"]


def _as_batch(points, name: str = "points") -> torch.Tensor:
    array = np.asarray(points, dtype=np.float32)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[1] < 1:
        raise InputError(f"{name} must have shape (B, N, 3) or (N, 3); got {np.shape(points)}")
    if not np.isfinite(array).all():
        raise InputError(f"{name} must be finite; got NaN or inf")
    return torch.from_numpy(np.ascontiguousarray(array))


class CheckpointPredictor:
    """A trained model from a kpd checkpoint, on the CPU (or ``device``).

    Attributes
    ----------
    K, C, m : keypoints, cage vertices, influence locality.
    template : kpd.cage.Cage, the cage template (vertices (C, 3) float64, faces (F, 3) int64).
    keypoint_source : "learned" or "fps".
    influence_param : (K, C) float64, W_C.
    model_config, train_config : the run's configuration.
    iteration : iterations trained.
    path : the checkpoint file.
    """

    def __init__(self, model: KeypointDeformer, checkpoint: dict, path: Path, device: torch.device) -> None:
        from kpd.cage import Cage

        self.model = model.eval()
        self.device = device
        self.path = path
        self.model_config: ModelConfig = model.config
        self.train_config = TrainConfig.from_dict(checkpoint["train_config"])
        self.sample_settings = dict(checkpoint.get("sample_settings", {}))
        self.iteration = int(checkpoint["iteration"])
        self.K = self.model_config.keypoints
        self.C = self.model_config.cage_vertices
        self.m = self.model_config.m
        self.keypoint_source = self.model_config.keypoint_source
        self.template = Cage(model.template_vertices[0].T.double().cpu().numpy(),
                             model.template_faces[0].cpu().numpy())
        self.influence_param = model.influence_param.detach().double().cpu().numpy()

    @classmethod
    def load(cls, path: str | os.PathLike, device: str = "cpu") -> "CheckpointPredictor":
        """Load ``checkpoint.pt`` from a run folder, or a checkpoint file."""
        path = Path(path)
        file = path / "checkpoint.pt" if path.is_dir() else path
        ckpt = load_checkpoint(file)
        config = ModelConfig.from_dict(ckpt["model_config"])
        states = ckpt["states"]
        for key in ("template_vertices", "template_faces", "influence_param"):
            if key not in states:
                raise InputError(f"checkpoint {file} lacks {key!r}")
        model = KeypointDeformer(config, states["template_vertices"][0].T, states["template_faces"][0])
        try:
            model.load_state_dict(states)
        except RuntimeError as exc:
            raise InputError(f"checkpoint {file} does not match its model config {config}: {exc}") from exc
        dev = torch.device(device)
        return cls(model.to(dev), ckpt, file, dev)

    @torch.no_grad()
    def _keypoints(self, points: torch.Tensor) -> torch.Tensor:
        return self.model.keypoints(points)

    def keypoints(self, points) -> np.ndarray:
        """Keypoints of normalised point clouds: points (B, N, 3) float32 -> (B, K, 3) float32."""
        with torch.no_grad():
            return self._keypoints(_as_batch(points).to(self.device)).cpu().numpy()

    def influence(self, points) -> np.ndarray:
        """Unmasked influence W = W_C + W_I(points): (B, N, 3) -> (B, K, C) float32."""
        with torch.no_grad():
            x = _as_batch(points).to(self.device)
            return (self.model.influence_param + self.model.influence_offset(x)).cpu().numpy()

    def align(self, source, target, cage, weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Deform sources toward targets by their keypoints (docs/method.md §1).

        Parameters
        ----------
        source, target : (B, N, 3) normalised point clouds.
        cage : (B, C, 3) the sources' fitted cages.
        weights : (B, N, C) MVC weights of the source points w.r.t. ``cage``.

        Returns
        -------
        deformed : (B, N, 3); source_keypoints, target_keypoints : (B, K, 3).
        """
        with torch.no_grad():
            src, tgt = _as_batch(source, "source").to(self.device), _as_batch(target, "target").to(self.device)
            cage_t = torch.as_tensor(np.asarray(cage, dtype=np.float32), device=self.device)
            w = torch.as_tensor(np.asarray(weights, dtype=np.float32), device=self.device)
            if cage_t.ndim == 2:
                cage_t, w = cage_t[None], w[None]
            b = src.shape[0]
            if tgt.shape[0] != b or cage_t.shape != (b, self.C, 3) or w.shape != (b, src.shape[1], self.C):
                raise InputError(f"align needs source (B, N, 3), target (B, M, 3), cage (B, {self.C}, 3), weights "
                                 f"(B, N, {self.C}); got {tuple(src.shape)}, {tuple(tgt.shape)}, "
                                 f"{tuple(cage_t.shape)}, {tuple(w.shape)}")
            kp = self._keypoints(torch.cat([src, tgt])) if src.shape[1] == tgt.shape[1] else \
                torch.cat([self._keypoints(src), self._keypoints(tgt)])
            result = self.model.deform(src, cage_t, w, kp[:b], kp[b:])
            return result.deformed.cpu().numpy(), kp[:b].cpu().numpy(), kp[b:].cpu().numpy()

    def __repr__(self) -> str:
        return (f"CheckpointPredictor(K={self.K}, C={self.C}, m={self.m}, keypoint_source={self.keypoint_source!r}, "
                f"iteration={self.iteration}, path={str(self.path)!r})")
