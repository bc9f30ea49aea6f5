"""kpd.collection.templates: the descriptor does not see rotations or scale; the medoids pick the typical shape."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kpd.collection.templates import chamfer_medoid, descriptor_medoid, rms_unit, shape_descriptor
from kpd.errors import InputError


def _box(seed: int, size=(2.0, 1.0, 0.5)) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (3000, 3)) * size


def test_rms_unit_and_descriptor_invariance():
    box = _box(0)
    unit = rms_unit(box * 7.0 + 3.0)
    np.testing.assert_allclose(unit.mean(0), 0, atol=1e-12)
    assert np.sqrt((unit**2).sum(1).mean()) == pytest.approx(1.0)
    with pytest.raises(InputError, match="zero extent"):
        rms_unit(np.ones((20, 3)))
    d = shape_descriptor(box, seed=0)
    turned = shape_descriptor(3.0 * box @ Rotation.random(random_state=1).as_matrix().T + 5.0, seed=0)
    assert d.shape == (35,) and np.abs(d - turned).max() < 1e-9  # same pairs, same distances, same extents
    other = shape_descriptor(_box(0, size=(1.0, 1.0, 1.0)), seed=0)
    assert np.abs(d - other).sum() > 0.1


def test_medoids_pick_the_shape_most_like_the_others():
    clouds = [_box(1), _box(2, (2.1, 1.0, 0.5)), _box(3, (1.9, 1.05, 0.5)), _box(4, (1.0, 1.0, 1.0))]
    chosen = descriptor_medoid(clouds)
    assert chosen in (0, 1, 2)  # never the cube among the slabs
    rotations = np.stack([np.eye(3)] * 4)
    assert chamfer_medoid(clouds, rotations, [0, 1, 2, 3]) in (0, 1, 2)
    with pytest.raises(InputError, match="no shapes"):
        descriptor_medoid([])
