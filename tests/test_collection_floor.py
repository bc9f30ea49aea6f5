"""kpd.collection.floor: the floor shapes share is found from their flat contacts, and shapes are stood on it."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kpd.collection.floor import floor_up, stand_collection


def dome(seed: int, radius: float = 1.0) -> np.ndarray:
    """A half ball resting on its flat disk (z = 0), up +z: one flat side only."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(3000, 3))
    d[:, 2] = np.abs(d[:, 2])
    cap = radius * d / np.linalg.norm(d, axis=1, keepdims=True)
    r, t = radius * np.sqrt(rng.uniform(size=2000)), rng.uniform(0, 2 * np.pi, 2000)
    disk = np.c_[r * np.cos(t), r * np.sin(t), np.zeros(2000)]
    return np.vstack([cap, disk])


def test_floor_up_finds_the_shared_flat_side():
    clouds = [dome(i, 1.0 + 0.1 * i) for i in range(4)]
    up, info = floor_up(clouds, np.stack([np.eye(3)] * 4), [0, 1, 2, 3])
    assert up is not None and np.degrees(np.arccos(np.clip(up @ [0, 0, 1], -1, 1))) < 5.0, info
    assert info["share"] > info["rival_share"]
    none, info = floor_up(clouds[:1], np.eye(3)[None], [0])
    assert none is None and "fewer than 2" in info["note"]


def test_stand_collection_levels_tilted_shapes_and_keeps_the_others():
    clouds = [dome(i) for i in range(3)]
    tilted = Rotation.from_rotvec([0.25, -0.1, 0.0]).as_matrix()  # 15 degrees off
    rotations = np.stack([tilted, tilted, np.eye(3)])
    stood, tilts = stand_collection(clouds, rotations, [0, 1], "+z")
    for i in (0, 1):
        base = clouds[i][-2000:] @ stood[i].T  # the disk, turned into the shared frame
        assert np.ptp(base[:, 2]) < 0.005 * np.ptp(base[:, 0])  # flat on the floor again (within 0.3 degrees)
        assert abs(tilts[i] - np.degrees(np.linalg.norm(Rotation.from_matrix(tilted).as_rotvec()))) < 0.5
    np.testing.assert_array_equal(stood[2], np.eye(3))
    assert np.isnan(tilts[2])
