"""Numbers written as text by compiled code, for the text mesh formats (:mod:`kpd.io.obj`, :mod:`kpd.io.off`).

* :func:`float_rows` (and :func:`write_float_rows`, a file's worth in pieces): rows of float64, each number the bytes
  Python's ``b"%.9g" % x`` gives (any precision 1-15, per column), for every float64: zero and ``-0``, subnormals,
  the exponent forms ``1e-05`` and ``1e+20``, values that round up to the next power of ten (``9.99999999951`` is
  ``10``), trailing zeros removed, ``nan``, ``inf`` and ``-inf``.
* :func:`index_rows` (:func:`write_index_rows`): rows of integers (triangle corners) after a prefix (``f`` or ``3``),
  in the OBJ corner forms ``v``, ``v/vt``, ``v/vt/vn`` and ``v//vn``.
* :func:`write_spliced`: a file's bytes with spans (the ``v`` lines of an OBJ) replaced by new text.
* :func:`count_obj_lines`: the ``v`` and ``f`` lines of a written OBJ, counted over its bytes as
  :func:`kpd.io.obj.parse` finds them.

Each kernel writes into a preallocated ``uint8`` buffer and has a plain Python twin (``*_reference``) that the tests
compare with it byte for byte.

**A number exactly as Python writes it.** ``x = m 2^b`` (``frexp``, ``0.5 <= m < 1``) lies in the decade of ``10^e``
with ``e`` one of two values known from ``b``; its 9 significant digits are ``m M`` rounded, with ``M = 2^b 10^(8 -
e)`` from a table of ``M`` as two float64 (``hi + lo``, within ``2^-106``, made once with Python's integers),
multiplied by Dekker's exact product. The fraction so found is within ``2^-52`` of the true one, so the rounding is
right unless it lies within ``2^-44`` of one half. Such a value is either an exact tie, found exactly from its bits
and rounded half to even as Python does (``1000000005.0``, or ``0.1611328125 = 165/1024``: 8 of the 4.1 million
coordinates of the scan below), or it is written by Python on a second pass over its rows (a value that close to a
tie without being one: about one in ten trillion; the scan's closest is 60 times farther).

The write_* functions format 65,536 rows at a time, so that a file costs a few MB beyond the mesh, not a list of a
byte string per row; formatting is many times faster than Python's ``%`` per row (figures in
``docs/formats.md``).
"""

from __future__ import annotations

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor

import numba  # noqa: F401  (imported before numba.core's modules, which cannot be imported first)
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from kpd._compiled import njit
from kpd.errors import InputError

__all__ = ["float_rows", "float_rows_reference", "write_float_rows", "index_rows", "index_rows_reference",
           "write_index_rows", "write_spliced", "splice_reference", "joined", "count_obj_lines",
           "count_obj_lines_reference", "MAX_PRECISION"]

MAX_PRECISION = 15  # significant digits the method holds (10^15 < 2^53)
_LOWEST = -1073  # frexp's binary exponent of the smallest subnormal (2^-1074 = 0.5 * 2^-1073)
_BINADES = 1024 - _LOWEST + 1  # frexp exponents -1073..1024
_TIE = 2.0**-44  # a fraction this close to one half is checked for an exact tie, or left to Python
_ROWS = 1 << 16  # rows formatted at a time by the write_* functions
_THREADED_ROWS = 65536  # rows below which a second thread costs more than it saves
_CHUNK = 1 << 24  # bytes read or written at a time
_PAIRS = np.frombuffer(b"".join(b"%02d" % i for i in range(100)), dtype=np.uint8)  # "00" .. "99"


@functools.cache
def _decades() -> np.ndarray:
    """(B,) int64: per frexp exponent ``b``, the decade ``floor(log10(2^(b-1)))`` of the binade's smallest value."""
    out = np.empty(_BINADES, dtype=np.int64)
    for i in range(_BINADES):
        k = i + _LOWEST - 1
        out[i] = len(str(2**k)) - 1 if k >= 0 else len(str(5**-k)) - 1 + k  # 2^-k = 5^k / 10^k
    return out


