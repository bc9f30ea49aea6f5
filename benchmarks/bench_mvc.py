"""Speed of mean value coordinates and cage fitting; prints one JSON object.

1. ``kpd.mvc.mvc_weights`` for 10k and 100k random points in the [-1, 1] box against the level-1 cage (42 vertices,
   80 faces), best of a few repeats, with the default threads and with one thread. Target: 100k in <= 1.0 s on two
   cores. Also the CPU time of the one-thread run, which a busy shared machine inflates much less than wall time.
2. A machine-limit reference measured in the same run: a float64 numpy matmul with the same output size,
   ``(N, 3F) @ (3F, C)``, i.e. the cost of merely scattering 3F corner weights to C vertices with BLAS. The ratio
   ``mvc / matmul`` is what to compare across machines and loads (this machine is shared).
3. ``kpd.cage.fit_cage`` on 1024 points: the authors' rule and with ``enclose=True``.

Usage: ``.venv/bin/python benchmarks/bench_mvc.py [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from kpd.benchmark import best_seconds
from kpd.cage import fit_cage, icosphere, points_outside
from kpd.mvc import mvc_weights


def chair_points(n: int, seed: int) -> np.ndarray:
    """A synthetic chair in the [-1, 1] box (seat, back, four legs), as in tests/test_cage.py."""
    rng = np.random.default_rng(seed)
    parts = [((-0.6, 0.6), (-0.6, 0.6), (-0.05, 0.05)), ((-0.6, 0.6), (0.5, 0.6), (0.05, 1.0))] + [
        ((x - 0.04, x + 0.04), (y - 0.04, y + 0.04), (-1.0, -0.05)) for x in (-0.55, 0.55) for y in (-0.55, 0.55)
    ]
    sizes = np.array([np.prod([hi - lo for lo, hi in box]) ** (2 / 3) for box in parts])
    counts = rng.multinomial(n, sizes / sizes.sum())
    return np.concatenate(
        [rng.uniform([b[0] for b in box], [b[1] for b in box], (k, 3)) for box, k in zip(parts, counts)]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats per measurement (best is reported)")
    args = parser.parse_args()

    cage = icosphere(1, 1.4)
    c, f = len(cage.vertices), len(cage.faces)
    rng = np.random.default_rng(0)
    result: dict = {
        "benchmark": "mvc",
        "cage": {"level": 1, "vertices": c, "faces": f},
        "machine": {
            "cpus": os.cpu_count(),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
        "mvc_bind": {},
    }
    for n in (10_000, 100_000):
        points = rng.uniform(-1.0, 1.0, (n, 3))
        corner = rng.standard_normal((n, 3 * f))
        scatter = rng.standard_normal((3 * f, c))
        mvc = best_seconds(lambda: mvc_weights(points, cage.vertices, cage.faces), args.repeats)
        one = best_seconds(lambda: mvc_weights(points, cage.vertices, cage.faces, threads=1), args.repeats)
        cpu_one = best_seconds(lambda: mvc_weights(points, cage.vertices, cage.faces, threads=1), args.repeats,
                               clock=time.process_time)  # CPU time: a busy shared machine inflates it less
        matmul = best_seconds(lambda: corner @ scatter, args.repeats)
        result["mvc_bind"][str(n)] = {
            "points": n,
            "seconds": round(mvc, 4),
            "seconds_one_thread": round(one, 4),
            "cpu_seconds_one_thread": round(cpu_one, 4),
            "baseline_numpy_matmul_seconds": round(matmul, 5),
            "baseline": f"float64 ({n}, {3 * f}) @ ({3 * f}, {c}) numpy matmul, same output size, same run",
            "ratio_to_baseline": round(mvc / matmul, 1),
            "points_per_second": round(n / mvc),
        }
    result["mvc_bind"]["target_100k_seconds"] = 1.0
    result["mvc_bind"]["meets_target"] = result["mvc_bind"]["100000"]["seconds"] <= 1.0

    points = chair_points(1024, seed=0)
    authors = fit_cage(points)
    enclosed = fit_cage(points, enclose=True)
    result["fit_cage_1024"] = {
        "points": 1024,
        "authors_seconds": round(best_seconds(lambda: fit_cage(points), args.repeats * 3), 5),
        "enclose_seconds": round(best_seconds(lambda: fit_cage(points, enclose=True), args.repeats * 3), 5),
        "outside_authors": int(points_outside(points, *authors).sum()),
        "outside_enclose": int(points_outside(points, *enclosed).sum()),
        "max_vertex_radius_authors": round(float(np.linalg.norm(authors.vertices, axis=1).max()), 4),
        "max_vertex_radius_enclose": round(float(np.linalg.norm(enclosed.vertices, axis=1).max()), 4),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
