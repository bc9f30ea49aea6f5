"""kpd.scan.shapes: the three kinds of shape scan preprocessing takes keep their type and their attributes when
restricted or moved."""

from __future__ import annotations

import numpy as np

from kpd.mesh import Mesh, PointSet
from kpd.scan.shapes import _shape_points, _take_points, _take_triangles, _with_points


def test_points_of_every_kind_and_restriction_of_point_sets():
    points = np.random.default_rng(0).normal(size=(12, 3))
    cloud = PointSet(points, normals=np.tile([0.0, 0, 1], (12, 1)), colors=np.full((12, 3), 0.5))
    for shape in (points, cloud, Mesh(points, np.array([[0, 1, 2]]))):
        np.testing.assert_array_equal(_shape_points(shape), points)
    keep = np.arange(12) % 3 == 0
    np.testing.assert_array_equal(_take_points(points, keep), points[keep])
    part = _take_points(cloud, keep)
    assert isinstance(part, PointSet) and len(part) == 4 and part.colors.shape == (4, 3)


def test_take_triangles_drops_unreferenced_vertices_and_keeps_uvs():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [5, 5, 5]])
    triangles = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4]])
    uvs = np.arange(18, dtype=float).reshape(9, 2) / 18
    mesh = Mesh(vertices, triangles, vertex_colors=np.eye(5, 3), triangle_uvs=uvs)
    part = _take_triangles(mesh, np.array([True, True, False]))
    assert len(part.vertices) == 4 and part.triangles.max() == 3  # vertex 4 gone
    np.testing.assert_array_equal(part.vertices[part.triangles], vertices[triangles[:2]])
    np.testing.assert_array_equal(part.triangle_uvs, uvs[:6])
    np.testing.assert_array_equal(part.vertex_colors, np.eye(5, 3)[:4])


def test_with_points_turns_point_normals_by_the_inverse_transpose():
    cloud = PointSet(np.zeros((2, 3)) + [[0, 0, 0], [1, 1, 0]], normals=[[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    stretch = np.diag([2.0, 1.0, 1.0])  # x doubled: a surface's normal tilts towards y
    moved = _with_points(cloud, cloud.points @ stretch.T, stretch)
    np.testing.assert_allclose(moved.normals[0], np.array([0.5, 1.0, 0.0]) / np.linalg.norm([0.5, 1.0, 0.0]))
    np.testing.assert_allclose(moved.normals[1], [0, 0, 1])
    np.testing.assert_array_equal(moved.points, cloud.points @ stretch.T)
