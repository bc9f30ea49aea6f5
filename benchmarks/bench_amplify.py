"""kpd amplify and kpd.augment on ModelNet10 chairs with the shipped chair model; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_amplify.py --out benchmarks/results/amplify.json

- **Throughput**: the first ``--shapes`` (100) training chairs x ``--variants`` (10), through
  :func:`kpd.amplify.amplify`
  in a fresh process each time: one local process, two local processes, and Ray tasks on a local cluster of two
  workers (the cluster's start timed apart from the work: a cluster outlives one run). ``--repeats`` rounds run each
  configuration once in turn; shapes per minute from the median, the Ray overhead as the median of each round's
  ratio to the two local processes, and the local runs' processor time beside their wall time.
- **Growth**: one local process on the first 10, 30 and 100 chairs: a line fitted through the times (a fixed start
  plus seconds per shape) and its largest relative residual.
- **The command**: ``kpd amplify`` itself (one process, with its contact sheet) once: wall time and peak memory.
- **Augmenter**: milliseconds per draw (median over ``--draws``; one BLAS thread) of 2,048 surface points and of a
  10,400-vertex mesh (the procedural chair at edge 0.52); peak memory of a process that opens a cache of 1,000
  rigs (every ModelNet10 chair, train and test, and the first chairs again, linked, to make up 1,000) and draws a
  point variant and a mesh variant of each.

Every figure is measured on a 2-core virtual machine shared with other work: medians, and ``machine_cpu`` and
``machine_speed`` recorded beside them.
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

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data")) / "modelnet10" / "chair"


def _collection(root: Path, count: int) -> Path:
    """The first ``count`` training chairs, linked into a folder of their own."""
    folder = root / f"chairs{count}"
    if not folder.exists():
        folder.mkdir()
        for path in sorted((DATA / "train").glob("*.ply"))[:count]:
            (folder / path.name).symlink_to(path)
    return folder


def _peak_mb() -> float:
    """This process's peak resident memory (VmHWM: of its own image, unlike ``ru_maxrss``, which keeps the peak of
    the process it was forked from across the exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _resident() -> dict:
    """Resident memory now: private (anonymous) and mapped from files (the cache's pages, shared by every process
    that maps them and given back by the kernel under pressure)."""
    fields = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(("RssAnon:", "RssFile:")):
            fields[line.split(":")[0]] = round(int(line.split()[1]) / 1024, 1)
    return {"private_mb": fields.get("RssAnon"), "file_mapped_mb": fields.get("RssFile")}


def worker(spec: dict) -> dict:
    """One amplify run in this fresh process: its seconds (and the Ray cluster's start apart)."""
    from kpd.amplify import Settings, amplify
    from kpd.bundle import manifest_checksum
    from kpd.runtime import Model

    model = Model.load("chair", threads=1)
    settings = Settings(model="chair", model_sha256=manifest_checksum(model.bundle.manifest), folder=spec["folder"],
                        variants=spec["variants"], scale=0.5, seed=0)
    cluster = 0.0
    if spec["engine"] == "ray":
        import logging

        import ray

        start = time.perf_counter()
        ray.init(num_cpus=spec["processes"], include_dashboard=False, logging_level=logging.ERROR,
                 log_to_driver=False)
        cluster = time.perf_counter() - start
    start = time.perf_counter()
    summary = amplify(settings, spec["out"], engine=spec["engine"], processes=spec["processes"])
    seconds = time.perf_counter() - start
    if spec["engine"] == "ray":
        import ray

        ray.shutdown()
    cpu = sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
              for f in ("ru_utime", "ru_stime"))
    return {"seconds": seconds, "cluster_start_s": cluster, "cpu_s": cpu, "shapes": summary.shapes,
            "failed": summary.failed,
            "typical": summary.typical, "folded_ok": summary.folded_ok, "folded_max": summary.folded_max,
            "peak_mb": _peak_mb()}