@functools.cache
def _scales(precision: int) -> np.ndarray:
    """(B, 2, 2) float64: per frexp exponent ``b`` and decade ``e`` (the binade's lowest, and the next), ``2^b
    10^(precision - 1 - e)`` as ``hi + lo``, each rounded to nearest."""
    decades = _decades()
    out = np.empty((_BINADES, 2, 2))
    for i in range(_BINADES):
        b = i + _LOWEST
        for j in range(2):
            k = precision - 1 - int(decades[i]) - j
            num = 2 ** max(b, 0) * 10 ** max(k, 0)
            den = 2 ** max(-b, 0) * 10 ** max(-k, 0)
            hi = num / den  # correctly rounded
            hn, hd = hi.as_integer_ratio()
            out[i, j] = hi, (num * hd - hn * den) / (den * hd)
    return out


# --- compiled kernels ------------------------------------------------------------------------------------------------


@njit(nogil=True, inline="always")
def _two_product(a, b):  # pragma: no cover - compiled
    """``a * b`` as ``hi + lo`` exactly (Dekker: splits at 27 bits, no fused multiply-add needed)."""
    p = a * b
    t = 134217729.0 * a
    a_hi = t - (t - a)
    a_lo = a - a_hi
    t = 134217729.0 * b
    b_hi = t - (t - b)
    b_lo = b - b_hi
    return p, ((a_hi * b_hi - p) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo


@njit(nogil=True, inline="always")
def _put_digits(out, end, value, count):  # pragma: no cover - compiled
    """The last ``count`` decimal digits of ``value`` (uint64) into ``out[end - count:end]``, two at a time."""
    k = end
    while count >= 2:
        pair = value % np.uint64(100)
        value //= np.uint64(100)
        out[k - 1] = _PAIRS[np.uint64(2) * pair + np.uint64(1)]
        out[k - 2] = _PAIRS[np.uint64(2) * pair]
        k -= 2
        count -= 2
    if count:
        out[k - 1] = np.uint8(48 + value % np.uint64(10))


@njit(nogil=True, inline="always")
def _put_int(out, at, value):  # pragma: no cover - compiled
    """``b"%d" % value`` into ``out[at:]``; returns the position after it."""
    if value < 0:
        out[at] = 45
        at += 1
    v = np.uint64(abs(value))
    count = 1
    bound = np.uint64(10)
    while count < 20 and v >= bound:
        count += 1
        bound *= np.uint64(10)
    _put_digits(out, at + count, v, count)
    return at + count


@njit(nogil=True, inline="always")
def _put_g(out, at, x, precision, top, decades, scales, column, tie):  # pragma: no cover - compiled
    """``b"%.{precision}g" % x`` into ``out[at:]`` (``top`` is ``10**precision``, ``scales[column]`` the
    :func:`_scales` of the precision); returns the position after it, or -1 for a value within ``tie`` of a rounding
    tie without being one, left to Python."""
    if math.isnan(x):
        out[at], out[at + 1], out[at + 2] = 110, 97, 110
        return at + 3
    if math.copysign(1.0, x) < 0.0:
        out[at] = 45
        at += 1
        x = -x
    if x == 0.0:
        out[at] = 48
        return at + 1
    if x == math.inf:
        out[at], out[at + 1], out[at + 2] = 105, 110, 102
        return at + 3
    m, b = math.frexp(x)
    i = b - _LOWEST
    e = decades[i]
    hi, lo = _two_product(m, scales[column, i, 0, 0])
    lo += m * scales[column, i, 0, 1]
    if hi >= top:  # x lies in the binade's upper decade
        e += 1
        hi, lo = _two_product(m, scales[column, i, 1, 0])
        lo += m * scales[column, i, 1, 1]
    whole = math.floor(hi)
    fraction = (hi - whole) + lo
    if fraction < 0.0:
        whole -= 1.0
        fraction += 1.0
    elif fraction >= 1.0:
        whole += 1.0
        fraction -= 1.0
    digits = np.uint64(whole)
    if abs(fraction - 0.5) < tie:
        # x 10^k is w + 1/2 exactly when 2 x 10^k = X 2^(q+1+k) 5^k (x = X 2^q, X odd) is an odd integer
        k = precision - 1 - e
        mantissa = np.int64(m * 9007199254740992.0)  # m 2^53
        q = b - 53
        while mantissa & 1 == 0:
            mantissa >>= 1
            q += 1
        if q + 1 + k != 0 or (k < 0 and (-k > 22 or mantissa % 5 ** (-k) != 0)):
            return -1
        digits += digits & np.uint64(1)  # half to even
    elif fraction > 0.5:
        digits += np.uint64(1)
    if digits == top:  # rounded up to the next power of ten
        digits = np.uint64(top // 10)
        e += 1
    fixed = -4 <= e < precision
    first = at + 1 - e if fixed and e < 0 else at + 1  # where the digits go: after "0.000" or one place on
    _put_digits(out, first + precision, digits, precision)
    count = precision  # significant digits without the trailing zeros
    while count > 1 and out[first + count - 1] == 48:
        count -= 1
    if fixed and e < 0:
        out[at] = 48
        out[at + 1] = 46
        for k in range(at + 2, first):
            out[k] = 48
        return first + count
    lead = e + 1 if fixed else 1  # digits before the point: moved one place back, for the point
    for k in range(at, at + lead):
        out[k] = out[k + 1]
    end = at + lead
    if count > lead:
        out[end] = 46
        end = at + count + 1
    if fixed:
        return end
    out[end] = 101
    out[end + 1] = 45 if e < 0 else 43
    e = abs(e)
    n = 2 if e < 100 else 3
    _put_digits(out, end + 2 + n, np.uint64(e), n)
    return end + 2 + n


@njit(nogil=True, inline="always")
def _put_bytes(out, at, data, start, stop):  # pragma: no cover - compiled
    for k in range(start, stop):
        out[at] = data[k]
        at += 1
    return at


@njit(nogil=True)
def _float_rows(values, precisions, tops, scales, decades, tie, prefix, suffix, tails, tail_ends, fixes, fix_ends,
                out, offsets):  # pragma: no cover - compiled
    """Rows of ``values`` (n, k) as text into ``out``, row ``i`` at ``out[offsets[i]:offsets[i + 1]]``; a value
    :func:`_put_g` leaves to Python takes the next of ``fixes`` (its bytes up to ``fix_ends``) or, once they are
    used up, nothing. Returns the bytes written, how many values were left to Python and their flat indices."""
    n, k = values.shape
    left = np.empty(16, dtype=np.int64)
    count = 0
    used = 0
    at = 0
    for r in range(n):
        offsets[r] = at
        at = _put_bytes(out, at, prefix, 0, len(prefix))
        for j in range(k):
            if j:
                out[at] = 32
                at += 1
            end = _put_g(out, at, values[r, j], precisions[j], tops[j], decades, scales, j, tie)
            if end >= 0:
                at = end
            elif used + 1 < len(fix_ends):
                at = _put_bytes(out, at, fixes, fix_ends[used], fix_ends[used + 1])
                used += 1
            else:
                if count == len(left):
                    grown = np.empty(2 * count, dtype=np.int64)
                    for q in range(count):  # not grown[:count] = left: its checks cost 1.5 s of a first compile
                        grown[q] = left[q]
                    left = grown
                left[count] = r * k + j
                count += 1
        if len(tail_ends) and tail_ends[r + 1] > tail_ends[r]:
            out[at] = 32
            at = _put_bytes(out, at + 1, tails, tail_ends[r], tail_ends[r + 1])
        at = _put_bytes(out, at, suffix, 0, len(suffix))
    offsets[n] = at
    return at, count, left[:count]


@njit(nogil=True)
def _index_rows(corners, uv, normal, base, prefix, suffix, with_uv, with_normal,
                out):  # pragma: no cover - compiled
    """Rows of corner indices into ``out`` (see :func:`index_rows`); returns the bytes written."""
    at = 0
    for r in range(corners.shape[0]):
        at = _put_bytes(out, at, prefix, 0, len(prefix))
        for c in range(corners.shape[1]):
            if c:
                out[at] = 32
                at += 1
            at = _put_int(out, at, corners[r, c] + base)
            if with_uv:
                out[at] = 47
                at = _put_int(out, at + 1, uv[r, c] + base)
            if with_normal:
                out[at] = 47
                at += 1
                if not with_uv:
                    out[at] = 47
                    at += 1
                at = _put_int(out, at, normal[r, c] + base)
        at = _put_bytes(out, at, suffix, 0, len(suffix))
    return at


@njit(nogil=True)
def _splice(data, spans, texts, text_ends, stream_ends, state, out):  # pragma: no cover - compiled
    """Go on writing ``data`` with its spans replaced into ``out`` until it is full: ``spans`` (E, 2) and the
    texts (``texts[text_ends[i]:text_ends[i + 1]]`` for span ``i``) are the concatenation of streams (ending at
    ``stream_ends``), each in file order, merged here; ``state`` holds the position in ``data`` and, per stream,
    its next span, and is updated. Returns the bytes written."""
    streams = len(stream_ends)
    n = 0
    capacity = len(out)
    while True:
        at = state[0]
        best = -1
        start = len(data)
        for s in range(streams):
            i = state[1 + s]
            if i < stream_ends[s] and spans[i, 0] < start:
                best, start = s, spans[i, 0]
        take = min(start - at, capacity - n)
        out[n : n + take] = data[at : at + take]
        n += take
        state[0] = at + take
        if best < 0 or at + take < start:
            return n
        i = state[1 + best]
        length = text_ends[i + 1] - text_ends[i]
        if n + length > capacity:
            return n
        out[n : n + length] = texts[text_ends[i] : text_ends[i + 1]]
        n += length
        state[0] = spans[i, 1]
        state[1 + best] = i + 1


_NEWLINES = 0x0A0A0A0A0A0A0A0A
_ONES = 0x0101010101010101
_HIGHS = 0x8080808080808080


@intrinsic
def _word_at(typingctx, data, i):  # pragma: no cover - compiled
    """``data[i:i + 8]`` (uint8) as one uint64, its first byte lowest (little-endian, x86 and ARM): a load at any
    byte."""

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        pointer = builder.bitcast(builder.gep(array.data, [args[1]]), ir.IntType(64).as_pointer())
        return builder.load(pointer, align=1)

    return types.uint64(data, i), codegen


@intrinsic
def _trailing_zeros(typingctx, value):  # pragma: no cover - compiled
    """The number of trailing zero bits of a non-zero uint64 (one instruction)."""

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 0))

    return types.uint64(types.uint64), codegen


