"""The training loop (docs/method.md §1, §6, §7) with exact resumption.

The recipe is :mod:`kpd.train.config`, the checkpoint files :mod:`kpd.train.checkpoint`, one iteration's losses
:mod:`kpd.train.objective`; their names stay importable from here.

Defaults are the authors' code; every paper value of docs/method.md §11 is a :class:`TrainConfig` option. Each
iteration's randomness (source order, targets, which cached sample, FPS starts) is drawn from
``numpy.random.default_rng`` seeded by ``(seed, iteration)``, so a run resumed from a checkpoint continues with exactly
the numbers an uninterrupted run would have used; the checkpoint holds the weights, both optimisers' states and the loss
history.

Under ``torchrun`` (:mod:`kpd.train.distributed`) each rank takes its slice of every iteration's global batch from
the same ``(seed, iteration)`` schedule and DistributedDataParallel averages the gradients, so W ranks follow the
single-process run to floating-point rounding, and a checkpoint resumes with any world size; rank 0 alone validates
and writes the files below. The step keeps every per-iteration tensor on the device: the loss terms are brought to
the host (and averaged over the ranks) every :data:`LOG_EVERY` iterations and at checkpoints only.

Output folder::

    checkpoint.pt   the latest checkpoint (atomic; torch.load(..., weights_only=True)):
                    {"format": "kpd-checkpoint", "version": 1, "iteration": int (iterations done),
                     "model_config": {...}, "train_config": {...}, "sample_settings": {...},
                     "states": KeypointDeformer.state_dict() (keys of docs/method.md §16),
                     "optimizers": {"keypoint": Adam state | None, "deformer": Adam state},
                     "history": {"train": (T, 5) float64 [iteration, loss, sim, kpt, inf],
                                 "val": (V, 3) float64 [iteration, val chamfer, val chamfer undeformed]},
                     "world_sizes": [[first iteration, world size], ...] (one entry per change of world size)}
    model.json      model config, train config, sample settings
    record.json     data, command, seed, iterations, metrics, skipped files, timings, world size, versions
    losses.csv      per-iteration losses;  losses.png  the curves
"""

from __future__ import annotations

import io
import logging
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from kpd.data import PreparedData, SampleSettings, ShapeSamples
from kpd.errors import InputError, TrainingError
from kpd.train import distributed
from kpd.train.checkpoint import (  # noqa: F401  (as before)
    CHECKPOINT_FORMAT,
    CHECKPOINT_NAME,
    CHECKPOINT_VERSION,
    _atomic_write,
    _write_json,
    load_checkpoint,
)
from kpd.train.config import TrainConfig, resolve_device  # noqa: F401  (importable from here as before)
from kpd.train.distributed import World
from kpd.train.nets import KeypointDeformer, ModelConfig
from kpd.train.objective import Objective  # noqa: F401
from kpd.train.ops import (
    chamfer,
    fps_keypoints,
    mvc_weights,
    serial,
)

__all__ = ["TrainConfig", "Trainer", "train", "resolve_device", "load_checkpoint", "CHECKPOINT_FORMAT",
           "CHECKPOINT_VERSION", "LOG_EVERY"]

log = logging.getLogger(__name__)

HISTORY_COLUMNS = ("iteration", "loss", "sim", "kpt", "inf")
LOG_EVERY = 10  # iterations between bringing the loss terms to the host


