"""OBJ, read by kpd itself so that nothing of the file is lost, and written back in the file's own structure.

Reading (:func:`read`) keeps the file's vertex order: vertex ``i`` of the :class:`~kpd.mesh.Mesh` is the file's
``i``-th ``v`` line (Assimp, inside Open3D, splits vertices where UVs or normals differ, reorders them by first use
and drops every UV of a file that mixes faces with and without texture coordinates; measured in docs/formats.md).
Faces with texture coordinates get them, faces without them are marked in ``Mesh.triangle_uv_mask``. Every material
of the ``.mtl`` that the faces use becomes one entry of ``Mesh.textures``: its ``map_Kd`` image as in the file, or
a 1x1 image of its ``Kd`` colour (what the drawing code shows, shaded, as the material's colour).

Writing a mesh read from an OBJ (:func:`write`, directly or after :meth:`~kpd.mesh.Mesh.with_vertices`) rewrites
only the ``v`` lines (and the ``vn`` lines, turned with the surface) of the input's own text: groups, smoothing
groups, lines, comments, materials and face order stay as they were; the ``.mtl`` is copied as ``<stem>.mtl`` with
its maps renamed, and every image it names is copied byte for byte as ``<stem>_<its name>`` (a JPEG stays a JPEG),
so that the outputs of one folder never collide. Only the files kpd read are copied: those inside the input's folder
tree that are what they claim (:mod:`kpd.io.references`); the statement of any other is kept as a comment. Any
other mesh is written by :func:`write` from its arrays: ``v`` (with ``r g b`` when it has vertex colours), ``vt``
on the faces that have UVs, ``vn``, one material per texture (a 1x1 texture as a plain ``Kd`` colour, others as
``<stem>_<i>.png``).

Faces of more than three corners (Blender's quads and n-gons) are read as fans of triangles from their first corner;
the file's own structure written back keeps them as the polygons they are.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kpd.errors import InputError, WriteError
from kpd._compiled import compiled_on_first_call
from kpd.io.atomic import atomic_files
from kpd.io.common import incomplete, verify_companion
from kpd.io import mtl, references
from kpd.io.images import decode_image
from kpd.io.mtl import (DEFAULT_KD as _DEFAULT_KD, MAP_KEYS as _MAP_KEYS, Material, find_map as _find_map,  # noqa: F401
                        library_files as _library_files, map_file as _map_file, map_statements as _map_statements,
                        read_library, renamed_library as _renamed_library, strip_comment as _strip_comment)
from kpd.io.numbers import BLANKS, in_halves, scan_numbers
from kpd.mesh import Mesh, PointSet, count_phrase
from kpd.triangles import turned_normals

__all__ = ["read", "write", "companions", "ObjSource"]

log = logging.getLogger("kpd.io.obj")


# --- reading -------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class ObjSource:
    """An OBJ file as read: its bytes, where its ``v``/``vn`` lines are, and its materials' files.

    Attributes
    ----------
    path : the file.
    data : its bytes.
    v_spans : (V, 2) int64, start and end (before the line break) of each ``v`` line.
    v_tails : bytes after the three coordinates of each ``v`` line (``w`` or ``r g b``), or None when all are empty.
    vn_spans : (N, 2) int64, likewise for the ``vn`` lines.
    corner_normals : (T, 3) int64, the ``vn`` index of each corner, -1 where the corner has none.
    vertices : (V, 3) float64, the positions as read (a write of unchanged positions copies the text as it is).
    libraries : the ``mtllib`` statements as (start, end) spans with their file names (resolved paths or None).
    files : {real path: bytes} of the material libraries and maps kpd read (:mod:`kpd.io.references`): the only
        files a write copies.
    root : the folder tree those files were looked for in.
    """

    path: Path
    data: bytes
    v_spans: np.ndarray
    v_tails: list | None
    vn_spans: np.ndarray
    corner_normals: np.ndarray
    normals: np.ndarray
    vertices: np.ndarray
    libraries: list = field(default_factory=list)
    face_lines: int = 0
    files: dict = field(default_factory=dict)
    root: Path | None = None


_SPACE, _TAB, _HASH, _SLASH, _NEWLINE = 32, 9, 35, 47, 10
_V, _F, _T, _N, _U, _M = ord("v"), ord("f"), ord("t"), ord("n"), ord("u"), ord("m")
_USEMTL, _MTLLIB = np.frombuffer(b"usemtl", np.uint8).copy(), np.frombuffer(b"mtllib", np.uint8).copy()
_KINDS = {"v": 1, "vt": 2, "vn": 3, "f": 4, "usemtl": 5, "mtllib": 6, "other": 0}
_in_halves, _numbers, _BLANKS = in_halves, scan_numbers, BLANKS  # the scanner's names in this module, still importable


def _scan(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Line starts, ends (before ``\\r\\n`` or ``\\n``), the first non-blank byte of each line and each line's kind
    (:data:`_KINDS`), (L,) int64 (the kinds int8): numpy finds the line breaks, a compiled pass the rest
    (:func:`_line_table`)."""
    buf = np.frombuffer(data, dtype=np.uint8)
    breaks = np.flatnonzero(buf == _NEWLINE)
    count = len(breaks) + 1
    if count > 1 and breaks[-1] == len(buf) - 1:  # a last line break ends the last line; no empty line follows
        count -= 1
    table = (*(np.empty(count, np.int64) for _ in range(3)), np.empty(count, np.int8))
    in_halves(_line_table, count, buf, breaks, *table)
    return table


