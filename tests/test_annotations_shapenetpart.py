"""kpd.annotations.shapenetpart: the ShapeNetPart reader on real data."""

from __future__ import annotations

import numpy as np
import pytest

from kpd import annotations as ann
from kpd.errors import DataError

CHAIR = "03001627"
PART_CHAIR = "1015e71a0d21b127de03ab2a27ba7531"  # ShapeNetPart points, also annotated in KeypointNet


def test_shapenetpart_reader(part_root, tmp_path):
    parts = ann.ShapeNetPart(part_root)
    assert len(parts.categories) == 16 and parts.synset("Chair") == CHAIR and parts.synset(CHAIR) == CHAIR
    assert parts.ids("chair") == [PART_CHAIR] and parts.ids("chair", "train") == [PART_CHAIR]
    with pytest.raises(DataError, match="shuffled_test_file_list.json; use split 'all' or one of train"):
        parts.ids("chair", "test")
    with pytest.raises(DataError, match="not in"):
        parts.synset("sofa")
    shape = parts.load("chair", PART_CHAIR)
    assert shape.points.shape == (2750, 3) and set(np.unique(shape.labels)) == {1, 2, 3}
    # a label file that does not match its points
    bad = tmp_path / "spn"
    (bad / CHAIR / "points").mkdir(parents=True)
    (bad / CHAIR / "points_label").mkdir()
    (bad / "synsetoffset2category.txt").write_text("Chair\t03001627\n")
    (bad / CHAIR / "points" / "x.pts").write_text("0 0 0\n1 1 1\n")
    (bad / CHAIR / "points_label" / "x.seg").write_text("1\n")
    with pytest.raises(DataError, match="1 labels for the 2 points"):
        ann.ShapeNetPart(bad).load("chair", "x")
    with pytest.raises(DataError, match="not a ShapeNetPart folder"):
        ann.ShapeNetPart(tmp_path)
