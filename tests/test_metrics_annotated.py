"""kpd.metrics.annotated: protocol metrics (PCK by regression, part correspondence, DAS, SC3K coverage and
inclusivity) and the ``kpd eval pck|parts|das|coverage|chamfer`` commands."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from helpers import make_toy_bundle

from kpd.cli import main
from kpd.errors import InputError
from kpd.metrics import (dual_alignment_score, fit_keypoint_regressor, keypoint_coverage, keypoint_inclusivity, pck,
                         part_association, part_correspondence, regression_pck)

seeds = st.integers(0, 2**31 - 1)


def _rigid(seed: int):
    rng = np.random.default_rng(seed)
    r, t = Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3)
    return lambda x: np.asarray(x) @ r.T + t


def _linear_data(seed: int, s: int = 40, k: int = 4, j: int = 3, noise: float = 0.0):
    """Annotations that are an affine function of the keypoints (plus noise)."""
    rng = np.random.default_rng(seed)
    kp = rng.normal(size=(s, k, 3)) * 0.3
    w = rng.normal(size=(3 * k, 3 * j)) * 0.3
    ann = (kp.reshape(s, -1) @ w + rng.normal(size=3 * j)).reshape(s, j, 3)
    return kp, ann + noise * rng.normal(size=ann.shape)


# --- PCK by linear regression ----------------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(seeds)
def test_pck_of_the_ground_truth_is_one(seed):
    kp, ann = _linear_data(seed)
    assert pck(ann, ann) == 1.0
    # the annotations predicting themselves, and an exact affine relation, are recovered exactly
    assert regression_pck(ann[:30], ann[:30], ann[30:], ann[30:], ridge=0).pck == 1.0
    result = regression_pck(kp[:30], ann[:30], kp[30:], ann[30:], ridge=0)
    assert result.pck == 1.0 and result.errors.max() < 1e-8
    assert result.per_keypoint.shape == (3,) and result.errors.shape == (10, 3)


@settings(max_examples=25, deadline=None)
@given(seeds, st.sampled_from([0.0, 1e-3, 0.1]))
def test_regression_pck_ignores_keypoint_order_and_rigid_motion(seed, ridge):
    kp, ann = _linear_data(seed, noise=0.05)
    base = regression_pck(kp[:25], ann[:25], kp[25:], ann[25:], ridge=ridge)
    order = np.random.default_rng(seed).permutation(kp.shape[1])
    permuted = regression_pck(kp[:25, order], ann[:25], kp[25:, order], ann[25:], ridge=ridge)
    np.testing.assert_allclose(permuted.errors, base.errors, atol=1e-9)
    move = _rigid(seed)
    moved = regression_pck(move(kp[:25]), move(ann[:25]), move(kp[25:]), move(ann[25:]), ridge=ridge)
    np.testing.assert_allclose(moved.errors, base.errors, atol=1e-9)
    assert moved.pck == base.pck


def test_ridge_shrinks_towards_the_mean():
    kp, ann = _linear_data(0, noise=0.05)
    strong = fit_keypoint_regressor(kp, ann, ridge=1e9)
    np.testing.assert_allclose(strong.predict(kp[:3]), np.broadcast_to(ann.mean(axis=0), (3, 3, 3)), atol=1e-6)


def test_pck_threshold_and_errors():
    ann = np.zeros((2, 2, 3))
    pred = ann.copy()
    pred[0, 0, 0] = 0.05  # on the threshold: correct
    pred[1, 1, 1] = 0.0501
    assert pck(pred, ann) == 0.75
    with pytest.raises(InputError, match="same shape"):
        pck(pred[:, :1], ann)
    with pytest.raises(InputError, match="ridge"):
        fit_keypoint_regressor(ann, ann, ridge=-1)
    with pytest.raises(InputError, match="same shapes"):
        fit_keypoint_regressor(ann, ann[:1])
    with pytest.raises(InputError, match=r"\(S, K, 3\)"):
        fit_keypoint_regressor(ann[0], ann[0])
    with pytest.raises(InputError, match="2 keypoints per shape"):
        fit_keypoint_regressor(ann, ann).predict(np.zeros((1, 3, 3)))


# --- part correspondence ---------------------------------------------------------------------------------------------


def _parts_scene(seed: int, shapes: int = 4):
    """Shapes made of three labelled blobs; keypoint k sits on blob k (keypoint 3 on blob 0 or far away)."""
    rng = np.random.default_rng(seed)
    points, labels, keypoints = [], [], []
    for s in range(shapes):
        centers = rng.uniform(-0.6, 0.6, (3, 3))
        pts = np.concatenate([c + 0.05 * rng.normal(size=(60, 3)) for c in centers])
        lab = np.repeat([4, 9, 2], 60)
        kp = [pts[60 * k + rng.integers(60)] for k in range(3)]
        kp.append(pts[rng.integers(60)] if s % 2 == 0 else np.array([5.0, 5.0, 5.0]))
        points.append(pts)
        labels.append(lab)
        keypoints.append(np.stack(kp))
    return keypoints, points, labels


def test_part_correspondence_known_answer():
    keypoints, points, labels = _parts_scene(0)
    r = part_correspondence(keypoints, points, labels, radius=1e-9)
    np.testing.assert_array_equal(r.parts, [2, 4, 9])
    np.testing.assert_allclose(r.frequency, [[0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 0.5, 0]])
    assert r.score == pytest.approx((1 + 1 + 1 + 0.5) / 4)
    assert r.part_score == 1.0
    np.testing.assert_array_equal(r.best_part, [4, 9, 2, 4])
    np.testing.assert_allclose(r.associated, [1, 1, 1, 0.5])
    # a part absent from every shape is not part of the reverse reduction, and never associated
    r5 = part_correspondence(keypoints, points, labels, radius=1e-9, parts=[2, 4, 9, 77])
    assert r5.part_score == 1.0 and r5.score == r.score and not r5.frequency[:, 3].any()


@settings(max_examples=20, deadline=None)
@given(seeds, st.floats(0.01, 0.3))
def test_part_correspondence_invariances(seed, radius):
    keypoints, points, labels = _parts_scene(seed)
    rng = np.random.default_rng(seed)
    keypoints = [k + rng.normal(scale=0.1, size=k.shape) for k in keypoints]
    base = part_correspondence(keypoints, points, labels, radius=radius)
    assert 0.0 <= base.score <= 1.0 and 0.0 <= base.part_score <= 1.0
    move = _rigid(seed)
    moved = part_correspondence([move(k) for k in keypoints], [move(p) for p in points], labels, radius=radius)
    np.testing.assert_allclose(moved.frequency, base.frequency)
    relabel = {4: 40, 9: 1, 2: 13}
    renamed = part_correspondence(keypoints, points, [np.vectorize(relabel.get)(lab) for lab in labels],
                                  radius=radius)
    assert (renamed.score, renamed.part_score) == (base.score, base.part_score)
    order = rng.permutation(4)
    reordered = part_correspondence([k[order] for k in keypoints], points, labels, radius=radius)
    assert reordered.score == pytest.approx(base.score) and reordered.part_score == base.part_score


def test_part_association_and_errors():
    pts = np.array([[0.0, 0, 0], [1, 0, 0]])
    a = part_association([[0.04, 0, 0], [0.5, 0, 0]], pts, [1, 2], [1, 2, 3], radius=0.05)
    np.testing.assert_array_equal(a, [[True, False, False], [False, False, False]])
    with pytest.raises(InputError, match="labels must be"):
        part_association([[0, 0, 0]], pts, [1.5, 2], [1])
    with pytest.raises(InputError, match="same number of keypoints"):
        part_correspondence([np.zeros((2, 3)), np.zeros((3, 3))], [pts, pts], [[1, 2], [1, 2]])
    with pytest.raises(InputError, match="same shapes"):
        part_correspondence([np.zeros((2, 3))], [pts, pts], [[1, 2]])
    with pytest.raises(InputError, match="at least one shape"):
        part_correspondence([], [], [])


# --- Dual Alignment Score --------------------------------------------------------------------------------------------


def _das_naive(keypoints, annotated, semantic_ids):
    """Skeleton Merger's eval_keypointnet.py, loop for loop (fwd_alignment_scores, bwd_alignment_scores)."""
    preds = []
    for kp, gt, ids in zip(keypoints, annotated, semantic_ids):
        dist = np.sum(np.square(np.expand_dims(kp, 1) - np.expand_dims(gt, 0)), -1)
        preds.append([ids[i] for i in np.argmin(dist, -1)])
    preds = np.array(preds)
    forward = np.mean([np.mean(pa == pb) for pa in preds for pb in preds])
    backward_by_id: dict = {}
    for kp, gt, ids in zip(keypoints, annotated, semantic_ids):
        dist = np.sum(np.square(np.expand_dims(kp, 1) - np.expand_dims(gt, 0)), -1)
        chosen = np.argmin(dist, -2)
        for i, c in enumerate(ids):
            backward_by_id.setdefault(c, []).append(chosen[i])
    backward = np.mean([np.mean(np.expand_dims(np.array(v), -1) == np.expand_dims(np.array(v), 0))
                        for v in backward_by_id.values()])
    return (forward + backward) / 2, forward, backward


