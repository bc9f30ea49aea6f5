"""Training speed: one full iteration vs the bare forward+backward of Φ and Γ, measured in the same run.

Batch 16, 1024 points, K = 12, past the warm-up (full loss, both optimisers). Uses 64 real ModelNet10 chairs from the
sample cache ($KPD_DATA or ../shared/data; sampled into the cache first if needed), or synthetic shapes when the data
is absent. The two measurements alternate in rounds and the medians are reported, so load from other processes
affects both alike. Prints one JSON object.

    python benchmarks/bench_train.py [--threads N] [--rounds 5] [--steps 6]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def real_data(count: int):
    from kpd.data import SampleSettings, discover, ingest, load_samples

    root = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data")) / "modelnet10"
    if not (root / "chair").is_dir():
        return None
    settings = SampleSettings()
    category = discover(root, "chair")
    done = ingest(category.splits["train"][:count], settings, processes=2, progress=False)
    return load_samples(done.entries, settings), settings, str(root)


def synthetic_data(count: int):
    """Random boxes-with-legs point clouds with their cages and MVC weights (no files)."""
    from kpd.cage import fit_cage, icosphere
    from kpd.data import SampleSettings, ShapeSamples
    from kpd.mvc import mvc_weights

    settings = SampleSettings(samples=1)
    rng = np.random.default_rng(0)
    template = icosphere(1, 1.4)
    n = settings.points
    points = np.empty((count, 1, n, 3), np.float32)
    cages = np.empty((count, 1, 42, 3), np.float32)
    weights = np.empty((count, 1, n, 42), np.float32)
    for i in range(count):
        p = rng.uniform(-1, 1, size=(n, 3)) * rng.uniform(0.3, 1.0, size=3)
        p /= np.abs(p).max()
        cage = fit_cage(p, template=template)
        points[i, 0], cages[i, 0], weights[i, 0] = p, cage.vertices, mvc_weights(p, cage.vertices, cage.faces)
    samples = ShapeSamples(names=[f"synthetic{i}" for i in range(count)], paths=[""] * count, points=points,
                           normals=np.zeros_like(points), cage_vertices=cages, cage_faces=template.faces,
                           weights=weights, centers=np.zeros((count, 3)), scales=np.ones(count))
    return samples, settings, "synthetic"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=6, help="timed iterations per round and method")
    parser.add_argument("--shapes", type=int, default=64)
    args = parser.parse_args(argv)

    import torch

    from kpd.data import Category, PreparedData
    from kpd.train.trainer import Trainer, TrainConfig

    threads = args.threads or os.cpu_count() or 1
    torch.set_num_threads(threads)
    loaded = real_data(args.shapes) or synthetic_data(args.shapes)
    samples, settings, source = loaded
    data = PreparedData(category=Category(Path(source), "benchmark", "chair"), settings=settings,
                        cache_dir=Path(tempfile.gettempdir()), samples={"train": samples}, skipped=[])
    config = TrainConfig(keypoints=12, batch=16, warmup=0, iterations=10**6, val_pairs=0)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, data, tmp, device="cpu", command="bench")
    model = trainer.model
    b = config.batch
    idx = trainer.batch_indices(0)
    x = torch.from_numpy(samples.points[np.concatenate([idx["source"], idx["target"]]), 0])  # (2B, N, 3)

    def bare() -> None:
        keypoints = model.keypoint_predictor(x)  # Φ on source and target
        offset = model.influence_predictor(x[:b])  # Γ on the source
        model.zero_grad(set_to_none=True)
        (keypoints.sum() + offset.sum()).backward()

    t = 0

    def iteration() -> None:
        nonlocal t
        trainer.step(t)
        t += 1

    for f in (iteration, bare, iteration, bare):  # warm up allocators and threads
        f()
    times: dict[str, list[float]] = {"iteration": [], "bare": []}
    for _ in range(args.rounds):
        for name, f in (("iteration", iteration), ("bare", bare)):
            start = time.perf_counter()
            for _ in range(args.steps):
                f()
            times[name].append((time.perf_counter() - start) / args.steps)
    it, bare_s = statistics.median(times["iteration"]), statistics.median(times["bare"])
    result = {
        "benchmark": "train_iteration",
        "data": source,
        "batch": b,
        "points": int(samples.points.shape[2]),
        "keypoints": 12,
        "iteration_seconds": round(it, 4),
        "bare_phi_gamma_fwd_bwd_seconds": round(bare_s, 4),
        "ratio": round(it / bare_s, 3),
        "projected_2000_iterations_minutes": round(2000 * it / 60, 1),
        "rounds": {k: [round(v, 4) for v in vs] for k, vs in times.items()},
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average": [round(v, 2) for v in os.getloadavg()],
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
