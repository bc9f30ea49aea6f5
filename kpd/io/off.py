"""OFF: text OFF read exactly by compiled passes, the completeness check Open3D leaves out, and writing.

Open3D 0.20's reader (``FileOFF.cpp``) skips blank lines and lines whose first word starts with ``#`` anywhere, wants
the header ``OFF``, ``COFF``, ``NOFF`` or ``CNOFF`` alone on its line, then the counts ``V F E`` (three whole
numbers, V and F not 0), then one vertex per line, ``x y z``, ``nx ny nz`` (``N``), ``r g b a`` (``C``: all four, each
divided by 255, ``a`` dropped), and one face per line, its corner count ``n`` and ``n`` vertex indices; it ignores
what follows on a line (a face's colour) and the lines after the last face. A face of more than three corners is cut
by its ear clipping (:func:`_cut_polygon_reference` in plain Python), which refuses the file when the polygon has no
ear where it looks. It reads every number as a float32 (0.3 comes back as 0.30000001), and a word through a C++
stream, which takes the number a word starts with (``3abc`` is 3, ``1.2.3`` is 1.2 and .3) and refuses ``nan``,
``inf`` and numbers beyond float32. It refuses ``STOFF``, ``4OFF``, binary OFF, ModelNet's header with the counts on
its line (``OFF1234 5678 0``), and a file with no faces; it reads garbage for a face of fewer than three corners.

:func:`read_mesh` reads text OFF as Open3D does: the same vertices, normals, colours and triangles, in the same
order, a polygon cut by the same ear clipping on the float32 positions Open3D holds, except that every number is the
file's decimal as float64, to the bit what Python's ``float`` gives (Clinger's fast path compiled, Python for the rest;
colours ``c / 255`` in float64). It also reads ModelNet's header, and gives :func:`kpd.io.read_shape` and
:func:`kpd.io.read_points` the vertices of a file without faces. A bad row is one :class:`~kpd.errors.InputError`
naming the file and the line; a word that is not a plain decimal (``nan``, ``0x10``, ``3abc``), a binary OFF and the
headers Open3D refuses are left to Open3D, which reads or refuses them as before. The file is read once, in blocks
of whole lines (4 MiB: what is held beside the mesh stays small), each by compiled passes in two halves on two
threads (:func:`kpd.io.numbers.in_halves`): the rows (lines that hold a word), the vertices' numbers (by
:func:`kpd.io.numbers.scan_numbers`, the OBJ reader's pass; a row with a word beyond its fast path or a ``#`` is
judged in Python), the faces' corners, the polygons' ear clipping.

Reading needs little beyond the mesh: a 4 MiB block and its line table, and numba's runtime.

:func:`write_mesh` writes what Open3D's OFF writer writes (the header ``OFF``, ``NOFF``, ``COFF`` or ``CNOFF``; per
vertex ``x y z``, then ``nx ny nz`` with normals, then ``r g b 255`` with colours, each channel ``round(255 c)``,
halves away from zero; per triangle ``3 a b c``), its numbers formatted by :mod:`kpd.io.text`, with 9 significant
digits where Open3D writes 6 (a C++ stream's default: up to 5e-6 of a coordinate lost): read back, a coordinate is
within 5e-9 of itself (relative), and a float32 coordinate rounds back to itself. Both are several times faster
than Open3D's at scan sizes (figures in ``docs/formats.md``).
"""

from __future__ import annotations

import codecs
import math
import os
import re
from pathlib import Path
from typing import Iterator

import numpy as np

from kpd._compiled import compiled_on_first_call
from kpd.errors import InputError
from kpd.io.common import count_lines
from kpd.io.numbers import BLANKS as _BLANKS, in_halves as _in_halves, scan_numbers as _numbers
from kpd.mesh import Mesh, PointSet

__all__ = ["check_complete", "read_mesh", "write_mesh"]

