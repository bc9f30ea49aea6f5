"""kpd.viewer.labels: keypoint numbers drawn into images where and in the colour asked; PNG round trip."""

from __future__ import annotations

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.io.images import read_png, write_png
from kpd.viewer.camera import camera_pose
from kpd.viewer.labels import label_image_at, overlay_labels
from kpd.viewer.settings import ViewSettings, keypoint_palette


def test_palette_labels_and_png_round_trip(tmp_path):
    colors = keypoint_palette(20)
    assert colors.shape == (20, 3) and len(np.unique(np.round(colors, 3), axis=0)) == 20
    image = np.full((60, 80, 3), 255, np.uint8)
    out = overlay_labels(image, [[10, 30], [50, 50]], ["3", "12"], colors[:2], scale=2)
    assert (out != 255).any(axis=2).sum() > 50 and (image == 255).all()
    path = write_png(tmp_path / "a.png", out)
    np.testing.assert_array_equal(read_png(path), out)
    with pytest.raises(InputError, match="uint8"):
        write_png(tmp_path / "b.png", out.astype(float))


def test_labels_land_beside_their_keypoints_in_their_colours():
    keypoints = np.array([[-0.6, 0.0, 0.0], [0.6, 0.0, 0.0]])
    camera = camera_pose(np.vstack([keypoints, [[0, 0, 0.5], [0, 0, -0.5]]]), ViewSettings(width=200, height=150))
    image = np.full((150, 200, 3), 255, np.uint8)
    out = label_image_at(image, keypoints, 0.05, camera)
    changed = (out != 255).any(axis=2)
    columns = np.flatnonzero(changed.any(axis=0))
    left, right = columns[columns < 100], columns[columns >= 100]
    assert len(left) and len(right)  # one number on each side
    palette = (keypoint_palette(2) * 0.75 * 255).astype(int)
    inks = {tuple(c) for c in out[changed].astype(int).tolist()}
    assert {tuple(p) for p in palette.tolist()} <= inks  # each in its keypoint's colour (and a white halo)
    hidden = label_image_at(image, keypoints + [0, 0, 100], 0.05, camera)  # behind the camera: not drawn
    assert ((hidden != 255).any(axis=2)).sum() <= changed.sum()
