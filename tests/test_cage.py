import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kpd.cage import (
    Cage,
    cage_faces_from_vertices,
    default_m,
    fit_cage,
    icosphere,
    influence_mask,
    points_outside,
    winding_number,
)
from kpd.errors import InputError


def signed_volume(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("fi,fi->f", a, np.cross(b, c)).sum() / 6.0)


def canonical(faces):
    """Triangles as a set, each rotated to start at its smallest index (orientation kept)."""
    return {tuple(np.roll(t, -int(np.argmin(t)))) for t in np.asarray(faces).tolist()}


def chair_points(n=1024, seed=0):
    """A synthetic chair in the [-1, 1] box: seat slab, back slab, four thin legs (surface-ish samples)."""
    rng = np.random.default_rng(seed)
    parts = [
        ((-0.6, 0.6), (-0.6, 0.6), (-0.05, 0.05)),  # seat
        ((-0.6, 0.6), (0.5, 0.6), (0.05, 1.0)),  # back
    ] + [((x - 0.04, x + 0.04), (y - 0.04, y + 0.04), (-1.0, -0.05)) for x in (-0.55, 0.55) for y in (-0.55, 0.55)]
    sizes = np.array([np.prod([hi - lo for lo, hi in box]) ** (2 / 3) for box in parts])
    counts = rng.multinomial(n, sizes / sizes.sum())
    pts = [rng.uniform([b[0] for b in box], [b[1] for b in box], (k, 3)) for box, k in zip(parts, counts)]
    return np.concatenate(pts)


def brute_force_fit(points, template, distance=0.4, iterations=100, step=0.01):
    """The authors' loop, one vertex at a time, with explicit distances."""
    out = []
    for c in template.vertices:
        c = c.copy()
        for _ in range(iterations):
            if np.min(np.linalg.norm(points - c, axis=1)) > distance:
                c = c + step * -c
            else:
                break
        out.append(c)
    return np.array(out)


# --- icosphere ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("level, c, f", [(0, 12, 20), (1, 42, 80), (2, 162, 320), (3, 642, 1280)])
def test_icosphere_counts_radius_and_orientation(level, c, f):
    cage = icosphere(level, radius=1.4)
    assert isinstance(cage, Cage)
    assert cage.vertices.shape == (c, 3) and cage.vertices.dtype == np.float64
    assert cage.faces.shape == (f, 3) and cage.faces.dtype == np.int64
    np.testing.assert_allclose(np.linalg.norm(cage.vertices, axis=1), 1.4, rtol=1e-14)
    assert signed_volume(*cage) > 0
    # Every face points away from the origin and every directed edge appears once, its reverse once.
    a, b, cc = (cage.vertices[cage.faces[:, k]] for k in range(3))
    assert (np.einsum("fi,fi->f", a, np.cross(b, cc)) > 0).all()
    directed = [(int(t[k]), int(t[(k + 1) % 3])) for t in cage.faces for k in range(3)]
    assert len(set(directed)) == 3 * f
    assert all((b_, a_) in set(directed) for a_, b_ in directed)
    assert len(np.unique(cage.vertices.round(12), axis=0)) == c


def test_icosphere_numbers_vertices_as_pytorch3d():
    cage = icosphere(1)
    # Level-0 vertices first (pytorch3d's icosahedron, normalised), then edge midpoints in sorted edge order: the
    # first edge is (0, 1), whose midpoint projects to (0, 1, 0); the level-1 cage fills the box [-1.4, 1.4].
    np.testing.assert_allclose(cage.vertices[0], 1.4 * np.array([-0.5257, 0.8507, 0]) / np.hypot(0.5257, 0.8507))
    np.testing.assert_allclose(cage.vertices[12], [0, 1.4, 0], atol=1e-15)
    np.testing.assert_allclose(np.abs(cage.vertices).max(), 1.4)
    # Face 0 of level 0 is (0, 11, 5); its first child is (0, mid(0, 11), mid(5, 0)) and edges (0, 1), (0, 5), (0, 7),
    # (0, 10), (0, 11) are the first five, so the midpoints are vertices 16 and 13.
    assert cage.faces[:3].tolist() == [[0, 16, 13], [0, 13, 12], [0, 12, 14]]


@pytest.mark.parametrize("level", [-1, 8, 1.5, True])
def test_icosphere_rejects_bad_level(level):
    with pytest.raises(InputError, match="level"):
        icosphere(level)


def test_icosphere_rejects_bad_radius():
    with pytest.raises(InputError, match="radius"):
        icosphere(1, radius=0.0)


