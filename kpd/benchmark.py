"""What the benchmarks share: timers and the JSON writer (``benchmarks/*.py`` and ``kpd bench``)."""

from __future__ import annotations

import json
import os
import statistics
import time

__all__ = ["write_json", "median_ms", "best_seconds", "machine_speed", "machine_cpu"]


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


def machine_speed(*, repeats: int = 5) -> dict:
    """Two figures of this machine's speed at the moment, for comparing benchmark runs of different days (a shared
    virtual machine's speed drifts by tens of percent): ``sort_s``, the median seconds of sorting 2M random float64
    numbers on one core (compute), and ``fresh_memory_gb_per_s``, the median rate of touching 256 MB of memory new to
    the process, one write per page (what the kernel, and under a virtual machine its host, spend on fresh pages:
    a large share of binding a million-vertex mesh)."""
    import mmap

    import numpy as np

    values = np.random.default_rng(0).random(2_000_000)
    sorts, rates = [], []
    size = 256 << 20
    for _ in range(repeats):
        start = time.perf_counter()
        np.sort(values, kind="quicksort")
        sorts.append(time.perf_counter() - start)
        region = mmap.mmap(-1, size)
        try:
            pages = np.frombuffer(region, dtype=np.uint8)
            start = time.perf_counter()
            pages[::mmap.PAGESIZE] = 1
            rates.append(size / 1e9 / (time.perf_counter() - start))
            del pages
        finally:
            region.close()
    return {"sort_s": round(statistics.median(sorts), 4), "fresh_memory_gb_per_s": round(statistics.median(rates), 2)}


def machine_cpu(cpuinfo: str = "/proc/cpuinfo") -> dict:
    """Which processor this is, for telling runs of different days apart (a virtual machine may be given
    different host processors from one day to the next): ``model``
    (the name the processor gives), ``family`` and ``model_number`` (x86's numbers), and ``vectors``, the widest
    vector instructions it offers (``avx512f``, ``avx2``, ``avx``, ``sse2`` or ``unknown``). Empty strings where
    the file or a line is missing (not Linux, another architecture)."""
    fields: dict[str, str] = {}
    flags: set[str] = set()
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as file:
            for line in file:
                if not line.strip():
                    break  # the first processor's block is enough
                key, _, value = line.partition(":")
                key, value = key.strip(), value.strip()
                if key == "flags":
                    flags = set(value.split())
                else:
                    fields.setdefault(key, value)
    except OSError:
        pass
    vectors = next((name for name in ("avx512f", "avx2", "avx", "sse2") if name in flags), "unknown")
    return {"model": fields.get("model name", ""), "family": fields.get("cpu family", ""),
            "model_number": fields.get("model", ""), "vectors": vectors}
