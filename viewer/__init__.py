"""The keypoint editor and headless rendering (installed as ``kpd.viewer``).

* :class:`~kpd.viewer.session.EditSession` -- keypoint positions, undo/redo, JSON sessions (numpy only).
* :func:`~kpd.viewer.render.render_rig` -- draw a rig (mesh, keypoints with their numbers, optionally the cage
  and the rest shape as a ghost) to an image without a window; :class:`~kpd.viewer.render.ViewSettings` is the one
  settings object shared with the editor.
* :class:`~kpd.viewer.app.EditorApp` -- the Open3D window: pick keypoints, drag them, watch the mesh deform live.

Importing this package is light: Open3D (and its GUI module) load only when a renderer or the editor is used, and
torch is never imported.
"""

from __future__ import annotations

import importlib
from typing import Any

from kpd.viewer.session import EditSession, component_offsets, propose

__all__ = ["EditSession", "propose", "component_offsets", "ViewSettings", "render_rig", "write_png", "EditorApp"]

_LAZY = {
    "ViewSettings": "kpd.viewer.render",
    "render_rig": "kpd.viewer.render",
    "write_png": "kpd.viewer.render",
    "EditorApp": "kpd.viewer.app",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'kpd.viewer' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
