"""kpd.viewer.rigdrawing: a rig's geometries in a view, its stand-in during gestures, its numbers in front."""

import numpy as np
from helpers import subdivided_box

from kpd.viewer.settings import Frame, ViewSettings


def test_numbers_behind_the_surface_come_in_front_of_it_along_their_lines_of_sight():
    from kpd.viewer.camera import camera_pose
    from kpd.viewer.rigdrawing import RigDrawing

    mesh = subdivided_box((1.0, 2.0, 1.0), 3, [0.5, 1.0, 0.5])
    settings = ViewSettings(width=200, height=160)
    drawing = RigDrawing(None, mesh, 2, settings=settings, digits=False)  # nothing drawn: no view needed
    camera = camera_pose(mesh.vertices, settings)
    eye = np.asarray(camera.eye)
    anchors = np.array([eye + 0.01 * (camera.center - eye), camera.center])  # before the mesh, and inside it
    moved, sizes = drawing.labels_in_front(anchors, camera)
    np.testing.assert_array_equal(moved[0], anchors[0])
    assert sizes[0] == 1.0 and 0 < sizes[1] < 1
    along = (moved[1] - eye) / np.linalg.norm(moved[1] - eye)
    np.testing.assert_allclose(along, (anchors[1] - eye) / np.linalg.norm(anchors[1] - eye))  # same line of sight
    forward = (camera.center - eye) / np.linalg.norm(camera.center - eye)
    assert (moved[1] - eye) @ forward < ((mesh.vertices - eye) @ forward).min()  # in front of the whole mesh


def test_a_gesture_draws_the_stand_in_and_the_next_frame_the_whole_mesh():
    from kpd.viewer.camera import camera_pose
    from kpd.viewer.display import gl_display
    from kpd.viewer.glview import GLView
    from kpd.viewer.rigdrawing import RigDrawing
    from kpd.viewer.standins import coarse_stand_in

    mesh = subdivided_box((1.0, 2.0, 1.0), 3, [0.5, 1.0, 0.5])
    settings = ViewSettings(width=200, height=160)
    camera = camera_pose(mesh.vertices, settings)
    keypoints = mesh.vertices[[0, 10, 20]]
    with gl_display("egl", settings.width, settings.height):
        view = GLView(settings.width, settings.height)
        try:
            drawing = RigDrawing(view, mesh, len(keypoints), settings=settings, digits=False)
            kept, faces = coarse_stand_in(mesh.vertices, mesh.triangles, len(mesh.triangles) // 4)
            drawing.set_stand_in(kept, faces)
            frame = Frame(mesh.vertices, keypoints, None, (1,))
            drawing.show(frame, camera, fast=True)
            assert drawing.stand_in_shown and view._shown["stand-in:0"] and not view._shown.get("mesh:0")
            assert len(drawing.stand_in.geometries[0].triangles) <= len(faces)
            drawing.show(frame, camera)
            assert not drawing.stand_in_shown and view._shown["mesh:0"] and not view._shown["stand-in:0"]
            markers = np.asarray(drawing.markers.geometry.vertices).reshape(len(keypoints), -1, 3)
            radii = np.linalg.norm(markers - keypoints[:, None], axis=2).max(axis=1)
            np.testing.assert_allclose(radii / drawing.marker_radius, [1.0, 1.6, 1.0])  # the selected one larger
        finally:
            view.close()
