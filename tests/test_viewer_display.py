"""kpd.viewer.display: the backends refuse in one clear error where they cannot run; a private Xvfb server starts,
shows what is drawn on it and stops."""

from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest

from kpd.errors import KpdError
from kpd.viewer.display import BACKENDS, grab_screen, private_display, resolve_backend


def test_backends_and_refusals(monkeypatch):
    assert BACKENDS == ("auto", "egl", "xvfb", "window") and resolve_backend("auto") == "egl"
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(KpdError, match=r"\$DISPLAY is not set"):
        resolve_backend("window")
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(KpdError, match="needs the Xvfb program"):
        resolve_backend("xvfb")


@pytest.mark.skipif(not (shutil.which("Xvfb") and shutil.which("xdotool")),
                    reason="Xvfb or xdotool not installed (make system)")
def test_private_display_runs_and_its_screen_can_be_grabbed(tmp_path):
    with private_display(320, 200, fbdir=tmp_path) as display:
        assert display.startswith(":")
        screen = grab_screen(tmp_path)
        assert screen.shape == (200, 320, 3) and screen.dtype == np.uint8
        geometry = subprocess.run(["xdotool", "getdisplaygeometry"], env=dict(os.environ, DISPLAY=display),
                                  capture_output=True, text=True, timeout=20)
        assert geometry.stdout.split() == ["320", "200"]
    after = subprocess.run(["xdotool", "getdisplaygeometry"], env=dict(os.environ, DISPLAY=display),
                           capture_output=True, text=True, timeout=20)
    assert after.returncode != 0  # the server stopped with the block


def test_the_editor_asked_to_end_closes_and_leaves_nothing_behind(data_dir, tmp_path):
    """``kill`` (SIGTERM) ends ``kpd view`` as Ctrl+C does: the window closes, its private runtime folder goes, one
    line says why, and the status is 128 + 15 (before, the process died at once and left the folder)."""
    import json
    import signal
    import sys
    import time

    temporary = tmp_path / "tmp"
    temporary.mkdir()
    events = tmp_path / "events.jsonl"
    chair = data_dir / "modelnet10" / "chair" / "test" / "chair_0956.ply"
    with private_display(1200, 800) as display:
        env = {k: v for k, v in os.environ.items() if k != "XDG_RUNTIME_DIR"}
        env.update(DISPLAY=display, TMPDIR=str(temporary))
        editor = subprocess.Popen([sys.executable, "-m", "kpd.cli", "view", "chair", str(chair), "--events",
                                   str(events)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.time() + 120
            while not (events.exists() and '"ready"' in events.read_text()):
                assert editor.poll() is None and time.time() < deadline, "the editor did not get ready"
                time.sleep(0.2)
            editor.send_signal(signal.SIGTERM)
            _, err = editor.communicate(timeout=60)
        finally:
            if editor.poll() is None:
                editor.kill()
    assert editor.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "kpd view: stopped by signal 15 (SIGTERM)"
    assert [json.loads(line)["event"] for line in events.read_text().splitlines()][-1] == "close"
    assert list(temporary.iterdir()) == []
