"""kpd deform, render, view and rig bind a mesh once: one surface sample serves the frame check and the rig
(kpd.commands.keypoints.rig_checked), with the same warnings and the same rig as drawing it twice."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import TURN_ONTO_SIDE

from kpd.io import Mesh, read_mesh


@pytest.fixture(scope="module")
def turned_chair(data_dir):
    chair = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")
    return Mesh(chair.vertices @ TURN_ONTO_SIDE.T, chair.triangles)


def test_frame_check_on_the_predictions_sample_is_the_check_on_a_fresh_one(chair_model, turned_chair):
    from kpd.commands.keypoints import frame_lines
    from kpd.frame import frame_warnings

    fresh = frame_warnings(chair_model, turned_chair, seed=3, name="turned.ply")
    assert len(fresh) == 1 and "turned" in fresh[0]
    prediction = chair_model.predict(turned_chair, seed=3)
    assert frame_lines(chair_model, turned_chair, 3, "turned.ply", prediction=prediction) == fresh


def test_rig_checked_samples_once_and_binds_as_model_rig(chair_model, turned_chair, capsys, monkeypatch):
    from kpd.commands.keypoints import rig_checked
    from kpd.runtime import Model

    expected = chair_model.rig(turned_chair, seed=1)
    calls = []
    sample = Model.sample

    def counted(self, shape, *, seed=0):
        calls.append(seed)
        return sample(self, shape, seed=seed)

    monkeypatch.setattr(Model, "sample", counted)
    rig = rig_checked(chair_model, turned_chair, 1, "turned.ply")
    assert calls == [1]  # one surface sample for the check and the rig
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and "turned.ply" in err and "--scan" in err
    np.testing.assert_array_equal(rig.keypoints, expected.keypoints)
    edit = expected.keypoints + np.linspace(-0.05, 0.05, expected.keypoints.size).reshape(-1, 3)
    np.testing.assert_array_equal(rig.deform(edit), expected.deform(edit))


def test_rig_checked_refuses_a_mesh_too_large_for_memory_before_any_work(chair_model, turned_chair, monkeypatch):
    import kpd.memory
    from kpd.commands.keypoints import rig_checked
    from kpd.errors import InputError
    from kpd.runtime import Model

    monkeypatch.setattr(kpd.memory, "available_memory", lambda: 1 << 20)
    monkeypatch.setattr(Model, "sample", lambda *a, **k: pytest.fail("sampled before the memory check"))
    with pytest.raises(InputError, match="to bind; 1 MiB of memory is available"):
        rig_checked(chair_model, turned_chair, 0, "turned.ply")
