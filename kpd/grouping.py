"""Grouping rows by value: vertices that share a position, corners that share a vertex and a UV.

One home for the question "which rows are the same?", so that every module answers it alike. Rows are equal when
their values are equal as numbers: ``-0.0`` and ``0.0`` are one position (a mesh exporter writes either for a vertex
on a symmetry plane), and no two different finite values are ever merged. Rows must be finite (the mesh types check
that at the door).

Positions go through a hash table of their bits (:func:`coincident_first`), integer keys not much larger than their
number (the vertices of a mesh's corners) through a table indexed by the key (:func:`_direct_groups`), a corner's
vertex and UV through a table of each vertex's groups (:func:`vertex_value_groups`); other keys through a sort of
their bytes (:func:`_sorted_groups`), the reference the others are tested against. The tables cost a pass over the
rows where a sort grows faster than the rows, which matters for the millions of corners of a dense scan.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kpd._compiled import compiled_on_first_call

__all__ = ["coincident_first", "first_occurrence_groups", "merge_coincident", "same_corners", "vertex_value_groups",
           "Groups"]

_KEY_LIMIT = 2**63 - 1  # the largest int64: rank keys of more distinct combinations fall back to a lexicographic sort


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

    Positions, (R, 3) float64 or float32, go through :func:`coincident_first`'s hash table, and so do (R, 1) and
    (R, 2) float rows (UVs) of at least ``_DIRECT_ROWS`` rows, padded with zeros (several times faster than the
    sort); integer keys, (R,) or (R, 1), of at least ``_DIRECT_ROWS`` rows
    whose values lie in [0, 4 R + 1024) through a table indexed by the value (:func:`_direct_groups`); as many
    float rows of more than three columns (positions and normals) by their first three's groups, then the rest
    within each (:func:`vertex_value_groups`); other keys through a sort (:func:`_sorted_groups`). The same groups
    either way.
    """
    a = np.asarray(keys)
    if a.ndim == 2 and a.shape[1] in (1, 2) and a.dtype in (np.float64, np.float32) and len(a) >= _DIRECT_ROWS:
        a = np.hstack([a, np.zeros((len(a), 3 - a.shape[1]), a.dtype)])  # UVs: rows of three, the same groups
    if a.ndim == 2 and a.shape[1] == 3 and a.dtype in (np.float64, np.float32) and len(a):
        same = coincident_first(a)  # (R,) the first row at each row's position
        starts = same == np.arange(len(same))
        rank = np.cumsum(starts) - 1  # (R,) each first row's group, in order of first occurrence
        return Groups(np.flatnonzero(starts), rank[same])
    if a.ndim == 2 and a.shape[1] > 3 and a.dtype.kind == "f" and len(a) >= _DIRECT_ROWS:
        # positions and more (a normal): the positions' groups, then each one's distinct rest
        position = first_occurrence_groups(a[:, :3]).index
        first, index, done = _vertex_value_groups(position, np.ascontiguousarray(a[:, 3:], dtype=np.float64),
                                                  len(a), 16 * len(a) + 4096)
        if done:
            return Groups(first, index)
    one_integer = a.dtype.kind in "iu" and a.dtype.isnative and a.ndim in (1, 2) and a.size == len(a)  # per row
    if one_integer and len(a) >= _DIRECT_ROWS:
        column = a.reshape(-1)
        top = int(column.max()) + 1
        if column.min() >= 0 and top <= _direct_bound(len(column)):
            return Groups(*_direct_groups(column, top))
    return _sorted_groups(keys)


_DIRECT_ROWS = 1 << 16  # fewer integer keys are sorted: numba's import costs more than their sort


def _direct_bound(rows: int) -> int:
    """One more than the largest integer key :func:`first_occurrence_groups` groups through a table for ``rows``
    keys: the table holds 8 bytes per value up to the largest, at most 32 per key and 8 KiB more."""
    return 4 * rows + 1024


