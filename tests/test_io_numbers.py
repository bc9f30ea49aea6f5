"""The compiled number scanner the text readers share (kpd.io.numbers)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.io import numbers


def scan(rows: list[bytes], width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``scan_numbers`` over the rows, one after another in one buffer: (n, width) values, (n,) counts and exact."""
    data = b"\n".join(rows)
    lengths = np.array([len(r) for r in rows], dtype=np.int64)
    begin = np.concatenate([[0], np.cumsum(lengths + 1)[:-1]]).astype(np.int64)
    stop = begin + lengths
    n = len(rows)
    out = np.zeros((n, width))
    counts = np.empty(n, dtype=np.int64)
    exact = np.empty(n, dtype=np.bool_)
    numbers.in_halves(numbers.scan_numbers, n, np.frombuffer(data, dtype=np.uint8), begin, stop, out, counts, exact)
    return out, counts, exact


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=0, max_size=5),
                min_size=1, max_size=20),
       st.sampled_from(["%r", "%.9g", "%.6f", "%e", "%+.3E"]))
def test_rows_read_as_python_reads_them(values, form):
    rows = [" \t".join(form % x for x in row).encode() for row in values]
    out, counts, exact = scan(rows, 5)
    for r, row in enumerate(values):
        assert counts[r] == len(row)
        if exact[r]:  # a row beyond the fast path is the caller's to read with Python
            want = [float(form % x) for x in row]
            assert out[r, :len(row)].view(np.int64).tolist() == np.array(want).view(np.int64).tolist()


def test_words_beyond_the_fast_path_mark_their_row():
    rows = [b"1 2 3", b"0.12345678901234567890123 0 0", b"nan 0 0", b"1x 0 0", b"1e400 0 0", b"4 5 6"]
    out, counts, exact = scan(rows, 3)
    assert exact.tolist() == [True, False, False, False, False, True]
    assert out[0].tolist() == [1.0, 2.0, 3.0] and out[5].tolist() == [4.0, 5.0, 6.0]
    assert counts.tolist() == [3] * 6


def test_a_comment_ends_the_row_and_extra_words_are_counted():
    out, counts, exact = scan([b"1 2 # 3 4", b"1 2 3 4 5 6", b"   ", b"-0 +.5 5."], 3)
    assert counts.tolist() == [2, 6, 0, 3]
    assert out[1].tolist() == [1.0, 2.0, 3.0]
    assert out[3].view(np.int64).tolist() == np.array([-0.0, 0.5, 5.0]).view(np.int64).tolist()
    assert exact.all()


@pytest.mark.parametrize("threshold", [1, numbers.THREADED_ROWS])
def test_in_halves_covers_every_row_once(monkeypatch, threshold):
    monkeypatch.setattr(numbers, "THREADED_ROWS", threshold)
    seen = np.zeros(1001, dtype=np.int64)

    def kernel(lo, hi, out):
        out[lo:hi] += 1

    numbers.in_halves(kernel, len(seen), seen)
    assert seen.tolist() == [1] * len(seen)
