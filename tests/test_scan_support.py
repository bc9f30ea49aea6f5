"""kpd.scan.support: the plane a shape stands on."""

from __future__ import annotations

import numpy as np
from scan_shapes import table
from scipy.spatial.transform import Rotation

from kpd.scan import (
    support_plane,
)


def test_support_plane_stands_a_table_on_its_legs():
    points = table(4000, 0)
    guess = Rotation.from_rotvec([0.15, -0.1, 0.0]).as_matrix() @ [0.0, 0.0, 1.0]  # 10 degrees off
    found = support_plane(points, guess)
    assert np.degrees(np.arccos(found.normal @ [0.0, 0.0, 1.0])) < 1.0
    assert found.stability > 0.2 and found.count > 0
    overhang = points.copy()
    overhang[:4000, 0] += 2.5  # the top pushed beyond the legs: the centroid is no longer over the leg tips
    assert support_plane(overhang, [0.0, 0.0, 1.0], max_angle=10.0).stability < 0.0
