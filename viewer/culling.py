"""What a frame draws: the triangles of a mesh that show in a pixel (:func:`visible_triangles`).

A scan-sized mesh seen in a window has several triangles a pixel, most of them hidden or between the sample points;
drawing only those that may cover a sample point in front is the same picture at a fraction of the rasteriser's work.
:class:`CullingLayout` orders a mesh part's triangles so that the two passes run fastest, and :class:`Viewport` is
what they are judged against.
"""

from __future__ import annotations

import itertools
import math
import os
from typing import Any, Callable

import numpy as np

from kpd._compiled import njit
from kpd.viewer.camera import box, look_at_matrix
from kpd.viewer.threads import MAX_PASS_THREADS, draw_pool, in_halves

__all__ = ["PIXEL_CENTRE", "Viewport", "DEPTH_SLACK", "visible_triangles", "edge_neighbours", "CullingLayout"]

_LOOK_EVERY = 1 << 16  # triangles a culling pass takes between two looks at whether it is to stop
_BLOCK = 32  # triangles of a run that culling's pass 1 first judges together (hidden all at once, or looked at)


# Where a rasteriser samples a pixel, as offsets from its lower-left corner (y up): a frame that is read back
# (pictures, screenshots: Open3D draws them into a framebuffer of one sample a pixel) at the centre; a window where
# its OpenGL context says (GLView asks it: Open3D asks for 4 samples, and Mesa's software renderer gives them under
# Xvfb at the points of the standard pattern).
PIXEL_CENTRE = np.array([[0.5, 0.5]])


class Viewport:
    """Where a view draws: ``width`` x ``height`` pixels seen through a look-at ``camera`` with a symmetric frustum
    (:meth:`GLView.set_camera`), each pixel sampled at ``samples`` (S, 2) (offsets from its lower-left corner), for
    :func:`visible_triangles`."""

    def __init__(self, camera: Any, width: int, height: int, samples: np.ndarray = PIXEL_CENTRE) -> None:
        self.camera, self.width, self.height = camera, int(width), int(height)
        self.samples = np.ascontiguousarray(samples, dtype=np.float64)
        self.view = look_at_matrix(camera)  # (4, 4) world -> camera, looking down -z
        self.focal = self.height / 2 / math.tan(math.radians(camera.fov) / 2)  # pixels


# Depth by which a triangle must lie behind one that surely covers a sample to be left out there, as a share of the
# depth: far above the depth buffer's steps (24 bits over Open3D's near and far planes: about 4e-6 of the depth at
# the default camera; 1e-3 with 16 bits) and float32 rounding.
DEPTH_SLACK = 3e-3


