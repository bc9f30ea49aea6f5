"""What the benchmarks share: timers and the JSON writer (``benchmarks/*.py`` and ``kpd bench``)."""

from __future__ import annotations

import json
import os
import statistics
import time

__all__ = ["write_json", "median_ms", "best_seconds"]


def write_json(path: str | os.PathLike, data: dict, *, indent: int = 2) -> None:
    """Write a benchmark's result as JSON through kpd's one atomic writer (a full disk or a read-only folder is one
    :class:`kpd.errors.WriteError`, nothing half-written is left); the folder is made when missing, an existing file
    replaced."""
    from pathlib import Path

    from kpd.io import atomic_output

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, force=True) as tmp:
        tmp.write_text(json.dumps(data, indent=indent) + "\n", encoding="utf-8")


def median_ms(fn, repeats: int, warmup: int = 10) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def best_seconds(fn, repeats: int, clock=time.perf_counter) -> float:
    """Fastest of ``repeats`` calls of ``fn()`` after one untimed call, in seconds of ``clock``."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = clock()
        fn()
        best = min(best, clock() - start)
    return best
