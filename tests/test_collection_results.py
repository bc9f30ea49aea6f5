"""kpd.collection.results: a collection's result reports its flagged shapes and converts to JSON."""

from __future__ import annotations

import json
import math

import numpy as np

from kpd.collection.results import CollectionAlignment, CollectionShape


def test_flags_and_json():
    shapes = [CollectionShape("a", np.eye(3), 0.01, 0.03, 120.0, 2.0, False, template=True),
              CollectionShape("b", np.eye(3)[[1, 0, 2]] * [1, 1, -1], 0.02, 0.021, 90.0, 0.05, True,
                              decided_by="undecided")]
    result = CollectionAlignment(shapes, np.stack([s.rotation for s in shapes]), ["a"], [], True, np.array([1.0, 2.0]))
    assert result.ambiguous.tolist() == [False, True]
    data = result.to_dict()
    json.dumps(data, allow_nan=False)  # JSON-safe
    assert data["shapes"][1]["ambiguous"] is True and data["shapes"][0]["template"] is True
    np.testing.assert_array_equal(np.array(data["shapes"][1]["transform"])[:3, :3], shapes[1].rotation)
    assert data["shapes"][0]["tilt"] is None and data["ambiguous"] == 1 and data["count"] == 2
    back = CollectionShape.from_dict(data["shapes"][1])
    assert back.name == "b" and back.ambiguous and back.margin == 0.05 and back.decided_by == "undecided"
    np.testing.assert_array_equal(back.rotation, shapes[1].rotation)
    assert math.isnan(shapes[0].tilt)