@compiled_on_first_call
def _line_table(lo, hi, buf, breaks, starts, ends, first, kind):  # pragma: no cover - compiled
    n = len(buf)
    for line in range(lo, hi):
        start = breaks[line - 1] + 1 if line else 0
        end = breaks[line] if line < len(breaks) else n
        if end > start and buf[end - 1] == 13:
            end -= 1
        j = start
        while j < end and (buf[j] == _SPACE or buf[j] == _TAB):
            j += 1
        starts[line], ends[line], first[line] = start, end, j
        kind[line] = 0
        c0 = buf[j] if j < n else 0
        c1 = buf[j + 1] if j + 1 < n else 0
        c2 = buf[j + 2] if j + 2 < n else 0
        white1 = (c1 == _SPACE or c1 == _TAB) and j + 1 < end
        white2 = (c2 == _SPACE or c2 == _TAB) and j + 2 < end
        if c0 == _V and white1:
            kind[line] = 1
        elif c0 == _V and c1 == _T and white2:
            kind[line] = 2
        elif c0 == _V and c1 == _N and white2:
            kind[line] = 3
        elif c0 == _F and white1:
            kind[line] = 4
        elif (c0 == _U or c0 == _M) and j + 6 <= n:  # usemtl / mtllib, then a blank or the file's end
            word = 5 if c0 == _U else 6
            for k in range(6):
                if buf[j + k] != (_USEMTL[k] if word == 5 else _MTLLIB[k]):
                    word = 0
                    break
            if word and (j + 6 == n or buf[j + 6] == _SPACE or buf[j + 6] == _TAB):
                kind[line] = word
    return starts, ends, first, kind


def _values(p: Path, data: bytes, lines, rows: np.ndarray, prefix: int, widths: tuple,
            kind: str) -> tuple[np.ndarray, bool]:
    """(n, w) float64 of the lines ``rows`` of one kind, and whether all lines hold w numbers (one of ``widths``);
    when they hold different counts, the first ``widths[0]`` numbers of each (the rest is their tail).

    Compiled (:func:`kpd.io.numbers.scan_numbers`); a word beyond its fast path (more than 15 significant digits,
    ``nan``, a stray character) is read by Python's ``float``, so every value is the correctly rounded one."""
    starts, ends, first, _ = lines
    n = len(rows)
    if not n:
        return np.zeros((0, widths[0])), True
    out = np.zeros((n, max(widths)))
    counts = np.empty(n, dtype=np.int64)
    exact = np.empty(n, dtype=np.bool_)
    buf = np.frombuffer(data, dtype=np.uint8)
    in_halves(scan_numbers, n, buf, first[rows] + prefix, ends[rows], out, counts, exact)
    for j in np.flatnonzero(~exact).tolist():  # rare: words Python reads, or reports
        i = int(rows[j])
        try:
            numbers = [float(x) for x in _strip_comment(data[first[i] + prefix:ends[i]]).split()]
        except ValueError:
            raise InputError(f"{p}: line {i + 1}: a '{kind}' line holds something that is not a number") from None
        out[j, :min(len(numbers), out.shape[1])] = numbers[:out.shape[1]]
    low, high = int(counts.min()), int(counts.max())
    if low == high and low in widths:
        return out[:, :low], True
    if low < widths[0]:
        i = int(rows[np.argmax(counts < widths[0])])
        raise InputError(f"{p}: line {i + 1}: a '{kind}' line needs {widths[0]} numbers; got {low}")
    return out[:, :widths[0]], False


# what _face_corners reports of a line
_FACE_FINE, _FACE_SHORT, _FACE_MIXED, _FACE_NOT_INDEX, _FACE_FORM = 0, 1, 2, 3, 4


@compiled_on_first_call
def _face_forms(lo, hi, buf, begin, stop, corners, forms, status):  # pragma: no cover - compiled
    """Per face line r: its corners (blank-separated words up to a ``#``) into ``corners[r]``, the slashes of each
    corner (0 ``v``, 1 ``v/vt``, 2 ``v/vt/vn`` or ``v//vn``) into ``forms[r]``, and ``status[r]``: fine, short
    (fewer than 3 corners) or mixed (corners of different forms, or more than 2 slashes)."""
    for r in range(lo, hi):
        i, end = begin[r], stop[r]
        c = 0
        form = -1
        mixed = False
        while True:
            while i < end and buf[i] <= _SPACE:
                i += 1
            if i >= end or buf[i] == _HASH:
                break
            slashes = 0
            while i < end and buf[i] > _SPACE and buf[i] != _HASH:
                slashes += buf[i] == _SLASH
                i += 1
            if form < 0:
                form = slashes
            mixed |= slashes != form or slashes > 2
            c += 1
        corners[r] = c
        forms[r] = max(form, 0)
        status[r] = _FACE_SHORT if c < 3 else (_FACE_MIXED if mixed else _FACE_FINE)


