"""Data-parallel equivalence at full size: 2 gloo ranks (torchrun, DistributedDataParallel) against one process.

The recipe of the shipped chair model (K = 12, batch 16, 1024 points, 4 samples per shape) on the first 64 ModelNet10
training chairs, 8 more validating, for ``--iterations`` (default 100, the first 20 warm-up): once in this process
and once under ``torchrun --standalone --nproc_per_node 2`` (8 pairs per rank, one thread each; this script's
``--worker`` mode builds the same :class:`kpd.train.trainer.Trainer` with the torchrun world, as ``kpd train`` does).
Both pairs of runs are made in float32 (how kpd trains) and in float64: the two are one computation in a different
order, so their gap is rounding carried along by training; a gap that shrinks by orders of magnitude in float64 is
rounding, one that stays would be a difference in what the ranks compute. Reported per precision: the loss curves'
largest and median relative differences, the validation chamfer, and each weight tensor's difference relative to
how far training moved it from the common initial weights. Prints one JSON object.

    python benchmarks/bench_distributed.py [--iterations 100] [--shapes 64]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data")) / "modelnet10" / "chair" / "train"


def prepared(args, world=None):
    """The benchmark's data and recipe (rank 0 samples missing meshes first, as kpd train does)."""
    from kpd.data import SampleSettings, prepare
    from kpd.train import distributed
    from kpd.train.trainer import TrainConfig

    root = DATA
    files = sorted(root.glob("*.ply"))[:args.shapes + 8]
    split = Path(args.split)
    if world is None:
        split.write_text(json.dumps({"train": [f.stem for f in files[:args.shapes]],
                                     "val": [f.stem for f in files[args.shapes:]]}))
    data = distributed.in_turn(world, lambda: prepare(root, None, settings=SampleSettings(), split_file=split,
                                                      processes=1, progress=False))
    config = TrainConfig(keypoints=12, batch=16, iterations=args.iterations, warmup=args.warmup,
                         save_every=args.iterations, val_pairs=32)
    return data, config


def run(args, out: Path, world=None) -> None:
    """Train ``args.iterations`` in ``args.dtype`` into ``out`` (rank 0 writes the checkpoint)."""
    import torch

    from kpd.train.trainer import Trainer

    torch.set_num_threads(1)
    data, config = prepared(args, world)
    trainer = Trainer(config, data, out, device="cpu", command="bench_distributed", world=world)
    if args.dtype == "float64":  # before the first step: the optimisers hold the same parameters, no state yet
        trainer.model.double()
        for name in ("train_set", "val_set"):
            setattr(trainer, name, {k: v.double() if v.is_floating_point() else v
                                    for k, v in getattr(trainer, name).items()})
    trainer.run(progress=False)


def worker(args) -> int:
    from kpd.train import distributed

    world = distributed.from_environment(16, "cpu")
    distributed.init(world)
    try:
        run(args, Path(args.worker), world)
    finally:
        distributed.shutdown()
    return 0


def compare(one: dict, two: dict) -> dict:
    """How far apart two checkpoints of the same recipe ended."""
    from kpd.train.nets import KeypointDeformer, ModelConfig

    h1, h2 = one["history"]["train"].numpy(), two["history"]["train"].numpy()
    curve = {}
    for j, name in enumerate(("loss", "sim", "kpt", "inf"), 1):
        ok = ~np.isnan(h1[:, j])
        rel = np.abs(h2[ok, j] - h1[ok, j]) / np.abs(h1[ok, j])
        curve[name] = {"max": float(rel.max()), "median": float(np.median(rel)), "iterations": int(ok.sum())}
    states = one["states"]
    init = KeypointDeformer(ModelConfig.from_dict(one["model_config"]), states["template_vertices"][0].T.float(),
                            states["template_faces"][0], seed=0).state_dict()
    weights = {}
    for name, value in states.items():
        if not name.startswith("template"):
            moved = float((value.double() - init[name].double()).norm())
            weights[name] = float((two["states"][name].double() - value.double()).norm()) / moved
    v1, v2 = one["history"]["val"].numpy()[-1, 1], two["history"]["val"].numpy()[-1, 1]
    return {
        "loss_curve_relative_difference": curve,
        "val_chamfer": {"one_process": float(v1), "two_gloo_ranks": float(v2),
                        "relative_difference": float(abs(v2 - v1) / v1)},
        "weights_difference_over_motion_max": {g: max(v for k, v in weights.items() if k.startswith(g))
                                               for g in ("keypoint_predictor", "influence_predictor",
                                                         "influence_param")},
        "weights_difference_over_motion": weights,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--shapes", type=int, default=64, help="training chairs (8 more validate)")
    parser.add_argument("--dtypes", default="float32,float64")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--dtype", default="float32", help=argparse.SUPPRESS)
    parser.add_argument("--split", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)

    import torch

    from kpd.train.trainer import load_checkpoint

    results, seconds = {}, {}
    source = str(DATA)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        args.split = str(tmp / "split.json")
        for dtype in args.dtypes.split(","):
            args.dtype = dtype
            start = time.perf_counter()
            run(args, tmp / f"one_{dtype}")
            seconds[f"one_process_{dtype}"] = round(time.perf_counter() - start, 1)
            command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                       __file__, "--worker", str(tmp / f"two_{dtype}"), "--dtype", dtype, "--split", args.split,
                       "--iterations", str(args.iterations), "--warmup", str(args.warmup), "--shapes", str(args.shapes)]
            start = time.perf_counter()
            done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
            if done.returncode != 0:
                raise SystemExit(f"bench_distributed: the 2-rank run failed:\n{done.stderr[-3000:]}")
            seconds[f"two_gloo_ranks_{dtype}"] = round(time.perf_counter() - start, 1)
            one, two = load_checkpoint(tmp / f"one_{dtype}"), load_checkpoint(tmp / f"two_{dtype}")
            assert two["world_sizes"] == [[0, 2]] and one["world_sizes"] == [[0, 1]]
            results[dtype] = compare(one, two)
    print(json.dumps({
        "benchmark": "distributed_equivalence",
        "data": source,
        "shapes": {"train": args.shapes, "val": 8},
        "iterations": args.iterations,
        "warmup": args.warmup,
        "batch": 16,
        "by_precision": results,
        "seconds": seconds,
        "torch": torch.__version__,
        "cpu_count": os.cpu_count(),
        "load_average": [round(v, 2) for v in os.getloadavg()],
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