# --- fit_cage ----------------------------------------------------------------------------------------------------

def test_fit_cage_matches_the_authors_loop():
    points = chair_points(300, seed=1)
    template = icosphere(1)
    cage = fit_cage(points)
    np.testing.assert_allclose(cage.vertices, brute_force_fit(points, template), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(cage.faces, template.faces)


def test_fit_cage_moves_vertices_along_their_rays_by_powers_of_099():
    points = chair_points(500)
    cage = fit_cage(points)
    template = icosphere(1)
    ratio = np.linalg.norm(cage.vertices, axis=1) / 1.4
    steps = np.log(ratio) / np.log(0.99)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    assert steps.min() >= -1e-9 and steps.max() <= 100 + 1e-9
    np.testing.assert_allclose(cage.vertices / ratio[:, None], template.vertices, atol=1e-12)
    # A vertex stopped early only once it was within the distance of the shape.
    nearest = np.min(np.linalg.norm(cage.vertices[:, None] - points[None], axis=2), axis=1)
    early = np.round(steps) < 100
    assert (nearest[early] <= 0.4).all()


def test_fit_cage_zero_iterations_returns_the_template():
    template = icosphere(2, radius=1.2)
    cage = fit_cage(chair_points(100), template=template, iterations=0)
    np.testing.assert_array_equal(cage.vertices, template.vertices)
    np.testing.assert_array_equal(cage.faces, template.faces)


def test_fit_cage_authors_rule_leaves_points_outside_and_enclose_fixes_it():
    points = chair_points()
    authors = fit_cage(points)
    outside = points_outside(points, *authors)
    assert outside.sum() > 0
    enclosed = fit_cage(points, enclose=True)
    assert not points_outside(points, *enclosed).any()
    np.testing.assert_allclose(winding_number(points, *enclosed), 1.0, atol=1e-9)
    # Vertices only move outward along their rays; the rest of the cage is the authors'.
    r0, r1 = np.linalg.norm(authors.vertices, axis=1), np.linalg.norm(enclosed.vertices, axis=1)
    assert (r1 >= r0 - 1e-15).all() and (r1 > r0).any()
    np.testing.assert_allclose(enclosed.vertices / r1[:, None], authors.vertices / r0[:, None], atol=1e-12)
    np.testing.assert_array_equal(enclosed.faces, authors.faces)
    # Deterministic.
    np.testing.assert_array_equal(fit_cage(points, enclose=True).vertices, enclosed.vertices)


def test_enclose_leaves_a_margin_and_keeps_inside_cages_unchanged():
    points = np.random.default_rng(3).normal(size=(400, 3))
    points *= 0.3 / np.abs(points).max()
    cage = fit_cage(points, enclose=True)
    np.testing.assert_array_equal(cage.vertices, fit_cage(points).vertices)  # nothing to push
    # A point on a vertex's ray just inside the cage is pushed to the margin: the vertex goes out by 2 %.
    template = icosphere(1)
    probe = 0.999 * template.vertices[5:6]
    pushed = fit_cage(probe, template=template, iterations=0, enclose=True)
    np.testing.assert_allclose(np.linalg.norm(pushed.vertices[5]), 0.999 * 1.4 / 0.98, rtol=1e-9)
    np.testing.assert_array_equal(np.delete(pushed.vertices, 5, axis=0), np.delete(template.vertices, 5, axis=0))


@settings(max_examples=25, deadline=None)
@given(
    arrays(np.float64, (60, 3), elements=st.floats(-1.8, 1.8)),
    arrays(np.float64, 42, elements=st.floats(0.2, 1.5)),
)
def test_enclose_puts_every_point_inside_any_star_cage(points, radii):
    template = icosphere(1)
    template = Cage(template.vertices * radii[:, None] / 1.4, template.faces)
    cage = fit_cage(points, template=template, iterations=0, enclose=True)
    assert not points_outside(points, *cage).any()


def border_points(template, rng, count):
    """Points on a star cage's cone borders: along vertex rays, on the planes of edges, at the origin."""
    units = template.vertices / np.linalg.norm(template.vertices, axis=1, keepdims=True)
    vertex = units[rng.integers(0, len(units), count)]
    edge = template.faces[rng.integers(0, len(template.faces), count)][:, :2]
    s = rng.uniform(0, 1, (count, 1))
    on_edge = s * units[edge[:, 0]] + (1 - s) * units[edge[:, 1]]
    return np.concatenate([vertex, on_edge, np.zeros((1, 3))]) * rng.uniform(0.2, 1.8, (2 * count + 1, 1))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2), st.integers(0, 2**31))
