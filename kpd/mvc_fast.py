"""Compiled mean value coordinates, projected onto what edits need while they are computed.

The same coordinates as :func:`kpd.mvc.mvc_weights` (the same formula), as a numba kernel: for a block of points it
computes the per-edge quantities ``G = (p_a - x) × (p_b - x)`` and ``θ / |G|`` once per cage edge, the face sums
``m = Σ_k θ_k G_k / |G_k|`` and the corner weights ``w_k = G_k · m / D``, sums them per cage vertex, normalises them
and multiplies them at once by a (C, R) matrix of rows, so that a caller who needs ``weights @ rows`` (an edit basis
``MVC · Wᵀ``, R = K) never holds the (N, C) weights. docs/scale.md has the measurements.

* **Lanes.** 32 points at a time are the vector lanes: every loop over them is branch-free and compiles to SIMD
  code, 512 bits wide where the processor has them (:func:`_tune`). Points are taken 4096 at a time in Z-curve
  order (:func:`_near_first`), so the 32 of a block are close together.
* **Faces in a strip.** The faces are visited in an order that keeps each edge's two faces close
  (:func:`_schedule`): an edge's quantities live in a few kilobytes from when they are computed until its second face
  has used them, and the corner weights go to the cage vertices as they come.
* **Arctangents without square roots.** An edge seen under at most π/4 (``0 < |G| <= a·b``, most edges from most
  points) gets ``θ / |G| = P(z) / (Q(z) a·b)`` with ``z = |G|² / (a·b)²``, a rational fit; only when some lane of a
  block sees it wider does the block also take the general way, a polynomial on a reduced argument after a square
  root (:func:`theta_over`); each lane keeps its own result, so a row depends on its point alone.
* **Divisions in pairs.** Divisions, the slowest instructions after square roots, are shared by the two edges or two
  faces computed together: ``1/a = b / (ab)``, ``1/b = a / (ab)``.

Points the vectorised formula cannot handle (within ``1e-6`` of some face's plane, on a cage vertex, more than
``1e6`` cage sizes away, or with a non-finite total) are flagged by the kernel and redone by the careful per-point
rules of :func:`kpd.mvc._careful_row`, compiled (:func:`_careful_rows`, which sums in the same order), so every result
equals :func:`kpd.mvc.mvc_weights` to rounding. The kernel scales coordinates by a power of two near the cage's size
(exactly, so it rounds as in the caller's units), which keeps the products of pairs far from overflow. It is compiled
once per machine and cached next to this file (numba's ``cache=True``); the first call in a fresh installation
compiles it (a few seconds).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba  # noqa: F401  (imported before numba.core's modules, which cannot be imported first)
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from kpd._compiled import njit
from kpd.errors import InputError, KpdError
from kpd.mvc import _LINEAR_FRACTION, _TOL_FACE, _TOL_INSIDE, _TOL_PLANE, _TOL_VERTEX, _prepare

__all__ = ["mvc_project", "mvc_weights_compiled", "theta_over"]

_LANES = 32  # points per block: the vector lanes of every inner loop
_CHUNK = 4096  # points ordered along a Z curve together (a multiple of _LANES)
_CHUNKS_PER_TASK = 8  # chunks a thread takes at a time
_MAX_THREADS = 2
_MIN_POINTS_PER_THREAD = 4096  # below this a second thread costs more than it saves
_FAR = 1e6  # points farther than this many cage sizes from the cage's centroid go to the careful path

# atan(u) = u p(u²) for |u| <= tan(π/8): least squares on Chebyshev nodes in 50-digit arithmetic (mpmath), the
# coefficients rounded to float64; |p(z) - atan(u)/u| <= 5e-18 over the interval.
_C1, _C2, _C3, _C4, _C5 = (-0.33333333333333126, 0.19999999999942342, -0.14285714279381564, 0.11111110751018727,
                           -0.09090896974391927)
_C6, _C7, _C8, _C9, _C10, _C11 = (0.07692048125814824, -0.06662982166188505, 0.05847090096609891,
                                  -0.05036020352571326, 0.03798774160996723, -0.017829184144146384)
# atan(u) = u P(u²) / Q(u²) for |u| <= 1: a rational least-squares fit (iterated linearised least squares on
# Chebyshev nodes in 50-digit arithmetic), coefficients rounded to float64; |P/Q - atan(u)/u| <= 3e-17 over the
# interval. All coefficients are positive, so neither polynomial cancels.
_P0, _P1, _P2, _P3, _P4, _P5, _P6 = (1.0, 2.5058711541048315, 2.283552921076234, 0.9214099303568334,
                                     0.15930676772763916, 0.009368908732573148, 8.081629455475974e-05)
_Q1, _Q2, _Q3, _Q4, _Q5, _Q6 = (2.8392044874381623, 3.029954416889169, 1.5064109813494801, 0.34994240819043615,
                                0.033026737446235827, 0.0008276426970218969)
_TAN_PI_8 = 0.41421356237309503
_PI, _PI_2, _PI_4, _PI_3_4 = np.pi, np.pi / 2, np.pi / 4, 3 * np.pi / 4


@intrinsic
def _tune(typingctx):  # pragma: no cover - compiled
    """Two promises to LLVM about the calling function, so that its loops over the lanes compile to wide SIMD code.

    * Its array arguments do not overlap (``noalias`` on their data pointers): otherwise LLVM must test at run time
      that a loop's stores do not feed its own loads, and gives up when there are more than a few such tests or the
      loop is short. :func:`mvc_project` passes separate arrays (it copies an input that shares memory with ``out``).
    * 512-bit vectors where the processor has them (``prefer-vector-width``; LLVM prefers 256 bits by default), about
      twice the lanes per instruction. Results do not change: every lane does the same operations in the same order
      whatever the width.

    llvmlite accepts only its own list of function attribute names, so the string attribute is added to the set it
    checks. Numba passes an array as its fields; the data pointer is field 4 (``arg.<name>.4``)."""

    def codegen(context, builder, signature, args):
        function = builder.function
        attribute = '"prefer-vector-width"="512"'
        known = getattr(function.attributes, "_known", None)
        if known is not None:  # llvmlite's private list of names; without it the kernel is only narrower
            function.attributes._known = known | {attribute}
            function.attributes.add(attribute)
        for argument in function.args:
            if argument.name.startswith("arg.") and argument.name.endswith(".4"):
                argument.add_attribute("noalias")
        return context.get_dummy_value()

    return types.void(), codegen


@njit(nogil=True, inline="always", error_model="numpy")
def _reduce(y, x):
    """atan2(y, x) for y >= 0 as ``base + atan(num / den)`` times a sign, with ``|num / den| <= tan(π/8)``.

    The smaller of y and |x| over the larger, t, is reduced to u = (t - 1) / (t + 1) above tan(π/8); the octant is
    restored by the base angle and the sign. Returns ``(num, den, base, signed_num)``."""
    ax = abs(x)
    swap = y > ax
    big = y if swap else ax
    small = ax if swap else y
    high = small > _TAN_PI_8 * big
    num = small - big if high else small
    den = big + small if high else big
    back = x < 0.0
    if high:
        base = _PI_3_4 if back else _PI_4
    else:
        base = _PI_2 if swap else (_PI if back else 0.0)
    signed = -num if back != swap else num
    return num, den, base, signed


@njit(nogil=True, inline="always", error_model="numpy", fastmath={"contract"})
def _atan_over(z):
    """atan(u) / u for z = u² <= tan²(π/8)."""
    return ((((((((((_C11 * z + _C10) * z + _C9) * z + _C8) * z + _C7) * z + _C6) * z + _C5) * z + _C4) * z + _C3) * z
             + _C2) * z + _C1) * z + 1.0


@njit(nogil=True, inline="always", error_model="numpy", fastmath={"contract"})
def _atan_parts(z):
    """``(P(z), Q(z))``, ``atan(u) / u = P / Q`` for z = u² <= 1 (angles up to π/4), without a reduction."""
    p = (((((_P6 * z + _P5) * z + _P4) * z + _P3) * z + _P2) * z + _P1) * z + _P0
    q = (((((_Q6 * z + _Q5) * z + _Q4) * z + _Q3) * z + _Q2) * z + _Q1) * z + 1.0
    return p, q


@njit(nogil=True, inline="always", error_model="numpy", fastmath={"contract"})
def _finish(num, den, base, signed, y, r):
    """θ / y from :func:`_reduce`'s parts and ``r = 1 / (den y)``: ``r (base den + signed p(u²))``, u = num y r."""
    u = num * (y * r)
    return r * (base * den + signed * _atan_over(u * u))


