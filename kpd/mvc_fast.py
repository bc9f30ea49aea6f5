"""Compiled mean value coordinates, projected onto what edits need while they are computed.

The same coordinates as :func:`kpd.mvc.mvc_weights` (the same formula, docs/scale.md says how it was measured), as
a numba kernel: for a block of points it computes the per-edge quantities ``G = (p_a - x) × (p_b - x)`` and
``θ / |G|`` once per cage edge, the face sums ``m = Σ_k θ_k G_k / |G_k|`` and the corner weights
``w_k = G_k · m / D``, normalises them and multiplies them at once by a (C, R) matrix of rows, so that a caller
who needs ``weights @ rows`` (an edit basis ``MVC · Wᵀ``, R = K) never holds the (N, C) weights. The points are
the vector lanes: each loop over a block's points is branch-free (the arctangent is Cephes' rational
approximation, written without branches) and the compiler turns it into SIMD code.

Points the vectorised formula cannot handle (within ``1e-6`` of some face's plane, on a cage vertex, or with a
non-finite total) are flagged by the kernel and redone with :mod:`kpd.mvc`'s careful per-point rules, so every
result equals :func:`kpd.mvc.mvc_weights` to rounding. The kernel is compiled once per machine and cached next to
this file (numba's ``cache=True``); the first call in a fresh installation compiles it (a few seconds).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba
import numpy as np

from kpd.errors import InputError
from kpd.mvc import _careful_row, _prepare

__all__ = ["mvc_project", "mvc_weights_compiled", "theta_over"]

_LANES = 16  # points per block: the vector lanes of every inner loop
_MAX_THREADS = 2
_MIN_POINTS_PER_THREAD = 4096  # below this a second thread costs more than it saves

# Cephes atan: atan(u) = u + u z P(z) / Q(z), z = u², |u| <= 0.66 (relative error ~2e-16)
_P0, _P1, _P2, _P3, _P4 = (-8.750608600031904122785e-01, -1.615753718733365076637e01, -7.500855792314704667340e01,
                           -1.228866684490136173410e02, -6.485021904942025371773e01)
_Q0, _Q1, _Q2, _Q3, _Q4 = (2.485846490142306297962e01, 1.650270098316988542046e02, 4.328810604912902668951e02,
                           4.853903996359136964868e02, 1.945506571482613964425e02)
_PIO4, _PIO2, _PI = 0.78539816339744830962, 1.57079632679489661923, 3.14159265358979323846
_MOREBITS = 6.123233995736765886130e-17


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _theta_over(y: float, x: float) -> float:
    """atan2(y, x) / y for y > 0 (the angle an edge subtends over |G|), without branches and with two divisions.

    The smaller of y and |x| over the larger, t, is reduced to |u| <= 0.66 (u = (t - 1) / (t + 1) above 0.66),
    Cephes' atan(u) = u + u z P(z) / Q(z) gives the angle, and selects restore the octant:
    θ = base + sign (u + u z P / Q), written over the one denominator Q y."""
    ax = abs(x)
    swap = y > ax
    big = y if swap else ax
    small = ax if swap else y
    high = 1.0 * (small > 0.66 * big)
    num = small - high * big
    u = num / (big + high * small)
    z = u * u
    p = (((_P0 * z + _P1) * z + _P2) * z + _P3) * z + _P4
    q = ((((z + _Q0) * z + _Q1) * z + _Q2) * z + _Q3) * z + _Q4
    turn = 1.0 * swap
    back = 1.0 * (x < 0.0)
    base = back * _PI + (1.0 - 2.0 * back) * (turn * _PIO2 + (1.0 - 2.0 * turn) * high * (_PIO4 + 0.5 * _MOREBITS))
    sign = (1.0 - 2.0 * back) * (1.0 - 2.0 * turn)
    # θ = base + sign (u + u z p / q) = (base q + sign u (q + z p)) / q
    return (base * q + sign * u * (q + z * p)) / (q * y)


@numba.njit(cache=True, nogil=True)
def theta_over(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The kernel's ``arctan2(y, x) / y`` for ``y > 0`` on arrays (for tests): ``(N,)`` float64."""
    out = np.empty(len(y))
    for i in range(len(y)):
        out[i] = _theta_over(y[i], x[i])
    return out


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _project_range(points, lo, hi, px, py, pz, edge_a, edge_b, face_edge, face_sign, nx, ny, nz, offset, near,
                   corner_start, corners, rows, out, flags):  # pragma: no cover - compiled
    """``out[lo:hi] = normalised MVC weights of points[lo:hi] @ rows``; ``flags[lo:hi]`` marks points to redo."""
    L = _LANES
    C = px.shape[0]
    E = edge_a.shape[0]
    F = face_edge.shape[0]
    R = rows.shape[1]
    d = np.empty((C, 3, L))  # p_c - x
    g = np.empty((E, 4, L))  # G = (p_a - x) x (p_b - x) and θ / |G|, per edge
    cw = np.empty((3 * F, L))  # corner weights, row 3 f + k
    w = np.empty((C, L))
    acc = np.empty((R, L))
    xs = np.empty((3, L))
    tot = np.empty(L)
    bad = np.empty(L, dtype=np.bool_)
    for start in range(lo, hi, L):
        n = min(L, hi - start)
        for i in range(L):  # a short last block repeats its last point
            j = start + min(i, n - 1)
            for k in range(3):
                xs[k, i] = points[j, k]
        for c in range(C):
            dc = d[c]
            for i in range(L):
                dc[0, i] = px[c] - xs[0, i]
                dc[1, i] = py[c] - xs[1, i]
                dc[2, i] = pz[c] - xs[2, i]
        for e in range(E):
            da = d[edge_a[e]]
            db = d[edge_b[e]]
            ge = g[e]
            for i in range(L):
                ax = da[0, i]
                ay = da[1, i]
                az = da[2, i]
                bx = db[0, i]
                by = db[1, i]
                bz = db[2, i]
                cx = ay * bz - az * by
                cy = az * bx - ax * bz
                cz = ax * by - ay * bx
                ge[0, i] = cx
                ge[1, i] = cy
                ge[2, i] = cz
                ge[3, i] = _theta_over(np.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)
        for i in range(L):
            bad[i] = False
        for f in range(F):
            a0 = g[face_edge[f, 0]]
            a1 = g[face_edge[f, 1]]
            a2 = g[face_edge[f, 2]]
            s0 = face_sign[f, 0]
            s1 = face_sign[f, 1]
            s2 = face_sign[f, 2]
            fx = nx[f]
            fy = ny[f]
            fz = nz[f]
            fo = offset[f]
            w0 = cw[3 * f]
            w1 = cw[3 * f + 1]
            w2 = cw[3 * f + 2]
            for i in range(L):
                g0x = s0 * a0[0, i]
                g0y = s0 * a0[1, i]
                g0z = s0 * a0[2, i]
                g1x = s1 * a1[0, i]
                g1y = s1 * a1[1, i]
                g1z = s1 * a1[2, i]
                g2x = s2 * a2[0, i]
                g2y = s2 * a2[1, i]
                g2z = s2 * a2[2, i]
                t0 = a0[3, i]
                t1 = a1[3, i]
                t2 = a2[3, i]
                mx = t0 * g0x + t1 * g1x + t2 * g2x
                my = t0 * g0y + t1 * g1y + t2 * g2y
                mz = t0 * g0z + t1 * g1z + t2 * g2z
                inv = 1.0 / (fo - (fx * xs[0, i] + fy * xs[1, i] + fz * xs[2, i]))  # 1 / det[p_0 - x, p_1 - x, p_2 - x]
                w0[i] = (g0x * mx + g0y * my + g0z * mz) * inv
                w1[i] = (g1x * mx + g1y * my + g1z * mz) * inv
                w2[i] = (g2x * mx + g2y * my + g2z * mz) * inv
            fn = near[f]
            for i in range(L):
                bad[i] |= abs(fo - (fx * xs[0, i] + fy * xs[1, i] + fz * xs[2, i])) <= fn
        for i in range(L):
            tot[i] = 0.0
        for c in range(C):
            wc = w[c]
            for i in range(L):
                wc[i] = 0.0
            for j in range(corner_start[c], corner_start[c + 1]):
                src = cw[corners[j]]
                for i in range(L):
                    wc[i] += src[i]
            for i in range(L):
                tot[i] += wc[i]
        for r in range(R):
            for i in range(L):
                acc[r, i] = 0.0
        for c in range(C):
            wc = w[c]
            for r in range(R):
                rc = rows[c, r]
                ar = acc[r]
                for i in range(L):
                    ar[i] += wc[i] * rc
        for i in range(n):
            t = tot[i]
            flags[start + i] = bad[i] | (not np.isfinite(t)) | (t == 0.0)
            inv = 1.0 / t
            for r in range(R):
                out[start + i, r] = acc[r, i] * inv


