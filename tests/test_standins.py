"""kpd.viewer.standins: the coarse and fine stand-ins of a large mesh, made of its vertices, in its colours."""

import numpy as np


def test_stand_in_of_a_large_mesh_is_coarse_and_made_of_its_vertices():
    import open3d as o3d

    from kpd.viewer.standins import coarse_stand_in

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=120)
    vertices, triangles = np.asarray(sphere.vertices), np.asarray(sphere.triangles).astype(np.int64)
    assert coarse_stand_in(vertices, triangles, len(triangles)) is None  # small enough: drawn whole
    kept, faces = coarse_stand_in(vertices, triangles, 5000)
    assert 1000 < len(faces) <= 5000 < len(triangles)
    assert faces.min() >= 0 and faces.max() < len(kept) and len(np.unique(kept)) == len(kept)
    assert (np.diff(np.sort(faces, axis=1), axis=1) > 0).all()  # no collapsed triangles
    radii = np.linalg.norm(vertices[kept], axis=1)
    np.testing.assert_allclose(radii, 1.0, atol=1e-9)  # original vertices: the deformed mesh's rows give its stand-in


def _pictures(shaded_meshes, camera, width: int, height: int) -> list:
    """(H, W, 3) int64 pictures of each ShadedMesh of ``shaded_meshes(view)`` drawn alone as ``camera`` sees it, in a
    hidden view (EGL)."""
    from kpd.viewer.display import gl_display
    from kpd.viewer.glview import GLView

    with gl_display("egl", width, height):
        view = GLView(width, height)
        try:
            pictures = []
            for shown in shaded_meshes(view):
                view.clear()
                shown.set_vertices(shown.mesh.vertices, camera)
                for i, part in enumerate(shown.geometries):
                    view.put(f"mesh:{i}", part)
                view.set_camera(camera)
                pictures.append(view.capture().astype(np.int64))
        finally:
            view.close()
    return pictures


SHAPENET_CHAIR = ("keypointnet", "models", "03001627", "eaf231f17fccb96d81dff5c2e57ad46e", "model.obj")


def test_a_cad_mesh_of_many_triangles_gets_a_fine_stand_in_that_looks_like_it(data_dir):
    """An unseen ShapeNet chair (9,848 vertices, 19,900 distinct triangles): its stand-in is made of its own
    vertices, draws at most three quarters of its triangles, and its picture is the whole mesh's but for under 1%
    of the shape's pixels; a mesh of few triangles gets none, a large one the coarse one."""
    from kpd.io import Mesh, read_mesh
    from kpd.viewer.render import ViewSettings, camera_pose
    from kpd.viewer.shaded import ShadedMesh
    from kpd.viewer.standins import (COARSE_STAND_IN_TRIANGLES, STAND_IN_TRIANGLES, coarse_stand_in, fine_stand_in,
                                     stand_in)

    mesh = read_mesh(data_dir.joinpath(*SHAPENET_CHAIR))
    shaded = ShadedMesh(mesh)
    drawn = shaded.drawn
    assert STAND_IN_TRIANGLES < len(drawn) <= COARSE_STAND_IN_TRIANGLES
    kept, faces = stand_in(mesh.vertices, drawn)
    assert len(faces) <= 0.75 * len(drawn) and len(faces) > 0.3 * len(drawn)
    assert faces.min() >= 0 and faces.max() < len(kept) and len(np.unique(kept)) == len(kept)
    assert (np.diff(np.sort(faces, axis=1), axis=1) > 0).all()  # no collapsed triangles
    assert stand_in(mesh.vertices, drawn[:STAND_IN_TRIANGLES]) is None  # few triangles: drawn whole
    assert stand_in(mesh.vertices, drawn, fine=False) is None  # textures or materials: drawn whole
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    assert fine_stand_in(flat, np.array([[0, 1, 2], [1, 3, 2]])) is None  # nothing to collapse
    big = np.tile(drawn, (3, 1))
    np.testing.assert_array_equal(stand_in(mesh.vertices, big)[1],
                                  coarse_stand_in(mesh.vertices, big, COARSE_STAND_IN_TRIANGLES)[1])
    width, height = 480, 360
    settings = ViewSettings(width=width, height=height, azimuth=30, elevation=20, up="+y")
    camera = camera_pose(mesh.vertices, settings)
    pictures = _pictures(lambda _view: (shaded, ShadedMesh(Mesh(vertices=mesh.vertices[kept], triangles=faces))),
                         camera, width, height)
    shape = (pictures[0] != 255).any(axis=2)
    assert shape.mean() > 0.05  # the chair is in the picture
    differs = np.abs(pictures[1] - pictures[0]).max(axis=2) > 24
    assert differs.sum() < 0.01 * shape.sum(), differs.sum() / shape.sum()


