"""The shoe bundle under random poses: keypoints of held-out shoes with --scan; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_shoes.py --model shoe --data runs/data/shoe \
        --split-file benchmarks/results/shoe_split_shipped.txt --poses 6 --out benchmarks/results/shoes.json \
        --sheet docs/shoe_keypoints.png

For every shoe of the model's *test* split (rebuilt from the aligned folder as the training did, or read from
``--split-file``; its counts must match those recorded in the bundle, so that no training shoe is scored), the
mesh is turned by ``--poses`` seeded random rotations; each turned copy goes through what ``kpd keypoints shoe
SHAPE --scan`` does (kpd.scan orients it to the bundle's template, the model predicts, the keypoints are mapped back
onto the turned copy), and the keypoints are turned back by the known rotation. The spread of a shoe is the mean
over its keypoints of the RMS distance of the pose copies to their mean, in % of the shoe's bounding-box diagonal.
``scan_settled`` is the same with an ambiguous orientation settled by the model (ScanFrame(settle=True),
kpd.frame.settle_orientation; off in --scan). The same without --scan (the networks see the
turned copy as it is) shows what the orientation step buys. Also:
the distance of each held-out shoe's keypoints to its *outer* surface (in its [-1, 1] frame; ``kpd eval keypoints``
measures to every face, interior ones included).
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

from scipy.spatial import cKDTree  # noqa: E402

from kpd.frame import ScanFrame  # noqa: E402
from kpd.geometry import Normalizer, sample_surface  # noqa: E402
from kpd.data import discover  # noqa: E402
from kpd.io import read_mesh  # noqa: E402
from kpd.runtime import Model  # noqa: E402
from kpd.benchmark import write_json  # noqa: E402


def spread(keypoints: np.ndarray, size: float) -> float:
    """keypoints (P, K, 3) of P poses in one frame -> mean over K of the RMS distance to the mean, in % of size."""
    centre = keypoints.mean(axis=0)  # (K, 3)
    rms = np.sqrt(((keypoints - centre) ** 2).sum(axis=2).mean(axis=0))  # (K,)
    return float(100.0 * rms.mean() / size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="shoe")
    parser.add_argument("--data", required=True, help="the aligned folder the model was trained on")
    parser.add_argument("--split-file", default=None,
                        help="the split the model was trained with (NAME SPLIT lines), when the folder alone no longer "
                             "gives it (a re-scan decides other shapes)")
    parser.add_argument("--poses", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sheet", default=None, help="also draw the first 12 held-out shoes with their keypoints")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    model = Model.load(args.model, threads=1)
    record = model.bundle.manifest.get("training") or {}
    discover_args = (record.get("data") or {}).get("discover") or {}
    category = discover(args.data, split_file=args.split_file,
                        val_fraction=float(discover_args.get("val_fraction", 0.1)),
                        seed=int(discover_args.get("seed", 0)))
    recorded = (record.get("data") or {}).get("counts") or {}
    found = {split: len(category.splits[split]) for split in recorded}
    if recorded and found != recorded:
        raise SystemExit(f"{args.data}: the split found ({found}) is not the one {args.model} was trained with "
                         f"({recorded}); pass the training split as --split-file")
    tests = category.splits["test"]
    rows = []
    started = time.perf_counter()
    for i, shape_file in enumerate(tests):
        mesh = read_mesh(shape_file.path)
        size = float(np.linalg.norm(mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)))
        turns = Rotation.random(args.poses, random_state=args.seed + i).as_matrix()  # (P, 3, 3)
        with_scan, with_settle, without, flagged, settled = [], [], [], 0, 0
        for q in turns:
            turned = mesh.with_vertices(mesh.vertices @ q.T)
            frame = ScanFrame(model, turned, None, settle=True)  # frame.rigid: what --scan does
            flagged += int(frame.result.orientation.ambiguous)
            settled += int(frame.settled is not None and frame.settled["chosen"] != 0)
            with_scan.append(frame.rigid.to_original(model.keypoints(frame.rigid.shape, seed=0)) @ q)
            settled_keypoints = (with_scan[-1] if frame.result is frame.rigid else
                                 frame.to_original(model.keypoints(frame.result.shape, seed=0)) @ q)
            with_settle.append(settled_keypoints)
            without.append(model.keypoints(turned, seed=0) @ q)
        # distance of the keypoints (the shoe as it is, in its [-1, 1] frame) to the outer surface
        normalizer = Normalizer().fit(mesh.vertices[np.unique(mesh.triangles)])
        outer = sample_surface(normalizer.apply(mesh.vertices), mesh.triangles, 50000, seed=0, outer=True).points
        keypoints = normalizer.apply(model.keypoints(mesh, seed=0))
        outer_distance = cKDTree(outer).query(keypoints)[0]
        rows.append({"name": shape_file.name, "size": size, "flagged_poses": flagged, "settled_otherwise": settled,
                     "spread_settled_pct": spread(np.stack(with_settle), size),
                     "outer_surface_distance": outer_distance.tolist(),
                     "spread_scan_pct": spread(np.stack(with_scan), size),
                     "spread_plain_pct": spread(np.stack(without), size)})
        print(f"{shape_file.name}: {rows[-1]['spread_scan_pct']:.2f}% with --scan "
              f"({rows[-1]['spread_settled_pct']:.2f}% settled by the model, {settled} poses turned otherwise), "
              f"{rows[-1]['spread_plain_pct']:.1f}% without", file=sys.stderr)
    seconds = time.perf_counter() - started
    if args.sheet:
        from kpd.viewer.pictures import render_sheet

        meshes = [read_mesh(f.path) for f in tests[:12]]
        render_sheet(meshes, args.sheet, keypoints=[model.keypoints(m, seed=0) for m in meshes],
                     titles=[f.name[:22] for f in tests[:12]], columns=4, up=(model.up or "+z").lstrip("+"),
                     cell=2.6, title=f"keypoints of held-out shoes ({args.model}, K={model.num_keypoints})")
    scan = np.array([r["spread_scan_pct"] for r in rows])
    plain = np.array([r["spread_plain_pct"] for r in rows])
    settled_spread = np.array([r["spread_settled_pct"] for r in rows])
    distances = np.concatenate([r["outer_surface_distance"] for r in rows])
    result = {"benchmark": "shoes", "model": args.model, "split_file": args.split_file, "test_shapes": len(rows),
              "poses": args.poses,
              "seed": args.seed, "machine": platform.machine(), "cpus": os.cpu_count(), "load": os.getloadavg()[0],
              "scan": {"median_spread_pct": float(np.median(scan)), "share_within_3pct": float((scan <= 3).mean()),
                       "max_spread_pct": float(scan.max())},
              "scan_settled": {"median_spread_pct": float(np.median(settled_spread)),
                               "share_within_3pct": float((settled_spread <= 3).mean()),
                               "max_spread_pct": float(settled_spread.max())},
              "plain": {"median_spread_pct": float(np.median(plain)), "share_within_3pct": float((plain <= 3).mean())},
              "outer_surface_distance": {"mean": float(np.mean(distances)), "median": float(np.median(distances)),
                                         "within_0.05": float(np.mean(distances <= 0.05))},
              "seconds_per_pose": seconds / max(1, len(rows) * args.poses), "shapes": rows}
    if args.out:
        write_json(args.out, result, indent=1)
    print(json.dumps({k: v for k, v in result.items() if k != "shapes"}, indent=1))


if __name__ == "__main__":
    main()