def visible_triangles(vertices: np.ndarray, triangles: np.ndarray, viewport: Viewport, *,
                      scratch: dict | None = None, stop: np.ndarray | None = None,
                      neighbours: np.ndarray | None = None, index: np.ndarray | None = None,
                      cells: np.ndarray | None = None) -> np.ndarray | None:
    """(T,) bool: the triangles that may show in a pixel of the viewport; a frame drawn without the others is the
    same picture.

    A rasteriser makes a triangle's fragments at the sample points it covers (the pixel centres, or several points a
    pixel with multisampling), and keeps at each the nearest. A scan-sized mesh in a window has many triangles per
    pixel, most of them hidden or between the sample points; drawing only the others (which is what a rasteriser
    spends its time finding out) makes a frame several times cheaper. Each vertex is projected as the view projects
    it; a corner may land up to ``delta`` pixels away along each axis in the rasteriser (sub-pixel snapping and
    float32 rounding, :func:`_margin`), which moves a point's edge functions by at most ``delta (2 D + L)`` (D the
    triangle's extent on the screen, L the edge's length), and the drawn triangle lies within ``delta √2`` of the
    projected one (each of its corners does, and so does their convex hull). Two passes:

    1. at each sample point, the depth behind which nothing of the triangles that surely cover it (inside by that
       bound) lies: the smallest of their farthest corners' depths. A point too near a triangle's edge to be sure
       is surely covered by the triangle or its neighbour across that edge (``neighbours``) when the two surely
       lie either side of the edge and the point is surely inside their four other edges: a rasteriser fills the
       edge two triangles share once, with no gap; a triangle works only on the pixels where its farthest corner
       would bring a sample point nearer. The triangles with a sample point in reach are listed for pass 2;
    2. a listed triangle is kept if it may cover a sample point (one within ``delta √2`` of it, either winding)
       where its nearest corner is not behind that depth by more than :data:`DEPTH_SLACK` of it. Slivers, whose
       short edges turn far when their corners stray, are so kept in a narrow band, where the bound on the edge
       functions would keep them over the pixels beside them too.

    A triangle with a corner behind the camera or over more than 25 pixels is kept untested.

    Parameters
    ----------
    vertices : (V, 3) float64.
    triangles : (T, 3) int.
    viewport : Viewport.
    scratch : the arrays of an earlier call with as many vertices and triangles and the same viewport size, reused
        (fresh memory costs as much as the work here); a dict, filled on the first call.
    stop : (1,) uint8, set non-zero by another thread to abandon the work: the passes look at it every 65,536
        triangles and None is returned (a frame no longer wanted gives the cores back within a few milliseconds).
    neighbours : (T, 3) int32 :func:`edge_neighbours` of ``triangles``, or None to judge each triangle alone.
    index : (V',) int, or None: the triangles index ``vertices[index]`` (a :class:`CullingLayout`'s order).
    cells : (C + 1,) int64, or None: the triangles come in runs ``cells[c]:cells[c + 1]`` of triangles near each
        other (a :class:`CullingLayout`'s). Pass 1 then takes the runs nearest the camera first (by the depth of a
        run's first corner), and a triangle whose nearest corner lies behind the depth reached so far at every
        sample point in its reach (by more than :data:`DEPTH_SLACK`) is left out there and then, without its
        coverage worked out: pass 2 would leave it out too, since that depth only comes nearer (the same
        triangles are kept as in any order). Most of a closed surface's far side is left out so, 32 triangles of a
        run at a time where they all are (:func:`_block_hidden`).
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    index = np.zeros(0, dtype=np.int64) if index is None else np.ascontiguousarray(index)
    count = len(index) if len(index) else len(vertices)  # the points the triangles index
    triangles = np.ascontiguousarray(triangles)
    w, h, samples = viewport.width, viewport.height, viewport.samples
    points = h * w * len(samples)
    if len(samples) > 64:  # more than the kernels' bit masks hold: every triangle
        return np.ones(len(triangles), dtype=np.bool_)
    n = len(triangles)
    threads = _culling_threads() if n >= 200_000 else 1
    pieces = _BANDS * threads if threads > 1 else 1  # the work in pieces, each taken by whichever thread is free
    scratch = {} if scratch is None else scratch
    if scratch.get("sizes") != (count, n, points, threads):
        scratch.update(sizes=(count, n, points, threads), screen=np.empty((count, 3)),
                       depth=np.empty((threads, points), np.float32), front=np.empty(points, np.float32),
                       keep=np.empty(n, np.bool_), listed=np.empty(n, np.int32),
                       listed_count=np.zeros(pieces, np.int64))
    screen = scratch["screen"]  # (V, 3) window x, y (y up) and the depth along the view axis
    in_halves(_project, count, vertices, index, viewport.view, viewport.focal, w / 2, h / 2, screen)
    delta = _margin(vertices, viewport)
    depth = scratch["depth"]  # (threads, H W S) per sample point, one row per thread
    depth.fill(np.inf)
    stop = np.zeros(1, np.uint8) if stop is None else stop
    listed, listed_count = scratch["listed"], scratch["listed_count"]  # (T,) int32, (pieces,): pass 1's candidates
    listed_count.fill(0)
    ox, oy = np.ascontiguousarray(samples[:, 0]), np.ascontiguousarray(samples[:, 1])  # (S,) each
    if neighbours is None:  # none: the kernels judge each triangle alone
        neighbours = np.empty((0, 3), dtype=np.int32)
    if cells is None:  # in their order
        bounds = np.linspace(0, n, pieces + 1).astype(np.int64)
        ranges = [bounds[p:p + 2].reshape(1, 2) for p in range(pieces)]
    else:  # the runs nearest first, in bands of about as many triangles; every threads-th run of a band in each of
        # its pieces, which the threads take at once (they come nearer together, as the depth fills from the front)
        first = triangles[cells[:-1], 0]  # (C,) a corner of each run
        order = np.argsort(screen[first, 2], kind="stable")
        runs = np.stack([cells[:-1], cells[1:]], axis=1)[order]  # (C, 2)
        if pieces == 1:
            ranges = [runs]
        else:
            ends = np.cumsum(runs[:, 1] - runs[:, 0])  # triangles up to each run's end
            cuts = np.searchsorted(ends, np.arange(1, _BANDS) * (n / _BANDS))
            ranges = [band[k::threads] for band in np.split(runs, cuts) for k in range(threads)]
    sizes = np.array([int((r[:, 1] - r[:, 0]).sum()) for r in ranges], np.int64)
    start = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)  # of each piece's list
    args = (triangles, neighbours, screen, w, h, ox, oy, delta, depth, listed, start, listed_count, stop,
            DEPTH_SLACK, cells is not None)
    _in_pieces(pieces, threads, stop, lambda p, row: _fronts(ranges[p], row, p, *args))
    if stop[0]:
        return None
    front = np.minimum.reduce(depth, axis=0, out=scratch["front"])  # (H W S,)
    keep = scratch["keep"]
    keep.fill(False)
    args = (triangles, screen, w, h, ox, oy, delta, front, DEPTH_SLACK, listed, start, listed_count, keep, stop)
    _in_pieces(pieces, threads, stop, lambda p, row: _showing(p, *args))
    return None if stop[0] else keep


# Bands the culling's passes cut their work into, each in one piece a thread: the threads take the pieces in turn,
# so that a thread held back by the system (another busy process) holds back one piece, not its share of the work
_BANDS = 8


def _culling_threads() -> int:
    """Threads of a culling pass: two a processor (at most :data:`MAX_PASS_THREADS`), so that beside another
    busy process the pass keeps a larger share of the cores (the system shares them among threads), and a thread held
    back holds back less (docs/results.md)."""
    cores = os.cpu_count() or 1
    return 1 if cores < 2 else min(2 * cores, MAX_PASS_THREADS)


def _in_pieces(pieces: int, threads: int, stop: np.ndarray, work: Callable[[int, int], None]) -> None:
    """``work(piece, row)`` for each piece in [0, pieces), in order of asking, on this thread (row 0) and
    ``threads - 1`` threads of the pool (rows 1...), each taking the next piece when it is free; until ``stop[0]``
    is set."""
    taken = itertools.count()  # next() of a count is atomic under the interpreter's lock

    def worker(row: int) -> None:
        while not stop[0]:
            piece = next(taken)
            if piece >= pieces:
                return
            work(piece, row)

    others = [draw_pool().submit(worker, row) for row in range(1, threads)]
    try:
        worker(0)
    finally:
        for other in others:
            other.result()


def _margin(vertices: np.ndarray, viewport: Viewport) -> float:
    """Pixels by which a drawn vertex may stray from its float64 projection: 1/256 (twice llvmpipe's rounding to its
    8-bit sub-pixel grid, at most 1/512) plus a few float32 roundings of the coordinates and the camera transform,
    seen at the nearest point of the vertices' bounding box (a larger margin keeps more hidden triangles)."""
    if not len(vertices):
        return 1.0 / 256
    lo, hi = box([vertices])
    eye = np.asarray(viewport.camera.eye, dtype=np.float64)
    nearest = float(np.linalg.norm(np.maximum(lo - eye, 0.0) + np.maximum(eye - hi, 0.0)))  # eye to the box
    size = float(max(np.abs(lo).max(), np.abs(hi).max(), np.abs(eye).max()))
    rounding = 16 * size * 2.0 ** -24  # units
    return 1.0 / 256 + viewport.focal * rounding / max(nearest, rounding, 1e-300)