@compiled_on_first_call
def _face_corners(lo, hi, buf, begin, stop, forms, first_triangle, guess, sides, v, vt, vn,
                  status):  # pragma: no cover - compiled
    """The triangles of face line r from ``first_triangle[r]`` on: their corners' indices in ``v``, ``vt`` and
    ``vn`` (T, 3) each (0 where a corner has none; ``vt`` and ``vn`` may be empty when no line has them), a fan
    from the first corner for a polygon. ``status[r]`` becomes not-an-index for a word
    that is not signed integers and slashes, or wrong-form for an index missing anywhere but the middle of
    ``v//vn``.

    With ``guess`` (0 to 2) instead of -1, every line is taken for a face of ``sides`` corners (3 or 4) of ``guess``
    slashes, its triangles from ``r * (sides - 2)`` on (``forms`` and ``first_triangle`` are not read): a line that
    is not (more or fewer corners, another form, an error) gets a status other than fine and ends the pass over its
    rows."""
    for r in range(lo, hi):
        if status[r] != _FACE_FINE:
            continue
        i, end = begin[r], stop[r]
        width = forms[r] + 1 if guess < 0 else guess + 1
        c = 0
        t = first_triangle[r] if guess < 0 else r * (sides - 2)
        v0 = t0 = n0 = v1 = t1 = n1 = 0
        while True:
            while i < end and buf[i] <= _SPACE:
                i += 1
            if i >= end or buf[i] == _HASH:
                break
            if guess >= 0 and c == sides:  # a corner more
                status[r] = _FACE_FORM
                break
            a = b = e = 0
            for part in range(width):
                negative = False
                if i < end and (buf[i] == 43 or buf[i] == 45):
                    negative = buf[i] == 45
                    i += 1
                digits = 0
                value = 0
                while i < end and 48 <= buf[i] <= 57:
                    value = value * 10 + (buf[i] - 48) if digits < 18 else value
                    digits += 1
                    i += 1
                last = part == width - 1
                follows = i < end and buf[i] > _SPACE and buf[i] != _HASH  # more of the word
                if digits > 18 or (follows and (last or buf[i] != _SLASH)):
                    status[r] = _FACE_NOT_INDEX
                elif digits == 0 and (negative or not (width == 3 and part == 1)):
                    status[r] = _FACE_FORM
                if not last and guess >= 0 and not (i < end and buf[i] == _SLASH):  # fewer slashes
                    status[r] = _FACE_FORM
                if status[r] != _FACE_FINE:
                    break
                if not last:
                    i += 1  # the slash
                value = -value if negative else value
                if part == 0:
                    a = value
                elif part == 1:
                    b = value
                else:
                    e = value
            if status[r] != _FACE_FINE:
                break
            if c == 0:
                v0, t0, n0 = a, b, e
            elif c >= 2:
                v[t, 0], v[t, 1], v[t, 2] = v0, v1, a
                if len(vt):
                    vt[t, 0], vt[t, 1], vt[t, 2] = t0, t1, b
                if len(vn):
                    vn[t, 0], vn[t, 1], vn[t, 2] = n0, n1, e
                t += 1
            v1, t1, n1 = a, b, e
            c += 1
        if guess >= 0 and (c != sides or status[r] != _FACE_FINE):
            status[r] = max(status[r], _FACE_SHORT)
            return


def _faces(p: Path, data: bytes, lines, rows: np.ndarray) -> tuple[list, np.ndarray]:
    """The corner indices of the triangles of the face lines, ``[v, vt, vn]``, each (T, 3) int64 (1-based, negative
    relative, 0 none) or None when no line has it, and (T,) the line of each triangle. A face of c > 3 corners
    (Blender's quads and n-gons) gives c - 2 triangles, a fan from its first corner; the file keeps the face as it is.
    One compiled pass (:func:`_face_corners`) when every line has the first one's corners, 3 or 4, of its form; else
    two: the corners and form of each line (:func:`_face_forms`), then the indices."""
    starts, ends, first, _ = lines
    n = len(rows)
    buf = np.frombuffer(data, dtype=np.uint8)
    begin, stop = first[rows] + 1, ends[rows]
    unread = np.empty(0, dtype=np.int64)
    words = _strip_comment(data[begin[0]:stop[0]]).split() if n else []
    guess = words[0].count(b"/") if 3 <= len(words) <= 4 else 3
    if guess <= 2:  # one pass when every line is like the first: triangles as scanners write them, Blender's quads
        sides = len(words)
        status = np.zeros(n, dtype=np.int8)
        indices = [np.zeros((n * (sides - 2) if guess >= k else 0, 3), dtype=np.int64) for k in range(3)]
        in_halves(_face_corners, n, buf, begin, stop, unread, unread, guess, sides, *indices, status)
        if not status.any():
            return [index if len(index) else None for index in indices], rows if sides == 3 else np.repeat(rows, 2)
    corners = np.empty(n, dtype=np.int64)
    forms = np.empty(n, dtype=np.int64)
    status = np.empty(n, dtype=np.int8)
    in_halves(_face_forms, n, buf, begin, stop, corners, forms, status)
    first_triangle = np.concatenate([[0], np.cumsum(np.maximum(corners - 2, 0))]).astype(np.int64)
    T = int(first_triangle[-1])
    widest = int(forms.max()) if n else 0
    indices = [np.zeros((T if widest >= k else 0, 3), dtype=np.int64) for k in range(3)]
    in_halves(_face_corners, n, buf, begin, stop, forms, first_triangle, -1, 0, *indices, status)
    if status.any():
        _face_error(p, data, lines, rows, status, corners, forms)
    return [index if len(index) else None for index in indices], rows if T == n else np.repeat(rows, corners - 2)


