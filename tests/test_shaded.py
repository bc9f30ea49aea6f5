"""kpd.viewer.shaded: a mesh ready to draw, its distinct triangles, the sides of faces with two materials, its UVs, and
frames of the triangles that show."""

import numpy as np
import pytest
pytest_plugins = ["viewer_fixtures"]  # the shared fixtures


def test_distinct_triangles_drop_a_triangle_stored_again_either_way_round():
    from kpd.viewer.shaded import distinct_triangles

    triangles = np.array([[0, 1, 2], [2, 1, 0], [1, 2, 3], [0, 1, 2], [3, 2, 1], [0, 2, 3]])
    np.testing.assert_array_equal(distinct_triangles(triangles), [0, 2, 5])
    big = triangles + (1 << 21)  # indices past 2^21 take the sorting path
    np.testing.assert_array_equal(distinct_triangles(big), [0, 2, 5])
    assert distinct_triangles(np.zeros((0, 3), np.int64)).shape == (0,)


def test_two_materials_over_one_face_are_its_two_sides_or_painted_over():
    from kpd.viewer.normals import Welding
    from kpd.viewer.shaded import material_sides

    # over the corners of 0-1-2 (also as 3-4-5, at the same places): material 0 one way round, material 1 the
    # other way (the face's two sides), then material 2 the first way again (painted over material 0)
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 0, 0], [1, 1, 0]], float)
    triangles = np.array([[0, 1, 2], [3, 4, 5], [1, 2, 0], [1, 6, 2], [4, 6, 3]])
    ids = np.array([0, 1, 2, 0, 0])
    hidden, sided = material_sides(triangles, ids, Welding(vertices))
    np.testing.assert_array_equal(hidden, [True, False, False, False, False])  # 3 and 4 alike: one material
    np.testing.assert_array_equal(sided, [False, True, True, False, False])
    ids = np.array([0, 1, 0, 0, 1])  # 0 and 2 alike in one material; 1-6-2 has material 1 on the other side
    triangles[4] = triangles[4, ::-1]
    hidden, sided = material_sides(triangles, ids, Welding(vertices))
    np.testing.assert_array_equal(hidden, [False, False, False, False, False])
    np.testing.assert_array_equal(sided, [True, True, True, True, True])
    empty = material_sides(np.zeros((0, 3), np.int64), np.zeros(0, np.int64), Welding(vertices))
    assert empty[0].shape == empty[1].shape == (0,)


def test_distinct_triangles_is_its_sorting_twin_on_any_triangles():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from kpd.viewer.shaded import _distinct_triangles_reference, distinct_triangles

    @settings(max_examples=60, deadline=None)
    @given(n=st.integers(1, 300), top=st.integers(1, 12), seed=st.integers(0, 2**16))
    def check(n, top, seed):
        triangles = np.random.default_rng(seed).integers(0, top, size=(n, 3))  # repeats, either way round, collapsed
        np.testing.assert_array_equal(distinct_triangles(triangles), _distinct_triangles_reference(triangles))

    check()


@pytest.mark.parametrize("offset", [0.0, 300.0])  # away from the origin: float32 rounds the drawn positions coarser
def test_a_frame_of_the_visible_triangles_is_the_picture_of_all_of_them(dense_chair, offset):
    """Culled and whole frames of a dense mesh are the same pixels, from outside, below, close up and from inside
    the mesh (corners behind the camera), while the culled ones draw far fewer triangles."""
    from kpd.io import Mesh
    from kpd.viewer.culling import visible_triangles
    from kpd.viewer.display import gl_display
    from kpd.viewer.glview import GLView
    from kpd.viewer.render import ViewSettings, camera_pose
    from kpd.viewer.shaded import ShadedMesh

    mesh = Mesh(dense_chair.vertices + offset, dense_chair.triangles)
    width, height = 400, 300
    with gl_display("egl", width, height):
        view = GLView(width, height)
        try:
            assert view.viewport(camera_pose(mesh.vertices, ViewSettings())) is not None  # one sample a pixel here
            shaded = ShadedMesh(mesh)
            view.set_box(mesh.vertices)
            for azimuth, elevation, zoom in [(30, 20, 1.0), (200, -40, 1.0), (75, 60, 4.0), (10, 5, 30.0)]:
                camera = camera_pose(mesh.vertices, ViewSettings(width=width, height=height, azimuth=azimuth,
                                                                 elevation=elevation, zoom=zoom))
                pictures = []
                for viewport in (None, view.viewport(camera)):
                    shaded.set_vertices(mesh.vertices, camera, viewport)
                    for i, part in enumerate(shaded.geometries):
                        view.put(f"mesh:{i}", part)
                    view.set_camera(camera)
                    pictures.append(view.capture())
                np.testing.assert_array_equal(pictures[1], pictures[0])
                assert (pictures[0] != 255).any(axis=2).mean() > 0.05  # the chair is in the picture
                kept = visible_triangles(mesh.vertices, shaded.drawn, view.viewport(camera))
                if zoom == 1.0:  # seen whole: most triangles are hidden or between pixel centres
                    assert kept.mean() < (0.4 if offset == 0 else 0.9), kept.mean()
        finally:
            view.close()