def test_enclose_matches_its_numpy_twin(level, seed):
    # the compiled cone walk over the points near the cage gives the cage of the numpy pass over every point and
    # face, also for points on cone borders, at the origin and in any order
    from kpd.cage import _enclose, _enclose_reference

    rng = np.random.default_rng(seed)
    template = icosphere(level)
    vertices = template.vertices * rng.uniform(0.3, 1.2, (len(template.vertices), 1))
    points = np.concatenate([rng.normal(size=(300, 3)) * rng.uniform(0.05, 0.6), border_points(template, rng, 40)])
    points = points[rng.permutation(len(points))]
    fast = _enclose(points, vertices, template.faces)
    np.testing.assert_allclose(fast, _enclose_reference(points, vertices, template.faces), rtol=0, atol=1e-12)
    assert not points_outside(points, fast, template.faces).any()


def test_enclose_raises_the_same_cage_for_a_chair_in_any_order():
    from kpd.cage import _enclose_reference

    points = chair_points(20000, seed=4)
    cage = fit_cage(points, distance=0.1)
    enclosed = fit_cage(points, template=cage, iterations=0, enclose=True)
    assert (enclosed.vertices != cage.vertices).any()  # something to raise
    np.testing.assert_allclose(enclosed.vertices, _enclose_reference(points, *cage), rtol=0, atol=1e-12)
    shuffled = points[np.random.default_rng(0).permutation(len(points))]
    np.testing.assert_allclose(fit_cage(shuffled, template=cage, iterations=0, enclose=True).vertices,
                               enclosed.vertices, rtol=0, atol=1e-12)


def test_face_neighbours_share_the_edge_opposite_each_corner():
    from kpd.cage import _face_neighbours

    faces = icosphere(2).faces
    neighbours = _face_neighbours(faces)
    assert (neighbours >= 0).all()
    for f in range(len(faces)):
        for k in range(3):
            edge = {faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]}
            g = neighbours[f, k]
            assert g != f and edge <= set(faces[g].tolist())
    open_faces = _face_neighbours(faces[:-1])  # the last face removed: its three neighbours lose one each
    assert (open_faces == -1).sum() == 3


def test_enclose_rejects_a_cage_that_is_not_star_shaped():
    v, f = icosphere(1)
    with pytest.raises(InputError, match="star-shaped"):
        fit_cage(np.zeros((1, 3)), template=Cage(v + [3.0, 0, 0], f), iterations=0, enclose=True)
    with pytest.raises(InputError, match="star-shaped"):
        fit_cage(np.zeros((1, 3)), template=Cage(v, f[:, ::-1]), iterations=0, enclose=True)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"step": 0.0}, "step"),
        ({"step": 1.0}, "step"),
        ({"distance": -1.0}, "distance"),
        ({"iterations": -1}, "iterations"),
        ({"iterations": 2.5}, "iterations"),
        ({"template": "sphere"}, "template"),
        ({"template": Cage(np.zeros((42, 3)), np.full((80, 3), 50))}, r"\[0, 41\] for 42 vertices"),
    ],
)
def test_fit_cage_rejects_bad_arguments(kwargs, match):
    with pytest.raises(InputError, match=match):
        fit_cage(chair_points(50), **kwargs)


def test_fit_cage_rejects_bad_points():
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        fit_cage(np.zeros((10, 2)))


# --- winding number ----------------------------------------------------------------------------------------------

def test_winding_number_inside_outside_and_on_the_surface():
    v, f = icosphere(1)
    inradius = np.min(np.abs(np.einsum("fi,fi->f", np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                       v[f[:, 0]])) / np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]],
                                                                             v[f[:, 2]] - v[f[:, 0]]), axis=1))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    inside = d * rng.uniform(0, 0.999 * inradius, (500, 1))
    outside = d * rng.uniform(1.401, 5, (500, 1))
    np.testing.assert_allclose(winding_number(inside, v, f), 1.0, atol=1e-12)
    np.testing.assert_allclose(winding_number(outside, v, f), 0.0, atol=1e-12)
    centre = v[f].mean(axis=1)  # (F, 3) on the faces; their normals point away from the origin
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    np.testing.assert_allclose(winding_number(centre - 1e-9 * normal, v, f), 1.0, atol=1e-6)
    np.testing.assert_allclose(winding_number(centre + 1e-9 * normal, v, f), 0.0, atol=1e-6)
    assert points_outside(outside, v, f).all() and not points_outside(inside, v, f).any()
    assert winding_number(np.zeros((0, 3)), v, f).shape == (0,)