@njit(nogil=True, error_model="numpy")
def _project(lo, hi, vertices, index, view, focal, half_width, half_height, screen):  # pragma: no cover - compiled
    """Window coordinates (x right, y up) and depth in front of the camera (<= 0: not in front) of
    ``vertices[index]`` (of ``vertices`` when ``index`` is empty)."""
    gather = index.shape[0] > 0
    for i in range(lo, hi):
        v = index[i] if gather else i
        px, py, pz = vertices[v, 0], vertices[v, 1], vertices[v, 2]
        x = view[0, 0] * px + view[0, 1] * py + view[0, 2] * pz + view[0, 3]
        y = view[1, 0] * px + view[1, 1] * py + view[1, 2] * pz + view[1, 3]
        z = view[2, 0] * px + view[2, 1] * py + view[2, 2] * pz + view[2, 3]
        screen[i, 2] = -z
        if z < 0.0:
            screen[i, 0] = half_width + focal * x / -z
            screen[i, 1] = half_height + focal * y / -z
        else:
            screen[i, 0] = screen[i, 1] = 0.0


@njit(nogil=True, error_model="numpy", inline="always")
def _offsets_in(lo, hi, offsets):  # pragma: no cover - compiled
    """Bit k set for each of the samples' offsets (S,) in [lo, hi] (S <= 64): the samples of a pixel column (row)
    whose x (y) lies in a box's span, found without branches."""
    mask = 0
    for k in range(offsets.shape[0]):
        mask |= (1 << k) if lo <= offsets[k] <= hi else 0
    return mask


