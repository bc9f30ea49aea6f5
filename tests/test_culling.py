"""kpd.viewer.culling: the triangles that show in a pixel, their neighbours across edges and their layout."""

import numpy as np
pytest_plugins = ["viewer_fixtures"]  # the shared fixtures


def test_edge_neighbours_name_the_third_corner_across_each_edge():
    from kpd.viewer.culling import edge_neighbours

    triangles = np.array([[0, 1, 2], [2, 1, 3], [4, 5, 6]])  # two sharing the edge 1-2, one alone
    np.testing.assert_array_equal(edge_neighbours(triangles, 7), [[-1, 3, -1], [0, -1, -1], [-1, -1, -1]])


def _nearest_at_samples(screen: np.ndarray, triangles: np.ndarray, width: int, height: int,
                        samples: np.ndarray) -> set:
    """The triangles nearest at some sample point, by the exact positions (the naive z-buffer)."""
    pixels = np.stack(np.meshgrid(np.arange(width), np.arange(height)), axis=-1)  # (H, W, 2)
    points = (pixels[:, :, None, :] + samples).reshape(-1, 2)  # (H W S, 2)
    best = np.full(len(points), -np.inf)  # 1 / depth is affine on the screen: the largest is the nearest
    owner = np.full(len(points), -1)
    for t, (a, b, c) in enumerate(screen[triangles]):
        lo, hi = np.minimum(np.minimum(a, b), c)[:2], np.maximum(np.maximum(a, b), c)[:2]
        inside = np.flatnonzero((points >= lo).all(axis=1) & (points <= hi).all(axis=1))
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if not len(inside) or area == 0:
            continue
        p = points[inside]
        wb = ((p[:, 0] - a[0]) * (c[1] - a[1]) - (p[:, 1] - a[1]) * (c[0] - a[0])) / area
        wc = ((b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0])) / area
        wa = 1 - wb - wc
        hit = (wa > 0) & (wb > 0) & (wc > 0)
        nearness = wa / a[2] + wb / b[2] + wc / c[2]
        better = hit & (nearness > best[inside])
        best[inside[better]], owner[inside[better]] = nearness[better], t
    return set(owner[owner >= 0].tolist())


def test_visible_triangles_with_neighbours_keep_fewer_and_every_nearest_one():
    """Judged with their neighbours across edges, fewer triangles of a dense sphere are kept than judged alone, all
    of them among those, and among them every triangle nearest at a sample point."""
    import open3d as o3d

    from kpd.viewer.culling import Viewport, _project, edge_neighbours, visible_triangles
    from kpd.viewer.render import ViewSettings, camera_pose

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=100)
    vertices, triangles = np.asarray(sphere.vertices), np.asarray(sphere.triangles).astype(np.int64)
    width, height = 64, 48
    samples = np.array([[0.375, 0.125], [0.875, 0.375], [0.125, 0.625], [0.625, 0.875]])
    camera = camera_pose(vertices, ViewSettings(width=width, height=height, azimuth=30, elevation=20))
    viewport = Viewport(camera, width, height, samples)
    alone = visible_triangles(vertices, triangles, viewport).copy()
    paired = visible_triangles(vertices, triangles, viewport, neighbours=edge_neighbours(triangles, len(vertices)))
    assert not (paired & ~alone).any()
    assert paired.sum() < 0.9 * alone.sum()
    screen = np.empty((len(vertices), 3))
    _project(0, len(vertices), vertices, np.zeros(0, np.int64), viewport.view, viewport.focal, width / 2, height / 2,
             screen)
    nearest = _nearest_at_samples(screen, triangles, width, height, samples)
    assert len(nearest) > 1000 and all(paired[t] for t in nearest)


def test_a_triangle_is_kept_wherever_its_corners_may_be_drawn():
    """Pass 2 keeps a triangle when a sample point lies within the distance its drawn corners may stray (delta along
    each axis) of it: whatever corners within that reach are drawn, the triangle covers no sample point of one left
    out. Slivers and small triangles, each corner moved to every extreme of its reach and at random."""
    import itertools

    from kpd.viewer.culling import _showing

    rng = np.random.default_rng(11)
    width = height = 8
    samples = np.array([[0.375, 0.125], [0.875, 0.375], [0.125, 0.625], [0.625, 0.875]])
    delta = 0.05  # far more than a drawn corner strays (1/256 pixel and float32's rounding): a test that can fail
    corners = []
    for _ in range(3000):
        a = rng.uniform(1.5, 6.5, size=2)
        b = a + rng.uniform(-1.5, 1.5, size=2)
        c = (a + b) / 2 + rng.uniform(-1.0, 1.0) * np.array([a[1] - b[1], b[0] - a[0]]) * 10.0 ** rng.uniform(-3, 0)
        corners.append([a, b, c])  # from slivers (c near the middle of ab) to plump triangles
    corners = np.array(corners)  # (T, 3, 2)
    t = len(corners)
    screen = np.concatenate([corners.reshape(-1, 2), np.ones((3 * t, 1))], axis=1)  # in front of the camera
    triangles = np.arange(3 * t).reshape(t, 3)
    keep = np.zeros(t, np.bool_)
    _showing(0, triangles, screen, width, height, samples[:, 0].copy(), samples[:, 1].copy(), delta,
             np.full(width * height * len(samples), np.inf, np.float32), 3e-3, np.arange(t, dtype=np.int32),
             np.array([0, t], np.int64), np.array([t, 0], np.int64), keep, np.zeros(1, np.uint8))
    points = (np.stack(np.meshgrid(np.arange(width), np.arange(height), indexing="ij"), -1).reshape(-1, 1, 2)
              + samples).reshape(-1, 2)  # (P, 2) every sample point

    def covers(p):  # (T, 3, 2) corners -> (T,) whether any sample point is inside (either winding, edges included)
        e = []
        for i in range(3):
            edge, to = p[:, (i + 1) % 3, None] - p[:, i, None], points[None] - p[:, i, None]  # (T, 1, 2), (T, P, 2)
            e.append(edge[..., 0] * to[..., 1] - edge[..., 1] * to[..., 0])
        return (((e[0] >= 0) & (e[1] >= 0) & (e[2] >= 0)) | ((e[0] <= 0) & (e[1] <= 0) & (e[2] <= 0))).any(axis=1)

    moves = [np.array(m).reshape(3, 2) for m in itertools.product((-delta, delta), repeat=6)]
    moves += [rng.uniform(-delta, delta, size=(3, 2)) for _ in range(64)]
    drawn = np.zeros(t, np.bool_)
    for move in moves:
        drawn |= covers(corners + move)
    assert not (drawn & ~keep).any()  # never left out where a drawn triangle covers a sample point
    assert (drawn & ~covers(corners)).sum() > 100  # many are covered only as drawn, not as projected
    assert (keep & ~drawn).sum() < 0.1 * keep.sum(), ((keep & ~drawn).sum(), keep.sum())  # few kept needlessly


