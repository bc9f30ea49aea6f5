"""kpd.scan.rotations: the rotation sets, axis names, exact similarity transforms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scan_shapes import rotation

from kpd.errors import InputError
from kpd.geometry import Normalizer
from kpd.scan import (
    icosahedral_rotations,
    parse_axis,
    proper_signed_permutations,
    similarity_matrices,
)


def test_rotation_sets_are_proper_and_distinct():
    for group, size in ((proper_signed_permutations(), 24), (icosahedral_rotations(), 60)):
        assert group.shape == (size, 3, 3)
        for r in group:
            np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(r) == pytest.approx(1.0)
        distinct = {tuple(np.round(r, 6).ravel()) for r in group}
        assert len(distinct) == size


def test_parse_axis():
    np.testing.assert_array_equal(parse_axis("z"), [0, 0, 1])
    np.testing.assert_array_equal(parse_axis("-Y"), [0, -1, 0])
    np.testing.assert_array_equal(parse_axis("+x"), [1, 0, 0])
    np.testing.assert_allclose(parse_axis([0, 0, 2]), [0, 0, 1])
    with pytest.raises(InputError, match="one of x, y, z"):
        parse_axis("w")
    with pytest.raises(InputError, match="non-zero"):
        parse_axis([0, 0, 0])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), log_scale=st.floats(-3, 3), offset=st.floats(-100, 100))
def test_similarity_matrices_are_exact_inverses(seed, log_scale, offset):
    rng = np.random.default_rng(seed)
    r = rotation(seed)
    points = rng.normal(size=(50, 3)) * 10.0**log_scale + offset
    normalizer = Normalizer().fit(points @ r.T)
    forward, inverse = similarity_matrices(r, normalizer)
    aligned = points @ forward[:3, :3].T + forward[:3, 3]
    np.testing.assert_allclose(aligned, normalizer.apply(points @ r.T), atol=1e-12)
    back = aligned @ inverse[:3, :3].T + inverse[:3, 3]
    np.testing.assert_allclose(back, points, rtol=0, atol=1e-9 * max(1.0, np.abs(points).max()))
    np.testing.assert_allclose(inverse @ forward, np.eye(4), atol=1e-12)