@njit(nogil=True, error_model="numpy")
def _pair_far(sx, sy, screen, p0, p1, q, d, delta):  # pragma: no cover - compiled
    """The depth behind which nothing of the triangles (p0, p1, q) and (p1, p0, d) lies when, wherever their corners
    land within ``delta``, they lie either side of their shared edge and the point (sx, sy) is inside their other
    four edges: then one of them covers it (a rasteriser fills the shared edge of two triangles once, without a
    gap); infinity when not sure."""
    ax, ay, za = screen[p0, 0], screen[p0, 1], screen[p0, 2]
    bx, by, zb = screen[p1, 0], screen[p1, 1], screen[p1, 2]
    cx, cy, zc = screen[q, 0], screen[q, 1], screen[q, 2]
    dx, dy, zd = screen[d, 0], screen[d, 1], screen[d, 2]
    if not zd > 0.0:
        return np.float32(np.inf)
    x0, x1 = min(ax, bx, cx, dx, sx), max(ax, bx, cx, dx, sx)
    y0, y1 = min(ay, by, cy, dy, sy), max(ay, by, cy, dy, sy)
    reach = 2.0 * math.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2) + 2.0 * delta  # bounds twice any distance here
    shared = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)  # q's side of the shared edge
    other = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax)  # d's side
    sign = 1.0 if shared > 0.0 else -1.0
    m = delta * (reach + math.sqrt((bx - ax) ** 2 + (by - ay) ** 2))
    if not (sign * shared >= m and sign * other <= -m):
        return np.float32(np.inf)
    e_bq = sign * ((cx - bx) * (sy - by) - (cy - by) * (sx - bx))  # the other four edges, inside positive
    e_qa = sign * ((ax - cx) * (sy - cy) - (ay - cy) * (sx - cx))
    e_ad = sign * ((dx - ax) * (sy - ay) - (dy - ay) * (sx - ax))
    e_db = sign * ((bx - dx) * (sy - dy) - (by - dy) * (sx - dx))
    if (e_bq >= delta * (reach + math.sqrt((cx - bx) ** 2 + (cy - by) ** 2))
            and e_qa >= delta * (reach + math.sqrt((ax - cx) ** 2 + (ay - cy) ** 2))
            and e_ad >= delta * (reach + math.sqrt((dx - ax) ** 2 + (dy - ay) ** 2))
            and e_db >= delta * (reach + math.sqrt((bx - dx) ** 2 + (by - dy) ** 2))):
        return np.float32(max(za, zb, zc, zd))
    return np.float32(np.inf)


@njit(nogil=True, error_model="numpy", inline="always")
def _reached(x0, x1, y0, y1, i0, i1, j0, j1, near, delta, width, ox, oy, depth):  # pragma: no cover - compiled
    """Whether a sample point within ``delta`` of the box [x0, x1] x [y0, y1] (in the pixels i0..i1, j0..j1) is
    not behind the depth reached there (every row of ``depth``, one a thread) by more than what ``near`` allows:
    where something nearest at ``near`` may still show (pass 1 of :func:`visible_triangles`)."""
    count = ox.shape[0]
    rows = depth.shape[0]
    for i in range(i0, i1 + 1):
        column = _offsets_in(x0 - delta - i, x1 + delta - i, ox)
        if column == 0:
            continue
        for j in range(j0, j1 + 1):
            row = column & _offsets_in(y0 - delta - j, y1 + delta - j, oy)
            if row == 0:
                continue
            base = (j * width + i) * count
            for k in range(count):
                behind = False
                for r in range(rows):
                    behind |= near > depth[r, base + k]
                row &= ~(behind << k)
            if row != 0:
                return True
    return False


