"""Open3D without its plotly/dash helpers at import time.

``import open3d`` imports ``open3d.visualization.draw_plotly``, which imports dash and plotly: a large part of
every kpd command's start (``python -X importtime -c "import open3d"``), for functions kpd never calls.
:func:`defer_plotly_helpers` puts a stand-in for that one module in ``sys.modules`` before Open3D is imported;
its three functions import the real module on first call, so Open3D behaves as before for anyone who uses them.
"""

from __future__ import annotations

import importlib
import sys
import types

_NAME = "open3d.visualization.draw_plotly"
_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _forward(attr: str):
    def call(*args, **kwargs):
        if getattr(sys.modules.get(_NAME), "_kpd_stand_in", False):
            del sys.modules[_NAME]
        return getattr(importlib.import_module(_NAME), attr)(*args, **kwargs)

    call.__name__ = attr
    return call


def defer_plotly_helpers() -> None:
    """Install the stand-in unless Open3D (or the real module) is already imported."""
    if _NAME in sys.modules or "open3d" in sys.modules:
        return
    stand_in = types.ModuleType(_NAME, "stand-in until first use (see kpd._open3d)")
    stand_in._kpd_stand_in = True
    for attr in _FUNCTIONS:
        setattr(stand_in, attr, _forward(attr))
    sys.modules[_NAME] = stand_in