def _das_scene(seed: int, shapes: int = 6, k: int = 5):
    rng = np.random.default_rng(seed)
    annotated, ids, keypoints = [], [], []
    for _ in range(shapes):
        present = np.sort(rng.choice(8, size=rng.integers(3, 8), replace=False))
        annotated.append(rng.uniform(-1, 1, (len(present), 3)))
        ids.append(present)
        keypoints.append(rng.uniform(-1, 1, (k, 3)))
    return keypoints, annotated, ids


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_das_matches_the_authors_script(seed):
    keypoints, annotated, ids = _das_scene(seed)
    got = dual_alignment_score(keypoints, annotated, ids)
    np.testing.assert_allclose(got, _das_naive(keypoints, annotated, ids), atol=1e-12)
    assert 0.0 < got.score <= 1.0


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_das_invariances_and_perfect_keypoints(seed):
    keypoints, annotated, ids = _das_scene(seed)
    base = dual_alignment_score(keypoints, annotated, ids)
    move = _rigid(seed)
    assert dual_alignment_score([move(k) for k in keypoints], [move(a) for a in annotated], ids) == \
        pytest.approx(base)
    order = np.random.default_rng(seed).permutation(len(keypoints[0]))
    assert dual_alignment_score([k[order] for k in keypoints], annotated, ids) == pytest.approx(base)
    # keypoints equal to complete annotations score 1
    rng = np.random.default_rng(seed)
    full = [rng.uniform(-1, 1, (6, 3)) for _ in range(5)]
    same = [np.arange(6)] * 5
    assert dual_alignment_score(full, full, same) == (1.0, 1.0, 1.0)