@njit(nogil=True, error_model="numpy")
def _block_hidden(s0, s1, triangles, screen, width, height, ox, oy, delta, depth, slack):  # pragma: no cover
    """Whether pass 1 would leave out each of the triangles ``s0:s1`` as hidden: all in front of the camera and over
    at most 25 pixels, and the nearest corner of them all behind the depth reached so far (any row, by more than
    ``slack``) at every sample point in reach of their common box (which holds each one's reach). The same verdict
    as for each triangle alone, at a fraction of the cost: a run's triangles lie near each other."""
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    nearest = np.inf
    for t in range(s0, s1):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        za, zb, zc = screen[a, 2], screen[b, 2], screen[c, 2]
        if not (za > 0.0 and zb > 0.0 and zc > 0.0):
            return False
        tx0, tx1 = min(screen[a, 0], screen[b, 0], screen[c, 0]), max(screen[a, 0], screen[b, 0], screen[c, 0])
        ty0, ty1 = min(screen[a, 1], screen[b, 1], screen[c, 1]), max(screen[a, 1], screen[b, 1], screen[c, 1])
        i0, i1 = max(math.floor(tx0 - delta), 0), min(math.floor(tx1 + delta), width - 1)
        j0, j1 = max(math.floor(ty0 - delta), 0), min(math.floor(ty1 + delta), height - 1)
        if i0 > i1 or j0 > j1:  # off the view: left out in any case
            continue
        if (i1 - i0 + 1) * (j1 - j0 + 1) > 25:  # judged without the depth (pass 2 keeps it untested)
            return False
        x0, x1, y0, y1 = min(x0, tx0), max(x1, tx1), min(y0, ty0), max(y1, ty1)
        nearest = min(nearest, za, zb, zc)
    i0, i1 = max(math.floor(x0 - delta), 0), min(math.floor(x1 + delta), width - 1)
    j0, j1 = max(math.floor(y0 - delta), 0), min(math.floor(y1 + delta), height - 1)
    return not _reached(x0, x1, y0, y1, i0, i1, j0, j1, nearest / (1.0 + slack), delta, width, ox, oy, depth)


