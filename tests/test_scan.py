"""kpd.scan and `kpd scan`: cleaning, orientation search, ambiguity flag, exact transforms, CLI errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kpd.cli import main
from kpd.errors import InputError, NotFittedError
from kpd.geometry import Normalizer, sample_surface
from kpd.io import Mesh, PointSet, read_mesh, read_points, write_points
from kpd.scan import (
    ScanAligner,
    clean,
    icosahedral_rotations,
    orient,
    parse_axis,
    preprocess,
    proper_signed_permutations,
    rotation_angle,
    similarity_matrices,
    support_plane,
)

# --- fixtures ---------------------------------------------------------------------------------------------------


def rotation(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


def cylinder(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1, 1, n)
    return np.c_[0.4 * np.cos(theta), 0.4 * np.sin(theta), z]


def sphere(n: int, seed: int, center=(0.0, 0.0, 0.0), radius=1.0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def floor(n: int, seed: int, half: float, z: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-half, half, (n, 2)), np.full(n, z) + rng.normal(0, 1e-3, n)]


def lumpy(n: int, seed: int) -> np.ndarray:
    """An asymmetric blob: an ellipsoid with a bump and a tail (no rotational symmetry)."""
    x = sphere(n, seed) * [1.0, 0.6, 0.35]
    bump = sphere(n // 4, seed + 1, center=(0.7, 0.3, 0.2), radius=0.25)
    tail = np.c_[np.linspace(-1.6, -1.0, n // 8), np.zeros(n // 8), np.linspace(0.0, 0.4, n // 8)]
    return np.concatenate([x, bump, tail])


def table(n: int, seed: int) -> np.ndarray:
    """A table standing on z = 0: a top at z = 1 and four legs."""
    rng = np.random.default_rng(seed)
    top = np.c_[rng.uniform(-1.0, 1.0, n), rng.uniform(-0.6, 0.6, n), rng.uniform(1.0, 1.05, n)]
    legs = [np.c_[rng.normal(x, 0.02, n // 8), rng.normal(y, 0.02, n // 8), rng.uniform(0.0, 1.0, n // 8)]
            for x, y in ((-0.9, -0.5), (-0.9, 0.5), (0.9, -0.5), (0.9, 0.5))]
    return np.concatenate([top, *legs])


@pytest.fixture(scope="module")
def sneaker(data_dir):
    mesh = read_mesh(data_dir / "scans" / "sneaker.ply")
    return mesh


@pytest.fixture(scope="module")
def chair(data_dir):
    return read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")


# --- small helpers ----------------------------------------------------------------------------------------------


def test_rotation_sets_are_proper_and_distinct():
    for group, size in ((proper_signed_permutations(), 24), (icosahedral_rotations(), 60)):
        assert group.shape == (size, 3, 3)
        for r in group:
            np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(r) == pytest.approx(1.0)
        distinct = {tuple(np.round(r, 6).ravel()) for r in group}
        assert len(distinct) == size


def test_parse_axis():
    np.testing.assert_array_equal(parse_axis("z"), [0, 0, 1])
    np.testing.assert_array_equal(parse_axis("-Y"), [0, -1, 0])
    np.testing.assert_array_equal(parse_axis("+x"), [1, 0, 0])
    np.testing.assert_allclose(parse_axis([0, 0, 2]), [0, 0, 1])
    with pytest.raises(InputError, match="one of x, y, z"):
        parse_axis("w")
    with pytest.raises(InputError, match="non-zero"):
        parse_axis([0, 0, 0])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), log_scale=st.floats(-3, 3), offset=st.floats(-100, 100))
def test_similarity_matrices_are_exact_inverses(seed, log_scale, offset):
    rng = np.random.default_rng(seed)
    r = rotation(seed)
    points = rng.normal(size=(50, 3)) * 10.0**log_scale + offset
    normalizer = Normalizer().fit(points @ r.T)
    forward, inverse = similarity_matrices(r, normalizer)
    aligned = points @ forward[:3, :3].T + forward[:3, 3]
    np.testing.assert_allclose(aligned, normalizer.apply(points @ r.T), atol=1e-12)
    back = aligned @ inverse[:3, :3].T + inverse[:3, 3]
    np.testing.assert_allclose(back, points, rtol=0, atol=1e-9 * max(1.0, np.abs(points).max()))
    np.testing.assert_allclose(inverse @ forward, np.eye(4), atol=1e-12)


# --- orientation ------------------------------------------------------------------------------------------------


def test_sneaker_rotations_are_undone(sneaker):
    reference = sample_surface(sneaker.vertices, sneaker.triangles, 4000, seed=1).points
    scan = sample_surface(sneaker.vertices, sneaker.triangles, 6000, seed=2).points
    aligner = ScanAligner().fit(reference)
    for seed in (3, 4):
        true = rotation(seed)
        o = aligner.orient(scan @ true.T)
        assert rotation_angle(o.rotation @ true) < 5.0
        assert not o.ambiguous and o.margin > 0.2
        assert o.runner_up_rotation is not None and o.runner_up_angle > aligner.distinct_angle
        assert o.hypotheses[0].score == pytest.approx(o.score)
        assert all(h.score >= o.score for h in o.hypotheses)


def test_chair_rotation_is_undone_and_mapped_onto_reference(chair):
    reference = sample_surface(chair.vertices, chair.triangles, 4000, seed=1).points
    scan = sample_surface(chair.vertices, chair.triangles, 5000, seed=2).points
    true = rotation(11)
    units = 0.01 * (scan @ true.T) + [5.0, -3.0, 2.0]  # other units, other place
    o = orient(units, reference)
    assert rotation_angle(o.rotation @ true) < 5.0
    assert not o.ambiguous
    mapped = (units @ o.rotation.T) * o.scale + o.translation  # onto the reference, in its units
    extent = np.ptp(reference, axis=0).max()
    assert np.abs(np.median(mapped, axis=0) - np.median(reference, axis=0)).max() < 0.05 * extent
    np.testing.assert_allclose(o.scale, 100.0, rtol=0.1)


def test_up_restricts_the_search_to_turns_about_it(chair):
    reference = sample_surface(chair.vertices, chair.triangles, 3000, seed=1).points  # z up
    scan = sample_surface(chair.vertices, chair.triangles, 3000, seed=2).points
    to_y_up = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])  # ModelNet -> y up, (x,y,z)->(-y,z,-x)
    turn = Rotation.from_rotvec([0.0, 2.1, 0.0]).as_matrix()  # about the scan's up (y)
    true = turn @ to_y_up
    o = orient(scan @ true.T, reference, up="y", reference_up="z")
    assert rotation_angle(o.rotation @ true) < 5.0
    for h in o.hypotheses:  # every hypothesis takes the scan's up to the reference's up
        np.testing.assert_allclose(h.rotation @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-9)


def test_support_plane_stands_a_table_on_its_legs():
    points = table(4000, 0)
    guess = Rotation.from_rotvec([0.15, -0.1, 0.0]).as_matrix() @ [0.0, 0.0, 1.0]  # 10 degrees off
    found = support_plane(points, guess)
    assert np.degrees(np.arccos(found.normal @ [0.0, 0.0, 1.0])) < 1.0
    assert found.stability > 0.2 and found.count > 0
    overhang = points.copy()
    overhang[:4000, 0] += 2.5  # the top pushed beyond the legs: the centroid is no longer over the leg tips
    assert support_plane(overhang, [0.0, 0.0, 1.0], max_angle=10.0).stability < 0.0


def test_reference_up_turns_on_the_support_prior(chair):
    reference = sample_surface(chair.vertices, chair.triangles, 3000, seed=1).points  # ModelNet10: z up
    scan = sample_surface(chair.vertices, chair.triangles, 4000, seed=2).points
    true = rotation(8)
    aligner = ScanAligner(reference_up="z").fit(reference)
    assert np.degrees(np.arccos(aligner.reference_support_.normal[2])) < 3.0
    o = aligner.orient(scan @ true.T)  # the scan's up is unknown: all rotations are searched
    assert rotation_angle(o.rotation @ true) < 5.0
    assert o.hypotheses[0].source.endswith("+support")
    assert sum("+turn" in h.source for h in o.hypotheses) == 3  # the best's quarter turns about the up axis
    assert ScanAligner().fit(reference).reference_support_ is None  # no reference_up: no prior
    with pytest.raises(InputError, match="snap_angle"):
        ScanAligner(snap_angle=95.0).fit(reference)


def test_round_object_is_ambiguous_and_asymmetric_one_is_not():
    o = orient(cylinder(3000, 0) @ rotation(5).T, cylinder(3000, 1))
    assert o.ambiguous and o.margin < 0.1
    o = orient(lumpy(3000, 2) @ rotation(6).T, lumpy(3000, 3))
    assert not o.ambiguous
    assert rotation_angle(o.rotation @ rotation(6)) < 5.0


def test_mirror_symmetric_bottle_is_ambiguous(data_dir):
    mesh = read_mesh(data_dir / "scans" / "ycb" / "mustard_bottle" / "textured_simple_reoriented.obj")
    reference = sample_surface(mesh.vertices, mesh.triangles, 3000, seed=0).points
    scan = sample_surface(mesh.vertices, mesh.triangles, 3000, seed=1).points @ rotation(2).T
    o = orient(scan, reference)
    assert o.ambiguous
    assert o.runner_up_angle > 150.0  # the bottle's near 180-degree symmetry about its long axis


def test_orientation_is_seed_stable():
    scan, reference = lumpy(2000, 0) @ rotation(1).T, lumpy(2000, 1)
    a = orient(scan, reference, seed=4)
    b = orient(scan, reference, seed=4)
    np.testing.assert_array_equal(a.rotation, b.rotation)
    assert a.score == b.score


def test_orient_errors():
    with pytest.raises(NotFittedError, match="fit"):
        ScanAligner().orient(lumpy(100, 0))
    with pytest.raises(InputError, match="trim"):
        ScanAligner(trim=2.0).fit(lumpy(100, 0))
    with pytest.raises(InputError, match="at least 10"):
        orient(lumpy(100, 0)[:5], lumpy(100, 1))
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        orient(np.zeros((100, 2)), lumpy(100, 1))
    with pytest.raises(InputError, match="coincide"):
        orient(np.ones((50, 3)), lumpy(100, 1))


# --- cleaning ---------------------------------------------------------------------------------------------------


def test_statistical_outliers_are_removed_and_counted():
    body = sphere(3000, 0)
    stray = np.random.default_rng(1).uniform(-6, 6, (60, 3))
    stray = stray[np.linalg.norm(stray, axis=1) > 2.0]
    cleaned, report = clean(np.concatenate([body, stray]))
    assert report.outliers_removed >= 0.9 * len(stray)
    assert report.input_count - report.outliers_removed == report.output_count == len(cleaned)
    assert report.ground_removed is None and "up axis is unknown" in report.ground_note
    kept, report = clean(np.concatenate([body, stray]), outliers=False)
    assert report.outliers_removed is None and len(kept) == len(body) + len(stray)


def test_ground_plane_is_removed_only_below_a_known_up():
    obj = sphere(3000, 0, center=(0, 0, 1.2))
    scan = np.concatenate([obj, floor(3000, 1, half=2.5)])
    cleaned, report = clean(scan, up="z", outliers=False)
    assert report.ground_removed >= 2990 and len(obj) - 10 <= report.output_count <= len(obj) + 10
    assert abs(report.ground_plane[2]) > 0.99
    assert cleaned[:, 2].min() > 0.0
    cleaned, report = clean(scan, up="z")  # both steps
    assert report.output_count >= 0.95 * len(obj) and cleaned[:, 2].min() > 0.0
    _, report = clean(scan)  # no up: not searched
    assert report.ground_removed is None
    _, report = clean(scan, up="z", ground=False, outliers=False)
    assert report.ground_removed is None and report.output_count == len(scan)
    _, report = clean(scan, up="x", outliers=False)  # the plane is not below the object along x
    assert report.ground_removed == 0


def test_table_top_is_not_taken_for_a_ground():
    rng = np.random.default_rng(0)
    top = np.c_[rng.uniform(-1, 1, (3000, 2)), np.full(3000, 1.0)]
    legs = np.concatenate([np.c_[np.full(300, x), np.full(300, y), np.linspace(0, 1, 300)]
                           for x in (-0.9, 0.9) for y in (-0.9, 0.9)])
    _, report = clean(np.concatenate([top, legs]), up="z", outliers=False)
    assert report.ground_removed == 0


def test_scan_of_only_a_floor_is_refused():
    with pytest.raises(InputError, match="empty after cleaning"):
        clean(np.concatenate([floor(2000, 0, half=1.0), [[0.0, 0.0, 0.5], [0.1, 0.0, 0.6]]]), up="z")


def test_nan_and_flat_arrays_are_refused():
    points = sphere(100, 0)
    points[7, 1] = np.nan
    with pytest.raises(InputError, match="finite"):
        clean(points)
    with pytest.raises(InputError, match="finite"):
        preprocess(points, sphere(100, 1))
    with pytest.raises(InputError, match=r"shape \(N, 3\); got \(100, 2\)"):
        preprocess(sphere(100, 0)[:, :2])


def _icosphere_mesh(offset=(0.0, 0.0, 0.0), scale=1.0) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=scale, resolution=10)
    return np.asarray(m.vertices) + offset, np.asarray(m.triangles).astype(np.int64)


def test_small_mesh_pieces_are_dropped_but_seams_do_not_split():
    v1, t1 = _icosphere_mesh()
    v2, t2 = _icosphere_mesh(offset=(5.0, 0.0, 0.0), scale=0.05)
    vertices = np.concatenate([v1, v2])
    triangles = np.concatenate([t1, t2 + len(v1)])
    uvs = np.tile([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], (len(triangles), 1))
    mesh = Mesh(vertices, triangles, triangle_uvs=uvs)
    cleaned, report = clean(mesh)
    assert isinstance(cleaned, Mesh)
    assert report.pieces_removed == 1 and report.pieces_vertices_removed == len(v2)
    assert len(cleaned.vertices) == len(v1) and len(cleaned.triangles) == len(t1)
    assert cleaned.triangle_uvs.shape == (3 * len(t1), 2)
    # duplicate the vertices of half the triangles (a texture seam): still one piece
    half = len(t1) // 2
    seam_v = np.concatenate([v1, v1])
    seam_t = np.concatenate([t1[:half], t1[half:] + len(v1)])
    _, report = clean(Mesh(seam_v, seam_t))
    assert report.pieces_removed == 0


def test_small_pieces_touching_the_object_are_kept():
    body_v, body_t = _icosphere_mesh()
    near_v, near_t = _icosphere_mesh(offset=(1.02, 0.0, 0.0), scale=0.05)  # a knob resting on the body
    far_v, far_t = _icosphere_mesh(offset=(1.6, 0.0, 0.0), scale=0.05)  # debris well apart from it
    vertices = np.concatenate([body_v, near_v, far_v])
    triangles = np.concatenate([body_t, near_t + len(body_v), far_t + len(body_v) + len(near_v)])
    cleaned, report = clean(Mesh(vertices, triangles))
    assert report.pieces_removed == 1 and report.pieces_vertices_removed == len(far_v)
    assert np.allclose(cleaned.vertices, np.concatenate([body_v, near_v]))


def test_a_cad_chair_built_of_parts_keeps_every_part(data_dir):
    # ModelNet10 chair_0891 is 24 separate pieces (seat, back, legs, feet, stretchers); 16 of them are under 5% of
    # the seat's area, and a rule by area alone took them all away
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0891.ply")
    cleaned, report = clean(mesh)
    assert report.pieces_removed == 0
    assert len(cleaned.vertices) == len(mesh.vertices) and len(cleaned.triangles) == len(mesh.triangles)
    _, by_area = clean(mesh, piece_gap=0.0)
    assert by_area.pieces_removed == 16


def test_point_set_keeps_its_type_and_colours():
    points = np.concatenate([sphere(500, 0), [[9.0, 9.0, 9.0]]])
    colors = np.random.default_rng(0).uniform(0, 1, points.shape)
    cleaned, report = clean(PointSet(points, colors=colors))
    assert isinstance(cleaned, PointSet) and report.outliers_removed >= 1
    assert not np.isclose(cleaned.points, [9.0, 9.0, 9.0]).all(axis=1).any()
    np.testing.assert_array_equal(cleaned.colors, colors[:-1][np.isin(points[:-1], cleaned.points).all(axis=1)])


# --- the one-call pipeline ----------------------------------------------------------------------------------------


def test_preprocess_round_trip_is_exact(sneaker):
    scan = sample_surface(sneaker.vertices, sneaker.triangles, 3000, seed=0).points @ rotation(9).T * 250.0 + 40.0
    reference = sample_surface(sneaker.vertices, sneaker.triangles, 3000, seed=1).points
    result = preprocess(scan, reference, clean_params={"outliers": False})
    assert len(result.points) == len(scan)
    assert np.abs(result.points).max() == pytest.approx(1.0)
    np.testing.assert_allclose(result.to_original(result.points), scan, rtol=0, atol=1e-9 * np.abs(scan).max())
    np.testing.assert_allclose(result.to_aligned(scan), result.points, atol=1e-12)
    np.testing.assert_allclose(result.inverse @ result.transform, np.eye(4), atol=1e-12)
    assert rotation_angle(result.rotation @ rotation(9)) < 5.0
    # the aligned scan lies in the reference's frame: same layout after both are normalised
    ref_box = Normalizer().fit(reference).apply(reference)
    assert np.abs(np.ptp(result.points, axis=0) - np.ptp(ref_box, axis=0)).max() < 0.1
    record = json.loads(json.dumps(result.to_dict()))
    assert record["orientation"]["ambiguous"] is False and len(record["transform"]) == 4


def test_preprocess_mesh_keeps_topology_and_turns_normals(sneaker):
    result = preprocess(sneaker)  # no reference: clean + normalise only
    assert isinstance(result.shape, Mesh) and result.orientation is None
    np.testing.assert_array_equal(result.shape.triangles, sneaker.triangles)
    np.testing.assert_allclose(result.to_original(result.shape.vertices), sneaker.vertices, atol=1e-9)


def test_mesh_scan_is_oriented_by_its_surface_not_its_vertices():
    # a box with a finely tessellated ball on one corner: 7000 of the vertices are on the ball, most of the area on
    # the box; oriented by its vertices the scan looks round (wrong and ambiguous), by its surface it is not
    import open3d as o3d

    shape = o3d.geometry.TriangleMesh.create_box(3.0, 1.5, 0.6)
    shape += o3d.geometry.TriangleMesh.create_sphere(0.35, resolution=60).translate((2.6, 1.2, 0.9))
    vertices, triangles = np.asarray(shape.vertices), np.asarray(shape.triangles)
    reference = sample_surface(vertices, triangles, 5000, seed=1).points
    for seed in range(2):
        true = rotation(seed)
        result = preprocess(Mesh(vertices=vertices @ true.T, triangles=triangles), reference)
        assert rotation_angle(result.rotation @ true) < 3.0 and not result.orientation.ambiguous
        assert isinstance(result.shape, Mesh) and len(result.shape.vertices) == len(vertices)


# --- command line -------------------------------------------------------------------------------------------------


def test_cli_writes_aligned_scan_and_report(tmp_path, capsys):
    scan = lumpy(3000, 0) @ rotation(3).T * 30.0 + 7.0
    write_points(tmp_path / "scan.ply", scan)
    write_points(tmp_path / "ref.ply", lumpy(3000, 1))
    out, report = tmp_path / "aligned.ply", tmp_path / "report.json"
    code = main(["scan", str(tmp_path / "scan.ply"), "--reference", str(tmp_path / "ref.ply"), "--out", str(out),
                 "--report", str(report), "--no-outliers"])
    assert code == 0
    assert "oriented" in capsys.readouterr().out
    aligned = read_points(out).points
    record = json.loads(report.read_text())
    inverse = np.asarray(record["inverse"])
    np.testing.assert_allclose(aligned @ inverse[:3, :3].T + inverse[:3, 3], scan, atol=1e-6)
    assert rotation_angle(np.asarray(record["rotation"]) @ rotation(3)) < 5.0
    assert record["clean"]["outliers_removed"] is None
    # a second run refuses to overwrite without --force
    code = main(["scan", str(tmp_path / "scan.ply"), "--out", str(out), "--report", str(report)])
    assert code == 2 and "exists" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["nan", "flat", "missing", "floor"])
def test_cli_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path, capsys, bad):
    path = tmp_path / "scan.npy"
    if bad == "nan":
        points = sphere(200, 0)
        points[3, 0] = np.nan
        np.save(path, points)
    elif bad == "flat":
        np.save(path, sphere(200, 0)[:, :2])
    elif bad == "floor":
        np.save(path, np.concatenate([floor(2000, 0, half=1.0), [[0.0, 0.0, 0.5]]]))
    out, report = tmp_path / "out.ply", tmp_path / "report.json"
    code = main(["scan", str(path), "--out", str(out), "--report", str(report), "--up", "z"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("kpd scan: error:")
    assert not out.exists() and not report.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["scan.npy"] if bad != "missing" else [])


def test_cli_refuses_mesh_output_for_points_and_bad_axis(tmp_path, capsys):
    write_points(tmp_path / "scan.ply", lumpy(500, 0))
    code = main(["scan", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "a.obj"),
                 "--report", str(tmp_path / "r.json")])
    assert code == 2 and "point cloud" in capsys.readouterr().err
    code = main(["scan", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "a.ply"),
                 "--report", str(tmp_path / "r.json"), "--up", "sideways"])
    assert code == 2 and "--up" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.ply"]


def test_cli_model_template(tmp_path, capsys, chair):
    from kpd.bundle import shipped_bundles

    assert "chair" in shipped_bundles()
    path = tmp_path / "chair.ply"
    write_points(path, sample_surface(chair.vertices, chair.triangles, 4000, seed=0).points @ rotation(1).T)
    code = main(["scan", str(path), "--model", "chair", "--out", str(tmp_path / "a.ply"),
                 "--report", str(tmp_path / "r.json")])
    assert code == 0
    record = json.loads((tmp_path / "r.json").read_text())
    assert "template" in record["reference"] and record["orientation"]["score"] > 0


def test_cli_picture_shows_the_scan_best_and_runner_up(tmp_path, capsys, chair):
    import matplotlib.image

    path = tmp_path / "chair.ply"
    write_points(path, sample_surface(chair.vertices, chair.triangles, 4000, seed=0).points @ rotation(2).T)
    picture = tmp_path / "check.png"
    code = main(["scan", str(path), "--model", "chair", "--out", str(tmp_path / "a.ply"),
                 "--report", str(tmp_path / "r.json"), "--picture", str(picture)])
    assert code == 0 and "check.png" in capsys.readouterr().out
    image = matplotlib.image.imread(picture)[..., :3]  # (H, W, 3) floats in [0, 1]
    assert image.shape[1] > 2 * image.shape[0]  # three panels side by side
    saturation = image.max(axis=2) - image.min(axis=2)
    grey = (saturation < 0.05) & (np.abs(image.mean(axis=2) - 0.7) < 0.12)  # the reference's points (and grid panes)
    for third in np.array_split(np.arange(image.shape[1]), 3):
        assert (saturation[:, third] > 0.3).mean() > 0.01  # the scan's coloured points in every panel
    assert grey[:, image.shape[1] // 3:].mean() > grey[:, : image.shape[1] // 3].mean()  # reference behind 2 and 3


def test_cli_picture_errors(tmp_path, capsys):
    write_points(tmp_path / "scan.ply", lumpy(500, 0))
    base = ["scan", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "a.ply"), "--report", str(tmp_path / "r.json")]
    assert main(base + ["--reference", str(tmp_path / "scan.ply"), "--picture", str(tmp_path / "p.jpg")]) == 2
    assert ".png" in capsys.readouterr().err
    assert main(base + ["--picture", str(tmp_path / "p.png")]) == 2
    assert "--reference or --model" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.ply"]


@pytest.mark.parametrize("name", ["banana", "mustard_bottle", "power_drill"])
def test_cli_on_real_ycb_scans_keeps_the_mesh_and_maps_back(tmp_path, capsys, data_dir, name):
    # real textured scans (the mustard bottle's texture file is missing: read without it, with a warning)
    path = data_dir / "scans" / "ycb" / name / "textured_simple_reoriented.obj"
    scan = read_mesh(path)
    out, report = tmp_path / "aligned.obj", tmp_path / "report.json"
    code = main(["scan", str(path), "--reference", str(path), "--out", str(out), "--report", str(report)])
    assert code == 0, capsys.readouterr().err
    aligned = read_mesh(out)
    record = json.loads(report.read_text())
    inverse = np.asarray(record["inverse"])
    np.testing.assert_array_equal(aligned.triangles, scan.triangles)  # nothing of this clean scan was dropped
    np.testing.assert_allclose(aligned.vertices @ inverse[:3, :3].T + inverse[:3, 3], scan.vertices, atol=1e-6)
    assert np.abs(aligned.vertices).max() <= 1.0 + 1e-9
    assert (aligned.triangle_uvs is not None) == (scan.triangle_uvs is not None)
    assert len(aligned.textures) == len(scan.textures)
    # oriented to itself: the identity, unless the object is flagged ambiguous (the bottle is mirror-symmetric)
    assert record["orientation"]["ambiguous"] or rotation_angle(np.asarray(record["rotation"])) < 5.0