def _face_error(p: Path, data: bytes, lines, rows: np.ndarray, status: np.ndarray, corners: np.ndarray,
                forms: np.ndarray) -> None:
    """Raise the error of the first face line that has one, as runs of consecutive face lines are judged: a run with
    a face of fewer than 3 corners is counted (all such faces are reported after the other runs), a run with corners
    of mixed forms is reported at its first such line, else the first line whose indices cannot be read."""
    starts, ends, first, _ = lines
    run = np.cumsum(np.diff(rows, prepend=rows[0]) != 1)  # (n,) the run of consecutive lines of each face line
    short = status == _FACE_SHORT
    judged = (status != _FACE_FINE) & ~short & ~np.isin(run, run[short])
    if judged.any():
        j = int(np.argmax(judged))
        mixed = (run == run[j]) & (status == _FACE_MIXED)
        if mixed.any():
            j = int(np.argmax(mixed))
        i = int(rows[j])
        if status[j] == _FACE_MIXED:
            raise InputError(f"{p}: line {i + 1}: the corners of a face must all have the same form (v, v/vt, "
                             f"v/vt/vn or v//vn); got {data[first[i]:ends[i]].decode(errors='replace')!r}")
        if status[j] == _FACE_NOT_INDEX:
            raise InputError(f"{p}: line {i + 1}: a face line holds something that is not an index")
        raise InputError(f"{p}: line {i + 1}: a face line does not hold {int(corners[j])} corners of "
                         f"{int(forms[j]) + 1} indices")
    raise InputError(f"{p}: {count_phrase(int(short.sum()), 'faces')} fewer than 3 vertices (first: line "
                     f"{int(rows[np.argmax(short)]) + 1})")


@compiled_on_first_call
def _indices(index, n):  # pragma: no cover - compiled
    """``index`` (T, 3) made 0-based in place (``index - 1``: -1 where a corner has none); returns how many were
    negative (relative: the caller then resolves them from the file's values, ``index + 1``), how many were 0, and how
    many triangles have one above ``n``."""
    relative = 0
    missing = 0
    bad = 0
    for t in range(index.shape[0]):
        wrong = False
        for c in range(3):
            x = index[t, c]
            index[t, c] = x - 1
            relative += x < 0
            missing += x == 0
            wrong |= x > n
        bad += wrong
    return relative, missing, bad


@compiled_on_first_call
def _normal_sums(triangles, normal_index, vn, n):  # pragma: no cover - compiled
    """(n, 3) float64: per vertex, the sum of the ``vn`` its corners use (``normal_index`` (T, 3), -1 none), added
    corner by corner in order (``np.bincount`` of them, to the bit, without the (3T, 3) gathered normals)."""
    out = np.zeros((n, 3))
    for t in range(triangles.shape[0]):
        for k in range(3):
            j = normal_index[t, k]
            if j >= 0:
                v = triangles[t, k]
                out[v, 0] += vn[j, 0]
                out[v, 1] += vn[j, 1]
                out[v, 2] += vn[j, 2]
    return out


def _keyword_lines(data: bytes, lines, keyword: str) -> list[tuple[int, bytes]]:
    """(line index, argument text) of the ``usemtl`` or ``mtllib`` lines."""
    starts, ends, first, kind = lines
    return [(i, _strip_comment(data[first[i] + 6 : ends[i]]).strip())
            for i in np.flatnonzero(kind == _KINDS[keyword]).tolist()]


