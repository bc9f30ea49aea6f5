"""The frame and category check (kpd.frame) measured: warned when turned, silent when upright, foreign flagged.

Prints one JSON object (``--out`` writes it too). For each model (the shipped chair and table bundles): ModelNet10
*test* shapes of its category as given (upright) and turned (y up, a quarter and a half turn about the up axis,
upside down, on the side), and shapes of other categories as given (the other ModelNet10 category's test shapes,
Google Scanned Objects shoes, the YCB banana, drill and bottle, the sneaker scan). Rates:

* ``turned_warned``: share of turned copies with a turn warning or a foreign flag (either tells the user the
  keypoints will be wrong); ``upright_silent``: share of the upright shapes with neither;
* ``foreign_flagged``: share of shapes of other categories flagged as not of the category.

The limits are the bundle's ``frame_check`` entry (written at export by :func:`kpd.frame.calibrate`); for a
bundle without one, ``--calibrate N`` computes them here the same way from N training shapes.

    python benchmarks/bench_frame.py --shapes 20 --out benchmarks/results/frame.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from kpd.data import discover
from kpd.frame import _aligner, _check, calibrate
from kpd.io import Mesh, read_mesh, read_shape
from kpd.runtime import Model
from kpd.benchmark import write_json

DATA = Path(os.environ.get("KPD_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def rotation(axis: str, degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


TURNS = {"y_up": rotation("x", -90), "quarter_turn": rotation("z", 90), "half_turn": rotation("z", 180),
         "upside_down": rotation("x", 180), "on_side": rotation("y", 90)}


def turned(mesh: Mesh, rot: np.ndarray) -> Mesh:
    return Mesh(mesh.vertices @ rot.T, mesh.triangles)


def others(category: str, limit: int) -> dict[str, list]:
    other = "table" if category == "chair" else "chair"
    files = {other: [f.path for f in sorted(discover(DATA / "modelnet10", other).splits["test"],
                                            key=lambda f: f.name)[:limit]]}
    shoes = sorted((DATA / "gso_shoes").glob("*/model.obj"))
    files["shoe"] = shoes[:: max(1, len(shoes) // limit)][:limit]
    files["ycb"] = sorted((DATA / "scans" / "ycb").glob("*/textured_simple_reoriented.obj"))
    files["sneaker_scan"] = [DATA / "scans" / "sneaker.ply"]
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--categories", default="chair,table")
    parser.add_argument("--shapes", type=int, default=20, help="test shapes per category and turn (default 20)")
    parser.add_argument("--others", type=int, default=10, help="shapes per other category (default 10)")
    parser.add_argument("--calibrate", type=int, default=100,
                        help="training shapes for the score limit of a bundle without one (default 100)")
    parser.add_argument("--bundle", action="append", default=[], help="CATEGORY=PATH instead of the shipped one")
    parser.add_argument("--out")
    args = parser.parse_args(argv)
    paths = dict(item.split("=", 1) for item in args.bundle)
    t0 = time.perf_counter()
    result: dict = {"benchmark": "frame", "settings": vars(args).copy(),
                    "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                                "load": os.getloadavg()}, "categories": {}}
    for category in args.categories.split(","):
        model = Model.load(paths.get(category, category), threads=1)
        aligner = _aligner(model.template_points, model.up)
        limit_entry = model.bundle.manifest.get("frame_check")
        if limit_entry is None:
            train = sorted(discover(DATA / "modelnet10", category).splits["train"], key=lambda f: f.name)
            train = train[:: max(1, len(train) // args.calibrate)][: args.calibrate]
            points = [model.sample(read_mesh(f.path))[1] for f in tqdm(train, desc="calibration", leave=False)]
            limit_entry = {**calibrate(model.template_points, model.up, points, lambda p: model.run(p)[0]),
                           "source": "computed by the bench"}
        tests = [read_mesh(f.path) for f in sorted(discover(DATA / "modelnet10", category).splits["test"],
                                                  key=lambda f: f.name)[: args.shapes]]
        seconds = []

        def check(shape):
            start = time.perf_counter()
            _, points = model.sample(shape)
            r = _check(aligner, lambda p: model.run(p)[0], points, model.up, limit_entry)
            seconds.append(time.perf_counter() - start)
            return r

        cases: dict = {}
        upright = [check(m) for m in tqdm(tests, desc=f"{category} upright", leave=False)]
        cases["upright"] = {"silent": float(np.mean([not (r.turned or r.foreign) for r in upright])),
                            "turn_warned": float(np.mean([r.turned for r in upright])),
                            "foreign_flagged": float(np.mean([r.foreign for r in upright])),
                            "best_score_median": float(np.median([r.best_score for r in upright])),
                            "keypoint_fit_median": float(np.median([r.keypoint_fit for r in upright]))}
        warned_all = []
        for name, rot in TURNS.items():
            rs = [check(turned(m, rot)) for m in tqdm(tests, desc=f"{category} {name}", leave=False)]
            warned = [r.turned or r.foreign for r in rs]
            warned_all += warned
            cases[name] = {"warned": float(np.mean(warned)), "turn_warned": float(np.mean([r.turned for r in rs])),
                           "foreign_flagged": float(np.mean([r.foreign for r in rs])),
                           "up_named_right": float(np.mean([r.up == "y" for r in rs])) if name == "y_up" else None}
        foreign = {}
        for other, files in others(category, args.others).items():
            rs = [check(read_shape(f)) for f in tqdm(files, desc=f"{category} vs {other}", leave=False)]
            foreign[other] = {"shapes": len(rs), "flagged": float(np.mean([r.foreign for r in rs])),
                              "best_score_median": float(np.median([r.best_score for r in rs])),
                              "keypoint_fit_median": float(np.median([r.keypoint_fit for r in rs]))}
        flagged = [v["flagged"] * v["shapes"] for v in foreign.values()]
        result["categories"][category] = {
            "bundle": str(model.bundle.path), "frame_check": limit_entry, "shapes": len(tests),
            "upright_silent": cases["upright"]["silent"], "turned_warned": float(np.mean(warned_all)),
            "foreign_flagged": float(sum(flagged) / sum(v["shapes"] for v in foreign.values())),
            "cases": cases, "other_categories": foreign,
            "seconds_per_check": {"median": float(np.median(seconds)), "p90": float(np.quantile(seconds, 0.9))},
        }
    result["seconds"] = time.perf_counter() - t0
    print(json.dumps(result, indent=2))
    if args.out:
        write_json(args.out, result, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
