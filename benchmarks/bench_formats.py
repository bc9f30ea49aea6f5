"""What each mesh reader keeps of real OBJ files, and what kpd's OBJ reading and writing cost at scan sizes.

Figures (docs/formats.md):

* ``shapenet``: over the 38 ShapeNetCore.v2 models of the shared data (``shapenetcore_obj``), per reader (kpd, Open3D
  0.20's legacy and tensor readers = Assimp, and trimesh when importable), how many models come back with the file's
  vertices (one per ``v`` line, in order), with texture coordinates on every face that has them (the 16 that mix faces
  with and without), with every used material (its colour or its map), and with the maps' images; for kpd also how many
  deformed outputs (``write_mesh`` after ``with_vertices``) are the input's text with only ``v``/``vn`` lines changed
  and its maps copied byte for byte.
* ``scale``: an OBJ of about 1M vertices and 2M triangles with one UV per vertex and a material, read by kpd and by
  Open3D, and written by kpd (a deformed copy: the file's own structure) and by Open3D (its OBJ writer), each in a
  fresh process: wall seconds (median of ``--runs``, the two libraries interleaved) and peak resident memory.
* ``formats``: a scan-sized CAD mesh, the unseen ShapeNet chair ``fe6b3c00...`` subdivided 4 times (1,375,656
  vertices, 5,505,024 triangles, as ``bench_viewer.py``'s ``1.3M``), written by kpd in each format from its arrays
  and read back, and the same by Open3D where it reads or writes that format, each in a fresh process: wall seconds
  of the call alone (median of ``--runs``, interleaved) and the process's peak resident memory.

    .venv/bin/python benchmarks/bench_formats.py [--runs 3] [--resolution 700] [--skip-formats] \
        > benchmarks/results/formats.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data"))


def facts(path: Path) -> dict:
    """What the file holds: v lines, faces, faces with texture coordinates, used materials, maps."""
    text = path.read_text(errors="replace")
    faces = re.findall(r"^f\s+(.*)$", text, re.M)
    with_uv = sum(1 for f in faces if all(c.count("/") >= 1 and c.split("/")[1] for c in f.split()))
    used, current = set(), None  # materials that faces use (a usemtl before lines only does not count)
    for line in text.splitlines():
        if line.startswith("usemtl"):
            current = line.split(None, 1)[1].strip()
        elif line.startswith("f") and current is not None:
            used.add(current)
    mtl = path.with_name(path.stem + ".mtl")
    maps, kd = {}, {}
    current = None
    if mtl.is_file():
        for line in mtl.read_text(errors="replace").splitlines():
            parts = line.split()
            if parts[:1] == ["newmtl"]:
                current = parts[1]
            elif parts[:1] == ["Kd"]:
                kd[current] = tuple(parts[1:4])
            elif parts[:1] == ["map_Kd"] and current in used and (mtl.parent / parts[-1]).is_file():
                maps[current] = parts[-1]
    looks = {(kd.get(m), maps.get(m)) for m in used}
    return {"v": len(re.findall(r"^v\s", text, re.M)), "faces": len(faces), "uv_faces": with_uv,
            "materials": len(used), "looks": len(looks), "maps": len(set(maps.values()))}


def kpd_keeps(path: Path, f: dict, out: Path) -> dict:
    from kpd.io import read_mesh, write_mesh

    mesh = read_mesh(path)
    uv_faces = 0 if mesh.triangle_uvs is None else int(len(mesh.triangles) if mesh.triangle_uv_mask is None
                                                       else mesh.triangle_uv_mask.sum())
    images = sum(1 for t in mesh.textures if t.shape[0] * t.shape[1] > 1)
    moved = mesh.with_vertices(mesh.vertices * [1.0, 1.1, 0.9])
    write_mesh(out, moved)
    a, b = path.read_text().splitlines(), out.read_text().splitlines()
    same_text = len(a) == len(b) and all(
        x == y for x, y in zip(a, b) if x.split()[:1] not in (["v"], ["vn"], ["mtllib"]))
    copied = [p for p in out.parent.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")]
    maps_bytes = sum(1 for p in copied if any(p.read_bytes() == q.read_bytes()
                                              for q in (path.parent / "../images").glob("*")))
    # one texture per used material; none when every used material looks the same (nothing to tell apart)
    materials = len(mesh.textures) == f["materials"] or (not mesh.textures and f["looks"] == 1 and not f["maps"])
    return {"file_vertices": len(mesh.vertices) == f["v"], "uv_faces_kept": uv_faces == f["uv_faces"],
            "materials_kept": materials,
            "images_kept": images == f["maps"], "output_is_the_input_text": same_text,
            "maps_copied_byte_for_byte": maps_bytes == f["maps"]}


def open3d_keeps(path: Path, f: dict) -> dict:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    m = o3d.io.read_triangle_mesh(str(path))
    uv_faces = len(m.triangles) if m.has_triangle_uvs() else 0
    images = sum(1 for t in m.textures if not t.is_empty())
    ids = np.unique(np.asarray(m.triangle_material_ids)) if m.has_triangle_material_ids() else []
    return {"file_vertices": len(m.vertices) == f["v"], "uv_faces_kept": uv_faces == f["uv_faces"],
            "materials_kept": len(ids) == f["materials"], "images_kept": images == f["maps"]}


def open3d_tensor_keeps(path: Path, f: dict) -> dict:
    import open3d as o3d

    m = o3d.t.io.read_triangle_mesh(str(path))
    n = len(m.triangle.indices)
    uv_faces = n if "texture_uvs" in m.triangle else 0
    albedo = m.has_valid_material() and "albedo" in m.material.texture_maps
    return {"file_vertices": len(m.vertex.positions) == f["v"], "uv_faces_kept": uv_faces == f["uv_faces"],
            "materials_kept": f["materials"] <= 1, "images_kept": int(albedo) == f["maps"]}


def trimesh_keeps(path: Path, f: dict) -> dict | None:
    try:
        import trimesh
    except ImportError:
        return None
    scene = trimesh.load(str(path), process=False)
    geometries = list(scene.geometry.values()) if hasattr(scene, "geometry") else [scene]
    vertices = sum(len(g.vertices) for g in geometries)
    uv_faces = sum(len(g.faces) for g in geometries if getattr(g.visual, "uv", None) is not None)
    materials = {getattr(getattr(g.visual, "material", None), "name", None) for g in geometries}
    images = sum(1 for g in geometries if getattr(getattr(g.visual, "material", None), "image", None) is not None)
    return {"file_vertices": vertices == f["v"], "uv_faces_kept": uv_faces == f["uv_faces"],
            "materials_kept": len(materials) == f["materials"], "images_kept": images == f["maps"]}


def shapenet() -> dict:
    files = sorted((DATA / "shapenetcore_obj").glob("*/*/models/model_normalized.obj"))
    counts: dict[str, dict[str, int]] = {}
    mixed = 0
    with tempfile.TemporaryDirectory() as folder:
        for i, path in enumerate(files):
            f = facts(path)
            mixed += 0 < f["uv_faces"] < f["faces"]
            out = Path(folder) / f"m{i}" / "out.obj"
            out.parent.mkdir()
            results = {"kpd": kpd_keeps(path, f, out), "open3d": open3d_keeps(path, f),
                       "open3d_tensor": open3d_tensor_keeps(path, f), "trimesh": trimesh_keeps(path, f)}
            for reader, kept in results.items():
                if kept is None:
                    continue
                for key, value in kept.items():
                    counts.setdefault(reader, {}).setdefault(key, 0)
                    counts[reader][key] += int(bool(value))
    return {"models": len(files), "models_mixing_uv_faces": int(mixed), "kept": counts}


_CHILD = r"""
import sys, time, json
import numpy as np
kind, path, out = sys.argv[1:4]
start = time.perf_counter()
if kind == "kpd_read":
    from kpd.io import read_mesh
    read_mesh(path)
