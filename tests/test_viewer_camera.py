"""kpd.viewer.camera: projection and picking agree (a pixel's ray goes through the projected point; a drag in the
camera's plane lands under the cursor)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kpd.viewer.camera import camera_pose, look_at_matrix, perspective_matrix, pixel_ray, plane_hit, project
from kpd.viewer.settings import ViewSettings



def _infinite_projection(fov: float, aspect: float, near: float) -> np.ndarray:
    """A perspective with the far plane at infinity, as Open3D's window camera reports it."""
    t = 1 / math.tan(math.radians(fov) / 2)
    return np.array([[t / aspect, 0, 0, 0], [0, t, 0, 0], [0, 0, -1, -2 * near], [0, 0, -1, 0]])


@pytest.mark.parametrize("infinite", [False, True])
def test_pixel_ray_goes_through_the_projected_point(infinite):
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(50, 3)) * [1, 2, 3] + [5, -1, 2]
    settings = ViewSettings(width=400, height=300, azimuth=40, elevation=25)
    camera = camera_pose(vertices, settings)
    view = look_at_matrix(camera)
    projection = (_infinite_projection(camera.fov, 4 / 3, camera.near) if infinite
                  else perspective_matrix(camera.fov, 4 / 3, camera.near, camera.far))
    pixels, depth = project(vertices, view, projection, 400, 300)
    assert (depth > 0).all()
    assert (pixels >= 0).all() and (pixels[:, 0] <= 400).all() and (pixels[:, 1] <= 300).all()  # the shape fits
    for point, (x, y) in zip(vertices[:5], pixels[:5]):
        origin, direction = pixel_ray(x, y, view, projection, 400, 300)
        np.testing.assert_allclose(origin, camera.eye, atol=1e-9)
        closest = origin + direction * ((point - origin) @ direction)
        np.testing.assert_allclose(closest, point, atol=1e-6)


def test_drag_in_the_camera_plane_keeps_depth():
    camera = camera_pose(np.array([[-1.0, -1, -1], [1, 1, 1]]), ViewSettings())
    view = look_at_matrix(camera)
    projection = perspective_matrix(camera.fov, 4 / 3, camera.near, camera.far)
    anchor = np.array([0.2, 0.1, 0.3])
    forward = -view[2, :3]
    x, y = project(anchor[None], view, projection, 640, 480)[0][0]
    hit = plane_hit(*pixel_ray(x + 40, y - 30, view, projection, 640, 480), anchor, forward)
    assert abs((hit - anchor) @ forward) < 1e-9  # moved within the plane facing the camera
    moved, _ = project(hit[None], view, projection, 640, 480)
    np.testing.assert_allclose(moved[0], [x + 40, y - 30], atol=1e-6)  # and lands under the cursor
    assert plane_hit(np.zeros(3), np.array([1.0, 0, 0]), anchor, np.array([0, 0, 1.0])) is None


@pytest.mark.parametrize("up", ["+z", "+y", "-x"])
def test_camera_pose_frames_the_shape_with_its_up_axis_up(up):
    vertices = np.random.default_rng(1).uniform(-1, 1, (200, 3)) * [3, 1, 2]
    settings = ViewSettings(width=320, height=240, up=up, azimuth=30, elevation=20)
    camera = camera_pose(vertices, settings)
    view = look_at_matrix(camera)
    pixels, depth = project(vertices, view, perspective_matrix(camera.fov, 4 / 3, camera.near, camera.far), 320, 240)
    assert (depth > 0).all() and (pixels >= 0).all() and (pixels <= [320, 240]).all()
    axis = {"+z": [0, 0, 1], "+y": [0, 1, 0], "-x": [-1, 0, 0]}[up]
    top, bottom = project(np.array([axis, [-a for a in axis]], float) * 0.5, view,
                          perspective_matrix(camera.fov, 4 / 3, camera.near, camera.far), 320, 240)[0]
    assert top[1] < bottom[1]  # the up axis points up in the picture (pixel y grows downwards)


@pytest.mark.parametrize("closest", [True, False])
@pytest.mark.parametrize("azimuth, elevation", [(30, 20), (150, 35), (-70, 10)])
def test_camera_pose_centres_the_picture_and_fits_it_to_the_margin(azimuth, elevation, closest):
    """In perspective the near side of a shape looks larger, so aiming at its bounding box's centre left a long shape
    seen at an angle low and to one side of the picture (a shoe from behind): the camera is aimed so that the
    projected shape is centred both ways, and as close as lets every point in with the margin to spare; or, not
    ``closest`` (the editor's home view), as far as the view aimed at the box's centre needed."""
    rng = np.random.default_rng(2)
    vertices = rng.uniform(-1, 1, (500, 3)) * [0.4, 0.6, 2.0] + [3.0, -1.0, 0.5]  # long along z, off the origin
    settings = ViewSettings(width=400, height=300, up="+y", azimuth=azimuth, elevation=elevation)
    camera = camera_pose(vertices, settings, margin=0.9, closest=closest)
    view = look_at_matrix(camera)
    local = vertices @ view[:3, :3].T + view[:3, 3]  # camera coordinates, looking down -z
    assert (local[:, 2] < 0).all()
    u, v = local[:, 0] / -local[:, 2], local[:, 1] / -local[:, 2]  # tangents across and up
    tan_v = math.tan(math.radians(settings.fov) / 2)
    tan_h = tan_v * 400 / 300
    for t, tan in ((u, tan_h), (v, tan_v)):  # inside the margin, centred (to 0.2% of the extent: a grid of tangents)
        assert t.max() <= 0.9 * tan + 1e-9 and -t.min() <= 0.9 * tan + 1e-9
        assert abs(t.max() + t.min()) < 2e-3 * (t.max() - t.min())
    if closest:  # the way the shape fills touches the margin on both sides
        assert max(u.max() / tan_h, v.max() / tan_v) == pytest.approx(0.9, abs=1e-9)
        assert max(-u.min() / tan_h, -v.min() / tan_v) == pytest.approx(0.9, abs=1e-9)
    else:  # the distance of the view aimed at the bounding box's centre
        center = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
        forward = view[2, :3]  # towards the camera
        offsets = vertices - center
        x, y, w = np.abs(offsets @ view[0, :3]), np.abs(offsets @ view[1, :3]), offsets @ forward
        expected = (w + np.maximum(x / (0.9 * tan_h), y / (0.9 * tan_v))).max()
        aim = camera.center - center
        assert abs(aim @ forward) < 1e-12  # moved across only
        assert np.linalg.norm(camera.eye - camera.center) == pytest.approx(expected, rel=1e-12)
