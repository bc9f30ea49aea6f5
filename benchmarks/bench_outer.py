"""Share of surface samples inside the shape (interior faces of overlapping or touching pieces), before and after
outer-surface sampling, on the GSO shoes and the ModelNet10 chairs; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_outer.py --out benchmarks/results/outer.json

"Before": ``sample_surface(..., outer=False)`` (what kpd sampled until now), the share of its points that
:func:`kpd.geometry.interior_mask` finds inside another piece. "After": the same test on ``outer=True`` samples
(zero by construction) and, as an independent check, the share of the *before* points that are farther than 1% of
the diagonal from every *after* point of a dense outer sample (points of interior faces lie away from the outer
surface; points of the outer surface do not).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from kpd.geometry import Normalizer, interior_mask, mesh_pieces, sample_surface  # noqa: E402
from kpd.io import read_mesh  # noqa: E402
from kpd.commands.bench import write_json  # noqa: E402


def measure(path: str, n: int, seed: int) -> dict:
    mesh = read_mesh(path)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    vertices = Normalizer().fit(mesh.vertices[np.unique(triangles)]).apply(mesh.vertices)
    started = time.perf_counter()
    before = sample_surface(vertices, triangles, n, seed=seed)
    plain = time.perf_counter() - started
    inside = interior_mask(vertices, triangles, before.points, before.faces)
    started = time.perf_counter()
    after = sample_surface(vertices, triangles, n, seed=seed, outer=True)
    outer_seconds = time.perf_counter() - started
    after_inside = interior_mask(vertices, triangles, after.points, after.faces)
    dense = sample_surface(vertices, triangles, 8 * n, seed=seed + 1, outer=True).points
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    far = cKDTree(dense).query(before.points)[0] > 0.01 * diagonal
    return {"name": Path(path).parent.name if Path(path).name == "model.obj" else Path(path).stem,
            "pieces": int(mesh_pieces(triangles).max() + 1), "interior_before": float(inside.mean()),
            "interior_after": float(after_inside.mean()), "far_from_outer_before": float(far.mean()),
            "far_from_outer_of_interior": float(far[inside].mean()) if inside.any() else None,
            "seconds_plain": plain, "seconds_outer": outer_seconds}


def summary(rows: list[dict]) -> dict:
    before = np.array([r["interior_before"] for r in rows])
    after = np.array([r["interior_after"] for r in rows])
    far = np.array([r["far_from_outer_before"] for r in rows])
    return {"shapes": len(rows), "interior_before_mean": float(before.mean()),
            "interior_before_median": float(np.median(before)), "shapes_with_interior": int((before > 0.001).sum()),
            "interior_after_mean": float(after.mean()), "far_from_outer_before_mean": float(far.mean()),
            "seconds_outer_median": float(np.median([r["seconds_outer"] for r in rows])),
            "seconds_plain_median": float(np.median([r["seconds_plain"] for r in rows]))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=os.environ.get("KPD_DATA", str(REPO.parent / "shared" / "data")))
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chairs", default="test", help="ModelNet10 chair split measured (default test)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    data = Path(args.data)
    sets = {"gso_shoes": sorted(glob.glob(str(data / "gso_shoes" / "*" / "model.obj"))),
            f"modelnet10_chair_{args.chairs}": sorted(glob.glob(str(data / "modelnet10" / "chair" / args.chairs /
                                                                   "*.ply")))}
    result = {"benchmark": "outer", "points": args.points, "seed": args.seed, "machine": platform.machine(),
              "cpus": os.cpu_count(), "load": os.getloadavg()[0], "sets": {}}
    for name, files in sets.items():
        rows = [measure(f, args.points, args.seed) for f in files]
        result["sets"][name] = {"summary": summary(rows), "shapes": rows}
    if args.out:
        write_json(args.out, result, indent=1)
    print(json.dumps({k: v["summary"] for k, v in result["sets"].items()}, indent=1))


if __name__ == "__main__":
    main()
