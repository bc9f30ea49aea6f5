"""kpd.io.atomic: an output appears whole or not at all; the old file stays when the block fails."""

from __future__ import annotations

import os

import pytest
from test_io import sphere_mesh, write_text

from kpd.errors import InputError, KpdError
from kpd.io import atomic_output, write_mesh


def test_atomic_output_keeps_the_old_file_when_the_block_raises(tmp_path):
    path = write_text(tmp_path / "result.json", "old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_output(path) as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".json" and tmp != path
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["result.json"]


def test_atomic_output_replaces_on_success(tmp_path):
    path = write_text(tmp_path / "result.json", "old")
    with atomic_output(path) as tmp:
        tmp.write_text("new")
        assert path.read_text() == "old"
    assert path.read_text() == "new" and os.listdir(tmp_path) == ["result.json"]


def test_atomic_output_errors(tmp_path):
    with pytest.raises(KpdError, match="nothing was written"):
        with atomic_output(tmp_path / "never.json"):
            pass
    with pytest.raises(InputError, match="does not exist"):
        with atomic_output(tmp_path / "missing" / "x.json"):
            pass
    with pytest.raises(InputError, match="does not exist"):
        write_mesh(tmp_path / "missing" / "x.obj", sphere_mesh())
    assert os.listdir(tmp_path) == []
