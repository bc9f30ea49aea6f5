"""kpd.metrics.edits: edit-quality measures: locality, folds, distortion, roles and semantic edits, prior response,
self-intersections, distance to the training keypoints."""

from __future__ import annotations

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.metrics import (edit_distortion, far_side_leakage, folded_area_share, folded_share, keypoint_roles,
                         keypoint_set_distance,
                         new_self_intersections, prior_response, semantic_edits, triangle_distance, vertex_areas)


def grid(n=8, z=0.0):
    """A flat n x n grid of unit size in the plane z: (n*n, 3) vertices and 2 (n-1)^2 triangles."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.full(n * n, z)], axis=1)
    index = np.arange(n * n).reshape(n, n)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def random_rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_vertex_areas_sum_to_the_surface():
    vertices, triangles = grid()
    areas = vertex_areas(vertices, triangles)
    assert areas.sum() == pytest.approx(1.0)
    assert areas.min() > 0 and areas[0] < areas[len(areas) // 2 + 4]  # a corner stands for less than an inner vertex


def test_far_side_leakage():
    vertices, triangles = grid()
    keypoint = np.array([0.0, 0.0, 0.0])
    moved = vertices + [0.0, 0.0, 0.3]  # everything moved with the keypoint: nothing is local
    assert far_side_leakage(vertices, moved, keypoint, 0.3) == pytest.approx(1.0)
    near = np.linalg.norm(vertices - keypoint, axis=1) < 0.4
    local = vertices + near[:, None] * [0.0, 0.0, 0.3]  # only the corner around the keypoint moved
    assert far_side_leakage(vertices, local, keypoint, 0.3) == 0.0
    weights = vertex_areas(vertices, triangles)
    assert far_side_leakage(vertices, local, keypoint, 0.3, weights) == 0.0
    # half of the far side moving half as far
    far = np.linalg.norm(vertices - keypoint, axis=1) > 1.0
    partly = vertices + far[:, None] * [0.0, 0.0, 0.15]
    assert 0.0 < far_side_leakage(vertices, partly, keypoint, 0.3) < 0.5
    with pytest.raises(InputError, match="move must be a positive length"):
        far_side_leakage(vertices, moved, keypoint, 0.0)
    with pytest.raises(InputError, match="weights must be 64 non-negative"):
        far_side_leakage(vertices, moved, keypoint, 0.3, np.ones(3))


def test_folds_and_distortion():
    vertices, triangles = grid()
    rigid = vertices @ random_rotation(0).T + [1.0, -2.0, 0.5]
    assert edit_distortion(vertices, rigid, triangles) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    scaled = edit_distortion(vertices, 2.0 * vertices, triangles)
    assert scaled.folded == 0.0 and scaled.edge == pytest.approx(1.0) and scaled.dihedral == pytest.approx(0.0)
    # mirroring the grid turns every triangle's normal over
    assert folded_share(vertices, vertices * [-1.0, 1.0, 1.0], triangles) == 1.0
    # a bump: no fold, the dihedral angles change
    bump = vertices.copy()
    bump[:, 2] = 0.1 * np.exp(-20 * ((vertices[:, 0] - 0.5) ** 2 + (vertices[:, 1] - 0.5) ** 2))
    bent = edit_distortion(vertices, bump, triangles)
    assert bent.folded == 0.0 and bent.dihedral > 1.0 and bent.edge > 0.0
    # pulling one inner vertex across its neighbours folds the triangles around it (and only those)
    pulled = vertices.copy()
    pulled[27, :2] += [0.4, 0.4]
    share = folded_share(vertices, pulled, triangles)
    assert 0 < share <= 6 / len(triangles)
    with pytest.raises(InputError, match="same shape"):
        edit_distortion(vertices, vertices[:-1], triangles)


def test_folded_area_share_weighs_triangles_by_area():
    # a fan of 20 thin slivers (0.05 of area in all) beside one large triangle (area 2)
    n = 20
    top = [[1.0, y, 0.0] for y in np.linspace(0, 0.1, n + 1)]
    vertices = np.array([[0.0, 0.0, 0.0]] + top + [[0.0, -0.5, 0.0], [2.0, -0.5, 0.0], [0.0, -2.5, 0.0]])
    slivers = [[0, 1 + i, 2 + i] for i in range(n)]
    triangles = np.array(slivers + [[n + 2, n + 4, n + 3]])
    areas = 0.5 * np.linalg.norm(np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                                          vertices[triangles[:, 2]] - vertices[triangles[:, 0]]), axis=1)
    # fold one sliver (swap its far corners' order by pushing one across the other)
    bent = vertices.copy()
    bent[5] = vertices[7] + [0.0, 0.001, 0.0]
    share, area = folded_share(vertices, bent, triangles), folded_area_share(vertices, bent, triangles)
    folded = np.einsum("ij,ij->i", np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                                            vertices[triangles[:, 2]] - vertices[triangles[:, 0]]),
                       np.cross(bent[triangles[:, 1]] - bent[triangles[:, 0]],
                                bent[triangles[:, 2]] - bent[triangles[:, 0]])) < 0
    assert 0 < folded.sum() < n
    assert share == pytest.approx(folded.mean())
    assert area == pytest.approx(areas[folded].sum() / areas.sum())
    assert area < share / 4  # slivers are a large share of the triangles, a small one of the surface
    assert folded_area_share(vertices, vertices * [-1.0, 1.0, 1.0], triangles) == pytest.approx(1.0)
    assert folded_area_share(vertices, 3.0 * vertices, triangles) == 0.0


# a chair-like mean keypoint set: four feet, three seat keypoints (one on the mirror plane), two top-of-back
CHAIR = np.array([[-0.5, -0.5, -0.9], [0.5, -0.5, -0.9], [-0.5, 0.5, -0.85], [0.5, 0.5, -0.88],
                  [-0.45, -0.5, -0.1], [0.45, -0.5, -0.1], [0.0, 0.0, -0.15],
                  [-0.4, 0.5, 0.85], [0.4, 0.5, 0.88]])


def test_roles_and_semantic_edits():
    roles = keypoint_roles(CHAIR)
    assert roles["top"].tolist() == [7, 8]
    assert roles["bottom"].tolist() == [0, 1, 2, 3]
    assert roles["above_bottom"].tolist() == [4, 5, 6]
    edits = semantic_edits(roles, "chair", 0.2)
    assert sorted(edits["taller_back"]) == [7, 8] and all(
        o.tolist() == [0, 0, 0.2] for o in edits["taller_back"].values())
    assert all(o.tolist() == [0, 0, -0.2] for o in edits["longer_legs"].values())
    # wider seat: the side keypoints outward, the one on the mirror plane stays
    assert {i: o.tolist() for i, o in edits["wider_seat"].items()} == {4: [-0.2, 0, 0], 5: [0.2, 0, 0]}
    # the order of the keypoints does not matter
    order = np.random.default_rng(0).permutation(len(CHAIR))
    shuffled = keypoint_roles(CHAIR[order])
    assert sorted(order[shuffled["top"]].tolist()) == [7, 8]
    with pytest.raises(InputError, match="semantic edits are defined for"):
        semantic_edits(roles, "lamp", 0.2)


def test_prior_response():
    before = CHAIR.copy()
    move = np.array([-0.1, 0.05, 0.2])
    after = before.copy()
    after[7] += move
    after[8] += move * [-1, 1, 1]  # the partner mirrors the move exactly, the others stay
    assert prior_response(before, after, 7, 8, move) == pytest.approx((1.0, 0.0))
    after[0] += [0.0, 0.0, np.linalg.norm(move)]  # one of the 7 others moves as far as the keypoint
    assert prior_response(before, after, 7, 8, move).others == pytest.approx(1 / 7)
    copied = before.copy()
    copied[7] += move
    copied[8] += move  # copied, not mirrored: the x part goes the wrong way
    assert prior_response(before, copied, 7, 8, move).partner < 1.0
    with pytest.raises(InputError, match="two different keypoints"):
        prior_response(before, after, 7, 7, move)


def test_triangle_distance_matches_dense_sampling():
    rng = np.random.default_rng(1)
    a = rng.uniform(-1, 1, (40, 3, 3))
    b = rng.uniform(-1, 1, (40, 3, 3)) + [2.5, 0, 0]  # disjoint from a
    d = triangle_distance(a, b)
    w = rng.dirichlet(np.ones(3), 800)  # (P, 3) barycentric samples
    for i in range(0, 40, 8):
        pa, pb = w @ a[i], w @ b[i]
        sampled = np.sqrt(((pa[:, None] - pb[None]) ** 2).sum(-1)).min()
        assert d[i] <= sampled + 1e-12 and d[i] > sampled - 0.1


def test_new_self_intersections():
    v1, t1 = grid(6, z=0.0)
    v2, t2 = grid(6, z=0.3)
    vertices, triangles = np.concatenate([v1, v2]), np.concatenate([t1, t2 + len(v1)])
    assert new_self_intersections(vertices, vertices, triangles) == 0
    pushed = vertices.copy()
    centre = np.linalg.norm(v2[:, :2] - 0.5, axis=1) < 0.3
    pushed[len(v1):][centre] -= [0, 0, 0.6]  # the middle of the upper sheet pushed through the lower one
    assert new_self_intersections(vertices, pushed, triangles) > 0
    # sheets already touching: moving them creates contacts, which do not count
    touching = np.concatenate([v1, grid(6, z=0.0)[0] + [0.5, 0, 0]])
    slid = touching.copy()
    slid[len(v1):] += [0.1, 0, 0.001]
    assert new_self_intersections(touching, slid - [0, 0, 0.002] * (np.arange(len(slid)) >= len(v1))[:, None],
                                  triangles) == 0


def test_keypoint_set_distance():
    reference = np.stack([CHAIR, CHAIR + 0.5])
    d = keypoint_set_distance(np.stack([CHAIR, CHAIR + 0.1, CHAIR + 0.45]), reference)
    np.testing.assert_allclose(d, [0.0, 0.1 * np.sqrt(3), 0.05 * np.sqrt(3)])
    with pytest.raises(InputError, match="same K"):
        keypoint_set_distance(CHAIR[None, :5], reference)
