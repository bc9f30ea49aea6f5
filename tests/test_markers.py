"""kpd.viewer.markers: keypoint markers, line sets, wireframe edges and camera-facing digits."""

import numpy as np

from kpd.viewer.camera import Camera
from kpd.viewer.markers import Digits, Markers, line_set, mesh_edges


def test_mesh_edges_are_each_undirected_edge_once_thinned_to_the_limit():
    triangles = np.array([[0, 1, 2], [2, 1, 3]])  # the edge 1-2 shared
    np.testing.assert_array_equal(mesh_edges(triangles), [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])
    thinned = mesh_edges(triangles, limit=3)
    assert len(thinned) == 3 and {tuple(e) for e in thinned} <= {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)}


def test_markers_are_spheres_of_the_radius_at_the_points_in_their_colours():
    colors = np.array([[1.0, 0, 0], [0, 0, 1.0]])
    markers = Markers(colors, radius=0.5)
    points = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    markers.set(points, scales=np.array([1.0, 2.0]))
    vertices = np.asarray(markers.geometry.vertices).reshape(2, -1, 3)
    np.testing.assert_allclose(np.linalg.norm(vertices[0] - points[0], axis=1), 0.5)
    np.testing.assert_allclose(np.linalg.norm(vertices[1] - points[1], axis=1), 1.0)  # a selected one, larger
    shown = np.asarray(markers.geometry.vertex_colors).reshape(2, -1, 3)
    assert (shown[0] == colors[0]).all() and (shown[1] == colors[1]).all()
    camera = Camera(center=np.zeros(3), eye=np.array([0.0, 0, 5]), up=np.array([0.0, 1, 0]), fov=40.0, near=0.1,
                    far=100.0)
    markers.set(points, camera=camera)  # lit: brighter towards the lights, each in its own hue
    lit = np.asarray(markers.geometry.vertex_colors).reshape(2, -1, 3)
    assert lit[0, :, 0].max() > lit[0, :, 0].min() and np.abs(lit[0, :, 1:]).max() == 0


def test_a_line_set_joins_the_points_by_the_edges_in_one_colour():
    lines = line_set(np.eye(3), np.array([[0, 1], [1, 2]]), (0.2, 0.4, 0.6))
    np.testing.assert_array_equal(np.asarray(lines.lines), [[0, 1], [1, 2]])
    np.testing.assert_allclose(np.asarray(lines.colors), [[0.2, 0.4, 0.6]] * 2)


def test_digits_face_the_camera_at_their_anchors():
    digits = Digits(np.array([[1.0, 0, 0]] * 11), height=0.7)  # numbers 0 to 10
    camera = Camera(center=np.zeros(3), eye=np.array([0.0, 0, 5]), up=np.array([0.0, 1, 0]), fov=40.0, near=0.1,
                    far=100.0)
    anchors = np.arange(33, dtype=np.float64).reshape(11, 3)
    digits.set(anchors, camera)
    vertices = np.asarray(digits.geometry.vertices)
    normals = np.asarray(digits.geometry.vertex_normals)
    np.testing.assert_allclose(normals, np.tile([0.0, 0, 1], (len(normals), 1)))  # towards the camera
    assert len(digits.geometry.triangles) == len(vertices) // 2  # two triangles a quad
    ink = vertices[:4 * len(digits._cells)].reshape(-1, 4, 3)  # each glyph cell near its label's anchor
    label = digits._cells[:, 0].astype(int)
    assert (np.linalg.norm(ink.mean(axis=1) - anchors[label], axis=1) < 4 * 0.7).all()