def test_das_known_answer():
    annotated = [np.array([[0.0, 0, 0], [1, 0, 0]])] * 2
    ids = [np.array([3, 7])] * 2
    keypoints = [np.array([[0.1, 0, 0], [0.9, 0, 0]]), np.array([[0.9, 0, 0], [0.8, 0, 0]])]
    # forward labels: shape 0 -> [3, 7], shape 1 -> [7, 7]; agreement: k0 (1+1)/4... pairs: k0: 2/4, k1: 4/4
    # backward: id 3 -> nearest keypoint [0, 1]: 2/4; id 7 -> [1, 0]: 2/4
    got = dual_alignment_score(keypoints, annotated, ids)
    assert got.forward == pytest.approx(0.75) and got.backward == pytest.approx(0.5)
    assert got.score == pytest.approx(0.625)


# --- SC3K coverage and inclusivity -----------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(seeds, st.floats(0.1, 10.0))
def test_coverage_and_inclusivity(seed, scale):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, (300, 3)) * [1.0, 0.5, 0.3]
    corners = np.stack([points.min(axis=0), points.max(axis=0)])
    on_cloud = points[rng.choice(300, 8, replace=False)]
    assert keypoint_coverage(corners, points) == pytest.approx(1.0)
    assert keypoint_coverage(np.zeros((3, 3)), points) == 0.0
    assert keypoint_coverage(corners * 5, points) == 0.0  # four times too wide: clipped at 0
    assert keypoint_inclusivity(on_cloud, points) == 1.0
    assert keypoint_inclusivity(on_cloud + 10, points) == 0.0
    shift = rng.normal(size=3)  # coverage uses axis-aligned boxes: invariant to translation and scale, not rotation
    base = keypoint_coverage(on_cloud, points)
    assert keypoint_coverage(scale * (on_cloud + shift), scale * (points + shift)) == pytest.approx(base)
    move = _rigid(seed)
    far = on_cloud + rng.normal(scale=0.05, size=on_cloud.shape)
    assert keypoint_inclusivity(move(far), move(points), 0.03) == keypoint_inclusivity(far, points, 0.03)
    with pytest.raises(InputError, match="zero bounding box"):
        keypoint_coverage(corners, np.zeros((4, 3)))


# --- kpd eval commands -----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def toy_bundle(tmp_path_factory):
    return make_toy_bundle(tmp_path_factory.mktemp("bundle") / "toy.kpd", k=6)


