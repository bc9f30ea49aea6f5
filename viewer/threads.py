"""The drawing path's worker threads: one pool shared by the compiled passes that release the GIL (shading normals,
culling), and the split of a pass in two halves."""

from __future__ import annotations

import os
from typing import Any

__all__ = ["MAX_PASS_THREADS", "draw_pool", "in_halves"]

MAX_PASS_THREADS = 8  # threads of one parallel pass at most (a culling pass, kpd.viewer.culling)
_HALVES_FROM = 200_000  # items below which a pass runs at once: two threads would cost more than they save

_POOL: Any = None


def draw_pool() -> Any:
    """The pool of the drawing path's threads (made on first use), room for two passes at once."""
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(2 * MAX_PASS_THREADS, thread_name_prefix="kpd-draw")  # two callers at once
    return _POOL


def _two_threads() -> bool:
    return (os.cpu_count() or 1) >= 2


def in_halves(kernel: Any, n: int, *args: Any) -> None:
    """``kernel(lo, hi, *args)`` over [0, n): in two halves on two threads (compiled kernels that release the GIL)
    when the machine has two cores and ``n`` is large, else at once."""
    if n < _HALVES_FROM or not _two_threads():
        kernel(0, n, *args)
        return
    half = n // 2
    other = draw_pool().submit(kernel, half, n, *args)
    kernel(0, half, *args)
    other.result()
