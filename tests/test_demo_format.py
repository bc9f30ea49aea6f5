"""The authors' project-page demo format: a rig written as its text tables reads back as the same rig."""

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.rig import Rig
from rig_shapes import corner_rig


def write_demo(rig: Rig, folder, *, shuffle_seed=0, with_weights=True):
    """Write a rig in the authors' project-page format, with the cage vertices in another order."""
    folder.mkdir()
    order = np.random.default_rng(shuffle_seed).permutation(len(rig.cage.vertices))
    vertices = rig.normalizer.apply(rig.mesh.vertices)
    np.savetxt(folder / "source_vertices.txt", vertices)
    np.savetxt(folder / "source_faces.txt", rig.mesh.triangles.astype(float))
    kp = rig.normalizer.apply(rig.keypoints)
    with open(folder / "source_keypoints.txt", "w") as fh:
        for i, p in enumerate(kp):
            fh.write("%03d %f %f %f\n" % (i, *p))
    np.savetxt(folder / "cage.txt", rig.cage.vertices[order])
    np.savetxt(folder / "influence.txt", rig.influence[:, order])
    if with_weights:
        np.savetxt(folder / "weights.txt", rig.weights[:, order])
    return vertices


@pytest.mark.parametrize("with_weights", [True, False])
def test_from_demo_recovers_the_rig(tmp_path, with_weights):
    rig = corner_rig()
    vertices = write_demo(rig, tmp_path / "demo", with_weights=with_weights)
    demo = Rig.from_demo(tmp_path / "demo")
    assert len(demo.cage.faces) == 80
    scale = rig.normalizer.scale_
    kp = demo.keypoints + np.array([[0.0, 0.05, 0.0]] * 8) * (np.arange(8) == 2)[:, None]
    expected = rig.normalizer.apply(rig.deform(rig.normalizer.invert(kp)))
    np.testing.assert_allclose(demo.deform(kp), expected, atol=1e-5 if with_weights else 1e-6 * scale)
    np.testing.assert_allclose(demo.deform(demo.keypoints), vertices, atol=1e-12)


def test_from_demo_errors(tmp_path):
    with pytest.raises(InputError, match="not a folder"):
        Rig.from_demo(tmp_path / "none")
    rig = corner_rig()
    write_demo(rig, tmp_path / "demo")
    (tmp_path / "demo" / "cage.txt").unlink()
    with pytest.raises(InputError, match="cage.txt: missing demo file"):
        Rig.from_demo(tmp_path / "demo")


# --- real data -------------------------------------------------------------------------------------------------
