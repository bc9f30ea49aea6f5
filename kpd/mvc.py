"""Mean value coordinates of points with respect to a closed triangle cage (docs/method.md §5).

Ju, Schaefer & Warren (2005), "Mean value coordinates for closed triangular meshes". For a point x and a face with
corners p_0, p_1, p_2, write G_k = (p_{k+1} - x) × (p_{k+2} - x) (the normal of the plane through x and the edge
opposite corner k, pointing into the face's cone when x sees the face from inside),
θ_k = atan2(``|G_k|``, (p_{k+1} - x) · (p_{k+2} - x)) the angle that edge subtends at x, and
D = det[p_0 - x, p_1 - x, p_2 - x] = 2·area·(signed distance of x to the face's plane). The mean vector of the face's
spherical triangle is m = ½ Σ_k θ_k G_k / ``|G_k|`` and the face adds

    w_k = G_k · m / D

to corner k's weight: Ju's ``w_i = n_i·m / (n_i·u_i) / d_i`` with every factor written in x-relative vectors, so no
sqrt(1 - c²) and no 3×3 determinant per pair. The sign of D carries Ju's ``sign(det)``, so the same formula holds
outside the cage, where the coordinates extend smoothly (and may be negative): the total weight is positive inside
and negative outside, never zero, and weights are normalised to sum to one. Near a face's interior the face's own
weights grow like 1/distance, with a relative rounding error common to its three corners, so the normalised result
stays accurate to ~1e-15 down to the special case below.

Degenerate positions, with distances relative to the cage's size (``max |vertex - centroid|``):

- within ``1e-12`` of a cage vertex: one-hot at that vertex;
- within ``1e-12`` of a face's plane and inside the face (edges included): the barycentric coordinates of the face,
  averaged over the faces touched (points on edges get the edge's linear interpolation);
- within ``1e-6`` of a face's plane but outside the face: the face's share tends to zero linearly at the plane
  (Ju's coplanar rule drops it), but the formula is 0/0 there and rounding would dominate. It is evaluated at a
  point lifted off the plane (by 1e-3 of the distance to the face) and scaled back linearly. This matters near
  vertices and edges, where such a face's share is large.

The fast kernel sends the rare points within ``1e-6`` of some face's plane, or with a non-finite total, to a careful
per-point path that applies these rules. Points very far from the cage (over ~100 cage sizes) lose accuracy
(the linear precision error grows like distance² × 1e-16) but stay finite and sum to one.

:func:`mvc_weights` is the fast kernel (per point-vertex, per point-edge and per point-face arrays, chunked over
points, in threads); :func:`mvc_weights_reference` is Ju's pseudo-code as a plain per-point loop, for tests.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from kpd.cage import check_cage, edge_table
from kpd.errors import InputError, KpdError
from kpd.geometry import as_points

__all__ = ["mvc_weights", "mvc_weights_reference"]

_TOL_VERTEX = 1e-12  # one-hot within this distance of a vertex (times the cage scale)
_TOL_FACE = 1e-12  # barycentric within this distance of a face's plane, inside the face
_TOL_PLANE = 1e-6  # this close to a face's plane, outside the face: its share is taken from a lifted point
_LINEAR_FRACTION = 1e-3  # the lift height, as a fraction of the point's distance to that face
_TOL_INSIDE = 1e-9  # barycentric slack of "inside the face"
_EPS_REFERENCE = 1e-300  # Ju's |s_i| <= eps rule in the reference
_DEFAULT_CHUNK = 256  # points per chunk: the ~25 (E, chunk) float64 work arrays stay near the L2 cache
_MAX_THREADS = 2


class _Tables:
    """Everything about one cage that the kernel needs, computed once per call."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.vertices, self.faces = vertices, faces
        self.C, self.F = len(vertices), len(faces)
        edges, face_edges = edge_table(faces, self.C)
        self.edges, self.E = edges, len(edges)
        self.ends = np.ascontiguousarray(edges.T.ravel())  # (2E,) the a's, then the b's
        counts = np.bincount(face_edges.ravel(), minlength=self.E)
        if (counts != 2).any():
            bad = int(np.flatnonzero(counts != 2)[0])
            raise InputError(
                "the cage must be a closed surface (every edge in exactly two faces); "
                f"edge {edges[bad].tolist()} is in {int(counts[bad])}"
            )
        used = np.bincount(faces.ravel(), minlength=self.C)
        if (used == 0).any():
            raise InputError(f"every cage vertex must belong to a face; vertex {int(np.argmin(used))} is in none")
        # The edge opposite corner k runs faces[k+1] -> faces[k+2]. Per-edge arrays hold both directions: row e is
        # edge (a, b) with a < b as stored, row E + e the reverse (G and θG/|G| change sign).
        start = faces[:, [1, 2, 0]]
        reverse = start != edges[face_edges, 0]  # (F, 3)
        self.rows = [np.ascontiguousarray(face_edges[:, k] + self.E * reverse[:, k]) for k in range(3)]
        # Scatter of the 3F corner weights (row k*F + f, plus a zero row 3F) to vertices: slot s of vertex j is the
        # s-th corner at j, or the zero row.
        vert = faces.T.ravel()  # (3F,)
        order = np.argsort(vert, kind="stable")
        slots = np.full((int(used.max()), self.C), 3 * self.F, dtype=np.int64)
        rank = np.arange(3 * self.F) - np.searchsorted(vert[order], vert[order])
        slots[rank, vert[order]] = order
        self.slots = [np.ascontiguousarray(s) for s in slots]
        p0, p1, p2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
        n2 = np.cross(p1 - p0, p2 - p0)  # (F, 3) twice the area times the unit normal
        self.n2 = n2
        self.n2_norm = np.linalg.norm(n2, axis=1)
        self.offset = np.einsum("fi,fi->f", n2, p0)  # D = offset - n2 . x
        self.scale = float(np.max(np.linalg.norm(vertices - vertices.mean(axis=0), axis=1)))
        # A point goes to the careful path when |D| <= near for some face (within _TOL_PLANE of its plane).
        near = (_TOL_PLANE * self.scale) * self.n2_norm
        self.col = {
            name: np.ascontiguousarray(arr)[:, None]
            for name, arr in (
                ("px", vertices[:, 0]), ("py", vertices[:, 1]), ("pz", vertices[:, 2]), ("offset", self.offset),
                ("nx", n2[:, 0]), ("ny", n2[:, 1]), ("nz", n2[:, 2]), ("near", near),
            )
        }


