"""What the viewer's tests share: an editor window to drive, on a private Xvfb with xdotool (the shared fixtures
are in ``viewer_fixtures``, the ``kpd`` command in ``helpers``)."""

import contextlib
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kpd.viewer.events import read_events, wait_for
from kpd.viewer.render import project

HAS_XVFB = shutil.which("Xvfb") is not None and shutil.which("xdotool") is not None


def last_event(path: Path, name: str, after: int = 0):
    """The last ``name`` event an editor wrote to ``path`` after its first ``after`` events, or None."""
    found = [e for e in read_events(path)[after:] if e["event"] == name]
    return found[-1] if found else None


class EditorWindow(NamedTuple):
    """A running editor on a private Xvfb: its events file, xdotool, its ready event and the 3D view's top-left corner
    on the screen."""

    events: Path
    xdo: Callable[..., str]
    ready: dict
    origin: tuple[int, int]
    display: str


@contextlib.contextmanager
def editor_window(tmp_path: Path, *args: object, size: str = "480x400", screen: Path | None = None
                  ) -> Iterator[EditorWindow]:
    """``kpd view ARGS --size SIZE --events ...`` in a real window on a private Xvfb, stopped on exit; with ``screen``
    (a folder) the server keeps its screen there for ``grab_screen``."""
    from kpd.viewer.render import private_display

    events = tmp_path / "events.jsonl"
    with private_display(1400, 900, fbdir=screen) as display:
        env = dict(os.environ, DISPLAY=display)
        window = subprocess.Popen(
            [sys.executable, "-m", "kpd.cli", "view", *map(str, args), "--size", size, "--events", str(events)],
            env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

        def xdo(*xargs: object) -> str:
            return subprocess.run(["xdotool", *map(str, xargs)], env=env, check=True, capture_output=True,
                                  text=True).stdout

        try:
            ready = wait_for(lambda: last_event(events, "ready"), 90, "the editor window")
            wid = wait_for(lambda: subprocess.run(["xdotool", "search", "--name", f"^{ready['title']}$"], env=env,
                                               capture_output=True, text=True).stdout.split(), 30, "the X window")[-1]
            geometry = dict(line.split("=") for line in xdo("getwindowgeometry", "--shell", wid).split())
            yield EditorWindow(events, xdo, ready, (int(geometry["X"]), int(geometry["Y"])), display)
        finally:
            window.terminate()
            try:
                window.wait(10)
            except subprocess.TimeoutExpired:
                window.kill()
                window.wait()
        assert b"Traceback" not in window.stderr.read(), "the editor raised"


def screen_pixels(win: EditorWindow, keypoints: np.ndarray) -> np.ndarray:
    """(K, 2) screen positions of keypoints in the editor's 3D view (the camera of its ready event)."""
    vx, vy, w, h = win.ready["viewport"]
    pixels, _ = project(np.asarray(keypoints), np.array(win.ready["view"]), np.array(win.ready["projection"]), w, h)
    return pixels + np.array([win.origin[0] + vx, win.origin[1] + vy])


def clear_keypoint(win: EditorWindow, keypoints: np.ndarray) -> int:
    """A keypoint well inside the view and far from the others' markers on screen."""
    vx, vy, w, h = win.ready["viewport"]
    pixels = screen_pixels(win, keypoints) - np.array([win.origin[0] + vx, win.origin[1] + vy])
    gaps = np.linalg.norm(pixels[:, None] - pixels[None], axis=2) + np.eye(len(pixels)) * 1e9
    inside = (pixels[:, 0] > 60) & (pixels[:, 0] < w - 60) & (pixels[:, 1] > 80) & (pixels[:, 1] < h - 60)
    return int(np.argmax(np.where(inside, gaps.min(axis=1), -1)))


def drags_with_nudges(win, keypoints: np.ndarray, index: int, count: int, *, timeout: float) -> np.ndarray:
    """``count`` drags of keypoint ``index`` towards the middle of the view (so it stays in sight), each followed by
    an arrow-key nudge (undone by the next one); returns the keypoints the window reports after the last nudge."""
    events, xdo = win.events, win.xdo
    vx, vy, w, h = win.ready["viewport"]
    centre = np.array([win.origin[0] + vx + w / 2, win.origin[1] + vy + h / 2])
    towards = np.sign(centre - screen_pixels(win, keypoints)[index])
    for drag in range(count):
        x, y = np.rint(screen_pixels(win, keypoints)[index]).astype(int)
        xdo("mousemove", x, y)
        xdo("mousedown", 1)
        for step in range(1, 6):
            xdo("mousemove", x + int(towards[0] * 2 * step), y + int(towards[1] * 3 * step))
        xdo("mouseup", 1)
        released = wait_for(lambda: [e for e in read_events(events) if e["event"] == "release"][drag:], timeout,
                            f"the end of drag {drag + 1}")[0]
        assert released["moved"] and released["selection"] == [index]
        xdo("key", "Left" if drag % 2 else "Right")
        nudges = wait_for(lambda: [e for e in read_events(events) if e["event"] == "nudge"][drag:], timeout, "a nudge")
        keypoints = np.array(nudges[0]["keypoints"])
    return keypoints
