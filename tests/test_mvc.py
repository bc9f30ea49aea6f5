import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from helpers import points_near_the_cage, star_cage

from kpd.cage import fit_cage, icosphere, points_outside
from kpd.errors import InputError
from kpd.geometry import Normalizer, sample_surface
from kpd.mvc import mvc_weights, mvc_weights_reference

TEMPLATE = icosphere(1)


def radial_distance(vertices, faces, directions):
    """Distance from the origin to a star-shaped cage along unit ``directions (N, 3)``."""
    cols = vertices[faces].transpose(0, 2, 1)  # (F, 3, 3) corners as columns
    lam = np.einsum("fij,nj->nfi", np.linalg.inv(cols), directions)  # (N, F, 3)
    best = lam.min(axis=2).argmax(axis=1)
    return 1.0 / lam[np.arange(len(directions)), best].sum(axis=1)


def inside_points(vertices, faces, directions, fractions):
    d = np.asarray(directions, dtype=float)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 1e-6, d / np.maximum(norm, 1e-300), [1.0, 0.0, 0.0])
    return d * (np.asarray(fractions)[:, None] * radial_distance(vertices, faces, d)[:, None])


def random_points(vertices, faces, n, lo, hi, seed):
    rng = np.random.default_rng(seed)
    return inside_points(vertices, faces, rng.normal(size=(n, 3)), rng.uniform(lo, hi, n))


# --- basic properties --------------------------------------------------------------------------------------------

def test_weights_shape_dtype_and_rows_sum_to_one():
    v, f = TEMPLATE
    x = np.random.default_rng(0).uniform(-1, 1, (1000, 3))
    w = mvc_weights(x, v, f)
    assert w.shape == (1000, 42) and w.dtype == np.float64
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-13)
    np.testing.assert_allclose(w @ v, x, atol=1e-12)


def test_weights_inside_a_convex_cage_are_positive():
    v, f = TEMPLATE
    x = random_points(v, f, 500, 0.0, 0.99, seed=1)
    assert (mvc_weights(x, v, f) > 0).all()


@settings(max_examples=60, deadline=None)
@given(
    arrays(np.float64, 42, elements=st.floats(0.3, 1.6)),
    arrays(np.float64, (24, 3), elements=st.floats(-1, 1)),
    arrays(np.float64, 24, elements=st.floats(0.0, 0.999)),
)
def test_linear_precision_inside_random_star_cages(radii, directions, fractions):
    check_reproduced(radii, directions, fractions)


def check_reproduced(radii, directions, fractions):
    """Points at ``fractions`` of the way to a star cage's surface (> 1: outside) get finite weights summing to 1
    that reproduce them."""
    v, f = star_cage(radii)
    x = inside_points(v, f, directions, fractions)
    w = mvc_weights(x, v, f)
    assert np.isfinite(w).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(w @ v, x, rtol=0, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    arrays(np.float64, 42, elements=st.floats(0.3, 1.6)),
    arrays(np.float64, (12, 3), elements=st.floats(-1, 1)),
    arrays(np.float64, 12, elements=st.floats(1.001, 4.0)),
)
def test_outside_points_are_finite_and_reproduced(radii, directions, fractions):
    check_reproduced(radii, directions, fractions)


# --- degenerate positions ----------------------------------------------------------------------------------------

def test_points_on_vertices_get_one_hot_weights():
    v, f = star_cage(np.random.default_rng(2).uniform(0.5, 1.5, 42))
    np.testing.assert_array_equal(mvc_weights(v, v, f), np.eye(42))
    np.testing.assert_array_equal(mvc_weights_reference(v, v, f), np.eye(42))


def test_points_on_faces_get_barycentric_weights():
    v, f = star_cage(np.random.default_rng(3).uniform(0.5, 1.5, 42))
    rng = np.random.default_rng(4)
    faces = rng.integers(0, len(f), 200)
    bary = rng.dirichlet([1, 1, 1], 200)
    x = np.einsum("nk,nki->ni", bary, v[f[faces]])
    w = mvc_weights(x, v, f)
    expected = np.zeros_like(w)
    np.add.at(expected, (np.repeat(np.arange(200), 3), f[faces].ravel()), bary.ravel())
    np.testing.assert_allclose(w, expected, atol=1e-12)