def test_a_stand_in_keeps_the_colours_of_plain_materials(data_dir):
    """The ShapeNet chair with two plain-colour materials (as kpd.io reads an OBJ's materials without maps): its
    stand-in is drawn in their colours, the same picture as the whole mesh's but for under 2% of the shape's
    pixels; a mesh with a texture image gets no fine stand-in (it would change colour while dragged)."""
    from kpd.io import Mesh, read_mesh
    from kpd.viewer.render import ViewSettings, camera_pose
    from kpd.viewer.rigdrawing import RigDrawing
    from kpd.viewer.shaded import ShadedMesh
    from kpd.viewer.standins import image_maps, stand_in, stand_in_colors

    chair = read_mesh(data_dir.joinpath(*SHAPENET_CHAIR))
    centres = chair.vertices[chair.triangles].mean(axis=1)
    ids = (centres[:, 1] > np.median(centres[:, 1])).astype(np.int64)  # the upper half red, the lower blue
    red, blue = np.array([[[200, 40, 40]]], np.uint8), np.array([[[40, 60, 200]]], np.uint8)
    mesh = Mesh(vertices=chair.vertices, triangles=chair.triangles, textures=[blue, red], triangle_material_ids=ids,
                triangle_uvs=np.zeros((3 * len(chair.triangles), 2)))
    assert not image_maps(mesh)
    colors = stand_in_colors(mesh)
    only_red = np.setdiff1d(chair.triangles[ids == 1], chair.triangles[ids == 0])
    assert len(only_red) > 1000
    np.testing.assert_allclose(colors[only_red], np.tile(red[0, 0] / 255.0, (len(only_red), 1)))
    width, height = 480, 360
    settings = ViewSettings(width=width, height=height, azimuth=30, elevation=20, up="+y")
    camera = camera_pose(mesh.vertices, settings)

    def whole_and_stand_in(view):
        drawing = RigDrawing(view, mesh, settings=settings, digits=False)
        drawing.set_stand_in(*stand_in(mesh.vertices, drawing.shaded.drawn, fine=not image_maps(mesh)))
        return drawing.shaded, drawing.stand_in

    pictures = _pictures(whole_and_stand_in, camera, width, height)
    shape = (pictures[0] != 255).any(axis=2)
    assert (pictures[0][..., 0] > pictures[0][..., 2] + 60).mean() > 0.02  # red in the picture
    assert (pictures[0][..., 2] > pictures[0][..., 0] + 60).mean() > 0.02  # and blue
    differs = np.abs(pictures[1] - pictures[0]).max(axis=2) > 24
    assert differs.sum() < 0.02 * shape.sum(), differs.sum() / shape.sum()
    mapped = Mesh(vertices=chair.vertices, triangles=chair.triangles, textures=[np.full((4, 4, 3), 90, np.uint8)],
                  triangle_uvs=np.zeros((3 * len(chair.triangles), 2)))
    drawn = ShadedMesh(mesh).drawn
    assert image_maps(mapped) and stand_in(mapped.vertices, drawn, fine=not image_maps(mapped)) is None
