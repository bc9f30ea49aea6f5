"""PLY: the header, the completeness check Open3D leaves out (it returns a half-read geometry for a truncated file),
binary reading and writing through numpy, and ASCII reading by compiled passes.

:func:`read_mesh` and :func:`read_vertices` read what Open3D reads, to the bit (positions, normals ``nx ny nz``,
colours ``red green blue`` divided by 255 whatever their type, triangles from ``vertex_indices`` or ``vertex_index``
in the file's order; other properties ignored); a file beyond their reach (polygons of more than three corners, lists
other than the faces', elements other than ``vertex`` and ``face``) gives None, for Open3D to read. They read the
properties by name, in any order; Open3D's reader counts a vertex done at its ``z`` (a normal at ``nz``) and refuses
a file whose ``z`` comes before ``x`` or ``y``. :func:`write_mesh` writes the bytes Open3D writes.

Binary: numpy reads and writes whole arrays, where Open3D's reader calls back once per value and copies.

ASCII: Open3D's PLY library (rply) reads the data as one stream of words, split at spaces, tabs and line breaks
alike: an integer property's word by C's ``strtol`` (a sign and digits: ``2.0`` is refused), a floating one's by
``strtod`` (the float64 nearest the decimal, for a ``float`` property too: ``0.1`` stays 0.1, not float32's
0.10000000149), each refused beyond its type's range (a ``float``'s is float32's). kpd reads one row per line
(lines of blanks alone passed over, ``\\r\\n`` read as ``\\n``, what follows the last face not read, as in Open3D), in
blocks of whole lines (:func:`kpd.io.off._blocks`, 4 MiB), by compiled passes: the rows (:func:`_filled`), then in
two halves on two threads (:func:`kpd.io.numbers.in_halves`) the integers and the number of words (:func:`_words`) and
the decimals (:func:`kpd.io.numbers.scan_numbers`, the OBJ reader's pass: the correctly rounded value, as ``strtod``
gives it). A row either pass leaves (a word of more than 15 significant digits or out of its type's range, a ``#``,
a row of the wrong length) is read word by word in Python (:meth:`_Rows.judge`), to the same bits. A row with other than
its element's number of words, a word that is not a number of its property's type or lies beyond its range, is an
:class:`~kpd.errors.InputError` naming its line; faces with corners outside the vertices are counted as the mesh
counts them, the first named by its line (Open3D read on across the line, refused the file without saying where, or
gave a mesh the checks refused without a line). A polygon, or a word only C reads (``nan``, ``inf``, hexadecimal
floats), in the first row out of the ordinary gives None: Open3D reads the file as before. :func:`read_vertices`
reads the vertex rows only.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kpd._compiled import compiled_on_first_call
from kpd.errors import InputError
from kpd.io.common import count_lines

__all__ = ["check_complete", "check_corners", "read_header", "read_mesh", "read_vertices", "write_mesh", "Header",
           "Element"]

_PLY_TYPE_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}
_PLY_NUMPY = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_FACE_LISTS = ("vertex_indices", "vertex_index")  # the names Open3D reads, in its order of preference
_NORMALS, _COLORS = ("nx", "ny", "nz"), ("red", "green", "blue")


class Element(NamedTuple):
    """One ``element`` of a PLY header: its name, count and properties, each ``(name, type)`` for a scalar or
    ``(name, (count type, item type))`` for a list."""

    name: str
    count: int
    properties: list


class Header(NamedTuple):
    """A PLY header: ``format`` (``ascii``, ``binary_little_endian``, ``binary_big_endian``), its elements, and the
    byte offset where the data starts; ``known`` is False when a property's type is not a PLY type (the header is
    then read no further)."""

    format: str | None
    elements: list
    data_start: int
    known: bool


def read_header(p: Path) -> Header:
    """The header of the PLY file ``p``.

    Raises
    ------
    InputError
        If the file does not start with ``ply``, has no ``end_header`` line in its first MiB, or an ``element`` line
        without a name and a whole count.
    """
    with open(p, "rb") as fh:
        head = fh.read(1 << 20)
    if not re.match(rb"ply[ \t]*\r?\n", head):
        raise InputError(f"{p}: not a PLY file (it does not start with the line 'ply')")
    end = re.search(rb"^end_header[ \t]*\r?\n", head, re.M)
    if not end:
        raise InputError(f"{p}: not a PLY file (no 'end_header' line in the first MiB)")
    lines = head[: end.end()].decode("ascii", errors="replace").splitlines()
    fmt, elements, known = None, [], True
    for s in lines[1:]:
        tokens = s.split()
        if not tokens:
            continue
        if tokens[0] == "format" and len(tokens) >= 2:
            fmt = tokens[1]
        elif tokens[0] == "element":  # a count that is not a whole number: rply reads its first digits, kpd not
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise InputError(f"{p}: the header line {s.strip()!r} does not give an element's name and count")
            elements.append(Element(tokens[1], int(tokens[2]), []))
        elif tokens[0] == "property" and elements:
            if len(tokens) == 5 and tokens[1] == "list" and tokens[2] in _PLY_TYPE_SIZES \
                    and tokens[3] in _PLY_TYPE_SIZES:
                elements[-1].properties.append((tokens[4], (tokens[2], tokens[3])))
            elif len(tokens) == 3 and tokens[1] in _PLY_TYPE_SIZES:
                elements[-1].properties.append((tokens[2], tokens[1]))
            else:
                known = False
                break
    return Header(fmt, elements, end.end(), known)


def check_complete(p: Path) -> None:
    """Raise if a PLY file holds less data than its header declares (Open3D returns a half-read cloud for that)."""
    header = read_header(p)
    if not header.known:
        return
    sizes = []
    for element in header.elements:
        size = 0
        for name, kind in element.properties:
            if isinstance(kind, tuple):  # a list: its count, and three items for the faces' corners
                size += _PLY_TYPE_SIZES[kind[0]] + (3 if name in _FACE_LISTS else 0) * _PLY_TYPE_SIZES[kind[1]]
            else:
                size += _PLY_TYPE_SIZES[kind]
        sizes.append(size)
    declared = " and ".join(f"{e.count} {e.name!r}" for e in header.elements) + " elements"
    data_size = p.stat().st_size - header.data_start
    if header.format in ("binary_little_endian", "binary_big_endian"):
        need = sum(e.count * size for e, size in zip(header.elements, sizes))
        if data_size < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {declared} (at least {need} bytes of data) "
                f"but {data_size} bytes follow"
            )
    elif header.format == "ascii":
        rows = count_lines(p, header.data_start)
        need = sum(e.count for e in header.elements)
        if rows < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {declared} ({need} rows) but {rows} rows follow"
            )


# --- reading -------------------------------------------------------------------------------------------------------


class _Data(NamedTuple):
    vertices: np.ndarray  # structured (V,), fields p0, p1, ... in the header's order
    properties: list  # the vertex element's (name, type)
    triangles: np.ndarray | None  # (T, 3) int64, or None without faces


def _read(p: Path, *, faces: bool) -> _Data | None:
    """The vertex records (and the triangles) of a PLY, binary or ASCII, or None when the layout is beyond this
    module's readers (see the module notes)."""
    header = read_header(p)
    if not header.known or header.format not in ("ascii", "binary_little_endian", "binary_big_endian"):
        return None
    names = [e.name for e in header.elements]
    if names not in (["vertex"], ["vertex", "face"]) or header.elements[0].count == 0:
        return None
    vertex = header.elements[0]
    present = {name for name, _ in vertex.properties}
    if any(isinstance(kind, tuple) for _, kind in vertex.properties) or not {"x", "y", "z"} <= present \
            or any(present & set(group) not in (set(), set(group)) for group in (_NORMALS, _COLORS)):
        return None  # lists, or some of a normal's or a colour's three parts (Open3D reads those its own way)
    if faces and len(names) == 2:
        face = header.elements[1]
        lists = [(name, kind) for name, kind in face.properties if isinstance(kind, tuple)]
        if face.count == 0 or len(lists) != 1 or lists[0][0] not in _FACE_LISTS:
            return None
    elif faces:
        return None  # no face element: Open3D tells what is missing
    if header.format == "ascii":
        if faces and any(_PLY_NUMPY[t][0] == "f" for t in lists[0][1]):
            return None  # a count or corners of a floating type: Open3D truncates them its own way
        return _read_ascii(p, header, faces)
    return _read_binary(p, header, faces)