class _Cage:
    """The cage's tables in the kernel's layout (from :class:`kpd.mvc._Tables`)."""

    def __init__(self, t) -> None:
        self.t = t
        rows = np.stack(t.rows, axis=1)  # (F, 3): edge row per corner, + E when the edge runs backwards
        self.face_edge = np.ascontiguousarray(rows % t.E)
        self.face_sign = np.where(rows >= t.E, -1.0, 1.0)
        v = t.vertices
        corner_vertex = t.faces.ravel()  # (3F,) cage vertex of corner 3 f + k
        corners = np.argsort(corner_vertex, kind="stable")
        corner_start = np.searchsorted(corner_vertex[corners], np.arange(t.C + 1))
        self.args = (
            np.ascontiguousarray(v[:, 0]), np.ascontiguousarray(v[:, 1]), np.ascontiguousarray(v[:, 2]),
            np.ascontiguousarray(t.edges[:, 0]), np.ascontiguousarray(t.edges[:, 1]), self.face_edge,
            self.face_sign, np.ascontiguousarray(t.n2[:, 0]), np.ascontiguousarray(t.n2[:, 1]),
            np.ascontiguousarray(t.n2[:, 2]), np.ascontiguousarray(t.offset), np.ascontiguousarray(t.col["near"][:, 0]),
            corner_start.astype(np.int64), corners.astype(np.int64),
        )


