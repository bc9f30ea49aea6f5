import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from helpers import points_near_the_cage, star_cage

from kpd.cage import icosphere
from kpd.errors import InputError
from kpd.mvc import _careful_row, _prepare, mvc_weights, mvc_weights_reference
from kpd.mvc_fast import _careful_rows, mvc_project, mvc_weights_compiled, theta_over

TEMPLATE = icosphere(1)


def awkward_points(v, f, rng, distance):
    """Points at ``distance`` from the cage's vertices, edges and faces, and exactly on them."""
    return points_near_the_cage(v, f, rng, distance, 60, exact=True)


def test_the_kernels_angle_over_length_is_atan2_over_y_to_rounding():
    rng = np.random.default_rng(0)
    y = np.abs(rng.normal(size=20_000)) * 10.0 ** rng.uniform(-12, 12, 20_000) + 1e-300
    x = rng.normal(size=20_000) * 10.0 ** rng.uniform(-12, 12, 20_000)
    size = 10.0 ** rng.uniform(-60, 60, 20_000)
    narrow = rng.uniform(0.0, 1.0, 20_000) * size  # angles up to π/4 (over x = size): the narrow way
    small = np.tan(np.pi / 8)
    # the octants' and reductions' edges; pairs of narrow angles up to π/4 (both ends) and mixed pairs
    y = np.concatenate([y, [1.0, 1.0, 1.0, 1.0, 1.0, 1e-9, 1e-9, small, small, 1.0, 1.0, 1.0, 0.5], narrow])
    x = np.concatenate([x, [0.0, 1.0, -1.0, 1.0 / small, -1.0 / small, 1.0, -1.0, 1.0, -1.0, 1.0, 1.0, 3.0, -1.0],
                        size])
    np.testing.assert_allclose(theta_over(y, x), np.arctan2(y, x) / y, rtol=1e-15, atol=0)


@pytest.mark.parametrize("distance", [0.0, 1e-13, 1e-10, 1e-7, 1e-4, 1e-2])
def test_compiled_weights_equal_the_numpy_kernel_on_and_near_the_cage(distance):
    rng = np.random.default_rng(int(distance * 1e13) % 1000)
    v, f = star_cage(rng.uniform(0.5, 1.5, 42))
    x = np.concatenate([awkward_points(v, f, rng, distance), rng.uniform(-2.0, 2.0, (300, 3))])
    compiled = mvc_weights_compiled(x, v, f)
    np.testing.assert_allclose(compiled, mvc_weights(x, v, f), rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled @ v, x, rtol=0, atol=1e-10)


@pytest.mark.parametrize("distance", [0.0, 1e-13, 1e-10, 1e-7])
def test_compiled_careful_rows_are_the_numpy_careful_rows(distance):
    rng = np.random.default_rng(int(distance * 1e13) % 1000 + 7)
    v, f = star_cage(rng.uniform(0.5, 1.5, 42))
    x, t = _prepare(awkward_points(v, f, rng, distance), v, f)  # on and near vertices, edges, faces and planes
    rows = rng.normal(size=(t.C, 5))
    out = np.full((len(x) + 2, 5), 7.0)
    index = np.arange(len(x)) + 1  # rows of out
    failed = _careful_rows(np.concatenate([x[:1], x, x[:1]]), index, t.vertices, t.faces, t.n2, t.n2_norm, t.offset,
                           t.scale, rows, out)
    assert failed == -1
    expected = np.stack([_careful_row(t, p) for p in x]) @ rows
    np.testing.assert_allclose(out[1:-1], expected, rtol=0, atol=1e-14)  # the same sums, the same arctangent
    assert (out[[0, -1]] == 7.0).all()  # only the rows asked for


def extended_weights(points, v, f):
    """The kernels' formula (w_k = G_k . m / D per face, normalised) in numpy's extended precision (long double): the
    weights to ~1e-18 where the formula holds, away from the faces' planes."""
    p = np.asarray(v, np.longdouble)[f][None] - np.asarray(points, np.longdouble)[:, None, None, :]  # (N, F, 3, 3)
    g = np.stack([np.cross(p[:, :, (k + 1) % 3], p[:, :, (k + 2) % 3]) for k in range(3)], axis=2)  # (N, F, 3, 3)
    length = np.sqrt((g * g).sum(axis=-1))  # (N, F, 3)
    dots = np.stack([(p[:, :, (k + 1) % 3] * p[:, :, (k + 2) % 3]).sum(axis=-1) for k in range(3)], axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):  # 0 / 0 on a face's plane, where the formula fails
        m = (np.arctan2(length, dots) / length)[..., None] * g  # (N, F, 3, 3)
        w = (g * m.sum(axis=2)[:, :, None, :]).sum(axis=-1) / (p[:, :, 0] * g[:, :, 0]).sum(axis=-1)[..., None]
    out = np.zeros((len(points), len(v)), np.longdouble)
    for k in range(3):
        np.add.at(out, (slice(None), f[:, k]), w[:, :, k])
    with np.errstate(invalid="ignore"):
        return (out / out.sum(axis=1, keepdims=True)).astype(np.float64)


