"""The one settings object of the editor and the pictures, the scene state a frame shows, the keypoint palette."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from kpd.errors import InputError

__all__ = ["ViewSettings", "Frame", "up_axis", "front_axis", "keypoint_palette", "cage_edges"]

# The first twelve keypoint colours are picked by hand to be saturated and far apart (and far from the grey of an
# uncoloured mesh and from a white or black background); more keypoints get golden-angle hues.
_PALETTE = np.array([
    [0.90, 0.10, 0.10], [0.10, 0.35, 0.95], [0.10, 0.70, 0.20], [1.00, 0.55, 0.00], [0.60, 0.15, 0.85],
    [0.00, 0.75, 0.85], [0.95, 0.20, 0.70], [0.80, 0.75, 0.00], [0.55, 0.30, 0.10], [0.00, 0.50, 0.45],
    [0.35, 0.90, 0.10], [0.15, 0.15, 0.55],
])


_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class ViewSettings:
    """How a rig is drawn: the one settings object of the editor and of :func:`render_rig`.

    Sizes are relative to the rest mesh's bounding-box diagonal, so they suit shapes in any units.
    """

    width: int = 960
    height: int = 720
    show_keypoints: bool = True
    show_labels: bool = True
    show_cage: bool = False
    show_ghost: bool = False
    xray: bool = False  # the mesh see-through, so keypoints inside it stay visible
    keypoint_size: float = 0.018  # marker radius / diagonal
    up: str = "+z"  # the shape's up axis: +x, -x, +y, -y, +z or -z
    # the axis the camera looks from at azimuth 0 (perpendicular to ``up``); None: :func:`front_axis` of ``up``
    front: str | None = None
    azimuth: float = 30.0  # degrees around the up axis, from the front view
    elevation: float = 20.0  # degrees above the horizontal
    fov: float = 35.0  # vertical field of view, degrees
    zoom: float = 1.0  # > 1 moves the camera closer
    background: tuple = (1.0, 1.0, 1.0)
    mesh_color: tuple = (0.80, 0.80, 0.82)  # used when the mesh has neither colours nor a texture
    ghost_color: tuple = (0.30, 0.50, 0.95, 0.22)
    cage_color: tuple = (0.95, 0.45, 0.05)
    prior: bool = False  # editor: moving keypoints moves the others as the category prior says
    nudge_step: float = 0.01  # editor: arrow-key step / diagonal

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 16 <= value <= 8192:
                raise InputError(f"{name} must be an integer in [16, 8192]; got {value!r}")
        up = up_axis(self.up)
        if self.front is not None and abs(float(up_axis(self.front) @ up)) > 1e-9:
            raise InputError(f"front must be an axis across up ({self.up}); got {self.front!r}")
        for name in ("keypoint_size", "fov", "zoom", "nudge_step"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number; got {value!r}")
        if not self.fov < 170:
            raise InputError(f"fov must be below 170 degrees; got {self.fov}")

    def replace(self, **changes: Any) -> "ViewSettings":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ViewSettings":
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items() if k in known}
        return cls(**values)


def up_axis(up: str) -> np.ndarray:
    """(3,) unit vector of ``"+z"``, ``"-y"``, ``"x"``..."""
    text = str(up).strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    name = text.lstrip("+-")
    if name not in _AXES:
        raise InputError(f"up must be one of x, y, z with an optional sign (+z, -y...); got {up!r}")
    axis = np.zeros(3)
    axis[_AXES[name]] = sign
    return axis


def front_axis(up: str) -> np.ndarray:
    """(3,) unit vector: where the camera stands at azimuth 0 for a shape with ``up``, the axis that a glTF file
    written with that up axis (:func:`kpd.morph.up_rotation`) turns to glTF's +Z, the front of a glTF asset. So the
    pictures, the window editor and the browser page (which shows the glTF file) see the same side at the same
    azimuth: -y for z up (a ModelNet chair's front, its back toward +y), +z for y up."""
    u = up_axis(up)
    if u[1] != 0:
        return np.array([0.0, 0.0, u[1]])  # no turn (+y) or half a turn about x (-y)
    # a quarter turn about k = u x Y takes u to +Y; the axis it takes to +Z is Z turned back: R^T Z = k x Z + k (k.Z)
    k = np.cross(u, [0.0, 1.0, 0.0])
    z = np.array([0.0, 0.0, 1.0])
    return -np.cross(k, z) + k * (k @ z)


def keypoint_palette(k: int) -> np.ndarray:
    """(K, 3) float64 in [0, 1]: a distinct colour per keypoint."""
    if k <= len(_PALETTE):
        return _PALETTE[:k].copy()
    extra = []
    for i in range(k - len(_PALETTE)):
        hue = (0.13 + i * 0.618033988749895) % 1.0
        extra.append(_hsv(hue, 0.85, 0.9))
    return np.vstack([_PALETTE, np.array(extra)])


def _hsv(h: float, s: float, v: float) -> list[float]:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


@dataclass
class Frame:
    """What changes while editing: the mesh vertices, the keypoints, the cage, the selection (user units)."""

    vertices: np.ndarray  # (V, 3)
    keypoints: np.ndarray  # (K, 3)
    cage: np.ndarray | None = None  # (C, 3)
    selection: tuple = ()


def cage_edges(faces: Any) -> np.ndarray:
    """(E, 2) int64 unique undirected edges of triangles (F, 3)."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)