@njit(nogil=True)
def _count_lines(data, n, state, counts):  # pragma: no cover - compiled
    """Go on counting ``v`` and ``f`` lines (``counts[0]``, ``counts[1]``) over ``data[:n]`` from ``state`` (0: at a
    line's start or in its leading blanks, 1: after its first byte ``v``, 2: ``f``, 3: elsewhere in a line); returns
    the state at the end. The rest of a line is skipped eight bytes at a time (a word holds a line break when one of
    its bytes XOR ``\\n`` is zero; the lowest such byte is the first)."""
    i = 0
    while i < n:
        if state == 3:
            while i + 8 <= n:
                x = _word_at(data, i) ^ np.uint64(_NEWLINES)
                found = (x - np.uint64(_ONES)) & ~x & np.uint64(_HIGHS)
                if found:
                    i += np.int64(_trailing_zeros(found) >> np.uint64(3))
                    break
                i += 8
            else:
                while i < n and data[i] != 10:
                    i += 1
            if i < n:
                state = 0
                i += 1
            continue
        byte = data[i]
        if byte == 10:
            state = 0
        elif state == 0:
            if byte != 32 and byte != 9:
                state = 1 if byte == 118 else 2 if byte == 102 else 3
        else:
            if byte == 32 or byte == 9:
                counts[state - 1] += 1
            state = 3
        i += 1
    return state