def _run(capsys, *argv):
    code = main(["eval", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_eval_pck_das_coverage_with_files(data_dir, tmp_path, capsys):
    from kpd import annotations as ann

    kpn, extra = data_dir / "keypointnet", data_dir / "shapenetpart_sample"
    chairs = ann.KeypointNet(kpn, "chair")
    shapes, _ = ann.keypointnet_shapes(chairs, "all", geometry_dirs=[extra])
    common = chairs.common_semantic_ids()
    folder = tmp_path / "kp"
    folder.mkdir()
    from kpd.io import write_keypoints

    for s in shapes:  # the annotations themselves, in each geometry file's coordinates
        k = s.keypoints[[int(np.flatnonzero(s.semantic_ids == c)[0]) for c in common]]
        write_keypoints(folder / f"{s.model_id}.txt", s.file_to_reference.inverse().apply(s.normalizer.invert(k)))
    out = tmp_path / "das.json"
    code, text, _ = _run(capsys, "das", kpn, "--category", "chair", "--keypoints", folder, "--geometry", extra,
                         "--out", out, "--quiet")
    assert code == 0 and "DAS" in text and "no geometry: 995" in text
    result = json.loads(out.read_text())
    assert result["protocol"] == "das" and result["results"]["das"] == 1.0 and result["results"]["shapes"] == 4
    assert result["arguments"]["category"] == "chair"
    out = tmp_path / "pck.json"
    code, text, _ = _run(capsys, "pck", kpn, "--category", "chair", "--keypoints", folder, "--geometry", extra,
                         "--fit-split", "all", "--test-split", "all", "--ridge", "0", "--out", out, "--quiet")
    result = json.loads(out.read_text())
    assert code == 0 and result["results"]["pck"] == 1.0  # annotations regress onto themselves
    assert any("also fit shapes" in n for n in result["notes"]) and "note: only 4 scored shapes" in text
    assert result["data"]["skipped"]["count"] == 995  # once each, although fit and test are the same split
    assert result["data"]["common_semantic_ids"] == common.tolist() and result["results"]["test_shapes"] == 4
    code, _, err = _run(capsys, "pck", kpn, "--category", "chair", "--keypoints", folder, "--out", out, "--quiet")
    assert code == 2 and "exists; pass --force" in err
    out = tmp_path / "cov.json"
    code, text, _ = _run(capsys, "coverage", kpn, "--category", "chair", "--keypoints", folder, "--out", out,
                         "--quiet")
    result = json.loads(out.read_text())
    assert code == 0 and result["results"]["inclusivity"] == 1.0 and result["results"]["shapes"] == 1


def test_eval_with_a_bundle(data_dir, toy_bundle, tmp_path, capsys):
    parts = data_dir / "shapenetpart_sample"
    out = tmp_path / "parts.json"
    code, text, _ = _run(capsys, "parts", parts, "--category", "airplane", "--split", "all", "--model", toy_bundle,
                         "--out", out, "--quiet")
    assert code == 0 and "part correspondence" in text
    result = json.loads(out.read_text())
    assert result["keypoints"]["up"] == "+z" and result["results"]["keypoints"] == 6
    assert np.array(result["results"]["frequency"]).shape == (6, len(result["results"]["parts"]))
    out = tmp_path / "chamfer.json"
    code, text, _ = _run(capsys, "chamfer", data_dir / "modelnet10", "--category", "chair", "--model", toy_bundle,
                         "--pairs", "2", "--out", out, "--quiet")
    assert code == 0 and "no deformation" in text
    result = json.loads(out.read_text())
    assert len(result["results"]["per_pair"]) == 2 and result["results"]["chamfer_x1e3"]["model"]["mean"] > 0


def test_eval_errors_are_one_line(data_dir, toy_bundle, tmp_path, capsys):
    parts = data_dir / "shapenetpart_sample"
    out = tmp_path / "x.json"
    no_up = make_toy_bundle(tmp_path / "no_up.kpd", up=None)
    cases = [
        (["parts", parts, "--category", "chair", "--model", toy_bundle], "shuffled_test_file_list.json"),
        (["parts", tmp_path / "nowhere", "--category", "chair", "--model", toy_bundle], "does not exist"),
        (["das", parts, "--category", "chair", "--model", toy_bundle], "not a KeypointNet folder"),
        (["pck", data_dir / "keypointnet", "--category", "lamp", "--model", toy_bundle], "no KeypointNet annotations"),
        (["coverage", parts, "--category", "chair", "--split", "all", "--keypoints", tmp_path],
         "gave keypoints for none"),
        (["parts", parts, "--category", "chair", "--split", "all", "--model", tmp_path / "none.kpd"], ""),
        (["parts", parts, "--category", "chair", "--split", "all", "--model", no_up], "--up"),
    ]
    for argv, message in cases:
        code, _, err = _run(capsys, *argv, "--out", out, "--quiet")
        assert code == 2 and err.count("\n") == 1 and message in err, (argv, err)
        assert not out.exists()
