"""The edit basis: computed once per distinct position, kept in float32 only where edits stay exact, applied by the
edit kernel."""

import numpy as np
import pytest

from kpd.basis import coincident_mvc_basis, coincident_mvc_weights, compact_basis, distinct_points, edit
from kpd.geometry import Normalizer
from kpd.io import read_mesh
from kpd.rig import Rig
from kpd.straighten import straighten_basis
from rig_shapes import fps_rig


def test_coincident_mvc_weights_equal_the_weights_of_every_vertex(data_dir):
    """ModelNet10 chair_0956 stores about four vertices per position: the weights computed once per position are
    the weights of every vertex, bit for bit, and the distinct positions are the mesh's."""
    from kpd.cage import fit_cage
    from kpd.mvc import mvc_weights

    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply")
    vertices = Normalizer().fit(mesh.vertices).apply(mesh.vertices)
    points = distinct_points(vertices)
    assert len(points) < len(vertices) / 3
    assert np.array_equal(np.unique(vertices, axis=0), points)
    cage = fit_cage(points, enclose=True)
    np.testing.assert_array_equal(coincident_mvc_weights(vertices, cage),
                                  mvc_weights(vertices, cage.vertices, cage.faces))


def test_coincident_mvc_basis_is_the_weights_times_the_rows(data_dir):
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply")  # ~4 vertices per position
    rig = fps_rig(mesh, straighten=False)
    vertices = rig.normalizer.apply(mesh.vertices)
    expected = coincident_mvc_weights(vertices, rig.cage) @ rig.influence.T
    np.testing.assert_allclose(coincident_mvc_basis(vertices, rig.cage, rig.influence.T), expected, rtol=0,
                               atol=1e-11)
    np.testing.assert_allclose(rig.weights, coincident_mvc_weights(vertices, rig.cage), rtol=0, atol=1e-11)


def test_float32_basis_only_where_edits_stay_within_1e6_of_the_diagonal(data_dir):
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")
    rig = fps_rig(mesh)
    assert rig.basis.dtype == np.float32
    vertices = rig.normalizer.apply(mesh.vertices)
    exact = straighten_basis(coincident_mvc_basis(vertices, rig.cage, rig.influence.T), vertices, mesh.triangles)
    full = Rig(mesh, rig.normalizer, rig.normalizer.apply(rig.keypoints), rig.cage, rig.influence, basis=exact)
    assert full.basis.dtype == np.float64
    diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    rng = np.random.default_rng(1)
    for _ in range(4):  # every keypoint moved by a whole diagonal
        direction = rng.normal(size=(rig.num_keypoints, 3))
        keypoints = rig.keypoints + diagonal * direction / np.linalg.norm(direction, axis=1, keepdims=True)
        assert np.abs(rig.deform(keypoints) - full.deform(keypoints)).max() <= 1e-6 * diagonal
    wide = np.full((4, 3), 6.0)  # rows summing to 18: float32 could move a vertex by more than 1e-6
    assert compact_basis(wide).dtype == np.float64
    assert compact_basis(wide / 6.0).dtype == np.float32


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("count", [0, 1, 255, 256, 257, 1000])
def test_an_edit_writes_every_vertex_as_the_sum_in_keypoint_order(dtype, count):
    # edit writes its output with non-temporal stores, a block of 256 vertices at a time: every row written, each
    # the rest position plus the moved keypoints' terms in keypoint order, rounded as numpy rounds them
    rng = np.random.default_rng(count)
    k = 5
    basis_t = rng.normal(size=(k, count)).astype(dtype)
    rest = rng.normal(size=(count, 3)) * 100
    for moved in ([], [3], [0, 2, 4], list(range(k))):
        offsets = np.zeros((k, 3))
        offsets[moved] = rng.normal(size=(len(moved), 3))
        expected = rest.copy()
        for j in moved:
            expected += basis_t[j].astype(np.float64)[:, None] * offsets[j]
        out = np.full((count, 3), np.nan)
        edit(basis_t, offsets, rest, out)
        np.testing.assert_array_equal(out, expected)
