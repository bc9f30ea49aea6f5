"""kpd.viewer.scheduler: which frames the editor draws by a stand-in, and a long session on a large mesh in a real
window under Xvfb, nothing lost."""

import numpy as np
import pytest
from viewer_helpers import HAS_XVFB, clear_keypoint, drags_with_nudges, editor_window, last_event

from kpd.viewer.events import read_events, wait_for


def test_the_editor_draws_a_fine_stand_in_while_the_whole_mesh_draws_slowly():
    from kpd.viewer.scheduler import GESTURE_BUDGET_MS, draws_stand_in
    from kpd.viewer.standins import COARSE_STAND_IN_TRIANGLES

    assert draws_stand_in(COARSE_STAND_IN_TRIANGLES + 1, [])  # a large mesh: always
    assert draws_stand_in(COARSE_STAND_IN_TRIANGLES + 1, [1.0])
    assert not draws_stand_in(20_000, [])  # nothing drawn whole yet
    assert not draws_stand_in(20_000, [GESTURE_BUDGET_MS / 2] * 3)  # a machine that keeps up keeps it whole
    assert draws_stand_in(20_000, [GESTURE_BUDGET_MS * 1.5] * 3)
    assert draws_stand_in(20_000, [GESTURE_BUDGET_MS / 2, GESTURE_BUDGET_MS * 2, GESTURE_BUDGET_MS * 3])  # median
    assert not draws_stand_in(20_000, [GESTURE_BUDGET_MS / 2, GESTURE_BUDGET_MS / 2, GESTURE_BUDGET_MS * 9])


@pytest.mark.slow
@pytest.mark.skipif(not HAS_XVFB, reason="Xvfb/xdotool not installed (make system)")
def test_editor_session_of_many_drags_on_a_million_vertex_mesh_loses_nothing(tmp_path):
    """Five drags with nudges between them, an undo and a redo on a 1.05M-vertex chair: the drags are drawn by the
    coarse stand-in, the last frame is the whole mesh in the final state, and the saved mesh is the edited one."""
    from kpd.commands.demo import procedural_chair
    from kpd.io import read_mesh, write_mesh

    mesh = procedural_chair(edge=0.048)
    assert len(mesh.vertices) > 1_000_000
    write_mesh(tmp_path / "chair.ply", mesh)
    out = tmp_path / "edited.ply"
    with editor_window(tmp_path, "chair", tmp_path / "chair.ply", "--out", out, size="640x480") as win:
        events, xdo = win.events, win.xdo
        keypoints = np.array(win.ready["keypoints"])
        rest = keypoints.copy()
        index = clear_keypoint(win, keypoints)
        keypoints = drags_with_nudges(win, keypoints, index, 5, timeout=120)
        xdo("key", "u")
        wait_for(lambda: last_event(events, "undo"), 120, "undo")
        xdo("key", "y")
        redone = wait_for(lambda: last_event(events, "redo"), 120, "redo")
        np.testing.assert_allclose(redone["keypoints"], keypoints)
        last = wait_for(lambda: [f for f in read_events(events) if f["event"] == "frame"
                                 and f["time"] > redone["time"] and not f["stand_in"]], 120, "the whole mesh")[-1]
        np.testing.assert_allclose(last["keypoints"], keypoints)  # nothing lost: the final state, whole
        xdo("key", "s")
        saved = wait_for(lambda: last_event(events, "save"), 120, "the saved mesh")
        np.testing.assert_allclose(saved["keypoints"], keypoints)
        frames = [e for e in read_events(events) if e["event"] == "frame"]
        inputs = [e for e in read_events(events) if e["event"] == "input"]
    assert len(inputs) >= 40
    assert any(f["stand_in"] for f in frames)  # the drags were drawn by the stand-in
    moved = np.flatnonzero(np.abs(keypoints - rest).max(axis=1) > 0)
    assert moved.tolist() == [index]
    edited = read_mesh(out)
    assert len(edited.vertices) == len(mesh.vertices) and len(edited.triangles) == len(mesh.triangles)
    shift = np.linalg.norm(edited.vertices - mesh.vertices, axis=1)
    assert shift.max() > 1e-3 * np.ptp(mesh.vertices)
    near = np.linalg.norm(mesh.vertices - rest[index], axis=1).argsort()[:100]
    assert shift[near].mean() > np.median(shift)  # what moved is around the dragged keypoint