class _Workspace:
    """Scratch arrays of one thread for chunks of ``n`` points, reused across chunks."""

    def __init__(self, t: _Tables, n: int) -> None:
        C, E, F = t.C, t.E, t.F
        self.n = n
        self.x = np.empty((3, n))
        self.dv = [np.empty((C, n)) for _ in range(3)]  # p_j - x, per component
        # Per component: rows [0, E) hold p_a - x and [E, 2E) p_b - x; then θ G / |G| for both directions.
        self.ab = [np.empty((2 * E, n)) for _ in range(3)]
        self.g = [np.empty((2 * E, n)) for _ in range(3)]  # G = (p_a - x) x (p_b - x), both directions
        self.e1, self.e2, self.e3 = np.empty((E, n)), np.empty((E, n)), np.empty((E, n))
        self.m = [np.empty((F, n)) for _ in range(3)]
        self.f1, self.f2, self.d = np.empty((F, n)), np.empty((F, n)), np.empty((F, n))
        self.w = np.zeros((3 * F + 1, n))  # corner weights; the last row stays zero
        self.wc = np.empty((C, n))
        self.tot = np.empty((1, n))


def _kernel(t: _Tables, pts: np.ndarray, out: np.ndarray, ws: _Workspace) -> np.ndarray:
    """Normalised weights of ``pts (n, 3)`` into ``out (n, C)``. Returns ``(n,)`` bool: points to redo carefully
    (within _TOL_PLANE of a face's plane, or a total weight that is not finite and non-zero)."""
    E, F = t.E, t.F
    x = ws.x
    np.copyto(x, pts.T)
    xs = [x[i : i + 1] for i in range(3)]  # (1, n) rows
    c = t.col
    for i, p in enumerate((c["px"], c["py"], c["pz"])):
        np.subtract(p, xs[i], out=ws.dv[i])  # (C, n)
    ab, g = ws.ab, ws.g
    for i in range(3):
        np.take(ws.dv[i], t.ends, axis=0, out=ab[i], mode="clip")  # (2E, n)
    a, b = [v[:E] for v in ab], [v[E:] for v in ab]
    tmp, length, theta = ws.e1, ws.e2, ws.e3
    for i in range(3):  # G = a x b
        j, k = (i + 1) % 3, (i + 2) % 3
        gi = g[i][:E]
        np.multiply(a[j], b[k], out=gi)
        np.multiply(a[k], b[j], out=tmp)
        gi -= tmp
    np.square(g[0][:E], out=length)
    for i in (1, 2):
        np.square(g[i][:E], out=tmp)
        length += tmp
    np.sqrt(length, out=length)  # |G| = |a||b| sin θ
    np.multiply(a[0], b[0], out=theta)
    for i in (1, 2):
        np.multiply(a[i], b[i], out=tmp)
        theta += tmp  # a . b = |a||b| cos θ
    np.arctan2(length, theta, out=theta)  # θ, accurate at every angle
    np.divide(theta, length, out=tmp)  # θ / |G|
    h = ab  # a and b are no longer needed
    for i in range(3):
        np.multiply(g[i][:E], tmp, out=h[i][:E])
        np.negative(h[i][:E], out=h[i][E:])
        np.negative(g[i][:E], out=g[i][E:])
    # Per face: m = Σ_k θ_k G_k / |G_k|, D = det[p_0 - x, p_1 - x, p_2 - x], w_k = G_k . m / D.
    f1, d = ws.f1, ws.d
    r0, r1, r2 = t.rows
    for i in range(3):
        m = ws.m[i]
        np.take(h[i], r0, axis=0, out=m, mode="clip")
        np.take(h[i], r1, axis=0, out=f1, mode="clip")
        m += f1
        np.take(h[i], r2, axis=0, out=f1, mode="clip")
        m += f1
    np.multiply(c["nx"], xs[0], out=d)
    np.multiply(c["ny"], xs[1], out=f1)
    d += f1
    np.multiply(c["nz"], xs[2], out=f1)
    d += f1
    np.subtract(c["offset"], d, out=d)  # D = n2 . (p_0 - x)
    np.abs(d, out=f1)
    redo = (f1 <= c["near"]).any(axis=0)  # (n,)
    np.divide(1.0, d, out=d)
    for k in range(3):
        wk = ws.w[k * F : (k + 1) * F]
        np.take(g[0], t.rows[k], axis=0, out=wk, mode="clip")
        wk *= ws.m[0]
        for i in (1, 2):
            np.take(g[i], t.rows[k], axis=0, out=f1, mode="clip")
            f1 *= ws.m[i]
            wk += f1
        wk *= d
    # Scatter the corners to the vertices, normalise, transpose into the output.
    wc = ws.wc
    np.take(ws.w, t.slots[0], axis=0, out=wc, mode="clip")
    for slot in t.slots[1:]:
        np.take(ws.w, slot, axis=0, out=ws.dv[0], mode="clip")
        wc += ws.dv[0]
    np.sum(wc, axis=0, keepdims=True, out=ws.tot)
    wc /= ws.tot
    np.copyto(out, wc.T)
    tot = ws.tot[0]
    redo |= ~np.isfinite(tot) | (tot == 0)
    return redo


