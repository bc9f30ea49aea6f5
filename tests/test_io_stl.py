"""kpd.io.stl: STL's unshared corners are welded back into one vertex per position."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from kpd.io import read_mesh, stl, write_mesh
from kpd.mesh import Mesh


def test_weld_merges_equal_positions_and_keeps_the_triangles():
    soup = o3d.geometry.TriangleMesh()
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)  # two triangles
    soup.vertices = o3d.utility.Vector3dVector(corners)
    soup.triangles = o3d.utility.Vector3iVector(np.arange(6).reshape(2, 3))
    welded = stl.weld(soup)
    v, t = np.asarray(welded.vertices), np.asarray(welded.triangles)
    assert len(v) == 4
    np.testing.assert_array_equal(v[t], corners.reshape(2, 3, 3))  # every triangle where it was


def test_stl_file_round_trip_is_welded(tmp_path):
    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij"), -1).reshape(-1, 2)
    vertices = np.c_[grid, np.zeros(16)]
    quads = [(i * 4 + j, i * 4 + j + 4, i * 4 + j + 5, i * 4 + j + 1) for i in range(3) for j in range(3)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    write_mesh(tmp_path / "g.stl", Mesh(vertices, triangles))
    back = read_mesh(tmp_path / "g.stl")
    assert len(back.vertices) == 16 and len(back.triangles) == 18  # not 3 corners per triangle
    np.testing.assert_allclose(back.vertices[back.triangles], vertices[triangles], atol=1e-6)