@njit(nogil=True, error_model="numpy")
def _fronts(ranges, row, slot, triangles, neighbours, screen, width, height, ox, oy, delta, depth, listed, start,
            listed_count, stop, slack, skip_hidden):  # pragma: no cover - compiled
    """Pass 1 of :func:`visible_triangles` over the triangles ``ranges[r, 0]:ranges[r, 1]`` in turn (one piece of
    the work), into ``depth[row]``, the calling thread's row (the other threads' rows are read as they write); the
    triangles with a sample point in reach (or a corner not in front of the camera) are listed for pass 2 in
    ``listed[start[slot]:start[slot] + listed_count[slot]]``, the piece's place. With ``skip_hidden``, one whose
    nearest corner lies behind the depth reached so far (any row, by more than ``slack``) at every sample point in
    its reach is left out. Returns early once ``stop[0]`` is set. A sample point is at ``(i + ox[k], j + oy[k])`` in
    pixel (i, j)."""
    out = depth[row]  # the other rows are read while their threads write (a depth only ever comes nearer)
    count = ox.shape[0]
    paired_edges = neighbours.shape[0] != 0  # (0, 3) neighbours: each triangle judged alone
    found = start[slot]  # the candidates go to listed[start[slot]:found]
    done = 0
    look = 0  # where the next look at stop is due
    for r in range(ranges.shape[0]):
        for s0 in range(ranges[r, 0], ranges[r, 1], _BLOCK):
            s1 = min(s0 + _BLOCK, ranges[r, 1])
            if done >= look:
                if stop[0] != 0:
                    return
                look = done + _LOOK_EVERY
            done += s1 - s0
            # a block of nearby triangles all behind the depth reached so far: left out at once (each would be)
            if skip_hidden and _block_hidden(s0, s1, triangles, screen, width, height, ox, oy, delta, depth,
                                             slack):
                continue
            for t in range(s0, s1):
                a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
                za, zb, zc = screen[a, 2], screen[b, 2], screen[c, 2]
                if not (za > 0.0 and zb > 0.0 and zc > 0.0):
                    listed[found] = t  # kept by pass 2
                    found += 1
                    continue
                ax, ay, bx, by = screen[a, 0], screen[a, 1], screen[b, 0], screen[b, 1]
                cx, cy = screen[c, 0], screen[c, 1]
                x0, x1, y0, y1 = min(ax, bx, cx), max(ax, bx, cx), min(ay, by, cy), max(ay, by, cy)
                i0, i1 = max(math.floor(x0 - delta), 0), min(math.floor(x1 + delta), width - 1)  # the pixels in reach
                j0, j1 = max(math.floor(y0 - delta), 0), min(math.floor(y1 + delta), height - 1)
                if i0 > i1 or j0 > j1:
                    continue
                # a sample point in reach (the box grown by delta) and not surely behind: most triangles of a dense mesh
                # have none and are left out (pass 2 keeps a triangle over more than 25 pixels untested: listed)
                near = min(za, zb, zc) / (1.0 + slack) if skip_hidden and (i1 - i0 + 1) * (j1 - j0 + 1) <= 25 \
                    else -np.inf
                if not _reached(x0, x1, y0, y1, i0, i1, j0, j1, near, delta, width, ox, oy, depth):
                    continue
                listed[found] = t
                found += 1
                # the sample points it surely covers lie in its box shrunk by delta (farther than that from its edges)
                if x1 - x0 < 2.0 * delta or y1 - y0 < 2.0 * delta or (i1 - i0 + 1) * (j1 - j0 + 1) > 4096:
                    continue
                area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)  # twice the signed area
                sign = 1.0 if area > 0.0 else -1.0
                reach = 2.0 * math.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2) + 2.0 * delta
                m0 = -1.0  # the edges' margins, worked out at the first sample point inside the shrunk box
                m1 = m2 = 0.0
                far = np.float32(max(za, zb, zc))  # nothing of the triangle lies behind its farthest corner
                for i in range(i0, i1 + 1):
                    column = _offsets_in(x0 + delta - i, x1 - delta - i, ox)
                    if column == 0:
                        continue
                    for j in range(j0, j1 + 1):
                        inside = column & _offsets_in(y0 + delta - j, y1 - delta - j, oy)
                        if inside == 0:
                            continue
                        base = (j * width + i) * count
                        nearer = False  # whether it may bring one of the pixel's sample points nearer: else no work
                        for k in range(count):
                            nearer |= ((inside >> k) & 1 != 0) & (far < out[base + k])
                        if not nearer:
                            continue
                        if m0 < 0.0:
                            m0 = delta * (reach + math.sqrt((bx - ax) ** 2 + (by - ay) ** 2))
                            m1 = delta * (reach + math.sqrt((cx - bx) ** 2 + (cy - by) ** 2))
                            m2 = delta * (reach + math.sqrt((ax - cx) ** 2 + (ay - cy) ** 2))
                        for k in range(count):  # few branches: whether a sample point is inside is a coin toss
                            sx, sy = i + ox[k], j + oy[k]
                            e0 = sign * ((bx - ax) * (sy - ay) - (by - ay) * (sx - ax))
                            e1 = sign * ((cx - bx) * (sy - by) - (cy - by) * (sx - bx))
                            e2 = sign * ((ax - cx) * (sy - cy) - (ay - cy) * (sx - cx))
                            held = out[base + k]
                            ok0, ok1, ok2 = e0 >= m0, e1 >= m1, e2 >= m2
                            bit = (inside >> k) & 1 != 0
                            # surely inside, and nearer
                            out[base + k] = far if bit & ok0 & ok1 & ok2 & (far < held) else held
                            # too near one edge to be sure: covered by the triangle or its neighbour across the edge
                            # if the two lie either side of it (a rare branch)
                            near0, near1, near2 = abs(e0) < m0, abs(e1) < m1, abs(e2) < m2
                            if paired_edges & bit & (far < held) & ((near0 & ok1 & ok2) | (ok0 & near1 & ok2) |
                                                                    (ok0 & ok1 & near2)):
                                edge = 0 if near0 else 1 if near1 else 2
                                d = neighbours[t, edge]
                                if d >= 0:
                                    p0, p1, q = (a, b, c) if edge == 0 else (b, c, a) if edge == 1 else (c, a, b)
                                    paired = _pair_far(sx, sy, screen, p0, p1, q, d, delta)
                                    if paired < out[base + k]:
                                        out[base + k] = paired
    listed_count[slot] = found - start[slot]


