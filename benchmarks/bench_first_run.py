"""A command's first run on a machine, against its later runs; prints one JSON object.

kpd's kernels are compiled by numba for the processor on their first call and cached (beside the package, or in
``NUMBA_CACHE_DIR``). A user's first command after installing pays for that once. Each case runs ``--runs`` times
with an empty cache of its own (``first_run_s``: every kernel the command needs is compiled) and as many times with
that cache filled (``cached_s``), in fresh processes, wall time, median, min and max. The cases:

* ``keypoints``: ``kpd keypoints chair chair_0956.ply`` (ModelNet10, 9,971 vertices);
* ``render``: ``kpd render chair chair_0956.ply --move 0:0,0.05,0``;
* ``deform_obj``: ``kpd deform chair chair_0956.ply --move 0:0,0.05,0 --out deformed.obj`` (OBJ written).

The editor's first frame on a first run is in ``bench_viewer.py``'s results, where a case is the first to compile.

Usage: ``.venv/bin/python benchmarks/bench_first_run.py [--runs 3] > benchmarks/results/first_run.json``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KPD_DATA", ROOT.parent / "shared" / "data"))
CHAIR = DATA / "modelnet10" / "chair" / "test" / "chair_0956.ply"


def timed(argv: list[str], cache: Path) -> float:
    """Wall seconds of ``kpd argv`` in a fresh process whose numba cache is ``cache``; a failure ends the run."""
    kpd = str(Path(sys.executable).with_name("kpd"))
    start = time.perf_counter()
    done = subprocess.run([kpd, *argv], capture_output=True, text=True,
                          env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)))
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"kpd {' '.join(argv)} failed: {done.stderr.strip()}")
    return seconds


def summary(values: list[float]) -> dict:
    return {"median": round(statistics.median(values), 2), "min": round(min(values), 2), "max": round(max(values), 2),
            "runs": len(values)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="first runs (each with an empty cache) and cached runs")
    args = parser.parse_args()
    from kpd.benchmark import machine_cpu, machine_speed

    result: dict = {
        "benchmark": "a command's first run (numba compiles kpd's kernels) against its later runs (the cache)",
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "cpu": machine_cpu(),
                    "speed_at_start": machine_speed()},
        "cases": {},
    }
    with tempfile.TemporaryDirectory(prefix="kpd-bench-first-run-") as tmp:
        folder = Path(tmp)
        cases = {
            "keypoints": ["keypoints", "chair", str(CHAIR)],
            "render": ["render", "chair", str(CHAIR), "--move", "0:0,0.05,0", "--out", str(folder / "r.png"),
                       "--force"],
            "deform_obj": ["deform", "chair", str(CHAIR), "--move", "0:0,0.05,0", "--out", str(folder / "d.obj"),
                           "--force"],
        }
        for name, argv in cases.items():
            first, cached = [], []
            for run in range(args.runs):
                cache = folder / f"cache-{name}-{run}"
                first.append(timed(argv, cache))  # an empty cache: everything compiled, then written there
                cached.append(timed(argv, cache))
            shown = " ".join(argv).replace(str(folder), "TMP").replace(str(DATA), "$KPD_DATA")
            result["cases"][name] = {"command": "kpd " + shown,
                                     "first_run_s": summary(first), "cached_s": summary(cached),
                                     "ratio": round(statistics.median(first) / statistics.median(cached), 1)}
            print(name, json.dumps(result["cases"][name]), file=sys.stderr)
    result["machine"]["load_average_1min"] = round(os.getloadavg()[0], 2)
    result["machine"]["speed_at_end"] = machine_speed()
    result["when"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
