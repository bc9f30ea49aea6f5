"""The compiled kernels of the straightening of slivers (:mod:`kpd.straighten`): the sparse pattern and terms of its
system over the merged points, rows and sub-matrices of it, the rings and parts of a region, and the slivers' steps
and seeds. Each reads only its arguments; :mod:`kpd.straighten` holds what they compute and why, and its slow twin
(:func:`kpd.straighten.straighten_basis_reference`) is the check of the whole.
"""

from __future__ import annotations

import numpy as np

from kpd._compiled import njit

__all__ = ["has_sliver"]


@njit(nogil=True)
def _graph_pattern(tri, point_of, same, n):  # pragma: no cover - compiled
    """CSR (indptr (n + 1,), indices) of the symmetric pattern of the triangles' edges plus the diagonal, each
    entry once, columns sorted; degenerate triangles (a repeated corner) add no edge. The triangles' corners are
    ``point_of[tri]`` (``tri`` itself when ``point_of`` is empty); only the triangles ``t`` with ``same[t] == t``
    (the first over their corners) are read."""
    count = np.ones(n + 1, dtype=np.int64)  # the diagonal
    count[0] = 0
    for t in range(tri.shape[0]):
        if same[t] != t:
            continue
        a, b, c = _corners(tri, point_of, t)
        if a == b or b == c or c == a:
            continue
        count[a + 1] += 2
        count[b + 1] += 2
        count[c + 1] += 2
    for i in range(n):
        count[i + 1] += count[i]
    fill = count[:-1].copy()
    other = np.empty(count[n], dtype=np.int32)  # n < 2**31: a mesh that large is refused before binding
    for i in range(n):
        other[fill[i]] = i
        fill[i] += 1
    for t in range(tri.shape[0]):
        if same[t] != t:
            continue
        a, b, c = _corners(tri, point_of, t)
        if a == b or b == c or c == a:
            continue
        other[fill[a]] = b
        other[fill[a] + 1] = c
        fill[a] += 2
        other[fill[b]] = c
        other[fill[b] + 1] = a
        fill[b] += 2
        other[fill[c]] = a
        other[fill[c] + 1] = b
        fill[c] += 2
    indptr = np.zeros(n + 1, dtype=np.int64)
    size = 0
    for i in range(n):
        lo, hi = count[i], count[i + 1]
        if hi - lo > 64:  # a fan's centre: a real sort
            other[lo:hi].sort()  # in place (assigning a sorted copy makes the first run's compiling slower)
        for j in range(lo + 1, hi):  # insertion sort: rows are short (a no-op after the sort)
            value = other[j]
            k = j - 1
            while k >= lo and other[k] > value:
                other[k + 1] = other[k]
                k -= 1
            other[k + 1] = value
        for j in range(lo, hi):
            if j == lo or other[j] != other[j - 1]:
                other[size] = other[j]  # size <= j: compacting in place
                size += 1
        indptr[i + 1] = size
    return indptr, other[:size].copy()


@njit(nogil=True, inline="always")
def _corners(tri, point_of, t):  # pragma: no cover - compiled
    """The three corners of triangle ``t``: ``tri[t]``, through ``point_of`` when it is not empty."""
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    if point_of.shape[0]:
        return point_of[a], point_of[b], point_of[c]
    return a, b, c


@njit(nogil=True, inline="always")
def _entry(indptr, indices, row, col):  # pragma: no cover - compiled
    """Position of (row, col) in a CSR pattern with sorted columns (it is there)."""
    lo, hi = indptr[row], indptr[row + 1] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if indices[mid] < col:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(nogil=True, error_model="numpy", inline="always")
def _sliver_weight(longest, height, cap):  # pragma: no cover - compiled
    """The weight of a sliver's straightness: its long edge over its height, squared, at most ``cap``."""
    return (longest / max(height, longest / np.sqrt(cap))) ** 2