@njit(nogil=True, inline="always", error_model="numpy", fastmath={"contract"})
def _theta_over_pair(y0, x0, y1, x1):
    """``(atan2(y0, x0) / y0, atan2(y1, x1) / y1)`` for y0, y1 > 0 with one division for both."""
    num0, den0, base0, signed0 = _reduce(y0, x0)
    num1, den1, base1, signed1 = _reduce(y1, x1)
    q0 = den0 * y0
    q1 = den1 * y1
    r = 1.0 / (q0 * q1)
    return _finish(num0, den0, base0, signed0, y0, r * q1), _finish(num1, den1, base1, signed1, y1, r * q0)


@njit(nogil=True, inline="always", error_model="numpy", fastmath={"contract"})
def _theta_over_narrow_pair(s0, x0, s1, x1):
    """``(atan2(y0, x0) / y0, atan2(y1, x1) / y1, both narrow)`` from ``s = y²``, without a square root, with two
    divisions for both; exact to rounding when both are narrow: ``0 < y <= x`` (angles up to π/4), where
    ``θ / y = P(z) / (Q(z) x)``, z = s / x²."""
    r = 1.0 / (x0 * x1)
    i0 = r * x1
    i1 = r * x0
    z0 = s0 * (i0 * i0)
    z1 = s1 * (i1 * i1)
    p0, q0 = _atan_parts(z0)
    p1, q1 = _atan_parts(z1)
    q0 *= x0
    q1 *= x1
    r = 1.0 / (q0 * q1)
    return p0 * q1 * r, p1 * q0 * r, (x0 > 0.0) & (x1 > 0.0) & (z0 <= 1.0) & (z1 <= 1.0)


