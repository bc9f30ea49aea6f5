"""Straightening of slivers: what it keeps from turning over, the solve near the slivers against the whole mesh's
and the slow twin, the system's parts."""

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.io import read_mesh
from kpd.straighten import _factorised, straighten_basis, straighten_basis_reference
from rig_shapes import box_mesh, fps_rig, subdivided_unstraightened


def panel_with_slivers():
    """A flat panel (the xz plane) of well-shaped triangles under a thin slat (0.01 high, 2 long) whose bottom edge
    is the panel's top row and whose top edge has only its two ends: the slat is a fan of long slivers from its top
    left corner, as CAD triangulations make them. Returns vertices (V, 3), triangles (T, 3) and the slat's rows."""
    xs = np.linspace(-1.0, 1.0, 9)
    zs = np.linspace(0.0, 0.99, 5)
    grid = np.array([[x, 0.0, z] for z in zs for x in xs])  # row r, column c at 9 r + c; the top row at z = 0.99
    vertices = np.concatenate([grid, [[-1.0, 0.0, 1.0], [1.0, 0.0, 1.0]]])  # 45, 46: the slat's top corners
    triangles = []
    for r in range(4):
        for c in range(8):
            i = 9 * r + c
            triangles += [[i, i + 1, i + 10], [i, i + 10, i + 9]]
    top = 36 + np.arange(9)
    triangles += [[45, int(top[c]), int(top[c + 1])] for c in range(8)]
    triangles += [[45, int(top[8]), 46]]
    return vertices, np.array(triangles), np.arange(32 * 2, len(triangles))


def test_straighten_basis_keeps_slivers_from_turning_over_and_leaves_affine_motion_alone():
    from kpd.metrics import _turned
    from kpd.triangles import cross as _normals

    vertices, triangles, slat = panel_with_slivers()
    sag = 1.0 - vertices[:, [0]] ** 2  # (V, 1): a bend along the slat, largest in the middle
    affine = np.stack([0.3 * vertices[:, 0] - vertices[:, 2] + 0.5, 0.1 + 0.0 * vertices[:, 0]], axis=1)
    out = straighten_basis(np.concatenate([sag, affine], axis=1), vertices, triangles)
    # an affine motion turns no triangle over: it changes by less than the slivers' thickness changes (1% here)
    assert np.abs(out[:, 1:] - affine).max() < 0.01 * np.ptp(affine)
    np.testing.assert_allclose(out[:, 2], 0.1, atol=1e-12)  # a translation exactly
    lift = np.array([[0.0, 0.0, 0.2]])  # the bend as an edit: the middle of the slat rises by 0.2

    def turned(basis):
        return _turned(_normals(vertices, triangles), _normals(vertices + basis[:, :1] @ lift, triangles))

    assert turned(sag)[slat].sum() >= 3 and not turned(sag)[~np.isin(np.arange(len(triangles)), slat)].any()
    assert not turned(out).any()
    # the slat's bottom row now moves as the line between its ends does; the panel's bottom row keeps its bend
    top = out[36:45, 0]
    assert np.abs(top - np.interp(vertices[36:45, 0], [-1, 1], [top[0], top[-1]])).max() < 0.01 * np.ptp(sag)
    np.testing.assert_allclose(out[:9, 0], sag[:9, 0], atol=0.25)
    assert np.ptp(out[:9, 0]) > 0.5
    # no sliver (a box): the basis comes back as it is
    box = box_mesh()
    basis = np.random.default_rng(0).random((8, 3))
    np.testing.assert_array_equal(straighten_basis(basis, box.vertices, box.triangles), basis)
    with pytest.raises(InputError, match="thinness"):
        straighten_basis(basis, box.vertices, box.triangles, thinness=0.0)
    with pytest.raises(InputError, match=r"basis must be \(V, K\)"):
        straighten_basis(basis[:5], box.vertices, box.triangles)


def test_straighten_basis_merges_coincident_corners():
    """A mesh stored with one vertex per triangle corner (as CAD files are) gets the same correction as the merged
    mesh, the same at every copy of a corner, so the edited mesh has no cracks."""
    vertices, triangles, _ = panel_with_slivers()
    basis = np.stack([1.0 - vertices[:, 0] ** 2, vertices[:, 0] * vertices[:, 2]], axis=1)
    merged = straighten_basis(basis, vertices, triangles)
    corners = triangles.ravel()
    split = straighten_basis(basis[corners], vertices[corners], np.arange(len(corners)).reshape(-1, 3))
    np.testing.assert_allclose(split, merged[corners], atol=1e-10)


