"""kpd bench: how fast the deployment path runs on this machine (torch-free)."""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

from kpd.benchmark import best_seconds, median_ms, write_json  # noqa: F401  (importable from here as before)
from kpd.commands import integer

HELP = "measure the deployment path on this machine: model load, keypoints + influence, rig binding, one edit"
EXAMPLE = "kpd bench chair --vertices 10000 100000 --out bench.json    (or: kpd bench chair --mesh my_chair.obj)"

# grid spacing of the procedural chair (kpd demo's shape) per vertex count: vertices ~ 2,812 / spacing^2
_CHAIR_VERTICES_PER_INVERSE_SQUARE = 2812.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_model_arguments

    add_model_arguments(parser, default="chair")
    parser.add_argument("--mesh", default=None, help="time your own mesh instead of procedural chairs")
    parser.add_argument("--vertices", type=integer(1_000, 2_000_000), nargs="+", default=[10_000, 100_000], metavar="V",
                        help="procedural chair sizes to time, in mesh vertices (default: 10000 100000)")
    parser.add_argument("--repeats", type=integer(1), default=200, help="timed calls per measurement (median reported)")
    parser.add_argument("--out", default=None, help="also write the results as JSON")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def _meshes(args: argparse.Namespace):
    from kpd.io import read_mesh
    from kpd.procedural import procedural_chair

    if args.mesh is not None:
        yield args.mesh, read_mesh(args.mesh)
        return
    for count in args.vertices:
        spacing = (_CHAIR_VERTICES_PER_INVERSE_SQUARE / count) ** 0.5
        mesh = procedural_chair(edge=spacing)
        spacing *= (len(mesh.vertices) / count) ** 0.5  # one correction: the boxes' grids round their cell counts
        yield "procedural chair", procedural_chair(edge=spacing)


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from kpd.io import Outputs
    from kpd.runtime import Model

    outputs = Outputs(force=args.force, inputs=(args.mesh,))
    out = outputs.file(args.out, "--out", formats=(".json",), what="JSON") if args.out else None

    start = time.perf_counter()
    model = Model.load(args.model, threads=args.threads)
    load_ms = 1000 * (time.perf_counter() - start)
    cloud = np.random.default_rng(args.seed).uniform(-1, 1, (1, model.point_count, 3)).astype(np.float32)
    networks_ms = median_ms(lambda: model.run(cloud), args.repeats, warmup=10)
    result = {
        "model": str(args.model), "category": model.category, "K": model.num_keypoints, "C": model.num_cage_vertices,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                    "load_average_1min": round(os.getloadavg()[0], 2)},
        "load_ms": round(load_ms, 1),
        f"keypoints_influence_{model.point_count}_points_ms": round(networks_ms, 3),
        "meshes": [],
    }
    meshes = list(_meshes(args))
    # on a terminal only (disable=None): a pipe or a log would keep the bar's redraws before an error's one line
    for name, mesh in tqdm(meshes, desc="meshes", unit="mesh", leave=False, disable=None):
        start = time.perf_counter()
        prediction = model.predict(mesh, seed=args.seed)
        predict_ms = 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
        rig = model.rig(mesh, prediction=prediction)
        bind_ms = 1000 * (time.perf_counter() - start)
        edited = rig.keypoints
        edited[0] += 0.05 * np.ptp(mesh.vertices, axis=0).max()
        buffer = np.empty_like(mesh.vertices)
        edit_ms = median_ms(lambda: rig.deform(edited, out=buffer), args.repeats, warmup=10)
        result["meshes"].append({"mesh": name, "vertices": len(mesh.vertices), "predict_ms": round(predict_ms, 1),
                                 "bind_ms": round(bind_ms, 1), "edit_ms": round(edit_ms, 3)})

    print(f"{args.model} (K={result['K']}, C={result['C']}) on {result['machine']['cpus']} CPUs, "
          f"load {result['machine']['load_average_1min']}")
    print(f"  load bundle                        {load_ms:9.1f} ms")
    print(f"  keypoints + influence ({model.point_count} points) {networks_ms:9.3f} ms")
    for row in result["meshes"]:
        print(f"  {row['mesh']} ({row['vertices']} vertices): predict {row['predict_ms']:.1f} ms, "
              f"bind {row['bind_ms']:.1f} ms, one edit {row['edit_ms']:.3f} ms")
    if out is not None:
        with outputs:
            outputs.stage(out).write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {out}")
    return 0
