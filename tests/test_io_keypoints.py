"""kpd.io.keypoints: JSON and the authors' text rows, exact round trips, clear refusals."""

from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from helpers import finite, write_text

from kpd.errors import InputError
from kpd.io import read_keypoints, write_keypoints


def test_keypoints_json_round_trip_with_metadata(tmp_path):
    k = np.random.default_rng(2).normal(size=(10, 3))
    path = tmp_path / "k.json"
    write_keypoints(path, k, category="chair", k=np.int64(10), scale=np.float32(0.5), frame=np.eye(3))
    np.testing.assert_array_equal(read_keypoints(path), k)
    data = json.loads(path.read_text())
    assert data["category"] == "chair" and data["k"] == 10 and data["frame"][0] == [1, 0, 0]


def test_keypoints_txt_in_the_authors_format(tmp_path):
    k = np.array([[0.125, -1.5, 2.0], [1e-8, 3.0, -0.0]])
    write_keypoints(tmp_path / "k.txt", k)
    lines = (tmp_path / "k.txt").read_text().splitlines()
    assert re.fullmatch(r"000 0\.125 -1\.5 2\.0", lines[0]) and lines[1].startswith("001 ")
    np.testing.assert_array_equal(read_keypoints(tmp_path / "k.txt"), k)
    authors = write_text(tmp_path / "source_keypoints.txt", "000 0.100000 0.200000 0.300000\n001 1 2 3\n")
    np.testing.assert_array_equal(read_keypoints(authors), [[0.1, 0.2, 0.3], [1, 2, 3]])
    plain = write_text(tmp_path / "plain.txt", "0.1 0.2 0.3\n")
    np.testing.assert_array_equal(read_keypoints(plain), [[0.1, 0.2, 0.3]])


@settings(max_examples=30, deadline=None)
@given(k=st.integers(1, 20).flatmap(lambda n: arrays(np.float64, (n, 3), elements=finite)),
       ext=st.sampled_from(["json", "txt"]))
def test_any_keypoints_round_trip_exactly(k, ext, tmp_path_factory):
    path = tmp_path_factory.mktemp("kp") / f"k.{ext}"
    write_keypoints(path, k)
    np.testing.assert_array_equal(read_keypoints(path), k)


def test_keypoint_errors(tmp_path):
    bare = write_text(tmp_path / "bare.json", "[[1, 2, 3], [4, 5, 6]]")
    assert read_keypoints(bare).shape == (2, 3)
    with pytest.raises(InputError, match=r"other\.json: expected the key 'keypoints'; found \['points'\]"):
        read_keypoints(write_text(tmp_path / "other.json", '{"points": []}'))
    with pytest.raises(InputError, match=r"flat\.json: keypoints must have shape \(N, 3\); got \(3,\)"):
        read_keypoints(write_text(tmp_path / "flat.json", '{"keypoints": [1, 2, 3]}'))
    with pytest.raises(InputError, match=r"broken\.json: not valid JSON"):
        read_keypoints(write_text(tmp_path / "broken.json", '{"keypoints": ['))
    with pytest.raises(InputError, match=r"must count 0, 1, 2"):
        read_keypoints(write_text(tmp_path / "idx.txt", "000 0 0 0\n005 1 1 1\n"))
    with pytest.raises(InputError, match="cannot hold metadata"):
        write_keypoints(tmp_path / "m.txt", np.zeros((2, 3)), category="chair")
    with pytest.raises(InputError, match="not JSON-serialisable"):
        write_keypoints(tmp_path / "m.json", np.zeros((2, 3)), thing=object())
    with pytest.raises(InputError, match=r"1 keypoint has NaN"):
        write_keypoints(tmp_path / "n.json", [[0, 0, np.nan]])
    assert sorted(os.listdir(tmp_path)) == ["bare.json", "broken.json", "flat.json", "idx.txt", "other.json"]
