"""Checkpoint files: written through kpd's one atomic writer, loaded with ``weights_only=True`` and checked (format,
version, content hash) before anything uses them."""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from kpd.errors import InputError

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "CHECKPOINT_NAME", "load_checkpoint"]


CHECKPOINT_FORMAT = "kpd-checkpoint"


CHECKPOINT_VERSION = 1


CHECKPOINT_NAME = "checkpoint.pt"


def _atomic_write(path: Path, write) -> None:
    """Write ``path`` through ``write(tmp)`` with kpd's one atomic writer (:func:`kpd.io.atomic_output`: a temporary
    name that ``--resume`` cleans up after a kill, fsync, one-line :class:`~kpd.errors.WriteError` on a full disk)."""
    from kpd.io import atomic_output

    with atomic_output(path) as tmp:
        write(str(tmp))


def _write_json(path: Path, data: dict) -> None:
    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            json.dump(data, f, indent=2, sort_keys=False)
            f.write("\n")

    _atomic_write(path, write)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Load and check a checkpoint file (or a run folder holding ``checkpoint.pt``) with ``weights_only=True``."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise InputError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several kinds for damaged or foreign files
        from kpd.io.integrity import checkpoint_failure

        raise InputError(f"cannot load checkpoint {path}: {checkpoint_failure(path, exc)}") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise InputError(f"{path} is not a kpd checkpoint (format {CHECKPOINT_FORMAT!r} missing)")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise InputError(f"{path}: checkpoint version {ckpt.get('version')}; this kpd reads {CHECKPOINT_VERSION}")
    from kpd.io.integrity import HASH_KEY, check_hash

    check_hash(ckpt, ckpt.get(HASH_KEY), str(path), "checkpoint")  # a flipped byte is refused, not trained on
    return ckpt