@njit(nogil=True, error_model="numpy")
def _showing(slot, triangles, screen, width, height, ox, oy, delta, front, slack, listed, start, listed_count, keep,
             stop):  # pragma: no cover - compiled
    """Pass 2 of :func:`visible_triangles` over the triangles that pass 1 listed in its slot ``slot`` (``keep``
    holds False for the others); returns early once ``stop[0]`` is set."""
    count = ox.shape[0]
    # a drawn corner strays by at most delta along each axis, so by at most this far: the triangle drawn lies within
    # this distance of the one projected (each drawn corner does, and so does their convex hull)
    stray = delta * math.sqrt(2.0)
    lo = start[slot]
    for n in range(lo, lo + listed_count[slot]):
        if (n - lo) % _LOOK_EVERY == 0 and stop[0] != 0:
            return
        t = listed[n]
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        za, zb, zc = screen[a, 2], screen[b, 2], screen[c, 2]
        if not (za > 0.0 and zb > 0.0 and zc > 0.0):
            keep[t] = True  # crosses the camera's plane: left to the clipper
            continue
        ax, ay, bx, by, cx, cy = screen[a, 0], screen[a, 1], screen[b, 0], screen[b, 1], screen[c, 0], screen[c, 1]
        # the sample points the triangle may cover lie within delta of its box
        x0, x1 = min(ax, bx, cx) - delta, max(ax, bx, cx) + delta
        y0, y1 = min(ay, by, cy) - delta, max(ay, by, cy) + delta
        i0, i1 = max(math.floor(x0), 0), min(math.floor(x1), width - 1)  # with a sample point (pass 1)
        j0, j1 = max(math.floor(y0), 0), min(math.floor(y1), height - 1)
        if (i1 - i0 + 1) * (j1 - j0 + 1) > 25:
            keep[t] = True
            continue
        near = min(za, zb, zc) / (1.0 + slack)  # nothing of the triangle lies before its nearest corner
        m0 = -1.0  # the edges' margins, worked out at the first sample point in reach and not behind (most hidden
        m1 = m2 = 0.0  # triangles have none)
        shows = False
        for i in range(i0, i1 + 1):
            column = _offsets_in(x0 - i, x1 - i, ox)
            if column == 0:
                continue
            for j in range(j0, j1 + 1):
                reached = column & _offsets_in(y0 - j, y1 - j, oy)
                base = (j * width + i) * count
                for k in range(count):  # out of reach, or behind what surely covers the point: left out
                    reached &= ~((near > front[base + k]) << k)
                if reached == 0:
                    continue
                if m0 < 0.0:  # each edge's line moved out by how far a corner may stray, in edge-function units
                    m0 = stray * math.sqrt((bx - ax) ** 2 + (by - ay) ** 2)
                    m1 = stray * math.sqrt((cx - bx) ** 2 + (cy - by) ** 2)
                    m2 = stray * math.sqrt((ax - cx) ** 2 + (ay - cy) ** 2)
                for k in range(count):  # without branches: whether a sample point is inside is a coin toss
                    sx, sy = i + ox[k], j + oy[k]
                    e0 = (bx - ax) * (sy - ay) - (by - ay) * (sx - ax)
                    e1 = (cx - bx) * (sy - by) - (cy - by) * (sx - bx)
                    e2 = (ax - cx) * (sy - cy) - (ay - cy) * (sx - cx)
                    shows |= ((reached >> k) & 1 != 0) & (((e0 >= -m0) & (e1 >= -m1) & (e2 >= -m2))
                                                          | ((e0 <= m0) & (e1 <= m1) & (e2 <= m2)))
                if shows:
                    break
            if shows:
                break
        keep[t] = shows

def edge_neighbours(triangles: np.ndarray, num_vertices: int) -> np.ndarray:
    """(T, 3) int32: for each triangle (a, b, c) and each of its edges ab, bc, ca, the third corner of another
    triangle with that edge (the same two vertices), -1 for none."""
    triangles = np.ascontiguousarray(triangles)
    out = np.full((len(triangles), 3), -1, dtype=np.int32)
    starts = np.zeros(num_vertices + 1, dtype=np.int64)
    _neighbours(triangles, starts, np.empty(3 * len(triangles), dtype=np.int32), out)
    return out


@njit(nogil=True)
def _neighbours(triangles, starts, entries, out):  # pragma: no cover - compiled
    for t in range(triangles.shape[0]):  # the triangles at each vertex (counting sort)
        for k in range(3):
            starts[triangles[t, k] + 1] += 1
    for v in range(1, starts.shape[0]):
        starts[v] += starts[v - 1]
    fill = starts[:-1].copy()
    for t in range(triangles.shape[0]):
        for k in range(3):
            v = triangles[t, k]
            entries[fill[v]] = t
            fill[v] += 1
    for t in range(triangles.shape[0]):
        for k in range(3):
            p0, p1 = triangles[t, k], triangles[t, (k + 1) % 3]
            for i in range(starts[p0], starts[p0 + 1]):
                u = entries[i]
                if u != t and (triangles[u, 0] == p1 or triangles[u, 1] == p1 or triangles[u, 2] == p1):
                    out[t, k] = triangles[u, 0] + triangles[u, 1] + triangles[u, 2] - p0 - p1
                    break