elif kind == "open3d_read":
    import open3d as o3d
    o3d.io.read_triangle_mesh(path)
elif kind == "kpd_write":
    from kpd.io import read_mesh, write_mesh
    m = read_mesh(path)
    moved = m.with_vertices(m.vertices * 1.01)
    start = time.perf_counter()
    write_mesh(out, moved)
elif kind == "open3d_write":
    import open3d as o3d
    m = o3d.io.read_triangle_mesh(path)
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * 1.01)
    start = time.perf_counter()
    o3d.io.write_triangle_mesh(out, m)
elif kind == "kpd_write_arrays":  # from a PLY's arrays: no file structure to follow
    from kpd.io import read_mesh, write_mesh
    m = read_mesh(path)
    start = time.perf_counter()
    write_mesh(out, m)
elif kind == "open3d_write_arrays":
    import open3d as o3d
    m = o3d.io.read_triangle_mesh(path)
    start = time.perf_counter()
    if out.endswith(".stl"):  # its STL writer needs the facets' normals
        m.compute_triangle_normals()
    if not o3d.io.write_triangle_mesh(out, m):
        raise SystemExit("Open3D could not write " + out)
seconds = time.perf_counter() - start
peak = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))  # kB, this process
print(json.dumps({"seconds": seconds, "peak_mib": peak / 1024}))
"""


def scale(runs: int, resolution: int) -> dict:
    import open3d as o3d

    from kpd.io import Mesh, write_mesh

    sphere = o3d.geometry.TriangleMesh.create_sphere(resolution=resolution)
    v, t = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, v[:, 2] * 0.5 + 0.5], axis=1)[t].reshape(-1, 2)
    texture = np.random.default_rng(0).integers(0, 256, (256, 256, 3), dtype=np.uint8)
    result = {"vertices": len(v), "triangles": len(t)}
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "big.obj"
        write_mesh(path, Mesh(v, t, triangle_uvs=uv, textures=[texture], triangle_material_ids=np.zeros(len(t), int)))
        del sphere, v, t, uv
        result["file_mib"] = path.stat().st_size / 2 ** 20
        kinds = ("kpd_read", "open3d_read", "kpd_write", "open3d_write")
        samples: dict[str, list] = {k: [] for k in kinds}
        for r in range(runs):
            for kind in kinds:  # interleaved: the machine's load falls on both alike
                out = str(Path(folder) / f"out_{kind}_{r}.obj")
                run = subprocess.run([sys.executable, "-c", _CHILD, kind, str(path), out], capture_output=True,
                                     text=True, check=True)
                samples[kind].append(json.loads(run.stdout.strip().splitlines()[-1]))
                for p in Path(folder).glob("out_*"):
                    p.unlink()
        for kind, values in samples.items():
            result[kind] = {"seconds_median": statistics.median(s["seconds"] for s in values),
                            "seconds": [round(s["seconds"], 2) for s in values],
                            "peak_mib_max": max(s["peak_mib"] for s in values)}
    return result


FORMATS = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf")


def _child(kind: str, path: Path, out: Path) -> dict | None:
    """One measurement in a fresh process; None when the library cannot do it (Open3D and glTF writing)."""
    run = subprocess.run([sys.executable, "-c", _CHILD, kind, str(path), str(out)], capture_output=True, text=True)
    if run.returncode != 0:
        return None
    return json.loads(run.stdout.strip().splitlines()[-1])


def formats(runs: int) -> dict:
    """Each format written from the 1.37M-vertex chair's arrays and read back, by kpd and by Open3D."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_viewer import SCAN_SIZED, _subdivided

    result: dict = {}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        source = _subdivided(SCAN_SIZED, folder, "chair", times=4)  # the arrays every format is written from
        from kpd.io import read_mesh

        mesh = read_mesh(source)
        result.update(mesh=f"{SCAN_SIZED.parent.name} subdivided 4 times", vertices=len(mesh.vertices),
                      triangles=len(mesh.triangles))
        del mesh
        samples: dict = {}
        for _ in range(runs):
            for ext in FORMATS:
                for library in ("kpd", "open3d"):  # interleaved: the machine's load falls on both alike
                    written = folder / f"{library}{ext}"
                    write = _child(f"{library}_write_arrays", source, written)
                    read = _child(f"{library}_read", written, folder / "unused") if written.exists() else None
                    samples.setdefault(ext, {}).setdefault(library, []).append((write, read))
                    for p in folder.iterdir():
                        if p.name.startswith(library) or p.name.startswith("unused"):
                            p.unlink()
        for ext, by_library in samples.items():
            for library, values in by_library.items():
                entry = {}
                for step, k in (("write", 0), ("read", 1)):
                    got = [v[k] for v in values if v[k] is not None]
                    if got:
                        entry[step] = {"seconds_median": round(statistics.median(g["seconds"] for g in got), 3),
                                       "seconds": [round(g["seconds"], 2) for g in got],
                                       "peak_mib_max": round(max(g["peak_mib"] for g in got))}
                result.setdefault(ext.lstrip("."), {})[library] = entry or "cannot"
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--resolution", type=int, default=700, help="Open3D sphere resolution (700: ~1M vertices)")
    parser.add_argument("--skip-scale", action="store_true")
    parser.add_argument("--skip-formats", action="store_true")
    args = parser.parse_args()
    import open3d

    from kpd.benchmark import machine_speed

    out = {"command": "python benchmarks/bench_formats.py " + " ".join(sys.argv[1:]), "machine": platform.machine(),
           "cpus": os.cpu_count(), "open3d": open3d.__version__,
           "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_at_start": os.getloadavg()[0],
           "speed_at_start": machine_speed()}  # to compare runs of different days
    try:
        import trimesh

        out["trimesh"] = trimesh.__version__
    except ImportError:
        out["trimesh"] = None
    out["shapenet"] = shapenet()
    if not args.skip_scale:
        out["scale"] = scale(args.runs, args.resolution)
    if not args.skip_formats:
        out["formats"] = formats(args.runs)
    out.update(load_at_end=os.getloadavg()[0], speed_at_end=machine_speed())
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