@pytest.mark.parametrize("name", ["chair_0890", "chair_0956"])
def test_straightening_by_pieces_equals_the_whole_mesh_solve(data_dir, name):
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / f"{name}.ply")
    rig = fps_rig(mesh, straighten=False)
    vertices = rig.normalizer.apply(mesh.vertices)
    basis = np.asarray(rig.basis, dtype=np.float64)
    local = straighten_basis(basis, vertices, mesh.triangles)
    pieces = straighten_basis(basis, vertices, mesh.triangles, tolerance=0)
    slow = straighten_basis_reference(basis, vertices, mesh.triangles)
    assert np.abs(slow - basis).max() > 1e-3  # the meshes have slivers to straighten
    np.testing.assert_allclose(pieces, slow, rtol=0, atol=1e-9)  # the same system, solved exactly by pieces
    assert np.abs(local - slow).max() <= 1e-4  # solved near the slivers only: the bound


def test_the_straightenings_factorisation_solves_a_symmetric_positive_definite_system_in_any_numbering():
    """The LDLᵀ solve the straightening uses, on a graph Laplacian plus a diagonal (its systems' kind) with several
    right-hand sides, against SciPy's general sparse solve, in a random numbering of the unknowns."""
    import scipy.sparse as sparse
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(3)
    n = 2000
    rows = rng.integers(0, n, 8000)
    cols = (rows + rng.integers(1, 40, 8000)) % n
    w = rng.uniform(0.1, 1e4, 8000)
    adjacency = sparse.coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()
    adjacency = adjacency + adjacency.T
    laplacian = sparse.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    system = (laplacian + sparse.diags(rng.uniform(1e-3, 1.0, n))).tocsc()
    rhs = rng.standard_normal((n, 5))
    expected = spsolve(system, rhs)
    np.testing.assert_allclose(_factorised(system)(rhs), expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    order = rng.permutation(n)
    shuffled = system[order][:, order].tocsc()
    np.testing.assert_allclose(_factorised(shuffled)(rhs[order]), expected[order], rtol=0,
                               atol=1e-9 * np.abs(expected).max())


def test_a_triangle_stored_again_adds_its_sliver_terms_as_often_as_it_is_stored():
    """The straightening's system counts a triangle stored again over the same corners (either way round, as
    ShapeNet stores every face) through its first copy: its terms are those of each copy, added. Where two edges
    of a sliver are equally longest, the copies' orders take different long edges: each copy adds its own."""
    from kpd.straighten import STRAIGHTEN_REACH, STRAIGHTEN_THINNESS, StraightenSystem

    points, triangles = [], []
    for i, h in enumerate((0.002, 0.01, 0.03)):  # per level: an isosceles sliver (two equal long edges), a plain one
        z = float(i)
        base = len(points)
        points += [[0.0, 0.0, z], [1.0, h, z], [1.0, -h, z], [1.3, h, z]]
        triangles += [[base, base + 1, base + 2], [base, base + 3, base + 2]]
    points = np.array(points)
    once = np.array(triangles)
    again = np.roll(once[:, ::-1], 1, axis=1)  # the other way round, from another corner
    half = np.concatenate([once[:2], again[2:]])  # a mix: each triangle once, some of them turned
    twice = np.concatenate([once, again, half])

    def system(tri):
        return StraightenSystem(points, tri, STRAIGHTEN_THINNESS, STRAIGHTEN_REACH)

    whole, parts = system(twice), [system(once), system(again), system(half)]
    assert all(np.array_equal(whole.indices, p.indices) for p in parts)
    np.testing.assert_allclose(whole.sliver_values, sum(p.sliver_values for p in parts), rtol=1e-12, atol=0)
    tied = system(once[::2]), system(again[::2])  # the isosceles slivers take a different long edge each way
    assert not np.allclose(tied[0].sliver_values, tied[1].sliver_values)
    # one sliver listed per plain triangle (its three copies in one), one per copy of an isosceles one
    assert whole.slivers == 3 + 3 * 3


def test_straightening_of_a_real_scan_solves_near_its_slivers_only(data_dir, caplog):
    """A real scan has few slivers (2.4% of the sneaker's triangles): the straightening solves for a small part of
    its points, grows that region by patches solved with the rest held, and agrees with the solve over the whole
    mesh within 1e-4."""
    import logging

    mesh, rig, vertices, basis = subdivided_unstraightened(data_dir / "scans" / "sneaker.ply", 1, "shoe")
    with caplog.at_level(logging.DEBUG, logger="kpd.straighten"):
        local = straighten_basis(basis, vertices, mesh.triangles)
    passes = [r for r in caplog.records if r.getMessage().startswith("straightening:")]
    assert len(passes) >= 2  # the first region, then at least one growth solved as a patch
    slow = straighten_basis_reference(basis, vertices, mesh.triangles)
    assert np.abs(slow - basis).max() > 1e-4  # it has slivers to straighten
    assert np.abs(local - slow).max() <= 1e-4
    untouched = (local == basis).all(axis=1)
    assert 0.5 < untouched.mean() < 1  # solved near the slivers: most vertices are left as they were
    assert (slow[untouched] != basis[untouched]).any()  # where the whole mesh's solve moves them a little


def test_straightening_of_a_dense_cad_mesh_solves_near_the_slivers_that_bend_it(data_dir):
    """A CAD mesh subdivided twice (a ShapeNet chair, 86k points): each of its slivers is now 16 slivers, each with
    a term that alone moves its corners by far less than the tolerance (the edges around them are 16 times stiffer).
    Solved near the slivers whose own term moves a point by more than the tolerance, it leaves about half the
    points as they were, and keeps as many triangles from turning over as the solve over the whole mesh in 72
    single moves (each keypoint by 10% of the box along each axis, both ways)."""
    chair = data_dir / "keypointnet" / "models" / "03001627" / "fe6b3c001a86d844d5767a0de8dd037e" / "model.obj"
    mesh, rig, vertices, basis = subdivided_unstraightened(chair, 2, "chair")
    local = straighten_basis(basis, vertices, mesh.triangles)
    slow = straighten_basis_reference(basis, vertices, mesh.triangles)
    untouched = (local == basis).all(axis=1)
    assert 0.3 < untouched.mean() < 0.8
    assert np.abs(slow[untouched] - basis[untouched]).max() > 1e-5  # the whole mesh's solve moves them

    def normals(points):
        corners = points[mesh.triangles]
        return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])

    rest = normals(vertices)
    worst = {}
    for name, b in (("plain", basis), ("local", local), ("whole", slow)):
        folded = []
        for k in range(rig.num_keypoints):
            for axis in range(3):
                for sign in (-1.0, 1.0):
                    delta = np.zeros((rig.num_keypoints, 3))
                    delta[k, axis] = 0.2 * sign  # 10% of the [-1, 1] box
                    folded.append(int((np.einsum("ij,ij->i", rest, normals(vertices + b @ delta)) < 0).sum()))
        worst[name] = max(folded)
    assert worst["local"] <= worst["whole"] < worst["plain"]


