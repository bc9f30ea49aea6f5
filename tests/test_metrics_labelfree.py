"""kpd.metrics.labelfree: label-free keypoint metrics and the alignment chamfer."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.errors import InputError
from kpd.geometry import chamfer
from kpd.metrics import (alignment_chamfer, fit_mirror_permutation, keypoint_stability, mirror_consistency,
                         point_triangle_distance, surface_distance)


def test_stability_known_values():
    base = np.random.default_rng(0).normal(size=(6, 3))
    assert keypoint_stability(np.stack([base] * 5)) == 0.0
    offsets = np.zeros((2, 6, 3))
    offsets[0, :, 0], offsets[1, :, 0] = 0.1, -0.1
    assert keypoint_stability(base + offsets) == pytest.approx(0.1)
    with pytest.raises(InputError, match=r"\(S, K, 3\)"):
        keypoint_stability(base)


def test_surface_distance_simple_cases():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    t = np.array([[0, 1, 2]])
    kp = np.array([[0.2, 0.2, 0.5],    # above the face
                   [-1.0, -1.0, 0.0],  # nearest the vertex (0, 0, 0)
                   [0.5, -2.0, 0.0],   # nearest the edge y = 0
                   [1.0, 1.0, 0.0],    # nearest the hypotenuse
                   [0.1, 0.1, 0.0]])   # on the face
    want = [0.5, np.sqrt(2), 2.0, np.sqrt(0.5), 0.0]
    np.testing.assert_allclose(surface_distance(kp, v, t), want, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_point_triangle_distance_matches_open3d(seed):
    import open3d as o3d

    rng = np.random.default_rng(seed)
    v = rng.normal(size=(12, 3))
    t = rng.integers(0, 12, size=(10, 3))
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    if len(t) == 0:
        return
    p = rng.normal(size=(30, 3)) * 2
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32)))
    want = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
    np.testing.assert_allclose(point_triangle_distance(p, v, t, chunk=3), want, atol=1e-4)


def test_mirror_permutation_recovers_a_known_pairing():
    rng = np.random.default_rng(1)
    s, k = 20, 6
    perm = np.array([1, 0, 2, 4, 3, 5])  # pairs (0,1), (3,4); 2 and 5 on the plane
    kp = rng.normal(size=(s, k, 3))
    mirrored = np.empty_like(kp)
    mirrored[:, perm] = kp + rng.normal(scale=0.01, size=kp.shape)
    got = fit_mirror_permutation(kp, mirrored)
    np.testing.assert_array_equal(got, perm)  # kp[:, k] pairs with mirrored[:, perm[k]]
    assert mirror_consistency(kp, mirrored, got) < 0.03
    assert mirror_consistency(kp, mirrored, np.arange(k)) > 0.5
    with pytest.raises(InputError, match="permutation"):
        mirror_consistency(kp, mirrored, [0, 0, 1, 2, 3, 4])
    with pytest.raises(InputError, match="same shape"):
        fit_mirror_permutation(kp, mirrored[:, :5])


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_mirror_permutation_is_a_permutation(seed):
    rng = np.random.default_rng(seed)
    kp, mk = rng.normal(size=(3, 7, 3)), rng.normal(size=(3, 7, 3))
    perm = fit_mirror_permutation(kp, mk)
    assert sorted(perm.tolist()) == list(range(7))
    assert mirror_consistency(kp, mk, perm) <= mirror_consistency(kp, mk, np.arange(7)) + 1e-12


def test_alignment_chamfer_is_the_reference_chamfer():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(60, 3))
    assert alignment_chamfer(a, b) == chamfer(a, b)
    assert alignment_chamfer(a, a) == pytest.approx(0.0, abs=1e-12)
