"""kpd.scan.clean: outliers, ground planes and small pieces removed, and nothing else."""

from __future__ import annotations

import numpy as np
import pytest
from scan_shapes import floor, sphere

from kpd.errors import InputError
from kpd.io import Mesh, PointSet, read_mesh
from kpd.scan import (
    clean,
    preprocess,
)


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


def test_touching_pieces_are_those_with_any_point_near_the_surface_probed_first_or_not():
    """_touching finds a piece by any one of its points within the gap, whether or not that point is among the
    few looked at first: the same pieces as every point's distance, for pieces of 1 to 3,000 points in any order."""
    import importlib

    clean_module = importlib.import_module("kpd.scan.clean")  # the module (kpd.scan.clean is also the function)
    rng = np.random.default_rng(0)
    surface = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])  # a triangle in z = 0
    scene = clean_module._scene(surface, np.array([[0, 1, 2]]))
    gap = 0.05
    for _ in range(20):
        sizes = rng.integers(1, 3000, size=rng.integers(1, 12))
        piece = rng.permutation(np.repeat(np.arange(len(sizes)), sizes))
        points = np.column_stack([rng.uniform(0.05, 0.3, len(piece)), rng.uniform(0.05, 0.3, len(piece)),
                                  rng.uniform(0.2, 1.0, len(piece))])  # above the triangle, beyond the gap
        for p in range(len(sizes)):  # a piece has no, one or many points within the gap
            members = np.flatnonzero(piece == p)
            near = rng.choice(members, size=[0, 1, len(members)][p % 3], replace=False)
            points[near, 2] = rng.uniform(0.0, 0.9 * gap, len(near))
        every = np.unique(piece[clean_module._distances(scene, points) <= gap])
        got = clean_module._touching(scene, points, piece, gap)
        np.testing.assert_array_equal(got, every)
        assert set(every) == {p for p in range(len(sizes)) if p % 3}


@pytest.mark.parametrize("cells", [256, 3])  # the grid as made, and widened to 3 cells an axis
def test_distances_within_the_gap_are_the_same_over_the_near_triangles_alone(cells, monkeypatch):
    """_near_triangles keeps every triangle that may come within the gap of a query point: the points within the gap
    of the surface are the same over the kept triangles as over all of them (small and large triangles, gaps from a
    hair to most of the box), and far triangles are left out."""
    import importlib

    clean_module = importlib.import_module("kpd.scan.clean")
    monkeypatch.setattr(clean_module, "_GRID_CELLS", cells)
    rng = np.random.default_rng(cells)
    dropped = 0
    for _ in range(12):
        centres = rng.uniform(-1, 1, size=(400, 3))
        sizes = rng.choice([0.01, 0.1, 1.0], size=(400, 1, 1))
        vertices = (centres[:, None, :] + sizes * rng.normal(size=(400, 3, 3))).reshape(-1, 3)
        triangles = np.arange(len(vertices)).reshape(-1, 3)
        points = rng.uniform(-1.2, 1.2, size=(300, 3)) * rng.choice([0.2, 1.0])
        everything = clean_module._scene(vertices, triangles)
        for gap in (1e-4, 0.02, 0.1, 0.5, 2.0):
            near = clean_module._near_triangles(vertices, triangles, points, gap)
            dropped += int((~near).sum())
            within = clean_module._distances(everything, points) <= gap
            if near.any():
                within_near = clean_module._distances(clean_module._scene(vertices, triangles[near]), points) <= gap
            else:
                within_near = np.zeros(len(points), dtype=bool)
            np.testing.assert_array_equal(within_near, within)
    assert dropped > 0 or cells < 8  # on a grid of 3 cells every cell is next to some point's
