"""Binding, editing, saving and loading rigs of scan-sized meshes; prints one JSON object.

Two real meshes, each subdivided with Open3D's ``subdivide_midpoint`` to about 85k, 330k and 1.3M vertices:

* ``scan``: the real sneaker scan of the shared data folder (``scans/sneaker.ply``, 22,043 vertices, 39,326
  triangles, 2.4% of them slivers) subdivided 1, 2 and 3 times (83k, 324k and 1.28M vertices), rigged with the
  shipped shoe model: what a user's dense scan looks like.
* ``chair``: a real ShapeNet chair (KeypointNet's ``fe6b3c001a86d844d5767a0de8dd037e``, 5,358 vertices and 21,504
  triangles, each stored twice) subdivided 2, 3 and 4 times (86k, 343k and 1.37M vertices), rigged with the shipped
  chair model: a CAD mesh stays full of slivers when subdivided (3.5M of its 5.5M triangles at 1.37M vertices), so
  the straightening of slivers has its most work here.

Each size runs in fresh subprocesses:

1. ``peak``: load the model, read the mesh, ``Model.rig`` once, one edit; peak resident memory
   (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) of that process. Target at 1.3M: <= 1.5 GB.
2. ``time``: ``Model.rig(mesh)`` as a user calls it (prediction included) and the binding alone for a given
   prediction, with and without straightening, best of a few repeats, in wall and in CPU seconds (both threads
   counted); its parts (the prediction, the MVC basis through the compiled kernel alone, the straightening alone);
   one edit ``rig.deform(keypoints, out=buffer)`` moving one keypoint (a drag), median of many, and one moving
   every keypoint; ``Rig.save`` and ``Rig.load`` of the rig and the file's size. Targets: ``Model.rig`` <= 0.3 s at
   100k, <= 1 s at 330k, <= 3 s at 1.3M; time(1.3M) /
   time(330k) <= 4.4; one edit at 1.3M <= 15 ms; a saved rig loads in <= 1 s.
3. The ``time`` run again beside one busy CPU-bound process (``--busy``).
4. ``kpd deform`` and ``kpd render`` end to end at the largest size (``--cli``), wall time of the command, and for
   the scan also with ``--scan`` (cleaned, oriented and normalised first). Target: <= 6 s each.

Usage: ``.venv/bin/python benchmarks/bench_scale.py --busy --cli > benchmarks/results/scale.json``
(``--meshes scan --levels 1,2`` for a quicker run).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KPD_DATA", ROOT.parent / "shared" / "data"))
MESHES = {  # name: (file, shipped model, subdivision levels of ~85k, ~330k and ~1.3M vertices)
    "scan": (DATA / "scans" / "sneaker.ply", "shoe", (1, 2, 3)),
    "chair": (DATA / "keypointnet" / "models" / "03001627" / "fe6b3c001a86d844d5767a0de8dd037e" / "model.obj",
              "chair", (2, 3, 4)),
}


def subdivided(source: Path, levels: list[int], folder: Path) -> dict[int, Path]:
    """``source`` subdivided ``level`` times, written to ``folder`` as binary PLY."""
    import open3d as o3d

    from kpd.io import Mesh, read_mesh, write_mesh

    mesh = read_mesh(source)
    base = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                     o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    paths = {}
    for level in levels:
        fine = base.subdivide_midpoint(level)
        path = folder / f"{source.parent.name}_{source.stem}_x{level}.ply"
        write_mesh(path, Mesh(vertices=np.asarray(fine.vertices), triangles=np.asarray(fine.triangles, np.int64)))
        paths[level] = path
    return paths


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kilobytes


def edited_keypoints(rig) -> np.ndarray:
    keypoints = rig.keypoints
    keypoints[0] += 0.1 * rig.normalizer.scale_  # one keypoint moved by 5% of the box
    return keypoints


def child_peak(name: str, path: str) -> dict:
    from kpd.io import read_mesh
    from kpd.runtime import Model

    start = time.perf_counter()
    model = Model.load(name)
    mesh = read_mesh(path)
    read_s = time.perf_counter() - start
    rig = model.rig(mesh)
    bound_s = time.perf_counter() - start
    rig.deform(edited_keypoints(rig))
    return {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "load_and_read_s": round(read_s, 2),
            "load_read_bind_edit_s": round(time.perf_counter() - start, 2), "bind_s": round(bound_s - read_s, 2),
            "peak_rss_mb": round(peak_rss_mb())}


def child_time(name: str, path: str, repeats: int, edits: int) -> dict:
    from kpd.io import read_mesh
    from kpd.rig import Rig, coincident_mvc_basis, straighten_basis
    from kpd.runtime import Model

    model = Model.load(name)
    mesh = read_mesh(path)
    prediction = model.predict(mesh)
    model.rig(mesh, prediction=prediction)  # warm: compiled kernels loaded, caches filled

    cpu = {}

    def best(fn, n, name=None):
        times = []
        for _ in range(n):
            start, start_cpu = time.perf_counter(), time.process_time()
            value = fn()
            times.append(time.perf_counter() - start)
            if name is not None:
                cpu[name] = min(cpu.get(name, float("inf")), time.process_time() - start_cpu)
        return min(times), value

    rig_s, rig = best(lambda: model.rig(mesh), repeats, "model_rig_cpu_s")
    plain_s, _ = best(lambda: model.rig(mesh, straighten=False), repeats, "model_rig_without_straightening_cpu_s")
    bind_s, _ = best(lambda: model.rig(mesh, prediction=prediction), repeats, "bind_cpu_s")
    predict_s, _ = best(lambda: model.predict(mesh), repeats)
    vertices = rig.normalizer.apply(mesh.vertices)
    mvc_s, basis = best(lambda: coincident_mvc_basis(vertices, rig.cage, rig.influence.T), repeats, "mvc_basis_cpu_s")
    # a partial, not a lambda: the basis is bound now and released by the del below
    straighten_s, _ = best(functools.partial(straighten_basis, basis, vertices, mesh.triangles), repeats,
                           "straighten_cpu_s")
    del basis

    keypoints = edited_keypoints(rig)
    out = np.empty_like(mesh.vertices)
    for _ in range(5):
        rig.deform(keypoints, out=out)
    times = []
    for _ in range(edits):
        start = time.perf_counter()
        rig.deform(keypoints, out=out)
        times.append(time.perf_counter() - start)
    every = rig.keypoints + 0.05 * rig.normalizer.scale_  # every keypoint moved: every row of the basis is read
    every_times = []
    for _ in range(edits):
        start = time.perf_counter()
        rig.deform(every, out=out)
        every_times.append(time.perf_counter() - start)

    with tempfile.TemporaryDirectory() as tmp:
        file = Path(tmp) / "rig.npz"
        save_s, _ = best(lambda: rig.save(file), 1)
        load_s, back = best(lambda: Rig.load(file), 2)
        size_mb = file.stat().st_size / 2**20
        same = bool(np.array_equal(back.deform(keypoints), rig.deform(keypoints)))
    return {
        "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
        "model_rig_s": round(rig_s, 3), "model_rig_without_straightening_s": round(plain_s, 3),
        "bind_given_prediction_s": round(bind_s, 3),
        "predict_s": round(predict_s, 3), "mvc_basis_s": round(mvc_s, 3), "straighten_s": round(straighten_s, 3),
        "slivers_straightened": rig.correction is not None if len(mesh.vertices) < 200_000 else None,
        "basis_dtype": str(rig.basis.dtype),
        "edit_ms_median": round(1000 * statistics.median(times), 2),
        "edit_every_keypoint_moved_ms_median": round(1000 * statistics.median(every_times), 2),
        "rig_save_s": round(save_s, 2), "rig_load_s": round(load_s, 3), "rig_file_mb": round(size_mb, 1),
        "loaded_rig_deforms_the_same": same,
        # CPU seconds of the same calls (both threads counted): less inflated than wall time on a busy machine
        **{name: round(value, 3) for name, value in cpu.items()},
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def run_child(*args: str) -> dict:
    done = subprocess.run([sys.executable, __file__, "--child", *args], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout)


def run_cli(args: list[str]) -> dict:
    kpd = str(Path(sys.executable).with_name("kpd"))
    start = time.perf_counter()
    done = subprocess.run([kpd, *args], capture_output=True, text=True, check=False)
    return {"command": "kpd " + " ".join(args), "seconds": round(time.perf_counter() - start, 2),
            "exit": done.returncode, **({"stderr": done.stderr.strip()[-300:]} if done.returncode else {})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="scan,chair", help="which meshes: scan (the sneaker scan, shoe model), "
                        "chair (the ShapeNet chair, chair model)")
    parser.add_argument("--levels", default="1,2,3", help="sizes by index: 1 ~85k, 2 ~330k, 3 ~1.3M vertices")
    parser.add_argument("--repeats", type=int, default=3, help="timed binds per size below 1M vertices (best)")
    parser.add_argument("--largest-repeats", type=int, default=1, help="timed binds at the largest size (best)")
    parser.add_argument("--edits", type=int, default=50, help="timed edits per size (median)")
    parser.add_argument("--busy", action="store_true", help="time again beside one busy CPU-bound process")
    parser.add_argument("--cli", action="store_true", help="time kpd deform and kpd render at the largest size")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        mode, name, path, *rest = args.child
        print(json.dumps(child_peak(name, path) if mode == "peak" else
                         child_time(name, path, int(rest[0]), int(rest[1]))))
        return

    from kpd.benchmark import machine_cpu, machine_speed

    picks = [int(x) - 1 for x in args.levels.split(",")]
    result: dict = {
        "benchmark": "kpd at scan sizes: bind, edit, save, load",
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count(),
                    "cpu": machine_cpu(), "speed_at_start": machine_speed()},  # to compare runs of different days
        "meshes": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        for mesh_name in args.meshes.split(","):
            source, model, levels = MESHES[mesh_name]
            paths = subdivided(source, [levels[i] for i in picks], Path(tmp))
            record: dict = {"mesh": f"{source.relative_to(DATA)} subdivided with Open3D subdivide_midpoint",
                            "model": f"{model} (shipped bundle)", "sizes": {}}
            result["meshes"][mesh_name] = record
            for level, path in paths.items():
                repeats = args.largest_repeats if level == levels[-1] else args.repeats
                entry = {"peak": run_child("peak", model, str(path)),
                         "quiet": run_child("time", model, str(path), str(repeats), str(args.edits))}
                record["sizes"][f"x{level}"] = entry
                print(f"{mesh_name} x{level}: {json.dumps(entry)}", file=sys.stderr, flush=True)
            if args.busy:
                busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
                try:
                    for level, path in paths.items():
                        repeats = args.largest_repeats if level == levels[-1] else args.repeats
                        record["sizes"][f"x{level}"]["beside_busy"] = run_child("time", model, str(path),
                                                                                str(repeats), str(args.edits))
                finally:
                    busy.kill()
                    busy.wait()
            if args.cli:
                level = max(paths)
                path, out = paths[level], Path(tmp)
                record["cli"] = {"level": level}
                # as the model's frame, and for the scan also with --scan (cleaned, oriented and normalised first,
                # as a user runs a raw scan)
                variants = [("deform", [], "deformed.ply"), ("render", [], "render.png")]
                if mesh_name == "scan":
                    variants += [("deform", ["--scan"], "deformed.ply"), ("render", ["--scan"], "render.png")]
                for command, extra, target in variants:
                    name = command + "".join(f"_{flag.strip('-')}" for flag in extra)
                    line = [command, model, str(path), *extra, "--move", "0:0,0.05,0", "--out",
                            str(out / f"{mesh_name}_{target}"), "--force"]
                    record["cli"][name] = run_cli(line)
                    if args.busy:
                        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
                        try:
                            record["cli"][f"{name}_beside_busy"] = run_cli(line)
                        finally:
                            busy.kill()
                            busy.wait()
            summary: dict = {}
            for name, entry in record["sizes"].items():
                quiet = entry.get("quiet", {})
                summary[name] = {"vertices": quiet.get("vertices"), "model_rig_s": quiet.get("model_rig_s"),
                                 "without_straightening_s": quiet.get("model_rig_without_straightening_s"),
                                 "peak_rss_mb": entry.get("peak", {}).get("peak_rss_mb"),
                                 "edit_ms": quiet.get("edit_ms_median")}
            names = list(record["sizes"])
            if len(names) >= 2:
                small, large = record["sizes"][names[-2]]["quiet"], record["sizes"][names[-1]]["quiet"]
                if "model_rig_s" in small and "model_rig_s" in large:
                    summary["rig_time_ratio_largest_over_next"] = round(large["model_rig_s"] / small["model_rig_s"],
                                                                        2)
            record["summary"] = summary
    result["machine"]["load_average_1min"] = round(os.getloadavg()[0], 2)
    result["machine"]["speed_at_end"] = machine_speed()
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
