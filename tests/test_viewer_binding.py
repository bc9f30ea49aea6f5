"""The editor with a rig still to be made: the mesh shown at once and bound on a worker thread (its positions grouped
once), input answered meanwhile, its errors and a saved session applied once it is bound; in real windows under Xvfb
driven by xdotool."""

import subprocess

import numpy as np
import pytest
from helpers import kpd_process as kpd  # the command in a fresh interpreter, as a user runs it
from viewer_helpers import HAS_XVFB, editor_window, last_event

from kpd.viewer.events import read_events, wait_for

pytest_plugins = ["viewer_fixtures"]  # the shared fixtures


def test_binding_and_drawing_a_mesh_at_once_group_its_positions_once(monkeypatch):
    import kpd.grouping
    import kpd.mesh
    import kpd.rig
    from kpd.commands.render import bind_beside_drawing
    from kpd.grouping import first_occurrence_groups
    from kpd.io import Mesh
    from kpd.rig import Rig
    from kpd.viewer.app import PendingRig
    from kpd.viewer.render import ViewSettings

    calls = []

    def counted(keys):
        calls.append(len(keys))
        return first_occurrence_groups(keys)

    for module in (kpd.mesh, kpd.grouping, kpd.rig):  # wherever a grouping may be asked for
        monkeypatch.setattr(module, "first_occurrence_groups", counted)
    rng = np.random.default_rng(5)
    vertices = rng.uniform(-1.0, 1.0, size=(3000, 3))
    vertices[2000:] = vertices[:1000]  # copies of a position
    mesh = Mesh(vertices, rng.integers(0, 3000, size=(6000, 3)))
    keypoints = vertices[:4]
    rig, shaded = bind_beside_drawing(PendingRig(mesh, 4, lambda: Rig.bind(mesh, keypoints)), ViewSettings())
    assert calls == [3000]  # the binding's and the drawing's groups, found once
    assert shaded.welding.groups == 2000
    alone = Rig.bind(Mesh(vertices.copy(), mesh.triangles), keypoints)  # its own positions grouped again
    assert calls == [3000, 3000]
    np.testing.assert_array_equal(rig.basis, alone.basis)


_HELD_BINDING = """
import sys, time
from pathlib import Path
from kpd.rig import Rig
from kpd.viewer.app import EditorApp, PendingRig
from kpd.viewer.render import ViewSettings

rig = Rig.load(sys.argv[1])
release = Path(sys.argv[3])

def bind():  # held until the test lets it go
    while not release.exists():
        time.sleep(0.05)
    return rig

app = EditorApp(PendingRig(rig.mesh, rig.num_keypoints, bind), settings=ViewSettings(width=480, height=400),
                events=sys.argv[2], title="kpd binding test")
sys.exit(app.run())
"""


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_editor_shows_the_mesh_at_once_and_answers_input_while_it_binds(chair_rig, tmp_path):
    """A rig still to be made (viewer.app.PendingRig): the mesh is on the screen before the rig is ready, a drag and
    keys meanwhile are taken (the view turns; edits wait, the panel says why), and the keypoints appear when the
    binding returns."""
    import os
    import sys

    from kpd.rig import Rig
    from kpd.viewer.render import private_display

    rig = Rig.load(chair_rig)
    events, release = tmp_path / "events.jsonl", tmp_path / "release"
    with private_display(1400, 900) as display:
        env = dict(os.environ, DISPLAY=display)
        window = subprocess.Popen([sys.executable, "-c", _HELD_BINDING, str(chair_rig), str(events), str(release)],
                                  env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

        def xdo(*args: object) -> None:
            subprocess.run(["xdotool", *map(str, args)], env=env, check=True, capture_output=True)

        try:
            wait_for(lambda: last_event(events, "shown"), 120, "the mesh")
            xdo("mousemove", 240, 200)
            xdo("mousedown", 1)
            for step in range(1, 5):
                xdo("mousemove", 240 + 15 * step, 200 + 5 * step)
            xdo("mouseup", 1)
            xdo("key", "u")
            xdo("key", "Right")
            wait_for(lambda: [e for e in read_events(events) if e["event"] == "frame" and e["serial"] >= 5], 60,
                     "a frame of the turned view")
            assert last_event(events, "ready") is None
            release.touch()
            wait_for(lambda: last_event(events, "ready"), 60, "the rig")
            wait_for(lambda: [e for e in read_events(events) if e["event"] == "frame" and e["keypoints"]], 60,
                     "a frame with the keypoints")
        finally:
            release.touch()
            window.terminate()
            window.wait(30)
        assert b"Traceback" not in window.stderr.read()
    log = read_events(events)
    names = [e["event"] for e in log]
    ready = log[names.index("ready")]
    assert names.index("shown") < names.index("ready")
    first = next(e for e in log if e["event"] == "frame")
    assert first["keypoints"] == [] and first["time"] < ready["time"]
    inputs = [e for e in log if e["event"] == "input"]
    assert len(inputs) >= 7 and all(e["time"] < ready["time"] for e in inputs)
    assert "undo" in names and "nudge" not in names  # the key was taken; no keypoint to nudge yet
    assert ready["undo"] == 0
    np.testing.assert_allclose(ready["keypoints"], rig.keypoints)
    last = [e for e in log if e["event"] == "frame"][-1]
    np.testing.assert_allclose(last["keypoints"], rig.keypoints)  # the keypoints are drawn


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_kpd_view_ends_with_the_bindings_error_in_one_line(tmp_path):
    """The binding runs after the window opened: its error still ends kpd view with one line and status 2."""
    import os

    from kpd.io import Mesh, write_mesh
    from kpd.viewer.render import private_display

    flat = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])  # every triangle without area: nothing to sample
    write_mesh(tmp_path / "flat.ply", Mesh(flat, np.array([[0, 1, 2], [1, 2, 3]])))
    with private_display(1400, 900) as display:
        done = kpd("view", "chair", tmp_path / "flat.ply", "--size", "320x240", env=dict(os.environ, DISPLAY=display))
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.strip().splitlines() if not line.startswith("warning:")]
    assert len(lines) == 1 and lines[0].startswith("kpd view: error:") and "zero area" in lines[0], done.stderr


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_kpd_view_applies_a_saved_session_once_the_rig_is_bound(data_dir, tmp_path):
    """kpd view MODEL SHAPE --load-session: the session (checked before the window opens) is applied to the rig
    bound on the worker thread, so the keypoints it shows first are the session's; a bad session file ends before."""
    import os

    from kpd.runtime import Model
    from kpd.viewer.session import EditSession

    shape = data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply"
    rest = Model.load("chair").rig(shape).keypoints
    session = EditSession(rest)
    session.move([3], [0.0, 0.0, 2.5])
    session.save(tmp_path / "session.json")
    (tmp_path / "bad.json").write_text("{not json")
    done = kpd("view", "chair", shape, "--load-session", tmp_path / "bad.json", env=dict(os.environ, DISPLAY=":404"))
    assert done.returncode == 2 and "not a JSON edit session" in done.stderr
    with editor_window(tmp_path, "chair", shape, "--load-session", tmp_path / "session.json") as win:
        np.testing.assert_allclose(win.ready["keypoints"], session.keypoints, atol=1e-9)
        assert win.ready["undo"] == 1


