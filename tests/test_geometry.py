import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from helpers import box

from kpd.errors import InputError, NotFittedError
from kpd.geometry import (
    Normalizer,
    as_points,
    bounds,
    chamfer,
    chamfer_naive,
    farthest_point_sampling,
    farthest_point_sampling_naive,
    sample_surface,
)

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


def clouds(min_size=1, max_size=40):
    return st.integers(min_size, max_size).flatmap(lambda n: arrays(np.float64, (n, 3), elements=finite))


# --- as_points -------------------------------------------------------------------------------------------------

def test_as_points_converts_lists_to_float64():
    p = as_points([[1, 2, 3]])
    assert p.dtype == np.float64 and p.shape == (1, 3) and p.flags.c_contiguous


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((128, 4)), r"shape \(N, 3\); got \(128, 4\)"),
        (np.zeros(3), r"shape \(N, 3\); got \(3,\)"),
        (np.array([[0.0, np.nan, 0.0], [1, 1, 1]]), "1 point\\(s\\) with NaN or inf"),
        (np.zeros((0, 3)), "at least 1 point"),
        ("abc", "numeric"),
    ],
)
def test_as_points_rejects_bad_input(bad, match):
    with pytest.raises(InputError, match=match):
        as_points(bad)


# --- Normalizer ------------------------------------------------------------------------------------------------

@given(clouds(min_size=2), st.floats(0.1, 100), arrays(np.float64, 3, elements=st.floats(-50, 50)))
def test_normalizer_round_trip_and_box(points, s, t):
    points = points * s + t
    if np.ptp(points, axis=0).max() < 1e-6:
        return
    norm = Normalizer().fit(points)
    assert norm.scale_ == np.abs(points - norm.center_).max()  # the largest offset, as rounded, to the bit
    y = norm.apply(points)
    assert np.abs(y).max() == pytest.approx(1.0)
    np.testing.assert_allclose((y.max(0) + y.min(0)) / 2, 0, atol=1e-9)
    np.testing.assert_allclose(norm.invert(y), points, rtol=1e-12, atol=1e-9 * np.abs(points).max())


def test_normalizer_keeps_aspect_ratio_and_vectors():
    pts = np.array([[0, 0, 0], [4, 2, 1.0]])
    norm = Normalizer().fit(pts)
    np.testing.assert_allclose(norm.apply(pts), [[-1, -0.5, -0.25], [1, 0.5, 0.25]])
    np.testing.assert_allclose(norm.apply_vectors([[2, 0, 0]]), [[1, 0, 0]])
    np.testing.assert_allclose(norm.invert_vectors(norm.apply_vectors([[1, 2, 3]])), [[1, 2, 3]])


def test_normalizer_dict_round_trip():
    norm = Normalizer().fit(np.random.default_rng(0).normal(size=(50, 3)))
    back = Normalizer.from_dict(norm.to_dict())
    np.testing.assert_array_equal(back.center_, norm.center_)
    assert back.scale_ == norm.scale_


def test_normalizer_errors():
    with pytest.raises(NotFittedError, match="not fitted"):
        Normalizer().apply(np.zeros((1, 3)))
    with pytest.raises(InputError, match="zero extent"):
        Normalizer().fit(np.ones((5, 3)))
    with pytest.raises(InputError, match="center"):
        Normalizer.from_dict({"scale": 1.0})


# --- surface sampling ------------------------------------------------------------------------------------------

def test_sample_surface_on_cube_is_on_the_surface_and_uniform():
    v, t = box()
    s = sample_surface(v, t, 6000, seed=1)
    assert s.points.shape == (6000, 3) and s.normals.shape == (6000, 3) and s.faces.shape == (6000,)
    on_face = np.isclose(s.points, 0) | np.isclose(s.points, 1)
    assert on_face.any(axis=1).all()
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1)
    # each of the 6 unit faces gets about a sixth of the points
    side = np.argmax(np.abs(s.normals), axis=1) * 2 + (s.normals.max(axis=1) > 0.5)
    counts = np.bincount(side, minlength=6)
    assert counts.min() > 850 and counts.max() < 1150


def test_sample_surface_is_seeded():
    v, t = box()
    a, b = sample_surface(v, t, 100, seed=3), sample_surface(v, t, 100, seed=3)
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.points, sample_surface(v, t, 100, seed=4).points)


