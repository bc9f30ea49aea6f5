"""kpd.io.atomic: an output appears whole or not at all; the old file stays when the block fails."""

from __future__ import annotations

import os

import pytest
from helpers import sphere_mesh, write_text

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


@pytest.mark.parametrize("suffix, names", [(".ply", ["out.ply"]), (".obj", ["out.mtl", "out.obj", "out_0.png"])])
def test_a_writer_inside_a_command_stage_writes_and_syncs_each_file_once(tmp_path, monkeypatch, suffix, names):
    """write_mesh into an Outputs stage (what every command does) writes each file once, under its final name in
    the staging folder, and the placement fsyncs it once; a failing writer there leaves nothing to place."""
    import numpy as np

    import kpd.io.atomic as atomic
    from kpd.io import Mesh, Outputs

    mesh = sphere_mesh()
    if suffix == ".obj":  # a textured OBJ: its .mtl and map are companions written beside it
        uvs = np.zeros((3 * len(mesh.triangles), 2))
        mesh = Mesh(vertices=mesh.vertices, triangles=mesh.triangles, triangle_uvs=uvs,
                    textures=[np.full((2, 2, 3), 200, dtype=np.uint8)])
    synced = []
    fsync = atomic._fsync

    def recorded(path):
        if path.is_file():
            synced.append(path.name)
        fsync(path)

    monkeypatch.setattr(atomic, "_fsync", recorded)
    with Outputs(force=False) as outputs:
        out = outputs.file(tmp_path / f"out{suffix}", "--out")
        write_mesh(outputs.stage(out), mesh)
    assert sorted(synced) == names == sorted(os.listdir(tmp_path))
    with pytest.raises(RuntimeError, match="boom"):
        with Outputs(force=True) as outputs:
            out = outputs.file(tmp_path / f"out{suffix}", "--out")
            with atomic_output(outputs.stage(out)) as target:
                target.write_bytes(b"half")
                raise RuntimeError("boom")
    assert sorted(os.listdir(tmp_path)) == names
