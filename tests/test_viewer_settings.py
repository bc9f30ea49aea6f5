"""kpd.viewer.settings: the one settings object checks its values; the palette and the up axes."""

from __future__ import annotations

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.viewer.settings import ViewSettings, cage_edges, keypoint_palette, up_axis


def test_view_settings_checks():
    with pytest.raises(InputError, match="up must be"):
        ViewSettings(up="w")
    with pytest.raises(InputError, match="width"):
        ViewSettings(width=3)
    assert ViewSettings.from_dict(ViewSettings(zoom=2.0).to_dict()).zoom == 2.0


def test_up_axis_palette_and_cage_edges():
    np.testing.assert_array_equal(up_axis("-y"), [0, -1, 0])
    np.testing.assert_array_equal(up_axis("Z"), [0, 0, 1])
    with pytest.raises(InputError, match="up must be"):
        up_axis("+w")
    colors = keypoint_palette(30)
    assert colors.shape == (30, 3) and colors.min() >= 0 and colors.max() <= 1
    np.testing.assert_array_equal(keypoint_palette(3), colors[:3])
    edges = cage_edges([[0, 1, 2], [0, 2, 3]])
    assert sorted(map(tuple, edges.tolist())) == [(0, 1), (0, 2), (0, 3), (1, 2), (2, 3)]
