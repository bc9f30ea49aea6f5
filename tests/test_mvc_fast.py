import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from test_mvc import points_near_the_cage

from kpd.cage import icosphere
from kpd.errors import InputError
from kpd.mvc import mvc_weights, mvc_weights_reference
from kpd.mvc_fast import mvc_project, mvc_weights_compiled, theta_over

TEMPLATE = icosphere(1)


def star_cage(radii):
    """The level-1 icosphere with each vertex moved along its ray to radius ``radii[j]``."""
    return TEMPLATE.vertices / 1.4 * np.asarray(radii, dtype=float)[:, None], TEMPLATE.faces


def awkward_points(v, f, rng, distance):
    """Points at ``distance`` from the cage's vertices, edges and faces, and exactly on them."""
    return points_near_the_cage(v, f, rng, distance, 60, exact=True)


def test_the_kernels_angle_over_length_is_atan2_over_y_to_rounding():
    rng = np.random.default_rng(0)
    y = np.abs(rng.normal(size=20_000)) * 10.0 ** rng.uniform(-12, 12, 20_000) + 1e-300
    x = rng.normal(size=20_000) * 10.0 ** rng.uniform(-12, 12, 20_000)
    y = np.concatenate([y, [1.0, 1.0, 1.0, 1.0, 1.0, 1e-9, 1e-9]])
    x = np.concatenate([x, [0.0, 1.0, -1.0, 1.0 / 0.66, -1.0 / 0.66, 1.0, -1.0]])  # the octants' and reduction's edges
    np.testing.assert_allclose(theta_over(y, x), np.arctan2(y, x) / y, rtol=1e-15, atol=0)


@pytest.mark.parametrize("distance", [0.0, 1e-13, 1e-10, 1e-7, 1e-4, 1e-2])
def test_compiled_weights_equal_the_numpy_kernel_on_and_near_the_cage(distance):
    rng = np.random.default_rng(int(distance * 1e13) % 1000)
    v, f = star_cage(rng.uniform(0.5, 1.5, 42))
    x = np.concatenate([awkward_points(v, f, rng, distance), rng.uniform(-2.0, 2.0, (300, 3))])
    compiled = mvc_weights_compiled(x, v, f)
    np.testing.assert_allclose(compiled, mvc_weights(x, v, f), rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled @ v, x, rtol=0, atol=1e-10)


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, 42, elements=st.floats(0.3, 1.6)), arrays(np.float64, (40, 3), elements=st.floats(-2, 2)))
def test_compiled_weights_equal_the_numpy_kernel_in_random_star_cages(radii, points):
    v, f = star_cage(radii)
    # both kernels round differently, and outside the cage their rounding grows like (distance / cage size)^2
    scale = np.linalg.norm(v - v.mean(axis=0), axis=1).max()
    tolerance = 2e-11 * (1.0 + (np.linalg.norm(points - v.mean(axis=0), axis=1) / scale) ** 2)  # (N,)
    difference = np.abs(mvc_weights_compiled(points, v, f) - mvc_weights(points, v, f)).max(axis=1)
    assert (difference <= tolerance).all(), (difference / tolerance).max()


def test_compiled_weights_match_the_reference_inside_and_outside():
    rng = np.random.default_rng(3)
    v, f = star_cage(rng.uniform(0.6, 1.4, 42))
    direction = rng.normal(size=(200, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    x = direction * np.concatenate([rng.uniform(0.0, 0.4, 120), rng.uniform(2.0, 4.0, 80)])[:, None]
    x = np.concatenate([x, v[:4]])  # and exactly on vertices
    np.testing.assert_allclose(mvc_weights_compiled(x, v, f), mvc_weights_reference(x, v, f), rtol=0, atol=1e-10)


def test_projection_equals_the_weights_times_the_rows_for_any_thread_count():
    v, f = icosphere(2, 1.4)
    rng = np.random.default_rng(4)
    x = rng.uniform(-1.3, 1.3, (9000, 3))  # more than a block per thread, a short last block
    x[:3] = v[:3]  # rows that go through the careful path
    rows = rng.normal(size=(len(v), 12))
    one = mvc_project(x, v, f, rows, threads=1)
    assert one.shape == (9000, 12) and one.dtype == np.float64
    np.testing.assert_array_equal(mvc_project(x, v, f, rows, threads=2), one)
    np.testing.assert_allclose(one, mvc_weights(x, v, f) @ rows, rtol=0, atol=1e-10)
    out = np.empty((9000, 12))
    assert mvc_project(x, v, f, rows, out=out) is out
    assert mvc_project(np.zeros((0, 3)), v, f, rows).shape == (0, 12)


def test_projection_rejects_bad_rows_and_buffers():
    v, f = TEMPLATE
    x = np.zeros((5, 3))
    with pytest.raises(InputError, match=r"rows must be \(C, R\) = \(42, R\)"):
        mvc_project(x, v, f, np.ones((41, 3)))
    with pytest.raises(InputError, match="rows must be"):
        mvc_project(x, v, f, np.full((42, 3), np.nan))
    with pytest.raises(InputError, match=r"out must be a C-contiguous \(N, R\) = \(5, 3\)"):
        mvc_project(x, v, f, np.ones((42, 3)), out=np.empty((5, 3), dtype=np.float32))
    with pytest.raises(InputError, match="threads"):
        mvc_project(x, v, f, np.ones((42, 3)), threads=0)
