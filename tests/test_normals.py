"""kpd.viewer.normals: shading normals turned towards the camera, welded by position, and their two-thread twin."""

import numpy as np


def test_shading_normals_turn_double_sided_triangles_towards_the_camera():
    from kpd.viewer.normals import shading_normals

    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    both = np.array([[0, 1, 2], [0, 2, 1]])  # the same triangle in both windings
    assert np.allclose(shading_normals(vertices, both, None), 0)  # by winding they cancel (black and white blotches)
    np.testing.assert_allclose(shading_normals(vertices, both, np.array([0.2, 0.2, 5.0])), np.tile([0, 0, 1.0], (3, 1)))
    np.testing.assert_allclose(shading_normals(vertices, both, np.array([0.2, 0.2, -5.0])),
                               np.tile([0, 0, -1.0], (3, 1)))
    unwelded = np.vstack([vertices, vertices[[1, 2]] + [0, 0, 0]])  # copies of two corners at the same places
    tris = np.array([[0, 1, 2], [3, 4, 0]])
    normals = shading_normals(unwelded, tris, np.array([0.0, 0, 3.0]))
    np.testing.assert_allclose(normals[1], normals[3])  # welded: the copies shade alike


def test_prepared_normals_are_the_serial_kernels_bit_for_bit():
    from kpd.viewer.normals import ShadingNormals, Welding, shading_normals

    rng = np.random.default_rng(4)
    vertices = rng.normal(size=(400, 3))
    vertices[300:] = vertices[:100]  # copies of a position (a UV seam) share its normal
    triangles = rng.integers(0, 400, size=(3000, 3))
    welding = Welding(vertices)
    for eye in (None, np.array([0.5, -4.0, 2.0])):
        expected = shading_normals(vertices, triangles, eye, welding=welding)
        groups = ShadingNormals(triangles, welding)(vertices, eye)  # (G, 3), two threads when large
        np.testing.assert_array_equal(groups[welding.inverse], expected)
    big = rng.integers(0, 400, size=(250_000, 3))  # past the size split over two threads
    np.testing.assert_array_equal(ShadingNormals(big, welding)(vertices, np.ones(3))[welding.inverse],
                                  shading_normals(vertices, big, np.ones(3), welding=welding))
