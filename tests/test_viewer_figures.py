"""kpd.viewer.figures: the pictures of the library's results, drawn from what the library returns."""

from __future__ import annotations

import numpy as np

from kpd.collection import CollectionAlignment, CollectionShape
from kpd.io.images import read_png
from kpd.train.evaluate import GalleryPairs
from kpd.viewer.figures import alignment_gallery, contact_sheet


def _box_cloud(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, (600, 3)) * [2.0, 1.0, 0.5]
    return points


def test_contact_sheet_draws_every_shape_and_flags_in_red(tmp_path):
    clouds = [_box_cloud(i) for i in range(3)]
    shapes = [CollectionShape(f"shape{i}", np.eye(3), 0.01, 0.02, 90.0, 1.0, i == 2, template=i == 0)
              for i in range(3)]
    alignment = CollectionAlignment(shapes, np.stack([np.eye(3)] * 3), ["shape0"], [], True, np.zeros(3))
    path = tmp_path / "sheet.png"
    contact_sheet(clouds, alignment, path, up="z", columns=3)
    image = read_png(path).astype(int)
    h, w, _ = image.shape
    assert w > h  # three cells side by side
    drawn = (np.abs(image - 255).sum(axis=2) > 60)
    for column in range(3):  # a shape in every cell
        assert drawn[h // 4:, column * w // 3:(column + 1) * w // 3].mean() > 0.01
    red = (image[..., 0] > 150) & (image[..., 1] < 80) & (image[..., 2] < 80)
    assert red[:, 2 * w // 3:].sum() > 10 and red[:, : 2 * w // 3].sum() == 0  # only the flagged caption is red


def test_alignment_gallery_from_the_evaluation_pairs(tmp_path):
    rng = np.random.default_rng(0)
    sources, targets = rng.normal(size=(2, 300, 3)), rng.normal(size=(2, 300, 3))
    pairs = GalleryPairs(sources=sources, targets=targets, deformed={"model": targets + 0.01},
                         keypoints={"model": (sources[:, :4], targets[:, :4])}, titles=["a -> b", "c -> d"],
                         scores={"no_deformation": np.array([3.0, 4.0]), "model": np.array([1.0, 2.0])})
    path = tmp_path / "gallery.png"
    alignment_gallery(path, pairs.sources, pairs.targets, pairs.deformed, pairs.keypoints, titles=pairs.titles,
                      scores=pairs.scores)
    image = read_png(path)
    assert image.shape[0] > 200 and image.shape[1] > image.shape[0]  # two rows of three panels
    assert (np.abs(image.astype(int) - 255).sum(axis=2) > 60).mean() > 0.02
