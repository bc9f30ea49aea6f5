"""kpd.procedural: the demo chair and its boxes are closed, outward and where the docstrings say."""

import numpy as np
import pytest

from kpd.procedural import box_mesh, procedural_chair


def test_procedural_chair_is_closed_and_outward():
    mesh = procedural_chair()
    v, t = mesh.vertices, mesh.triangles
    signed_volume = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6
    expected = 20 * 20 * 2 + 4 * 2 * 2 * 16 + 20 * 2 * 18  # seat + legs + back
    assert signed_volume == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(v.min(axis=0), [-10, -10, -18])
    np.testing.assert_allclose(v.max(axis=0), [10, 10, 18])



def test_chair_sizes_and_colours():
    assert len(procedural_chair().vertices) == 3060
    fine = procedural_chair(edge=0.52)
    assert len(fine.vertices) == 10400
    assert set(map(tuple, np.unique(fine.vertex_colors, axis=0).round(2).tolist())) == {(0.55, 0.36, 0.2),
                                                                                     (0.72, 0.14, 0.12)}


@pytest.mark.parametrize("edge", [0.5, 1.0, 3.0])
def test_box_mesh_grid_and_volume(edge):
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([2.0, 1.0, 3.5])
    v, t = box_mesh(lo, hi, edge=edge)
    np.testing.assert_allclose(v.min(axis=0), lo)
    np.testing.assert_allclose(v.max(axis=0), hi)
    volume = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6
    assert volume == pytest.approx(np.prod(hi - lo), rel=1e-12)
    edges = np.linalg.norm(v[t[:, 1]] - v[t[:, 0]], axis=1)
    assert edges.max() <= edge * np.sqrt(2) * 1.0000001  # grid squares of at most edge, cut along a diagonal
