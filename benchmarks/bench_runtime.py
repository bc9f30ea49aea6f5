"""Speed of the deployment path; prints one JSON object.

1. Keypoints + influence for one 1024-point shape: onnxruntime (the bundle's two graphs) next to torch (the same
   networks) in the same process, same thread count, median of many warm runs. Target: onnxruntime faster.
2. ``model.rig(mesh)`` + one edit (``rig.deform``) on a 10k-vertex mesh, warm. Target <= 150 ms.
3. ``kpd deform MODEL MESH --move ... --out ...`` end to end in a fresh process (Python start, imports including
   Open3D, bundle validation, sessions, rig, write). Target <= 3 s.

The model is the shipped chair bundle with the torch networks from ``--run`` (its training run) when given; without a
run, a K=12 network with the authors' initialisation is exported to a temporary bundle (speed does not depend on the
weights). Usage: ``python benchmarks/bench_runtime.py [--run RUN --model chair] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from kpd.benchmark import median_ms


def solo_ms(side: str, bundle, run: str | None, threads: int, repeats: int) -> float:
    """Median milliseconds of keypoints + influence for one 1024-point cloud, measured in a fresh process."""
    argv = [sys.executable, __file__, "--solo", side, "--model", str(bundle), "--threads", str(threads),
            "--repeats", str(repeats)] + (["--run", run] if run else [])
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{side} timing failed: {done.stderr}")
    return float(done.stdout.strip().splitlines()[-1])


def solo(side: str, bundle: str, run: str | None, threads: int, repeats: int) -> float:
    cloud = np.random.default_rng(0).uniform(-1, 1, (1, 1024, 3)).astype(np.float32)
    if side == "torch":
        import torch

        torch.set_num_threads(threads)
        net, _ = torch_network(run)
        tensor = torch.from_numpy(cloud)

        def call():
            with torch.inference_mode():
                net.keypoints(tensor)
                net.influence_offset(tensor)
    else:
        from kpd.runtime import Model

        model = Model.load(bundle, threads=threads)

        def call():
            model.run(cloud)
    return median_ms(call, repeats, warmup=30)


def torch_network(run: str | None):
    """The torch networks (from a run, or freshly initialised K=12) and where they came from."""
    import torch

    from kpd.cage import icosphere
    from kpd.train.nets import KeypointDeformer, ModelConfig

    if run is not None:
        from kpd.export.build import model_from_checkpoint
        from kpd.train.trainer import load_checkpoint

        return model_from_checkpoint(load_checkpoint(run)), f"run {run}"
    cage = icosphere(1, 1.4)
    config = ModelConfig(keypoints=12, cage_vertices=42, cage_faces=80, m=5)
    net = KeypointDeformer(config, torch.from_numpy(cage.vertices), torch.from_numpy(cage.faces))
    return net.eval(), "K=12 network, authors' initialisation"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default=None, help="training run of the bundle (torch side of the comparison)")
    parser.add_argument("--model", default=None, help="bundle (default: exported from --run, or a fresh K=12 net)")
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--solo", choices=("onnxruntime", "torch"), default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.solo is not None:
        print(solo(args.solo, args.model, args.run, args.threads, args.repeats))
        return

    import torch

    from kpd.procedural import procedural_chair
    from kpd.export.build import export_model, synthetic_clouds
    from kpd.io import write_mesh
    from kpd.runtime import Model

    torch.set_num_threads(args.threads)
    result: dict = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "threads": args.threads,
                                "torch": torch.__version__}}
    net, source = torch_network(args.run)
    with tempfile.TemporaryDirectory(prefix="kpd-bench-") as tmp:
        tmp = Path(tmp)
        bundle = args.model
        if bundle is None:
            bundle = export_model(net, tmp / "bench.kpd", category="chair", point_count=1024,
                                  parity_points=synthetic_clouds(2, 1024)).path
        model = Model.load(bundle, threads=args.threads)
        result["model"] = {"bundle": str(bundle), "torch": source, "K": model.num_keypoints,
                           "C": model.num_cage_vertices}
        mesh = procedural_chair(edge=0.52)  # 10,400 vertices, 18,200 triangles

        # each side in its own fresh process, one after the other, so neither's worker threads (torch's OpenMP
        # threads keep spinning after a call) slow the other down
        comparison = {}
        for threads in sorted({1, args.threads}):
            ort_ms = solo_ms("onnxruntime", bundle, args.run, threads, args.repeats)
            torch_ms = solo_ms("torch", bundle, args.run, threads, args.repeats)
            comparison[f"threads_{threads}"] = {"onnxruntime_ms": round(ort_ms, 3), "torch_ms": round(torch_ms, 3),
                                                "speedup": round(torch_ms / ort_ms, 2)}
        result["keypoints_influence_1024"] = {
            **comparison, "target": "onnxruntime faster than torch",
            "met": {k: v["onnxruntime_ms"] < v["torch_ms"] for k, v in comparison.items()},
        }

        def rig_and_edit():
            rig = model.rig(mesh)
            keypoints = rig.keypoints
            keypoints[0] += [0.0, 0.0, 1.0]
            rig.deform(keypoints)

        rig = model.rig(mesh)
        stages = {}
        start = time.perf_counter()
        prediction = model.predict(mesh)
        stages["predict_ms"] = 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
        model.rig(mesh, prediction=prediction)
        stages["cage_mvc_bind_ms"] = 1000 * (time.perf_counter() - start)
        edited = rig.keypoints
        edited[0] += [0.0, 0.0, 1.0]
        out = np.empty_like(mesh.vertices)
        edit_ms = median_ms(lambda: rig.deform(edited, out=out), args.repeats)
        rig_ms = median_ms(rig_and_edit, 20, warmup=2)
        result["rig_and_edit_10k"] = {
            "vertices": len(mesh.vertices), "rig_plus_edit_ms": round(rig_ms, 1),
            "stages_ms": {k: round(v, 1) for k, v in stages.items()}, "edit_only_ms": round(edit_ms, 3),
            "target_ms": 150, "met": rig_ms <= 150,
        }

        mesh_file = tmp / "chair.ply"
        write_mesh(mesh_file, mesh)
        command = [str(Path(sys.executable).with_name("kpd")), "deform", str(bundle), str(mesh_file), "--move",
                   "0:0,0,2", "--out", str(tmp / "out.ply"), "--force"]
        walls, cpus = [], []
        for _ in range(3):
            before = os.times()
            start = time.perf_counter()
            done = subprocess.run(command, capture_output=True, text=True)
            walls.append(time.perf_counter() - start)
            after = os.times()
            cpus.append((after.children_user - before.children_user) + (after.children_system - before.children_system))
            if done.returncode != 0:
                raise SystemExit(f"kpd deform failed: {done.stderr}")
        result["kpd_deform_fresh_process"] = {
            "vertices": len(mesh.vertices), "wall_s": [round(w, 2) for w in walls],
            "median_wall_s": round(statistics.median(walls), 2), "median_cpu_s": round(statistics.median(cpus), 2),
            "target_s": 3.0, "met": statistics.median(walls) <= 3.0,
        }
    load = os.getloadavg()
    result["machine"]["load_average_1min"] = round(load[0], 2)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
