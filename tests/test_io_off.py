"""kpd.io.off's writer: what Open3D's OFF writer writes (header, colours, faces) with 9 significant digits instead of
6; read back by kpd and by Open3D to the mesh within float32, the precision Open3D's OFF reader holds; written
atomically, and a file that stops early is caught."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest

from kpd.errors import InputError, WriteError
from kpd.io import Mesh, read_mesh, text, write_mesh


def grid_mesh(normals: bool, colors: bool, n: int = 12, seed: int = 0) -> Mesh:
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(0, 3, n))
    vertices = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x).ravel()], axis=1) * 10.0 ** rng.integers(-3, 3)
    vertices = vertices + rng.standard_normal(vertices.shape) * 1e-4
    quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j)
             for i in range(n - 1) for j in range(n - 1)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    vn = rng.standard_normal(vertices.shape)
    return Mesh(vertices, triangles, vertex_normals=vn / np.linalg.norm(vn, axis=1, keepdims=True) if normals else None,
                vertex_colors=rng.random(vertices.shape) if colors else None)


def open3d_written(mesh: Mesh, path) -> list[str]:
    import open3d as o3d

    assert o3d.io.write_triangle_mesh(str(path), mesh.to_open3d())
    return path.read_text().splitlines()


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("colors", [False, True])
def test_what_open3d_writes_with_nine_digits(tmp_path, normals, colors):
    mesh = grid_mesh(normals, colors)
    write_mesh(tmp_path / "kpd.off", mesh)
    ours = (tmp_path / "kpd.off").read_text().splitlines()
    theirs = open3d_written(mesh, tmp_path / "open3d.off")
    V, T = len(mesh.vertices), len(mesh.triangles)
    assert ours[0] == theirs[0] == ("C" if colors else "") + ("N" if normals else "") + "OFF"
    assert ours[1] == theirs[1] == f"{V} {T} 0"
    assert len(ours) == len(theirs) == 2 + V + T
    assert ours[2 + V:] == theirs[2 + V:]  # faces: "3 a b c"
    floats = [mesh.vertices] + ([mesh.vertex_normals] if normals else [])
    rows = [line.split() for line in ours[2 : 2 + V]]
    expected = text.float_rows_reference(np.hstack(floats), 9, suffix=b"")
    assert [" ".join(r[: 3 * len(floats)]).encode() for r in rows] == expected
    a = np.array([line.split() for line in theirs[2 : 2 + V]], dtype=float)
    b = np.array(rows, dtype=float)
    np.testing.assert_allclose(b[:, : 3 * len(floats)], a[:, : 3 * len(floats)], rtol=5e-6, atol=1e-300)
    np.testing.assert_array_equal(b[:, 3 * len(floats):], a[:, 3 * len(floats):])  # colours: r g b 255


def test_colours_round_half_away_from_zero_as_open3d(tmp_path):
    mesh = grid_mesh(False, True, n=8)
    halves = (np.arange(len(mesh.vertices) * 3) % 255 + 0.5) / 255  # k + 1/2 once scaled, as near as float64 goes
    colors = np.concatenate([[0.3, 0.5, 1 / 510, 0.7, 1.0, 0.0], halves])[: len(mesh.vertices) * 3].reshape(-1, 3)
    mesh = Mesh(mesh.vertices, mesh.triangles, vertex_colors=colors)
    write_mesh(tmp_path / "kpd.off", mesh)
    ours = (tmp_path / "kpd.off").read_text().splitlines()
    theirs = open3d_written(mesh, tmp_path / "open3d.off")
    assert [line.split()[3:] for line in ours[2:]] == [line.split()[3:] for line in theirs[2:]]
    assert ours[2].split()[3:] == ["77", "128", "1", "255"]
    signed = Mesh(mesh.vertices, mesh.triangles, vertex_colors=np.where(colors == 0, -0.0, colors))
    write_mesh(tmp_path / "signed.off", signed)  # a colour of -0.0 (Open3D writes "-0") is written 0
    assert (tmp_path / "signed.off").read_text() == "\n".join(ours) + "\n"


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("colors", [False, True])
def test_read_back_by_kpd_and_open3d_within_float32(tmp_path, normals, colors):
    import open3d as o3d

    mesh = grid_mesh(normals, colors, seed=3)
    f32 = Mesh(mesh.vertices.astype(np.float32).astype(np.float64), mesh.triangles,
               vertex_normals=mesh.vertex_normals, vertex_colors=mesh.vertex_colors)
    for m, name in ((mesh, "a.off"), (f32, "b.off")):
        write_mesh(tmp_path / name, m)
        back = read_mesh(tmp_path / name)
        o3d_back = o3d.io.read_triangle_mesh(str(tmp_path / name))
        np.testing.assert_array_equal(np.asarray(o3d_back.vertices), back.vertices)
        np.testing.assert_array_equal(back.triangles, m.triangles)
        if m is f32:  # a float32 coordinate comes back to the bit
            np.testing.assert_array_equal(back.vertices, m.vertices)
        spacing = np.spacing(np.abs(m.vertices).astype(np.float32)).astype(np.float64)
        assert (np.abs(back.vertices - m.vertices) <= spacing).all()
        if normals:
            np.testing.assert_allclose(back.vertex_normals, m.vertex_normals, atol=1e-7)
        else:
            assert back.vertex_normals is None
        if colors:
            scaled = m.vertex_colors * 255
            np.testing.assert_array_equal(np.round(back.vertex_colors * 255), np.floor(scaled + 0.5))
        else:
            assert back.vertex_colors is None


def test_real_meshes_round_trip(data_dir, tmp_path):
    for name in ("scans/sneaker.ply", "scans/ycb/banana/textured_simple_reoriented.obj"):
        mesh = read_mesh(data_dir / name)
        mesh = Mesh(mesh.vertices, mesh.triangles, vertex_normals=mesh.vertex_normals)
        out = tmp_path / (os.path.basename(name) + ".off")
        write_mesh(out, mesh)
        back = read_mesh(out)
        np.testing.assert_array_equal(back.triangles, mesh.triangles)
        spacing = np.spacing(np.abs(mesh.vertices).astype(np.float32)).astype(np.float64)
        assert (np.abs(back.vertices - mesh.vertices) <= spacing).all(), name
        if mesh.vertices.astype(np.float32).astype(np.float64).tolist() == mesh.vertices.tolist():
            np.testing.assert_array_equal(back.vertices, mesh.vertices)  # the sneaker scan's float32 coordinates


def test_textures_are_dropped_with_a_warning(tmp_path, caplog):
    mesh = grid_mesh(True, False, n=4)
    T = len(mesh.triangles)
    textured = Mesh(mesh.vertices, mesh.triangles, triangle_uvs=np.zeros((3 * T, 2)),
                    textures=[np.zeros((2, 2, 3), np.uint8)])
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        write_mesh(tmp_path / "t.off", textured)
    assert "cannot store UVs and textures" in caplog.text
    assert (tmp_path / "t.off").read_text().startswith("OFF\n16 18 0\n")


def test_truncated_file_is_caught(tmp_path, monkeypatch):
    mesh = grid_mesh(True, True)
    write_mesh(tmp_path / "whole.off", mesh)
    data = (tmp_path / "whole.off").read_bytes()
    (tmp_path / "cut.off").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.off: the file is truncated"):
        read_mesh(tmp_path / "cut.off")

    def stops_early(fh, corners, **options):  # a writer that stops halfway through the faces
        fh.write(text.index_rows(corners[: len(corners) // 2], **options))

    monkeypatch.setattr(text, "write_index_rows", stops_early)
    with pytest.raises(WriteError, match=r"cannot write .*early\.off: the written file is incomplete"):
        write_mesh(tmp_path / "early.off", mesh)
    assert sorted(os.listdir(tmp_path)) == ["cut.off", "whole.off"]
