"""kpd.viewer: edit sessions, camera maths, images, `kpd render`, `kpd view` errors, and the real editor window driven
under Xvfb with xdotool."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import kpd_process as kpd  # the command in a fresh interpreter, as a user runs it
from viewer_helpers import HAS_XVFB, clear_keypoint, drags_with_nudges, editor_window, last_event, screen_pixels

from kpd.errors import InputError
from kpd.viewer.events import read_events, wait_for
from kpd.viewer.render import ViewSettings, keypoint_palette, read_png
from kpd.viewer.session import EditSession, component_offsets, propose

pytest_plugins = ["viewer_fixtures"]  # the shared fixtures


# --- edit sessions ------------------------------------------------------------------------------------------------


def test_session_undo_redo_and_gesture_merge():
    rest = np.arange(12.0).reshape(4, 3)
    session = EditSession(rest)
    assert not session.can_undo
    assert session.move([1], [0.5, 0, 0], merge="drag")
    assert session.move([1], [0.5, 0, 0], merge="drag")  # same gesture: one undo step
    assert session.depth == 1
    np.testing.assert_allclose(session.keypoints[1], rest[1] + [1.0, 0, 0])
    session.end_gesture()
    session.move([0, 2], [0, 0, -1])
    assert session.depth == 2 and set(session.moved) == {0, 1, 2}
    assert session.undo() and session.undo() and not session.undo()
    np.testing.assert_array_equal(session.keypoints, rest)
    assert session.redo()
    np.testing.assert_allclose(session.keypoints[1], rest[1] + [1.0, 0, 0])
    session.reset()
    np.testing.assert_array_equal(session.keypoints, rest)
    assert session.undo()  # reset is undoable
    np.testing.assert_allclose(session.keypoints[1], rest[1] + [1.0, 0, 0])


def test_session_json_round_trip_applies_offsets(tmp_path):
    rest = np.random.default_rng(0).normal(size=(5, 3))
    session = EditSession(rest)
    session.move([3], [0.1, 0.2, 0.3])
    path = session.save(tmp_path / "s.json", model="chair")
    data = json.loads(path.read_text())
    assert data["format"] == "kpd-edit/1" and data["model"] == "chair" and list(data["moves"]) == ["3"]
    other = EditSession(rest + 1e-12)
    other.load(path)
    np.testing.assert_allclose(other.keypoints, rest + 1e-12 + session.offsets, atol=1e-12)
    assert other.undo()
    np.testing.assert_array_equal(other.keypoints, rest + 1e-12)


@pytest.mark.parametrize("text, match", [
    ("{not json", "not a JSON edit session"),
    ('{"format": "other"}', "session format must be"),
    ('{"format": "kpd-edit/1", "rest_keypoints": [[0, 0, 0]], "keypoints": [[0, 0, 0]]}', "has 1 keypoints"),
])
def test_session_bad_files(tmp_path, text, match):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(InputError, match=match):
        EditSession(np.zeros((5, 3))).load(path)


def test_session_rejects_bad_input():
    with pytest.raises(InputError, match="shape"):
        EditSession(np.zeros((4, 2)))
    session = EditSession(np.zeros((4, 3)))
    with pytest.raises(InputError, match="finite"):
        session.apply(np.full((4, 3), np.nan))
    with pytest.raises(InputError, match=r"\[0, 4\)"):
        session.move([7], [0, 0, 1])


class _ToyPrior:
    """A one-component prior: keypoints 0 and 1 move together (mirror in x)."""

    num_keypoints = 3
    components_ = np.array([[[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0]]]) / math.sqrt(2)
    explained_variance_ = np.array([4.0])

    def sync(self, keypoints, edits):
        from kpd.prior import KeypointPrior

        return KeypointPrior.sync(self, keypoints, edits)

    def _as_keypoints(self, keypoints, name="keypoints"):
        return np.asarray(keypoints, dtype=np.float64)

    def _check_params(self):
        return 1

    def _check_fitted(self):
        return None

    def covariance(self):
        from kpd.prior import KeypointPrior

        return KeypointPrior.covariance(self)

    ridge_ = 1e-9
    mirror_permutation_ = None


def test_propose_with_and_without_prior():
    from kpd.geometry import Normalizer

    base = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0]])
    normalizer = Normalizer.from_dict({"center": [0.0, 0.0, 0.0], "scale": 2.0})
    alone = propose(base, {0: [1.5, 0, 0]})
    np.testing.assert_allclose(alone, [[1.5, 0, 0], [-1.0, 0, 0], [0, 1.0, 0]])
    synced = propose(base, {0: [1.5, 0, 0]}, prior=_ToyPrior(), normalizer=normalizer)
    np.testing.assert_array_equal(synced[0], [1.5, 0, 0])  # exactly where asked
    np.testing.assert_allclose(synced[1], [-1.5, 0, 0], atol=1e-6)  # the mirror partner follows
    np.testing.assert_allclose(synced[2], base[2], atol=1e-9)
    offsets = component_offsets(_ToyPrior(), normalizer, [1.0])  # one standard deviation: 2 model units
    np.testing.assert_allclose(offsets[0], [2 * 2 / math.sqrt(2), 0, 0])
    with pytest.raises(InputError, match="normalizer"):
        propose(base, {0: [0, 0, 0]}, prior=_ToyPrior())


# --- commands on a real chair -------------------------------------------------------------------------------------


def _one_line_error(done: subprocess.CompletedProcess, match: str) -> None:
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and match in lines[0], done.stderr


def test_bad_input_ends_with_one_line(chair_rig, tmp_path):
    _one_line_error(kpd("render", "--rig", tmp_path / "missing.npz", "--out", tmp_path / "a.png"), "no such rig")
    _one_line_error(kpd("render", "chair", tmp_path / "missing.obj", "--out", tmp_path / "a.png"), "no such file")
    _one_line_error(kpd("render", "--rig", chair_rig, "--model", "table", "--out", tmp_path / "a.png"),
                    "has 8 keypoints")
    _one_line_error(kpd("view", "--rig", chair_rig, "--model", "table"), "has 8 keypoints")
    _one_line_error(kpd("render", "--rig", chair_rig, "--out", tmp_path / "a.jpg"), "PNG")
    _one_line_error(kpd("render", "--rig", chair_rig, "--move", "40:0,0,1", "--out", tmp_path / "a.png"),
                    "[0, 12)")
    (tmp_path / "exists.png").write_bytes(b"x")
    _one_line_error(kpd("render", "--rig", chair_rig, "--out", tmp_path / "exists.png"), "--force")
    assert (tmp_path / "exists.png").read_bytes() == b"x"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    _one_line_error(kpd("view", "--rig", chair_rig, env=env), "needs a display")
    help_text = kpd("render", "--help").stdout
    assert "example:" in help_text and "kpd render" in help_text
    assert "example:" in kpd("view", "--help").stdout


def _check_render(path: Path, k: int) -> None:
    image = read_png(path)
    assert image.shape == (240, 320, 3)
    background = image[0, 0]
    shape = np.abs(image.astype(int) - background).sum(axis=2) > 30
    assert 0.03 < shape.mean() < 0.8  # the shape is there and not everything
    colors = (keypoint_palette(k) * 255).astype(int)
    found = sum(bool((np.abs(image.astype(int) - c).max(axis=2) < 40).sum() >= 3) for c in colors)
    assert found >= k // 2, f"only {found} of {k} keypoint colours visible"


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["auto", "xvfb"])
def test_render_writes_a_png_of_the_shape(chair_rig, tmp_path, backend):
    if backend == "xvfb" and not HAS_XVFB:
        pytest.skip("Xvfb/xdotool not installed (make system)")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}  # no display needed
    out = tmp_path / "view.png"
    done = kpd("render", "--rig", chair_rig, "--move", "0:0,0,-3", "--size", "320x240", "--backend", backend,
               "--out", out, env=env)
    assert done.returncode == 0, done.stderr
    _check_render(out, 12)


@pytest.mark.slow
def test_render_is_cleanly_shaded_and_frames_the_deformed_shape(data_dir, tmp_path):
    """ModelNet10 chair_0890 is double-sided (every triangle twice, both windings: normals averaged over it cancel to
    zero, which drew black and white blotches). Raised by 80% of its height at the back, the chair must stay inside
    the picture, and its plain grey surface must shade without near-black or near-white patches."""
    from kpd.io import read_mesh, write_mesh
    from kpd.runtime import Model

    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")
    rig = Model.load("chair").rig(mesh)
    height = float(np.ptp(mesh.vertices[:, 2]))
    tops = np.argsort(rig.keypoints[:, 2])[-2:]
    moves = [f"{i}:0,0,{0.8 * height:.4f}" for i in tops]
    path = tmp_path / "chair.ply"
    write_mesh(path, mesh)
    out = tmp_path / "taller.png"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    done = kpd("render", "chair", path, *[a for m in moves for a in ("--move", m)], "--no-labels", "--size",
               "480x360", "--out", out, env=env)
    assert done.returncode == 0, done.stderr
    image = read_png(out).astype(int)
    background = image[0, 0]
    shape = np.abs(image - background).sum(axis=2) > 24
    assert shape.mean() > 0.04
    ys, xs = np.nonzero(shape)
    assert ys.min() > 2 and xs.min() > 2 and ys.max() < image.shape[0] - 3 and xs.max() < image.shape[1] - 3
    colours = keypoint_palette(12) * 255
    grey = shape & (np.abs(image[..., :, None, :] - colours[None, None]).max(axis=3).min(axis=2) > 60)  # not markers
    brightness = image[grey].mean(axis=1)
    assert (brightness < 40).mean() < 0.01 and (brightness > 245).mean() < 0.01, (
        (brightness < 40).mean(), (brightness > 245).mean())
    assert brightness.std() > 8  # shaded, not flat


def test_a_scan_rig_deforms_the_rows_of_a_stand_in_alone(data_dir):
    """kpd view --scan: a drag drawn by the stand-in deforms its vertices only (ScanRig.deform(rows=)), the same
    rows as the whole deformation, the other rows of the buffer left as they were."""
    from kpd.frame import ScanFrame, ScanRig
    from kpd.io import read_mesh
    from kpd.runtime import Model

    model = Model.load("chair")
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply")
    frame = ScanFrame(model, mesh, "z")
    rig = ScanRig(model.rig(mesh.with_vertices(frame.to_aligned(mesh.vertices))), mesh, frame)
    keypoints = rig.keypoints
    keypoints[2] += [0.0, 0.0, 0.05 * np.ptp(mesh.vertices)]
    whole = rig.deform(keypoints)
    rows = np.arange(0, len(mesh.vertices), 7)
    out = np.full_like(mesh.vertices, np.nan)
    assert rig.deform(keypoints, out=out, rows=rows) is out
    np.testing.assert_allclose(out[rows], whole[rows], rtol=0, atol=1e-12 * np.ptp(mesh.vertices))
    assert np.isnan(np.delete(out, rows, axis=0)).all()
    assert np.abs(whole[rows] - mesh.vertices[rows]).max() > 1e-3 * np.ptp(mesh.vertices)  # it moved
    with pytest.raises(InputError, match="rows"):
        rig.deform(keypoints, out=out, rows=np.array([len(mesh.vertices)]))


def test_open3d_plotly_helpers_load_on_first_use():
    code = ("import sys, kpd, open3d, numpy as np\n"
            "assert 'dash' not in sys.modules and 'plotly' not in sys.modules\n"
            "fig = open3d.visualization.get_plotly_fig([open3d.geometry.TriangleMesh.create_box()])\n"
            "print(type(fig).__name__)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "Figure"


@pytest.mark.slow
def test_eval_chamfer_gallery_draws_the_pairs_as_meshes(data_dir, tmp_path):
    """``kpd eval chamfer --gallery``: one row per pair, source (blue), deformed (green) and target (red) meshes."""
    out, gallery = tmp_path / "c.json", tmp_path / "g.png"
    done = kpd("eval", "chamfer", data_dir / "modelnet10", "--category", "chair", "--model", "chair", "--pairs", "4",
               "--out", out, "--gallery", gallery, "--gallery-pairs", "2", "--quiet")
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text())["gallery"] == str(gallery)
    image = read_png(gallery).astype(int)
    rows, columns = 2, 3
    assert image.shape[1] == columns * 280 and image.shape[0] > rows * 280
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    tints = {"blue": (b > r + 30) & (b > g + 10), "green": (g > r + 25) & (g > b + 10),
             "red": (r > g + 40) & (r > b + 40)}
    for column, name in enumerate(("blue", "green", "red")):
        part = tints[name][:, column * 280:(column + 1) * 280]
        assert part.mean() > 0.02, f"the {name} meshes are missing from column {column}"


def test_no_window_is_one_line(chair_rig, tmp_path):
    env = dict(os.environ, DISPLAY=":987")  # no X server there
    _one_line_error(kpd("view", "--rig", chair_rig, env=env), "could not open an OpenGL window")
    _one_line_error(kpd("render", "--rig", chair_rig, "--backend", "window", "--out", tmp_path / "a.png", env=env),
                    "could not open an OpenGL")
    assert not (tmp_path / "a.png").exists()


# --- the real window -------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_editor_window_pick_drag_save_undo(chair_rig, tmp_path):
    from kpd.io import read_mesh
    from kpd.rig import Rig

    rig = Rig.load(chair_rig)
    out = tmp_path / "edited.ply"
    with editor_window(tmp_path, "--rig", chair_rig, "--out", out) as win:
        events, xdo, ready = win.events, win.xdo, win.ready
        np.testing.assert_allclose(ready["keypoints"], rig.keypoints)
        index = clear_keypoint(win, rig.keypoints)
        x, y = np.rint(screen_pixels(win, rig.keypoints)[index]).astype(int)
        xdo("mousemove", x, y)
        xdo("mousedown", 1)
        selected = wait_for(lambda: last_event(events, "select"), 60, "the selection")
        assert selected["selection"] == [index] and selected["picked"] == index
        for step in range(1, 6):
            xdo("mousemove", x + 4 * step, y - 10 * step)
        xdo("mouseup", 1)
        released = wait_for(lambda: last_event(events, "release"), 120, "the end of the drag")
        assert released["moved"]
        xdo("key", "s")
        saved = wait_for(lambda: last_event(events, "save"), 60, "the saved mesh")
        keypoints = np.array(saved["keypoints"])
        moved = np.flatnonzero(np.abs(keypoints - rig.keypoints).max(axis=1) > 0)
        assert moved.tolist() == [index]  # the prior is off: only the selection moved
        mesh = read_mesh(out)
        assert len(mesh.triangles) == len(rig.mesh.triangles)
        expected = rig.deform(keypoints)
        scale = np.abs(expected).max()
        np.testing.assert_allclose(mesh.vertices, expected, atol=1e-5 * scale)
        assert np.abs(mesh.vertices - rig.mesh.vertices).max() > 1e-3 * scale  # the mesh did change
        count = len(read_events(events))
        xdo("key", "u")
        undone = wait_for(lambda: last_event(events, "undo", count), 60, "undo")
        np.testing.assert_allclose(undone["keypoints"], rig.keypoints)
        count = len(read_events(events))
        xdo("key", "s")
        wait_for(lambda: last_event(events, "save", count), 60, "the second save")
        np.testing.assert_allclose(read_mesh(out).vertices, rig.mesh.vertices, atol=1e-5 * scale)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
@pytest.mark.parametrize("green_out", [True, False])
def test_editor_window_shows_the_outer_side_of_faces_with_two_materials(tmp_path, green_out):
    """A box whose faces are stored twice, wound opposite ways, green on one side and white on the other (as ShapeNet
    stores a cup's label over its inside), green listed first: the editor's window, read from the Xvfb screen, shows
    the side facing out. Which coincident face showed was once the renderer's order of geometries."""
    from helpers import two_sided_box

    from kpd.io import write_mesh
    from kpd.viewer.display import grab_screen

    write_mesh(tmp_path / "box.obj", two_sided_box(green_out, green_first=True))
    screen = tmp_path / "screen"
    screen.mkdir()
    with editor_window(tmp_path, "chair", tmp_path / "box.obj", screen=screen) as win:
        time.sleep(1.0)  # ready (the rig bound): its frame is on the screen
        vx, vy, w, h = (int(round(v)) for v in win.ready["viewport"])
        x, y = win.origin[0] + vx, win.origin[1] + vy
        r, g, b = np.moveaxis(grab_screen(screen)[y:y + h, x:x + w].astype(int), 2, 0)
        shown = (np.abs(r - 255) + np.abs(g - 255) + np.abs(b - 255) > 40).sum()
        green = ((g > r + 60) & (g > b + 60)).sum()
        assert shown > 0.1 * w * h and (green > 0.8 * shown if green_out else green < 0.02 * shown), (green, shown)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_editor_window_shows_the_number_of_every_keypoint_in_view(data_dir, tmp_path):
    """The real sneaker scan in the editor's window, seen from the model's up axis: most of its keypoints lie behind
    the surface the camera sees, and each one's number still shows beside where its marker would be, in its colour
    (as the numbers of ``kpd render`` pictures do). Numbers drawn where the keypoints are were cut off by the
    surface, or showed only a piece of their white card."""
    from kpd.viewer.display import grab_screen
    from kpd.viewer.settings import keypoint_palette

    screen = tmp_path / "screen"
    screen.mkdir()
    with editor_window(tmp_path, "shoe", data_dir / "scans" / "sneaker.ply", size="640x520", screen=screen) as win:
        time.sleep(1.0)  # ready (the rig bound): its frame is on the screen
        keypoints = np.array(win.ready["keypoints"])
        vx, vy, w, h = (int(round(v)) for v in win.ready["viewport"])
        x, y = win.origin[0] + vx, win.origin[1] + vy
        image = grab_screen(screen)[y:y + h, x:x + w].astype(int)
    pixels = screen_pixels(win, keypoints) - np.array([x, y])
    ink = np.rint(255 * 0.75 * keypoint_palette(len(keypoints))).astype(int)
    shown = []
    for k, (px, py) in enumerate(pixels):
        if not (20 < px < w - 60 and 40 < py < h - 20):
            continue  # its number may leave the view
        around = image[max(int(py) - 40, 0):int(py) + 10, max(int(px) - 10, 0):int(px) + 50]  # up and to the right
        shown.append(int((np.abs(around - ink[k]).max(axis=2) <= 24).sum()))
    assert len(shown) >= 8 and min(shown) >= 4, shown  # a "1" in its colour is 10-12 pixels here


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_editor_scripted_session_of_many_drags_and_keys(chair_rig, tmp_path):
    """Eight drags of one keypoint with nudges between them, an undo and a redo (over 50 inputs): nothing is lost
    (the last frame drawn shows the final keypoints), the saved mesh is Rig.deform of the keypoints the window
    reports, and the screenshots differ where the dragged part is."""
    from kpd.io import read_mesh
    from kpd.rig import Rig

    rig = Rig.load(chair_rig)
    out = tmp_path / "edited.ply"
    with editor_window(tmp_path, "--rig", chair_rig, "--out", out, "--screenshot", tmp_path / "shot.png") as win:
        events, xdo = win.events, win.xdo
        xdo("key", "p")
        first = wait_for(lambda: last_event(events, "screenshot"), 60, "the first screenshot")
        index = clear_keypoint(win, rig.keypoints)
        keypoints = rig.keypoints
        keypoints = drags_with_nudges(win, keypoints, index, 8, timeout=60)
        xdo("key", "u")
        wait_for(lambda: last_event(events, "undo"), 60, "undo")
        xdo("key", "y")
        redone = wait_for(lambda: last_event(events, "redo"), 60, "redo")
        np.testing.assert_allclose(redone["keypoints"], keypoints)
        xdo("key", "s")
        saved = wait_for(lambda: last_event(events, "save"), 60, "the saved mesh")
        xdo("key", "p")
        second = wait_for(lambda: [e for e in read_events(events) if e["event"] == "screenshot"][1:], 60,
                       "the second screenshot")[0]
        final = np.array(saved["keypoints"])
        np.testing.assert_allclose(final, keypoints)
        inputs = [e for e in read_events(events) if e["event"] == "input"]
        assert len(inputs) >= 50
        frames = [e for e in read_events(events) if e["event"] == "frame"]
        redo = max(i for i, e in enumerate(inputs, 1) if e["kind"] == "key" and e["key"] == ord("Y"))
        assert frames[-1]["serial"] >= redo  # the last input that changed anything was drawn (save and P change none)
        np.testing.assert_allclose(frames[-1]["keypoints"], final)  # nothing lost: the last frame is the final state
    moved = np.flatnonzero(np.abs(final - rig.keypoints).max(axis=1) > 0)
    assert moved.tolist() == [index]
    mesh = read_mesh(out)
    scale = np.abs(rig.mesh.vertices).max()
    np.testing.assert_allclose(mesh.vertices, rig.deform(final), atol=1e-5 * scale)
    before, after = read_png(first["path"]).astype(int), read_png(second["path"]).astype(int)
    changed = np.abs(after - before).sum(axis=2) > 60
    assert changed.sum() > 200
    ys, xs = np.nonzero(changed)
    centroid = np.array([xs.mean(), ys.mean()]) + np.array(win.origin) + np.array(win.ready["viewport"][:2])
    path_mid = (screen_pixels(win, rig.keypoints)[index] + screen_pixels(win, final)[index]) / 2
    others = np.linalg.norm(screen_pixels(win, rig.keypoints) - path_mid, axis=1)
    assert np.linalg.norm(centroid - path_mid) < np.sort(others)[len(others) // 2]  # near the dragged keypoint


@pytest.mark.slow
def test_render_draws_textures_the_right_way_up():
    """A square whose texture is red in its top half (as the image file shows it) and blue below, with UVs whose v
    grows upward (OBJ): the rendered square must be red above and blue below."""
    from kpd.geometry import Normalizer
    from kpd.io import Mesh
    from kpd.rig import Rig
    from kpd.viewer.render import render_rig

    vertices = np.array([[-1.0, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]])  # facing the front view (-y for z up)
    uv = {0: (0.0, 0.0), 1: (1.0, 0.0), 2: (1.0, 1.0), 3: (0.0, 1.0)}
    triangles = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])  # both windings: seen from either side
    texture = np.zeros((64, 64, 3), np.uint8)
    texture[:32] = (230, 20, 20)
    texture[32:] = (20, 20, 230)
    mesh = Mesh(vertices=vertices, triangles=triangles, triangle_uvs=np.array([uv[i] for i in triangles.ravel()]),
                textures=[texture], triangle_material_ids=np.zeros(len(triangles), np.int64))
    rig = Rig.bind(mesh, np.array([[0.0, 0, 0.5], [0, 0, -0.5]]), normalizer=Normalizer().fit(vertices))
    settings = ViewSettings(width=240, height=240, show_keypoints=False, show_labels=False, azimuth=0.0,
                            elevation=0.0)
    _check_texture(render_rig(rig, settings=settings, backend="egl").astype(int))


def _check_texture(image: np.ndarray) -> None:
    red = (image[..., 0] > image[..., 2] + 40) & (image[..., 0] > 60)
    blue = (image[..., 2] > image[..., 0] + 40) & (image[..., 2] > 60)
    assert red.sum() > 500 and blue.sum() > 500, (red.sum(), blue.sum())
    rows = np.arange(image.shape[0])[:, None]
    assert (rows * red).sum() / red.sum() < (rows * blue).sum() / blue.sum()  # red above blue
