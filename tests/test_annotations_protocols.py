"""kpd.annotations.protocols: part correspondence, the parts protocol with keypoint files,
seeded alignment pairs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kpd import annotations as ann
from kpd.errors import DataError
from kpd.io import write_keypoints
from kpd.metrics import part_correspondence

PART_CHAIR = "1015e71a0d21b127de03ab2a27ba7531"  # ShapeNetPart points, also annotated in KeypointNet


def test_part_score_of_perfect_random_and_relabelled_keypoints(part_shapes):
    """On each category's part-labelled shape: keypoints on the parts score 1.0, keypoints placed at random in the
    box far lower, and relabelling the parts changes nothing."""
    rng = np.random.default_rng(0)
    random_scores = []
    for name, s in part_shapes.items():
        parts = np.unique(s.labels)
        perfect = np.stack([s.points[np.flatnonzero(s.labels == p)[len(parts)]] for p in parts] +
                           [s.points[i] for i in rng.choice(len(s.points), 6, replace=False)])
        result = part_correspondence([perfect], [s.points], [s.labels])
        assert result.score == 1.0 and result.part_score == 1.0, name
        assert (np.diag(result.frequency[: len(parts)]) == 1.0).all()  # each on its own part (maybe others too)
        random = rng.uniform(-1, 1, (12, 3))
        score = part_correspondence([random], [s.points], [s.labels]).score
        random_scores.append(score)
        new = rng.permutation(100)[: len(parts)] + 7
        relabelled = new[np.searchsorted(parts, s.labels)]
        for keypoints in (perfect, random):
            a = part_correspondence([keypoints], [s.points], [s.labels])
            b = part_correspondence([keypoints], [s.points], [relabelled])
            assert (a.score, a.part_score) == (b.score, b.part_score)
    assert max(random_scores) <= 0.5 and np.mean(random_scores) < 0.2, random_scores


def test_parts_protocol_with_files(part_root, part_shapes, tmp_path):
    s = part_shapes["chair"]
    keypoints = np.stack([s.points[np.flatnonzero(s.labels == p)[0]] for p in (1, 2, 3)])
    write_keypoints(tmp_path / f"{PART_CHAIR}.json", s.normalizer.invert(keypoints))  # .pts coordinates
    result = ann.parts_protocol(ann.ShapeNetPart(part_root), "chair", ann.FileKeypoints(tmp_path), split="all")
    assert result["results"]["score"] == 1.0 and result["results"]["best_part"] == [1, 2, 3]
    assert result["data"]["shapes"][0]["id"] == PART_CHAIR
    json.dumps(result, allow_nan=False)


def test_alignment_pairs_match_training_evaluation():
    from kpd.train import evaluate  # torch: the [train] extra, which make test installs

    for n, count, seed in ((2, 5, 0), (99, 200, 0), (17, 30, 4)):
        np.testing.assert_array_equal(ann.alignment_pairs(n, count, seed), evaluate.fixed_pairs(n, count, seed))
    with pytest.raises(DataError, match="at least 2"):
        ann.alignment_pairs(1, 3)
