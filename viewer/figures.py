"""Figures of kpd's results: a scan's orientation, an aligned collection, an alignment evaluation.

The library computes (:mod:`kpd.scan`, :mod:`kpd.collection`, :mod:`kpd.train.evaluate`); these functions draw what it
computed, through the editor's OpenGL path (:func:`kpd.viewer.pictures.point_panels`, lit point splats), so the core
never imports the viewer. Each writes one PNG at the path it is given (use :class:`kpd.io.Outputs` or
:func:`kpd.io.atomic_output` around it).
"""

from __future__ import annotations

import os
from typing import Any, Sequence

import numpy as np

from kpd.collection import rms_unit
from kpd.errors import InputError
from kpd.geometry import Normalizer, as_points, as_rng
from kpd.scan import parse_axis
from kpd.viewer.pictures import point_panels

__all__ = ["alignment_picture", "contact_sheet", "alignment_gallery"]


def alignment_picture(result: Any, reference: Any, path: Any, *, up: Any = "z",
                      max_points: int = 4000, seed: int = 0) -> None:
    """Draw the scan as given, then over the reference (grey) as the best and as the runner-up rotation, to a PNG.

    Both rotated scans are shown in the reference's [-1, 1] box with the reference's ``up`` axis vertical, so a wrong
    or ambiguous orientation is seen at a glance (a chair upside down, a shoe back to front).

    Parameters
    ----------
    result : :func:`kpd.scan.preprocess`'s result (with an orientation); the scan is drawn as cleaned, in its own units.
    reference : (M, 3) points in the model's frame.
    path : the PNG to write (written as given; use :func:`kpd.io.atomic_output` around it).
    """
    if result.orientation is None:
        raise InputError("no orientation to draw: preprocess was given no reference")
    rng = as_rng(seed)

    def thin(points: np.ndarray) -> np.ndarray:
        return points if len(points) <= max_points else points[rng.choice(len(points), max_points, replace=False)]

    points = result.to_original(result.points)
    mesh = result.shape if hasattr(result.shape, "triangles") and len(result.shape.triangles) else None
    ref = thin(Normalizer().fit(as_points(reference, "reference")).apply(as_points(reference, "reference")))
    up_axis = parse_axis(up, "up")
    vertical = int(np.argmax(np.abs(up_axis)))
    up_name = ("+" if up_axis[vertical] > 0 else "-") + "xyz"[vertical]

    def shown(rotation: np.ndarray | None) -> dict:
        """The scan (its mesh when it has one) turned by ``rotation`` into the reference's box."""
        orange = (0.93, 0.55, 0.25)
        if rotation is None:  # the mesh's vertices are the scan's points
            return {"mesh": mesh.with_vertices(points), "tint": orange} if mesh is not None else {
                "points": thin(points), "tint": orange}
        turned = points @ rotation.T
        normalizer = Normalizer().fit(turned)
        if mesh is not None:
            return {"mesh": mesh.with_vertices(normalizer.apply(turned)), "tint": orange}
        return {"points": thin(normalizer.apply(turned)), "tint": orange}

    o = result.orientation
    panels = [{"title": "the scan as given", **shown(None)}]
    panels.append({"title": f"best: score {o.score:.4f}", "behind": ref, **shown(o.rotation)})
    if o.runner_up_rotation is not None:
        flag = "  AMBIGUOUS" if o.ambiguous else ""
        panels.append({"title": f"runner-up, {o.runner_up_angle:.0f} deg away: score {o.runner_up_score:.4f}\n"
                                f"margin {o.margin:.3f}{flag}", "behind": ref,
                       "color": (200, 20, 20) if o.ambiguous else (20, 20, 20), **shown(o.runner_up_rotation)})
    point_panels(panels, path, up=up_name, cell=4.2, columns=len(panels),
                 title="kpd scan: the scan (orange) turned into the reference's frame; grey points: the reference")




def contact_sheet(clouds: Sequence[np.ndarray], alignment: Any, path: Any, *, up: Any = None,
                  columns: int = 12, max_points: int = 1500, seed: int = 0, title: str | None = None,
                  cell: float = 1.6) -> None:
    """Draw every shape turned into the shared frame, side by side, to a PNG (flagged ones captioned in red).

    Every cell shows its shape from one camera (kpd.viewer.pictures.point_panels, lit splats): the template's
    longest principal axis across the picture and ``up`` (if given; else the template's middle principal axis)
    upwards, so a shape turned back to front or upside down stands out among the others.
    """
    rng = as_rng(seed)
    template = next((i for i, s in enumerate(alignment.shapes) if s.template), 0)
    ref = rms_unit(clouds[template] @ alignment.rotations[template].T)
    if up is not None:  # vertical: up; horizontal: the template's longest direction across it
        vertical = parse_axis(up)
        flat = ref - np.outer(ref @ vertical, vertical)
        horizontal = np.linalg.eigh(flat.T @ flat)[1][:, -1]
    else:  # the template's principal axes: longest horizontal, middle vertical
        basis = np.linalg.eigh(ref.T @ ref)[1]
        horizontal, vertical = basis[:, 2], basis[:, 1]
    depth = np.cross(horizontal, vertical)
    view = np.stack([horizontal, vertical, depth])  # (3, 3) rows: picture x, picture y (up), depth
    panels = []
    for i, shape in enumerate(alignment.shapes):
        cloud = clouds[i]
        if len(cloud) > max_points:
            cloud = cloud[rng.choice(len(cloud), max_points, replace=False)]
        label = shape.name if len(shape.name) <= 16 else shape.name[:15] + "…"
        panels.append({"points": rms_unit(cloud @ alignment.rotations[i].T) @ view.T,
                       "title": ("* " if shape.template else "") + label,
                       "color": (200, 20, 20) if shape.ambiguous else (20, 20, 20)})
    count = len(panels)
    point_panels(panels, path, up="y", cell=cell, columns=max(1, min(columns, count)), shared_camera=True,
                 title=title or f"{count} shapes in the shared frame ({int(alignment.ambiguous.sum())} flagged "
                                f"ambiguous, in red; * the template)")


def alignment_gallery(path: str | os.PathLike, sources: np.ndarray, targets: np.ndarray, deformed: dict,
                      keypoints: dict, *, titles: list[str], scores: dict, up: str = "z") -> None:
    """PNG grid, one row per pair: source with its keypoints, each method's deformed source, target with keypoints,
    drawn as lit point splats by the editor's OpenGL path (:func:`kpd.viewer.pictures.point_panels`).

    sources, targets : (P, N, 3); deformed : name -> (P, N, 3); keypoints : name -> ((P, K, 3), (P, K, 3)).
    up : the data's up axis (ModelNet: z).
    """
    names = list(deformed)
    first = names[0]
    blue, green, red = (0.45, 0.6, 0.9), (0.45, 0.78, 0.5), (0.92, 0.5, 0.45)
    panels = []
    for i in range(len(sources)):
        panels.append({"points": sources[i], "keypoints": keypoints[first][0][i], "tint": blue,
                       "title": f"source {titles[i]}"})
        for name in names:
            panels.append({"points": deformed[name][i], "tint": green, "title": f"{name}: {scores[name][i]:.2f}"})
        panels.append({"points": targets[i], "keypoints": keypoints[first][1][i], "tint": red,
                       "title": f"target (undeformed {scores['no_deformation'][i]:.2f})"})
    point_panels(panels, path, up=up, cell=2.6, columns=2 + len(names), shared_camera=True,
                 title="alignment chamfer x10^3: source (blue), deformed to the target (green), target (red)")