@compiled_on_first_call
def _direct_groups(keys, top):  # pragma: no cover - compiled
    """:func:`first_occurrence_groups` of (R,) integer keys in [0, top): one pass, each key's group found in a table
    of ``top`` slots indexed by the key. Returns ``first`` (G,) int64 and ``index`` (R,) int64."""
    group_of = np.full(top, -1, dtype=np.int64)
    first = np.empty(len(keys), dtype=np.int64)
    index = np.empty(len(keys), dtype=np.int64)
    groups = 0
    for i in range(len(keys)):
        key = keys[i]
        group = group_of[key]
        if group < 0:
            group = groups
            group_of[key] = group
            first[group] = i
            groups += 1
        index[i] = group
    return first[:groups].copy(), index


def vertex_value_groups(vertex: np.ndarray, values: np.ndarray) -> Groups:
    """:func:`first_occurrence_groups` of the rows ``(vertex[i], *values[i])`` (corners that share a vertex and a
    UV), without building those rows: each row is compared with the groups of its own vertex, found through a table
    indexed by the vertex (:func:`_vertex_value_groups`).

    Parameters
    ----------
    vertex : (R,) integer, non-negative
    values : (R, D) float64, finite

    Returns
    -------
    Groups
        Equal to ``first_occurrence_groups(np.hstack([vertex[:, None], values]))``.

    A vertex's groups are searched one by one, quick while each vertex has a few distinct values (a pole where n
    triangles meet, each with its own UV, costs n² / 2 comparisons): past 16 comparisons a row on average the
    search stops, and the rows go through :func:`first_occurrence_groups`, as do vertex numbers of 4 R + 1024 or more
    (:func:`_direct_bound`).
    """
    vertex = np.asarray(vertex)
    values = np.asarray(values, dtype=np.float64)
    if len(vertex) and vertex.dtype.kind in "iu" and vertex.dtype.isnative:
        top = int(vertex.max()) + 1
        if vertex.min() >= 0 and top <= _direct_bound(len(vertex)):
            first, index, done = _vertex_value_groups(vertex, values, top, 16 * len(vertex) + 4096)
            if done:
                return Groups(first, index)
    return first_occurrence_groups(np.hstack([vertex[:, None], values]))


@compiled_on_first_call
def _vertex_value_groups(vertex, values, top, budget):  # pragma: no cover - compiled
    """:func:`vertex_value_groups` of (R,) integer ``vertex`` in [0, top) and (R, D) ``values``: ``last[v]`` is the
    newest group of vertex v, ``older[g]`` the group of g's vertex made before g (-1: none); a row joins the first
    group of its vertex whose first row has its values, equal as numbers, else starts a group. Returns ``first``
    (G,) int64, ``index`` (R,) int64 and whether it finished within ``budget`` comparisons."""
    n, width = values.shape
    last = np.full(top, -1, dtype=np.int64)
    older = np.empty(n, dtype=np.int64)
    first = np.empty(n, dtype=np.int64)
    index = np.empty(n, dtype=np.int64)
    groups = 0
    for i in range(n):
        v = vertex[i]
        group = last[v]
        while group >= 0:
            budget -= 1
            if budget < 0:
                return first[:0].copy(), index[:0].copy(), False
            j = first[group]
            same = True
            for d in range(width):
                if values[j, d] != values[i, d]:
                    same = False
                    break
            if same:
                break
            group = older[group]
        if group < 0:
            group = groups
            first[group] = i
            older[group] = last[v]
            last[v] = group
            groups += 1
        index[i] = group
    return first[:groups].copy(), index, True


