"""The compiled number scanner the text readers share (OBJ, OFF, ASCII PLY): the decimals of many rows of bytes read
in one pass, each the correctly rounded value Python's ``float`` gives, and a helper that runs such a pass in two
halves on two threads.

A row is a span ``buf[begin[r]:stop[r]]`` of one file's bytes; its words are split where ``bytes.split()`` splits
(:data:`BLANKS`) and end at a ``#``. A word beyond the fast path (more than 15 significant digits, ``nan``, a stray
character) marks its row as not exact, and the caller reads that row with Python.
"""

from __future__ import annotations

import os

import numpy as np

from kpd._compiled import compiled_on_first_call

__all__ = ["THREADED_ROWS", "BLANKS", "HASH", "in_halves", "scan_numbers"]

HASH = 35  # '#': a comment starts
THREADED_ROWS = 65536  # rows below which a second thread costs more than it saves


def in_halves(kernel, n: int, *args) -> None:
    """``kernel(lo, hi, *args)`` over the rows [0, n): in two halves on two threads for many rows (the kernels let go
    of the interpreter's lock)."""
    kernel(0, 0, *args)  # compiled (or loaded) here, once
    if n < THREADED_ROWS or (os.cpu_count() or 1) < 2:
        kernel(0, n, *args)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, thread_name_prefix="kpd-io") as pool:
        other = pool.submit(kernel, n // 2, n, *args)
        kernel(0, n // 2, *args)
        other.result()


# powers of ten that float64 holds exactly: a decimal whose digits make an integer below 2**53, times or over one of
# them, is one correctly rounded operation, the value Python's float() gives (Clinger's fast path); any other word is
# read by Python
POW10_EXACT = np.array([10.0**k for k in range(23)])
EXACT_MANTISSA = 2**53
BLANKS = np.array([b in b" \t\n\r\x0b\x0c" for b in range(256)])  # what bytes.split() splits at


@compiled_on_first_call
def scan_numbers(lo, hi, buf, begin, stop, out, counts, exact):  # pragma: no cover - compiled
    """Row r's numbers, the blank-separated words of ``buf[begin[r]:stop[r]]`` up to a ``#``: the first
    ``out.shape[1]`` into ``out[r]``, how many into ``counts[r]``, and ``exact[r]`` False when some word is not a
    plain decimal (sign, digits, point, exponent) within the fast path's reach (Python then reads the row)."""
    width = out.shape[1]
    for r in range(lo, hi):
        i, end = begin[r], stop[r]
        k = 0
        good = True
        while True:
            while i < end and BLANKS[buf[i]]:
                i += 1
            if i >= end or buf[i] == HASH:
                break
            j = i
            while j < end and not BLANKS[buf[j]] and buf[j] != HASH:
                j += 1
            # the word buf[i:j]
            negative = False
            if buf[i] == 43 or buf[i] == 45:  # + -
                negative = buf[i] == 45
                i += 1
            mantissa = 0
            digits = 0  # significant digits in the mantissa
            exponent = 0
            seen = False
            cut = False  # a non-zero digit beyond the 18 the mantissa holds
            point = False
            while i < j:
                if buf[i] == 46 and not point:  # .
                    point = True
                    i += 1
                    continue
                if not 48 <= buf[i] <= 57:
                    break
                seen = True
                d = buf[i] - 48
                if digits < 18:
                    if mantissa or d:
                        mantissa = mantissa * 10 + d
                        digits += 1
                    exponent -= point
                else:
                    exponent += not point
                    cut |= d != 0
                i += 1
            if seen and i < j and (buf[i] == 101 or buf[i] == 69):  # e E
                i += 1
                down = False
                if i < j and (buf[i] == 43 or buf[i] == 45):
                    down = buf[i] == 45
                    i += 1
                seen = i < j
                e = 0
                while i < j and 48 <= buf[i] <= 57:
                    if e < 100000:
                        e = e * 10 + buf[i] - 48
                    i += 1
                exponent += -e if down else e
            value = 0.0
            ok = seen and i == j and not cut and mantissa <= EXACT_MANTISSA
            if ok and mantissa:
                if 0 <= exponent <= 22:
                    value = float(mantissa) * POW10_EXACT[exponent]
                elif -22 <= exponent < 0:
                    value = float(mantissa) / POW10_EXACT[-exponent]
                elif 22 < exponent <= 37 and mantissa <= EXACT_MANTISSA // 10 ** (exponent - 22):
                    value = float(mantissa * 10 ** (exponent - 22)) * POW10_EXACT[22]  # still an exact integer
                else:
                    ok = False
            if k < width:
                out[r, k] = -value if negative else value
            k += 1
            good &= ok
            i = j
        counts[r] = k
        exact[r] = good
