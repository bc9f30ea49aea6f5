"""kpd.annotations: KeypointNet and ShapeNetPart readers, frames, annotation registration, protocols on real data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from kpd import annotations as ann
from kpd.errors import DataError, InputError
from kpd.geometry import sample_surface
from kpd.io import Mesh, read_mesh, read_points, write_keypoints
from kpd.metrics import part_correspondence, point_triangle_distance

CHAIR = "03001627"
PCD_CHAIR = "88382b877be91b2a572f8e1c1caad99e"  # KeypointNet cloud + ShapeNet v2 mesh
FITTED_CHAIRS = ("eaf231f17fccb96d81dff5c2e57ad46e", "fe6b3c001a86d844d5767a0de8dd037e")  # deep_cage meshes
PART_CHAIR = "1015e71a0d21b127de03ab2a27ba7531"  # ShapeNetPart points, also annotated in KeypointNet


@pytest.fixture(scope="module")
def kpn_root(data_dir) -> Path:
    return data_dir / "keypointnet"


@pytest.fixture(scope="module")
def part_root(data_dir) -> Path:
    return data_dir / "shapenetpart_sample"


@pytest.fixture(scope="module")
def chairs(kpn_root) -> ann.KeypointNet:
    return ann.KeypointNet(kpn_root, "chair")


@pytest.fixture(scope="module")
def chair_shapes(chairs, part_root):
    shapes, skipped = ann.keypointnet_shapes(chairs, "all", geometry_dirs=[part_root])
    return {s.model_id: s for s in shapes}, skipped


# --- frames ----------------------------------------------------------------------------------------------------------


def test_frame_maps_are_rotations():
    for m in (ann.KEYPOINTNET_TO_REFERENCE, ann.MODELNET_TO_REFERENCE):
        np.testing.assert_allclose(m @ m.T, np.eye(3))
        assert np.linalg.det(m) == pytest.approx(1.0)
    # the authors' fix: (x, y, z) -> (-z, y, x)
    np.testing.assert_array_equal(np.array([[1.0, 2.0, 3.0]]) @ ann.KEYPOINTNET_TO_REFERENCE.T, [[-3.0, 2.0, 1.0]])
    np.testing.assert_array_equal(np.array([[1.0, 2.0, 3.0]]) @ ann.MODELNET_TO_REFERENCE.T, [[-2.0, 3.0, -1.0]])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_similarity_inverse_and_composition(seed):
    rng = np.random.default_rng(seed)
    a = ann.Similarity(float(rng.uniform(0.2, 5)), Rotation.random(random_state=seed).as_matrix() * [1, 1, -1],
                       rng.normal(size=3))
    b = ann.Similarity(float(rng.uniform(0.2, 5)), Rotation.random(random_state=seed + 1).as_matrix(),
                       rng.normal(size=3))
    x = rng.normal(size=(7, 3))
    np.testing.assert_allclose(a.inverse().apply(a.apply(x)), x, atol=1e-10)
    np.testing.assert_allclose(a.then(b).apply(x), b.apply(a.apply(x)), atol=1e-10)


def _upright_back(points: np.ndarray) -> np.ndarray:
    """Offset of the top 10% of a chair (its back) from the bounding-box centre, divided by the extent."""
    top = points[points[:, 1] > np.percentile(points[:, 1], 90)]
    return (top.mean(axis=0) - (points.max(axis=0) + points.min(axis=0)) / 2) / np.ptp(points, axis=0)


def test_datasets_agree_on_the_reference_frame(data_dir, kpn_root, part_root):
    """Chair backs point to -x, y up, in ShapeNetPart, in KeypointNet after the authors' fix, and in ModelNet after
    MODELNET_TO_REFERENCE, so one model frame mapping serves all of them."""
    part = read_points(part_root / CHAIR / "points" / f"{PART_CHAIR}.pts").points
    cloud = read_points(kpn_root / "pcds" / CHAIR / f"{PCD_CHAIR}.pcd").points @ ann.KEYPOINTNET_TO_REFERENCE.T
    modelnet = sorted((data_dir / "modelnet10" / "chair" / "train").glob("*.ply"))[:3]
    backs = [_upright_back(part), _upright_back(cloud)]
    backs += [_upright_back(read_mesh(p).vertices @ ann.MODELNET_TO_REFERENCE.T) for p in modelnet]
    for back in backs:
        assert back[0] < -0.2 and abs(back[2]) < 0.1, back


# --- registration ----------------------------------------------------------------------------------------------------


def _box_mesh() -> Mesh:
    v = np.array([[x, y, z] for x in (-0.2, 0.3) for y in (-0.45, 0.35) for z in (-0.1, 0.2)], dtype=float)
    t = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6],
         [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return Mesh(v, np.array(t))


@pytest.mark.parametrize("candidate", ["keypointnet-to-reference", "identity"])
def test_fit_annotation_frame_recovers_a_known_map(candidate):
    mesh = _box_mesh()
    surface = sample_surface(mesh.vertices, mesh.triangles, 20000, seed=1).points
    rng = np.random.default_rng(3)
    corners = mesh.vertices[[0, 3, 5, 6, 7]]
    source = np.concatenate([corners, surface[rng.choice(len(surface), 7)]])  # "KeypointNet" frame
    truth = ann.Similarity(2.0, ann.FIT_CANDIDATES[candidate], np.array([0.05, -0.02, 0.03]))
    surface_target = truth.apply(surface)
    diagonal = float(np.linalg.norm(np.ptp(surface, axis=0)))
    fit = ann.fit_annotation_frame(source, surface_target, source_diagonal=diagonal)
    assert fit.candidate == candidate
    np.testing.assert_allclose(fit.transform.apply(source), truth.apply(source), atol=0.02)
    assert fit.distances.max() < 0.02
    assert set(fit.residuals) == set(ann.FIT_CANDIDATES)


def test_fit_annotation_frame_checks_input():
    with pytest.raises(InputError, match="at least 3"):
        ann.fit_annotation_frame(np.zeros((2, 3)), np.random.default_rng(0).normal(size=(10, 3)))
    with pytest.raises(InputError, match="candidate"):
        ann.fit_annotation_frame(np.eye(3), np.random.default_rng(0).normal(size=(10, 3)), candidates={})


# --- KeypointNet on real data ----------------------------------------------------------------------------------------


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


def test_shapenet_v2_mesh_needs_no_fit(tmp_path, kpn_root):
    """Without the cloud, the ShapeNet v2 mesh of the same model is in the annotations' frame already."""
    (tmp_path / "annotations").symlink_to(kpn_root / "annotations")
    (tmp_path / "models").symlink_to(kpn_root / "models")
    shapes, _ = ann.keypointnet_shapes(ann.KeypointNet(tmp_path, "chair"), "all")
    s = {x.model_id: x for x in shapes}[PCD_CHAIR]
    assert s.frame == "keypointnet" and s.path.name == "model_normalized.obj"
    d = point_triangle_distance(s.keypoints, s.normalizer.apply(s.geometry.vertices), s.geometry.triangles)
    assert d.max() <= 0.01


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