def _run_block(t: _Tables, points: np.ndarray, out: np.ndarray, chunk: int) -> np.ndarray:
    """Kernel over consecutive chunks of ``points``; returns the flags."""
    ws = _Workspace(t, min(chunk, len(points)))
    flags = np.empty(len(points), dtype=bool)
    # Degenerate points divide by zero here; they are flagged and redone. (errstate is per thread.)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for start in range(0, len(points), chunk):
            stop = min(start + chunk, len(points))
            if stop - start != ws.n:
                ws = _Workspace(t, stop - start)
            flags[start:stop] = _kernel(t, points[start:stop], out[start:stop], ws)
    return flags


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products ``(..., 3) -> (...)``, summed left to right (the compiled twin,
    :func:`kpd.mvc_fast._careful_rows`, sums the same way, so the two round alike)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


_libm_atan2 = np.frompyfunc(math.atan2, 2, 1)  # the C library's, as compiled code calls it (numpy's may be SIMD)


def _face_weights(p: np.ndarray) -> np.ndarray:
    """Ju's weights of whole faces: ``p (F', 3, 3)`` are the corners minus the point -> ``(F', 3)`` w_k = G_k.m / D."""
    g = np.stack([np.cross(p[:, (k + 1) % 3], p[:, (k + 2) % 3]) for k in range(3)], axis=1)  # (F', 3, 3)
    length = np.sqrt(_rowdot(g, g))  # (F', 3)
    dots = np.stack([_rowdot(p[:, (k + 1) % 3], p[:, (k + 2) % 3]) for k in range(3)], axis=1)
    t = _libm_atan2(length, dots).astype(np.float64) / length  # (F', 3)
    m = t[:, 0, None] * g[:, 0] + t[:, 1, None] * g[:, 1] + t[:, 2, None] * g[:, 2]  # (F', 3)
    return _rowdot(g, m[:, None, :]) / _rowdot(p[:, 0], g[:, 0])[:, None]


