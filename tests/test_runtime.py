"""kpd.runtime.Model on a torch-free toy bundle (helpers.make_toy_bundle) and real meshes."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import make_toy_bundle, toy_reference, toy_weights

from kpd.errors import BundleError, InputError
from kpd.io import Mesh, PointSet
from kpd.rig import Rig
from kpd.runtime import Model

K, C = 4, 42


@pytest.fixture(scope="module")
def bundle_path(tmp_path_factory):
    return make_toy_bundle(tmp_path_factory.mktemp("bundle") / "toy.kpd", k=K, c=C)


@pytest.fixture(scope="module")
def model(bundle_path):
    return Model.load(bundle_path, threads=1)


def box_mesh(divisions: int = 6, size=(1.0, 2.0, 3.0)) -> Mesh:
    """A closed box surface made of a grid of triangles, with vertex colours."""
    from kpd.procedural import box_mesh as grid_box

    vertices, triangles = grid_box(np.zeros(3), np.asarray(size, float), edge=max(size) / divisions)
    colours = (vertices - vertices.min(0)) / np.ptp(vertices, axis=0)
    return Mesh(vertices=vertices, triangles=triangles, vertex_colors=colours)


@pytest.fixture(scope="module")
def chair(data_dir):
    from kpd.io import read_mesh

    return read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")


def test_run_matches_reference(model):
    points = np.random.default_rng(0).uniform(-1, 1, (3, 200, 3)).astype(np.float32)
    keypoints, influence = model.run(points)
    want_k, want_w = toy_reference(points, toy_weights(K, C), K, C)
    assert keypoints.shape == (3, K, 3) and influence.shape == (3, K, C)
    np.testing.assert_allclose(keypoints, want_k, atol=1e-5)
    np.testing.assert_allclose(influence, want_w, atol=1e-5)
    single_k, single_w = model.run(points[1])
    np.testing.assert_allclose(single_k, keypoints[1], atol=1e-6)
    assert single_w.shape == (K, C)


def test_run_checks_input(model):
    with pytest.raises(InputError, match=r"shape \(B, N, 3\) or \(N, 3\)"):
        model.run(np.zeros((2, 10, 4)))
    with pytest.raises(InputError, match="finite"):
        model.run(np.full((5, 3), np.nan))


def test_properties(model):
    assert (model.num_keypoints, model.num_cage_vertices, model.m, model.point_count) == (K, C, 5, 256)
    assert model.category == "toy" and model.up == "+z"
    assert model.prior is not None and model.template_points.shape == (100, 3)
    assert "K=4" in repr(model)


def test_same_input_same_keypoints(model):
    mesh = box_mesh()
    first = model.keypoints(mesh)
    np.testing.assert_array_equal(first, model.keypoints(mesh))
    np.testing.assert_array_equal(first, Model.load(model.bundle.path).keypoints(mesh))
    assert not np.array_equal(first, model.keypoints(mesh, seed=1))


def test_keypoints_follow_the_shape_frame(model):
    """Keypoints come back in the input's frame: scaling and moving the input scales and moves them."""
    mesh = box_mesh()
    scale, shift = 37.5, np.array([100.0, -20.0, 3.0])
    moved = mesh.with_vertices(mesh.vertices * scale + shift)
    np.testing.assert_allclose(model.keypoints(moved), model.keypoints(mesh) * scale + shift, atol=1e-6 * scale)
    prediction = model.predict(mesh)
    np.testing.assert_allclose(prediction.normalizer.invert(prediction.keypoints), model.keypoints(mesh))
    assert prediction.points.shape == (256, 3) and np.abs(prediction.points).max() <= 1 + 1e-9


def test_influence_is_shared_plus_instance(model):
    mesh = box_mesh()
    prediction = model.predict(mesh)
    _, offset = model.run(prediction.points)
    np.testing.assert_allclose(model.influence(mesh), model.shared_influence + offset, atol=1e-12)


def test_point_sets_and_arrays(model):
    rng = np.random.default_rng(1)
    cloud = rng.uniform(-3, 5, (1000, 3))
    from_array = model.keypoints(cloud)
    np.testing.assert_array_equal(from_array, model.keypoints(PointSet(cloud)))
    small = cloud[:50]  # fewer than point_count: all points are used
    normalizer, points = model.sample(small)
    assert len(points) == 50
    np.testing.assert_allclose(normalizer.invert(points), small)
    with pytest.raises(InputError):
        model.keypoints(np.zeros((10, 2)))


def test_batches_equal_single_calls(model):
    rng = np.random.default_rng(2)
    shapes = [box_mesh(), rng.uniform(-1, 1, (40, 3)), box_mesh(size=(3, 1, 1)), rng.uniform(0, 9, (700, 3))]
    batch = model.keypoints_batch(shapes, batch_size=3)
    single = np.stack([model.keypoints(s) for s in shapes])
    np.testing.assert_allclose(batch, single, atol=1e-5)
    np.testing.assert_allclose(model.influence_batch(shapes), np.stack([model.influence(s) for s in shapes]),
                               atol=1e-5)
    assert model.keypoints_batch([]).shape == (0, K, 3)
    with pytest.raises(InputError, match="batch_size"):
        model.keypoints_batch(shapes, batch_size=0)


def test_rig_and_zero_edit(model, chair):
    rig = model.rig(chair)
    assert isinstance(rig, Rig) and rig.num_keypoints == K and rig.influence.shape == (K, C)
    np.testing.assert_allclose(rig.keypoints, model.keypoints(chair), atol=1e-9)
    np.testing.assert_array_equal(rig.deform(rig.keypoints), chair.vertices)
    from kpd.cage import points_outside

    assert not points_outside(rig.normalizer.apply(chair.vertices), rig.cage.vertices, rig.cage.faces).any()
    loose = model.rig(chair, enclose=False)  # the authors' cage alone
    assert np.linalg.norm(loose.cage.vertices, axis=1).max() <= np.linalg.norm(rig.cage.vertices, axis=1).max()
    with pytest.raises(InputError, match="a rig needs a triangle mesh"):
        model.rig(PointSet(chair.vertices))


