"""Groupwise collection alignment (kpd.collection) on the GSO shoes turned by seeded random rotations; prints ONE JSON.

    .venv/bin/python benchmarks/bench_collection.py --rounds 2 --out benchmarks/results/collection.json
    .venv/bin/python benchmarks/bench_collection.py --limit 60 --surface all --out /tmp/collection_all.json

Every shoe is sampled (5000 points, the outer surface unless ``--surface all``), turned by its own seeded random
rotation Q_i and aligned without a reference. For two decided (not flagged) shapes i, j the pairwise relative
rotation error is the angle of (E_i Q_i)(E_j Q_j)^T, E the estimated rotations: zero when both come back into one
frame. A shape counts as right when the median of its errors against the other decided shapes is at most 10 degrees.
Without an up axis kpd.collection stands the aligned shapes on the floor they share (``floor``); the same rounds
(from the state) scored without that step are in ``rotated.without_standing``.

The originals are not all in one frame themselves: the run also aligns the *unrotated* shoes (same settings), and a
shoe whose own rotation there is more than 30 degrees is counted as an original that was off. The errors are given
raw (against the known rotations alone) and corrected for those originals (the truth of shoe i is then Q_i followed
by its recovered turn); see the contact sheet of the aligned originals for the check by eye.
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

from kpd.collection import (align_collection, collection_points, find_shapes,  # noqa: E402
                            pairwise_rotation_errors)
from kpd.viewer.figures import contact_sheet  # noqa: E402
from kpd.io import read_mesh  # noqa: E402
from kpd.scan import rotation_angle  # noqa: E402
from kpd.benchmark import write_json  # noqa: E402

OFF_ANGLE = 30.0  # an original turned by more than this against the shared frame was off


def score(estimated: np.ndarray, truth: np.ndarray, ambiguous: np.ndarray) -> dict:
    decided = ~ambiguous
    errors = pairwise_rotation_errors(estimated, truth, decided)
    upper = errors[np.triu_indices(len(errors), 1)]
    per_shape = np.array([np.median(np.delete(row, i)) for i, row in enumerate(errors)]) if len(errors) > 1 else \
        np.zeros(len(errors))
    return {"decided": int(decided.sum()), "flagged": int(ambiguous.sum()), "shapes": len(ambiguous),
            "right": int((per_shape <= 10.0).sum()), "wrong": int((per_shape > 10.0).sum()),
            "right_share_of_decided": float((per_shape <= 10.0).mean()) if len(per_shape) else None,
            "pairs_within_10deg": float((upper <= 10.0).mean()) if len(upper) else None,
            "median_pair_error_deg": float(np.median(upper)) if len(upper) else None,
            "per_shape_median_error_deg": per_shape.tolist()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=os.environ.get("KPD_DATA", str(REPO.parent / "shared" / "data")))
    parser.add_argument("--limit", type=int, default=None, help="the first N shoes by name (default all)")
    parser.add_argument("--points", type=int, default=5000)
    parser.add_argument("--surface", choices=("outer", "all"), default="outer")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--original-rounds", type=int, default=2,
                        help="rounds of the alignment of the unrotated originals, which only counts those that were "
                             "off (default 2)")
    parser.add_argument("--processes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0, help="seed of the rotations (default 0)")
    parser.add_argument("--state", default="/tmp/kpd-bench-collection", help="folder of resumable state files")
    parser.add_argument("--sheet", default=None, help="also draw the rotated collection, aligned, to this PNG")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    shapes = find_shapes(Path(args.data) / "gso_shoes")[: args.limit]
    names = [n for n, _ in shapes]
    started = time.perf_counter()
    clouds = [collection_points(read_mesh(p), args.points, seed=args.seed, outer=args.surface == "outer")
              for _, p in shapes]
    sampling = time.perf_counter() - started
    truth = Rotation.random(len(clouds), random_state=args.seed).as_matrix()  # (S, 3, 3)
    turned = [c @ q.T for c, q in zip(clouds, truth)]
    state = Path(args.state)
    state.mkdir(parents=True, exist_ok=True)
    tag = f"{args.surface}_{len(clouds)}_{args.points}_{args.seed}"
    started = time.perf_counter()
    result = align_collection(turned, names, rounds=args.rounds, processes=args.processes,
                              state=state / f"rotated_{tag}.json", progress=True, seed=0)
    seconds_rotated = time.perf_counter() - started
    unstood = align_collection(turned, names, rounds=args.rounds, processes=args.processes,
                               state=state / f"rotated_{tag}.json", seed=0, stand=False)  # the same rounds, kept
    started = time.perf_counter()
    originals = align_collection(clouds, names, rounds=args.original_rounds, processes=args.processes,
                                 state=state / f"originals_{tag}.json", progress=True, seed=0)
    seconds_originals = time.perf_counter() - started
    # the shared frame of the originals is their template's own; an original turned far from it was off
    off = np.array([rotation_angle(r) > OFF_ANGLE and not s.ambiguous
                    for r, s in zip(originals.rotations, originals.shapes)])
    corrected = np.where(off[:, None, None], np.einsum("sij,skj->sik", truth, originals.rotations), truth)
    if args.sheet:
        contact_sheet(turned, result, args.sheet, up=(result.floor or {}).get("up"),
                      title=f"{len(clouds)} GSO shoes turned at random (seed {args.seed}) and aligned groupwise, "
                            f"stood on their floor: {int(result.ambiguous.sum())} flagged (red)")
    report = {
        "benchmark": "collection", "shapes": len(clouds), "points": args.points, "surface": args.surface,
        "rotation_seed": args.seed, "rounds_limit": args.rounds, "processes": args.processes,
        "machine": platform.machine(), "cpus": os.cpu_count(), "load": os.getloadavg()[0],
        "rotated": {"templates": result.templates, "changed": result.changed, "converged": result.converged,
                    "decided_by_neighbours": int(sum(s.decided_by == "neighbours" for s in result.shapes)),
                    "raw": score(result.rotations, truth, result.ambiguous),
                    "corrected_for_off_originals": score(result.rotations, corrected, result.ambiguous),
                    "floor": result.floor,
                    "without_standing": {
                        "raw": score(unstood.rotations, truth, unstood.ambiguous),
                        "corrected_for_off_originals": score(unstood.rotations, corrected, unstood.ambiguous)},
                    "seconds": seconds_rotated, "seconds_per_shape": seconds_rotated / len(clouds),
                    "seconds_per_shape_per_round": seconds_rotated / len(clouds) / len(result.templates),
                    # each shape's orientation time over the rounds, as measured when it was oriented (also by an
                    # earlier run whose state this one continued: then "seconds" above is only this run's)
                    "orientation_seconds_per_shape": float(result.seconds.mean()),
                    "orientation_seconds_per_shape_per_round": float(result.seconds.mean()) / len(result.templates)},
        "originals": {"templates": originals.templates, "flagged": int(originals.ambiguous.sum()),
                      "off": int(off.sum()), "off_names": [n for n, o in zip(names, off) if o],
                      "off_angles_deg": [round(rotation_angle(r), 1) for r, o in zip(originals.rotations, off) if o],
                      "seconds": seconds_originals},
        "sampling_seconds": sampling,
        "shapes_detail": [{"name": s.name, "score": s.score, "margin": s.margin, "ambiguous": s.ambiguous,
                           "decided_by": s.decided_by, "tilt": s.tilt if np.isfinite(s.tilt) else None,
                           "runner_up_angle": s.runner_up_angle if np.isfinite(s.runner_up_angle) else None}
                          for s in result.shapes],
    }
    if args.out:
        write_json(args.out, report, indent=1)
    brief = {k: v for k, v in report.items() if k != "shapes_detail"}

    def strip(d: dict) -> dict:
        return {k: v for k, v in d.items() if k != "per_shape_median_error_deg"}

    rotated = dict(report["rotated"])
    for key in ("raw", "corrected_for_off_originals"):
        rotated[key] = strip(rotated[key])
    rotated["without_standing"] = {k: strip(v) for k, v in rotated["without_standing"].items()}
    brief["rotated"] = rotated
    print(json.dumps(brief, indent=1))


if __name__ == "__main__":
    main()