# --- ShapeNetPart on real data ---------------------------------------------------------------------------------------


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


@pytest.fixture(scope="module")
def part_shapes(part_root):
    parts = ann.ShapeNetPart(part_root)
    return {name: ann.shapenetpart_shapes(parts, name)[0] for name in sorted(parts.categories)}


def test_part_score_of_perfect_random_and_relabelled_keypoints(part_shapes):
    """On each category's part-labelled shape: keypoints on the parts score 1.0, keypoints placed at random in the
    box far lower, and relabelling the parts changes nothing."""
    rng = np.random.default_rng(0)
    random_scores = []
    for name, s in part_shapes.items():
        parts = np.unique(s.labels)
        perfect = np.stack([s.points[np.flatnonzero(s.labels == p)[len(parts)]] for p in parts] +
                           [s.points[i] for i in rng.choice(len(s.points), 6, replace=False)])
        result = part_correspondence([perfect], [s.points], [s.labels])
        assert result.score == 1.0 and result.part_score == 1.0, name
        assert (np.diag(result.frequency[: len(parts)]) == 1.0).all()  # each on its own part (maybe others too)
        random = rng.uniform(-1, 1, (12, 3))
        score = part_correspondence([random], [s.points], [s.labels]).score
        random_scores.append(score)
        new = rng.permutation(100)[: len(parts)] + 7
        relabelled = new[np.searchsorted(parts, s.labels)]
        for keypoints in (perfect, random):
            a = part_correspondence([keypoints], [s.points], [s.labels])
            b = part_correspondence([keypoints], [s.points], [relabelled])
            assert (a.score, a.part_score) == (b.score, b.part_score)
    assert max(random_scores) <= 0.5 and np.mean(random_scores) < 0.2, random_scores


def test_parts_protocol_with_files(part_root, part_shapes, tmp_path):
    s = part_shapes["chair"]
    keypoints = np.stack([s.points[np.flatnonzero(s.labels == p)[0]] for p in (1, 2, 3)])
    write_keypoints(tmp_path / f"{PART_CHAIR}.json", s.normalizer.invert(keypoints))  # .pts coordinates
    result = ann.parts_protocol(ann.ShapeNetPart(part_root), "chair", ann.FileKeypoints(tmp_path), split="all")
    assert result["results"]["score"] == 1.0 and result["results"]["best_part"] == [1, 2, 3]
    assert result["data"]["shapes"][0]["id"] == PART_CHAIR
    json.dumps(result, allow_nan=False)


def test_point_cloud_shapes(kpn_root, part_root, tmp_path):
    clouds, kind = ann.point_cloud_shapes(kpn_root, "chair")
    assert kind == "keypointnet" and [s.model_id for s in clouds] == [PCD_CHAIR]
    clouds, kind = ann.point_cloud_shapes(part_root, "chair")
    assert kind == "shapenetpart" and len(clouds) == 1
    with pytest.raises(DataError, match="neither"):
        ann.point_cloud_shapes(tmp_path, "chair")


def test_alignment_pairs_match_training_evaluation():
    from kpd.train import evaluate  # torch: the [train] extra, which make test installs

    for n, count, seed in ((2, 5, 0), (99, 200, 0), (17, 30, 4)):
        np.testing.assert_array_equal(ann.alignment_pairs(n, count, seed), evaluate.fixed_pairs(n, count, seed))
    with pytest.raises(DataError, match="at least 2"):
        ann.alignment_pairs(1, 3)


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