def test_align_uses_the_sources_frame(model, chair, data_dir):
    from kpd.io import read_mesh

    # aligning a shape to itself changes nothing
    np.testing.assert_array_equal(model.align(chair, chair).vertices, chair.vertices)
    # the target's position and size do not matter, only its shape
    target = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0891.ply")
    far = target.with_vertices(target.vertices * 0.01 + 500.0)
    a, b = model.align(chair, target), model.align(chair, far)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6 * np.ptp(chair.vertices))
    assert a.triangles is chair.triangles or np.array_equal(a.triangles, chair.triangles)
    # the deformed source's keypoints frame: rig keypoints moved onto the target's, mapped by the source's normaliser
    rig = model.rig(chair)
    expected = rig.deform(rig.normalizer.invert(model.predict(target).keypoints))
    np.testing.assert_allclose(a.vertices, expected, atol=1e-9)
    many = model.align_batch(chair, [target, far])
    np.testing.assert_allclose(many[0].vertices, a.vertices, atol=1e-9)


def test_sync_in_user_units(model, chair):
    rig = model.rig(chair)
    target = rig.keypoints[1] + [0.0, 0.0, 2.0]
    synced = model.sync(rig, {1: target})
    np.testing.assert_array_equal(synced[1], target)
    assert np.abs(synced - rig.keypoints).max() > 0
    np.testing.assert_array_equal(model.sync(rig, {}), rig.keypoints)
    variants = model.sample_keypoints(rig, 5, seed=0, scale=0.5)
    assert variants.shape == (5, K, 3)
    np.testing.assert_allclose(model.sample_keypoints(rig, 2, scale=0.0)[0], rig.keypoints, atol=1e-9)


def test_missing_prior_is_named(tmp_path, chair):
    bare = Model.load(make_toy_bundle(tmp_path / "bare.kpd", prior=False, template=False))
    rig = bare.rig(chair)
    with pytest.raises(BundleError, match="has no keypoint prior"):
        bare.sync(rig, {0: rig.keypoints[0]})
    assert bare.template_points is None


def test_graph_disagreeing_with_manifest_refused(tmp_path):
    with pytest.raises(BundleError, match=r"output 'keypoints' has shape \['batch', 5, 3\]; expected \[batch, 4, 3\]"):
        Model.load(make_toy_bundle(tmp_path / "k5.kpd", graph_k=5, prior=False))
    with pytest.raises(BundleError, match="graph format version '9'"):
        Model.load(make_toy_bundle(tmp_path / "v9.kpd", meta_version="9"))


def test_thread_settings(bundle_path):
    assert Model.load(bundle_path, threads=2, inter_op_threads=1).num_keypoints == K
    assert Model.load(bundle_path, threads=1, spinning=True).num_keypoints == K
    with pytest.raises(InputError, match="threads must be a non-negative integer"):
        Model.load(bundle_path, threads=-1)


def test_runtime_runs_without_torch(bundle_path):
    code = (
        "import sys, numpy as np\n"
        "sys.modules['torch'] = None  # any import of torch now fails\n"
        "from kpd.runtime import Model\n"
        f"m = Model.load({str(bundle_path)!r})\n"
        "print(m.keypoints(np.random.default_rng(0).uniform(-1, 1, (300, 3))).shape)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "(4, 3)"


_PREDICT = """
import sys
from kpd.io import read_mesh
from kpd.runtime import Model
print(Model.load("chair").keypoints(read_mesh(sys.argv[1])).shape)
"""


@pytest.mark.parametrize("user_setting", [None, "0"])
def test_inference_leaves_nothing_of_onnxruntime_s_reporting_behind(data_dir, tmp_path, user_setting):
    """onnxruntime's own builds report to Microsoft unless ORT_DISABLE_TELEMETRY is set before it starts (a device id
    under ~/.cache, a session file in the temporary folder and the working folder, events uploaded): kpd sets it, so
    predicting writes nothing in the home, temporary or working folder. A user who sets it to 0 is obeyed (which is
    how this test can fail: onnxruntime then writes its files)."""
    home, temporary, work = tmp_path / "home", tmp_path / "tmp", tmp_path / "work"
    for folder in (home, temporary, work):
        folder.mkdir()
    # onnxruntime reports nothing where a CI service is named (CI, GITHUB_ACTIONS, JENKINS_URL, TF_BUILD): a user's
    # machine names none
    unset = ("ORT_DISABLE_TELEMETRY", "XDG_CACHE_HOME", "CI", "GITHUB_ACTIONS", "JENKINS_URL", "TF_BUILD")
    env = {k: v for k, v in os.environ.items() if k not in unset}
    env.update(HOME=str(home), TMPDIR=str(temporary))
    if user_setting is not None:
        env["ORT_DISABLE_TELEMETRY"] = user_setting
    chair = data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply"
    done = subprocess.run([sys.executable, "-c", _PREDICT, str(chair)], env=env, cwd=work, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["(12,", "3)"]
    left = [p for folder in (home, temporary, work) for p in folder.rglob("*")]
    if user_setting is None:
        assert left == []
    else:  # onnxruntime 1.29 and later on Linux; earlier ones report nothing here
        import onnxruntime

        if tuple(int(x) for x in onnxruntime.__version__.split(".")[:2]) >= (1, 29):
            assert left, "onnxruntime wrote nothing with its reporting on"
