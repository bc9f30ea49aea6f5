"""kpd.triangles: cross products, areas, normals and vertex normals against hand-computed values."""

import numpy as np
import pytest

from kpd.triangles import _face_sums, areas, cross, turned_normals, unit_normals, vertex_normals

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


def face_sums_reference(vertices, triangles, slots, n):
    """``np.bincount`` of the corners' slots weighted by their triangles' cross products (the former formula)."""
    face = cross(vertices, triangles)  # (T, 3)
    used = slots >= 0
    weights = np.repeat(face[:, None, :], 3, axis=1)[used]  # (c, 3), corners in order
    return np.stack([np.bincount(slots[used], weights=weights[:, k], minlength=n) for k in range(3)],
                    axis=1).astype(np.float64)


@pytest.mark.parametrize("dtype", [np.int32, np.int64])
def test_face_sums_equal_the_bincount_of_the_corners(dtype):
    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(500, 3)) * 10.0 ** rng.integers(-3, 3, (500, 1))
    triangles = rng.integers(0, 500, (3000, 3)).astype(dtype)
    triangles[:10, 1] = triangles[:10, 0]  # degenerate triangles add zero
    slots = rng.integers(-1, 200, (3000, 3))
    np.testing.assert_array_equal(_face_sums(vertices, triangles, slots, 200),
                                  face_sums_reference(vertices, triangles, slots, 200))


def test_vertex_normals_with_and_without_groups_are_the_summed_unit_normals():
    rng = np.random.default_rng(2)
    vertices = rng.normal(size=(300, 3))
    triangles = rng.integers(0, 300, (1000, 3))
    groups = rng.integers(0, 120, 300)
    for g, n in ((None, 300), (groups, 120)):
        slots = triangles if g is None else g[triangles]
        summed = face_sums_reference(vertices, triangles, slots, n)
        length = np.linalg.norm(summed, axis=1, keepdims=True)
        want = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
        np.testing.assert_array_equal(vertex_normals(vertices, triangles, g), want if g is None else want[g])