def _sorted_groups(keys: np.ndarray) -> Groups:
    """:func:`first_occurrence_groups` of any finite keys through ``np.unique`` of the rows' bytes (a sort): the
    general path, and the twin the tests compare the table and the hash table with."""
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

    The rows are sorted by x alone; the rows whose x another row shares (few in a scan, most in a CAD mesh) are then
    sorted by all three coordinates, through their ranks on each axis in one integer key. The same result as a
    lexicographic sort of every row (:func:`_merge_coincident_reference`), in a fifth of its time on a scan and
    about its time on a CAD mesh.

    Parameters
    ----------
    vertices : (V, 3) float64, finite

    Returns
    -------
    points : (n, 3) float64, the distinct positions (a zero is written as ``0.0``)
    inverse : (V,) int64, ``points[inverse]`` equals ``vertices`` as numbers
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    x, y, z = (vertices[:, axis] + 0.0 for axis in range(3))  # (V,) each, contiguous; -0.0 + 0.0 is 0.0
    order = np.argsort(x)  # (V,)
    tied = _tied(x, order)  # (P,) the places in that order whose x is not the only one
    if 2 * len(tied) > len(order):  # most rows share their x (a CAD mesh): every row by its three ranks
        x_rank = np.empty(len(x), dtype=np.int64)
        order = _by_ranks(x_rank, _dense_ranks(x, order, x_rank), y, z)
    elif len(tied):  # a few (a scan): those rows alone
        rows = order[tied]
        xs = x[rows]  # ascending
        x_rank = np.zeros(len(rows), dtype=np.int64)
        np.cumsum(xs[1:] != xs[:-1], out=x_rank[1:])
        del xs
        order[tied] = rows[_by_ranks(x_rank, int(x_rank[-1]) + 1, y[rows], z[rows])]
        del rows
    del tied
    points = np.empty((len(vertices), 3))
    inverse = np.empty(len(vertices), dtype=np.int64)
    groups = _group_sorted(order, x, y, z, points, inverse)
    return (points if groups == len(points) else points[:groups].copy()), inverse