def test_points_on_edges_interpolate_the_edge():
    v, f = star_cage(np.random.default_rng(5).uniform(0.5, 1.5, 42))
    rng = np.random.default_rng(6)
    faces = rng.integers(0, len(f), 100)
    t = rng.uniform(0, 1, 100)
    a, b = f[faces, 0], f[faces, 1]
    x = (1 - t)[:, None] * v[a] + t[:, None] * v[b]
    w = mvc_weights(x, v, f)
    np.testing.assert_allclose(w[np.arange(100), a], 1 - t, atol=1e-12)
    np.testing.assert_allclose(w[np.arange(100), b], t, atol=1e-12)
    np.testing.assert_allclose(np.abs(w).sum(axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("distance", [1e-13, 1e-10, 1e-7, 1e-4])
def test_points_near_vertices_edges_and_face_planes_keep_linear_precision(distance):
    v, f = star_cage(np.random.default_rng(7).uniform(0.5, 1.5, 42))
    x = points_near_the_cage(v, f, np.random.default_rng(8), distance, 300)
    w = mvc_weights(x, v, f)
    assert np.isfinite(w).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(w @ v, x, rtol=0, atol=1e-11)


def test_far_points_are_finite_and_sum_to_one():
    v, f = TEMPLATE
    d = np.random.default_rng(9).normal(size=(50, 3))
    x = d / np.linalg.norm(d, axis=1, keepdims=True) * np.logspace(0.5, 9, 50)[:, None]
    w = mvc_weights(x, v, f)
    assert np.isfinite(w).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-5)


# --- fast kernel against the reference ---------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1])
def test_fast_matches_reference(seed):
    rng = np.random.default_rng(seed)
    v, f = star_cage(rng.uniform(0.4, 1.5, 42))
    faces = rng.integers(0, len(f), 10)
    bary = rng.dirichlet([1, 1, 1], 10)
    t = rng.uniform(0.1, 0.9, (10, 1))
    x = np.concatenate(
        [
            random_points(v, f, 150, 0.0, 0.98, seed),  # inside
            random_points(v, f, 60, 1.05, 3.0, seed + 10),  # outside
            np.einsum("nk,nki->ni", bary, v[f[faces]]),  # on faces
            t * v[f[faces, 0]] + (1 - t) * v[f[faces, 2]],  # on edges
            v[rng.integers(0, 42, 5)],  # on vertices
        ]
    )
    fast = mvc_weights(x, v, f)
    slow = mvc_weights_reference(x, v, f)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-10)


@pytest.mark.parametrize("chunk, threads", [(1, 1), (7, 3), (100, 2), (512, 1), (10_000, 2)])
def test_chunks_and_threads_do_not_change_the_result(chunk, threads):
    v, f = star_cage(np.random.default_rng(10).uniform(0.5, 1.5, 42))
    x = np.random.default_rng(11).uniform(-1.5, 1.5, (1500, 3))
    x[:3] = v[:3]  # a few degenerate rows through the careful path
    base = mvc_weights(x, v, f)
    np.testing.assert_allclose(mvc_weights(x, v, f, chunk=chunk, threads=threads), base, rtol=0, atol=1e-14)


def test_level_2_cage_and_no_points():
    v, f = icosphere(2)
    x = random_points(v, f, 300, 0, 0.99, seed=12)
    w = mvc_weights(x, v, f)
    assert w.shape == (300, 162)
    np.testing.assert_allclose(w @ v, x, atol=1e-12)
    assert mvc_weights(np.zeros((0, 3)), v, f).shape == (0, 162)


def test_deformation_is_linear_in_the_cage():
    v, f = TEMPLATE
    x = random_points(v, f, 100, 0, 0.9, seed=13)
    w = mvc_weights(x, v, f)
    a = np.diag([2.0, 0.5, 1.0])
    np.testing.assert_allclose(w @ (v @ a.T + [0.3, 0, 0]), x @ a.T + [0.3, 0, 0], atol=1e-12)


# --- errors ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize(
    "points, vertices, faces, kwargs, match",
    [
        (np.zeros((5, 2)), TEMPLATE.vertices, TEMPLATE.faces, {}, r"points must have shape \(N, 3\)"),
        ([[np.nan, 0, 0]], TEMPLATE.vertices, TEMPLATE.faces, {}, "finite"),
        (np.zeros((1, 3)), TEMPLATE.vertices[:3], TEMPLATE.faces, {}, "at least 4"),
        (np.zeros((1, 3)), TEMPLATE.vertices, TEMPLATE.faces + 1, {}, r"\[0, 41\] for 42 vertices"),
        (np.zeros((1, 3)), TEMPLATE.vertices, TEMPLATE.faces[1:], {}, "closed surface"),
        (np.zeros((1, 3)), TEMPLATE.vertices, TEMPLATE.faces.astype(float) + 0.5, {}, "integer"),
        (np.zeros((1, 3)), np.vstack([TEMPLATE.vertices, [[0, 0, 0]]]), TEMPLATE.faces, {}, "vertex 42 is in none"),
        (np.zeros((1, 3)), TEMPLATE.vertices, TEMPLATE.faces, {"chunk": 0}, "chunk"),
        (np.zeros((1, 3)), TEMPLATE.vertices, TEMPLATE.faces, {"threads": 0}, "threads"),
    ],
)
def test_bad_input_is_rejected(points, vertices, faces, kwargs, match):
    with pytest.raises(InputError, match=match):
        mvc_weights(points, vertices, faces, **kwargs)


# --- a real chair --------------------------------------------------------------------------------------------------

def test_real_chair_enclosed_cage_reproduces_every_point(data_dir):
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply"))
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    vertices = Normalizer().fit(vertices).apply(vertices)
    points = sample_surface(vertices, triangles, 1024, seed=0).points

    authors = fit_cage(points)
    assert points_outside(points, *authors).sum() > 10  # the authors' rule leaves part of the chair outside
    cage = fit_cage(points, enclose=True)
    assert not points_outside(points, *cage).any()
    w = mvc_weights(points, *cage)
    np.testing.assert_allclose(w @ cage.vertices, points, rtol=0, atol=1e-9)
    # Mesh vertices too, with a cage enclosing them as well.
    both = np.concatenate([points, vertices])
    cage = fit_cage(both, enclose=True)
    assert not points_outside(both, *cage).any()
    np.testing.assert_allclose(mvc_weights(vertices, *cage) @ cage.vertices, vertices, rtol=0, atol=1e-9)
