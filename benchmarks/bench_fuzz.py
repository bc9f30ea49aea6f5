"""The long run of the reader fuzz (tests/fuzzing.py; its seeded sample is tests/test_fuzz.py): ``--cases`` mutated
real files of every format, each read by a public reader in a worker process, and what came of them: per format the
cases and their outcomes, and in all the tracebacks (an exception that is not a kpd error), hangs (no answer within
30 s), memory failures (more than 1 GiB above the worker's start), files opened outside the input's folder and
native crashes, each failure with its case number, mutations and the innermost kpd frame.

    .venv/bin/python benchmarks/bench_fuzz.py [--cases 12000] [--seed 51] [--workers 2] [--work /tmp/fuzz/run] \
        [--out benchmarks/results/fuzz.json]

A case is rebuilt alone with ``fuzzing.make_case(root, seed, index)`` (``root``: the ``--work`` folder, whose seeds
are kept). Progress goes to stderr every 500 cases.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(REPO / "tests"))

import fuzzing  # noqa: E402

from kpd.benchmark import machine_cpu, write_json  # noqa: E402


def grouped(failures: list) -> list:
    """Failures grouped by outcome, kpd frame and message (numbers and paths aside): each group's count, formats and
    first three cases (number, reader, mutations), largest group first."""
    import re

    groups: dict = {}
    for f in failures:
        message = re.sub(r"/\S+", "PATH", re.sub(r"\d{4,}", "N", f["detail"] or ""))[:160]
        group = groups.setdefault((f["outcome"], f["where"], message), {"count": 0, "formats": set(), "cases": []})
        group["count"] += 1
        group["formats"].add(f["format"])
        if len(group["cases"]) < 3:
            group["cases"].append({k: f[k] for k in ("index", "reader", "mutations")})
    return [{"outcome": o, "where": w, "detail": m, "count": g["count"], "formats": sorted(g["formats"]),
             "cases": g["cases"]} for (o, w, m), g in sorted(groups.items(), key=lambda kv: -kv[1]["count"])]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=12000)
    parser.add_argument("--seed", type=int, default=51)
    parser.add_argument("--work", type=Path, default=None, help="folder for the seeds, cases and failing cases")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="kpd-fuzz-"))
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if not (work / "seeds").is_dir():
        fuzzing.make_seeds(work, DATA if (DATA / "modelnet10").is_dir() else None)
    results = []

    def run(first: int) -> None:  # every --workers-th case from `first`, in a worker process of its own
        with fuzzing.Runner(work, args.seed, keep=True) as runner:
            for index in range(first, args.cases, args.workers):
                results.append(runner.run(index))
                if len(results) % 500 == 0:
                    counts = fuzzing.summary(list(results))
                    print(f"{len(results)} cases, {time.perf_counter() - started:.0f} s: "
                          + ", ".join(f"{k} {counts[k]}" for k in ("tracebacks", "hangs", "memorys", "outsides",
                                                                   "crashs")), file=sys.stderr, flush=True)

    with ThreadPoolExecutor(args.workers) as pool:
        for done in [pool.submit(run, w) for w in range(args.workers)]:
            done.result()
    results.sort(key=lambda r: r.index)
    counts = fuzzing.summary(results)
    seconds = [r.seconds for r in results]
    result = {
        "benchmark": "fuzz", "seed": args.seed, "cases": counts["cases"],
        "source_mesh": "modelnet10 chair_0890, decimated to 200 triangles" if (DATA / "modelnet10").is_dir()
        else "kpd.procedural chair, decimated to 200 triangles",
        "tracebacks": counts["tracebacks"], "hangs": counts["hangs"], "memory_failures": counts["memorys"],
        "outside_reads": counts["outsides"], "crashes": counts["crashs"],
        "peak_above_start_mib_max": round(counts["peak_bytes_max"] / 2**20, 1),
        "case_seconds_max": round(max(seconds, default=0.0), 3),
        "per_format": counts["per_format"], "failures": grouped(counts["failures"]),
        "limits": {"seconds": fuzzing.TIMEOUT, "memory_mib": fuzzing.MEMORY_LIMIT >> 20}, "workers": args.workers,
        "machine": platform.machine(), "machine_cpu": machine_cpu(), "cpus": os.cpu_count(),
        "load": os.getloadavg()[0], "seconds": round(time.perf_counter() - started, 1),
    }
    if args.out:
        write_json(args.out, result, indent=1)
    print(json.dumps({k: v for k, v in result.items() if k != "failures"}, indent=1))


if __name__ == "__main__":
    main()