def _check_threads(threads: Any) -> int:
    if threads is None:
        return min(_MAX_THREADS, os.cpu_count() or 1)
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InputError(f"threads must be a positive integer; got {threads!r}")
    return int(threads)


def mvc_project(points: Any, cage_vertices: Any, cage_faces: Any, rows: Any, *, out: np.ndarray | None = None,
                threads: int | None = None) -> np.ndarray:
    """Mean value coordinates of points times a matrix, without the (N, C) coordinates.

    ``mvc_project(x, v, f, rows) == mvc_weights(x, v, f) @ rows`` to rounding; with ``rows = influence.T`` this is
    a rig's edit basis (:class:`kpd.rig.Rig`). Work memory is a few hundred kilobytes per thread, whatever N.

    Parameters
    ----------
    points : (N, 3) float64
    cage_vertices : (C, 3) float64
    cage_faces : (F, 3) int, outward-oriented, closed.
    rows : (C, R) float64, what each cage vertex carries.
    out : optional (N, R) float64 C-contiguous buffer to write into.
    threads : worker threads; ``min(2, cpu count)`` when ``None``. The result does not depend on it.

    Returns
    -------
    (N, R) float64.
    """
    points, t = _prepare(points, cage_vertices, cage_faces)
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[0] != t.C or not np.isfinite(rows).all():
        raise InputError(f"rows must be (C, R) = ({t.C}, R) finite numbers; got shape {rows.shape}")
    rows = np.ascontiguousarray(rows)
    n, r = len(points), rows.shape[1]
    if out is None:
        out = np.empty((n, r))
    elif out.shape != (n, r) or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise InputError(f"out must be a C-contiguous (N, R) = ({n}, {r}) float64 array; got {out.shape} {out.dtype}")
    if n == 0:
        return out
    threads = min(_check_threads(threads), max(1, n // _MIN_POINTS_PER_THREAD))
    cage = _Cage(t)
    flags = np.zeros(n, dtype=bool)
    points = np.ascontiguousarray(points)

    def run(lo: int, hi: int) -> None:
        _project_range(points, lo, hi, *cage.args, rows, out, flags)

    if threads == 1:
        run(0, n)
    else:
        # whole blocks per thread, as equal as they come
        blocks = -(-n // _LANES)
        bounds = [min(n, (blocks * i // threads) * _LANES) for i in range(threads + 1)]
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(run, bounds[:-1], bounds[1:]))
    for i in np.flatnonzero(flags):
        out[i] = _careful_row(t, points[i]) @ rows
    return out


def mvc_weights_compiled(points: Any, cage_vertices: Any, cage_faces: Any, *, threads: int | None = None
                         ) -> np.ndarray:
    """(N, C) float64: :func:`kpd.mvc.mvc_weights` by the compiled kernel (``mvc_project`` with the identity)."""
    c = len(np.asarray(cage_vertices))
    return mvc_project(points, cage_vertices, cage_faces, np.eye(c), threads=threads)
