"""Calibration of --scan's settling of ambiguous orientations, on *training* shoes; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_settle.py --model shoe --data runs/data/shoe \\
        --split-file benchmarks/results/shoe_split_shipped.txt --every 5 --poses 4 --out benchmarks/results/settle.json

Every ``--every``-th shoe of the model's *train* split (never the held-out test shoes, which bench_shoes scores) is
turned by ``--poses`` seeded random rotations (seed 100 + its index) and oriented as ``kpd keypoints shoe SHAPE --scan``
does, with the settling step on (``ScanFrame(settle=True)``). Where the rigid fit to the template is ambiguous, every
candidate rotation (kpd.scan.candidate_rotations) is scored by what settle_orientation measures (the chamfer between the
scan deformed onto the template's keypoints and the template) and by the truth: the mean distance of its keypoints,
mapped back onto the shoe, to the keypoints the model predicts on the shoe as it was trained (the aligned folder's
frame), in % of the shoe's size; a candidate within 5% is right. Reported: how often the rigid fit's choice, the settled
choice and the best candidate (an oracle) are right, and the keypoint spread across poses with and without settling.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_shoes import spread  # noqa: E402

from kpd.benchmark import write_json  # noqa: E402
from kpd.frame import ScanFrame  # noqa: E402
from kpd.data import discover  # noqa: E402
from kpd.io import read_mesh  # noqa: E402
from kpd.runtime import Model  # noqa: E402
from kpd.scan import candidate_rotations, reorient  # noqa: E402

RIGHT_PCT = 5.0  # a candidate whose keypoints are within this (% of the size) of the truth is the right rotation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="shoe")
    parser.add_argument("--data", required=True, help="the aligned folder the model was trained on")
    parser.add_argument("--split-file", default=None, help="the split the model was trained with")
    parser.add_argument("--every", type=int, default=4, help="every N-th training shoe (default 4)")
    parser.add_argument("--poses", type=int, default=4)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    model = Model.load(args.model, threads=1)
    category = discover(args.data, split_file=args.split_file)
    shoes = category.splits["train"][:: args.every]
    rows, started = [], time.perf_counter()
    for i, shape_file in enumerate(shoes):
        mesh = read_mesh(shape_file.path)
        size = float(np.linalg.norm(mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)))
        truth = model.keypoints(mesh, seed=0)
        picks = {"rigid": [], "settled": [], "oracle": []}
        poses = []
        for q in Rotation.random(args.poses, random_state=100 + i).as_matrix():
            frame = ScanFrame(model, mesh.with_vertices(mesh.vertices @ q.T), None, settle=True)
            candidates = [frame.rigid] if frame.settled is None else [
                frame.rigid if k == 0 else reorient(frame.rigid, r)
                for k, (r, _) in enumerate(candidate_rotations(frame.rigid.orientation))]
            keypoints = [c.to_original(model.keypoints(c.shape, seed=0)) @ q for c in candidates]
            errors = [float(100 * np.linalg.norm(k - truth, axis=1).mean() / size) for k in keypoints]
            chosen = 0 if frame.settled is None else frame.settled["chosen"]
            oracle = int(np.argmin(errors))
            picks["rigid"].append(keypoints[0])
            picks["settled"].append(keypoints[chosen])
            picks["oracle"].append(keypoints[oracle])
            poses.append({"ambiguous": frame.settled is not None, "errors_pct": errors, "chosen": chosen,
                          "fits": None if frame.settled is None else [c["fit"] for c in frame.settled["candidates"]]})
        rows.append({"name": shape_file.name, "poses": poses,
                     **{f"spread_{k}_pct": spread(np.stack(v), size) for k, v in picks.items()}})
        print(f"{shape_file.name}: spread {rows[-1]['spread_rigid_pct']:.2f}% rigid, "
              f"{rows[-1]['spread_settled_pct']:.2f}% settled", file=sys.stderr)
    ambiguous = [p for r in rows for p in r["poses"] if p["ambiguous"]]

    def right(pick) -> int:
        return int(sum(p["errors_pct"][pick(p)] <= RIGHT_PCT for p in ambiguous))

    result = {"benchmark": "settle", "model": args.model, "split": "train", "shoes": len(rows), "poses": args.poses,
              "machine": platform.machine(), "cpus": os.cpu_count(), "load": os.getloadavg()[0],
              "ambiguous_poses": len(ambiguous),
              "right_of_ambiguous": {"rigid": right(lambda p: 0), "settled": right(lambda p: p["chosen"]),
                                     "oracle": right(lambda p: int(np.argmin(p["errors_pct"])))},
              "shoes_within_3pct": {k: int(sum(r[f"spread_{k}_pct"] <= 3 for r in rows))
                                    for k in ("rigid", "settled", "oracle")},
              "seconds": time.perf_counter() - started, "shapes": rows}
    if args.out:
        write_json(args.out, result, indent=1)
    print(json.dumps({k: v for k, v in result.items() if k != "shapes"}, indent=1))


if __name__ == "__main__":
    main()
