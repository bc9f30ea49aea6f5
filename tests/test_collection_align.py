"""kpd.collection.align: a small collection turned at random comes back to one frame; the state file resumes it;
the rotation-error measure is exact on known rotations."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kpd.collection.align import align_collection, pairwise_rotation_errors
from kpd.collection.results import CollectionAlignment
from kpd.errors import InputError


def lumpy(seed: int) -> np.ndarray:
    """An asymmetric blob (ellipsoid, bump, tail): one right orientation."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(1500, 3))
    body = d / np.linalg.norm(d, axis=1, keepdims=True) * [1.0, 0.6, 0.35]
    b = rng.normal(size=(400, 3))
    bump = 0.25 * b / np.linalg.norm(b, axis=1, keepdims=True) + [0.7, 0.3, 0.2]
    tail = np.c_[np.linspace(-1.6, -1.0, 200), np.zeros(200), np.linspace(0.0, 0.4, 200)]
    return np.vstack([body, bump, tail])


def test_pairwise_rotation_errors_known_values():
    truth = Rotation.random(3, random_state=0).as_matrix()
    exact = np.transpose(truth, (0, 2, 1))  # the inverse of each: every pair ends in one frame
    np.testing.assert_allclose(pairwise_rotation_errors(exact, truth), 0.0, atol=1e-4)  # arccos near 1: 1e-5 deg
    off = exact.copy()
    off[2] = Rotation.from_euler("z", 30, degrees=True).as_matrix() @ off[2]
    errors = pairwise_rotation_errors(off, truth)  # (S, S), symmetric
    np.testing.assert_allclose(errors, [[0, 0, 30], [0, 0, 30], [30, 30, 0]], atol=1e-5)
    np.testing.assert_allclose(pairwise_rotation_errors(off, truth, np.array([True, True, False])), 0.0, atol=1e-5)


def test_a_turned_collection_comes_back_to_one_frame_and_resumes(tmp_path):
    truth = Rotation.random(4, random_state=3).as_matrix()
    clouds = [lumpy(i) @ r.T for i, r in enumerate(truth)]
    state = tmp_path / "state.json"
    result = align_collection(clouds, ["a", "b", "c", "d"], rounds=2, state=state, stand=False, seed=0)
    assert isinstance(result, CollectionAlignment) and [s.name for s in result.shapes] == ["a", "b", "c", "d"]
    decided = ~result.ambiguous
    assert decided.sum() >= 3
    assert pairwise_rotation_errors(result.rotations, truth, decided).max() < 5.0
    saved = json.loads(state.read_text())
    again = align_collection(clouds, ["a", "b", "c", "d"], rounds=2, state=state, stand=False, seed=0)
    np.testing.assert_allclose(again.rotations, result.rotations, atol=1e-12)  # read back, not redone
    assert json.loads(state.read_text()).keys() == saved.keys()
    with pytest.raises(InputError):
        align_collection(clouds[:1])