def parse(p: Path, data: bytes, points: bool = False) -> tuple[dict, ObjSource | None]:
    """Parse an OBJ's geometry; returns the arrays of :func:`read` and the :class:`ObjSource` for writing."""
    lines = _scan(data)
    starts, ends, first, kind = lines
    v_rows, vt_rows, vn_rows, f_rows = (np.flatnonzero(kind == _KINDS[k]) for k in ("v", "vt", "vn", "f"))
    table, uniform = _values(p, data, lines, v_rows, 1, (3, 4, 6, 7), "v")
    if not len(table):
        raise InputError(f"{p}: no vertices (empty geometry)")
    vertices = np.ascontiguousarray(table[:, :3])
    colors = _colors(table[:, 3:6]) if table.shape[1] >= 6 else None
    if not len(f_rows):
        if points:
            return {"vertices": vertices, "colors": colors}, None
        raise InputError(f"{p}: has {len(vertices)} vertices but no triangles (a point cloud? use read_points or "
                         "read_shape)")
    vt = _values(p, data, lines, vt_rows, 2, (2, 3, 1), "vt")[0]
    if vt.shape[1] == 1:
        vt = np.hstack([vt, np.zeros_like(vt)])
    vt = vt[:, :2]
    vn = _values(p, data, lines, vn_rows, 2, (3,), "vn")[0]
    corner, face_rows = _faces(p, data, lines, f_rows)  # [v, vt, vn] (T, 3) or None, (T,) the line of each
    T = len(face_rows)

    def resolve(index: np.ndarray | None, rows: np.ndarray, kind: str, n: int, optional: bool) -> np.ndarray:
        """(T, 3) 0-based indices, -1 where missing (a read-only view of -1 when no face has this kind)."""
        if index is None:
            return np.broadcast_to(np.int64(-1), (T, 3))
        relative, missing, bad = _indices(index, n)  # in place: index - 1
        if not (relative or (missing and not optional) or bad):
            return index
        index += 1  # as the file has them
        out = index - 1
        if relative:  # negative: relative to the elements defined before the face
            before = np.searchsorted(rows, face_rows)[:, None]
            out = np.where(index < 0, before + index, out)
        missing = index == 0
        if not optional and missing.any():
            raise InputError(f"{p}: a face has the vertex index 0 (OBJ counts from 1)")
        bad = ~missing & ((out < 0) | (out >= n))
        if bad.any():
            raise InputError(f"{p}: {count_phrase(int(bad.any(axis=1).sum()), 'faces', 'name', 'names')} a "
                             f"{kind} outside 1..{n}")
        return np.where(missing, -1, out)

    triangles = resolve(corner[0], v_rows, "vertex", len(vertices), False)
    uv_index = resolve(corner[1], vt_rows, "texture coordinate", len(vt), True)
    normal_index = resolve(corner[2], vn_rows, "normal", len(vn), True)
    has_uv = None  # (T,) a face with coordinates on some corners only counts as without
    if corner[1] is not None:
        has_uv = (uv_index >= 0).all(axis=1)
    uvs = None
    if has_uv is not None and has_uv.any():
        # np.take of rows: an order of magnitude faster than fancy indexing of a 2-d array by a (T, 3) one
        if has_uv.all():
            uvs = np.take(vt, uv_index.reshape(-1), axis=0)
        else:
            uvs = np.take(vt, np.where(has_uv[:, None], uv_index, 0).reshape(-1), axis=0)
            uvs.reshape(T, 6)[~has_uv] = 0.0

    normals = None
    if corner[2] is not None and (normal_index >= 0).any():
        from kpd.triangles import vertex_normals

        normals = _normal_sums(triangles, normal_index, vn, len(vertices))  # (V, 3) the corners' vn summed
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.maximum(length, 1e-300)
        weak = ~(length[:, 0] > 1e-12)  # no normal, ones that cancel (or not a number): the faces' own
        if weak.any():
            normals[weak] = vertex_normals(vertices, triangles)[weak]

    # materials: the last 'usemtl' before each face
    usemtl = _keyword_lines(data, lines, "usemtl")
    face_material = None
    if usemtl:
        names = [None] + [text.decode("utf-8", "replace") for _, text in usemtl]
        which = np.searchsorted(np.array([i for i, _ in usemtl], dtype=np.int64), face_rows)  # 0: before any
        used: dict = {}  # the names the faces use, in order of first use (which never decreases)
        lookup = np.full(len(names), -1, dtype=np.int64)
        for w in which[np.flatnonzero(np.diff(which, prepend=-1))].tolist():
            lookup[w] = used.setdefault(names[w], len(used))
        face_material = (list(used), lookup[which])
    libraries = [(int(starts[i]), int(ends[i]), text.decode("utf-8", "replace"))
                 for i, text in _keyword_lines(data, lines, "mtllib")]
    source = ObjSource(path=p, data=data, v_spans=np.stack([starts[v_rows], ends[v_rows]], axis=1),
                       v_tails=_tails(data, lines, v_rows) if table.shape[1] > 3 or not uniform else None,
                       vn_spans=np.stack([starts[vn_rows], ends[vn_rows]], axis=1), corner_normals=normal_index,
                       normals=vn, vertices=vertices, libraries=libraries, face_lines=len(f_rows))
    arrays = {"vertices": vertices, "triangles": triangles, "vertex_normals": normals, "vertex_colors": colors,
              "triangle_uvs": uvs, "uv_mask": has_uv if uvs is not None and not has_uv.all() else None,
              "face_material": face_material}
    return arrays, source


def _tails(data: bytes, lines, rows: np.ndarray) -> list[bytes]:
    """The text after the three coordinates of each ``v`` line (``w`` or ``r g b``)."""
    starts, ends, first, _ = lines
    return [b" ".join(_strip_comment(data[first[i] + 1 : ends[i]]).split()[3:]) for i in rows.tolist()]