def _read_binary(p: Path, header: Header, faces: bool) -> _Data | None:
    """The vertex records of a binary PLY as a numpy structured array (a view of one read) and its triangles, or None
    for polygons."""
    order = "<" if header.format == "binary_little_endian" else ">"
    vertex = header.elements[0]
    vertex_type = np.dtype([(f"p{i}", order + _PLY_NUMPY[kind]) for i, (_, kind) in enumerate(vertex.properties)])
    face_type = None
    if faces:
        fields = []
        for i, (_, kind) in enumerate(header.elements[1].properties):
            if isinstance(kind, tuple):  # a triangle: its count, then three corners
                fields += [("count", order + _PLY_NUMPY[kind[0]]), ("corners", order + _PLY_NUMPY[kind[1]], (3,))]
            else:
                fields.append((f"p{i}", order + _PLY_NUMPY[kind]))
        face_type = np.dtype(fields)
    v = vertex.count * vertex_type.itemsize
    t = 0 if face_type is None else header.elements[1].count * face_type.itemsize
    raw = np.fromfile(p, dtype=np.uint8, count=v + t, offset=header.data_start)
    if len(raw) < v + t:  # polygons of more than three corners in fewer faces, or a truncated file
        return None
    triangles = None
    if face_type is not None:
        records = raw[v:].view(face_type)
        if not (records["count"] == 3).all():
            return None  # polygons: Open3D cuts them into triangles
        triangles = records["corners"].astype(np.int64)  # (T, 3)
    return _Data(raw[:v].view(vertex_type), vertex.properties, triangles)