@njit(nogil=True, error_model="numpy")
def _sliver_terms(points, tri, point_of, same, indptr, indices, thinness, inverse_reach2, ends_weight, cap,
                  sliver_values, anchor, sliver_ends, sliver_along, sliver_height,
                  piece):  # pragma: no cover - compiled
    """One pass over the triangles: the slivers' ``SᵀWS`` into the pattern (``sliver_values``); per sliver, in the
    order found, its third corner and long edge's ends (``sliver_ends``), the corner's place along that edge and its
    height; each point's anchor weight (``anchor``) and connected piece (``piece``, numbered from 0 in order of
    the points). Returns the number of slivers and the longest edge.

    A triangle whose corners an earlier one has (``same[t] != t``; -1: two equal corners) adds what it would add
    through that first one, which counts its copies: the same long edge, so the same terms. Not where two edges are
    equally longest: which one is taken depends on the order of the corners, so each copy adds its own, as it is."""
    n = points.shape[0]
    copies = np.zeros(tri.shape[0], dtype=np.int32)
    for t in range(tri.shape[0]):
        if same[t] >= 0:
            copies[same[t]] += 1
    for i in range(n):
        piece[i] = i  # union-find: each point's parent
    area = np.zeros(n)
    corner_of = np.zeros(n, dtype=np.bool_)
    slivers = 0
    longest_edge = 0.0
    for t in range(tri.shape[0]):
        first = same[t]
        if first < 0 or (first != t and copies[first] == 0):  # two equal corners; a copy counted already
            continue
        v = _corners(tri, point_of, t)
        a, b, c = v
        l0 = np.sqrt((points[c, 0] - points[b, 0]) ** 2 + (points[c, 1] - points[b, 1]) ** 2
                     + (points[c, 2] - points[b, 2]) ** 2)
        l1 = np.sqrt((points[a, 0] - points[c, 0]) ** 2 + (points[a, 1] - points[c, 1]) ** 2
                     + (points[a, 2] - points[c, 2]) ** 2)
        l2 = np.sqrt((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
                     + (points[b, 2] - points[a, 2]) ** 2)
        k, longest = 0, l0
        if l1 > longest:
            k, longest = 1, l1
        if l2 > longest:
            k, longest = 2, l2
        tied = (l0 == longest) + (l1 == longest) + (l2 == longest) > 1
        if first != t and not tied:
            continue  # added by its first copy
        times = 1.0
        if first == t and not tied:
            times = float(copies[t])
            copies[t] = 0  # its copies are counted (a tied one keeps its count: its copies add their own)
        if first == t:
            for x, y in ((a, b), (a, c)):
                while piece[x] != x:
                    piece[x] = piece[piece[x]]
                    x = piece[x]
                while piece[y] != y:
                    piece[y] = piece[piece[y]]
                    y = piece[y]
                if x != y:
                    piece[max(x, y)] = min(x, y)
        longest_edge = max(longest_edge, longest)
        ux, uy, uz = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        vx, vy, vz = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        twice_area = np.sqrt(nx * nx + ny * ny + nz * nz)
        area[a] += times * twice_area / 6.0
        area[b] += times * twice_area / 6.0
        area[c] += times * twice_area / 6.0
        height = twice_area / max(longest, 1e-300)
        if not height < thinness * longest:
            continue
        corner, start, end = v[k], v[(k + 1) % 3], v[(k + 2) % 3]
        ex, ey = points[end, 0] - points[start, 0], points[end, 1] - points[start, 1]
        ez = points[end, 2] - points[start, 2]
        dot = ((points[corner, 0] - points[start, 0]) * ex + (points[corner, 1] - points[start, 1]) * ey
               + (points[corner, 2] - points[start, 2]) * ez)
        s = min(max(dot / (ex * ex + ey * ey + ez * ez), 0.0), 1.0)
        weight = times * _sliver_weight(longest, height, cap)
        ends = (corner, start, end)
        coef = (1.0, s - 1.0, -s)
        corner_of[corner] = True
        sliver_ends[slivers, 0], sliver_ends[slivers, 1], sliver_ends[slivers, 2] = corner, start, end
        sliver_along[slivers] = s
        sliver_height[slivers] = height
        slivers += 1
        for i in range(3):
            for j in range(3):
                sliver_values[_entry(indptr, indices, ends[i], ends[j])] += weight * coef[i] * coef[j]
    mean_area = 0.0
    for i in range(n):
        mean_area += area[i]
    mean_area = max(mean_area / max(n, 1), 1e-300)
    for i in range(n):
        anchor[i] = (area[i] / mean_area + 1e-6) * (1.0 if corner_of[i] else ends_weight) * inverse_reach2
    pieces = 0
    for i in range(n):  # roots are the smallest point of their piece: number them in order, then the rest
        if piece[i] == i:
            piece[i] = -1 - pieces  # numbered roots are negative until the end
            pieces += 1
        else:
            root = piece[piece[i]]
            piece[i] = root if root < 0 else piece[root]  # a root below i is numbered already
    for i in range(n):
        piece[i] = -1 - piece[i]
    return slivers, longest_edge


@njit(nogil=True, error_model="numpy", inline="always")
def _row(i, indptr, indices, points, sliver_values, anchor, floor, out):  # pragma: no cover - compiled
    """Row ``i`` of the system into ``out`` (its pattern entries in order): the edges' stiffness ``-1 / l²`` (lengths
    floored at ``floor``) and on the diagonal their sum and the anchor, plus the slivers' terms. Returns the
    diagonal entry."""
    diagonal = anchor[i]
    at_diagonal = 0
    for e in range(indptr[i], indptr[i + 1]):
        j = indices[e]
        out[e - indptr[i]] = sliver_values[e]
        if j == i:
            at_diagonal = e - indptr[i]
        else:
            length = max(np.sqrt((points[i, 0] - points[j, 0]) ** 2 + (points[i, 1] - points[j, 1]) ** 2
                                 + (points[i, 2] - points[j, 2]) ** 2), floor)
            stiffness = 1.0 / (length * length)
            out[e - indptr[i]] -= stiffness
            diagonal += stiffness
    out[at_diagonal] += diagonal
    return out[at_diagonal]


@njit(nogil=True, error_model="numpy")
def _submatrix(indptr, indices, members, local, points, sliver_values, anchor, floor):  # pragma: no cover - compiled
    """CSR (indptr, indices, data) of the system's rows and columns ``members`` (sorted), renumbered by ``local``;
    entries whose column has no local number (-1: outside the region) are left out."""
    m = len(members)
    ptr = np.zeros(m + 1, dtype=np.int64)
    widest = 0
    for r in range(m):
        kept = 0
        for e in range(indptr[members[r]], indptr[members[r] + 1]):
            if local[indices[e]] >= 0:
                kept += 1
        ptr[r + 1] = ptr[r] + kept
        widest = max(widest, indptr[members[r] + 1] - indptr[members[r]])
    idx = np.empty(ptr[m], dtype=np.int32)
    val = np.empty(ptr[m])
    row = np.empty(widest)
    for r in range(m):
        i = members[r]
        _row(i, indptr, indices, points, sliver_values, anchor, floor, row)
        at = ptr[r]
        for e in range(indptr[i], indptr[i + 1]):
            if local[indices[e]] >= 0:
                idx[at] = local[indices[e]]
                val[at] = row[e - indptr[i]]
                at += 1
    return ptr, idx, val


@njit(nogil=True)
def _region_parts(indptr, indices, inside):  # pragma: no cover - compiled
    """The connected parts of the graph restricted to ``inside`` (n,) bool: (n,) part numbers (-1 outside), in
    order of their smallest point, and (n,) whether an inside point has a neighbour outside."""
    n = len(inside)
    part = np.full(n, -1, dtype=np.int64)
    rim = np.zeros(n, dtype=np.bool_)
    stack = np.empty(n, dtype=np.int64)
    parts = 0
    for start in np.flatnonzero(inside):
        if part[start] >= 0:
            continue
        part[start] = parts
        top = 1
        stack[0] = start
        while top:
            top -= 1
            i = stack[top]
            for e in range(indptr[i], indptr[i + 1]):
                j = indices[e]
                if not inside[j]:
                    rim[i] = True
                elif part[j] < 0:
                    part[j] = parts
                    stack[top] = j
                    top += 1
        parts += 1
    return part, rim


@njit(nogil=True)
def _rings(indptr, indices, sources, rings):  # pragma: no cover - compiled
    """(n,) bool: the points within ``rings`` edges of ``sources`` (breadth first from all of them at once)."""
    n = len(indptr) - 1
    depth = np.full(n, -1, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    tail = 0
    for s in sources:
        if depth[s] < 0:
            depth[s] = 0
            queue[tail] = s
            tail += 1
    head = 0
    while head < tail:
        i = queue[head]
        head += 1
        if depth[i] >= rings:
            continue
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if depth[j] < 0:
                depth[j] = depth[i] + 1
                queue[tail] = j
                tail += 1
    return depth >= 0


@njit(nogil=True, error_model="numpy")
def _beyond_rim(indptr, indices, points, sliver_values, anchor, floor, rim, inside, slot, values,
                tolerance):  # pragma: no cover - compiled
    """The points outside the region next to its ``rim`` whose correction, one Jacobi step from the region's
    (``-Σ_i A_ji D_i / A_jj``), exceeds ``tolerance`` in some column (the region's correction in ``values`` at
    each point's ``slot``, :class:`_Correction`)."""
    k = values.shape[1]
    seen = np.zeros(len(inside), dtype=np.bool_)
    estimate = np.empty(k)
    row = np.empty(1)
    out = []
    for i in rim:
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if inside[j] or seen[j]:
                continue
            seen[j] = True
            if len(row) < indptr[j + 1] - indptr[j]:
                row = np.empty(indptr[j + 1] - indptr[j])
            _row(j, indptr, indices, points, sliver_values, anchor, floor, row)
            estimate[:] = 0.0
            diagonal = 1.0
            for f in range(indptr[j], indptr[j + 1]):
                col = indices[f]
                if col == j:
                    diagonal = row[f - indptr[j]]
                elif inside[col] and slot[col] >= 0:
                    for c in range(k):
                        estimate[c] -= row[f - indptr[j]] * values[slot[col], c]
            for c in range(k):
                if abs(estimate[c]) > tolerance * diagonal:
                    out.append(j)
                    break
    return np.array(out, dtype=np.int64)


@njit(nogil=True, error_model="numpy")
def _held_rhs(indptr, indices, points, sliver_values, anchor, floor, rows, patch, basis, slot,
              values):  # pragma: no cover - compiled
    """(len(rows), K): the right-hand side of the system's ``rows`` with the points outside ``patch`` (n,) bool
    held at their correction D (``values`` at each point's ``slot``, :class:`_Correction`):
    ``-(Sᵀ W S basis)[rows] - A[rows, outside] D[outside]``."""
    k = basis.shape[1]
    out = np.zeros((len(rows), k))
    row = np.empty(1)
    for r in range(len(rows)):
        i = rows[r]
        if len(row) < indptr[i + 1] - indptr[i]:
            row = np.empty(indptr[i + 1] - indptr[i])
        _row(i, indptr, indices, points, sliver_values, anchor, floor, row)
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            value = sliver_values[e]
            if value != 0.0:
                for c in range(k):
                    out[r, c] -= value * basis[j, c]
            if not patch[j] and slot[j] >= 0:
                value = row[e - indptr[i]]
                for c in range(k):
                    out[r, c] -= value * values[slot[j], c]
    return out


@njit(nogil=True)
def _has_outside(indptr, indices, rows, inside):  # pragma: no cover - compiled
    """(len(rows),) bool: whether each of ``rows`` has a neighbour outside ``inside``."""
    out = np.zeros(len(rows), dtype=np.bool_)
    for r in range(len(rows)):
        for e in range(indptr[rows[r]], indptr[rows[r] + 1]):
            if not inside[indices[e]]:
                out[r] = True
                break
    return out


@njit(nogil=True)
def _rows_times(indptr, indices, data, rows, basis):  # pragma: no cover - compiled
    """(len(rows), K): ``-(M @ basis)[rows]`` for the CSR matrix M (indptr, indices, data)."""
    out = np.zeros((len(rows), basis.shape[1]))
    for r in range(len(rows)):
        for e in range(indptr[rows[r]], indptr[rows[r] + 1]):
            value = data[e]
            if value != 0.0:
                j = indices[e]
                for c in range(basis.shape[1]):
                    out[r, c] -= value * basis[j, c]
    return out


@njit(nogil=True, error_model="numpy")
def _sliver_steps(points, indptr, indices, sliver_values, anchor, floor, ends, along, height, cap
                  ):  # pragma: no cover - compiled
    """(S,) each sliver's Jacobi step from no correction per unit of straightness, at the corner it moves most: its
    weight (:func:`_sliver_weight`) times that corner's coefficient over the corner's diagonal entry of the system
    (:func:`_row`; on a thin sliver of a native mesh its weight is most of the diagonal, and the step is 1). It does
    not depend on the basis: made with the system. The diagonal is made for the slivers' corners only."""
    n = points.shape[0]
    step = np.empty(ends.shape[0])
    diagonal = np.full(n, -1.0)  # made on first use
    row = np.empty(1)
    for s in range(ends.shape[0]):
        c, a, b = ends[s, 0], ends[s, 1], ends[s, 2]
        t = along[s]
        for i in (c, a, b):
            if diagonal[i] < 0.0:
                if len(row) < indptr[i + 1] - indptr[i]:
                    row = np.empty(indptr[i + 1] - indptr[i])
                diagonal[i] = _row(i, indptr, indices, points, sliver_values, anchor, floor, row)
        longest = np.sqrt((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
                          + (points[b, 2] - points[a, 2]) ** 2)
        w = _sliver_weight(longest, height[s], cap)
        step[s] = max(w / diagonal[c], w * (1.0 - t) / diagonal[a], w * t / diagonal[b])
    return step


@njit(nogil=True, error_model="numpy")
def _sliver_seeds(lo, hi, merged, ends, along, height, step, tolerance, move, seed):  # pragma: no cover - compiled
    """``seed`` (n,) bool set at the corners of the slivers ``lo:hi`` whose own term alone would move one of their
    corners by more than ``tolerance`` in a keypoint's column, or move its third corner across its height for a
    ``move`` of every keypoint: one Jacobi step from no correction, the straightness ``r`` (off in ``merged``
    (n, K)) times the sliver's ``step`` (:func:`_sliver_steps`). Only ever sets True: two threads may share
    ``seed``."""
    k = merged.shape[1]
    for s in range(lo, hi):
        c, a, b = ends[s, 0], ends[s, 1], ends[s, 2]
        t = along[s]
        largest, total = 0.0, 0.0
        for j in range(k):
            off = abs(merged[c, j] - (1.0 - t) * merged[a, j] - t * merged[b, j])
            largest = max(largest, off)
            total += off
        if largest * step[s] > tolerance or total * step[s] * move > height[s]:
            seed[c] = True
            seed[a] = True
            seed[b] = True


@njit(nogil=True, error_model="numpy")
def has_sliver(points, tri, thinness):  # pragma: no cover - compiled
    """Whether any triangle's height is below ``thinness`` times its longest edge (:func:`_thin_triangles`)."""
    for t in range(tri.shape[0]):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        l0 = ((points[c, 0] - points[b, 0]) ** 2 + (points[c, 1] - points[b, 1]) ** 2
              + (points[c, 2] - points[b, 2]) ** 2)
        l1 = ((points[a, 0] - points[c, 0]) ** 2 + (points[a, 1] - points[c, 1]) ** 2
              + (points[a, 2] - points[c, 2]) ** 2)
        l2 = ((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
              + (points[b, 2] - points[a, 2]) ** 2)
        longest = np.sqrt(max(l0, l1, l2))
        ux, uy, uz = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        vx, vy, vz = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        if np.sqrt(nx * nx + ny * ny + nz * nz) / max(longest, 1e-300) < thinness * longest:
            return True
    return False


@njit(nogil=True, error_model="numpy")
def _triangle_shapes(points, tri, apex, longest, twice_area):  # pragma: no cover - compiled
    """Per triangle: the corner opposite the longest edge (the first on ties), that edge's length and twice the
    area (|(b - a) x (c - a)|)."""
    for t in range(tri.shape[0]):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        ax, ay, az = points[a, 0], points[a, 1], points[a, 2]
        bx, by, bz = points[b, 0], points[b, 1], points[b, 2]
        cx, cy, cz = points[c, 0], points[c, 1], points[c, 2]
        l0 = np.sqrt((cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2)
        l1 = np.sqrt((ax - cx) ** 2 + (ay - cy) ** 2 + (az - cz) ** 2)
        l2 = np.sqrt((bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2)
        k, best = 0, l0
        if l1 > best:
            k, best = 1, l1
        if l2 > best:
            k, best = 2, l2
        apex[t] = k
        longest[t] = best
        ux, uy, uz = bx - ax, by - ay, bz - az
        vx, vy, vz = cx - ax, cy - ay, cz - az
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        twice_area[t] = np.sqrt(nx * nx + ny * ny + nz * nz)
