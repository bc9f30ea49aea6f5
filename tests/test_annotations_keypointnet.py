"""kpd.annotations.keypointnet: the KeypointNet reader on real data and its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kpd import annotations as ann
from kpd.errors import DataError
from kpd.io import read_points
from kpd.metrics import point_triangle_distance

CHAIR = "03001627"
PCD_CHAIR = "88382b877be91b2a572f8e1c1caad99e"  # KeypointNet cloud + ShapeNet v2 mesh
FITTED_CHAIRS = ("eaf231f17fccb96d81dff5c2e57ad46e", "fe6b3c001a86d844d5767a0de8dd037e")  # deep_cage meshes


def test_keypointnet_reader(chairs, kpn_root):
    assert len(chairs) == 999 and chairs.synset == CHAIR
    assert (len(chairs.ids("train")), len(chairs.ids("val")), len(chairs.ids("test"))) == (699, 100, 200)
    assert chairs.get(FITTED_CHAIRS[0]).split == "test"
    # the paper's subset: semantic ids present together in more than 80% of the chairs
    np.testing.assert_array_equal(chairs.common_semantic_ids(), [0, 1, 2, 3, 4, 5, 17, 18, 19, 20])
    # annotations are points of KeypointNet's own cloud
    model = chairs.get(PCD_CHAIR)
    cloud = read_points(kpn_root / "pcds" / CHAIR / f"{PCD_CHAIR}.pcd").points
    np.testing.assert_allclose(cloud[model.pcd_index], model.keypoints, atol=1e-5)
    assert ann.KeypointNet(kpn_root, CHAIR).category == "chair"  # a synset works too


def test_keypointnet_errors(tmp_path, kpn_root):
    with pytest.raises(DataError, match="not a KeypointNet folder"):
        ann.KeypointNet(tmp_path, "chair")
    with pytest.raises(DataError, match=r"for 'lamp'.*\(available: (\w+, )*chair"):
        ann.KeypointNet(kpn_root, "lamp")  # the data has chair and airplane annotations, no lamps
    (tmp_path / "annotations").mkdir()
    (tmp_path / "annotations" / "chair.json").write_text(json.dumps([{"model_id": "a", "keypoints": [{"xyz": [1]}]}]))
    with pytest.raises(DataError, match="model 0 \\(a\\): malformed"):
        ann.KeypointNet(tmp_path, "chair")
    (tmp_path / "annotations" / "chair.json").write_text("[")
    with pytest.raises(DataError, match="not valid JSON"):
        ann.KeypointNet(tmp_path, "chair")
    (tmp_path / "annotations" / "chair.json").write_text(json.dumps(
        [{"model_id": "a", "keypoints": [{"xyz": [0, 0, 0], "semantic_id": 0}]}]))
    with pytest.raises(DataError, match="no splits/ folder"):
        ann.KeypointNet(tmp_path, "chair").ids("test")
    with pytest.raises(DataError, match="no 7 or more semantic ids"):
        ann.KeypointNet(tmp_path, "chair").common_semantic_ids()


def test_shapenet_v2_mesh_needs_no_fit(tmp_path, kpn_root):
    """Without the cloud, the ShapeNet v2 mesh of the same model is in the annotations' frame already."""
    (tmp_path / "annotations").symlink_to(kpn_root / "annotations")
    (tmp_path / "models").symlink_to(kpn_root / "models")
    shapes, _ = ann.keypointnet_shapes(ann.KeypointNet(tmp_path, "chair"), "all")
    s = {x.model_id: x for x in shapes}[PCD_CHAIR]
    assert s.frame == "keypointnet" and s.path.name == "model_normalized.obj"
    d = point_triangle_distance(s.keypoints, s.normalizer.apply(s.geometry.vertices), s.geometry.triangles)
    assert d.max() <= 0.01
