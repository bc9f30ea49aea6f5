"""kpd.annotations.sources: keypoints from files and from a model, in the evaluation frame
and back."""

from __future__ import annotations

import numpy as np
import pytest

from kpd import annotations as ann
from kpd.errors import InputError
from kpd.io import Mesh, write_keypoints

CHAIR = "03001627"
PCD_CHAIR = "88382b877be91b2a572f8e1c1caad99e"  # KeypointNet cloud + ShapeNet v2 mesh
FITTED_CHAIRS = ("eaf231f17fccb96d81dff5c2e57ad46e", "fe6b3c001a86d844d5767a0de8dd037e")  # deep_cage meshes
PART_CHAIR = "1015e71a0d21b127de03ab2a27ba7531"  # ShapeNetPart points, also annotated in KeypointNet


def test_file_keypoints_frames(chair_shapes, tmp_path):
    shapes, _ = chair_shapes
    chosen = [shapes[PCD_CHAIR], shapes[FITTED_CHAIRS[0]]]
    for frame in ("file", "unit"):
        folder = tmp_path / frame
        folder.mkdir()
        for s in chosen:
            k = s.keypoints[:5]
            if frame == "file":
                k = s.file_to_reference.inverse().apply(s.normalizer.invert(k))
            write_keypoints(folder / f"{CHAIR}-{s.model_id}.json", k)
        got, skipped = ann.FileKeypoints(folder, frame=frame)(chosen + [shapes[PART_CHAIR]])
        assert got[2] is None and skipped[0].model_id == PART_CHAIR
        for s, k in zip(chosen, got[:2]):
            np.testing.assert_allclose(k, s.keypoints[:5], atol=1e-9)
    with pytest.raises(InputError, match="does not exist"):
        ann.FileKeypoints(tmp_path / "missing")


class _TopModel:
    """A stand-in for kpd.runtime.Model whose one 'keypoint' is the highest point (max z: ModelNet's up)."""

    up = "+z"
    num_keypoints = 1
    category = "chair"

    class bundle:  # noqa: N801
        path = "top.kpd"

    def keypoints_batch(self, shapes, seed=0):
        out = []
        for s in shapes:
            pts = s.vertices if isinstance(s, Mesh) else np.asarray(s)
            out.append(pts[[np.argmax(pts[:, 2])]])
        return np.stack(out)


def test_model_keypoints_rotate_into_the_model_frame_and_back(chair_shapes):
    shapes, _ = chair_shapes
    chosen = [shapes[PCD_CHAIR], shapes[FITTED_CHAIRS[1]], shapes[PART_CHAIR]]
    got, skipped = ann.ModelKeypoints(_TopModel())(chosen)
    assert not skipped
    for s, k in zip(chosen, got):
        geometry = s.geometry.vertices if isinstance(s.geometry, Mesh) else s.geometry
        top = s.normalizer.apply(geometry[[np.argmax(geometry[:, 1])]])  # y up in the reference frame
        np.testing.assert_allclose(k, top, atol=1e-12)
        assert k[0, 1] > 0.9  # near the top of the [-1, 1] box
    with pytest.raises(InputError, match="'\\+y' or '\\+z'"):
        ann.ModelKeypoints(_TopModel(), up="-x")