def _by_ranks(x_rank: np.ndarray, x_count: int, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(n,) the order of rows by (x, y, z), given x's dense ranks (n,) and how many there are: the ranks of y and
    z joined to them in one integer key, sorted once."""
    key = x_rank.copy()  # (n,) int64
    distinct = x_count
    rank = np.empty(len(key), dtype=np.int64)
    for column in (y, z):
        values = _dense_ranks(column, np.argsort(column), rank)
        distinct *= values
        if distinct > _KEY_LIMIT:  # more distinct values than one key holds
            return np.lexsort((z, y, x_rank))
        key *= values
        key += rank
    return np.argsort(key)


@compiled_on_first_call
def _tied(values, order):  # pragma: no cover - compiled
    """(P,) int64: the places ``i`` in the sorting ``order`` whose value another place shares."""
    out = np.empty(len(order), dtype=np.int64)
    count = 0
    for i in range(len(order)):
        value = values[order[i]]
        if (i > 0 and values[order[i - 1]] == value) or (i + 1 < len(order) and values[order[i + 1]] == value):
            out[count] = i
            count += 1
    return out[:count]


@compiled_on_first_call
def _dense_ranks(values, order, out):  # pragma: no cover - compiled
    """``out[i]``: the number of distinct values below ``values[i]``, given the sorting ``order``; returns how many
    distinct values there are."""
    rank = -1
    last = 0.0
    for i in range(len(order)):
        value = values[order[i]]
        if i == 0 or value != last:
            rank += 1
            last = value
        out[order[i]] = rank
    return rank + 1


@compiled_on_first_call
def _group_sorted(order, x, y, z, points, inverse):  # pragma: no cover - compiled
    """Rows in lexicographic ``order`` grouped by position: each group's position written to ``points``, each row's
    group to ``inverse``; returns the number of groups."""
    group = -1
    for i in range(len(order)):
        row = order[i]
        if group < 0 or x[row] != points[group, 0] or y[row] != points[group, 1] or z[row] != points[group, 2]:
            group += 1
            points[group, 0], points[group, 1], points[group, 2] = x[row], y[row], z[row]
        inverse[row] = group
    return group + 1


def coincident_first(vertices: np.ndarray) -> np.ndarray:
    """Per row of ``vertices`` (V, 3) float64 or float32, finite, the first row at the same position (equal as
    numbers).

    For callers that need which rows coincide and not :func:`merge_coincident`'s sorted positions: one pass through
    a hash table of the rows' bit patterns (a fifth of the sort's time on a dense scan). float32 rows (an STL's
    corners) are hashed as they are, 12 bytes a row.

    Returns
    -------
    (V,) int64, ``first[i] <= i``; ``first[i] == i`` for the first row at each position.
    """
    a = np.asarray(vertices)
    a = a if a.dtype == np.float32 else a.astype(np.float64, copy=False)
    rows = np.ascontiguousarray(a.reshape(-1, 3) + a.dtype.type(0.0))  # -0.0 + 0.0 is 0.0
    return _hash_first(rows.view(np.int32 if a.dtype == np.float32 else np.int64))


@compiled_on_first_call
def _hash_first(bits):  # pragma: no cover - compiled
    """:func:`coincident_first` of (V, 3) rows given as bit patterns (int64, or int32 for float32 rows): open
    addressing, linear probing, a table of at least twice the rows, each row hashed by splitmix64-style rounds of
    multiply and xor-shift."""
    n = bits.shape[0]
    size = 1
    while size < 2 * n:
        size <<= 1
    mask = size - 1
    table = np.full(size, -1, dtype=np.int64)
    first = np.empty(n, dtype=np.int64)
    for i in range(n):
        h = bits[i, 0] * -7046029254386353131  # 0x9E3779B97F4A7C15 as int64 (the products wrap)
        h = (h ^ (h >> 29)) + bits[i, 1]
        h = h * -4658895280553007687  # 0xBF58476D1CE4E5B9
        h = (h ^ (h >> 32)) + bits[i, 2]
        h = h * -7723592293110705685  # 0x94D049BB133111EB
        h ^= h >> 29
        slot = h & mask
        while True:
            j = table[slot]
            if j < 0:
                table[slot] = i
                first[i] = i
                break
            if bits[j, 0] == bits[i, 0] and bits[j, 1] == bits[i, 1] and bits[j, 2] == bits[i, 2]:
                first[i] = j
                break
            slot = (slot + 1) & mask
    return first


def _merge_coincident_reference(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_coincident` by a lexicographic sort of the rows (the slow twin tests compare with)."""
    vertices = np.asarray(vertices, dtype=np.float64) + 0.0
    order = np.lexsort(vertices.T[::-1])
    ordered = vertices[order]
    new = np.ones(len(vertices), dtype=bool)
    new[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    inverse = np.empty(len(vertices), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return ordered[new], inverse


@compiled_on_first_call
def same_corners(triangles, mapping, top, drop_collapsed, same):  # pragma: no cover - compiled
    """``same[t]``: the first triangle with the corners of t (t itself when no earlier one has them), each corner
    taken through ``mapping`` (into [0, top)); with ``drop_collapsed``, -1 for triangles with two equal corners.
    Triangles are bucketed by their smallest corner (a counting sort, in triangle order), then compared on the other
    two within a bucket. ``same`` holds each triangle's smallest corner until the buckets are compared."""
    n = triangles.shape[0]
    rest = np.empty(n, dtype=np.int64)  # the two larger corners as one number
    starts = np.zeros(top + 2, dtype=np.int64)
    for t in range(n):
        a, b, c = mapping[triangles[t, 0]], mapping[triangles[t, 1]], mapping[triangles[t, 2]]
        if a > b:
            a, b = b, a
        if b > c:
            b, c = c, b
        if a > b:
            a, b = b, a
        if drop_collapsed and (a == b or b == c):
            same[t] = -1
            continue
        same[t] = a
        rest[t] = b * top + c
        starts[a + 2] += 1
    for v in range(top):
        starts[v + 2] += starts[v + 1]
    order = np.empty(starts[top + 1], dtype=np.int64)  # by smallest corner; bucket v ends up at starts[v]:starts[v + 1]
    for t in range(n):
        a = same[t]
        if a >= 0:
            order[starts[a + 1]] = t
            starts[a + 1] += 1
    for v in range(top):
        for i in range(starts[v], starts[v + 1]):
            key = rest[order[i]]
            same[order[i]] = order[i]
            for j in range(starts[v], i):
                if rest[order[j]] == key:
                    same[order[i]] = order[j]
                    break
