"""A collection on disk: the shape files of a folder and the surface points each is aligned by."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from kpd.errors import DataError, InputError
from kpd.geometry import as_points, as_rng, sample_surface

__all__ = ["find_shapes", "collection_points"]

log = logging.getLogger("kpd.collection")


def find_shapes(folder: str | os.PathLike) -> list[tuple[str, Path]]:
    """The shapes of a collection folder: mesh or point files in it (named by their stem) and sub-folders holding
    exactly one such file (named by the sub-folder, as ``gso_shoes/<name>/model.obj``), sorted by name.

    Returns
    -------
    shapes : list of (name, path); DataError when there are none or two share a name.
    """
    from kpd.io import MESH_FORMATS, POINT_FORMATS

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    suffixes = set(MESH_FORMATS) | set(POINT_FORMATS)

    def shape_files(where: Path) -> list[Path]:
        return sorted(p for p in where.iterdir() if p.is_file() and p.suffix.lower() in suffixes
                      and not p.name.startswith("."))

    found: dict[str, Path] = {}
    for path in shape_files(folder):
        found.setdefault(path.stem, path)
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        files = shape_files(sub)
        if len(files) == 1:
            if sub.name in found:
                raise DataError(f"{folder}: two shapes are named {sub.name!r} ({found[sub.name]} and {files[0]})")
            found[sub.name] = files[0]
    if not found:
        raise DataError(f"no shapes (mesh or point files, or sub-folders with one each) in {folder}")
    return sorted(found.items())


def collection_points(shape: Any, n: int = 5000, *, seed: int = 0, outer: bool = True) -> np.ndarray:
    """(n, 3) float64 points a shape is aligned by: area-weighted surface samples of a mesh (its outer surface by
    default, :func:`kpd.geometry.sample_surface`), or at most ``n`` of a point set's points."""
    triangles = np.asarray(getattr(shape, "triangles", np.zeros((0, 3))))
    if hasattr(shape, "vertices") and len(triangles):
        return sample_surface(shape.vertices, triangles, n, seed=seed, outer=outer).points
    points = as_points(shape.points if hasattr(shape, "points") else shape, "shape", min_count=10)
    if len(points) > n:
        points = points[np.sort(as_rng(seed).choice(len(points), n, replace=False))]
    return points