def _colors(values: np.ndarray) -> np.ndarray | None:
    """(V, 3) vertex colours of ``v x y z r g b`` lines (0-1, or 0-255 scaled down), or None."""
    if not len(values) or values.min() < 0.0:
        return None
    if values.max() > 1.0 + 1e-6:
        return values / 255.0 if values.max() <= 255.0 else None
    return np.ascontiguousarray(values)


def _material_files(p: Path, source: ObjSource, root: Path) -> tuple[dict, dict, dict]:
    """The material libraries the OBJ ``p`` names and the maps they name, as :mod:`kpd.io.references` allows them:
    {real path: bytes} of every file accepted (the libraries' text, the maps' bytes: all a writer copies),
    {real path: (H, W, C) uint8} of the maps, and the materials by name. One warning for each file not read."""
    files: dict[Path, bytes] = {}
    images: dict[Path, np.ndarray] = {}
    materials: dict[str, Material] = {}
    judged: set = set()  # files looked at (read or refused), each reported once
    said: set = set()
    missing = []
    for _, _, names in source.libraries:
        for lib_name, found in mtl.library_references(p, names, root):
            if found.refused is not None:
                references.warn_refused(p, "material library", lib_name, found.refused, said)
                continue
            if found.path is None:
                log.warning("%s: material library %r is missing; read without materials and textures", p, lib_name)
                continue
            if found.path not in judged:
                judged.add(found.path)
                data = references.read_named(found.path, references.MTL_BYTES)
                if isinstance(data, bytes) and not references.is_text(data):
                    data = "not a text file"
                if isinstance(data, str):
                    references.warn_refused(p, "material library", lib_name, data, said)
                    continue
                files[found.path] = data
                _map_files(p, root, found.path, data, files, images, judged, said)
            if found.path not in files:
                continue
            for material in mtl.read_library(p, found.path, files[found.path], root).values():
                materials.setdefault(material.name, material)
                if material.map_kd_name and material.map_kd is None and material.map_kd_refused is None:
                    missing.append(material.map_kd_name)
    if missing:
        log.warning("%s: texture file(s) %s named in the material library are missing; read without them",
                    p, ", ".join(dict.fromkeys(missing)))
    return files, images, materials


def _map_files(p: Path, root: Path, library: Path, data: bytes, files: dict, images: dict, judged: set,
               said: set) -> None:
    """Read every map the library names that :mod:`kpd.io.references` allows and that decodes as an image into
    ``files`` (its bytes) and ``images`` (its pixels); one warning for each other one."""
    for _, arguments in mtl.map_statements(data):
        name, whole = mtl.map_name(arguments)
        found = mtl.locate_map(root, library.parent, name, whole)
        if found.refused is not None:
            references.warn_refused(p, f"map of {library.name}", name, found.refused, said)
            continue
        if found.path is None or found.path in judged:
            continue  # a missing map_Kd is reported with the materials
        judged.add(found.path)
        raw = references.read_named(found.path, references.IMAGE_BYTES)
        image = decode_image(raw) if isinstance(raw, bytes) else None
        if image is None:
            references.warn_refused(p, f"map of {library.name}", name,
                                    raw if isinstance(raw, str) else "not an image that decodes", said)
            continue
        files[found.path] = raw
        images[found.path] = image


def read(p: Path, name: str | None = None, *, points: bool = False, root: Path | None = None) -> "Mesh | PointSet":
    """Read an OBJ file (see the module notes); ``name`` is the path as the user gave it, for messages. With
    ``points``, a file without faces gives a :class:`~kpd.mesh.PointSet` of its vertices instead of an error. The
    files it names are read inside ``root`` only (its own folder when None; :mod:`kpd.io.references`)."""
    data = p.read_bytes()
    if b"\0" in data[:4096]:
        raise InputError(f"{p}: not a text OBJ file (it holds binary data)")
    arrays, source = parse(p, data, points)
    if source is None:
        return PointSet(arrays["vertices"], None, arrays["colors"], path=name if name is not None else os.fspath(p))
    T = len(arrays["triangles"])
    source.root = p.parent if root is None else Path(root)
    source.files, images, materials = _material_files(p, source, source.root)
    textures, ids, texture_files = [], None, []
    face_material = arrays["face_material"]
    if face_material is not None and materials:
        used, face_ids = face_material
        chosen, colors = [], []
        for m in used:
            material = materials.get(m) if m is not None else None
            image = images.get(material.map_kd) if material is not None and material.map_kd is not None else None
            kd = material.kd if material is not None else _DEFAULT_KD
            colors.append(kd)
            chosen.append(image)
            texture_files.append(material.map_kd if image is not None else None)
        if any(i is not None for i in chosen) or len(set(colors)) > 1:
            for image, kd in zip(chosen, colors):
                if image is None:
                    image = np.round(np.array(kd, dtype=np.float64) * 255).astype(np.uint8).reshape(1, 1, 3)
                textures.append(image)
            ids = face_ids
    uvs, mask = arrays["triangle_uvs"], arrays["uv_mask"]
    if textures and uvs is None:
        uvs = np.zeros((3 * T, 2), dtype=np.float64)  # plain colours only: every face samples its 1x1 texture
        mask = np.zeros(T, dtype=bool)
    mesh = Mesh(vertices=arrays["vertices"], triangles=arrays["triangles"], vertex_normals=arrays["vertex_normals"],
                vertex_colors=arrays["vertex_colors"], triangle_uvs=uvs, textures=textures,
                triangle_material_ids=ids, triangle_uv_mask=mask, path=name if name is not None else os.fspath(p))
    mesh._source = source
    mesh._texture_files = texture_files if textures else []
    return mesh


