"""kpd.collection.files: the shapes of a collection folder and the points each is aligned by."""

from __future__ import annotations

import numpy as np
import pytest

from kpd.collection.files import collection_points, find_shapes
from kpd.errors import DataError, InputError
from kpd.io import PointSet, write_mesh, write_points
from kpd.procedural import procedural_chair


def test_find_shapes_files_and_one_file_folders(tmp_path):
    write_points(tmp_path / "b.xyz", np.random.default_rng(0).normal(size=(20, 3)))
    write_mesh(tmp_path / "a.ply", procedural_chair())
    (tmp_path / "shoe").mkdir()
    write_mesh(tmp_path / "shoe" / "model.obj", procedural_chair())
    (tmp_path / "two").mkdir()  # two files: not a shape folder
    write_points(tmp_path / "two" / "x.xyz", np.zeros((12, 3)) + np.arange(12)[:, None])
    write_points(tmp_path / "two" / "y.xyz", np.zeros((12, 3)) + np.arange(12)[:, None])
    (tmp_path / "notes.txt").write_text("not a shape")
    (tmp_path / ".hidden.ply").write_bytes(b"")
    assert [(n, p.relative_to(tmp_path).as_posix()) for n, p in find_shapes(tmp_path)] == [
        ("a", "a.ply"), ("b", "b.xyz"), ("shoe", "shoe/model.obj")]
    write_mesh(tmp_path / "shoe.ply", procedural_chair())
    with pytest.raises(DataError, match="two shapes are named 'shoe'"):
        find_shapes(tmp_path)


def test_find_shapes_refusals(tmp_path):
    with pytest.raises(InputError, match="is not a folder"):
        find_shapes(tmp_path / "missing")
    with pytest.raises(DataError, match="no shapes"):
        find_shapes(tmp_path)


def test_collection_points_of_meshes_and_point_sets():
    chair = procedural_chair()
    points = collection_points(chair, 500, seed=1)
    assert points.shape == (500, 3)
    np.testing.assert_array_equal(points, collection_points(chair, 500, seed=1))  # seeded
    lo, hi = chair.vertices.min(0), chair.vertices.max(0)
    assert (points >= lo - 1e-9).all() and (points <= hi + 1e-9).all()
    cloud = PointSet(np.random.default_rng(2).normal(size=(800, 3)))
    few = collection_points(cloud, 300, seed=0)
    assert few.shape == (300, 3) and len({tuple(p) for p in few.tolist()}) == 300
    assert {tuple(p) for p in few.tolist()} <= {tuple(p) for p in cloud.points.tolist()}  # its own points
    np.testing.assert_array_equal(collection_points(cloud, 5000), cloud.points)  # at most n: all of them
