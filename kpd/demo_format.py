"""The authors' project-page demo format: a rig as text tables in one folder (docs/method.md §17)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kpd.cage import Cage, cage_faces_from_vertices
from kpd.errors import InputError
from kpd.io import Mesh
from kpd.mvc import mvc_weights

__all__ = ["DemoRig", "read_demo"]


class DemoRig(NamedTuple):
    """A rig as the demo files hold it, everything in the model frame.

    mesh : Mesh, the source shape (vertices (V, 3), triangles (T, 3)).
    keypoints : (K, 3) float64.
    cage : Cage, vertices (C, 3), its triangles recovered from the vertex directions.
    influence : (K, C) float64, masked.
    weights : (V, C) float64, the MVC weights (computed when the folder has none).
    """

    mesh: Mesh
    keypoints: np.ndarray
    cage: Cage
    influence: np.ndarray
    weights: np.ndarray


def read_demo(directory: str | os.PathLike) -> DemoRig:
    """Read a rig in the authors' project-page demo format (docs/method.md §17).

    Reads ``source_vertices.txt`` (V × 3), ``source_faces.txt`` (T × 3), ``source_keypoints.txt`` (K lines
    ``%03d x y z``), ``cage.txt`` (C × 3), ``influence.txt`` (K × C, masked) and, when present, ``weights.txt``
    (V × C); missing weights are computed. The cage's triangles are recovered from its vertex directions.

    Raises
    ------
    InputError
        For a missing folder or file, or a table that is not numbers of the expected shape, with the file's name.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"{directory}: not a folder of demo files")
    vertices = _read_table(directory / "source_vertices.txt", 3)
    faces = _read_table(directory / "source_faces.txt", 3)
    if not np.allclose(faces, np.round(faces)):
        raise InputError(f"{directory / 'source_faces.txt'}: face indices must be integers")
    triangles = np.round(faces).astype(np.int64)
    keypoints = _read_table(directory / "source_keypoints.txt", None)
    if keypoints.shape[1] == 4:
        keypoints = keypoints[:, 1:]
    if keypoints.shape[1] != 3:
        raise InputError(f"{directory / 'source_keypoints.txt'}: rows must be 'x y z' or 'index x y z'")
    cage_vertices = _read_table(directory / "cage.txt", 3)
    influence = _read_table(directory / "influence.txt", len(cage_vertices))
    mesh = Mesh(vertices=vertices, triangles=triangles)
    _check_faces(triangles, len(vertices), directory / "source_faces.txt")
    cage = Cage(cage_vertices, cage_faces_from_vertices(cage_vertices))
    weights_file = directory / "weights.txt"
    if weights_file.exists():
        weights = _read_table(weights_file, len(cage_vertices))
    else:
        weights = mvc_weights(vertices, cage.vertices, cage.faces)
    return DemoRig(mesh, keypoints, cage, influence, weights)


def _read_table(path: Path, columns: int | None) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: missing demo file")
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise InputError(f"{path}: not a table of numbers: {exc}") from exc
    if table.size == 0:
        raise InputError(f"{path}: empty")
    if columns is not None and table.shape[1] != columns:
        raise InputError(f"{path}: rows must have {columns} numbers; got {table.shape[1]}")
    if not np.isfinite(table).all():
        raise InputError(f"{path}: contains NaN or inf")
    return table


def _check_faces(triangles: np.ndarray, count: int, where: Path) -> None:
    if triangles.min() < 0 or triangles.max() >= count:
        raise InputError(f"{where}: face indices must lie in [0, {count}); got [{triangles.min()}, {triangles.max()}]")
