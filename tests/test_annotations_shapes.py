"""kpd.annotations.shapes: annotated models and point clouds in the evaluation frame."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from kpd import annotations as ann
from kpd.errors import DataError
from kpd.metrics import point_triangle_distance

PCD_CHAIR = "88382b877be91b2a572f8e1c1caad99e"  # KeypointNet cloud + ShapeNet v2 mesh
FITTED_CHAIRS = ("eaf231f17fccb96d81dff5c2e57ad46e", "fe6b3c001a86d844d5767a0de8dd037e")  # deep_cage meshes
PART_CHAIR = "1015e71a0d21b127de03ab2a27ba7531"  # ShapeNetPart points, also annotated in KeypointNet


def test_annotations_land_on_the_surface(chair_shapes, part_root):
    """Every KeypointNet keypoint of every annotated chair with geometry lies on its surface after the mapping
    (<= 0.01 in the [-1, 1] box; for the ShapeNetPart cloud, within the cloud's own point spacing)."""
    shapes, skipped = chair_shapes
    assert set(shapes) == {PCD_CHAIR, *FITTED_CHAIRS, PART_CHAIR}
    assert len(skipped) == 995 and {s.reason for s in skipped} == {"no geometry"}
    cloud = shapes[PCD_CHAIR]
    assert cloud.frame == "keypointnet"
    assert cKDTree(cloud.points).query(cloud.keypoints)[0].max() < 1e-5
    for model_id in FITTED_CHAIRS:
        s = shapes[model_id]
        assert s.frame == "fitted:keypointnet-to-reference"  # no mirror needed: the same chair, another frame
        d = point_triangle_distance(s.keypoints, s.normalizer.apply(s.geometry.vertices), s.geometry.triangles)
        assert d.max() <= 0.01, (model_id, d.max())
        assert s.fit_distance == pytest.approx(d.max())
        assert np.abs(s.points).max() == pytest.approx(1.0, abs=0.02)
    part = shapes[PART_CHAIR]
    tree = cKDTree(part.points)
    spacing = tree.query(part.points, k=2)[0][:, 1]
    assert tree.query(part.keypoints)[0].max() <= np.percentile(spacing, 90)


def test_point_cloud_shapes(kpn_root, part_root, tmp_path):
    clouds, kind = ann.point_cloud_shapes(kpn_root, "chair")
    assert kind == "keypointnet" and [s.model_id for s in clouds] == [PCD_CHAIR]
    clouds, kind = ann.point_cloud_shapes(part_root, "chair")
    assert kind == "shapenetpart" and len(clouds) == 1
    with pytest.raises(DataError, match="neither"):
        ann.point_cloud_shapes(tmp_path, "chair")