class Trainer:
    """One training run on prepared data; :meth:`run` trains, checkpoints and writes the record.

    Parameters
    ----------
    config : the recipe.
    data : from :func:`kpd.data.prepare` with the ``train`` (and optionally ``val``) split.
    out_dir : the run folder (created).
    device : ``auto``, ``cpu``, ``cuda``... (under torchrun the device of ``world``).
    command : recorded in ``record.json``.
    world : this rank's torchrun job (:func:`kpd.train.distributed.from_environment`, after
        :func:`~kpd.train.distributed.init`); None for one process.
    """

    def __init__(self, config: TrainConfig, data: PreparedData, out_dir: str | os.PathLike, *, device: str = "auto",
                 command: str | None = None, world: World | None = None) -> None:
        from kpd.cage import default_m, icosphere

        config.check()
        if world is not None and config.batch % world.size:
            raise InputError(f"batch {config.batch} does not split over {world.size} ranks")
        self.config = config
        self.data = data
        self.out_dir = Path(out_dir)
        self.world = world if world is not None and world.size > 1 else None
        self.main = world is None or world.main
        self.world_size = 1 if world is None else world.size
        self.device = world.device if world is not None else resolve_device(device)
        self.command = command if command is not None else " ".join(sys.argv)
        train = data.samples["train"]
        self.settings: SampleSettings = data.settings
        template = icosphere(self.settings.cage_level, self.settings.cage_radius)
        c, k = len(template.vertices), config.keypoints
        m = config.m if config.m is not None else default_m(c, k, paper=config.paper_m)
        if not 1 <= m <= c:
            raise InputError(f"m must lie in [1, {c}] for a {c}-vertex cage; got {m}")
        self.model_config = ModelConfig(keypoints=k, cage_vertices=c, cage_faces=len(template.faces), m=m,
                                        keypoint_source=config.keypoint_source, clamp=config.clamp)
        self.model = KeypointDeformer(self.model_config, torch.from_numpy(template.vertices),
                                      torch.from_numpy(np.asarray(template.faces)), seed=config.seed).to(self.device)
        self.train_set = self._tensors(train)
        self.val_set = self._tensors(data.samples["val"]) if "val" in data.samples else None
        phi = self.model.phi_parameters()
        # fused: one kernel per step, several times faster than the default per-tensor loop on a CPU.
        self.opt_keypoints = torch.optim.Adam(phi, lr=config.lr, fused=True) if phi else None
        self.opt_deformer = torch.optim.Adam([
            {"params": list(self.model.influence_predictor.parameters()), "lr": config.lr},
            {"params": [self.model.influence_param], "lr": config.wc_lr},
        ], fused=True)
        learned = self.model_config.keypoint_source == "learned"
        self.objectives = {warm: Objective(self.model, config, warm)
                           for warm in ((True, False) if learned else (False,))}
        self._ddp: tuple[bool, nn.Module] | None = None  # (warm, the DDP wrapper of that objective)
        self.iteration = 0
        self.history: list[list[float]] = []
        self.val_history: list[list[float]] = []
        self.world_sizes: list[list[int]] = []  # [first iteration, world size] per change
        self.world_info = None if world is None else world.to_dict()
        self.seconds = 0.0  # time in optimisation steps
        self.run_seconds = 0.0  # wall time of the training loop, with validation and checkpoints
        self._val_pairs = self._validation_pairs()

    # ----------------------------------------------------------------------------------------------- data
    def _tensors(self, samples: ShapeSamples) -> dict[str, torch.Tensor]:
        dev = self.device
        out = {
            "points": torch.from_numpy(samples.points).to(dev),
            "cages": torch.from_numpy(samples.cage_vertices).to(dev),
        }
        if samples.weights is not None:
            out["weights"] = torch.from_numpy(samples.weights).to(dev)
        else:
            faces = torch.from_numpy(samples.cage_faces).to(dev)
            n_shapes, r, n, _ = samples.points.shape
            flat_p = out["points"].reshape(n_shapes * r, n, 3)
            flat_c = out["cages"].reshape(n_shapes * r, -1, 3)
            w = [mvc_weights(flat_p[i:i + 8], flat_c[i:i + 8], faces) for i in range(0, len(flat_p), 8)]
            out["weights"] = torch.cat(w).reshape(n_shapes, r, n, -1)
        if self.config.keypoint_source == "fps":
            n_shapes, r, n, _ = samples.points.shape
            kp = fps_keypoints(out["points"].reshape(n_shapes * r, n, 3), self.config.keypoints)
            out["fps_keypoints"] = kp.reshape(n_shapes, r, self.config.keypoints, 3)
        return out

    def _validation_pairs(self) -> np.ndarray | None:
        if self.val_set is None or self.config.val_pairs == 0:
            return None
        n = self.val_set["points"].shape[0]
        rng = np.random.default_rng([self.config.seed, 2])
        return np.stack([rng.integers(n, size=self.config.val_pairs), rng.integers(n, size=self.config.val_pairs)], 1)

    def batch_indices(self, t: int) -> dict[str, np.ndarray]:
        """Which shapes and samples iteration ``t`` uses, derived from ``(seed, t)`` only.

        Sources run through a fresh permutation of the train split each epoch (``drop_last``, as the authors'
        loader); targets are uniform over the split; each picks one of its cached samples; FPS starts are uniform.
        """
        cfg = self.config
        n_shapes, r, n, _ = self.train_set["points"].shape
        b = cfg.batch
        rng = np.random.default_rng([cfg.seed, 0, t])
        per_epoch = n_shapes // b
        if per_epoch >= 1:
            epoch, slot = divmod(t, per_epoch)
            order = np.random.default_rng([cfg.seed, 1, epoch]).permutation(n_shapes)
            source = order[slot * b:(slot + 1) * b]
        else:
            source = rng.integers(n_shapes, size=b)
        return {
            "source": source,
            "target": rng.integers(n_shapes, size=b),
            "source_sample": rng.integers(r, size=b),
            "target_sample": rng.integers(r, size=b),
            "fps_start": rng.integers(n, size=2 * b),
        }

    # ----------------------------------------------------------------------------------------------- step
    def _keypoints(self, data: dict, shapes: torch.Tensor, samples: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        if self.model_config.keypoint_source == "fps":
            return data["fps_keypoints"][shapes, samples]
        return self.model.keypoints(points)

    def _upload(self, array: np.ndarray) -> torch.Tensor:
        """A host array on the device without waiting for it (pinned memory, asynchronous copy on CUDA)."""
        tensor = torch.from_numpy(array)
        if self.device.type == "cuda":
            return tensor.pin_memory().to(self.device, non_blocking=True)
        return tensor.to(self.device)

    def batch(self, t: int) -> dict[str, torch.Tensor]:
        """This rank's share of iteration ``t``'s pairs (all of them in one process), gathered on the device.

        Returns the keyword arguments of :meth:`Objective.forward`: ``points`` (2b, N, 3) sources then targets,
        ``cage`` (b, C, 3), ``weights`` (b, N, C), ``fps_start`` (2b,), ``fps_keypoints`` (2b, K, 3) or None, with
        b = B / W pairs from slot ``[rank * b, (rank + 1) * b)`` of :meth:`batch_indices`.
        """
        data, b = self.train_set, self.config.batch
        idx = self.batch_indices(t)
        share = slice(0, b) if self.world is None else self.world.share(b)
        rows = np.stack([idx["source"][share], idx["target"][share], idx["source_sample"][share],
                         idx["target_sample"][share], idx["fps_start"][:b][share], idx["fps_start"][b:][share]])
        source, target, source_sample, target_sample, fps_source, fps_target = self._upload(rows).unbind(0)
        shapes = torch.cat([source, target])
        samples = torch.cat([source_sample, target_sample])
        return {
            "points": data["points"][shapes, samples],
            "cage": data["cages"][source, source_sample],
            "weights": data["weights"][source, source_sample],
            "fps_start": torch.cat([fps_source, fps_target]),
            "fps_keypoints": data["fps_keypoints"][shapes, samples] if "fps_keypoints" in data else None,
        }

    def _objective(self, warm: bool) -> nn.Module:
        """The objective of this phase; under torchrun wrapped in DistributedDataParallel (re-wrapped once, when
        the warm-up ends: the old wrapper is dropped first, which removes its gradient hooks)."""
        objective = self.objectives[warm]
        if self.world is None:
            return objective
        if self._ddp is None or self._ddp[0] != warm:
            from torch.nn.parallel import DistributedDataParallel

            self._ddp = None
            ids = [self.device.index] if self.device.type == "cuda" else None
            self._ddp = (warm, DistributedDataParallel(objective, device_ids=ids, forward_sync_buffers=False))
        return self._ddp[1]

    def losses(self, t: int) -> dict[str, torch.Tensor]:
        """Forward pass of this rank's share of iteration ``t``; the ``loss`` entry is what :meth:`step`
        backpropagates (see :meth:`Objective.forward`)."""
        warm = self.model_config.keypoint_source == "learned" and t < self.config.warmup
        return self._objective(warm)(**self.batch(t))

    def step(self, t: int) -> torch.Tensor:
        """One optimisation step. Returns this rank's loss terms ``[loss, sim, kpt, inf]`` (4,) on the device, NaN
        for terms not computed; nothing waits for the device (no value is read on the host)."""
        out = self.losses(t)
        warm = self.model_config.keypoint_source == "learned" and t < self.config.warmup
        if self.opt_keypoints is not None:
            self.opt_keypoints.zero_grad(set_to_none=True)
        self.opt_deformer.zero_grad(set_to_none=True)
        out["loss"].backward()
        with serial(self.device):  # memory-bound; see kpd.train.ops.serial
            if self.opt_keypoints is not None:
                self.opt_keypoints.step()
            if not warm:
                self.opt_deformer.step()
        nan = out["loss"].detach().new_full((), math.nan)
        return torch.stack([out[k].detach() if k in out else nan for k in HISTORY_COLUMNS[1:]])

    def _log_terms(self, first: int, terms: list[torch.Tensor]) -> np.ndarray:
        """Bring the terms of iterations ``first ..`` to the host (the mean over the ranks) into :attr:`history`;
        :class:`~kpd.errors.TrainingError` at the first non-finite loss. Returns the rows (L, 5)."""
        stacked = torch.stack(terms)  # (L, 4) on the device
        if self.world is not None:
            distributed.average(stacked)
        values = stacked.cpu().double().numpy()
        rows = np.column_stack([np.arange(first, first + len(values), dtype=np.float64), values])
        self.history.extend(rows.tolist())
        bad = np.flatnonzero(~np.isfinite(values[:, 0]))
        if len(bad):
            kept = self.out_dir / CHECKPOINT_NAME
            error = TrainingError if self.main else distributed.Stopped  # every rank sees it; rank 0 says it
            raise error(f"training diverged at iteration {first + bad[0]}: loss {values[bad[0], 0]}; "
                        + (f"{kept} keeps the last good checkpoint" if kept.is_file()
                           else "no checkpoint had been written yet"))
        return rows

    # ----------------------------------------------------------------------------------------------- validation
    @torch.no_grad()
    def validate(self) -> tuple[float, float]:
        """Mean chamfer of the fixed validation pairs (sample 0), deformed and undeformed."""
        if self._val_pairs is None:
            return math.nan, math.nan
        data, b = self.val_set, self.config.batch
        deformed_sum, plain_sum = 0.0, 0.0
        zero = torch.zeros(1, dtype=torch.int64, device=self.device)
        for s in range(0, len(self._val_pairs), b):
            pairs = torch.from_numpy(self._val_pairs[s:s + b]).to(self.device)
            src, tgt = pairs[:, 0], pairs[:, 1]
            shapes = torch.cat([src, tgt])
            samples = zero.expand(len(shapes))
            points = data["points"][shapes, samples]
            kp = self._keypoints(data, shapes, samples, points)
            n = len(src)
            result = self.model.deform(points[:n], data["cages"][src, 0], data["weights"][src, 0], kp[:n], kp[n:])
            deformed_sum += float(chamfer(result.deformed, points[n:]).sum())
            plain_sum += float(chamfer(points[:n], points[n:]).sum())
        count = len(self._val_pairs)
        return deformed_sum / count, plain_sum / count

    # ----------------------------------------------------------------------------------------------- state
    def state(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "iteration": self.iteration,
            "model_config": self.model_config.to_dict(),
            "train_config": self.config.to_dict(),
            "sample_settings": self.settings.to_dict(),
            "states": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
            "optimizers": {
                "keypoint": None if self.opt_keypoints is None else self.opt_keypoints.state_dict(),
                "deformer": self.opt_deformer.state_dict(),
            },
            "history": {
                "train": torch.tensor(self.history, dtype=torch.float64).reshape(-1, len(HISTORY_COLUMNS)),
                "val": torch.tensor(self.val_history, dtype=torch.float64).reshape(-1, 3),
            },
            "seconds": self.seconds,
            "run_seconds": self.run_seconds,
            "world_sizes": [list(s) for s in self.world_sizes],
        }

    def load_state(self, ckpt: dict) -> None:
        """Continue from a checkpoint written by :meth:`save` with the same recipe."""
        saved = TrainConfig.from_dict(ckpt["train_config"])
        mine = self.config.to_dict()
        diffs = {k: (v, mine[k]) for k, v in saved.to_dict().items() if k != "iterations" and mine[k] != v}
        if diffs:
            raise InputError("cannot resume: the recipe differs from the checkpoint's (saved, requested): "
                             + ", ".join(f"{k}={a!r} vs {b!r}" for k, (a, b) in diffs.items()))
        if SampleSettings.from_dict(ckpt["sample_settings"]) != self.settings:
            raise InputError(f"cannot resume: sample settings differ: saved {ckpt['sample_settings']}, "
                             f"requested {self.settings.to_dict()}")
        self.model.load_state_dict(ckpt["states"])
        if self.opt_keypoints is not None:
            self.opt_keypoints.load_state_dict(ckpt["optimizers"]["keypoint"])
        self.opt_deformer.load_state_dict(ckpt["optimizers"]["deformer"])
        self.iteration = int(ckpt["iteration"])
        self.history = ckpt["history"]["train"].tolist()
        self.val_history = ckpt["history"]["val"].tolist()
        self.seconds = float(ckpt.get("seconds", 0.0))
        self.run_seconds = float(ckpt.get("run_seconds", 0.0))
        self.world_sizes = [[int(a), int(b)] for a, b in ckpt.get("world_sizes", [[0, 1]])]

    def save(self) -> None:
        """Write checkpoint, model.json, record.json, losses.csv and losses.png (each atomically)."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        from kpd.io.integrity import HASH_KEY, content_hash

        state = self.state()
        state[HASH_KEY] = content_hash(state)  # checked by load_checkpoint
        buffer = io.BytesIO()  # serialised in memory, written by Python: a full disk is an OSError, not torch's
        torch.save(state, buffer)  # RuntimeError from a stream it cannot report on
        _atomic_write(self.out_dir / CHECKPOINT_NAME, lambda tmp: Path(tmp).write_bytes(buffer.getvalue()))
        _write_json(self.out_dir / "model.json", {
            "model_config": self.model_config.to_dict(), "train_config": self.config.to_dict(),
            "sample_settings": self.settings.to_dict()})
        _write_json(self.out_dir / "record.json", self.record())
        self._write_curves()

    def record(self) -> dict:
        last = self.history[-1] if self.history else None
        recent = np.asarray(self.history[-50:]) if self.history else np.zeros((0, len(HISTORY_COLUMNS)))
        metrics: dict = {"iterations_done": self.iteration}
        if len(recent):
            for j, name in enumerate(HISTORY_COLUMNS[1:], 1):
                column = recent[:, j][~np.isnan(recent[:, j])]
                metrics[f"{name}_last50"] = float(column.mean()) if len(column) else None
        if self.val_history:
            metrics["val_chamfer"] = self.val_history[-1][1]
            metrics["val_chamfer_undeformed"] = self.val_history[-1][2]
            metrics["val_pairs"] = self.config.val_pairs
        return {
            "data": self.data.to_dict(),
            "command": self.command,
            "seed": self.config.seed,
            "iterations": self.config.iterations,
            "metrics": metrics,
            "skipped": [s._asdict() for s in self.data.skipped],
            "model_config": self.model_config.to_dict(),
            "train_config": self.config.to_dict(),
            "train_seconds": round(self.seconds, 2),
            "run_seconds": round(self.run_seconds, 2),
            "device": str(self.device),
            "threads": torch.get_num_threads(),
            "world_size": self.world_size,
            "distributed": self.world_info,
            "world_sizes": [list(s) for s in self.world_sizes],
            "versions": {"torch": torch.__version__, "numpy": np.__version__, "python": platform.python_version()},
            "last": None if last is None else dict(zip(HISTORY_COLUMNS, last)),
        }

    def _write_curves(self) -> None:
        rows = self.history

        def write_csv(tmp: str) -> None:
            with open(tmp, "w") as f:
                f.write(",".join(HISTORY_COLUMNS) + "\n")
                for row in rows:
                    f.write(f"{int(row[0])}," + ",".join("" if math.isnan(v) else f"{v:.8g}" for v in row[1:]) + "\n")

        _atomic_write(self.out_dir / "losses.csv", write_csv)
        if not rows:
            return
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        h = np.asarray(rows)
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for j, name in enumerate(HISTORY_COLUMNS[1:], 1):
            ok = ~np.isnan(h[:, j])
            if ok.any() and name != "inf":
                axes[0].plot(h[ok, 0], h[ok, j], label=name, lw=0.8)
        if self.val_history:
            v = np.asarray(self.val_history)
            axes[0].plot(v[:, 0], v[:, 1], "o-", label="val chamfer", ms=3)
            axes[0].plot(v[:, 0], v[:, 2], "--", label="val undeformed", lw=0.8)
        axes[0].set_yscale("log")
        axes[0].set_xlabel("iteration")
        axes[0].legend()
        axes[0].set_title("losses")
        ok = ~np.isnan(h[:, 4])
        if ok.any():
            axes[1].plot(h[ok, 0], h[ok, 4], lw=0.8)
        axes[1].set_yscale("log")
        axes[1].set_xlabel("iteration")
        axes[1].set_title("influence regulariser (unweighted)")
        fig.tight_layout()
        _atomic_write(self.out_dir / "losses.png", lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
        plt.close(fig)

    # ----------------------------------------------------------------------------------------------- loop
    def run(self, *, progress: bool = True, stop_at: int | None = None) -> dict:
        """Train from :attr:`iteration` to ``config.iterations`` (or ``stop_at``), checkpointing every
        ``save_every`` iterations and at the end (rank 0 only under torchrun). Returns the record."""
        from tqdm import tqdm

        cfg = self.config
        end = cfg.iterations if stop_at is None else min(stop_at, cfg.iterations)
        if self.iteration < end and (not self.world_sizes or self.world_sizes[-1][1] != self.world_size):
            self.world_sizes.append([self.iteration, self.world_size])
        self.model.train()
        bar = tqdm(total=end, initial=self.iteration, desc="training", unit="it", disable=not (progress and self.main))
        loop_start = time.perf_counter() - self.run_seconds
        pending: list[torch.Tensor] = []  # loss terms on the device, not yet logged
        try:
            start = time.perf_counter()
            while self.iteration < end:
                t = self.iteration
                pending.append(self.step(t))
                self.iteration = t + 1
                checkpoint = self.iteration % cfg.save_every == 0 or self.iteration == end
                if checkpoint or self.iteration % LOG_EVERY == 0:
                    rows = self._log_terms(self.iteration - len(pending), pending)
                    pending = []
                    self.seconds += time.perf_counter() - start  # steps, and the wait for the device
                    terms = dict(zip(HISTORY_COLUMNS[1:], rows[-1, 1:]))
                    bar.set_postfix({k: f"{v:.3g}" for k, v in terms.items() if not math.isnan(v)}, refresh=False)
                    bar.update(len(rows))
                    if checkpoint and self.main:
                        self.run_seconds = time.perf_counter() - loop_start
                        val = self.validate()
                        self.val_history.append([float(self.iteration), *val])
                        self.save()
                        log.info("iteration %d: loss %.5g, val chamfer %.5g (undeformed %.5g)", self.iteration,
                                 terms["loss"], *val)
                    start = time.perf_counter()
        finally:
            bar.close()
        distributed.barrier(self.world)  # the others end after rank 0 wrote the last checkpoint
        return self.record()


def train(data: PreparedData, config: TrainConfig, out_dir: str | os.PathLike, *, device: str = "auto",
          resume: bool = False, progress: bool = True, command: str | None = None,
          stop_at: int | None = None, world: World | None = None) -> dict:
    """Train (or resume) a model in ``out_dir``; returns the training record (also in ``out_dir/record.json``).

    Under torchrun (``world``), rank 0 reads and checks the checkpoint and sends it to the other ranks.
    """
    trainer = Trainer(config, data, out_dir, device=device, command=command, world=world)
    if resume:
        def load() -> dict:
            ckpt = load_checkpoint(Path(out_dir) / CHECKPOINT_NAME)
            trainer.load_state(ckpt)
            return ckpt

        ckpt = distributed.broadcast_state(world, distributed.only_main(world, load))
        if not trainer.main:
            trainer.load_state(ckpt)
        log.info("resuming %s at iteration %d", out_dir, trainer.iteration)
    return trainer.run(progress=progress, stop_at=stop_at)
