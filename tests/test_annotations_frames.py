"""kpd.annotations.frames: the reference frame, similarities, the registration of an annotation frame."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from helpers import box

from kpd import annotations as ann
from kpd.errors import InputError
from kpd.geometry import sample_surface
from kpd.io import Mesh, read_mesh, read_points

CHAIR = "03001627"
PCD_CHAIR = "88382b877be91b2a572f8e1c1caad99e"  # KeypointNet cloud + ShapeNet v2 mesh
PART_CHAIR = "1015e71a0d21b127de03ab2a27ba7531"  # ShapeNetPart points, also annotated in KeypointNet


def test_frame_maps_are_rotations():
    for m in (ann.KEYPOINTNET_TO_REFERENCE, ann.MODELNET_TO_REFERENCE):
        np.testing.assert_allclose(m @ m.T, np.eye(3))
        assert np.linalg.det(m) == pytest.approx(1.0)
    # the authors' fix: (x, y, z) -> (-z, y, x)
    np.testing.assert_array_equal(np.array([[1.0, 2.0, 3.0]]) @ ann.KEYPOINTNET_TO_REFERENCE.T, [[-3.0, 2.0, 1.0]])
    np.testing.assert_array_equal(np.array([[1.0, 2.0, 3.0]]) @ ann.MODELNET_TO_REFERENCE.T, [[-2.0, 3.0, -1.0]])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_similarity_inverse_and_composition(seed):
    rng = np.random.default_rng(seed)
    a = ann.Similarity(float(rng.uniform(0.2, 5)), Rotation.random(random_state=seed).as_matrix() * [1, 1, -1],
                       rng.normal(size=3))
    b = ann.Similarity(float(rng.uniform(0.2, 5)), Rotation.random(random_state=seed + 1).as_matrix(),
                       rng.normal(size=3))
    x = rng.normal(size=(7, 3))
    np.testing.assert_allclose(a.inverse().apply(a.apply(x)), x, atol=1e-10)
    np.testing.assert_allclose(a.then(b).apply(x), b.apply(a.apply(x)), atol=1e-10)


def _upright_back(points: np.ndarray) -> np.ndarray:
    """Offset of the top 10% of a chair (its back) from the bounding-box centre, divided by the extent."""
    top = points[points[:, 1] > np.percentile(points[:, 1], 90)]
    return (top.mean(axis=0) - (points.max(axis=0) + points.min(axis=0)) / 2) / np.ptp(points, axis=0)


def test_datasets_agree_on_the_reference_frame(data_dir, kpn_root, part_root):
    """Chair backs point to -x, y up, in ShapeNetPart, in KeypointNet after the authors' fix, and in ModelNet after
    MODELNET_TO_REFERENCE, so one model frame mapping serves all of them."""
    part = read_points(part_root / CHAIR / "points" / f"{PART_CHAIR}.pts").points
    cloud = read_points(kpn_root / "pcds" / CHAIR / f"{PCD_CHAIR}.pcd").points @ ann.KEYPOINTNET_TO_REFERENCE.T
    modelnet = sorted((data_dir / "modelnet10" / "chair" / "train").glob("*.ply"))[:3]
    backs = [_upright_back(part), _upright_back(cloud)]
    backs += [_upright_back(read_mesh(p).vertices @ ann.MODELNET_TO_REFERENCE.T) for p in modelnet]
    for back in backs:
        assert back[0] < -0.2 and abs(back[2]) < 0.1, back


@pytest.mark.parametrize("candidate", ["keypointnet-to-reference", "identity"])
def test_fit_annotation_frame_recovers_a_known_map(candidate):
    mesh = Mesh(*box((-0.2, -0.45, -0.1), (0.3, 0.35, 0.2)))
    surface = sample_surface(mesh.vertices, mesh.triangles, 20000, seed=1).points
    rng = np.random.default_rng(3)
    corners = mesh.vertices[[0, 3, 5, 6, 7]]
    source = np.concatenate([corners, surface[rng.choice(len(surface), 7)]])  # "KeypointNet" frame
    truth = ann.Similarity(2.0, ann.FIT_CANDIDATES[candidate], np.array([0.05, -0.02, 0.03]))
    surface_target = truth.apply(surface)
    diagonal = float(np.linalg.norm(np.ptp(surface, axis=0)))
    fit = ann.fit_annotation_frame(source, surface_target, source_diagonal=diagonal)
    assert fit.candidate == candidate
    np.testing.assert_allclose(fit.transform.apply(source), truth.apply(source), atol=0.02)
    assert fit.distances.max() < 0.02
    assert set(fit.residuals) == set(ann.FIT_CANDIDATES)


def test_fit_annotation_frame_checks_input():
    with pytest.raises(InputError, match="at least 3"):
        ann.fit_annotation_frame(np.zeros((2, 3)), np.random.default_rng(0).normal(size=(10, 3)))
    with pytest.raises(InputError, match="candidate"):
        ann.fit_annotation_frame(np.eye(3), np.random.default_rng(0).normal(size=(10, 3)), candidates={})
