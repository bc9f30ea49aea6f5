"""kpd.triangles: cross products, areas, normals and vertex normals against hand-computed values."""

import numpy as np

from kpd.triangles import areas, cross, turned_normals, unit_normals, vertex_normals

# a unit right triangle in the xy plane and a degenerate one (all corners on a line)
V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]])
T = np.array([[0, 1, 2], [1, 3, 4]])


def test_cross_areas_and_unit_normals():
    np.testing.assert_array_equal(cross(V, T), [[0, 0, 1], [0, 0, 0]])
    np.testing.assert_array_equal(areas(V, T), [0.5, 0.0])
    np.testing.assert_array_equal(unit_normals(V, T), [[0, 0, 1], [0, 0, 0]])
    np.testing.assert_array_equal(unit_normals(V, T[:, ::-1]), [[0, 0, -1], [0, 0, 0]])


def test_vertex_normals_area_weighted_and_grouped():
    # a tent: two triangles meeting at the ridge x = 0, one twice the other's area
    v = np.array([[0.0, 0, 1], [0, 1, 1], [1, 0, 0], [-2, 0, 0], [0, 1, 1], [0, 0, 1]])
    t = np.array([[0, 2, 1], [5, 4, 3]])
    n = vertex_normals(v, t)
    expected0 = np.array([1.0, 0, 1]) / np.sqrt(2)
    np.testing.assert_allclose(n[0], expected0)
    np.testing.assert_allclose(n[3], [-1 / np.sqrt(5), 0, 2 / np.sqrt(5)])
    # grouped: the ridge copies (0 and 5, 1 and 4) share the area-weighted sum of both faces
    groups = np.array([0, 1, 2, 3, 1, 0])
    g = vertex_normals(v, t, groups)
    both = np.cross(v[2] - v[0], v[1] - v[0]) + np.cross(v[4] - v[5], v[3] - v[5])
    np.testing.assert_allclose(g[0], both / np.linalg.norm(both))
    np.testing.assert_array_equal(g[0], g[5])
    assert np.isclose(np.linalg.norm(g, axis=1), 1).all()
    # an unused vertex has no normal
    assert not vertex_normals(np.vstack([v, [[9, 9, 9]]]), t)[-1].any()


def test_turned_normals_keep_an_artists_offset_from_the_surface():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    triangles = np.array([[0, 1, 2]])
    tilted = np.array([[0.0, np.sin(0.3), np.cos(0.3)]])  # 0.3 rad off the face normal (+z)
    new = vertices[:, [2, 1, 0]] * [1, 1, -1]  # the face turned to face +x
    turned = turned_normals(vertices, new, triangles, np.zeros((1, 3), np.int64), tilted)
    np.testing.assert_allclose(turned[0] @ [1.0, 0, 0], np.cos(0.3), atol=1e-12)  # still 0.3 rad off the face