def test_winding_number_of_a_reversed_cage_is_negative():
    v, f = icosphere(1)
    np.testing.assert_allclose(winding_number(np.zeros((1, 3)), v, f[:, ::-1]), -1.0)


# --- faces from vertices -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("level", [1, 2])
def test_cage_faces_from_shuffled_vertices_recover_the_surface(level):
    points = chair_points(600, seed=level)
    cage = fit_cage(points, template=icosphere(level))
    perm = np.random.default_rng(level).permutation(len(cage.vertices))
    shuffled = cage.vertices[perm]
    faces = cage_faces_from_vertices(shuffled)
    assert faces.dtype == np.int64 and faces.shape == cage.faces.shape
    inverse = np.argsort(perm)  # shuffled index -> original index is perm; original -> shuffled is inverse
    assert canonical(perm[faces]) == canonical(cage.faces)
    a, b, c = (shuffled[faces[:, k]] for k in range(3))
    assert (np.einsum("fi,fi->f", a, np.cross(b, c)) > 0).all()
    assert signed_volume(shuffled, faces) > 0
    assert canonical(faces) == canonical(inverse[cage.faces])


def test_cage_faces_from_vertices_output_is_canonical():
    faces = cage_faces_from_vertices(icosphere(1).vertices)
    assert (faces[:, 0] < faces[:, 1]).all() and (faces[:, 0] < faces[:, 2]).all()
    assert faces.tolist() == sorted(faces.tolist())


@pytest.mark.parametrize(
    "vertices, match",
    [
        (np.vstack([icosphere(1).vertices, np.zeros((1, 3))]), "origin"),
        (np.vstack([icosphere(1).vertices, 0.5 * icosphere(1).vertices[:1]]), "own direction"),
        (icosphere(1).vertices[icosphere(1).vertices[:, 2] > 0.3], "half-space"),
        (np.array([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]), "span no volume"),
    ],
)
def test_cage_faces_from_vertices_rejects_bad_cages(vertices, match):
    with pytest.raises(InputError, match=match):
        cage_faces_from_vertices(vertices)


# --- influence mask ----------------------------------------------------------------------------------------------

@settings(max_examples=50, deadline=None)
@given(
    arrays(np.float64, (6, 3), elements=st.floats(-2, 2)),
    arrays(np.float64, (20, 3), elements=st.floats(-2, 2)),
    st.integers(1, 20),
)
def test_influence_mask_keeps_the_m_nearest_and_ties(keypoints, cage, m):
    mask = influence_mask(keypoints, cage, m)
    assert mask.shape == (6, 20) and mask.dtype == bool
    d2 = np.sum((keypoints[:, None] - cage[None]) ** 2, axis=2)
    for k in range(6):
        kth = np.sort(d2[k])[m - 1]
        np.testing.assert_array_equal(mask[k], d2[k] <= kth)
        assert mask[k].sum() >= m


def test_influence_mask_keeps_ties():
    octahedron = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [3, 0, 0]])
    mask = influence_mask(np.zeros((2, 3)), octahedron, 2)  # six vertices tie at distance 1
    np.testing.assert_array_equal(mask, [[True] * 6 + [False]] * 2)
    mask = influence_mask([[0.5, 0, 0]], octahedron, 1)
    np.testing.assert_array_equal(mask[0], [True] + [False] * 6)


@pytest.mark.parametrize("m", [0, 43, 2.0, True])
def test_influence_mask_rejects_bad_m(m):
    with pytest.raises(InputError, match="m must"):
        influence_mask(np.zeros((1, 3)), icosphere(1).vertices, m)


@pytest.mark.parametrize(
    "c, k, paper, expected",
    [(42, 8, False, 5), (42, 12, False, 5), (42, 4, False, 10), (42, 16, False, 5), (162, 8, False, 20),
     (42, 8, True, 5), (42, 12, True, 3), (42, 16, True, 2), (42, 4, True, 10), (4, 1, False, 4)],
)
def test_default_m(c, k, paper, expected):
    assert default_m(c, k, paper=paper) == expected


@pytest.mark.parametrize("c, k, paper, match", [(0, 1, False, "C must"), (42, 0, False, "K must"),
                                               (4, 8, True, "gives 0")])
def test_default_m_rejects_bad_counts(c, k, paper, match):
    with pytest.raises(InputError, match=match):
        default_m(c, k, paper=paper)