def test_a_mesh_drawn_once_is_culled_in_its_own_order_to_the_same_picture(dense_chair, monkeypatch):
    """A mesh drawn once (kpd render, render_rig) is culled in its own order, each triangle judged alone, with
    neither a CullingLayout nor the edges' neighbours made: the same pixels as the editor's culling, more
    triangles kept (each of those the editor keeps among them)."""
    from kpd.rig import Rig
    from kpd.viewer import culling
    from kpd.viewer import shaded as shaded_module
    from kpd.viewer.display import gl_display
    from kpd.viewer.glview import GLView
    from kpd.viewer.render import ViewSettings, camera_pose, render_rig
    from kpd.viewer.shaded import ShadedMesh

    mesh = dense_chair
    width, height = 400, 300
    paired, alone = ShadedMesh(mesh), ShadedMesh(mesh, once=True)
    assert paired.parts[0].layout_for_culling is not None and alone.parts[0].layout_for_culling is None
    with gl_display("egl", width, height):
        view = GLView(width, height)
        try:
            view.set_box(mesh.vertices)
            for azimuth, elevation, zoom in [(30, 20, 1.0), (200, -40, 1.0), (75, 60, 4.0)]:
                camera = camera_pose(mesh.vertices, ViewSettings(width=width, height=height, azimuth=azimuth,
                                                                 elevation=elevation, zoom=zoom))
                pictures, drawn = [], []
                for shaded in (paired, alone):
                    shaded.set_vertices(mesh.vertices, camera, view.viewport(camera))
                    for i, part in enumerate(shaded.geometries):
                        view.put(f"mesh:{i}", part)
                    view.set_camera(camera)
                    pictures.append(view.capture())
                    part = shaded.parts[0]  # the verdicts on its triangles (the same in both)
                    drawn.append((part.keep if part.layout_for_culling is not None else part.scratch["keep"]).copy())
                np.testing.assert_array_equal(alone.parts[0].triangles, paired.parts[0].triangles)
                np.testing.assert_array_equal(pictures[1], pictures[0])
                # fewer kept with the pairs, all among those kept alone; and culled all the same
                assert not (drawn[0] & ~drawn[1]).any() and drawn[1].sum() > drawn[0].sum()
                assert drawn[1].mean() < 0.5, drawn[1].mean()
        finally:
            view.close()
    made = []
    monkeypatch.setattr(culling, "edge_neighbours", lambda *a: made.append("neighbours"))
    monkeypatch.setattr(shaded_module, "CullingLayout", lambda *a: made.append("layout"))
    keypoints = mesh.vertices[[0, 100, 2000, 30000]]
    image = render_rig(Rig.bind(mesh, keypoints), settings=ViewSettings(width=width, height=height),
                       backend="egl")
    assert made == [] and (image != 255).any(axis=2).mean() > 0.05


def test_texture_coordinates_in_one_pass_are_the_numpy_steps_to_the_bit():
    """A textured part's UVs (a compiled pass since a 1.28M-vertex textured scan spent 1 s in numpy's steps): moved by
    whole tiles into the first, kept within the outer texel centres, v turned; NaN and inf as numpy gives them, UVs
    in float32 too, of chosen triangles only."""
    from kpd.viewer.shaded import _texture_coordinates

    rng = np.random.default_rng(3)
    T = 3000
    uv = rng.normal(0.0, 3.0, (3 * T, 2))
    for value, share in ((np.nan, 0.01), (np.inf, 0.01), (-np.inf, 0.01), (0.0, 0.05), (1.0, 0.05), (-0.0, 0.02)):
        uv[rng.random(uv.shape) < share] = value
    chosen = np.sort(rng.choice(T, T // 2, replace=False))
    for dtype in (np.float64, np.float32):
        u = uv.astype(dtype)
        for height, width in ((512, 1024), (7, 1)):
            expected = np.array(u[(3 * chosen[:, None] + np.arange(3)).ravel()], dtype=np.float64).reshape(-1, 3, 2)
            with np.errstate(invalid="ignore"):
                expected -= np.floor(expected.min(axis=1, keepdims=True))
            edge = 0.5 / np.array([width, height], dtype=np.float64)
            expected = np.clip(expected, edge, 1.0 - edge)
            expected[:, :, 1] = 1.0 - expected[:, :, 1]
            out = np.empty((len(chosen), 3, 2))
            _texture_coordinates(u, chosen, 0.5 / width, 0.5 / height, out)
            assert np.isnan(expected).any() and (expected != np.round(expected)).any()
            np.testing.assert_array_equal(out, expected)  # NaN where numpy has NaN
            assert (np.signbit(out) == np.signbit(expected)).all()