# --- writing -------------------------------------------------------------------------------------------------------


def _own_source(mesh: Mesh) -> ObjSource | None:
    """The OBJ the mesh was read from, when its topology is still that file's."""
    source = getattr(mesh, "_source", None)
    if not isinstance(source, ObjSource) or len(source.vertices) != len(mesh.vertices):
        return None
    if len(source.corner_normals) != len(mesh.triangles):
        return None
    return source


def write(p: Path, mesh: Mesh) -> None:
    """Write ``mesh`` to ``p`` with its companions, atomically, and check the result (see the module notes)."""
    source = _own_source(mesh)
    with atomic_files(p) as target:
        if source is not None:
            _write_from_source(target, mesh, source)
        else:
            _write_arrays(target, mesh)
        _verify(p, target, mesh, len(mesh.triangles) if source is None else source.face_lines)


def companions(p: Path, mesh: Mesh) -> list[str]:
    """The files :func:`write` adds beside ``p``."""
    source = _own_source(mesh)
    if source is not None:
        libraries, images = _source_companions(p.stem, source)
        return [name for name, _ in libraries.values()] + list(images.values())
    if not mesh.textures:
        return []
    return [p.stem + ".mtl"] + [f"{p.stem}_{i}.png" for i, t in enumerate(mesh.textures) if _is_image(t)]


def _is_image(texture: np.ndarray) -> bool:
    return texture.shape[0] * texture.shape[1] > 1


def _fmt(rows: np.ndarray, prefix: bytes, tails: list | None = None) -> tuple:
    """(n, 3) float64 rows as ``prefix`` and ``%.9g %.9g %.9g`` (and `` tail`` where a row has one), without line
    breaks, as a stream of :func:`kpd.io.text.write_spliced`: the text (B,) uint8 and the rows' (n + 1,) offsets."""
    from kpd.io import text

    return text.float_rows(rows, 9, prefix=prefix, suffix=b"", tails=tails)


def _source_companions(stem: str, source: ObjSource) -> tuple[dict, dict]:
    """Output names: {library path: (new name, its map renames)} and {image path: new name}, of the files kpd read
    (``source.files``); a map it did not read is renamed to None (:func:`kpd.io.mtl.renamed_library`)."""
    libs: dict[Path, tuple[str, dict]] = {}
    images: dict[Path, str] = {}
    taken = {f"{stem}.obj".lower()}
    for _, _, names in source.libraries:
        for lib_name, lib in _library_files(source.path, names, source.root):
            if lib is None or lib in libs or lib not in source.files:
                continue
            new = f"{stem}.mtl" if not libs else _unique(f"{stem}_{Path(lib_name).name}", taken)
            taken.add(new.lower())
            renames = {}
            for statement in _map_statements(source.files[lib]):
                name, whole = mtl.map_name(statement[1])
                found = mtl.locate_map(source.root or source.path.parent, lib.parent, name, whole)
                f = found.path
                if f is None or f not in source.files:
                    if found.refused is not None or f is not None:
                        renames[name] = None
                    continue
                if f not in images:
                    images[f] = _unique(f"{stem}_{f.name}", taken)
                    taken.add(images[f].lower())
                renames[name] = images[f]
            libs[lib] = (new, renames)
    return libs, images


def _unique(name: str, taken: set) -> str:
    if name.lower() not in taken:
        return name
    base, suffix = os.path.splitext(name)
    k = 2
    while f"{base}_{k}{suffix}".lower() in taken:
        k += 1
    return f"{base}_{k}{suffix}"


