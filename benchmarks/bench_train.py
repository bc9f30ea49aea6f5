"""Training speed: one full iteration vs the bare forward+backward of Φ and Γ, measured in the same run.

Batch 16, 1024 points, K = 12, past the warm-up (full loss, both optimisers). Uses 64 real ModelNet10 chairs from the
sample cache ($KPD_DATA or ../shared/data; sampled into the cache first if needed), or synthetic shapes when the data
is absent. Each round measures, in turn, the bare networks and the iteration with 1 and with 2 threads in this
process, then the iteration with DistributedDataParallel over 2 gloo ranks of one thread each (``torchrun
--standalone``, this script's ``--worker`` mode: the same code path as ``torchrun ... kpd train``); medians over the
rounds are reported, so load from other processes affects every configuration alike. Peak memory: the process's
peak resident set (CPU; each rank's for DDP) or ``torch.cuda.max_memory_allocated`` (CUDA).

``--device cuda`` (a machine with a GPU) times the bare networks and the iteration on the GPU (synchronised around
each timed block), reports the peak GPU memory of each, checks that the step never waits for the device
(``torch.cuda.set_sync_debug_mode("error")``), and with 2 or more GPUs adds DDP over 2 GPUs (NCCL). Prints one JSON
object.

    python benchmarks/bench_train.py [--device cpu|cuda|auto] [--rounds 5] [--steps 6] [--ddp 2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BATCH, KEYPOINTS = 16, 12


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


def make_trainer(shapes: int, device: str, world=None):
    """The benchmark's Trainer (warm-up off: every step is the full loss) and the data source's name."""
    from kpd.data import Category, PreparedData
    from kpd.train.trainer import Trainer, TrainConfig

    samples, settings, source = real_data(shapes) or synthetic_data(shapes)
    data = PreparedData(category=Category(Path(source), "benchmark", "chair"), settings=settings,
                        cache_dir=Path(tempfile.gettempdir()), samples={"train": samples}, skipped=[])
    config = TrainConfig(keypoints=KEYPOINTS, batch=BATCH, warmup=0, iterations=10**6, val_pairs=0)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, data, tmp, device=device, command="bench", world=world)
    return trainer, samples, source


def peak_rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)  # Linux: KiB


class Timer:
    """Seconds per call of ``f`` over ``steps`` calls, synchronised on CUDA; peak GPU memory of those calls."""

    def __init__(self, device) -> None:
        import torch

        self.torch, self.cuda = torch, device.type == "cuda"

    def __call__(self, f, steps: int) -> tuple[float, float | None]:
        torch = self.torch
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        for _ in range(steps):
            f()
        if self.cuda:
            torch.cuda.synchronize()
        seconds = (time.perf_counter() - start) / steps
        peak = round(torch.cuda.max_memory_allocated() / 2**20, 1) if self.cuda else None
        return seconds, peak


def worker(args) -> int:
    """One rank of the DDP measurement (under torchrun): warm up, time ``--steps`` iterations, rank 0 writes JSON."""
    import torch

    from kpd.train import distributed

    world = distributed.from_environment(BATCH, args.device)
    torch.set_num_threads(1)
    distributed.init(world)
    try:
        trainer, _, _ = make_trainer(args.shapes, args.device, world)
        timer = Timer(trainer.device)
        t = 0

        def iteration() -> None:
            nonlocal t
            trainer.step(t)
            t += 1

        for _ in range(2):
            iteration()
        distributed.barrier(world)
        seconds, peak = timer(iteration, args.steps)
        distributed.barrier(world)  # the slowest rank counts
        rss = torch.tensor([peak_rss_mb()], device=trainer.device)
        gathered = [torch.zeros_like(rss) for _ in range(world.size)]
        torch.distributed.all_gather(gathered, rss)
        if world.main:
            Path(args.worker).write_text(json.dumps({
                "seconds": seconds, "peak_gpu_mb": peak, "peak_rss_mb_per_rank": [round(float(g), 1) for g in gathered],
                "ranks": world.size, "backend": world.backend}))
    finally:
        distributed.shutdown()
    return 0


def ddp_round(args, ranks: int) -> dict:
    """Launch ``ranks`` processes with torchrun on this machine and return rank 0's measurement."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "ddp.json"
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(ranks),
                   __file__, "--worker", str(out), "--device", args.device, "--steps", str(args.steps),
                   "--shapes", str(args.shapes)]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        done = subprocess.run(command, capture_output=True, text=True, env=env)
        if done.returncode != 0:
            raise SystemExit(f"bench_train: the DDP round failed:\n{done.stderr[-3000:]}")
        return json.loads(out.read_text())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu (default), cuda or auto")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=6, help="timed iterations per round and configuration")
    parser.add_argument("--shapes", type=int, default=64)
    parser.add_argument("--threads", default="1,2", help="CPU thread counts measured in this process (default 1,2)")
    parser.add_argument("--ddp", type=int, default=2,
                        help="ranks of the DDP measurement (one thread, or one GPU, each; 0 = none)")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)

    import torch

    from kpd.train.trainer import resolve_device

    device = resolve_device(args.device)
    args.device = device.type
    cuda = device.type == "cuda"
    threads = [1] if cuda else [int(n) for n in args.threads.split(",")]
    ddp = args.ddp if not cuda or torch.cuda.device_count() >= args.ddp else 0
    torch.set_num_threads(threads[0])
    trainer, samples, source = make_trainer(args.shapes, args.device)
    rss_data = peak_rss_mb()
    model = trainer.model
    idx = trainer.batch_indices(0)
    x = torch.from_numpy(samples.points[np.concatenate([idx["source"], idx["target"]]), 0]).to(device)  # (2B, N, 3)
    timer = Timer(device)

    def bare() -> None:
        keypoints = model.keypoint_predictor(x)  # Φ on source and target
        offset = model.influence_predictor(x[:BATCH])  # Γ on the source
        model.zero_grad(set_to_none=True)
        (keypoints.sum() + offset.sum()).backward()

    t = 0

    def iteration() -> None:
        nonlocal t
        trainer.step(t)
        t += 1

    times: dict[str, list[float]] = {}
    peaks: dict[str, float] = {}
    ddp_runs: list[dict] = []
    for _ in range(args.rounds):
        for n in threads:
            torch.set_num_threads(n)
            for name, f in ((f"bare_{n}t", bare), (f"iteration_{n}t", iteration)):
                f()  # warm the thread pool and allocators
                seconds, peak = timer(f, args.steps)
                times.setdefault(name, []).append(seconds)
                if peak is not None:
                    peaks[name] = max(peaks.get(name, 0.0), peak)
        if ddp:
            ddp_runs.append(ddp_round(args, ddp))
            times.setdefault(f"iteration_ddp{ddp}", []).append(ddp_runs[-1]["seconds"])
    syncs = None
    if cuda:  # does the step wait for the device anywhere?
        torch.cuda.set_sync_debug_mode("error")
        try:
            for _ in range(3):
                iteration()
            syncs = "none"
        except RuntimeError as exc:
            syncs = str(exc).splitlines()[0]
        finally:
            torch.cuda.set_sync_debug_mode(0)
    med = {k: statistics.median(v) for k, v in times.items()}
    configs: dict[str, dict] = {}
    for n in threads:
        it, b = med[f"iteration_{n}t"], med[f"bare_{n}t"]
        key = "gpu" if cuda else f"{n} thread{'s' if n > 1 else ''}"
        configs[key] = {"iteration_seconds": round(it, 4), "bare_phi_gamma_fwd_bwd_seconds": round(b, 4),
                        "ratio_to_bare": round(it / b, 3)}
        if cuda:
            configs[key].update({"peak_gpu_mb_iteration": peaks[f"iteration_{n}t"],
                                 "peak_gpu_mb_bare": peaks[f"bare_{n}t"], "step_synchronizes": syncs})
    if ddp:
        it = med[f"iteration_ddp{ddp}"]
        key = f"{ddp} {'GPUs (nccl)' if cuda else 'gloo processes x 1 thread'}"
        configs[key] = {"iteration_seconds": round(it, 4), "pairs_per_rank": BATCH // ddp}
        for n in threads:
            name = "gpu" if cuda else f"{n}_thread{'s' if n > 1 else ''}"
            configs[key][f"ratio_to_bare_{name}"] = round(it / med[f"bare_{n}t"], 3)
        if cuda:
            configs[key]["peak_gpu_mb_rank0"] = max(r["peak_gpu_mb"] for r in ddp_runs)
        else:
            configs[key]["peak_rss_mb_per_rank"] = [max(r["peak_rss_mb_per_rank"][i] for r in ddp_runs)
                                                    for i in range(ddp)]
    first = med[f"iteration_{threads[0]}t"]
    result = {
        "benchmark": "train_iteration",
        "device": str(device),
        "data": source,
        "batch": BATCH,
        "points": int(samples.points.shape[2]),
        "keypoints": KEYPOINTS,
        # the single-thread (or GPU) figures, as before
        "iteration_seconds": round(first, 4),
        "bare_phi_gamma_fwd_bwd_seconds": round(med[f"bare_{threads[0]}t"], 4),
        "ratio": round(first / med[f"bare_{threads[0]}t"], 3),
        "projected_2000_iterations_minutes": round(2000 * first / 60, 1),
        "configs": configs,
        "speedup_over_first": {k: round(first / v["iteration_seconds"], 3) for k, v in configs.items()},
        "peak_rss_mb": {"data_loaded": rss_data, "after_steps": peak_rss_mb()},
        "rounds": {k: [round(v, 4) for v in vs] for k, vs in times.items()},
        "torch": torch.__version__,
        "gpu": torch.cuda.get_device_name(device) if cuda else None,
        "cpu_count": os.cpu_count(),
        "load_average": [round(v, 2) for v in os.getloadavg()],
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