def run_worker(spec: dict) -> dict:
    out = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], capture_output=True, text=True,
                         cwd=REPO, check=False)
    if out.returncode:
        raise SystemExit(f"worker failed: {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


CONFIGS = (("local_1", "local", 1), ("local_2", "local", 2), ("ray_2", "ray", 2))


def rounds(root: Path, shapes: int, variants: int, repeats: int) -> tuple[dict, dict]:
    """``repeats`` rounds, each running every configuration once in turn (and one process on 10 and 30 shapes), so
    that the other sessions' load, which drifts over minutes, weighs on all of them alike."""
    folders = {count: _collection(root, count) for count in (10, 30, shapes)}
    plan = [(name, engine, processes, shapes) for name, engine, processes in CONFIGS]
    plan += [(f"local_1_{count}", "local", 1, count) for count in (10, 30)]
    runs: dict[str, list[dict]] = {name: [] for name, *_ in plan}
    loads = []
    for i in range(repeats):
        loads.append(round(os.getloadavg()[0], 2))
        for name, engine, processes, count in plan:
            out = root / f"out_{name}_{i}"
            runs[name].append(run_worker({"folder": str(folders[count]), "variants": variants, "engine": engine,
                                          "processes": processes, "out": str(out)}))
            subprocess.run(["rm", "-rf", str(out)], check=True)
    summary = {name: _summarise(runs[name], engine, processes, variants) for name, engine, processes, _ in plan}
    ratios = [ray["seconds"] / local["seconds"] for ray, local in zip(runs["ray_2"], runs["local_2"])]
    with_start = [(ray["seconds"] + ray["cluster_start_s"]) / local["seconds"]
                  for ray, local in zip(runs["ray_2"], runs["local_2"])]
    summary["ray_overhead_vs_local_2"] = {
        "median_of_rounds": round(statistics.median(ratios) - 1, 3), "rounds": [round(x - 1, 3) for x in ratios],
        "with_cluster_start_median": round(statistics.median(with_start) - 1, 3)}
    summary["load_average_at_round_start"] = loads
    return summary, {count: summary[f"local_1_{count}"] if count != shapes else summary["local_1"]
                     for count in (10, 30, shapes)}


def _summarise(runs: list[dict], engine: str, processes: int, variants: int) -> dict:
    seconds = statistics.median(r["seconds"] for r in runs)
    shapes = runs[0]["shapes"]
    result = {"engine": engine, "processes": processes, "shapes": shapes, "variants": variants,
              "seconds_median": round(seconds, 2), "seconds_all": [round(r["seconds"], 2) for r in runs],
              "shapes_per_minute": round(60 * shapes / seconds, 1), "failed": runs[0]["failed"],
              "variants_within_3_sigma": round(runs[0]["typical"], 4),
              "variants_at_most_half_percent_folded": round(runs[0]["folded_ok"], 4),
              "folded_worst": round(runs[0]["folded_max"], 5)}
    if engine == "ray":
        result["cluster_start_s_median"] = round(statistics.median(r["cluster_start_s"] for r in runs), 2)
    else:  # the processor time of the run and its workers: what the load of other sessions does not inflate
        cpu = statistics.median(r["cpu_s"] for r in runs)
        result["cpu_seconds_median"] = round(cpu, 2)
        result["shapes_per_cpu_minute"] = round(60 * shapes / cpu, 1)
    return result


def command_run(root: Path, folder: Path, variants: int) -> dict:
    out = root / "out_command"
    code = ("import resource, subprocess, sys, time\nstart = time.perf_counter()\n"
            f"r = subprocess.run([sys.executable, '-m', 'kpd.cli', 'amplify', 'chair', {str(folder)!r}, '--variants', "
            f"'{variants}', '--out', {str(out)!r}], capture_output=True, text=True)\n"
            "print(r.returncode, time.perf_counter() - start, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    line = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                          check=True).stdout.split()
    sheet = out / "contact_sheet.png"
    result = {"status": int(line[0]), "seconds": round(float(line[1]), 1), "peak_mb": round(int(line[2]) / 1024, 1),
              "contact_sheet": sheet.exists()}
    return result


def augment_worker(spec: dict) -> dict:
    """Draw costs (``spec['mode'] == 'draws'``) or the memory of a large cache (``'memory'``) in this process."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    from kpd.augment import Augmenter
    from kpd.benchmark import median_ms

    if spec["mode"] == "memory":
        base = _peak_mb()
        aug = Augmenter(spec["cache"])
        with threadpool_limits(1):
            for i in range(len(aug)):
                aug.points(i, seed=i)
            points = {"peak_mb": round(_peak_mb(), 1), **_resident()}
            for i in range(len(aug)):
                aug.mesh(i, seed=i)
        return {"rigs": len(aug), "peak_mb_after_imports": round(base, 1), "after_point_draws": points,
                "after_mesh_draws": {"peak_mb": round(_peak_mb(), 1), **_resident()}}
    aug = Augmenter(spec["cache"])
    big = aug.sources.index(spec["big"])
    seeds = iter(range(10**9))
    with threadpool_limits(1):
        points_ms = median_ms(lambda: aug.points(0, seed=next(seeds)), spec["draws"])
        mesh_ms = median_ms(lambda: aug.mesh(big, seed=next(seeds)), spec["draws"])
    return {"points": int(aug.points(0, seed=0).points.shape[0]), "points_ms": round(points_ms, 4),
            "mesh_vertices": int(aug.mesh(big, seed=0).points.shape[0]), "mesh_ms": round(mesh_ms, 4),
            "mesh_triangles": len(aug.triangles(big)), "keypoints": int(aug.prior.num_keypoints),
            "numpy": np.__version__}


def augmenter(root: Path, draws: int, limit: int) -> dict:
    from kpd.augment import Augmenter
    from kpd.io import write_mesh
    from kpd.procedural import procedural_chair
    from kpd.runtime import Model

    model = Model.load("chair", threads=1)
    big = root / "procedural_10k.ply"
    write_mesh(big, procedural_chair(0.52))
    small = root / "cache_draws"
    Augmenter.build(model, [*sorted((DATA / "train").glob("*.ply"))[:5], big], small, points=2048)
    draws_result = json.loads(subprocess.run(
        [sys.executable, __file__, "--augment-worker", json.dumps({"mode": "draws", "cache": str(small),
                                                                   "big": str(big), "draws": draws})],
        capture_output=True, text=True, check=True, cwd=REPO).stdout.strip().splitlines()[-1])
    everything = sorted((DATA / "train").glob("*.ply")) + sorted((DATA / "test").glob("*.ply"))
    everything = everything[:limit] if limit else everything
    large = root / "cache_1000"
    start = time.perf_counter()
    aug = Augmenter.build(model, everything, large, points=2048)
    build_s = time.perf_counter() - start
    bound = len(aug)
    disk = sum(p.stat().st_size for p in large.rglob("*.npy"))
    _fill_to(large, 1000)
    memory = json.loads(subprocess.run(
        [sys.executable, __file__, "--augment-worker", json.dumps({"mode": "memory", "cache": str(large)})],
        capture_output=True, text=True, check=True, cwd=REPO).stdout.strip().splitlines()[-1])
    return {**draws_result, "cache_build_s": round(build_s, 1), "cache_shapes_bound": bound,
            "cache_failed": len(aug.failed), "cache_disk_mb": round(disk / 2**20, 1),
            "memory_1000": memory}


def _fill_to(cache: Path, count: int) -> None:
    """Make a cache list ``count`` rigs: the first ones again, their arrays hard-linked under new keys."""
    index = json.loads((cache / "index.json").read_text())
    shapes = index["shapes"]
    for i in range(count - len(shapes)):
        entry = dict(shapes[i])
        key = f"{len(shapes):06d}"
        (cache / key).mkdir()
        for array in (cache / entry["key"]).iterdir():
            os.link(array, cache / key / array.name)
        shapes.append({**entry, "key": key})
    (cache / "index.json").write_text(json.dumps(index) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=100)
    parser.add_argument("--variants", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--draws", type=int, default=2000)
    parser.add_argument("--cache-limit", type=int, default=0, help="bind only this many chairs for the 1,000-rig "
                                                                     "cache (0: all; for a quick check)")
    parser.add_argument("--out", default=None)
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--augment-worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    if args.augment_worker:
        print(json.dumps(augment_worker(json.loads(args.augment_worker))))
        return
    from kpd.benchmark import machine_cpu, machine_speed, write_json

    result = {"benchmark": "amplify", "complete": False, "machine_cpu": machine_cpu(), "machine_speed": machine_speed(),
              "cpus": os.cpu_count(), "collection": f"ModelNet10 chair/train, first {args.shapes}",
              "variants": args.variants}

    def save() -> None:  # after each part, so that a failure late in a long run keeps what was measured
        if args.out:
            write_json(args.out, result)

    with tempfile.TemporaryDirectory(prefix="kpd-bench-amplify-") as tmp:
        root = Path(tmp)
        folder = _collection(root, args.shapes)
        result["runs"], growth = rounds(root, args.shapes, args.variants, args.repeats)
        counts = sorted(growth)
        times = [growth[c]["seconds_median"] for c in counts]
        slope, intercept = (float(v) for v in __import__("numpy").polyfit(counts, times, 1))
        residual = max(abs(t - (intercept + slope * c)) / t for c, t in zip(counts, times))
        result["growth"] = {"shapes": counts, "seconds": times, "fixed_s": round(intercept, 2),
                            "seconds_per_shape": round(slope, 3), "largest_relative_residual": round(residual, 3)}
        save()
        result["command"] = command_run(root, folder, args.variants)
        save()
        result["augmenter"] = augmenter(root, args.draws, args.cache_limit)
    result["complete"] = True
    print(json.dumps(result, indent=2))
    save()


if __name__ == "__main__":
    main()
