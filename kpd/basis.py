"""A rig's edit basis: the mean value coordinates times the influence, computed once per distinct position; kept in
float32 where that is exact enough; applied to keypoint offsets by a compiled kernel.
"""

from __future__ import annotations

from typing import Any

import numba  # noqa: F401  (first: numba.core's modules cannot be imported before it)
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from kpd._compiled import njit
from kpd.cage import Cage
from kpd.geometry import as_points
from kpd.grouping import merge_coincident
from kpd.mvc import mvc_weights
from kpd.mvc_fast import mvc_project

__all__ = ["coincident_mvc_weights", "coincident_mvc_basis", "distinct_points", "compact_basis", "edit", "edit_rows"]

_FLOAT32_ROW_SUM = 16.0  # a basis whose rows' absolute sums stay below this is kept in float32 (see compact_basis)


def coincident_mvc_weights(vertices: Any, cage: Cage) -> np.ndarray:
    """(V, C) mean value coordinates of ``vertices`` in ``cage``, computed once per distinct position.

    CAD meshes store one vertex per triangle corner (ModelNet10's chairs have about four vertices per position), and
    the coordinates of a position do not depend on how often it is stored: this is :func:`kpd.mvc.mvc_weights` at a
    quarter of the cost on such meshes, with the same result.
    """
    vertices = as_points(vertices, "vertices")
    points, inverse = merge_coincident(vertices)
    if len(points) == len(vertices):
        return mvc_weights(vertices, cage.vertices, cage.faces)
    return mvc_weights(points, cage.vertices, cage.faces)[inverse]


def coincident_mvc_basis(vertices: Any, cage: Cage, rows: Any) -> np.ndarray:
    """(V, R) float64: ``coincident_mvc_weights(vertices, cage) @ rows`` without the (V, C) weights.

    Computed once per distinct position by the compiled kernel (:func:`kpd.mvc_fast.mvc_project`); with
    ``rows = influence.T`` (C, K) this is a rig's edit basis before straightening.
    """
    vertices = as_points(vertices, "vertices")
    points, inverse = merge_coincident(vertices)
    if len(points) == len(vertices):
        return mvc_project(vertices, cage.vertices, cage.faces, rows)
    return mvc_project(points, cage.vertices, cage.faces, rows)[inverse]


def distinct_points(vertices: Any) -> np.ndarray:
    """(n, 3) the distinct positions among ``vertices`` (V, 3), in lexicographic order."""
    return merge_coincident(as_points(vertices, "vertices"))[0]


def compact_basis(basis: np.ndarray) -> np.ndarray:
    """``basis`` (V, K) in float32 when that moves no vertex by more than 1e-6 of the box diagonal for keypoint
    moves of up to a box diagonal each, else as it is.

    Rounding to float32 changes each entry by at most 2^-24 of it, so a vertex moves by at most
    ``2^-24 · Σ_k |B_vk| · max_k |Δp_k|``: within 1e-6 of a diagonal ``max_k |Δp_k|`` when every row's absolute
    sum is below 16 (a mesh inside its cage has rows that sum to about 1 per keypoint that moves it).
    """
    if basis.dtype == np.float32 or not len(basis):
        return basis
    if _largest_row_sum(np.ascontiguousarray(basis, dtype=np.float64)) > _FLOAT32_ROW_SUM:
        return basis
    return basis.astype(np.float32)


@njit(nogil=True)
def _largest_row_sum(basis):  # pragma: no cover - compiled
    """``np.abs(basis).sum(axis=1).max()`` without the (V, K) temporary (NaN if any entry is NaN)."""
    largest = 0.0
    for v in range(basis.shape[0]):
        total = 0.0
        for k in range(basis.shape[1]):
            total += abs(basis[v, k])
        if total != total:
            return total
        largest = max(largest, total)
    return largest


_EDIT_LANES = 256  # vertices per block of an edit


@intrinsic
def _store_streaming(typingctx, array, index, value):  # pragma: no cover - compiled
    """``array[index] = value`` for a 1-d float64 array, as a non-temporal store: the line is written to memory
    without being read into the cache first, as a plain store does (half the memory traffic of writing an output
    that nothing reads soon). Other threads see it after :func:`_streaming_done`."""

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        store = builder.store(args[2], builder.gep(data, [args[1]]))
        store.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
        return context.get_dummy_value()

    return types.void(array, types.intp, types.float64), codegen


@intrinsic
def _streaming_done(typingctx):  # pragma: no cover - compiled
    """A full memory fence (``mfence`` on x86, ``dmb`` on ARM): the non-temporal stores before it are in memory
    for every thread after it."""

    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return types.void(), codegen


@njit(nogil=True, error_model="numpy")
def edit(basis_t, offsets, rest, out):  # pragma: no cover - compiled
    """``out = rest + basis_t.T @ offsets`` with float64 sums: (K, V) basis of float32 or float64, (K, 3) offsets.

    Blocks of vertices, each keypoint's row of the block in order: the loops over the block are SIMD code (over
    twice as fast as a vertex at a time, whose K sums depend on each other). The rows of keypoints that did not move
    are not read: a drag of one keypoint reads one row of the basis, not K. The pass is bound by memory, so ``out``
    is written with non-temporal stores (:func:`_store_streaming`), which do not read its lines into the cache."""
    moved = np.zeros(offsets.shape[0], dtype=np.int64)
    k = 0
    for j in range(offsets.shape[0]):
        if offsets[j, 0] != 0.0 or offsets[j, 1] != 0.0 or offsets[j, 2] != 0.0:
            moved[k] = j
            k += 1
    n_all = rest.shape[0]
    x = np.empty(_EDIT_LANES)
    y = np.empty(_EDIT_LANES)
    z = np.empty(_EDIT_LANES)
    flat = out.reshape(-1)  # C-contiguous (V, 3): vertex v's coordinates at 3v, 3v + 1, 3v + 2
    for start in range(0, n_all, _EDIT_LANES):
        n = min(_EDIT_LANES, n_all - start)
        for i in range(n):
            x[i] = rest[start + i, 0]
            y[i] = rest[start + i, 1]
            z[i] = rest[start + i, 2]
        for m in range(k):
            j = moved[m]
            o0 = offsets[j, 0]
            o1 = offsets[j, 1]
            o2 = offsets[j, 2]
            row = basis_t[j, start:start + n]
            for i in range(n):
                b = np.float64(row[i])
                x[i] += b * o0
                y[i] += b * o1
                z[i] += b * o2
        for i in range(n):
            v = 3 * (start + i)
            _store_streaming(flat, v, x[i])
            _store_streaming(flat, v + 1, y[i])
            _store_streaming(flat, v + 2, z[i])
    _streaming_done()


@njit(nogil=True, error_model="numpy")
def edit_rows(basis_t, offsets, rest, rows, out):  # pragma: no cover - compiled
    """:func:`edit` for the vertices ``rows`` only."""
    k = offsets.shape[0]
    for v in rows:
        x = rest[v, 0]
        y = rest[v, 1]
        z = rest[v, 2]
        for j in range(k):
            b = np.float64(basis_t[j, v])
            x += b * offsets[j, 0]
            y += b * offsets[j, 1]
            z += b * offsets[j, 2]
        out[v, 0] = x
        out[v, 1] = y
        out[v, 2] = z