_HEAD = 1 << 16  # the bytes where the header and the counts are looked for (Open3D reads a file with more comments)
_BLOCK = 1 << 22  # bytes read at a time: a block's line table and flags stay small beside the mesh
_HEADER = re.compile(rb"(C?N?OFF)(?:[ \t]*(\d.*))?", re.S)  # the keyword, and the counts when ModelNet puts them there
_COUNT = re.compile(rb"\+?\d{1,18}")
_UINT_MAX = 2**32 - 1  # Open3D reads the counts as unsigned int
_FLOAT32_OVERFLOW = 2.0**128 - 2.0**103  # the least value a float32 rounds to infinity: Open3D refuses it
_HASH, _NEWLINE, _PLUS = 35, 10, 43
_DECIMAL = re.compile(rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")  # what Open3D reads as a number, kpd too

# what the compiled passes find in a row; the first row (in file order) with one of them decides
_FINE, _OPEN3D, _SHORT, _FEW_CORNERS, _NOT_COUNT, _NO_EAR = 0, 2, 3, 4, 5, 6


# --- reading -------------------------------------------------------------------------------------------------------


def read_mesh(p: Path, name: str | None = None, *, points: bool = False) -> Mesh | PointSet | None:
    """Read a text OFF file as Open3D does, its numbers exact (see the module notes).

    Parameters
    ----------
    p : the file
    name : the path as the user gave it, for the mesh's ``path``; ``p`` when None
    points : a file without faces gives a :class:`~kpd.mesh.PointSet` of its vertices instead of an error

    Returns
    -------
    Mesh (vertices (V, 3), triangles (T, 3) and, when the file has them, normals (V, 3) and colours (V, 3), all
    float64 but the int64 triangles), a PointSet with ``points``, or None when the file is Open3D's to read (binary
    OFF, a header Open3D refuses, a word that is not a plain decimal).

    Raises
    ------
    InputError
        Naming the line: a counts line without three whole numbers, a row with too few numbers, a face of fewer
        than three corners or without its count, a polygon Open3D's ear clipping cannot cut; a file with fewer rows
        than its header declares; what :class:`~kpd.mesh.Mesh` refuses (indices outside the vertices).
    """
    with open(p, "rb") as fh:
        head = fh.read(_HEAD)
        header = _header(p, head, complete=len(head) < _HEAD)
        if header is None:
            _check_text(p)
            return None
        normals, colors, V, F, start, line = header
        rows = _Rows(p, normals, colors, V, F, os.fstat(fh.fileno()).st_size - start)
        fh.seek(start)
        for block, ends in _blocks(fh):
            if rows.read(block, ends, line):
                break
            line += len(ends)
    shape = rows.shape(name if name is not None else os.fspath(p), points)
    if shape is None:
        _check_text(p)
    return shape


def _check_text(p: Path) -> None:
    """Raise unless the file is UTF-8 text, before Open3D reads it: Open3D refuses binary OFF, and its message,
    which quotes the file's words, cannot be given to Python (a UnicodeDecodeError out of its reader)."""
    decoder = codecs.getincrementaldecoder("utf-8")()
    at = 0
    with open(p, "rb") as fh:
        while True:
            chunk = fh.read(_BLOCK)
            try:
                decoder.decode(chunk, final=not chunk)
            except UnicodeDecodeError as exc:
                raise InputError(f"{p}: not a text OFF file (byte {at + exc.start} is not UTF-8 text)") from None
            if not chunk:
                return
            at += len(chunk)


def _significant_lines(data: bytes, complete: bool) -> Iterator[tuple[int, bytes, int]]:
    """(number from 1, stripped text, offset after its line break) of each line of ``data`` that holds a word and
    does not start with ``#``, the lines Open3D reads; ``complete``: ``data`` is the whole file (its last line may
    lack a line break)."""
    at, number = 0, 0
    while at < len(data):
        end = data.find(b"\n", at)
        if end < 0:
            if not complete:
                return
            end = len(data)
        number += 1
        text = data[at:end].strip()
        at = end + 1
        if text and not text.startswith(b"#"):
            yield number, text, at


def _header(p: Path, head: bytes, complete: bool) -> tuple | None:
    """(normals, colours, V, F, the offset of the first row, its line number) from the first bytes of the file, or
    None when Open3D is to read it: another keyword (``STOFF``, ``OFF BINARY``), no counts in ``head``."""
    lines = _significant_lines(head, complete)
    first = next(lines, None)
    match = _HEADER.fullmatch(first[1]) if first else None
    if match is None:
        return None
    keyword, counts = match.groups()
    number, _, start = first
    if counts is None:
        second = next(lines, None)
        if second is None:
            return None
        number, counts, start = second
    words = counts.split()[:3]
    if len(words) < 3 or not all(_COUNT.fullmatch(w) for w in words) or max(int(w) for w in words) > _UINT_MAX:
        raise InputError(f"{p}: line {number}: the counts line must start with the numbers of vertices, faces and "
                         f"edges (three whole numbers); got {counts.decode('utf-8', 'replace')!r}")
    V, F = int(words[0]), int(words[1])
    if V == 0:
        raise InputError(f"{p}: line {number}: the header declares 0 vertices (empty geometry)")
    return b"N" in keyword, keyword.startswith(b"C"), V, F, start, number + 1


def _blocks(fh) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The file from where ``fh`` stands (the start of a line) to its end, in blocks of whole lines: each block (B,)
    uint8 and the end of each of its lines (L,) int64, its line break or, for a last line without one, the block's
    end. A block is valid until the next one is asked for."""
    buf = np.empty(2 * _BLOCK, np.uint8)
    held = 0
    while True:
        if len(buf) - held < _BLOCK:  # a line longer than what is held
            buf = np.concatenate([buf[:held], np.empty(max(held, _BLOCK), np.uint8)])
        got = fh.readinto(memoryview(buf)[held : held + _BLOCK])
        held += got
        ends = np.flatnonzero(buf[:held] == _NEWLINE)
        if not got:
            if held and (not len(ends) or ends[-1] != held - 1):
                ends = np.append(ends, held)
            if len(ends):
                yield buf[:held], ends
            return
        if len(ends):
            cut = int(ends[-1]) + 1
            yield buf[:cut], ends
            buf[: held - cut] = buf[cut:held]
            held -= cut


def _room(a: np.ndarray, rows: int, most: float = math.inf) -> np.ndarray:
    """``a`` (n, k) when it has ``rows`` rows, else a copy with room for them (twice ``n`` if more, up to ``most``)."""
    if rows <= len(a):
        return a
    bigger = np.empty((int(min(max(rows, 2 * len(a)), most)), a.shape[1]), a.dtype)
    bigger[: len(a)] = a
    return bigger


class _Rows:
    """The rows of one text OFF as its blocks are read: the vertices' numbers, the triangles, the number of rows
    read, and the first row that is wrong or that Open3D must read.

    The arrays grow with the rows read (a header's counts promise nothing): ``values`` (V, w) float64, the ``w`` numbers
    of each vertex (``x y z``, then ``nx ny nz``, then ``r g b a``); ``triangles`` (T, 3) int64.
    """

    def __init__(self, p: Path, normals: bool, colors: bool, V: int, F: int, size: int) -> None:
        self.p, self.normals, self.colors, self.V, self.F = p, normals, colors, V, F
        self.width = 3 + 3 * normals + 4 * colors
        self.values = np.empty((min(V, size // (2 * self.width) + 1), self.width))  # a number takes 2 bytes or more
        self.triangles = np.empty((min(F, size // 8 + 1), 3), np.int64)  # a face, 8 or more ("3 0 1 2\n")
        self.vertices_read = self.faces_read = self.triangles_made = 0
        self.error: str | None = None  # the message for the first wrong row
        self.open3d = False  # the first wrong row is Open3D's to judge: it reads the file

    def read(self, block: np.ndarray, ends: np.ndarray, line: int) -> bool:
        """Read the rows of one block whose first line is the file's line ``line``; True when every row is read."""
        flags = np.empty(len(ends), np.bool_)
        _in_halves(_significant, len(ends), block, ends, flags)
        rows = np.flatnonzero(flags)  # (R,) the block's lines that hold a row
        v = min(len(rows), self.V - self.vertices_read)
        if v:
            self._vertices(block, ends, rows[:v], line)
        f = min(len(rows) - v, self.F - self.faces_read)
        if f:
            self._faces(block, ends, rows[v : v + f], line)
        return self.vertices_read == self.V and self.faces_read == self.F

    def _vertices(self, block: np.ndarray, ends: np.ndarray, rows: np.ndarray, line: int) -> None:
        n, at, width = len(rows), self.vertices_read, self.width
        self.values = _room(self.values, at + n, self.V)
        values = np.zeros((n, width))
        counts = np.empty(n, np.int64)
        exact = np.empty(n, np.bool_)  # every word a decimal within the fast path
        begin = np.where(rows > 0, ends[rows - 1] + 1, 0)
        _in_halves(_numbers, n, block, begin, ends[rows], values, counts, exact)  # kpd.io.obj's pass
        status = np.where(counts < width, _SHORT, _FINE).astype(np.int8)  # the fast path stays below float32's top
        # rare: a word beyond the fast path, or a `#` (kpd.io.obj's pass ends a line there, Open3D's stream does not)
        hashed = np.isin(rows, np.searchsorted(ends, np.flatnonzero(block == _HASH)))
        for r in np.flatnonzero(~exact | hashed).tolist():
            text = _line(block, ends, rows[r])
            words = text.split()[:width]
            plain = [_DECIMAL.fullmatch(word) is not None for word in words]
            if not all(plain):  # the first word that is not a plain decimal is Open3D's to read
                status[r] = _OPEN3D
            elif len(words) < width:
                status[r] = _SHORT
            else:
                values[r] = [float(word) for word in words]
                status[r] = _OPEN3D if np.abs(values[r]).max() >= _FLOAT32_OVERFLOW else _FINE
        self.values[at:at + n] = values
        self._note(block, ends, rows, line, status, None)
        self.vertices_read += n

    def _faces(self, block: np.ndarray, ends: np.ndarray, rows: np.ndarray, line: int) -> None:
        n = len(rows)
        sizes = np.empty(n, np.int64)
        status = np.empty(n, np.int8)
        _in_halves(_face_sizes, n, block, ends, rows, sizes, status)
        made = np.where(status == _FINE, sizes - 2, 0)  # (n,) triangles of each face
        first = np.cumsum(made) - made + self.triangles_made  # (n,) its first triangle
        total = self.triangles_made + int(made.sum())
        self.triangles = _room(self.triangles, total)
        flat = self.triangles.reshape(-1)
        _in_halves(_face_rows, n, block, ends, rows, sizes, first, flat, status)
        polygons = np.flatnonzero((status == _FINE) & (sizes > 3))
        if len(polygons):
            _in_halves(_cut_polygons, len(polygons), polygons, sizes, first, self.values, flat, status)
        self._note(block, ends, rows, line, status, sizes)
        self.faces_read += n
        self.triangles_made = total

    def _note(self, block, ends, rows, line: int, status: np.ndarray, sizes: np.ndarray | None) -> None:
        """Keep what the first row whose status is not fine calls for: its message, or Open3D's reading."""
        wrong = np.flatnonzero(status)
        if self.error is not None or self.open3d or not len(wrong):
            return
        r = int(wrong[0])
        text, kind = _line(block, ends, rows[r]), int(status[r])
        where = f"{self.p}: line {line + int(rows[r])}:"
        if kind == _OPEN3D:
            self.open3d = True
            return
        if sizes is None:  # a vertex with too few numbers
            keyword = "C" * self.colors + "N" * self.normals + "OFF"
            columns = " ".join(["x y z"] + ["nx ny nz"] * self.normals + ["r g b a"] * self.colors)
            message = (f"{where} a vertex needs {self.width} numbers under the header {keyword} ({columns}); got "
                       f"{len(text.split())}")
        elif kind == _NOT_COUNT:
            shown = text.decode("utf-8", "replace")
            message = f"{where} a face line must start with its number of corners; got {shown!r}"
        elif kind == _FEW_CORNERS:
            message = f"{where} a face needs 3 corners or more; got {int(sizes[r])}"
        elif kind == _SHORT:
            message = (f"{where} a face of {int(sizes[r])} corners needs {int(sizes[r])} vertex indices after its "
                       f"count; got {len(text.split()) - 1}")
        else:
            message = (f"{where} a face of {int(sizes[r])} corners has no ear where Open3D's ear clipping looks for "
                       "one (a flat or concave polygon): it cannot be cut into triangles as Open3D cuts it")
        self.error = message

    def shape(self, name: str, points: bool) -> Mesh | PointSet | None:
        """The mesh (or, with ``points`` and no faces, the points) once every block is read; None for Open3D."""
        read = self.vertices_read + self.faces_read
        if read < self.V + self.F:
            raise InputError(f"{self.p}: the file is truncated: its header declares {self.V} vertices and {self.F} "
                             f"faces ({self.V + self.F} rows) but {read} rows follow")
        if self.error is not None:
            raise InputError(self.error)
        if self.open3d:
            return None
        vertices = np.ascontiguousarray(self.values[:, :3])
        normals = self.values[:, 3:6] if self.normals else None
        colors = self.values[:, self.width - 4 : self.width - 1] / 255.0 if self.colors else None
        if not self.F:
            if points:
                return PointSet(vertices, normals, colors, path=name)
            raise InputError(f"{self.p}: has {self.V} vertices but no triangles (a point cloud? use read_points or "
                             "read_shape)")
        triangles = self.triangles if len(self.triangles) == self.triangles_made else \
            self.triangles[: self.triangles_made].copy()
        return Mesh(vertices=vertices, triangles=triangles, vertex_normals=normals, vertex_colors=colors, path=name)


def _line(block: np.ndarray, ends: np.ndarray, i: int) -> bytes:
    """The text of the block's line ``i``, stripped."""
    return block[ends[i - 1] + 1 if i else 0 : ends[i]].tobytes().strip()


@compiled_on_first_call
def _significant(lo, hi, block, ends, flags):  # pragma: no cover - compiled
    """flags[i]: the block's line i holds a word that does not start with ``#`` (Open3D skips other lines)."""
    for i in range(lo, hi):
        j = ends[i - 1] + 1 if i else 0
        end = ends[i]
        while j < end and _BLANKS[block[j]]:
            j += 1
        flags[i] = j < end and block[j] != _HASH


@compiled_on_first_call
def _face_sizes(lo, hi, block, ends, rows, sizes, status):  # pragma: no cover - compiled
    """The corner count of face row r (its first word) into ``sizes[r]``, and ``status[r]``: fine; not a count
    (the word is not ``[+]digits``); fewer than 3 corners; short (more corners than the line has room for)."""
    for r in range(lo, hi):
        line = rows[r]
        i = ends[line - 1] + 1 if line else 0
        end = ends[line]
        while _BLANKS[block[i]]:  # the row holds a word
            i += 1
        if block[i] == _PLUS:
            i += 1
        n = 0
        digits = 0
        while i < end and 48 <= block[i] <= 57:
            if digits < 18:
                n = n * 10 + block[i] - 48
            digits += 1
            i += 1
        sizes[r] = n
        if digits == 0 or digits > 18 or (i < end and not _BLANKS[block[i]]):
            status[r] = _NOT_COUNT
        elif n < 3:
            status[r] = _FEW_CORNERS
        elif n > (end - i) // 2:  # each index takes a blank and a digit at least
            status[r] = _SHORT
        else:
            status[r] = _FINE


@compiled_on_first_call
def _face_rows(lo, hi, block, ends, rows, sizes, first, flat, status):  # pragma: no cover - compiled
    """The vertex indices of the fine face rows, after their count: a triangle's three into its row of ``flat``
    (the (T, 3) triangles as (3T,)), a polygon's n into the first n of the 3(n - 2) places of its triangles (which
    :func:`_cut_polygons` fills). ``status[r]`` becomes short for fewer than n words, Open3D's for a word that is not
    ``[+]digits`` (a C++ stream reads ``2.5`` as 2, ``-1`` as 4294967295)."""
    for r in range(lo, hi):
        if status[r] != _FINE:
            continue
        line = rows[r]
        i = ends[line - 1] + 1 if line else 0
        end = ends[line]
        while _BLANKS[block[i]]:
            i += 1
        while i < end and not _BLANKS[block[i]]:  # the count
            i += 1
        at = 3 * first[r]
        for c in range(sizes[r]):
            while i < end and _BLANKS[block[i]]:
                i += 1
            if i >= end:
                status[r] = _SHORT
                break
            if block[i] == _PLUS:
                i += 1
            value = 0
            digits = 0
            while i < end and 48 <= block[i] <= 57:
                if digits < 18:
                    value = value * 10 + block[i] - 48
                digits += 1
                i += 1
            if digits == 0 or digits > 18 or (i < end and not _BLANKS[block[i]]):
                status[r] = _OPEN3D
                break
            flat[at + c] = value


@compiled_on_first_call
def _cut_polygons(lo, hi, polygons, sizes, first, values, flat, status):  # pragma: no cover - compiled
    """Cut the polygons (face rows ``polygons``, their corners as :func:`_face_rows` left them in ``flat``) into
    triangles as Open3D's ear clipping does (:func:`_cut_polygon_reference`, its plain twin), on the positions
    ``values[:, :3]`` rounded to float32 as Open3D holds them; ``status`` becomes no-ear where it fails. A polygon
    with a corner beyond the vertices is a fan, for the mesh to report the index."""
    V = values.shape[0]
    for q in range(lo, hi):
        r = polygons[q]
        n = sizes[r]
        at = 3 * first[r]
        corners = flat[at : at + n].copy()
        t = at
        if corners.max() >= V:
            for k in range(1, n - 1):
                flat[t], flat[t + 1], flat[t + 2] = corners[0], corners[k], corners[k + 1]
                t += 3
            continue
        x = np.empty(n)
        y = np.empty(n)
        z = np.empty(n)
        for c in range(n):
            x[c] = np.float32(values[corners[c], 0])
            y[c] = np.float32(values[corners[c], 1])
            z[c] = np.float32(values[corners[c], 2])
        nx = ny = nz = 0.0
        for i in range(n):
            a, b, c = i, (i + 1) % n, (i + 2) % n
            ux, uy, uz = x[b] - x[a], y[b] - y[a], z[b] - z[a]
            vx, vy, vz = x[c] - x[b], y[c] - y[b], z[c] - z[b]
            nx += uy * vz - uz * vy
            ny += uz * vx - ux * vz
            nz += ux * vy - uy * vx
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0.0:  # Open3D's normal is then NaN: no corner is convex
            status[r] = _NO_EAR
            continue
        inverse = 1.0 / length
        nx, ny, nz = nx * inverse, ny * inverse, nz * inverse
        order = np.arange(n)  # the corners left
        m = n
        found = True
        while m > 3 and found:
            found = False
            for i in range(1, m - 1):
                a, b, c = order[i - 1], order[i], order[i + 1]
                ux, uy, uz = x[b] - x[a], y[b] - y[a], z[b] - z[a]
                vx, vy, vz = x[c] - x[b], y[c] - y[b], z[c] - z[b]
                if nx * (uy * vz - uz * vy) + ny * (uz * vx - ux * vz) + nz * (ux * vy - uy * vx) <= 0.0:
                    continue  # not convex (or NaN)
                ear = True
                for j in range(m):
                    if j == i - 1 or j == i or j == i + 1:
                        continue
                    px, py = x[order[j]], y[order[j]]
                    inside = False
                    for e in range(3):  # the triangle's edges, in x and y only
                        s, u = order[i - 1 + e], order[i - 1 + (e + 1) % 3]
                        if (y[s] <= py < y[u]) or (y[u] <= py < y[s]):
                            if (x[u] - x[s]) * (py - y[s]) / (y[u] - y[s]) + x[s] < px:
                                inside = not inside
                    if inside:
                        ear = False
                        break
                if ear:
                    found = True
                    flat[t], flat[t + 1], flat[t + 2] = corners[a], corners[b], corners[c]
                    t += 3
                    for k in range(i, m - 1):
                        order[k] = order[k + 1]
                    m -= 1
                    break
        if m > 3:
            status[r] = _NO_EAR
            continue
        flat[t], flat[t + 1], flat[t + 2] = corners[order[0]], corners[order[1]], corners[order[2]]


def _cut_polygon_reference(points: np.ndarray, corners: list[int]) -> list[tuple[int, int, int]] | None:
    """Open3D's ``AddTrianglesByEarClipping`` (``TriangleMeshIO.cpp``), in plain Python: the triangles of the
    polygon ``corners`` (n > 3 vertex indices) of ``points`` (V, 3), or None where it fails.

    The polygon's normal is the sum of the crosses of its consecutive edges, normalised. Corner ``i`` from 1 to
    n - 2 (never the first or the last) is an ear when it is convex about that normal and no other corner lies
    inside the triangle ``i - 1, i, i + 1`` seen along z (an even-odd crossing count in x and y); the first ear is
    cut off and the search starts again, until three corners are left. No ear in a pass, or a zero normal, fails.
    """
    p = [[float(np.float32(v)) for v in points[c]] for c in corners]  # the float32 positions Open3D holds
    n = len(p)
    normal = [0.0, 0.0, 0.0]
    for i in range(n):
        u = [p[(i + 1) % n][k] - p[i][k] for k in range(3)]
        v = [p[(i + 2) % n][k] - p[(i + 1) % n][k] for k in range(3)]
        normal = [normal[0] + (u[1] * v[2] - u[2] * v[1]), normal[1] + (u[2] * v[0] - u[0] * v[2]),
                  normal[2] + (u[0] * v[1] - u[1] * v[0])]
    length = math.sqrt(normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2])
    if length == 0.0:
        return None
    normal = [k * (1.0 / length) for k in normal]
    order = list(range(n))
    out = []
    while len(order) > 3:
        for i in range(1, len(order) - 1):
            a, b, c = p[order[i - 1]], p[order[i]], p[order[i + 1]]
            u = [b[k] - a[k] for k in range(3)]
            v = [c[k] - b[k] for k in range(3)]
            cross = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
            if not normal[0] * cross[0] + normal[1] * cross[1] + normal[2] * cross[2] > 0.0:
                continue
            triangle = (a, b, c)
            if not any(_inside_xy(triangle, p[order[j]]) for j in range(len(order)) if abs(j - i) > 1):
                out.append((corners[order[i - 1]], corners[order[i]], corners[order[i + 1]]))
                del order[i]
                break
        else:
            return None
    return out + [tuple(corners[k] for k in order)]


def _inside_xy(triangle: tuple, point: list[float]) -> bool:
    """Open3D's ``IsPointInsidePolygon`` for a triangle: an even-odd count of the edges crossing the line from
    ``point`` towards -x."""
    inside = False
    for e in range(3):
        s, u = triangle[e], triangle[(e + 1) % 3]
        if (s[1] <= point[1] < u[1]) or (u[1] <= point[1] < s[1]):
            if (u[0] - s[0]) * (point[1] - s[1]) / (u[1] - s[1]) + s[0] < point[0]:
                inside = not inside
    return inside


# --- completeness and writing --------------------------------------------------------------------------------------


def check_complete(p: Path) -> None:
    """Raise if a text OFF file has fewer rows than its header declares (Open3D keeps the vertices it got)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    header = re.match(rb"[ \t]*[A-Z]*OFF[ \t]*\r?\n(?:[ \t]*(?:#[^\n]*)?\n)*[ \t]*(\d+)[ \t]+(\d+)[^\n]*\n", head)
    if not header:
        return  # binary OFF, counts on the first line, or not OFF at all: Open3D decides
    n_vertices, n_faces = int(header.group(1)), int(header.group(2))
    rows = count_lines(p, header.end())
    if rows < n_vertices + n_faces:
        raise InputError(
            f"{p}: the file is truncated: its header declares {n_vertices} vertices and {n_faces} faces "
            f"({n_vertices + n_faces} rows) but {rows} rows follow"
        )


def write_mesh(p: Path, mesh: Mesh) -> None:
    """Write ``mesh`` to ``p`` as a text OFF (see the module notes); UVs and textures are not written.

    Parameters
    ----------
    p : the file (the caller writes it atomically and checks it)
    mesh : Mesh, its (V, 3) vertices, (T, 3) triangles and, when present, (V, 3) normals and (V, 3) colours
    """
    from kpd.io import text

    blocks = [mesh.vertices]
    if mesh.vertex_normals is not None:
        blocks.append(mesh.vertex_normals)
    suffix = b"\n"
    if mesh.vertex_colors is not None:
        scaled = mesh.vertex_colors * 255.0
        down = np.floor(scaled)
        blocks.append(np.where(scaled - down >= 0.5, down + 1.0, down) + 0.0)  # C's round(): halves away from zero
        suffix = b" 255\n"
    kind = ("C" if mesh.vertex_colors is not None else "") + ("N" if mesh.vertex_normals is not None else "")
    with open(p, "wb") as fh:
        fh.write(f"{kind}OFF\n{len(mesh.vertices)} {len(mesh.triangles)} 0\n".encode())
        text.write_float_rows(fh, blocks, 9, suffix=suffix)
        text.write_index_rows(fh, mesh.triangles, prefix=b"3 ", base=0)
