"""PNG: the one encoder every kpd picture and texture goes through, its completeness check, and reading.

:func:`encode_png` is plain zlib over the rows (filter 0), so any (H, W, C) uint8 image with C in 1-4 becomes a PNG
without a temporary file; :func:`write_png` writes one atomically; :func:`read_png` decodes through Open3D.
"""

from __future__ import annotations

import io
import logging
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from kpd.errors import InputError
from kpd.io.atomic import atomic_output, incomplete

__all__ = ["encode_png", "write_png", "read_png", "verify_png", "check_png", "read_image", "read_image_bytes",
           "decode_image"]

log = logging.getLogger("kpd.io")

_COLOR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> PNG colour type (grey, grey + alpha, RGB, RGBA)


def encode_png(image: Any) -> bytes:
    """PNG bytes of an (H, W), (H, W, C) uint8 image, C in 1 (grey), 2 (grey + alpha), 3 (RGB), 4 (RGBA)."""
    array = np.asarray(image)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] not in _COLOR_TYPES or 0 in array.shape:
        raise InputError(f"image must be (H, W, 1|2|3|4) uint8; got {array.shape} {array.dtype}")
    h, w, c = array.shape
    raw = np.zeros((h, 1 + w * c), dtype=np.uint8)  # one filter byte (0: none) before each row
    raw[:, 1:] = array.reshape(h, w * c)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, _COLOR_TYPES[c], 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
            + chunk(b"IEND", b""))


def write_png(path: str | os.PathLike, image: Any) -> Path:
    """Write an (H, W, 3) or (H, W, 4) uint8 image as PNG, atomically; returns the path."""
    array = np.asarray(image)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] not in (3, 4):
        raise InputError(f"image must be (H, W, 3|4) uint8; got {array.shape} {array.dtype}")
    data = encode_png(array)
    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return path


def read_png(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8 of a PNG file (through Open3D's reader)."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such image")
    image = np.asarray(o3d.io.read_image(str(path)))
    if image.ndim != 3 or image.shape[2] < 3:
        raise InputError(f"{path}: not an RGB image (shape {image.shape})")
    return image[:, :, :3].copy()


def check_png(p: Path, tmp: Path) -> None:
    """Raise :class:`~kpd.errors.WriteError` for ``p`` unless ``tmp`` is a PNG that ends with its IEND chunk (a file
    cut short by a full disk does not)."""
    with open(tmp, "rb") as fh:
        head = fh.read(8)
        fh.seek(max(0, tmp.stat().st_size - 12))
        tail = fh.read()
    if head != b"\x89PNG\r\n\x1a\n" or not tail.endswith(b"IEND\xaeB`\x82"):
        raise incomplete(p, "the PNG has no end chunk")


def verify_png(path: str | os.PathLike) -> None:
    """Raise :class:`~kpd.errors.WriteError` unless ``path`` is a complete PNG (use as
    ``atomic_output(..., verify=verify_png)``)."""
    check_png(Path(path), Path(path))


def decode_image(data: bytes) -> np.ndarray | None:
    """(H, W, C) uint8 (C in 1, 3, 4) of an image file's bytes (JPEG, PNG, ... through Pillow), as stored (top row
    first), or None when they do not decode. Pillow's bound on pixels refuses a small file of huge dimensions."""
    return _decoded(data)[0]


def _decoded(data: bytes) -> tuple[np.ndarray | None, Exception | None]:
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():  # an image between Pillow's bound and twice it decodes, without a word
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as image:
                if image.mode not in ("L", "RGB", "RGBA"):
                    image = image.convert("RGBA" if "A" in image.mode or "transparency" in image.info else "RGB")
                return np.array(image, dtype=np.uint8), None
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        return None, exc


def read_image_bytes(data: bytes, name: str) -> np.ndarray | None:
    """:func:`decode_image`, with a logged warning naming ``name`` when the bytes do not decode."""
    image, exc = _decoded(data)
    if image is None:
        log.warning("%s: the image cannot be read (%s); read without it", name, exc)
    return image


def read_image(path: str | os.PathLike) -> np.ndarray | None:
    """:func:`read_image_bytes` of a file."""
    return read_image_bytes(Path(path).read_bytes(), str(path))
