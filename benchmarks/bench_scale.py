"""Binding, editing, saving and loading rigs of scan-sized meshes; prints one JSON object.

A real ShapeNet chair (KeypointNet's ``fe6b3c001a86d844d5767a0de8dd037e``, 5,358 vertices and 21,504 triangles,
from the shared data folder) subdivided with Open3D's ``subdivide_midpoint`` 2, 3 and 4 times (86k, 343k and 1.37M
vertices; a CAD mesh stays full of slivers when subdivided, so straightening has its most work), rigged with the
shipped chair model. Each size runs in fresh subprocesses:

1. ``peak``: load the model, read the mesh, ``Model.rig`` once, one edit; peak resident memory
   (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) of that process. Target at 1.3M: <= 1.5 GB.
2. ``time``: ``Model.rig`` (default, with the straightening of slivers) and without straightening, best of a few
   repeats for a predicted shape, in wall and in CPU seconds (both threads counted); its parts (the MVC basis through the compiled kernel alone, the straightening
   alone); one edit ``rig.deform(keypoints, out=buffer)``, median of many; ``Rig.save`` and ``Rig.load`` of the
   rig and the file's size. Targets: ``Model.rig`` <= 0.3 s at 100k, <= 1 s at 330k, <= 3 s at 1.3M; time(1.3M) /
   time(330k) <= 4.4; one edit at 1.3M <= 15 ms; a saved rig loads in <= 1 s.
3. The ``time`` run again beside one busy CPU-bound process (``--busy``).
4. ``kpd deform`` and ``kpd render`` end to end at the largest size (``--cli``), wall time of the command.
   Target: <= 6 s each.

Usage: ``.venv/bin/python benchmarks/bench_scale.py --busy --cli > benchmarks/results/scale.json``
(``--levels 2,3`` for a quicker run).
"""

from __future__ import annotations

import argparse
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
CHAIR = DATA / "keypointnet" / "models" / "03001627" / "fe6b3c001a86d844d5767a0de8dd037e" / "model.obj"


def subdivided(levels: list[int], folder: Path) -> dict[int, Path]:
    """The chair subdivided ``level`` times, written to ``folder`` as binary PLY."""
    import open3d as o3d

    from kpd.io import Mesh, read_mesh, write_mesh

    mesh = read_mesh(CHAIR)
    base = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                     o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    paths = {}
    for level in levels:
        fine = base.subdivide_midpoint(level)
        path = folder / f"chair_x{level}.ply"
        write_mesh(path, Mesh(vertices=np.asarray(fine.vertices), triangles=np.asarray(fine.triangles, np.int64)))
        paths[level] = path
    return paths


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kilobytes


def edited_keypoints(rig) -> np.ndarray:
    keypoints = rig.keypoints
    keypoints[0] += 0.1 * rig.normalizer.scale_  # one keypoint moved by 5% of the box
    return keypoints


def child_peak(path: str) -> dict:
    from kpd.io import read_mesh
    from kpd.runtime import Model

    start = time.perf_counter()
    model = Model.load("chair")
    mesh = read_mesh(path)
    read_s = time.perf_counter() - start
    rig = model.rig(mesh)
    bound_s = time.perf_counter() - start
    rig.deform(edited_keypoints(rig))
    return {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "load_and_read_s": round(read_s, 2),
            "load_read_bind_edit_s": round(time.perf_counter() - start, 2), "bind_s": round(bound_s - read_s, 2),
            "peak_rss_mb": round(peak_rss_mb())}


