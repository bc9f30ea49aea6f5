"""kpd.train.checkpoint: only a kpd checkpoint of this version with an intact content hash is loaded."""

from __future__ import annotations

import pytest
import torch

from kpd.errors import InputError
from kpd.io.integrity import HASH_KEY, content_hash
from kpd.train.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_NAME, CHECKPOINT_VERSION, load_checkpoint


def _checkpoint(**changes) -> dict:
    ckpt = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "iteration": 3,
            "states": {"w": torch.arange(6.0).reshape(2, 3)}}
    ckpt.update(changes)
    ckpt[HASH_KEY] = content_hash({k: v for k, v in ckpt.items() if k != HASH_KEY})
    return ckpt


def test_a_checkpoint_loads_from_its_file_or_its_run_folder(tmp_path):
    torch.save(_checkpoint(), tmp_path / CHECKPOINT_NAME)
    for path in (tmp_path / CHECKPOINT_NAME, tmp_path):
        ckpt = load_checkpoint(path)
        assert ckpt["iteration"] == 3 and torch.equal(ckpt["states"]["w"], torch.arange(6.0).reshape(2, 3))


def test_refusals_name_the_problem(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    with pytest.raises(InputError, match=f"{CHECKPOINT_NAME} does not exist"):
        load_checkpoint(tmp_path)  # a folder without one
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(2)}, foreign)
    with pytest.raises(InputError, match="is not a kpd checkpoint"):
        load_checkpoint(foreign)
    newer = tmp_path / "newer.pt"
    torch.save(_checkpoint(version=CHECKPOINT_VERSION + 1), newer)
    with pytest.raises(InputError, match=f"checkpoint version {CHECKPOINT_VERSION + 1}"):
        load_checkpoint(newer)
    tampered = _checkpoint()
    tampered["states"]["w"][0, 0] = 99.0  # changed after the hash was taken
    path = tmp_path / "tampered.pt"
    torch.save(tampered, path)
    with pytest.raises(InputError):
        load_checkpoint(path)
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint\n")
    with pytest.raises(InputError, match="cannot load checkpoint"):
        load_checkpoint(text)