def _segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from ``x (3,)`` to the segments ``a (F', 3)`` - ``b (F', 3)``."""
    ab = b - a
    s = np.clip(_rowdot(x - a, ab) / _rowdot(ab, ab), 0.0, 1.0)
    d = a + s[:, None] * ab - x
    return np.sqrt(_rowdot(d, d))


def _careful_row(t: _Tables, x: np.ndarray) -> np.ndarray:
    """Normalised weights of one point, with the vertex and face rules and care near face planes.

    Near a face's plane the lifted share below is steep (it scales with the point's distance to the plane over a
    height of 1e-6), so the rounding of that distance shows in the weights at ~1e-10; every sum here runs in a fixed
    order and the arctangent is the C library's, as in :func:`kpd.mvc_fast._careful_rows`, so that the numpy and the
    compiled path round alike."""
    v, faces = t.vertices, t.faces
    rel = v - x  # (C, 3)
    dist = np.sqrt(_rowdot(rel, rel))  # (C,)
    j = int(np.argmin(dist))
    w = np.zeros(t.C)
    if dist[j] <= _TOL_VERTEX * t.scale:
        w[j] = 1.0
        return w
    p = rel[faces]  # (F, 3, 3) corners relative to x
    delta = (t.offset - _rowdot(t.n2, x)) / t.n2_norm  # (F,) signed distance to each plane
    # Barycentric coordinates of x's projection: corner k gets n2 . (p_{k+1} - x) x (p_{k+2} - x) / |n2|^2.
    bary = np.stack(
        [_rowdot(t.n2, np.cross(p[:, (k + 1) % 3], p[:, (k + 2) % 3])) for k in range(3)], axis=1
    ) / (t.n2_norm * t.n2_norm)[:, None]  # (F, 3)
    inside = bary.min(axis=1) >= -_TOL_INSIDE
    on_face = (np.abs(delta) <= _TOL_FACE * t.scale) & inside
    if on_face.any():
        np.add.at(w, faces[on_face].ravel(), bary[on_face].ravel())
        return w / w.sum()
    # A face whose plane passes within _TOL_PLANE of x, outside the face, adds a share that vanishes linearly as x
    # reaches the plane, while the formula turns into 0/0 there. Evaluate it at a point lifted off the plane, at a
    # height that is small next to x's distance to the face, and scale it down linearly.
    grazing = np.flatnonzero((np.abs(delta) <= _TOL_PLANE * t.scale) & ~inside)
    reach = np.min(
        [_segment_distance(x, v[faces[grazing, k]], v[faces[grazing, (k + 1) % 3]]) for k in range(3)], axis=0
    )  # (G,) distance from x to each grazing face
    height = np.minimum(_TOL_PLANE * t.scale, _LINEAR_FRACTION * reach)
    low = np.abs(delta[grazing]) < height
    lift, height = grazing[low], height[low]
    plain = np.ones(t.F, dtype=bool)
    plain[lift] = False
    np.add.at(w, faces[plain].ravel(), _face_weights(p[plain]).ravel())
    if len(lift):
        unit = t.n2[lift] / t.n2_norm[lift, None]  # (L, 3)
        dl = delta[lift]
        # x sits at signed distance delta below the plane (delta = n.(p_0 - x)); y = x + (delta - sign(delta) h) n
        # sits at height h on the same side, and p - y = p - x - (delta - sign(delta) h) n.
        shift = (dl - np.where(dl < 0, -height, height))[:, None, None] * unit[:, None, :]
        share = _face_weights(p[lift] - shift) * (np.abs(dl) / height)[:, None]
        np.add.at(w, faces[lift].ravel(), share.ravel())
    total = w.sum()
    if not (np.isfinite(total) and total != 0):
        raise KpdError(f"mean value coordinates failed at point {x.tolist()}: total weight {total}")
    return w / total


def _prepare(points: Any, cage_vertices: Any, cage_faces: Any) -> tuple[np.ndarray, _Tables]:
    points = as_points(points, min_count=0)
    vertices, faces = check_cage(cage_vertices, cage_faces)
    return points, _Tables(vertices, faces)


def mvc_weights(
    points: Any, cage_vertices: Any, cage_faces: Any, *, chunk: int | None = None, threads: int | None = None
) -> np.ndarray:
    """Mean value coordinates of points with respect to a closed, outward-oriented triangle cage.

    ``weights @ cage_vertices`` reproduces every point inside the cage (linear precision), and moving the cage
    vertices to ``c'`` moves the points to ``weights @ c'``. Works for points on faces, edges and vertices, and
    outside the cage (where the coordinates extend smoothly and may be negative).

    Parameters
    ----------
    points : (N, 3) float64
    cage_vertices : (C, 3) float64
    cage_faces : (F, 3) int, outward-oriented, closed (every edge in two faces).
    chunk : points per chunk (work memory per thread: about 25 × chunk × E float64, E = 1.5 F edges); 256 when
        ``None``.
    threads : worker threads; ``min(2, cpu count)`` when ``None``. The result does not depend on it.

    Returns
    -------
    weights : (N, C) float64, rows sum to 1.
    """
    points, t = _prepare(points, cage_vertices, cage_faces)
    chunk = _DEFAULT_CHUNK if chunk is None else chunk
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise InputError(f"chunk must be a positive integer; got {chunk!r}")
    if threads is None:
        threads = min(_MAX_THREADS, os.cpu_count() or 1)
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InputError(f"threads must be a positive integer; got {threads!r}")
    n = len(points)
    out = np.empty((n, t.C))
    if n == 0:
        return out
    chunk = int(chunk)
    # Whole chunks per thread, in contiguous blocks.
    n_chunks = -(-n // chunk)
    threads = int(min(threads, n_chunks))
    bounds = [min(n, (n_chunks * i // threads) * chunk) for i in range(threads + 1)]
    if threads == 1:
        flags = _run_block(t, points, out, chunk)
    else:
        with ThreadPoolExecutor(threads) as pool:  # numpy releases the GIL inside its loops
            parts = pool.map(
                lambda i: _run_block(t, points[bounds[i] : bounds[i + 1]], out[bounds[i] : bounds[i + 1]], chunk),
                range(threads),
            )
            flags = np.concatenate(list(parts))
    for i in np.flatnonzero(flags):
        out[i] = _careful_row(t, points[i])
    return out


def mvc_weights_reference(points: Any, cage_vertices: Any, cage_faces: Any) -> np.ndarray:
    """Slow reference for :func:`mvc_weights`: Ju et al.'s pseudo-code, one point and one face at a time.

    The half-angle form: θ_i = 2 asin(l_i / 2), h = Σθ_i / 2,
    c_i = 2 sin h sin(h - θ_i) / (sin θ_{i+1} sin θ_{i-1}) - 1, s_i = sign(det[u_1, u_2, u_3]) sqrt(1 - c_i²),
    w_i = (θ_i - c_{i+1} θ_{i-1} - c_{i-1} θ_{i+1}) / (d_i sin θ_{i+1} s_{i-1}), a face dropped when some s_i is 0
    (Ju's coplanar rule), and the same one-hot and on-face rules as :func:`mvc_weights`. Its rounding grows near
    faces and edges (sqrt(1 - c²), asin near 1): trust it to ~1e-10 only farther than ~1e-3 from the cage's faces,
    or exactly on them.
    """
    points, t = _prepare(points, cage_vertices, cage_faces)
    v, faces = t.vertices.tolist(), t.faces.tolist()
    out = np.zeros((len(points), t.C))
    for n, x in enumerate(points.tolist()):
        rel = [[p[0] - x[0], p[1] - x[1], p[2] - x[2]] for p in v]
        d = [math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2) for r in rel]
        j = min(range(t.C), key=d.__getitem__)
        if d[j] <= _TOL_VERTEX * t.scale:
            out[n, j] = 1.0
            continue
        u = [[r[0] / dj, r[1] / dj, r[2] / dj] for r, dj in zip(rel, d)]
        w = [0.0] * t.C
        on_face = False
        for f, face in enumerate(faces):
            normal, area2 = t.n2[f].tolist(), float(t.n2_norm[f])
            q = [rel[i] for i in face]
            delta = sum(normal[k] * q[0][k] for k in range(3)) / area2
            bary = [_dot(normal, _cross(q[(k + 1) % 3], q[(k + 2) % 3])) / area2**2 for k in range(3)]
            inside = min(bary) >= -_TOL_INSIDE
            if abs(delta) <= _TOL_FACE * t.scale and inside:
                if not on_face:
                    w, on_face = [0.0] * t.C, True
                for k in range(3):
                    w[face[k]] += bary[k]
                continue
            if on_face:
                continue
            uu = [u[i] for i in face]
            dd = [d[i] for i in face]
            theta = [2.0 * math.asin(min(1.0, _norm(_sub(uu[(k + 1) % 3], uu[(k + 2) % 3])) / 2.0)) for k in range(3)]
            h = sum(theta) / 2.0
            sin = [math.sin(th) for th in theta]
            c = [2.0 * math.sin(h) * math.sin(h - th) / (sin[(k + 1) % 3] * sin[(k + 2) % 3]) - 1.0
                 for k, th in enumerate(theta)]
            sgn = math.copysign(1.0, _dot(uu[0], _cross(uu[1], uu[2])))
            s = [sgn * math.sqrt(max(0.0, 1.0 - ck * ck)) for ck in c]
            if min(abs(sk) for sk in s) <= _EPS_REFERENCE:
                continue  # Ju's rule: x on the face's plane, outside it
            for k in range(3):
                kp, km = (k + 1) % 3, (k + 2) % 3
                w[face[k]] += (theta[k] - c[kp] * theta[km] - c[km] * theta[kp]) / (dd[k] * sin[kp] * s[km])
        total = sum(w)
        out[n] = np.asarray(w) / total
    return out


def _dot(a: list, b: list) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: list, b: list) -> list:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _sub(a: list, b: list) -> list:
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def _norm(a: list) -> float:
    return math.sqrt(_dot(a, a))
