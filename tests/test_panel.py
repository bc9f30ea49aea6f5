"""kpd.viewer.panel: the editor's panel, driven in a real window under Xvfb with xdotool."""

import time

import numpy as np
import pytest
from viewer_helpers import HAS_XVFB, editor_window

from kpd.viewer.events import read_events, wait_for
from kpd.viewer.session import component_offsets

pytest_plugins = ["viewer_fixtures"]  # the shared fixtures


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_editor_window_pca_slider_explores_the_category(chair_rig, tmp_path):
    """Drag the first PCA slider in the real window: the keypoints become the rig's plus that many standard
    deviations of the chair prior's first component."""
    from kpd.rig import Rig
    from kpd.runtime import Model

    rig = Rig.load(chair_rig)
    prior = Model.load("chair").prior
    with editor_window(tmp_path, "--rig", chair_rig, "--model", "chair") as win:
        assert len(win.ready["sliders"]) == min(len(prior.components_), 8)
        sx, sy, sw, sh = win.ready["sliders"][0]  # on the screen (the panel is a window of its own)
        assert sw > 150  # drawn across the panel, not a thumb's width
        x, y = sx + sw // 2, sy + sh // 2  # the thumb: value 0
        win.xdo("mousemove", x, y)
        time.sleep(0.3)
        win.xdo("mousedown", 1)
        for step in range(1, 7):
            time.sleep(0.2)
            win.xdo("mousemove", x + step * sw // 20, y)  # to 0.3 of the width right of the middle
        win.xdo("mouseup", 1)
        moved = wait_for(lambda: [e for e in read_events(win.events) if e["event"] == "component" and e["value"] > 1.0],
                      120, "the slider at more than one standard deviation")[-1]
    assert moved["component"] == 0
    sigmas = np.zeros(len(prior.components_))
    sigmas[0] = moved["value"]
    expected = rig.keypoints + component_offsets(prior, rig.normalizer, sigmas)
    np.testing.assert_allclose(moved["keypoints"], expected, atol=1e-6 * np.abs(expected).max())
    assert np.abs(expected - rig.keypoints).max() > 1e-3 * np.abs(rig.keypoints).max()  # a visible change