def test_the_straightenings_seeds_are_the_same_on_two_threads_as_on_one(data_dir, monkeypatch):
    """The region's seeds are judged from each sliver's step, made with the system (beside the MVC basis): the same
    seeds whether the slivers are judged in two halves on two threads or at once, and each step is the sliver's
    weight times its corner's coefficient over that corner's diagonal entry."""
    import kpd.straighten as ks
    from kpd.grouping import merge_coincident

    chair = data_dir / "keypointnet" / "models" / "03001627" / "fe6b3c001a86d844d5767a0de8dd037e" / "model.obj"
    mesh, rig, vertices, basis = subdivided_unstraightened(chair, 1, "chair")
    points, inverse = merge_coincident(vertices)
    system = ks.StraightenSystem(points, np.ascontiguousarray(inverse[mesh.triangles]), ks.STRAIGHTEN_THINNESS,
                                 ks.STRAIGHTEN_REACH)
    assert system.slivers > 1000 and system.step.shape == (system.slivers,)
    merged = np.ascontiguousarray(basis[np.unique(inverse, return_index=True)[1]])
    monkeypatch.setattr(ks, "_SEEDS_ON_TWO_THREADS", 10**12)
    alone = system._seeds(merged, ks.STRAIGHTEN_TOLERANCE)
    monkeypatch.setattr(ks, "_SEEDS_ON_TWO_THREADS", 0)
    halves = system._seeds(merged, ks.STRAIGHTEN_TOLERANCE)
    np.testing.assert_array_equal(halves, alone)
    assert 0 < alone.sum() < len(alone)
    for s in (0, system.slivers // 2, system.slivers - 1):
        c, a, b = system.ends[s]
        t = system.along[s]
        diagonal = {}
        for i in (c, a, b):
            row = np.empty(system.indptr[i + 1] - system.indptr[i])
            diagonal[i] = ks._row(i, system.indptr, system.indices, system.points, system.sliver_values,
                                  system.anchor, system.floor, row)
        w = ks._sliver_weight(np.linalg.norm(points[b] - points[a]), system.height[s], ks._STRAIGHTEN_CAP)
        expected = max(w / diagonal[c], w * (1 - t) / diagonal[a], w * t / diagonal[b])
        assert system.step[s] == pytest.approx(expected, rel=1e-12)