def test_extended_weights_are_the_numpy_kernels_where_that_is_accurate():
    v, f = star_cage(np.random.default_rng(5).uniform(0.6, 1.4, 42))
    x = np.random.default_rng(6).uniform(-0.3, 0.3, (50, 3))
    np.testing.assert_allclose(extended_weights(x, v, f), mvc_weights(x, v, f), rtol=0, atol=1e-14)


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, 42, elements=st.floats(0.3, 1.6)), arrays(np.float64, (40, 3), elements=st.floats(-2, 2)))
def test_compiled_weights_equal_the_numpy_kernel_in_random_star_cages(radii, points):
    v, f = star_cage(radii)
    # Both kernels round differently. Outside the cage their rounding grows like (distance / cage size)^2, and more
    # near a face's plane beyond the careful zone and far outside a spiky cage: there the numpy kernel errs by 3e-9
    # against the exact weights as often as not (1e-10 at one point, 5e-9 a hair away), and so does the compiled one.
    # So the tolerance adds the numpy kernel's own error against the extended precision weights, the largest over
    # the point and eight others within 1e-12 of it (the old constant alone failed for the previous compiled kernel
    # too, 23 points in 12,000 with spiky cages). In the careful zone both kernels apply the same careful rules.
    centre = v.mean(axis=0)
    scale = np.linalg.norm(v - centre, axis=1).max()
    expected = mvc_weights(points, v, f)
    n2 = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    plane = np.abs(np.einsum("fi,fi->f", n2, v[f[:, 0]]) - points @ n2.T) / np.linalg.norm(n2, axis=1)  # (N, F)
    rng = np.random.default_rng(0)
    own = np.zeros(len(points))
    for k in range(9):
        nearby = points + (k > 0) * rng.normal(size=points.shape) * 1e-12 * scale
        own = np.maximum(own, np.abs(mvc_weights(nearby, v, f) - extended_weights(nearby, v, f)).max(axis=1))
    own[plane.min(axis=1) <= 1e-6 * scale] = 0.0  # the careful rules, which depart from the formula
    tolerance = 2e-11 * (1.0 + (np.linalg.norm(points - centre, axis=1) / scale) ** 2) + 5.0 * own  # (N,)
    difference = np.abs(mvc_weights_compiled(points, v, f) - expected).max(axis=1)
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
    x = rng.uniform(-1.3, 1.3, (70_000, 3))  # more than a piece per thread, a short last piece and block
    x[:3] = v[:3]  # rows that go through the careful path
    rows = rng.normal(size=(len(v), 12))
    one = mvc_project(x, v, f, rows, threads=1)
    assert one.shape == (70_000, 12) and one.dtype == np.float64
    np.testing.assert_array_equal(mvc_project(x, v, f, rows, threads=2), one)
    np.testing.assert_array_equal(mvc_project(x, v, f, rows, threads=3), one)
    np.testing.assert_allclose(one[:9000], mvc_weights(x[:9000], v, f) @ rows, rtol=0, atol=1e-10)
    out = np.empty((70_000, 12))
    assert mvc_project(x, v, f, rows, out=out) is out
    assert mvc_project(np.zeros((0, 3)), v, f, rows).shape == (0, 12)


def test_each_row_depends_on_its_point_alone():
    # the kernel orders points in space and takes 32 at a time, some seeing an edge under a wide angle and some not;
    # each row is computed the same way whatever its neighbours, so coincident points get equal rows
    v, f = icosphere(2, 1.4)
    rng = np.random.default_rng(5)
    x = rng.uniform(-1.3, 1.3, (6000, 3))
    x[:500] *= 3.0  # outside too
    x[-20:] = x[:20]  # the same positions twice
    rows = rng.normal(size=(len(v), 4))
    whole = mvc_project(x, v, f, rows)
    np.testing.assert_array_equal(whole[-20:], whole[:20])
    order = rng.permutation(len(x))
    np.testing.assert_array_equal(mvc_project(x[order], v, f, rows), whole[order])
    np.testing.assert_array_equal(mvc_project(x[::7], v, f, rows, threads=1), whole[::7])


def test_the_weights_do_not_depend_on_the_units():
    rng = np.random.default_rng(8)
    v, f = star_cage(rng.uniform(0.5, 1.5, 42))
    x = np.concatenate([awkward_points(v, f, rng, 1e-7), rng.uniform(-2.0, 2.0, (200, 3))])
    w = mvc_weights_compiled(x, v, f)
    for k in (-200, 200):  # pairs of products of lengths would overflow past 1e308 in these units without scaling
        np.testing.assert_array_equal(mvc_weights_compiled(np.ldexp(x, k), np.ldexp(v, k), f), w)
    # a cage a million times larger, ten million units from the origin
    np.testing.assert_allclose(mvc_weights_compiled(x * 1e6 + 1e7, v * 1e6 + 1e7, f), w, rtol=0, atol=1e-9)


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