# --- entry points and their plain twins ------------------------------------------------------------------------------


def _precisions(precision, k: int) -> np.ndarray:
    """(k,) int64: one precision per column, checked."""
    out = np.asarray(precision, dtype=np.int64).reshape(-1)
    if len(out) == 1:
        out = np.repeat(out, k)
    if len(out) != k or ((out < 1) | (out > MAX_PRECISION)).any():
        raise InputError(f"precision must be one number or {k}, each in 1..{MAX_PRECISION}; got {precision}")
    return out


def joined(pieces: list) -> tuple[np.ndarray, np.ndarray]:
    """Byte strings as one (B,) uint8 array and their (n + 1,) int64 bounds (a stream's text for
    :func:`write_spliced`)."""
    ends = np.zeros(len(pieces) + 1, dtype=np.int64)
    np.cumsum([len(p) for p in pieces], out=ends[1:])
    return np.frombuffer(b"".join(pieces), dtype=np.uint8), ends


def float_rows(values: np.ndarray, precision=9, *, prefix: bytes = b"", suffix: bytes = b"\n",
               tails: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rows of numbers as text, each ``prefix + b" ".join(b"%.{p}g" % x for x in row) + suffix`` (with ``b" " +
    tail`` before the suffix when the row's tail is not empty).

    Parameters
    ----------
    values : (n, k) float64
    precision : significant digits, one for all columns or (k,) one per column, each in 1..15
    prefix, suffix : bytes before and after each row
    tails : n byte strings, or None

    Returns
    -------
    text : (B,) uint8
    offsets : (n + 1,) int64, row ``i`` is ``text[offsets[i]:offsets[i + 1]]``
    """
    return _rows(values, precision, prefix, suffix, tails, _TIE)


def _rows(values, precision, prefix: bytes, suffix: bytes, tails: list | None,
          tie: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`float_rows`, leaving to Python the values whose fraction lies within ``tie`` of one half without being
    a tie (a test makes it large to reach that path). Many rows are written in two halves on two threads (the kernel
    lets go of the interpreter's lock); a value left to Python in either half has all rows written again, on one."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise InputError(f"values must have shape (n, k); got {values.shape}")
    n, k = values.shape
    precisions = _precisions(precision, k)
    scales = np.stack([_scales(int(p)) for p in precisions]) if k else np.zeros((0, _BINADES, 2, 2))
    if tails is None:
        tail_text, tail_ends = joined([])[0], np.zeros(0, dtype=np.int64)
    else:
        tail_text, tail_ends = joined(tails)
    width = len(prefix) + len(suffix) + int((precisions + 8).sum())  # a number: its digits and at most 7 bytes more
    out = np.empty(n * width + (int(tail_ends[-1]) + n if tails is not None else 0), dtype=np.uint8)
    offsets = np.empty(n + 1, dtype=np.int64)
    constants = (precisions, 10**precisions, scales, _decades(), tie, np.frombuffer(prefix, np.uint8),
                 np.frombuffer(suffix, np.uint8), tail_text)

    no_fixes = joined([])

    def part(lo, hi, at, fixes=no_fixes):
        """Rows [lo, hi) into ``out[at:]``, their offsets counted from there."""
        return _float_rows(values[lo:hi], *constants, tail_ends[lo : hi + 1], *fixes, out[at:], offsets[lo : hi + 1])

    if n < _THREADED_ROWS or (os.cpu_count() or 1) < 2:
        size, count, left = part(0, n, 0)
    else:  # the second half written past the first half's widest text, then moved down to follow it
        half = n // 2
        start = half * width + (int(tail_ends[half]) + half if tails is not None else 0)
        with ThreadPoolExecutor(1, thread_name_prefix="kpd-text") as pool:
            other = pool.submit(part, half, n, start)
            size, count, left = part(0, half, 0)
            rest, more, later = other.result()
        out[size : size + rest] = out[start : start + rest]
        offsets[half + 1 :] += size
        offsets[half] = size
        size, count, left = size + rest, count + more, np.concatenate([left, later + half * k])
    if count:
        flat = values.reshape(-1)
        size = part(0, n, 0, joined([b"%.*g" % (int(precisions[i % k]), flat[i]) for i in left.tolist()]))[0]
    return out[:size], offsets


def float_rows_reference(values: np.ndarray, precision=9, *, prefix: bytes = b"", suffix: bytes = b"\n",
                         tails: list | None = None) -> list[bytes]:
    """:func:`float_rows` with Python's ``%`` formatting: the rows, one byte string each."""
    values = np.asarray(values, dtype=np.float64)
    precisions = _precisions(precision, values.shape[1]).tolist()
    rows = []
    for i, row in enumerate(values.tolist()):
        text = b" ".join(b"%.*g" % (p, x) for p, x in zip(precisions, row))
        if tails is not None and tails[i]:
            text += b" " + tails[i]
        rows.append(prefix + text + suffix)
    return rows


def write_float_rows(fh, blocks: list, precision=9, *, prefix: bytes = b"", suffix: bytes = b"\n") -> None:
    """:func:`float_rows` of the columns of ``blocks`` side by side, written to the binary file ``fh`` 65,536 rows
    at a time.

    Parameters
    ----------
    blocks : arrays of n rows each, (n, k_i) float64
    precision : as in :func:`float_rows`, for the columns of all blocks together
    """
    n = len(blocks[0])
    for a in range(0, n, _ROWS):
        parts = [np.asarray(block)[a : a + _ROWS] for block in blocks]
        table = parts[0] if len(parts) == 1 else np.hstack(parts)
        fh.write(float_rows(table, precision, prefix=prefix, suffix=suffix)[0])


def index_rows(corners: np.ndarray, *, prefix: bytes = b"f ", base: int = 1, uv: np.ndarray | None = None,
               normal: np.ndarray | None = None, suffix: bytes = b"\n") -> np.ndarray:
    """Rows of corner indices as text: ``prefix``, the corners separated by spaces, each ``v``, ``v/vt``,
    ``v/vt/vn`` or ``v//vn`` (``base`` added to every index), and ``suffix``.

    Parameters
    ----------
    corners : (n, c) integer, the vertex of each corner
    uv, normal : (n, c) integer or None, the texture coordinate and the normal of each corner
    base : added to every index (1 for OBJ, which counts from 1)

    Returns
    -------
    (B,) uint8
    """
    corners = np.ascontiguousarray(corners, dtype=np.int64)
    n, c = corners.shape
    uv_ = corners if uv is None else np.ascontiguousarray(uv, dtype=np.int64)
    normal_ = corners if normal is None else np.ascontiguousarray(normal, dtype=np.int64)
    width = len(prefix) + len(suffix) + c * (1 + 22 * (1 + (uv is not None) + (normal is not None)))
    out = np.empty(n * width, dtype=np.uint8)
    size = _index_rows(corners, uv_, normal_, base, np.frombuffer(prefix, np.uint8), np.frombuffer(suffix, np.uint8),
                       uv is not None, normal is not None, out)
    return out[:size]


def index_rows_reference(corners: np.ndarray, *, prefix: bytes = b"f ", base: int = 1, uv: np.ndarray | None = None,
                         normal: np.ndarray | None = None, suffix: bytes = b"\n") -> bytes:
    """:func:`index_rows` with Python's ``%d``."""
    corners = np.asarray(corners, dtype=np.int64)
    form = b"%d" + (b"/%d" if uv is not None else b"") + (
        b"" if normal is None else b"/%d" if uv is not None else b"//%d")
    parts = [corners + base] + [np.asarray(a, dtype=np.int64) + base for a in (uv, normal) if a is not None]
    table = np.stack(parts, axis=2).reshape(len(corners), -1)
    row = prefix + b" ".join([form] * corners.shape[1]) + suffix
    return b"".join(row % tuple(r) for r in table.tolist())


def write_index_rows(fh, corners: np.ndarray, **options) -> None:
    """:func:`index_rows` (same options) written to the binary file ``fh`` 65,536 rows at a time."""
    uv, normal = options.pop("uv", None), options.pop("normal", None)
    for a in range(0, len(corners), _ROWS):
        b = a + _ROWS
        fh.write(index_rows(corners[a:b], uv=None if uv is None else uv[a:b],
                            normal=None if normal is None else normal[a:b], **options))


def write_spliced(fh, data: bytes, streams: list) -> bytes:
    """``data`` with spans replaced, written to the binary file ``fh`` 16 MiB at a time.

    Parameters
    ----------
    data : the original bytes
    streams : ``(spans, text, offsets)`` each: spans (E, 2) int64 (start, end) in increasing order, not overlapping
        those of other streams, replaced by ``text[offsets[i]:offsets[i + 1]]`` ((B,) uint8; (E + 1,) int64 from 0
        to B, as :func:`float_rows` gives them)

    Returns
    -------
    The last byte written (empty when nothing was).
    """
    each = [np.asarray(s, dtype=np.int64).reshape(-1, 2) for s, _, _ in streams]
    spans = np.concatenate(each)
    counts = np.array([len(s) for s in each], dtype=np.int64)
    stream_ends = np.cumsum(counts)
    state = np.concatenate([[0], stream_ends - counts])  # the position in data, each stream's next span
    texts = np.concatenate([np.asarray(t, dtype=np.uint8) for _, t, _ in streams])
    bases = np.cumsum([0] + [len(t) for _, t, _ in streams])  # where each stream's text starts in texts
    text_ends = np.concatenate([np.asarray(o[:-1], dtype=np.int64) + base for (_, _, o), base in zip(streams, bases)]
                               + [bases[-1:]])
    out = np.empty(max(_CHUNK, int(np.diff(text_ends).max(initial=0))), dtype=np.uint8)
    source = np.frombuffer(data, dtype=np.uint8)
    last = b""
    while True:
        n = _splice(source, spans, texts, text_ends, stream_ends, state, out)
        if n == 0:
            return last
        fh.write(out[:n])
        last = out[n - 1 : n].tobytes()


def splice_reference(data: bytes, streams: list) -> bytes:
    """:func:`write_spliced`'s bytes, joined in Python."""
    edits = sorted((int(s), int(e), bytes(text[o[i] : o[i + 1]]))
                   for spans, text, o in streams for i, (s, e) in enumerate(np.asarray(spans).reshape(-1, 2).tolist()))
    parts, at = [], 0
    for start, end, new in edits:
        parts += [data[at:start], new]
        at = end
    return b"".join(parts) + data[at:]


def count_obj_lines(path) -> tuple[int, int, bool]:
    """The ``v`` and ``f`` lines of an OBJ file (lines whose first non-blank byte is ``v`` or ``f``, followed by a
    space or a tab) and whether the file ends with a line break; read 16 MiB at a time.

    Returns
    -------
    (vertex lines, face lines, ends with ``\\n``)
    """
    counts = np.zeros(2, dtype=np.int64)
    state, last = 0, b""
    data = np.empty(_CHUNK, dtype=np.uint8)
    with open(path, "rb", buffering=0) as fh:
        while size := fh.readinto(data):
            state = _count_lines(data, size, state, counts)
            last = data[size - 1 : size].tobytes()
    return int(counts[0]), int(counts[1]), last == b"\n"


def count_obj_lines_reference(data: bytes) -> tuple[int, int, bool]:
    """:func:`count_obj_lines` of a file's bytes, line by line in Python."""
    v = f = 0
    for line in data.split(b"\n"):
        s = line.lstrip(b" \t")
        if s[1:2] in (b" ", b"\t"):
            v += s[:1] == b"v"
            f += s[:1] == b"f"
    return v, f, data.endswith(b"\n")