class CullingLayout:
    """The triangles of a mesh part in the order :func:`visible_triangles` goes through them fastest: near each other
    in space (by the Morton order of their centroids at rest, over 64 cells a side of the part's bounding cube), and
    their vertices numbered in order of first use, so that the culling's passes read the projected vertices and
    write the sample points' depths near where they read and wrote last: the two passes take about 40% less time
    than in the mesh's own order.

    ``order`` (T,) the part's triangles in that order, ``used`` (V',) the vertices they use in order of first use,
    ``triangles`` (T, 3) int32 the ordered triangles indexing ``used``, ``neighbours`` their :func:`edge_neighbours`,
    ``cells`` (C + 1,) where the triangles of each cell start: pass 1 takes the cells nearest the camera first.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        triangles = np.ascontiguousarray(triangles, dtype=np.int64)
        self.order = np.empty(len(triangles), dtype=np.int64)
        self.triangles = np.empty((len(triangles), 3), dtype=np.int32)
        used = np.empty(len(vertices), dtype=np.int64)
        starts = np.empty(len(triangles) + 1, dtype=np.int64)
        n, c = _near_layout(vertices, triangles, _LAYOUT_CELLS, self.order, self.triangles, used, starts)
        self.used = used[:n].copy()
        self.cells = starts[:c + 1].copy()  # (C + 1,) the runs of triangles in one cell
        self.neighbours = edge_neighbours(self.triangles, n)

    def visible(self, vertices: np.ndarray, viewport: Viewport, keep: np.ndarray, *, scratch: dict | None = None,
                stop: np.ndarray | None = None) -> np.ndarray | None:
        """:func:`visible_triangles` of the part's triangles over ``vertices`` (the whole mesh's), into ``keep`` (T,)
        bool in the part's order; None when stopped."""
        shown = visible_triangles(vertices, self.triangles, viewport, scratch=scratch, stop=stop,
                                  neighbours=self.neighbours, index=self.used, cells=self.cells)
        if shown is None:
            return None
        keep[self.order] = shown
        return keep


_LAYOUT_CELLS = 64  # cells a side of the Morton order of a CullingLayout


@njit(nogil=True)
def _near_layout(vertices, triangles, cells, order, local, used, runs):  # pragma: no cover - compiled
    """:class:`CullingLayout`'s arrays: ``order`` (T,) the triangles by the Morton order of their centroids over
    ``cells`` (a power of two, at most 128) cells a side of their bounding cube (a counting sort; in their order
    within a cell), ``local`` (T, 3) the ordered triangles renumbered over ``used[:n]``, the vertices in order of
    first use, and ``runs[:c + 1]`` where each non-empty cell's triangles start (and the end); returns (n, c)."""
    t_count = triangles.shape[0]
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for t in range(t_count):
        for k in range(3):
            v = triangles[t, k]
            for a in range(3):
                low[a] = min(low[a], vertices[v, a])
                high[a] = max(high[a], vertices[v, a])
    size = 0.0
    for a in range(3):
        size = max(size, high[a] - low[a])
    step = (cells - 1e-9) / size if size > 0.0 else 0.0
    bits = 0
    while (1 << bits) < cells:
        bits += 1
    code = np.empty(t_count, dtype=np.int64)
    start = np.zeros(cells * cells * cells + 1, dtype=np.int64)
    for t in range(t_count):
        c = 0
        for a in range(3):
            centre = (vertices[triangles[t, 0], a] + vertices[triangles[t, 1], a] + vertices[triangles[t, 2], a]) / 3.0
            q = min(max(int((centre - low[a]) * step), 0), cells - 1)
            for b in range(bits):  # bit b of axis a goes to bit 3b + a
                c |= ((q >> b) & 1) << (3 * b + a)
        code[t] = c
        start[c + 1] += 1
    for c in range(cells * cells * cells):
        start[c + 1] += start[c]
    c = 0
    for cell in range(cells * cells * cells):
        if start[cell + 1] > start[cell]:
            runs[c] = start[cell]
            c += 1
    runs[c] = t_count
    for t in range(t_count):
        order[start[code[t]]] = t
        start[code[t]] += 1
    renumber = np.full(vertices.shape[0], -1, dtype=np.int64)
    n = 0
    for i in range(t_count):
        t = order[i]
        for k in range(3):
            v = triangles[t, k]
            if renumber[v] < 0:
                renumber[v] = n
                used[n] = v
                n += 1
            local[i, k] = renumber[v]
    return n, c
