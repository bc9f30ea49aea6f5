"""Keypoint files: ``.json`` (``{"keypoints": [[x, y, z], ...], ...}`` or a bare list) and ``.txt`` (rows ``x y z``
or the authors' ``%03d x y z``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from kpd.errors import InputError
from kpd.io.atomic import atomic_output
from kpd.io.common import KEYPOINT_FORMATS, input_path, output_path, read_table
from kpd.mesh import _vertex_array

__all__ = ["write_keypoints", "read_keypoints"]


def write_keypoints(path: str | os.PathLike, keypoints: Any, **meta: Any) -> None:
    """Write keypoints atomically.

    Parameters
    ----------
    path : ``.json`` -> ``{"keypoints": [[x, y, z], ...], **meta}``; ``.txt`` -> the authors' rows ``%03d x y z``
        (no metadata).
    keypoints : (K, 3) array-like
    **meta : JSON-serialisable values (numpy arrays and scalars are converted), stored beside the keypoints.
    """
    p = output_path(path, KEYPOINT_FORMATS, "keypoint")
    k = _vertex_array(keypoints, f"{p}: ", "keypoints", "keypoints")
    if p.suffix.lower() == ".txt":
        if meta:
            raise InputError(f"{p}: .txt keypoints cannot hold metadata ({', '.join(meta)}); use .json")
        text = "".join(f"{i:03d} {x!r} {y!r} {z!r}\n" for i, (x, y, z) in enumerate(k.tolist()))
    else:
        if "keypoints" in meta:
            raise InputError(f"{p}: 'keypoints' cannot also be a metadata key")
        try:
            text = json.dumps({"keypoints": k.tolist(), **meta}, indent=2, default=_json_default, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{p}: metadata is not JSON-serialisable ({exc})") from exc
    with atomic_output(p) as target:
        target.write_text(text + ("" if text.endswith("\n") else "\n"), encoding="utf-8")


def read_keypoints(path: str | os.PathLike) -> np.ndarray:
    """Read keypoints.

    Parameters
    ----------
    path : ``.json`` (``{"keypoints": [[x, y, z], ...], ...}`` or a bare list of triples) or ``.txt`` (rows
        ``x y z`` or ``%03d x y z``)

    Returns
    -------
    keypoints : (K, 3) float64
    """
    p, ext = input_path(path, KEYPOINT_FORMATS, "keypoint")
    if ext == ".txt":
        table = read_table(p)
        if table.shape[1] == 4:
            index = table[:, 0]
            if not np.array_equal(index, np.arange(len(table))):
                raise InputError(f"{p}: the first of 4 columns must count 0, 1, 2, ... (format '%03d x y z')")
            table = table[:, 1:]
        elif table.shape[1] != 3:
            raise InputError(f"{p}: rows must be 'x y z' or '%03d x y z'; got {table.shape[1]} columns")
        return _vertex_array(table, f"{p}: ", "keypoints", "keypoints")
    try:
        # whole numbers as floats: one of 400 digits is inf (refused as not finite), not an int numpy cannot convert
        data = json.loads(p.read_text(encoding="utf-8"), parse_int=float)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: not valid JSON ({exc})") from exc
    except RecursionError as exc:  # Python's JSON parser recurses once per nested list or object
        raise InputError(f"{p}: not keypoints: its JSON nests lists or objects too deeply") from exc
    if isinstance(data, dict):
        if "keypoints" not in data:
            raise InputError(f"{p}: expected the key 'keypoints'; found {sorted(data)}")
        data = data["keypoints"]
    return _vertex_array(data, f"{p}: ", "keypoints", "keypoints")


def _json_default(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"{type(x).__name__} is not JSON-serialisable")
