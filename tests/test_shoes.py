"""Shoes from real scans: outer-surface sampling, collection alignment, the shipped shoe bundle.

Real-data tests read ``../shared/data/gso_shoes`` (convex decompositions of Google Scanned Objects shoes) and
``../shared/data/scans/sneaker.ply``.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import box

from kpd.errors import InputError
from kpd.geometry import interior_mask, mesh_pieces, sample_surface

SHOES = ("ASICS_GEL1140V_WhiteRoyalSilver", "AMBERLIGHT_UP_W", "11pro_SL_TRX_FG", "ASICS_GELAce_Pro_Pearl_WhitePink",
         "ASICS_GEL1140V_WhiteBlackSilver", "ASICS_GELBlur33_20_GS_BlackWhiteSafety_Orange")


def two_boxes(start):
    """Box A [0, 2]^3 and box B [start, 4] x [0, 2]^2: overlapping for start < 2, touching for 2, apart beyond."""
    va, ta = box((0, 0, 0), (2, 2, 2))
    vb, tb = box((start, 0, 0), (4, 2, 2))
    return np.concatenate([va, vb]), np.concatenate([ta, tb + 8])


@pytest.fixture(scope="module")
def shoes_dir(data_dir):
    folder = data_dir / "gso_shoes"
    if not folder.is_dir():
        pytest.fail(f"{folder} is missing: the shoes are part of the shared data")
    return folder


def read_shoe(shoes_dir, name):
    from kpd.io import read_mesh

    mesh = read_mesh(shoes_dir / name / "model.obj")
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


# --- outer-surface sampling -------------------------------------------------------------------------------------

def test_interior_points_of_overlapping_boxes_are_found_and_outer_sampling_drops_them():
    vertices, triangles = two_boxes(0.5)  # B starts at x = 0.5, inside A up to x = 2
    assert sorted(np.unique(mesh_pieces(triangles), return_counts=True)[1]) == [12, 12]
    plain = sample_surface(vertices, triangles, 20000, seed=0)
    inside = interior_mask(vertices, triangles, plain.points, plain.faces)
    x = plain.points[:, 0]
    own_b = plain.faces >= 12
    # the truth: A's points with x > 0.5 inside B, B's points with x < 2 inside A (faces on the union's boundary stay)
    truth = np.where(own_b, (x < 2 - 1e-6) & (plain.points[:, 1:] > 1e-6).all(1) & (plain.points[:, 1:] < 2 - 1e-6)
                     .all(1), (x > 0.5 + 1e-6) & (plain.points[:, 1:] > 1e-6).all(1) & (plain.points[:, 1:] < 2 - 1e-6)
                     .all(1))
    assert truth.mean() > 0.1
    assert np.mean(inside != truth) < 0.01
    outer = sample_surface(vertices, triangles, 5000, seed=0, outer=True)
    assert len(outer.points) == 5000
    assert not interior_mask(vertices, triangles, outer.points, outer.faces).any()
    # nothing inside the union: points of A with x in (0.5, 2) lie only on its top, bottom, front and back faces
    inner = (outer.points[:, 0] > 0.6) & (outer.points[:, 0] < 1.9)
    on_boundary = np.isclose(outer.points[inner, 1:], 0).any(1) | np.isclose(outer.points[inner, 1:], 2).any(1)
    assert on_boundary.all()


def test_touching_faces_are_interior_and_apart_pieces_keep_everything():
    vertices, triangles = two_boxes(2.0)  # B starts where A ends: the faces at x = 2 are inside the union
    plain = sample_surface(vertices, triangles, 20000, seed=1)
    inside = interior_mask(vertices, triangles, plain.points, plain.faces)
    on_contact = np.isclose(plain.points[:, 0], 2.0)
    assert inside[on_contact].mean() > 0.99 and not inside[~on_contact].any()
    apart_v, apart_t = two_boxes(2.5)
    plain = sample_surface(apart_v, apart_t, 5000, seed=1)
    assert not interior_mask(apart_v, apart_t, plain.points, plain.faces).any()


def test_outer_sampling_is_seeded_and_a_single_piece_is_unchanged():
    vertices, triangles = two_boxes(0.5)
    a = sample_surface(vertices, triangles, 300, seed=3, outer=True)
    b = sample_surface(vertices, triangles, 300, seed=3, outer=True)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.faces, b.faces)
    v, t = box((0, 0, 0), (1, 1, 1))
    assert np.array_equal(sample_surface(v, t, 100, seed=0, outer=True).points, sample_surface(v, t, 100,
                                                                                               seed=0).points)
    with pytest.raises(InputError, match="faces must be"):
        interior_mask(v, t, np.zeros((2, 3)), np.array([0, 99]))


@pytest.mark.parametrize("name", SHOES[:3])
def test_shoe_interior_samples_are_gone_where_pieces_overlap(shoes_dir, name):
    vertices, triangles = read_shoe(shoes_dir, name)
    assert len(np.unique(mesh_pieces(triangles))) >= 6  # a convex decomposition
    plain = sample_surface(vertices, triangles, 4000, seed=0)
    inside = interior_mask(vertices, triangles, plain.points, plain.faces)
    assert inside.mean() > 0.1  # the cut faces between pieces
    outer = sample_surface(vertices, triangles, 4000, seed=0, outer=True)
    assert not interior_mask(vertices, triangles, outer.points, outer.faces).any()
    # the interior points lie away from the outer surface; the kept ones on it
    from scipy.spatial import cKDTree

    diagonal = np.linalg.norm(vertices.max(0) - vertices.min(0))
    dense = cKDTree(sample_surface(vertices, triangles, 40000, seed=1, outer=True).points)
    assert np.median(dense.query(plain.points[inside])[0]) > 0.01 * diagonal
    assert np.median(dense.query(plain.points[~inside])[0]) < 0.005 * diagonal


# --- collection alignment ---------------------------------------------------------------------------------------

FAST = {"n_points": 600, "coarse_points": 200, "fpfh_runs": 1}  # a lighter search: a test's budget


@pytest.fixture(scope="module")
def turned_shoes(shoes_dir):
    """Five shoes as 3000 outer-surface points each, turned by seeded random rotations (and the rotations)."""
    from scipy.spatial.transform import Rotation

    from kpd.collection import collection_points
    from kpd.io import read_mesh

    names = list(SHOES[:5])
    clouds = [collection_points(read_mesh(shoes_dir / n / "model.obj"), 3000, seed=0) for n in names]
    truth = Rotation.random(len(names), random_state=7).as_matrix()
    return names, [c @ q.T for c, q in zip(clouds, truth)], truth


def test_a_small_collection_turned_at_random_comes_back_to_one_frame(turned_shoes, tmp_path):
    from kpd.collection import align_collection, pairwise_rotation_errors

    names, clouds, truth = turned_shoes
    result = align_collection(clouds, names, rounds=2, state=tmp_path / "state.json", **FAST)
    assert len(result.shapes) == 5 and [s.name for s in result.shapes] == names
    assert sum(s.template for s in result.shapes) == 1
    decided = ~result.ambiguous
    assert decided.sum() >= 4
    errors = pairwise_rotation_errors(result.rotations, truth, decided)
    assert errors.max() <= 10.0, errors.round(1)
    # without the estimates the same shapes are far apart: the check can fail
    assert pairwise_rotation_errors(np.repeat(np.eye(3)[None], 5, 0), truth)[np.triu_indices(5, 1)].min() > 20


def test_collection_alignment_continues_from_its_state(turned_shoes, tmp_path, monkeypatch):
    import kpd.collection as collection
    import kpd.collection.align as align

    names, clouds, truth = turned_shoes
    state = tmp_path / "state.json"
    first = collection.align_collection(clouds[:3], names[:3], rounds=1, state=state, **FAST)

    def refuse(item):
        raise AssertionError("a shape was oriented again although its result was saved")

    monkeypatch.setattr(align, "_worker_orient", refuse)
    again = collection.align_collection(clouds[:3], names[:3], rounds=1, state=state, **FAST)
    assert np.array_equal(first.rotations, again.rotations)
    with pytest.raises(InputError, match="other shapes or settings"):
        collection.align_collection(clouds[:3], names[:3], rounds=1, state=state, up="y", **FAST)


def test_pairwise_rotation_errors_and_input_checks():
    from scipy.spatial.transform import Rotation

    from kpd.collection import align_collection, pairwise_rotation_errors

    truth = Rotation.random(4, random_state=0).as_matrix()
    common = Rotation.random(random_state=1).as_matrix()
    estimated = np.einsum("ij,skj->sik", common, truth)  # E_i = G Q_i^T: all come back into frame G
    assert pairwise_rotation_errors(estimated, truth).max() < 1e-5
    estimated[2] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix() @ estimated[2]
    errors = pairwise_rotation_errors(estimated, truth)
    assert np.allclose(errors[2, [0, 1, 3]], 90.0) and errors[0, 1] < 1e-5
    with pytest.raises(InputError, match="at least 2 shapes"):
        align_collection([np.zeros((20, 3))])
    with pytest.raises(InputError, match="distinct"):
        align_collection([np.random.default_rng(0).random((20, 3))] * 2, ["a", "a"])


def test_kpd_scan_on_a_folder_writes_an_aligned_folder_kpd_train_reads(turned_shoes, shoes_dir, tmp_path):
    from scipy.spatial.transform import Rotation

    from kpd.cli import main
    from kpd.data import discover
    from kpd.io import read_mesh, write_mesh

    names = sorted(SHOES[:3])  # kpd scan lists a folder by name
    collection = tmp_path / "shoes"
    collection.mkdir()
    truth = Rotation.random(3, random_state=3).as_matrix()
    for name, q in zip(names, truth):
        mesh = read_mesh(shoes_dir / name / "model.obj")
        (collection / name).mkdir()
        write_mesh(collection / name / "model.obj", mesh.with_vertices(mesh.vertices @ q.T))
    out = tmp_path / "shoe"
    assert main(["scan", str(collection), "--out", str(out), "--points", "2000", "--rounds", "1"]) == 0
    report = __import__("json").loads((out / "alignment.json").read_text())
    assert [row["name"] for row in report["shapes"]] == names
    assert (out / "contact_sheet.png").stat().st_size > 0 and not (tmp_path / ".shoe.partial").exists()
    floor = report["floor"]  # without --up: the floor the shoes share, or why none was clear (three shoes)
    if floor["up"] is None:
        assert floor["note"] and all(r["tilt"] is None for r in report["shapes"])
    else:
        assert floor["stood"] == sum(not r["ambiguous"] for r in report["shapes"])
    rotations = np.array([np.asarray(row["transform"])[:3, :3] for row in report["shapes"]])
    decided = [not row["ambiguous"] for row in report["shapes"]]
    assert sum(decided) >= 2
    for row, rotation in zip(report["shapes"], rotations):
        aligned = read_mesh(row["output"]).vertices
        given = read_mesh(collection / row["name"] / "model.obj").vertices
        assert np.allclose(aligned, given @ rotation.T, atol=1e-5)  # the file is the input turned
    from kpd.collection import pairwise_rotation_errors

    assert pairwise_rotation_errors(rotations, truth, np.array(decided)).max() <= 10.0
    category = discover(out)
    found = sorted(f.name for s in category.splits.values() for f in s)
    assert found == sorted(n for n, d in zip(names, decided) if d)
    assert main(["scan", str(collection), "--out", str(out)]) == 2  # exists, no --force


# --- the shipped shoe bundle --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def shoe_model():
    from kpd.runtime import Model

    return Model.load("shoe")


def test_the_shipped_shoe_bundle_loads_with_its_prior_template_and_record(shoe_model):
    assert shoe_model.category == "shoe" and shoe_model.num_keypoints == 12
    assert shoe_model.prior is not None and shoe_model.template_points is not None
    assert shoe_model.up == "+y" and shoe_model.outer_surface
    record = shoe_model.bundle.manifest["training"]
    assert record["data"]["counts"]["test"] >= 10  # a held-out split of its own
    assert "--outer-surface" in record["command"] and "--keypoints 12" in record["command"]


def test_shoe_keypoints_on_the_real_sneaker_scan_lie_near_its_surface(shoe_model, data_dir):
    from scipy.spatial import cKDTree

    from kpd.frame import ScanFrame
    from kpd.io import read_mesh

    scan = read_mesh(data_dir / "scans" / "sneaker.ply")
    frame = ScanFrame(shoe_model, scan, None)
    keypoints = frame.to_original(shoe_model.keypoints(frame.result.shape, seed=0))
    assert keypoints.shape == (12, 3) and np.isfinite(keypoints).all()
    size = np.linalg.norm(scan.vertices.max(0) - scan.vertices.min(0))
    surface = cKDTree(sample_surface(scan.vertices, scan.triangles, 50000, seed=0).points)
    distance = surface.query(keypoints)[0] / size
    assert np.median(distance) < 0.03 and distance.max() < 0.08, distance.round(3)
    # spread over the shoe, not collapsed: the keypoints span most of its length
    length_axis = np.argmax(np.ptp(scan.vertices, axis=0))
    assert np.ptp(keypoints[:, length_axis]) > 0.5 * np.ptp(scan.vertices[:, length_axis])


def test_kpd_deform_shoe_with_a_zero_move_reproduces_the_input(shoes_dir, tmp_path):
    from kpd.cli import main
    from kpd.io import read_mesh

    source = shoes_dir / SHOES[0] / "model.obj"
    out = tmp_path / "same.obj"
    assert main(["deform", "shoe", str(source), "--move", "0:0,0,0", "--out", str(out)]) == 0
    given, result = read_mesh(source), read_mesh(out)
    assert result.triangles.shape == given.triangles.shape
    assert np.allclose(result.vertices, given.vertices, atol=1e-6)