def full_array_sample(vertices, triangles, n, seed):
    """sample_surface as it was written first: every triangle's corners and cross product, then the draw."""
    rng = np.random.default_rng(seed)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))  # (T, 3) each
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    faces = rng.choice(len(triangles), size=n, p=area2 / area2.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    u, v = 1.0 - s, s * (1.0 - r2)
    points = u[:, None] * a[faces] + v[:, None] * b[faces] + (1.0 - u - v)[:, None] * c[faces]
    return points, cross[faces] / area2[faces, None], faces


@settings(max_examples=25, deadline=None)
@given(st.integers(3, 60), st.integers(1, 200), st.integers(-6, 6), st.integers(0, 2**31))
def test_sample_surface_draws_what_the_full_arrays_drew(count, triangles, exponent, seed):
    # the same points, normals and faces to the bit, though only the drawn triangles' corners are gathered now
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(count, 3)) * 10.0**exponent + rng.normal(size=3)
    t = rng.integers(0, count, (triangles, 3))
    t[0] = [0, 1, 2]  # some area
    sample = sample_surface(v, t, 64, seed=seed)
    for got, want in zip(sample, full_array_sample(v, t, 64, seed)):
        np.testing.assert_array_equal(got, want)


def test_double_areas_are_the_norms_of_the_cross_products_to_the_bit():
    from kpd.geometry import _double_areas
    from kpd.triangles import cross

    rng = np.random.default_rng(5)
    v = rng.normal(size=(3000, 3)) * np.exp(rng.normal(size=(3000, 1)) * 3)
    t = rng.integers(0, 3000, (20000, 3))
    t[:5] = [[0, 0, 1], [2, 2, 2], [0, 1, 2], [3, 4, 3], [5, 6, 7]]  # degenerate ones too
    np.testing.assert_array_equal(_double_areas(v, t), np.linalg.norm(cross(v, t), axis=1))
    assert _double_areas(v, t[:0]).shape == (0,)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 5000), st.integers(1, 3000), st.integers(1, 8), st.floats(0.0, 0.6), st.integers(0, 2**31))