def test_culling_near_runs_first_keeps_the_same_triangles_and_judges_fewer(dense_chair):
    """A CullingLayout's runs of nearby triangles, taken nearest first, leave the hidden ones out in pass 1: the
    same triangles are kept as when they are judged in the mesh's order (whole, below, close up, from inside), and
    pass 2 judges far fewer."""
    from kpd.viewer.culling import CullingLayout, Viewport, visible_triangles
    from kpd.viewer.render import ViewSettings, camera_pose

    vertices, triangles = dense_chair.vertices, dense_chair.triangles
    layout = CullingLayout(vertices, triangles)
    assert sorted(layout.order.tolist()) == list(range(len(triangles)))
    np.testing.assert_array_equal(layout.used[layout.triangles], triangles[layout.order])  # the same triangles
    assert len(layout.cells) > 100 and layout.cells[0] == 0 and layout.cells[-1] == len(triangles)
    samples = np.array([[0.375, 0.125], [0.875, 0.375], [0.125, 0.625], [0.625, 0.875]])
    for azimuth, elevation, zoom in [(30, 20, 1.0), (200, -40, 1.0), (75, 60, 4.0), (10, 5, 30.0)]:
        camera = camera_pose(vertices, ViewSettings(width=400, height=300, azimuth=azimuth, elevation=elevation,
                                                    zoom=zoom))
        viewport = Viewport(camera, 400, 300, samples)
        judged = {}
        for name, cells in (("in order", None), ("near first", layout.cells)):
            scratch: dict = {}
            judged[name] = visible_triangles(vertices, layout.triangles, viewport, scratch=scratch,
                                             neighbours=layout.neighbours, index=layout.used, cells=cells).copy()
            judged[name + " listed"] = int(scratch["listed_count"].sum())
        np.testing.assert_array_equal(judged["near first"], judged["in order"])
        alone = visible_triangles(vertices, triangles, viewport)  # the mesh's own order, each triangle alone
        assert not (judged["in order"] & ~alone[layout.order]).any()  # judged with neighbours: fewer kept
        if zoom == 1.0:  # seen whole: much of the surface lies behind the rest
            assert judged["near first listed"] < 0.9 * judged["in order listed"], judged


def test_a_block_of_triangles_is_hidden_only_when_each_of_them_is(dense_chair):
    """Pass 1 leaves out 32 nearby triangles at once when their common box is behind the depth reached: a block is
    judged hidden only when each of its triangles, judged alone against the same depths, is; and seen whole, many
    blocks of the far side are."""
    from kpd.viewer.culling import (_BLOCK, DEPTH_SLACK, CullingLayout, Viewport, _block_hidden, _margin,
                                    visible_triangles)
    from kpd.viewer.render import ViewSettings, camera_pose

    vertices, triangles = dense_chair.vertices, dense_chair.triangles
    layout = CullingLayout(vertices, triangles)
    samples = np.array([[0.375, 0.125], [0.875, 0.375], [0.125, 0.625], [0.625, 0.875]])
    camera = camera_pose(vertices, ViewSettings(width=400, height=300, azimuth=30, elevation=20))
    viewport = Viewport(camera, 400, 300, samples)
    scratch: dict = {}
    visible_triangles(vertices, layout.triangles, viewport, scratch=scratch, neighbours=layout.neighbours,
                      index=layout.used, cells=layout.cells)
    screen, depth = scratch["screen"], scratch["depth"]  # the projected points and the depths at the end of pass 1
    delta = _margin(vertices, viewport)
    args = (layout.triangles, screen, 400, 300, samples[:, 0].copy(), samples[:, 1].copy(), delta, depth, DEPTH_SLACK)
    blocks = range(0, len(layout.triangles) - _BLOCK, _BLOCK)
    hidden = [s for s in blocks if _block_hidden(s, s + _BLOCK, *args)]
    assert 0.1 * len(blocks) < len(hidden) < 0.9 * len(blocks)
    for s in hidden[::7]:
        assert all(_block_hidden(t, t + 1, *args) for t in range(s, s + _BLOCK))
    # one triangle that shows makes a block of hidden ones worth looking at
    shown = next(t for t in range(len(layout.triangles)) if not _block_hidden(t, t + 1, *args))
    mixed = np.concatenate([layout.triangles[hidden[0]:hidden[0] + _BLOCK], layout.triangles[shown:shown + 1]])
    assert _block_hidden(0, _BLOCK, mixed, *args[1:])
    assert not _block_hidden(0, _BLOCK + 1, mixed, *args[1:])
