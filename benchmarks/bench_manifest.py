"""``kpd amplify``'s manifest at a large collection's size; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_manifest.py --shapes 50000 --out benchmarks/results/manifest.json

A manifest of ``--shapes`` sources x 10 variants (ShapeNet's 50k models x 10: 500,000 records, about 570 MB) is
written in the reverse of its sorted order, as a run's workers might finish, with records shaped as the real ones (12
keypoints, 8 coefficients). A fresh process then does what a run's driver does with it, once a run is continued and
finishes: reads it (:class:`kpd.amplify.Manifest`), sums the plausibility measures (the summary line) and rewrites it
sorted. Its wall time and peak resident memory are recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DRIVER = """
import json, resource, sys, time
from kpd.amplify import Manifest, _summary
start = time.perf_counter()
manifest = Manifest(sys.argv[1], 10)
read = time.perf_counter()
summary = _summary(manifest, sorted(manifest.done()), 0, 0.0)
summed = time.perf_counter()
manifest.finish()
end = time.perf_counter()
print(json.dumps({"shapes": summary.done, "records": summary.variants, "read_s": round(read - start, 2),
                  "summary_s": round(summed - read, 2), "sort_s": round(end - summed, 2),
                  "seconds": round(end - start, 2),
                  "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}))
"""


def write_manifest(path: Path, shapes: int, variants: int = 10) -> int:
    rng = np.random.default_rng(0)
    template = [{"variant": v, "seed": int(rng.integers(2**63)), "attempt": 0, "shrink": 1.0,
                 "coefficients": rng.normal(size=8).tolist(), "keypoints": rng.normal(size=(12, 3)).tolist(),
                 "sigma": float(rng.uniform(0, 3)), "folded": float(rng.uniform(0, 0.005))} for v in range(variants)]
    with open(path, "w") as file:
        for i in reversed(range(shapes)):
            source = f"sub{i % 97:02d}/shape_{i:06d}.obj"
            for record in template:
                file.write(json.dumps({"source": source, **record,
                                       "file": f"sub{i % 97:02d}/shape_{i:06d}_{record['variant']:03d}.obj"}) + "\n")
    return path.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=50000)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    from kpd.benchmark import machine_cpu, write_json

    with tempfile.TemporaryDirectory(prefix="kpd-bench-manifest-") as tmp:
        size = write_manifest(Path(tmp) / "manifest.jsonl", args.shapes)
        baseline = subprocess.run([sys.executable, "-c", "import resource, kpd.amplify; "
                                   "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"],
                                  capture_output=True, text=True, check=True, cwd=REPO)
        done = subprocess.run([sys.executable, "-c", DRIVER, tmp], capture_output=True, text=True, check=True,
                              cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    result = {"benchmark": "manifest", "machine_cpu": machine_cpu(), "manifest_mb": round(size / 2**20, 1),
              "peak_mb_after_imports": round(float(baseline.stdout.split()[-1]), 1),
              **json.loads(done.stdout.strip().splitlines()[-1])}
    print(json.dumps(result, indent=2))
    if args.out:
        write_json(args.out, result)


if __name__ == "__main__":
    main()