def test_picks_by_area_are_numpys_choice_to_the_bit(count, n, power, zeros, seed):
    # zero areas (degenerate triangles), a few large areas among many small ones, and ties
    from kpd.geometry import _picks_by_area

    rng = np.random.default_rng(seed)
    area2 = rng.random(count) ** power
    area2[rng.random(count) < zeros] = 0.0
    if seed % 3 == 0:
        area2 = np.round(area2, 1)
    area2[count // 2] = 0.5
    want = np.random.default_rng(seed).choice(count, size=n, p=area2 / area2.sum())
    got = np.empty(n, dtype=np.int64)
    uniform = np.random.default_rng(seed).random(n)
    _picks_by_area(area2, float(area2.sum()), uniform, np.argsort(uniform), got)
    np.testing.assert_array_equal(got, want)
    if seed % 2:  # repeated numbers: the same triangles whichever of them comes first
        uniform = np.round(uniform, 2)
        want = np.searchsorted(np.cumsum(area2 / area2.sum()) / np.cumsum(area2 / area2.sum())[-1], uniform,
                               side="right")
        _picks_by_area(area2, float(area2.sum()), uniform, np.lexsort((-np.arange(n), uniform)), got)
        np.testing.assert_array_equal(got, want)


def test_sample_surface_errors():
    v, t = box()
    with pytest.raises(InputError, match="overflow"):
        sample_surface(v * 1e200, t, 10)
    with pytest.raises(InputError, match="indices"):
        sample_surface(v, t + 10, 10)
    with pytest.raises(InputError, match="zero area"):
        sample_surface(np.zeros((3, 3)), [[0, 1, 2]], 10)
    with pytest.raises(InputError, match="shape \\(T, 3\\)"):
        sample_surface(v, np.zeros((0, 3), int), 10)


# --- farthest point sampling -----------------------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(clouds(min_size=2, max_size=30), st.integers(0, 2**31), st.data())
def test_fps_matches_naive_unique_and_seed_stable(points, seed, data):
    points = np.unique(points, axis=0)
    k = data.draw(st.integers(1, len(points)))
    idx = farthest_point_sampling(points, k, seed=seed)
    assert len(np.unique(idx)) == k
    np.testing.assert_array_equal(idx, farthest_point_sampling(points, k, seed=seed))
    np.testing.assert_array_equal(idx, farthest_point_sampling_naive(points, k, seed=seed))


def test_fps_picks_extremes():
    pts = np.array([[0, 0, 0], [0.1, 0, 0], [10, 0, 0], [5, 0, 0]], dtype=float)
    assert farthest_point_sampling(pts, 2, start=0).tolist() == [0, 2]
    with pytest.raises(InputError, match="k must lie in"):
        farthest_point_sampling(pts, 5)


# --- chamfer ---------------------------------------------------------------------------------------------------

@given(clouds(), clouds())
def test_chamfer_symmetric_nonnegative_and_matches_naive(a, b):
    c = chamfer(a, b)
    assert c >= 0
    assert c == pytest.approx(chamfer(b, a), rel=1e-9, abs=1e-9)
    assert c == pytest.approx(chamfer_naive(a, b), rel=1e-6, abs=1e-6)


@given(clouds())
def test_chamfer_zero_on_itself(a):
    assert chamfer(a, a) == pytest.approx(0, abs=1e-6)


def test_chamfer_known_value_and_kdtree_path():
    a = np.zeros((1, 3))
    b = np.array([[1.0, 0, 0], [0, 2, 0]])
    # a->b: min 1; b->a: (1 + 4)/2
    assert chamfer(a, b) == pytest.approx(1 + 2.5)
    rng = np.random.default_rng(0)
    big_a, big_b = rng.normal(size=(3000, 3)), rng.normal(size=(2500, 3))
    assert chamfer(big_a, big_b) == pytest.approx(chamfer_naive(big_a, big_b), rel=1e-9)


# --- closed pieces ---------------------------------------------------------------------------------------------

def test_closed_pieces_at_once_equal_the_check_of_each_piece(data_dir):
    """The one-pass closedness of every piece (edges bucketed by corner) against the sort per piece, on real convex
    decompositions (mostly closed pieces), a real scan (open), a fan whose centre has hundreds of edges, and a
    degenerate triangle."""
    from kpd.geometry import _closed_pieces, _is_closed, mesh_pieces
    from kpd.io import read_mesh

    shoes = sorted((data_dir / "gso_shoes").glob("*/*.obj"))[:4]
    assert shoes
    n = 300
    fan = np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)]
                   + [[n + 1, 1 + (i + 1) % n, 1 + i] for i in range(n)])  # two cones: closed
    cases = [np.asarray(read_mesh(path).triangles) for path in [*shoes, data_dir / "scans" / "sneaker.ply"]]
    cases += [fan, fan[:-1], np.concatenate([fan, [[0, 0, 5]]]), np.concatenate([fan, fan + n + 2])]
    closed_somewhere = 0
    for triangles in cases:
        triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        labels = mesh_pieces(triangles)
        pieces = int(labels.max()) + 1
        each = np.array([_is_closed(triangles[labels == p]) for p in range(pieces)])
        np.testing.assert_array_equal(_closed_pieces(triangles, labels, pieces, int(triangles.max()) + 1), each)
        closed_somewhere += int(each.sum())
    assert closed_somewhere > 10  # the shoes' pieces and the fans are closed; the open ones are told apart


def test_bounds_are_the_columns_lowest_and_highest_values():
    rng = np.random.default_rng(3)
    for points in (rng.normal(size=(1000, 3)), rng.normal(size=(1, 3)), rng.normal(size=(50, 2)) * 1e300,
                   np.array([[0.0, -0.0, 5.0], [-0.0, 0.0, -5.0]])):
        lo, hi = bounds(points)
        np.testing.assert_array_equal(lo, points.min(axis=0))
        np.testing.assert_array_equal(hi, points.max(axis=0))
        assert lo.dtype == hi.dtype == points.dtype
    with_nan = rng.normal(size=(10, 3))
    with_nan[4, 1] = np.nan
    lo, hi = bounds(with_nan)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and np.isfinite(lo[[0, 2]]).all() and np.isfinite(hi[[0, 2]]).all()