# ASCII: the words of a row, as rply (Open3D's PLY library) reads them: split at spaces, tabs and carriage returns,
# an integer property's word read by C's strtol (a sign and digits), a floating one's by strtod, each refused beyond
# its type's range
_SPACE, _TAB, _RETURN, _HASH, _VTAB, _FORMFEED = 32, 9, 13, 35, 11, 12
_RPLY_BLANKS = re.compile(rb"[ \t\r]+")
_WHOLE = re.compile(rb"[+-]?\d+")
_DECIMAL = re.compile(rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
# what C reads beyond those (leading \v or \f; nan, inf and hexadecimal floats): Open3D's to read
_C_WHOLE = re.compile(rb"[\x0b\x0c]+[+-]?\d+")
_C_DECIMAL = re.compile(rb"[\x0b\x0c]*[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:e[+-]?\d+)?|nan(?:\([0-9a-z_]*\))?|inf(?:inity)?"
                        rb"|0x(?:[0-9a-f]+\.?[0-9a-f]*|\.[0-9a-f]+)(?:p[+-]?\d+)?)", re.I)
_FLOAT32_MAX = float(np.finfo(np.float32).max)


class _Rows:
    """The words of one element's ASCII rows: per word its property's name and type (a face's list as its count and
    three corners); which words are of an integer type, their bounds (the count's 3, a corner's also within the
    vertices) and their column in what :meth:`read` stores of them (-1: not stored): a vertex's integer properties
    in their order, a face's three corners."""

    def __init__(self, element: Element, vertices: int) -> None:
        self.element = element
        self.kinds = []  # (name, type) per word
        self.count = -1  # the word of the list's count
        for name, kind in element.properties:
            if isinstance(kind, tuple):
                self.count = len(self.kinds)
                self.kinds += [(name, kind[0])] + [(name, kind[1])] * 3
            else:
                self.kinds.append((name, kind))
        self.width = len(self.kinds)
        self.vertices = vertices
        self.whole = np.array([_PLY_NUMPY[kind][0] != "f" for _, kind in self.kinds])
        self.low = np.zeros(self.width, np.int64)
        self.high = np.zeros(self.width, np.int64)
        for k in np.flatnonzero(self.whole):
            limits = np.iinfo(_PLY_NUMPY[self.kinds[k][1]])
            self.low[k], self.high[k] = limits.min, limits.max
        self.stored = np.flatnonzero(self.whole)  # the words read into the columns of `out`
        if self.count >= 0:
            self.low[self.count] = self.high[self.count] = 3
            self.stored = np.arange(self.count + 1, self.count + 4)
            self.low[self.stored] = np.maximum(self.low[self.stored], 0)
            self.high[self.stored] = np.minimum(self.high[self.stored], vertices - 1)
        self.place = np.full(self.width, -1, np.int64)
        self.place[self.stored] = np.arange(len(self.stored))

    def read(self, block: np.ndarray, begin: np.ndarray, stop: np.ndarray, floats: np.ndarray | None,
             out: np.ndarray) -> np.ndarray:
        """Read the rows ``block[begin[r]:stop[r]]`` (n) by compiled passes in two halves: their numbers into
        ``floats`` (n, w) float64 (:func:`kpd.io.obj._numbers`, exact; None to leave them unread when no word is of a
        floating type), the integers :attr:`stored` into ``out`` (n, s) int64 (:func:`_words`); the rows that are
        left for :meth:`judge`, (m,) in order: those with other than w words, a word beyond the fast paths or out of
        its bounds, a byte the two passes read otherwise than rply (``#``, ``\\v``, ``\\f``)."""
        from kpd.io.numbers import in_halves as _in_halves, scan_numbers as _numbers

        n = len(begin)
        judge = np.empty(n, np.bool_)
        _in_halves(_words, n, block, begin, stop, self.whole, self.low, self.high, self.place, out, judge)
        if floats is not None:
            exact = np.empty(n, np.bool_)
            _in_halves(_numbers, n, block, begin, stop, floats, np.empty(n, np.int64), exact)
            judge |= ~exact
        return np.flatnonzero(judge)

    def judge(self, text: bytes) -> list | str | None:
        """The row ``text`` as rply reads it: its values (floats, one per word; a face's corners may lie outside the
        vertices, which the caller checks), what is wrong with it (a message), or None when Open3D is to read the
        file (a polygon; a word only C reads: ``nan``, ``inf``, hexadecimal)."""
        words = _RPLY_BLANKS.split(text.strip(b" \t\r"))
        values = []
        for k, (name, kind) in enumerate(self.kinds):
            if k == len(words):
                return self._count_message(len(words))
            value = _value(words[k], kind)
            if not isinstance(value, float):
                return value if value is None else \
                    f"the '{self.element.name}' property '{name}' ({kind}) holds {_shown(words[k])}, {value}"
            if k == self.count and value != 3:
                return None  # a polygon: Open3D cuts it into triangles
            values.append(value)
        if len(words) > self.width:
            return self._count_message(len(words))
        return values

    def _count_message(self, got: int) -> str:
        if self.count < 0:
            names = " ".join(name for name, _ in self.kinds)
            return f"a '{self.element.name}' row holds {got} values; the header declares {self.width} ({names})"
        names = ", ".join(f"{name} (3 and three corners)" if isinstance(kind, tuple) else name
                          for name, kind in self.element.properties)
        return f"a '{self.element.name}' row holds {got} values; a triangle takes {self.width}: {names}"


def _value(word: bytes, kind: str) -> float | str | None:
    """The value rply reads from ``word`` for a property of type ``kind``: a float; None when only C reads it (Open3D
    then reads the file); or what is wrong with it."""
    if _PLY_NUMPY[kind][0] != "f":
        if _WHOLE.fullmatch(word):
            limits = np.iinfo(_PLY_NUMPY[kind])
            if not limits.min <= int(word) <= limits.max:
                return f"beyond the range of {kind} ({limits.min} to {limits.max})"
            return float(int(word))
        return None if _C_WHOLE.fullmatch(word) else "not a whole number"
    if _DECIMAL.fullmatch(word):
        value = float(word)
        if abs(value) > (_FLOAT32_MAX if _PLY_NUMPY[kind] == "f4" else sys.float_info.max):
            return f"beyond the range of {kind}"
        return value
    return None if _C_DECIMAL.fullmatch(word) else "not a number"


def _shown(word: bytes) -> str:
    return repr(word.decode("utf-8", "replace"))


def _read_ascii(p: Path, header: Header, faces: bool) -> _Data | None:
    """The vertex rows of an ASCII PLY as a structured array of float64 fields and its triangles (T, 3) int64, or
    None when Open3D is to read the file (module notes).

    Raises
    ------
    InputError
        Naming the line (module notes): a row with other than its element's number of words, a word that is not a
        number of its property's type or lies beyond its range, faces with corners outside the vertices; fewer rows
        than the header declares (lines of blanks among the lines :func:`check_complete` counts).
    """
    from kpd.io.off import _blocks, _room

    layouts = [_Rows(element, header.elements[0].count) for element in header.elements[: 1 + faces]]
    vertex, face = layouts[0], layouts[1] if faces else None
    V, F = vertex.element.count, face.element.count if faces else 0
    size = p.stat().st_size - header.data_start
    values = np.empty((min(V, (size + 1) // (2 * vertex.width) + 1), vertex.width))  # a row takes 2 bytes a word
    triangles = None if face is None else np.empty((min(F, (size + 1) // (2 * face.width) + 1), 3), np.int64)
    read_v = read_f = 0
    outside = None  # the line of the first face with a corner that is not a vertex
    with open(p, "rb") as fh:
        line = fh.read(header.data_start).count(b"\n") + 1  # the file's line of the block's first line
        for block, ends in _blocks(fh):
            begin = np.empty_like(ends)
            begin[0], begin[1:] = 0, ends[:-1] + 1
            filled = np.empty(len(ends), np.bool_)
            _filled(0, len(ends), block, begin, ends, filled)  # one thread: it reads little of each line
            rows = np.flatnonzero(filled)  # (R,) the block's lines that hold a row
            v = min(len(rows), V - read_v)
            f = min(len(rows) - v, F - read_f)
            for layout, these, at in ((vertex, rows[:v], read_v), (face, rows[v:v + f], read_f)):
                if not len(these):
                    continue
                n = len(these)
                if layout is vertex:
                    values = _room(values, at + n, V)
                    floats, out = values[at:at + n], np.empty((n, len(vertex.stored)), np.int64)
                else:
                    triangles = _room(triangles, at + n, F)
                    floats = None if layout.whole.all() else np.empty((n, layout.width))
                    out = triangles[at:at + n]
                b, s = begin[these], ends[these]
                judged_rows = layout.read(block, b, s, floats, out)
                if layout is vertex and len(vertex.stored):
                    floats[:, vertex.stored] = out  # strtol's values ("-0" is 0)
                for r in judged_rows.tolist():
                    judged = layout.judge(block[b[r]:s[r]].tobytes())
                    if not isinstance(judged, list) and outside is not None:  # a corner outside came first
                        raise _outside(p, triangles[:at + r], V, outside)
                    if judged is None:
                        return None
                    if isinstance(judged, str):
                        raise InputError(f"{p}: line {line + int(these[r])}: {judged}")
                    if layout is vertex:
                        floats[r] = judged
                        continue
                    out[r] = [judged[k] for k in face.stored]
                    if outside is None and not 0 <= out[r].min() <= out[r].max() < V:
                        outside = line + int(these[r])
            read_v, read_f = read_v + v, read_f + f
            if read_v == V and read_f == F:
                break
            line += len(ends)
    if read_v + read_f < V + F:
        declared = " and ".join(f"{layout.element.count} {layout.element.name!r}" for layout in layouts)
        raise InputError(f"{p}: the file is truncated: its header declares {declared} elements ({V + F} rows) but "
                         f"{read_v + read_f} rows follow")
    if outside is not None:
        raise _outside(p, triangles, V, outside)
    fields = np.dtype([(f"p{i}", "f8") for i in range(vertex.width)])
    return _Data(values.view(fields).reshape(-1), vertex.element.properties, triangles)


def _outside(p: Path, triangles: np.ndarray, V: int, line: int) -> InputError:
    """The error for ``triangles`` (T, 3) with corners outside [0, V), the first on ``line``: the mesh's message and
    the line."""
    from kpd.mesh import count_phrase

    bad = ((triangles < 0) | (triangles >= V)).any(axis=1)
    return InputError(f"{p}: {count_phrase(int(bad.sum()), 'triangles', 'index', 'indexes')} vertices outside "
                      f"[0, {V}) (indices from {int(triangles.min())} to {int(triangles.max())}; the first on line "
                      f"{line})")


@compiled_on_first_call
def _filled(lo, hi, block, begin, stop, flags):  # pragma: no cover - compiled
    """flags[i]: line i, ``block[begin[i]:stop[i]]``, holds a byte other than a space, a tab or a carriage return
    (rply passes over the others)."""
    for i in range(lo, hi):
        j = begin[i]
        while j < stop[i] and (block[j] == _SPACE or block[j] == _TAB or block[j] == _RETURN):
            j += 1
        flags[i] = j < stop[i]


@compiled_on_first_call
def _words(lo, hi, block, begin, stop, whole, low, high, place, out, judge):  # pragma: no cover - compiled
    """Row r's words, ``block[begin[r]:stop[r]]`` split at spaces, tabs and carriage returns as rply splits them: the
    k-th read as an integer where ``whole[k]`` (a property of an integer type), into ``out[r, place[k]]`` where
    ``place[k]`` is not -1. ``judge[r]`` True when the row holds other than ``len(whole)`` words, when an integer
    word is not a sign and 1 to 18 digits or lies outside ``[low[k], high[k]]``, or when a word holds ``#``, ``\\v``
    or ``\\f`` (which :func:`kpd.io.obj._numbers` reads otherwise than rply); the pass over the row ends there."""
    width = len(whole)
    for r in range(lo, hi):
        i, end = begin[r], stop[r]
        k = 0
        wrong = False
        while i < end:
            c = block[i]
            if c == _SPACE or c == _TAB or c == _RETURN:
                i += 1
                continue
            if k < width and whole[k]:  # the word at i, an integer
                negative = c == 45
                if c == 43 or c == 45:  # + -
                    i += 1
                start = i
                value = 0
                while i < end:
                    digit = np.int64(block[i]) - 48
                    if digit < 0 or digit > 9:
                        break
                    value = value * 10 + digit
                    i += 1
                if negative:
                    value = -value
                if i < end and not (block[i] == _SPACE or block[i] == _TAB or block[i] == _RETURN) \
                        or i == start or i - start > 18 or value < low[k] or value > high[k]:
                    wrong = True
                    break
                if place[k] >= 0:
                    out[r, place[k]] = value
            else:  # the word at i, read by the other pass
                while i < end:
                    c = block[i]
                    if c == _SPACE or c == _TAB or c == _RETURN:
                        break
                    wrong |= c == _HASH or c == _VTAB or c == _FORMFEED
                    i += 1
                if wrong:
                    break
            k += 1
        judge[r] = wrong or k != width


def _columns(data: _Data, names: tuple) -> np.ndarray | None:
    """(V, 3) float64 of three vertex properties, or None when the file has none of them."""
    index = {name: f"p{i}" for i, (name, _) in enumerate(data.properties)}
    if not any(name in index for name in names):
        return None
    out = np.empty((len(data.vertices), 3), dtype=np.float64)
    for k, name in enumerate(names):
        out[:, k] = data.vertices[index[name]]
    return out


def _vertex_arrays(data: _Data) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    points = _columns(data, ("x", "y", "z"))
    normals = _columns(data, _NORMALS)
    colors = _columns(data, _COLORS)
    if colors is not None:
        colors /= 255.0  # as Open3D, whatever the type
    return points, normals, colors


def read_vertices(p: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None] | None:
    """Points (V, 3), normals (V, 3) or None and colours (V, 3) or None of a PLY's ``vertex`` element, all float64,
    as Open3D's point cloud reader gives them; None when the file is beyond this module's readers (module notes).
    Call :func:`check_complete` first.

    Raises
    ------
    InputError
        For an ASCII file's malformed vertex row, naming the line (module notes).
    """
    data = _read(p, faces=False)
    return None if data is None else _vertex_arrays(data)


def read_mesh(p: Path, name: str | None = None):
    """A PLY's triangle mesh (:class:`kpd.mesh.Mesh`, checked), or None when the file is beyond this module's readers
    (module notes: Open3D reads it then). Call :func:`check_complete` first.

    Raises
    ------
    InputError
        For what :class:`~kpd.mesh.Mesh` refuses: non-finite coordinates, triangles indexing missing vertices; for an
        ASCII file's malformed row, naming the line (module notes).
    """
    from kpd.mesh import Mesh

    data = _read(p, faces=True)
    if data is None:
        check_corners(p)
        return None
    points, normals, colors = _vertex_arrays(data)
    return Mesh(vertices=points, triangles=data.triangles, vertex_normals=normals, vertex_colors=colors, path=name)


# --- what Open3D is given -----------------------------------------------------------------------------------------


def check_corners(p: Path) -> None:
    """Raise if a face of a PLY that Open3D is to read (:func:`read_mesh` gave None) has a corner outside the
    vertices or fewer than three corners: Open3D's reader cuts a polygon by ear clipping on its corners' positions
    without checking their indices or their number, and ends the process (a segmentation fault) on such a face.
    Files whose face lists cannot be walked (a header beyond :func:`read_header`, lists of a floating type, data that
    ends early) are left to Open3D, which refuses them.

    Raises
    ------
    InputError
        Naming the first such face (its number, from 0) and its corner or its number of corners.
    """
    header = read_header(p)
    if not header.known or header.format not in ("ascii", "binary_little_endian", "binary_big_endian"):
        return
    vertices = next((e.count for e in header.elements if e.name == "vertex"), 0)
    faces = next((e for e in header.elements if e.name == "face"), None)
    if faces is None or not any(name in _FACE_LISTS and isinstance(kind, tuple) for name, kind in faces.properties):
        return
    if any(_PLY_NUMPY[kind[1]][0] == "f" or _PLY_NUMPY[kind[0]][0] == "f"
           for e in header.elements for _, kind in e.properties if isinstance(kind, tuple)):
        return
    face_list = next(name for name in _FACE_LISTS if any(n == name for n, _ in faces.properties))
    if header.format == "ascii":
        found = _ascii_corner_outside(p, header, faces, face_list, vertices)
    else:
        found = _binary_corner_outside(p, header, faces, face_list, vertices)
    if found is not None:
        face, corner, corners = found
        if corner is None:
            raise InputError(f"{p}: face {face} has {corners} corners; a face has 3 or more")
        raise InputError(f"{p}: face {face} has the corner {corner}, outside the {vertices} vertices [0, {vertices})")


def _layout(element: Element, face_list: str | None) -> tuple[np.ndarray, ...]:
    """Per property of ``element``: 1 for a list, its (count) size and signedness, the list's item size and
    signedness, and 1 for the face list whose items are checked."""
    rows = []
    for name, kind in element.properties:
        if isinstance(kind, tuple):
            rows.append((1, _PLY_TYPE_SIZES[kind[0]], _PLY_NUMPY[kind[0]][0] == "i", _PLY_TYPE_SIZES[kind[1]],
                         _PLY_NUMPY[kind[1]][0] == "i", name == face_list))
        else:
            rows.append((0, _PLY_TYPE_SIZES[kind], 0, 0, 0, 0))
    table = np.array(rows, np.int64).reshape(-1, 6)
    return tuple(table[:, k].copy() for k in range(6))


def _binary_corner_outside(p: Path, header: Header, faces: Element, face_list: str, vertices: int):
    raw = np.fromfile(p, dtype=np.uint8, offset=header.data_start)
    big = header.format == "binary_big_endian"
    at = 0
    found = np.full(3, -1, np.int64)  # the face, its corner outside, or its number of corners when fewer than 3
    for element in header.elements:
        layout = _layout(element, face_list if element is faces else None)
        at = _walk(raw, at, element.count, *layout, big, vertices, found)
        if at < 0:
            return None  # the data ends early: Open3D refuses the file
        if element is faces:
            return None if found[0] < 0 else (int(found[0]), int(found[1]) if found[2] < 0 else None,
                                               int(found[2]))
    return None


@compiled_on_first_call
def _walk(raw, at, count, is_list, size, signed, item_size, item_signed, checked, big, vertices,
          found):  # pragma: no cover - compiled
    """Walk ``count`` records of one element from byte ``at`` of ``raw``; the first record with a checked corner
    outside [0, vertices) is put in ``found`` (record, corner). The byte after the records, or -1 when the data
    ends first."""
    n = len(raw)
    for r in range(count):
        for k in range(len(is_list)):
            if at + size[k] > n:
                return -1
            if is_list[k] == 0:
                at += size[k]
                continue
            length = 0
            for j in range(size[k]):  # the count, an integer of size[k] bytes in the file's byte order
                length = length * 256 + np.int64(raw[at + (j if big else size[k] - 1 - j)])
            if signed[k] and length >= np.int64(1) << (8 * size[k] - 1):
                length -= np.int64(1) << (8 * size[k])
            at += size[k]
            if length < 0 or at + length * item_size[k] > n:
                return -1
            if checked[k] and found[0] < 0:
                if length < 3:
                    found[0], found[1], found[2] = r, -1, length
                    return at
                for j in range(length):
                    corner = 0
                    w = item_size[k]
                    for i in range(w):
                        corner = corner * 256 + np.int64(raw[at + j * w + (i if big else w - 1 - i)])
                    if item_signed[k] and corner >= np.int64(1) << (8 * w - 1):
                        corner -= np.int64(1) << (8 * w)
                    if corner < 0 or corner >= vertices:
                        found[0], found[1] = r, corner
                        return at
            at += length * item_size[k]
    return at


def _ascii_corner_outside(p: Path, header: Header, faces: Element, face_list: str, vertices: int):
    """As :func:`_binary_corner_outside`, for an ASCII PLY read one row per line (as :func:`_read_ascii` reads it),
    in blocks of whole lines by a compiled pass; from the first face row that is not its properties' words (its
    count and corners whole numbers) on, the words are read as rply reads them
    (:func:`_ascii_stream_corner_outside`)."""
    from kpd.io.off import _blocks

    is_list, _, _, _, _, checked = _layout(faces, face_list)
    before = sum(e.count for e in header.elements[: header.elements.index(faces)])  # the rows before the faces
    passed = done = 0
    found = np.full(3, -1, np.int64)
    with open(p, "rb") as fh:
        fh.seek(header.data_start)
        for block, ends in _blocks(fh):
            begin = np.empty_like(ends)
            begin[0], begin[1:] = 0, ends[:-1] + 1
            filled = np.empty(len(ends), np.bool_)
            _filled(0, len(ends), block, begin, ends, filled)
            rows = np.flatnonzero(filled)  # (R,) the block's lines that hold a row
            skip = min(len(rows), before - passed)
            passed += skip
            these = rows[skip : skip + faces.count - done]
            if len(these):
                _face_rows(block, begin[these], ends[these], is_list, checked, vertices, done, found)
                done += len(these)
            if found[0] >= 0 or done == faces.count:
                break
    if found[2] == -2:  # a face row that is not one face: the words as rply streams them
        return _ascii_stream_corner_outside(p, header, faces, face_list, vertices)
    return None if found[0] < 0 else (int(found[0]), int(found[1]) if found[2] == -1 else None, int(found[2]))


def _ascii_stream_corner_outside(p: Path, header: Header, faces: Element, face_list: str, vertices: int):
    """As :func:`_ascii_corner_outside`, over the words as one stream, the way rply reads them (a face may span
    lines): numpy reads them all as float64 (slower; for files whose rows are not one face a line)."""
    with open(p, "rb") as fh:
        fh.seek(header.data_start)
        try:
            values = np.fromfile(fh, dtype=np.float64, sep=" ")
        except ValueError:
            return None  # a word that is not a number: rply refuses the file
    at = 0
    found = np.full(3, -1, np.int64)
    for element in header.elements:
        is_list, _, _, _, _, checked = _layout(element, face_list if element is faces else None)
        at = _walk_values(values, at, element.count, is_list, checked, vertices, found)
        if at < 0:
            return None
        if element is faces:
            break
    return None if found[0] < 0 else (int(found[0]), int(found[1]) if found[2] < 0 else None, int(found[2]))


@compiled_on_first_call
def _walk_values(values, at, count, is_list, checked, vertices, found):  # pragma: no cover - compiled
    """:func:`_walk` over an ASCII PLY's words, one value each: the value after the records, -1 when the values end
    first or a list's count or a checked corner is not a whole number."""
    n = len(values)
    for r in range(count):
        for k in range(len(is_list)):
            if at >= n:
                return -1
            if is_list[k] == 0:
                at += 1
                continue
            length = values[at]
            if length != np.floor(length) or length < 0 or at + 1 + length > n:
                return -1
            at += 1
            if checked[k] and found[0] < 0:
                if length < 3:
                    found[0], found[1], found[2] = r, -1, np.int64(length)
                    return at
                for j in range(np.int64(length)):
                    corner = values[at + j]
                    if corner != np.floor(corner):
                        return -1
                    if corner < 0 or corner >= vertices:
                        found[0], found[1] = r, np.int64(corner)
                        return at
            at += np.int64(length)
    return at


@compiled_on_first_call
def _face_rows(block, begin, stop, is_list, checked, vertices, first, found):  # pragma: no cover - compiled
    """Face rows ``block[begin[r]:stop[r]]``, their words split at spaces, tabs and carriage returns: the first
    (``first + r``) with a checked list of fewer than 3 corners or a corner outside [0, vertices), or whose words
    are not its properties' (a list's count and corners whole numbers, no word missing or left over), is put in
    ``found``: (row, corner, -1), (row, -1, corners) or (row, -1, -2)."""
    for r in range(len(begin)):
        i, end = begin[r], stop[r]
        for k in range(len(is_list)):
            while i < end and (block[i] == _SPACE or block[i] == _TAB or block[i] == _RETURN):
                i += 1
            if i == end:
                found[0], found[1], found[2] = first + r, -1, -2
                return
            if is_list[k] == 0:
                while i < end and not (block[i] == _SPACE or block[i] == _TAB or block[i] == _RETURN):
                    i += 1
                continue
            length = -1
            items = 0  # the count, then each corner
            while items <= length or length < 0:
                while i < end and (block[i] == _SPACE or block[i] == _TAB or block[i] == _RETURN):
                    i += 1
                negative = i < end and block[i] == 45
                if i < end and (block[i] == 43 or block[i] == 45):
                    i += 1
                start, value = i, np.int64(0)
                while i < end and 48 <= block[i] <= 57 and i - start < 18:
                    value = value * 10 + np.int64(block[i]) - 48
                    i += 1
                if i == start or i < end and not (block[i] == _SPACE or block[i] == _TAB or block[i] == _RETURN):
                    found[0], found[1], found[2] = first + r, -1, -2
                    return
                if negative:
                    value = -value
                if length < 0:
                    if value < 0:
                        found[0], found[1], found[2] = first + r, -1, -2
                        return
                    length = value
                    if checked[k] and length < 3:
                        found[0], found[1], found[2] = first + r, -1, length
                        return
                elif checked[k] and (value < 0 or value >= vertices):
                    found[0], found[1], found[2] = first + r, value, -1
                    return
                items += 1
                if length == 0:
                    break
        while i < end and (block[i] == _SPACE or block[i] == _TAB or block[i] == _RETURN):
            i += 1
        if i < end:
            found[0], found[1], found[2] = first + r, -1, -2
            return


# --- writing -------------------------------------------------------------------------------------------------------


def write_mesh(p: Path, mesh) -> None:
    """Write ``mesh`` (:class:`kpd.mesh.Mesh`) to ``p`` as Open3D's ``write_triangle_mesh`` does, byte for byte:
    binary little-endian, positions and normals as doubles, colours as bytes (``round(255 c)`` of ``c`` clipped to
    [0, 1]), triangles as a ``uchar`` count and ``uint`` corners; UVs and textures are not stored (PLY has no place
    Open3D writes them to)."""
    v, t = len(mesh.vertices), len(mesh.triangles)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    lines = ["ply", "format binary_little_endian 1.0", "comment Created by Open3D", f"element vertex {v}",
             "property double x", "property double y", "property double z"]
    if mesh.vertex_normals is not None:
        fields += [("nx", "<f8"), ("ny", "<f8"), ("nz", "<f8")]
        lines += ["property double nx", "property double ny", "property double nz"]
    if mesh.vertex_colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    lines += [f"element face {t}", "property list uchar uint vertex_indices", "end_header"]
    records = np.empty(v, dtype=np.dtype(fields))
    for k, axis in enumerate("xyz"):
        records[axis] = mesh.vertices[:, k]
    if mesh.vertex_normals is not None:
        for k, axis in enumerate(("nx", "ny", "nz")):
            records[axis] = mesh.vertex_normals[:, k]
    if mesh.vertex_colors is not None:
        scaled = np.clip(mesh.vertex_colors, 0.0, 1.0) * 255.0  # (V, 3)
        low = np.floor(scaled)
        rgb = np.where(scaled - low >= 0.5, low + 1.0, low).astype(np.uint8)  # halves away from zero (std::round)
        for k, channel in enumerate(("red", "green", "blue")):
            records[channel] = rgb[:, k]
    faces = np.empty(t, dtype=np.dtype([("count", "u1"), ("corners", "<u4", (3,))]))
    faces["count"] = 3
    faces["corners"] = mesh.triangles
    with open(p, "wb") as fh:
        fh.write(("\n".join(lines) + "\n").encode("ascii"))
        records.tofile(fh)
        faces.tofile(fh)
