"""Keypoint numbers drawn into images: a small built-in digit font at the projected keypoint positions."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from kpd.viewer.camera import Camera, look_at_matrix, perspective_matrix, project
from kpd.viewer.settings import keypoint_palette

__all__ = ["overlay_labels", "label_image_at"]

_DIGITS = {
    "0": ["01110", "10001", "10011", "10101", "11001", "10001", "01110"],
    "1": ["00100", "01100", "00100", "00100", "00100", "00100", "01110"],
    "2": ["01110", "10001", "00001", "00010", "00100", "01000", "11111"],
    "3": ["11110", "00001", "00001", "01110", "00001", "00001", "11110"],
    "4": ["00010", "00110", "01010", "10010", "11111", "00010", "00010"],
    "5": ["11111", "10000", "11110", "00001", "00001", "10001", "01110"],
    "6": ["00110", "01000", "10000", "11110", "10001", "10001", "01110"],
    "7": ["11111", "00001", "00010", "00100", "01000", "01000", "01000"],
    "8": ["01110", "10001", "10001", "01110", "10001", "10001", "01110"],
    "9": ["01110", "10001", "10001", "01111", "00001", "00010", "01100"],
}


_GLYPHS = {c: np.array([[ch == "1" for ch in row] for row in rows]) for c, rows in _DIGITS.items()}



def _text_mask(text: str, scale: int) -> np.ndarray:
    glyphs = [_GLYPHS[c] for c in text if c in _GLYPHS]
    if not glyphs:
        return np.zeros((7 * scale, 1), dtype=bool)
    spaced = []
    for g in glyphs:
        spaced += [g, np.zeros((7, 1), dtype=bool)]
    mask = np.hstack(spaced[:-1])
    return np.kron(mask, np.ones((scale, scale), dtype=bool))


def overlay_labels(image: np.ndarray, pixels: Any, labels: Sequence[str], colors: Any, *,
                   scale: int | None = None, visible: Any = None) -> np.ndarray:
    """Draw ``labels`` (digits) at ``pixels`` (N, 2) in ``colors`` (N, 3 in [0, 1]) with a white halo.

    Parameters
    ----------
    image : (H, W, 3) uint8 (modified copy returned).
    pixels : (N, 2) float, the label's lower-left corner (x right, y down).
    visible : (N,) bool, labels to draw (default all).
    """
    out = np.array(image, dtype=np.uint8, copy=True)
    h, w = out.shape[:2]
    scale = scale or max(2, int(round(h / 300)))
    pixels = np.asarray(pixels, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.float64)
    visible = np.ones(len(labels), dtype=bool) if visible is None else np.asarray(visible, dtype=bool)
    for text, (x, y), color, show in zip(labels, pixels, colors, visible):
        if not show or not np.isfinite([x, y]).all():
            continue
        mask = _text_mask(str(text), scale)
        mh, mw = mask.shape
        halo = np.zeros((mh + 2 * scale, mw + 2 * scale), dtype=bool)
        for dy in range(2 * scale + 1):
            for dx in range(2 * scale + 1):
                halo[dy:dy + mh, dx:dx + mw] |= mask
        x0, y0 = int(round(x)) - scale, int(round(y)) - mh - scale
        ink = np.clip(np.asarray(color) * 0.75 * 255, 0, 255).astype(np.uint8)
        for layer, value in ((halo, np.array([255, 255, 255], np.uint8)), (None, ink)):
            m = layer if layer is not None else np.pad(mask, scale)
            ys, xs = np.nonzero(m)
            ys, xs = ys + y0, xs + x0
            keep = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
            out[ys[keep], xs[keep]] = value
    return out


def label_image_at(image: np.ndarray, keypoints: Any, radius: float, camera: Camera) -> np.ndarray:
    """Keypoint numbers (in the keypoint palette) drawn beside markers of ``radius`` at ``keypoints`` (K, 3), as
    ``camera`` sees them: up and to the right of each marker on screen."""
    h, w = image.shape[:2]
    keypoints = np.asarray(keypoints, dtype=np.float64)
    view = look_at_matrix(camera)
    projection = perspective_matrix(camera.fov, w / h, camera.near, camera.far)
    pixels, depth = project(keypoints, view, projection, w, h)
    distance = np.linalg.norm(keypoints - camera.eye, axis=1)
    focal = h / 2 / math.tan(math.radians(camera.fov) / 2)
    r = focal * radius / np.maximum(distance, 1e-12)  # (K,) marker radius in pixels
    pixels = pixels + np.stack([1.1 * r, -0.9 * r], axis=1)
    labels = [str(i) for i in range(len(keypoints))]
    return overlay_labels(image, pixels, labels, keypoint_palette(len(keypoints)), visible=depth > 0)
