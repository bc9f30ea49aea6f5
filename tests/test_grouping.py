"""kpd.grouping: one answer to "which rows are the same?", -0.0 and 0.0 included."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kpd.grouping import _merge_coincident_reference, coincident_first, first_occurrence_groups, merge_coincident

small = st.sampled_from([-1.5, -0.0, 0.0, 0.25, 2.0])


def test_signed_zeros_are_one_position_in_every_grouper():
    rows = np.array([[0.0, 1.0, -0.0], [-0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    first, index = first_occurrence_groups(rows)
    assert first.tolist() == [0, 3] and index.tolist() == [0, 0, 0, 1]
    points, inverse = merge_coincident(rows)
    assert len(points) == 2 and inverse.tolist() == [0, 0, 0, 1]
    assert not np.signbit(points).any()  # zeros come out as 0.0


def test_first_occurrence_order_and_integer_keys():
    keys = np.array([5, 3, 5, 7, 3])
    first, index = first_occurrence_groups(keys)
    assert first.tolist() == [0, 1, 3] and index.tolist() == [0, 1, 0, 2, 1]
    first, index = first_occurrence_groups(np.zeros((0, 3)))
    assert first.size == 0 and index.size == 0


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)), elements=small))
def test_groupers_agree_and_reproduce_the_rows(rows):
    first, index = first_occurrence_groups(rows)
    points, inverse = merge_coincident(rows)
    np.testing.assert_array_equal(rows[first][index], rows)  # equal as numbers (-0.0 == 0.0)
    np.testing.assert_array_equal(points[inverse], rows)
    assert len(first) == len(points) == len({tuple(r) for r in (rows + 0.0).tolist()})
    # the same partition: two rows share a group in one exactly when they do in the other
    assert np.array_equal(index[:, None] == index[None, :], inverse[:, None] == inverse[None, :])
    assert (np.diff(np.lexsort(points.T[::-1])) > 0).all()  # distinct positions in lexicographic order
    first_at = coincident_first(rows)  # the hash table's answer: each row's first row at its position
    np.testing.assert_array_equal(first_at, first[index])


def rows_with_ties(draw_count, seed, levels):
    """(n, 3) rows whose coordinates take ``levels`` values per axis (many ties when few), zeros of both signs."""
    rng = np.random.default_rng(seed)
    values = np.concatenate([[0.0, -0.0], rng.normal(size=max(levels, 1))])
    return values[rng.integers(0, len(values), (draw_count, 3))]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 400), st.integers(0, 2**31), st.sampled_from([1, 3, 20, 1000]))
def test_merge_coincident_matches_its_lexicographic_twin(count, seed, levels):
    # all ties on x (a CAD mesh), a few (a scan), rows repeated, -0.0: the same points and inverse to the bit
    rows = rows_with_ties(count, seed, levels)
    rows = np.concatenate([rows, rows[: count // 3]])
    points, inverse = merge_coincident(rows)
    want_points, want_inverse = _merge_coincident_reference(rows)
    np.testing.assert_array_equal(points, want_points)
    np.testing.assert_array_equal(inverse, want_inverse)
    assert not np.signbit(points[points == 0]).any() and points.flags.c_contiguous  # zeros as 0.0


def test_merge_coincident_sorts_rows_when_ranks_do_not_fit_one_key(monkeypatch):
    import kpd.grouping as grouping

    rows = rows_with_ties(500, 1, 7)
    monkeypatch.setattr(grouping, "_KEY_LIMIT", 10)  # as for billions of distinct coordinates
    points, inverse = merge_coincident(rows)
    want_points, want_inverse = _merge_coincident_reference(rows)
    np.testing.assert_array_equal(points, want_points)
    np.testing.assert_array_equal(inverse, want_inverse)


def test_every_grouper_in_kpd_agrees_on_signed_zeros():
    """The rig's distinct positions, the viewer's welding for shading normals and the mesh's UV-seam groups are one
    partition of the same vertices."""
    from kpd.mesh import Mesh
    from kpd.rig import distinct_points
    from kpd.viewer.gl import _Welding

    vertices = np.array([[0.0, 0, 0], [-0.0, 0, 0], [1, 0, -0.0], [1, 0, 0.0], [0, 1, 0], [0, -0.0, 1]])
    triangles = np.array([[0, 2, 4], [1, 5, 3]])
    first, index = first_occurrence_groups(vertices)
    assert len(first) == 4
    assert len(distinct_points(vertices)) == 4
    welding = _Welding(vertices, triangles)
    assert np.array_equal(welding.inverse[:, None] == welding.inverse[None, :], index[:, None] == index[None, :])
    mesh = Mesh(vertices=vertices, triangles=triangles, vertex_normals=np.tile([0.0, 0, 1], (6, 1)))
    moved = mesh.with_vertices(vertices * 2)
    np.testing.assert_array_equal(moved.vertex_normals[0], moved.vertex_normals[1])  # one position, one normal


def test_importing_modules_with_kernels_compiled_on_first_call_does_not_import_numba():
    # every mesh reader imports kpd.grouping and kpd.geometry, every bundle kpd.cage: their kernels are compiled
    # (or loaded from numba's cache) on the first call instead
    import subprocess
    import sys

    code = ("import sys\nimport kpd.grouping, kpd.geometry, kpd.cage\nassert 'numba' not in sys.modules\n"
            "import numpy as np\nkpd.grouping.merge_coincident(np.zeros((2, 3)))\nassert 'numba' in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_coincident_first_on_a_scan_sized_grid_of_repeated_rows():
    # integer-valued keys, as the scan cleaner welds, many equal in one or two coordinates (the hash must not
    # confuse them), each distinct row stored three times in a shuffled order
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(np.arange(40.0), np.arange(-20.0, 20.0), np.arange(30.0), indexing="ij"), -1)
    rows = np.repeat(grid.reshape(-1, 3), 3, axis=0)[rng.permutation(3 * 48_000)]
    first = coincident_first(rows)
    _, inverse = merge_coincident(rows)
    assert (first <= np.arange(len(rows))).all()
    np.testing.assert_array_equal(rows[first], rows)
    lowest = np.full(inverse.max() + 1, len(rows))
    np.minimum.at(lowest, inverse, np.arange(len(rows)))
    np.testing.assert_array_equal(first, lowest[inverse])


def test_same_corners_names_the_first_triangle_over_the_same_corners():
    from kpd.grouping import same_corners

    @settings(max_examples=60, deadline=None)
    @given(n=st.integers(1, 200), points=st.integers(1, 15), top=st.integers(1, 8), drop=st.booleans(),
           seed=st.integers(0, 2**16))
    def check(n, points, top, drop, seed):
        rng = np.random.default_rng(seed)
        triangles = rng.integers(0, points, size=(n, 3))  # repeats, either way round, collapsed
        mapping = rng.integers(0, top, size=points)  # several points onto one corner
        same = np.empty(n, dtype=np.int64)
        same_corners(triangles, mapping, top, drop, same)
        corners = np.sort(mapping[triangles], axis=1)
        for t in range(n):
            if drop and (corners[t, 0] == corners[t, 1] or corners[t, 1] == corners[t, 2]):
                assert same[t] == -1
            else:
                assert same[t] == np.flatnonzero((corners[: t + 1] == corners[t]).all(axis=1))[0]

    check()


def test_the_direct_table_equals_the_sort_on_integer_keys():
    from kpd.grouping import _direct_groups, _sorted_groups

    @settings(max_examples=80, deadline=None)
    @given(n=st.integers(1, 400), spread=st.integers(1, 2000), seed=st.integers(0, 2**16),
           dtype=st.sampled_from([np.int64, np.int32, np.uint16, np.uint64]), column=st.booleans())
    def check(n, spread, seed, dtype, column):
        keys = np.random.default_rng(seed).integers(0, spread, n).astype(dtype)  # repeats wherever spread < n
        first, index = _direct_groups(keys, int(keys.max()) + 1)
        want = _sorted_groups(keys[:, None] if column else keys)
        assert first.dtype == index.dtype == want.first.dtype == want.index.dtype == np.int64
        np.testing.assert_array_equal(first, want.first)
        np.testing.assert_array_equal(index, want.index)

    check()
    first, index = _direct_groups(np.zeros(0, np.int64), 1)
    assert first.shape == index.shape == (0,) and first.dtype == index.dtype == np.int64
    first, index = _direct_groups(np.array([7]), 8)
    assert first.tolist() == [0] and index.tolist() == [0]


def test_integer_keys_take_the_table_exactly_within_its_bound(monkeypatch):
    import kpd.grouping as grouping

    tables = []
    direct = grouping._direct_groups
    monkeypatch.setattr(grouping, "_direct_groups", lambda keys, top: tables.append(top) or direct(keys, top))
    rows = grouping._DIRECT_ROWS
    bound = grouping._direct_bound(rows)
    assert bound == 4 * rows + 1024
    rng = np.random.default_rng(3)
    for largest, tabled in ((bound - 1, True), (bound, False)):  # keys up to 4 R + 1023 take the table
        keys = rng.integers(0, rows // 3, rows)
        keys[rng.integers(rows)] = largest
        for shaped in (keys, keys[:, None], keys.astype(np.int32), keys.astype(np.uint32)):
            got, want = first_occurrence_groups(shaped), grouping._sorted_groups(shaped)
            assert got.first.dtype == got.index.dtype == np.int64
            np.testing.assert_array_equal(got.first, want.first)
            np.testing.assert_array_equal(got.index, want.index)
        assert tables == ([largest + 1] * 4 if tabled else [])
        tables.clear()
    keys = rng.integers(0, 100, rows)
    # too few, a negative one, two columns, bool, big-endian: sorted
    for sorted_keys in (keys[:-1], np.r_[keys[:-1], -1], np.c_[keys, keys], keys.astype(bool), keys.astype(">i8")):
        got, want = first_occurrence_groups(sorted_keys), grouping._sorted_groups(sorted_keys)
        np.testing.assert_array_equal(got.first, want.first)
        np.testing.assert_array_equal(got.index, want.index)
    assert tables == []
    got = first_occurrence_groups(np.zeros((0, 1), np.int64))
    assert got.first.shape == got.index.shape == (0,) and got.first.dtype == got.index.dtype == np.int64


def test_vertex_value_groups_equal_the_groups_of_the_joined_rows():
    from kpd.grouping import _sorted_groups, vertex_value_groups

    @settings(max_examples=80, deadline=None)
    @given(n=st.integers(0, 300), vertices=st.integers(1, 40), values=st.integers(1, 6), seed=st.integers(0, 2**16),
           far=st.booleans())
    def check(n, vertices, values, seed, far):
        rng = np.random.default_rng(seed)
        vertex = rng.integers(0, vertices, n)
        if far and n:  # a vertex number beyond the table's bound: the rows' own grouping
            vertex[rng.integers(n)] = 4 * n + 1024
        levels = np.array([0.0, -0.0, 0.5, -1.25, 3.0, 1e-300])[:values]  # zeros of both signs are one value
        uv = levels[rng.integers(0, len(levels), (n, 2))]
        got = vertex_value_groups(vertex, uv)
        want = _sorted_groups(np.hstack([vertex[:, None], uv]))
        assert got.first.dtype == got.index.dtype == np.int64
        np.testing.assert_array_equal(got.first, want.first)
        np.testing.assert_array_equal(got.index, want.index)

    check()


def test_vertex_value_groups_of_a_pole_with_a_value_per_row_give_up_the_search():
    """One vertex with 20,000 distinct UVs (a sphere's pole, mapped per triangle): the search would compare about
    2e8 pairs; past its budget it stops, and the groups are still the joined rows' groups."""
    from kpd import grouping
    from kpd.grouping import _sorted_groups, vertex_value_groups

    n = 20_000
    vertex = np.zeros(n, dtype=np.int64)
    uv = np.stack([np.arange(n, dtype=np.float64), np.zeros(n)], axis=1)
    assert not grouping._vertex_value_groups(vertex, uv, 1, 16 * n + 4096)[2]  # the budget runs out
    got, want = vertex_value_groups(vertex, uv), _sorted_groups(np.hstack([vertex[:, None], uv]))
    np.testing.assert_array_equal(got.first, want.first)
    np.testing.assert_array_equal(got.index, want.index)


def test_float32_positions_take_the_hash_table_with_the_sorts_groups():
    from kpd.grouping import _sorted_groups

    for count, seed, levels in ((0, 0, 3), (1, 1, 3), (500, 2, 3), (500, 3, 1000)):
        rows = rows_with_ties(count, seed, levels).astype(np.float32)  # zeros of both signs, many ties
        rows = np.concatenate([rows, rows[: count // 3]])
        got, want = first_occurrence_groups(rows), _sorted_groups(rows)
        np.testing.assert_array_equal(got.first, want.first)
        np.testing.assert_array_equal(got.index, want.index)
        np.testing.assert_array_equal(coincident_first(rows), coincident_first(rows.astype(np.float64)))


@pytest.mark.parametrize("width", [1, 2])
def test_many_uv_rows_take_the_hash_table_with_the_sorts_groups(width):
    from kpd.grouping import _DIRECT_ROWS, _sorted_groups

    rng = np.random.default_rng(width)
    levels = np.array([0.0, -0.0, 0.25, 1.0, -3.5, 1e-300, 0.1])  # zeros of both signs are one value
    rows = levels[rng.integers(0, len(levels), (_DIRECT_ROWS + 100, width))]
    got, want = first_occurrence_groups(rows), _sorted_groups(rows)
    np.testing.assert_array_equal(got.first, want.first)
    np.testing.assert_array_equal(got.index, want.index)


@pytest.mark.parametrize("crowded", [False, True])
def test_many_positions_with_normals_group_as_the_joined_rows(crowded):
    """(R, 6) rows, positions and normals, above the table's threshold: grouped by position, then by normal within
    each; with one position holding a normal per row the search runs out of budget and the rows are sorted."""
    from kpd.grouping import _DIRECT_ROWS, _sorted_groups

    rng = np.random.default_rng(7)
    n = _DIRECT_ROWS + 500
    positions = rng.integers(0, 5, (n, 3)).astype(np.float64)
    positions[::5] *= -0.0  # zeros of both signs are one position
    normals = np.array([[0.0, 0, 1], [0, 1, 0], [-0.0, 0, 1]])[rng.integers(0, 3, n)]
    if crowded:
        positions[:] = 0.0
        normals = np.stack([np.arange(n, dtype=np.float64), np.zeros(n), np.ones(n)], axis=1)
    rows = np.hstack([positions, normals])
    got, want = first_occurrence_groups(rows), _sorted_groups(rows)
    np.testing.assert_array_equal(got.first, want.first)
    np.testing.assert_array_equal(got.index, want.index)