def _write_from_source(target: Path, mesh: Mesh, source: ObjSource) -> None:
    """The source's bytes with its ``v`` lines (and referenced ``vn`` lines) rewritten when the positions changed and
    its ``mtllib`` statements naming the copied libraries, spliced by :func:`kpd.io.text.write_spliced`."""
    from kpd.io import text

    libs, images = _source_companions(target.stem, source)
    streams = []  # (spans, text, offsets), each in file order
    if not np.array_equal(mesh.vertices, source.vertices):
        streams.append((source.v_spans, *_fmt(mesh.vertices, b"v ", source.v_tails)))
        if len(source.vn_spans):
            normals = turned_normals(source.vertices, mesh.vertices, mesh.triangles, source.corner_normals,
                                     source.normals)
            referenced = np.zeros(len(normals), dtype=bool)
            referenced[source.corner_normals[source.corner_normals >= 0]] = True
            streams.append((source.vn_spans[referenced], *_fmt(normals[referenced], b"vn ")))
    lib_names = {}
    for _, _, names in source.libraries:
        for lib_name, lib in _library_files(source.path, names, source.root):
            if lib in libs:
                lib_names[lib_name] = libs[lib][0]
    statements = []
    for _, _, names in source.libraries:
        found = mtl.library_references(source.path, names, source.root)
        files = [lib_names[n] for n, f in found if f.path in libs]
        missing = all(f.path is None and f.refused is None for _, f in found)
        why = b" (missing when kpd read the file)" if missing else b" (not read by kpd)"
        statements.append(("mtllib " + " ".join(files)).encode("utf-8") if files else b"# mtllib " +
                          names.encode("utf-8") + why)
    spans = np.array([(start, end) for start, end, _ in source.libraries], dtype=np.int64).reshape(-1, 2)
    streams.append((spans, *text.joined(statements)))
    with open(target, "wb") as fh:
        if text.write_spliced(fh, source.data, streams) != b"\n":
            fh.write(b"\n")
    for lib, (new, renames) in libs.items():
        target.parent.joinpath(new).write_bytes(_renamed_library(source.files[lib], renames))
    for image, new in images.items():
        target.parent.joinpath(new).write_bytes(source.files[image])


def _write_arrays(target: Path, mesh: Mesh) -> None:
    """An OBJ (and its .mtl and PNGs) from the mesh's arrays alone, its rows formatted by :mod:`kpd.io.text` and
    written a block at a time."""
    from kpd.grouping import first_occurrence_groups
    from kpd.io import text

    stem = target.stem
    T = len(mesh.triangles)
    materials = bool(mesh.textures)
    with open(target, "wb") as fh:
        fh.write(b"# written by kpd\n")
        if materials:
            fh.write(f"mtllib {stem}.mtl\n".encode("utf-8"))
        if mesh.vertex_colors is None:
            text.write_float_rows(fh, [mesh.vertices], prefix=b"v ")
        else:
            text.write_float_rows(fh, [mesh.vertices, mesh.vertex_colors], (9, 9, 9, 6, 6, 6), prefix=b"v ")
        uv_index = None
        mask = np.ones(T, dtype=bool) if mesh.triangle_uv_mask is None else mesh.triangle_uv_mask
        if mesh.triangle_uvs is not None and mask.any():
            corners = mesh.triangle_uvs.reshape(T, 3, 2)[mask].reshape(-1, 2)
            first, index = first_occurrence_groups(corners)
            text.write_float_rows(fh, [corners[first]], prefix=b"vt ")
            uv_index = np.full((T, 3), -1, dtype=np.int64)
            uv_index[mask] = index.reshape(-1, 3)
        normals = mesh.vertex_normals is not None
        if normals:
            text.write_float_rows(fh, [mesh.vertex_normals], prefix=b"vn ")
        ids = mesh.triangle_material_ids
        if materials and ids is None:
            ids = np.zeros(T, dtype=np.int64)
        # faces in runs of one material and one form (with or without UVs)
        has_uv = np.zeros(T, dtype=bool) if uv_index is None else uv_index[:, 0] >= 0
        key = has_uv.astype(np.int64) if ids is None else ids * 2 + has_uv
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(key)) + 1, [T]]).tolist()
        current = None
        for a, b in zip(cuts[:-1], cuts[1:]):
            if materials and ids[a] != current:
                current = int(ids[a])
                fh.write(f"usemtl material_{current}\n".encode())
            v = mesh.triangles[a:b]
            text.write_index_rows(fh, v, uv=uv_index[a:b] if has_uv[a] else None, normal=v if normals else None)
    if materials:
        from kpd.io.images import encode_png

        mtl = []
        for i, texture in enumerate(mesh.textures):
            mtl.append(f"newmtl material_{i}")
            if _is_image(texture):
                mtl += ["Kd 1 1 1", f"map_Kd {stem}_{i}.png"]
                target.parent.joinpath(f"{stem}_{i}.png").write_bytes(encode_png(texture))
            else:
                rgb = texture.reshape(-1)[:3] / 255.0 if texture.shape[2] >= 3 else [texture.reshape(-1)[0] / 255.0] * 3
                mtl.append("Kd %.6g %.6g %.6g" % tuple(rgb))
            mtl.append("")
        target.parent.joinpath(f"{stem}.mtl").write_text("\n".join(mtl), encoding="utf-8")


def _verify(p: Path, tmp: Path, mesh: Mesh, T: int) -> None:
    """The written file holds every vertex and its ``T`` face lines, and ends with a line break (its lines counted
    over its bytes as :func:`parse` finds them, by :func:`kpd.io.text.count_obj_lines`)."""
    from kpd.io import text

    V = len(mesh.vertices)
    v, f, ends_with_break = text.count_obj_lines(tmp)
    if v != V or f != T or not ends_with_break:
        raise incomplete(p, f"{v} of {V} vertices and {f} of {T} faces")
    for companion in tmp.parent.iterdir():
        if companion != tmp:
            verify_companion(p.parent / companion.name, companion)
    if not (tmp.parent / tmp.name).is_file():
        raise WriteError(f"cannot write {p}: nothing was written")