def child_time(path: str, repeats: int, edits: int) -> dict:
    from kpd.io import read_mesh
    from kpd.rig import Rig, coincident_mvc_basis, straighten_basis
    from kpd.runtime import Model

    model = Model.load("chair")
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

    rig_s, rig = best(lambda: model.rig(mesh, prediction=prediction), repeats, "model_rig_cpu_s")
    plain_s, _ = best(lambda: model.rig(mesh, prediction=prediction, straighten=False), repeats,
                      "model_rig_without_straightening_cpu_s")
    predict_s, _ = best(lambda: model.predict(mesh), repeats)
    vertices = rig.normalizer.apply(mesh.vertices)
    mvc_s, basis = best(lambda: coincident_mvc_basis(vertices, rig.cage, rig.influence.T), repeats, "mvc_basis_cpu_s")
    straighten_s, _ = best(lambda: straighten_basis(basis, vertices, mesh.triangles), repeats, "straighten_cpu_s")
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

    with tempfile.TemporaryDirectory() as tmp:
        file = Path(tmp) / "rig.npz"
        save_s, _ = best(lambda: rig.save(file), 1)
        load_s, back = best(lambda: Rig.load(file), 2)
        size_mb = file.stat().st_size / 2**20
        same = bool(np.array_equal(back.deform(keypoints), rig.deform(keypoints)))
    return {
        "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
        "model_rig_s": round(rig_s, 3), "model_rig_without_straightening_s": round(plain_s, 3),
        "predict_s": round(predict_s, 3), "mvc_basis_s": round(mvc_s, 3), "straighten_s": round(straighten_s, 3),
        "slivers_straightened": rig.correction is not None if len(mesh.vertices) < 200_000 else None,
        "basis_dtype": str(rig.basis.dtype),
        "edit_ms_median": round(1000 * statistics.median(times), 2),
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
    parser.add_argument("--levels", default="2,3,4", help="midpoint subdivision levels of the chair (2: 86k, "
                        "3: 343k, 4: 1.37M vertices)")
    parser.add_argument("--repeats", type=int, default=3, help="timed binds per size below 1M vertices (best)")
    parser.add_argument("--edits", type=int, default=50, help="timed edits per size (median)")
    parser.add_argument("--busy", action="store_true", help="time again beside one busy CPU-bound process")
    parser.add_argument("--cli", action="store_true", help="time kpd deform and kpd render at the largest size")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        mode, path, *rest = args.child
        print(json.dumps(child_peak(path) if mode == "peak" else child_time(path, int(rest[0]), int(rest[1]))))
        return

    levels = [int(x) for x in args.levels.split(",")]
    result: dict = {
        "benchmark": "kpd at scan sizes: bind, edit, save, load",
        "mesh": f"{CHAIR.relative_to(DATA)} subdivided with Open3D subdivide_midpoint",
        "model": "chair (shipped bundle)",
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count()},
        "sizes": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        paths = subdivided(levels, Path(tmp))
        for level, path in paths.items():
            big = level >= 4
            repeats = 1 if big else args.repeats
            entry = {"peak": run_child("peak", str(path)),
                     "quiet": run_child("time", str(path), str(repeats), str(args.edits))}
            result["sizes"][f"x{level}"] = entry
            print(f"level {level}: {json.dumps(entry)}", file=sys.stderr, flush=True)
        if args.busy:
            busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            try:
                for level, path in paths.items():
                    repeats = 1 if level >= 4 else args.repeats
                    result["sizes"][f"x{level}"]["beside_busy"] = run_child("time", str(path), str(repeats),
                                                                            str(args.edits))
            finally:
                busy.kill()
                busy.wait()
        if args.cli:
            path = paths[max(paths)]
            out = Path(tmp)
            result["cli"] = {
                "vertices_level": max(paths),
                "deform": run_cli(["deform", "chair", str(path), "--move", "0:0,0.05,0", "--out",
                                   str(out / "deformed.ply")]),
                "render": run_cli(["render", "chair", str(path), "--move", "0:0,0.05,0", "--out",
                                   str(out / "render.png")]),
            }
    sizes = result["sizes"]
    summary = {}
    for name, entry in sizes.items():
        quiet = entry.get("quiet", {})
        summary[name] = {"vertices": quiet.get("vertices"), "model_rig_s": quiet.get("model_rig_s"),
                         "peak_rss_mb": entry.get("peak", {}).get("peak_rss_mb"),
                         "edit_ms": quiet.get("edit_ms_median")}
    if "x3" in sizes and "x4" in sizes and "model_rig_s" in sizes["x3"]["quiet"] and "model_rig_s" in sizes["x4"][
            "quiet"]:
        summary["rig_time_ratio_x4_over_x3"] = round(sizes["x4"]["quiet"]["model_rig_s"]
                                                     / sizes["x3"]["quiet"]["model_rig_s"], 2)
        summary["rig_time_ratio_x4_over_x3_without_straightening"] = round(
            sizes["x4"]["quiet"]["model_rig_without_straightening_s"]
            / sizes["x3"]["quiet"]["model_rig_without_straightening_s"], 2)
    result["summary"] = summary
    result["machine"]["load_average_1min"] = round(os.getloadavg()[0], 2)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
