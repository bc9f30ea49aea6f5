"""Grouping rows by value: vertices that share a position, corners that share a vertex and a UV.

One home for the question "which rows are the same?", so that every module answers it alike. Rows are equal when
their values are equal as numbers: ``-0.0`` and ``0.0`` are one position (a mesh exporter writes either for a vertex
on a symmetry plane), and no two different finite values are ever merged. Rows must be finite (the mesh types check
that at the door).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["first_occurrence_groups", "merge_coincident", "Groups"]


class Groups(NamedTuple):
    """Distinct rows and, per input row, the index of its group."""

    first : np.ndarray  # (G,) int64, index of each group's first row
    index : np.ndarray  # (R,) int64, group of each row


def _row_keys(keys: np.ndarray) -> np.ndarray:
    """(R,) one opaque key per row; equal keys exactly when the rows are equal as numbers."""
    a = np.asarray(keys)
    if a.ndim == 1:
        a = a[:, None]
    if a.dtype.kind == "f":
        a = a + 0.0  # -0.0 + 0.0 is 0.0: one byte pattern for zero
    a = np.ascontiguousarray(a)
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()


def first_occurrence_groups(keys: np.ndarray) -> Groups:
    """Unique rows of ``keys`` in order of first occurrence.

    Parameters
    ----------
    keys : (R, D) or (R,) array, finite

    Returns
    -------
    Groups
        ``first`` (G,): the first row of each group, in the order the groups first occur; ``index`` (R,): the group
        of each row, so ``keys[first][index]`` equals ``keys`` (up to the sign of zeros).
    """
    rows = _row_keys(keys)
    if len(rows) == 0:
        return Groups(np.zeros(0, np.int64), np.zeros(0, np.int64))
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return Groups(first[order].astype(np.int64), rank[inverse.reshape(-1)].astype(np.int64))


def merge_coincident(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct positions in lexicographic order and, per vertex, the index of its position.

    Parameters
    ----------
    vertices : (V, 3) float64, finite

    Returns
    -------
    points : (n, 3) float64, the distinct positions (a zero is written as ``0.0``)
    inverse : (V,) int64, ``points[inverse]`` equals ``vertices`` as numbers
    """
    vertices = np.asarray(vertices, dtype=np.float64) + 0.0
    order = np.lexsort(vertices.T[::-1])
    ordered = vertices[order]
    new = np.ones(len(vertices), dtype=bool)
    new[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    inverse = np.empty(len(vertices), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return ordered[new], inverse
