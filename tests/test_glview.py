"""kpd.viewer.glview: the window, where it samples its pixels, and the environment Mesa is given."""

import os
import subprocess

import numpy as np
import pytest
from viewer_helpers import HAS_XVFB

pytest_plugins = ["viewer_fixtures"]  # the shared fixtures


def test_software_rasteriser_gets_eight_threads_a_processor_unless_the_user_says(monkeypatch):
    from kpd.viewer.glview import _raster_threads

    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    _raster_threads()
    assert os.environ["LP_NUM_THREADS"] == str(min(8 * (os.cpu_count() or 1), 16))
    monkeypatch.setenv("LP_NUM_THREADS", "1")
    _raster_threads()
    assert os.environ["LP_NUM_THREADS"] == "1"


def test_a_picture_leaves_no_runtime_folder_behind(data_dir, tmp_path):
    """Without $XDG_RUNTIME_DIR, OpenGL is given a private folder for its time (GLFW and Mesa ask for one); it is
    gone when kpd render ends, nothing else left in the temporary folder."""
    import sys

    temporary = tmp_path / "tmp"
    temporary.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "XDG_RUNTIME_DIR"}
    env["TMPDIR"] = str(temporary)
    chair = data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply"
    out = tmp_path / "r.png"
    done = subprocess.run([sys.executable, "-m", "kpd.cli", "render", "chair", str(chair), "--size", "160x120",
                           "--out", str(out)], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert out.stat().st_size > 0
    assert list(temporary.iterdir()) == []


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_a_window_frame_of_the_visible_triangles_is_the_picture_on_the_screen(dense_chair, tmp_path, monkeypatch):
    """On the screen a window is multisampled (Mesa's software renderer gives Open3D the four samples it asks for):
    frames culled at the sample points the window's OpenGL context reports show the same pixels as whole frames,
    read from the Xvfb screen; culled at the pixel centres alone they would not (the test can fail)."""
    import os
    import time

    from kpd.viewer.culling import PIXEL_CENTRE, Viewport
    from kpd.viewer.display import grab_screen
    from kpd.viewer.glview import GLView
    from kpd.viewer.render import ViewSettings, camera_pose, private_display
    from kpd.viewer.shaded import ShadedMesh

    mesh = dense_chair
    width, height = 480, 400
    with private_display(width + 40, height + 40, fbdir=tmp_path) as display:
        monkeypatch.setenv("DISPLAY", display)
        view = GLView(width, height, visible=True, left=0, top=0)
        try:
            assert view.viewport(camera_pose(mesh.vertices, ViewSettings())).samples.shape == (4, 2)
            shaded = ShadedMesh(mesh)
            view.set_box(mesh.vertices)

            def on_screen(camera, viewport) -> np.ndarray:
                shaded.set_vertices(mesh.vertices, camera, viewport)
                for i, part in enumerate(shaded.geometries):
                    view.put(f"mesh:{i}", part)
                view.set_camera(camera)
                view.draw()
                time.sleep(0.3)  # the server has the frame
                return grab_screen(os.fspath(tmp_path))[:height, :width]

            for azimuth, elevation, zoom in [(30, 20, 1.0), (200, -40, 2.0)]:
                camera = camera_pose(mesh.vertices, ViewSettings(width=width, height=height, azimuth=azimuth,
                                                                 elevation=elevation, zoom=zoom))
                whole = on_screen(camera, None)
                np.testing.assert_array_equal(on_screen(camera, view.viewport(camera)), whole)
                assert len(shaded.geometries[0].triangles) < 0.8 * len(shaded.drawn)
                if zoom == 1.0:  # the centres alone miss samples: the check above can fail
                    centres = on_screen(camera, Viewport(camera, width, height, PIXEL_CENTRE))
                    assert (centres != whole).any(axis=2).sum() > 100
        finally:
            view.close()
