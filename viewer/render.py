"""Draw a rig -- its (deformed) mesh with its own colours or texture, the keypoints as coloured markers with their
numbers, optionally the cage as a wireframe and the rest shape as a ghost -- to an image, without a window.

:func:`render_rig` and :func:`render_frames` draw through the editor's OpenGL path (:mod:`kpd.viewer.gl`), in one of
:data:`BACKENDS` (:mod:`kpd.viewer.display`): ``egl`` (what ``auto`` means) in a headless EGL context in this
process (no X server, first frame about 0.2 s after start, tens of milliseconds a frame with Mesa's software
rasteriser), ``xvfb`` in a hidden window on a private Xvfb server, ``window`` on the current ``$DISPLAY``. Keypoint
numbers are drawn into the image after rendering (:mod:`kpd.viewer.labels`); the editor shows them as camera-facing
digits in the 3D view instead.

The settings, the camera, the labels, the displays and PNG files live in their own modules
(:mod:`kpd.viewer.settings`, :mod:`kpd.viewer.camera`, :mod:`kpd.viewer.labels`, :mod:`kpd.viewer.display`,
:mod:`kpd.io.images`); their names stay importable from here.
"""

from __future__ import annotations

import logging
from typing import Any, Sequence

import numpy as np

from kpd.errors import InputError
from kpd.io.images import read_png, write_png
from kpd.viewer.camera import (Camera, camera_pose, look_at_matrix, perspective_matrix, pixel_ray, plane_hit,
                               project)
from kpd.viewer.display import BACKENDS, gl_display, grab_screen, private_display, resolve_backend
from kpd.viewer.labels import label_image_at, overlay_labels
from kpd.viewer.settings import Frame, ViewSettings, cage_edges, keypoint_palette, up_axis

__all__ = [
    "ViewSettings", "Frame", "render_rig", "render_frames", "write_png", "read_png", "keypoint_palette",
    "camera_pose", "project", "pixel_ray", "overlay_labels", "BACKENDS", "private_display", "grab_screen",
    "Camera", "look_at_matrix", "perspective_matrix", "plane_hit", "up_axis", "cage_edges", "label_image_at",
    "gl_display", "resolve_backend",
]

log = logging.getLogger(__name__)


def _rig_frames(rig: Any, keypoint_sets: Sequence[Any], selections: Sequence[Sequence[int]] | None) -> list[Frame]:
    frames = []
    for i, keypoints in enumerate(keypoint_sets):
        keypoints = np.asarray(keypoints, dtype=np.float64)
        selection = tuple(selections[i]) if selections is not None else ()
        frames.append(Frame(rig.deform(keypoints), keypoints, rig.deform_cage(keypoints), selection))
    return frames


def render_rig(rig: Any, keypoints: Any = None, *, settings: ViewSettings | None = None, selection: Sequence[int] = (),
               backend: str = "auto", timeout: float = 300.0, shaded: Any = None) -> np.ndarray:
    """Draw a rig with its keypoints at ``keypoints`` (default: rest) without opening a window.

    Parameters
    ----------
    rig : kpd.rig.Rig.
    keypoints : (K, 3) float64 in the rig's units, or None for the rest keypoints.
    settings : ViewSettings (size, camera, what to show).
    selection : keypoint indices drawn as selected.
    backend : one of :data:`BACKENDS` (see the module notes).
    timeout : seconds to wait for a window backend's child process.
    shaded : ``kpd.viewer.shaded.ShadedMesh(rig.mesh, settings.mesh_color)`` made beforehand (``kpd render`` makes it on
        a thread while the mesh is bound), or None.

    Returns
    -------
    image : (H, W, 3) uint8.
    """
    keypoints = rig.keypoints if keypoints is None else keypoints
    return render_frames(rig, [keypoints], settings=settings, selections=[selection], backend=backend,
                         timeout=timeout, shaded=shaded)[0]


def render_frames(rig: Any, keypoint_sets: Sequence[Any], *, settings: ViewSettings | None = None,
                  selections: Sequence[Sequence[int]] | None = None, backend: str = "auto",
                  timeout: float = 300.0, shaded: Any = None) -> list[np.ndarray]:
    """:func:`render_rig` of several keypoint sets with one renderer (a gallery of edits): a list of (H, W, 3).

    One camera frames every frame's deformed shape (and its keypoints), so edits that grow the shape stay in view and
    the frames compare on one scale.
    """
    settings = settings or ViewSettings()
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    k = rig.num_keypoints
    for keypoints in keypoint_sets:
        shape = np.shape(keypoints)
        if shape != (k, 3):
            raise InputError(f"keypoints must have shape ({k}, 3) for this rig; got {shape}")
    frames = _rig_frames(rig, keypoint_sets, selections)
    backend = resolve_backend(backend)
    framed = [f.vertices for f in frames] + [f.keypoints for f in frames]  # every frame's shape and keypoints
    camera = camera_pose(framed, settings)
    log.info("rendering %d frame(s) of %dx%d with the %s backend", len(frames), settings.width, settings.height,
             backend)
    with gl_display(backend, settings.width, settings.height):
        return _render_gl(rig, frames, settings, camera, on_display=backend != "egl", shaded=shaded)


def _render_gl(rig: Any, frames: list[Frame], settings: ViewSettings, camera: Camera, *,
               on_display: bool = False, shaded: Any = None) -> list[np.ndarray]:
    from kpd.viewer.glview import GLView
    from kpd.viewer.rigdrawing import RigDrawing
    from kpd.viewer.shaded import ShadedMesh

    if shaded is None:  # each picture drawn once
        shaded = ShadedMesh(rig.mesh, settings.mesh_color, once=True)
    view = GLView(settings.width, settings.height, background=settings.background, on_display=on_display)
    try:
        drawing = RigDrawing(view, rig.mesh, rig.num_keypoints, rig.cage.faces, settings=settings, digits=False,
                             shaded=shaded)
        view.set_box([f.vertices for f in frames] + [f.keypoints for f in frames])
        images = []
        for frame in frames:
            drawing.show(frame, camera, capture=True)
            image = view.capture()
            if settings.show_labels and settings.show_keypoints:
                image = label_image_at(image, frame.keypoints, drawing.marker_radius, camera)
            images.append(image)
        return images
    finally:
        view.close()