@njit(nogil=True, error_model="numpy")
def theta_over(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The kernel's ``arctan2(y, x) / y`` for ``y > 0`` on arrays (for tests): ``(N,)`` float64.

    Consecutive elements are paired as the kernel pairs edges: a pair where both angles are at most π/4 goes the
    narrow way (:func:`_theta_over_narrow_pair`, from ``y²``), any other the general way (:func:`_theta_over_pair`)."""
    n = len(y)
    out = np.empty(n + 1)
    yy = np.append(y, 1.0)
    xx = np.append(x, 1.0)
    for i in range(0, n, 2):
        out[i], out[i + 1], narrow = _theta_over_narrow_pair(yy[i] * yy[i], xx[i], yy[i + 1] * yy[i + 1], xx[i + 1])
        if not narrow:
            out[i], out[i + 1] = _theta_over_pair(yy[i], xx[i], yy[i + 1], xx[i + 1])
    return out[:n]


@njit(nogil=True)
def _near_first(points, lo, m):  # pragma: no cover - compiled
    """``(m,)`` an order of points[lo:lo + m] along a Z curve (Morton order) over 16³ cells of their bounding cube,
    points in a cell in their order, so that the kernel's blocks of consecutive points are small in space: an edge is
    then seen under a narrow angle from all the points of a block more often. A counting sort, O(m)."""
    low = np.empty(3)
    size = 0.0
    for k in range(3):
        low[k] = points[lo, k]
        high = points[lo, k]
        for i in range(lo, lo + m):
            low[k] = min(low[k], points[i, k])
            high = max(high, points[i, k])
        size = max(size, high - low[k])
    step = 15.999 / size if size > 0.0 else 0.0
    cells = np.empty(m, dtype=np.int64)
    start = np.zeros(4097, dtype=np.int64)
    for i in range(m):
        cell = 0
        for k in range(3):
            q = int((points[lo + i, k] - low[k]) * step)  # 0..15: its 4 bits go to bits k, k + 3, k + 6, k + 9
            cell |= ((q & 1) | (q & 2) << 2 | (q & 4) << 4 | (q & 8) << 6) << k
        cells[i] = cell
        start[cell + 1] += 1
    for c in range(4096):
        start[c + 1] += start[c]
    order = np.empty(m, dtype=np.int64)
    for i in range(m):
        order[start[cells[i]]] = i
        start[cells[i]] += 1
    return order


@njit(nogil=True, fastmath={"contract"}, error_model="numpy")
def _project_range(points, lo, hi, center, inv_size, px, py, pz, edge_a, edge_b, edge_slot, step_edges, face_slot,
                   face_sign, corner_vertex, nx, ny, nz, offset, near, nonzero_row, nonzero_column, nonzero_value, R,
                   out, flags, xs, g, lane_dot, lane_narrow, bad, w, w0, w1, acc):  # pragma: no cover
    """``out[lo:hi] = normalised MVC weights of points[lo:hi] @ rows``; ``flags[lo:hi]`` marks points to redo.

    Coordinates are scaled by ``inv_size``, a power of two; ``center`` is the cage's centroid so scaled. Step s
    computes the edge pairs ``step_edges[s]:step_edges[s + 1]`` (edges ``2k`` and ``2k + 1``, into the pair slot
    ``edge_slot[k]`` of g), then faces ``2s`` and ``2s + 1`` (in schedule order), whose corner k uses the rows of g
    from ``face_slot[f, k]`` times ``face_sign[f, k]`` and adds its weight to cage vertex ``corner_vertex[3f + k]``
    (in w0 for the first face, w1 for the second). ``rows`` (C, R + 1), the last column ones for the total, comes as
    its non-zero entries. Every array is flat with the lanes last and the lane count a constant, so that each loop
    over the lanes reads and writes at fixed offsets from a few bases; the arguments from xs on are the thread's
    scratch."""
    _tune()
    L = _LANES
    C = px.shape[0]
    S = face_slot.shape[0] // 2
    M = bad.shape[0]  # L, but not a constant, so that LLVM vectorises the short loops over the lanes below
    c0, c1, c2 = center[0], center[1], center[2]
    for chunk in range(lo, hi, _CHUNK):
        m = min(_CHUNK, hi - chunk)
        order = _near_first(points, chunk, m)
        for start in range(0, m, L):
            n = min(L, m - start)
            for i in range(L):  # a short last block repeats its last point
                j = chunk + order[start + min(i, n - 1)]
                xs[i] = points[j, 0] * inv_size
                xs[L + i] = points[j, 1] * inv_size
                xs[2 * L + i] = points[j, 2] * inv_size
            for i in range(L):
                bad[i] = max(abs(xs[i] - c0), abs(xs[L + i] - c1), abs(xs[2 * L + i] - c2)) > _FAR
            for s in range(S):
                for k in range(step_edges[s], step_edges[s + 1]):
                    e0 = 2 * k
                    e1 = e0 + 1
                    ax0, ay0, az0 = px[edge_a[e0]], py[edge_a[e0]], pz[edge_a[e0]]
                    bx0, by0, bz0 = px[edge_b[e0]], py[edge_b[e0]], pz[edge_b[e0]]
                    ax1, ay1, az1 = px[edge_a[e1]], py[edge_a[e1]], pz[edge_a[e1]]
                    bx1, by1, bz1 = px[edge_b[e1]], py[edge_b[e1]], pz[edge_b[e1]]
                    o = max(edge_slot[k], 0) * 8 * L  # G, θ / |G| of edge 2k from o, of edge 2k + 1 from o + 4L
                    # both edges seen under at most π/4 from every lane: θ / |G| = P(z) / (Q(z) a.b), z = |G|² / (a.b)²
                    wide = False
                    for i in range(L):
                        x = xs[i]
                        y = xs[L + i]
                        z = xs[2 * L + i]
                        a0 = ax0 - x
                        a1 = ay0 - y
                        a2 = az0 - z
                        b0 = bx0 - x
                        b1 = by0 - y
                        b2 = bz0 - z
                        gx0 = a1 * b2 - a2 * b1
                        gy0 = a2 * b0 - a0 * b2
                        gz0 = a0 * b1 - a1 * b0
                        dot0 = a0 * b0 + a1 * b1 + a2 * b2
                        a0 = ax1 - x
                        a1 = ay1 - y
                        a2 = az1 - z
                        b0 = bx1 - x
                        b1 = by1 - y
                        b2 = bz1 - z
                        gx1 = a1 * b2 - a2 * b1
                        gy1 = a2 * b0 - a0 * b2
                        gz1 = a0 * b1 - a1 * b0
                        dot1 = a0 * b0 + a1 * b1 + a2 * b2
                        t0, t1, narrow = _theta_over_narrow_pair(gx0 * gx0 + gy0 * gy0 + gz0 * gz0, dot0,
                                                                 gx1 * gx1 + gy1 * gy1 + gz1 * gz1, dot1)
                        wide |= not narrow
                        lane_narrow[i] = narrow
                        lane_dot[i] = dot0
                        lane_dot[L + i] = dot1
                        g[o + i] = gx0
                        g[o + L + i] = gy0
                        g[o + 2 * L + i] = gz0
                        g[o + 3 * L + i] = t0
                        g[o + 4 * L + i] = gx1
                        g[o + 5 * L + i] = gy1
                        g[o + 6 * L + i] = gz1
                        g[o + 7 * L + i] = t1
                    if wide:  # the general arctangent, for the lanes that are not narrow
                        for i in range(L):
                            gx0, gy0, gz0 = g[o + i], g[o + L + i], g[o + 2 * L + i]
                            gx1, gy1, gz1 = g[o + 4 * L + i], g[o + 5 * L + i], g[o + 6 * L + i]
                            t0, t1 = _theta_over_pair(np.sqrt(gx0 * gx0 + gy0 * gy0 + gz0 * gz0), lane_dot[i],
                                                      np.sqrt(gx1 * gx1 + gy1 * gy1 + gz1 * gz1), lane_dot[L + i])
                            narrow = lane_narrow[i]
                            g[o + 3 * L + i] = g[o + 3 * L + i] if narrow else t0
                            g[o + 7 * L + i] = g[o + 7 * L + i] if narrow else t1
                fa = 2 * s
                fb = fa + 1
                oa0, oa1, oa2 = max(face_slot[fa, 0], 0) * L, max(face_slot[fa, 1], 0) * L, max(face_slot[fa, 2], 0) * L
                ob0, ob1, ob2 = max(face_slot[fb, 0], 0) * L, max(face_slot[fb, 1], 0) * L, max(face_slot[fb, 2], 0) * L
                sa0, sa1, sa2 = face_sign[fa, 0], face_sign[fa, 1], face_sign[fa, 2]
                sb0, sb1, sb2 = face_sign[fb, 0], face_sign[fb, 1], face_sign[fb, 2]
                nxa, nya, nza, da0, near_a = nx[fa], ny[fa], nz[fa], offset[fa], near[fa]
                nxb, nyb, nzb, db0, near_b = nx[fb], ny[fb], nz[fb], offset[fb], near[fb]
                # the first face's corners add to w0, the second's to w1 (a face's three corners are distinct)
                cv = corner_vertex[6 * s:6 * s + 6]
                q0, q1, q2 = max(cv[0], 0) * L, max(cv[1], 0) * L, max(cv[2], 0) * L
                q3, q4, q5 = max(cv[3], 0) * L, max(cv[4], 0) * L, max(cv[5], 0) * L
                for i in range(L):
                    x = xs[i]
                    y = xs[L + i]
                    z = xs[2 * L + i]
                    da = da0 - (nxa * x + nya * y + nza * z)  # det[p_0 - x, p_1 - x, p_2 - x]
                    db = db0 - (nxb * x + nyb * y + nzb * z)
                    r = 1.0 / (da * db)
                    ia = r * db
                    ib = r * da
                    gx0, gy0, gz0 = g[oa0 + i], g[oa0 + L + i], g[oa0 + 2 * L + i]
                    gx1, gy1, gz1 = g[oa1 + i], g[oa1 + L + i], g[oa1 + 2 * L + i]
                    gx2, gy2, gz2 = g[oa2 + i], g[oa2 + L + i], g[oa2 + 2 * L + i]
                    t0 = sa0 * g[oa0 + 3 * L + i]
                    t1 = sa1 * g[oa1 + 3 * L + i]
                    t2 = sa2 * g[oa2 + 3 * L + i]
                    mx = t0 * gx0 + t1 * gx1 + t2 * gx2
                    my = t0 * gy0 + t1 * gy1 + t2 * gy2
                    mz = t0 * gz0 + t1 * gz1 + t2 * gz2
                    w0[q0 + i] += (gx0 * mx + gy0 * my + gz0 * mz) * (sa0 * ia)
                    w0[q1 + i] += (gx1 * mx + gy1 * my + gz1 * mz) * (sa1 * ia)
                    w0[q2 + i] += (gx2 * mx + gy2 * my + gz2 * mz) * (sa2 * ia)
                    gx0, gy0, gz0 = g[ob0 + i], g[ob0 + L + i], g[ob0 + 2 * L + i]
                    gx1, gy1, gz1 = g[ob1 + i], g[ob1 + L + i], g[ob1 + 2 * L + i]
                    gx2, gy2, gz2 = g[ob2 + i], g[ob2 + L + i], g[ob2 + 2 * L + i]
                    t0 = sb0 * g[ob0 + 3 * L + i]
                    t1 = sb1 * g[ob1 + 3 * L + i]
                    t2 = sb2 * g[ob2 + 3 * L + i]
                    mx = t0 * gx0 + t1 * gx1 + t2 * gx2
                    my = t0 * gy0 + t1 * gy1 + t2 * gy2
                    mz = t0 * gz0 + t1 * gz1 + t2 * gz2
                    w1[q3 + i] += (gx0 * mx + gy0 * my + gz0 * mz) * (sb0 * ib)
                    w1[q4 + i] += (gx1 * mx + gy1 * my + gz1 * mz) * (sb1 * ib)
                    w1[q5 + i] += (gx2 * mx + gy2 * my + gz2 * mz) * (sb2 * ib)
                    bad[i] |= (abs(da) <= near_a) | (abs(db) <= near_b)
            for i in range(C * L):
                w[i] = w0[i] + w1[i]
                w0[i] = 0.0
                w1[i] = 0.0
            for i in range((R + 1) * L):
                acc[i] = 0.0
            for j in range(nonzero_row.shape[0]):  # the last row of rows is ones: the total weight
                oc = max(nonzero_row[j], 0) * L
                oa = max(nonzero_column[j], 0) * L
                v = nonzero_value[j]
                for i in range(M):
                    acc[oa + i] += w[oc + i] * v
            for i in range(n):
                j = chunk + order[start + i]
                t = acc[R * L + i]
                flags[j] = bad[i] | (not np.isfinite(t)) | (t == 0.0)
                inv = 1.0 / t
                for r in range(R):
                    out[j, r] = acc[r * L + i] * inv


@njit(nogil=True, error_model="numpy")
def _face_weights(p0, p1, p2, out, k0, k1, k2, w, scale_by):  # pragma: no cover - compiled
    """``w[k_j] += scale_by * w_j`` with Ju's weights ``w_j = G_j . m / D`` of a face whose corners minus the point are
    ``p0, p1, p2`` ((3,) each), as :func:`kpd.mvc._face_weights`; ``out`` is (3, 3) scratch for the G's."""
    ps = (p0, p1, p2)
    mx = 0.0
    my = 0.0
    mz = 0.0
    for j in range(3):
        a = ps[(j + 1) % 3]
        b = ps[(j + 2) % 3]
        gx = a[1] * b[2] - a[2] * b[1]
        gy = a[2] * b[0] - a[0] * b[2]
        gz = a[0] * b[1] - a[1] * b[0]
        out[j, 0] = gx
        out[j, 1] = gy
        out[j, 2] = gz
        length = np.sqrt(gx * gx + gy * gy + gz * gz)
        t = np.arctan2(length, a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / length
        mx += t * gx
        my += t * gy
        mz += t * gz
    big_d = p0[0] * out[0, 0] + p0[1] * out[0, 1] + p0[2] * out[0, 2]
    ks = (k0, k1, k2)
    for j in range(3):
        w[ks[j]] += scale_by * ((out[j, 0] * mx + out[j, 1] * my + out[j, 2] * mz) / big_d)


@njit(nogil=True, error_model="numpy")
def _segment_distance(x, a, b):  # pragma: no cover - compiled
    """Distance from ``x`` to the segment ``a b`` ((3,) each)."""
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    s = ((x[0] - a[0]) * ab0 + (x[1] - a[1]) * ab1 + (x[2] - a[2]) * ab2) / (ab0 * ab0 + ab1 * ab1 + ab2 * ab2)
    s = min(max(s, 0.0), 1.0)
    d0, d1, d2 = a[0] + s * ab0 - x[0], a[1] + s * ab1 - x[1], a[2] + s * ab2 - x[2]
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(nogil=True, error_model="numpy")
def _careful_rows(points, index, v, faces, n2, n2_norm, offset, scale, rows, out):  # pragma: no cover - compiled
    """``out[i] = careful weights of points[i] @ rows`` for i in ``index``: :func:`kpd.mvc._careful_row`'s rules
    (one-hot on a vertex, barycentric on a face, a lifted point for faces whose plane grazes the point), compiled.
    Returns -1, or the position in ``index`` of a point whose total weight is not finite and non-zero."""
    C = v.shape[0]
    F = faces.shape[0]
    R = rows.shape[1]
    w = np.empty(C)
    rel = np.empty((C, 3))
    delta = np.empty(F)
    bary = np.empty((F, 3))
    inside = np.empty(F, dtype=np.bool_)
    scratch = np.empty((3, 3))
    lifted = np.empty(3)
    q0, q1, q2 = np.empty(3), np.empty(3), np.empty(3)
    for q in range(index.shape[0]):
        x = points[index[q]]
        for c in range(C):
            w[c] = 0.0
        nearest = 0
        best = np.inf
        for c in range(C):
            for k in range(3):
                rel[c, k] = v[c, k] - x[k]
            dist = np.sqrt(rel[c, 0] * rel[c, 0] + rel[c, 1] * rel[c, 1] + rel[c, 2] * rel[c, 2])
            if dist < best:
                best = dist
                nearest = c
        if best <= _TOL_VERTEX * scale:
            w[nearest] = 1.0
        else:
            on_face = False
            for f in range(F):
                a, b, c = rel[faces[f, 0]], rel[faces[f, 1]], rel[faces[f, 2]]
                delta[f] = (offset[f] - (n2[f, 0] * x[0] + n2[f, 1] * x[1] + n2[f, 2] * x[2])) / n2_norm[f]
                ps = (a, b, c)
                lowest = np.inf
                for k in range(3):
                    u = ps[(k + 1) % 3]
                    t = ps[(k + 2) % 3]
                    gx = u[1] * t[2] - u[2] * t[1]
                    gy = u[2] * t[0] - u[0] * t[2]
                    gz = u[0] * t[1] - u[1] * t[0]
                    bary[f, k] = (n2[f, 0] * gx + n2[f, 1] * gy + n2[f, 2] * gz) / (n2_norm[f] * n2_norm[f])
                    lowest = min(lowest, bary[f, k])
                inside[f] = lowest >= -_TOL_INSIDE
                on_face |= (abs(delta[f]) <= _TOL_FACE * scale) and inside[f]
            if on_face:
                for f in range(F):
                    if abs(delta[f]) <= _TOL_FACE * scale and inside[f]:
                        for k in range(3):
                            w[faces[f, k]] += bary[f, k]
            else:
                for f in range(F):  # the faces whose plane does not graze x, then the grazing ones
                    grazing = abs(delta[f]) <= _TOL_PLANE * scale and not inside[f]
                    if grazing:
                        reach = np.inf
                        for k in range(3):
                            reach = min(reach, _segment_distance(x, v[faces[f, k]], v[faces[f, (k + 1) % 3]]))
                        height = min(_TOL_PLANE * scale, _LINEAR_FRACTION * reach)
                        if abs(delta[f]) < height:
                            continue
                    _face_weights(rel[faces[f, 0]], rel[faces[f, 1]], rel[faces[f, 2]], scratch, faces[f, 0],
                                  faces[f, 1], faces[f, 2], w, 1.0)
                for f in range(F):
                    if not (abs(delta[f]) <= _TOL_PLANE * scale and not inside[f]):
                        continue
                    reach = np.inf
                    for k in range(3):
                        reach = min(reach, _segment_distance(x, v[faces[f, k]], v[faces[f, (k + 1) % 3]]))
                    height = min(_TOL_PLANE * scale, _LINEAR_FRACTION * reach)
                    dl = delta[f]
                    if not abs(dl) < height:
                        continue
                    # x sits at signed distance dl below the plane; y = x + (dl - sign(dl) h) n sits at height h on
                    # the same side, and p - y = p - x - (dl - sign(dl) h) n
                    shift = dl - (-height if dl < 0 else height)
                    for k in range(3):
                        lifted[k] = shift * (n2[f, k] / n2_norm[f])
                    for k in range(3):
                        q0[k] = rel[faces[f, 0], k] - lifted[k]
                        q1[k] = rel[faces[f, 1], k] - lifted[k]
                        q2[k] = rel[faces[f, 2], k] - lifted[k]
                    _face_weights(q0, q1, q2, scratch, faces[f, 0], faces[f, 1], faces[f, 2], w, abs(dl) / height)
        total = 0.0
        for c in range(C):
            total += w[c]
        if not (np.isfinite(total) and total != 0.0):
            return q
        row = index[q]
        for r in range(R):
            acc = 0.0
            for c in range(C):
                acc += w[c] / total * rows[c, r]
            out[row, r] = acc
    return -1


def _schedule(faces: np.ndarray, face_edges: np.ndarray, n_edges: int):
    """An order of the faces that keeps each edge's two faces close, and when each edge is computed and kept.

    Faces are taken greedily, each time one with the most edges already computed (the first such in index order),
    so the computed edges still waiting for their second face stay few (tens for the rig cages). The faces go in
    pairs (a closed triangle mesh has an even number of faces); before each pair the edges it needs that are not
    computed yet are computed, in pairs, one edge early when their number is odd. A pair of edges takes a slot
    (of 8 rows) from when it is computed until the second face of both is done.

    Returns ``(order (F,), edges (E,) in computation order, step_edges (F/2 + 1,) edge-pair ranges per face pair,
    pair_slot (E/2,), face_row (F, 3) row of g of each corner's edge, slot count)``.
    """
    n_faces = len(faces)
    edge_faces = np.argsort(face_edges.ravel(), kind="stable").reshape(n_edges, 2) // 3  # (E, 2)
    done = np.zeros(n_edges, dtype=bool)
    known = np.zeros(n_faces, dtype=np.int64)  # computed edges per face
    taken = np.zeros(n_faces, dtype=bool)
    order = []
    for _ in range(n_faces):
        f = int(np.argmax(np.where(taken, -1, known)))
        taken[f] = True
        order.append(f)
        for e in face_edges[f]:
            if not done[e]:
                done[e] = True
                known[edge_faces[e]] += 1
    order = np.asarray(order, dtype=np.int64)
    position = np.empty(n_faces, dtype=np.int64)
    position[order] = np.arange(n_faces)
    first_pair = position[edge_faces].min(axis=1) // 2  # (E,) the face pair that first needs each edge
    last_pair = position[edge_faces].max(axis=1) // 2
    edges = np.argsort(first_pair, kind="stable")  # by first use
    needed = np.searchsorted(first_pair[edges], np.arange(n_faces // 2), side="right")  # edges done by each pair
    step_edges = np.concatenate([[0], (needed + 1) // 2]).astype(np.int64)  # edge pairs done by each pair
    pair_last = last_pair[edges].reshape(-1, 2).max(axis=1)  # (E/2,)
    pair_slot = np.empty(n_edges // 2, dtype=np.int64)
    free: list[int] = []
    used = 0
    release: dict[int, list[int]] = {}
    for s in range(n_faces // 2):
        for k in range(step_edges[s], step_edges[s + 1]):
            if free:
                pair_slot[k] = free.pop()
            else:
                pair_slot[k] = used
                used += 1
            release.setdefault(int(pair_last[k]), []).append(int(pair_slot[k]))
        free.extend(release.pop(s, []))
    row = np.empty(n_edges, dtype=np.int64)  # first of the 4 rows of g holding each edge
    row[edges] = 8 * np.repeat(pair_slot, 2) + 4 * (np.arange(n_edges) % 2)
    return order, edges, step_edges, pair_slot, row[face_edges[order]], used


class _Cage:
    """The cage's tables in the kernel's layout and frame (from :class:`kpd.mvc._Tables`)."""

    def __init__(self, t) -> None:
        v = t.vertices
        self.inv_size = float(np.ldexp(1.0, -np.frexp(t.scale)[1]))  # a power of two, so scaling is exact
        v = v * self.inv_size  # (C, 3) in the cage's frame
        self.center = v.mean(axis=0)
        rows = np.stack(t.rows, axis=1)  # (F, 3): edge row per corner, + E when the edge runs backwards
        order, edges, step_edges, pair_slot, face_row, slots = _schedule(t.faces, rows % t.E, t.E)
        self.slots, self.C = slots, t.C
        faces = t.faces[order]
        sign = np.where(rows[order] >= t.E, -1.0, 1.0)  # (F, 3)
        p0, p1, p2 = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
        n2 = np.cross(p1 - p0, p2 - p0)  # (F, 3) twice the area times the unit normal
        offset = np.einsum("fi,fi->f", n2, p0)  # D = offset - n2 . x
        near = (_TOL_PLANE * t.scale * self.inv_size) * np.linalg.norm(n2, axis=1)
        edge_ends = t.edges[edges]  # (E, 2)
        self.args = (
            self.center, self.inv_size,
            np.ascontiguousarray(v[:, 0]), np.ascontiguousarray(v[:, 1]), np.ascontiguousarray(v[:, 2]),
            np.ascontiguousarray(edge_ends[:, 0]), np.ascontiguousarray(edge_ends[:, 1]), pair_slot, step_edges,
            np.ascontiguousarray(face_row), sign, np.ascontiguousarray(faces.ravel()), np.ascontiguousarray(n2[:, 0]),
            np.ascontiguousarray(n2[:, 1]), np.ascontiguousarray(n2[:, 2]), offset, near,
        )

    def scratch(self, r: int) -> tuple:
        """One thread's work arrays: xs, g, lane_dot, lane_narrow, bad, w, w0, w1, acc (w0 and w1 zero: the kernel
        leaves them so)."""
        L = _LANES
        return (np.empty(3 * L), np.empty(8 * self.slots * L), np.empty(2 * L), np.empty(L, dtype=bool),
                np.empty(L, dtype=bool), np.empty(self.C * L),
                np.zeros(self.C * L), np.zeros(self.C * L), np.empty((r + 1) * L))


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
    a rig's edit basis (:class:`kpd.rig.Rig`). Work memory is a few hundred kilobytes per thread, whatever N; a
    row depends on its point alone (not on the other points, nor on the threads).

    Parameters
    ----------
    points : (N, 3) float64
    cage_vertices : (C, 3) float64
    cage_faces : (F, 3) int, outward-oriented, closed.
    rows : (C, R) float64, what each cage vertex carries.
    out : optional (N, R) float64 C-contiguous buffer to write into.
    threads : worker threads; ``min(2, cpu count)`` when ``None``.

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

    if np.may_share_memory(points, out):  # the kernel is told that its arrays do not overlap (_tune)
        points = points.copy()
    rows_and_ones = np.concatenate([rows, np.ones((t.C, 1))], axis=1)  # (C, R + 1)
    nonzero = [np.ascontiguousarray(a) for a in (*np.nonzero(rows_and_ones), rows_and_ones[rows_and_ones != 0])]

    def run(lo: int, hi: int) -> None:
        _project_range(points, lo, hi, *cage.args, *nonzero, r, out, flags, *cage.scratch(r))

    if threads == 1:
        run(0, n)
    else:  # pieces of a few chunks, taken by whichever thread is free (a row does not depend on the split)
        bounds = list(range(0, n, _CHUNKS_PER_TASK * _CHUNK)) + [n]
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(run, bounds[:-1], bounds[1:]))
    index = np.flatnonzero(flags)
    failed = _careful_rows(points, index, t.vertices, t.faces, t.n2, t.n2_norm, t.offset, t.scale, rows, out)
    if failed >= 0:
        x = points[index[failed]]
        raise KpdError(f"mean value coordinates failed at point {x.tolist()}: total weight not finite and non-zero")
    return out


def mvc_weights_compiled(points: Any, cage_vertices: Any, cage_faces: Any, *, threads: int | None = None
                         ) -> np.ndarray:
    """(N, C) float64: :func:`kpd.mvc.mvc_weights` by the compiled kernel (``mvc_project`` with the identity)."""
    c = len(np.asarray(cage_vertices))
    return mvc_project(points, cage_vertices, cage_faces, np.eye(c), threads=threads)
