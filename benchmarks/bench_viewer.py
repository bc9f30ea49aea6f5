"""Editor drag-step cost: ``Rig.deform`` plus one geometry upload to an Open3D scene, at 10k and 100k vertices.

Prints JSON. The upload is timed two ways: a legacy TriangleMesh remove + add (what :class:`RigScene` does,
normals recomputed), and a ``t.geometry.PointCloud`` positions/normals update with
``Scene.update_geometry(UPDATE_POINTS_FLAG)`` (Open3D's fast path; float32 positions). Rendering itself
(software rasteriser here) is excluded. A synthetic rig (a subdivided sphere, K = 12, C = 42) keeps the numbers
independent of data files.

    .venv/bin/python benchmarks/bench_viewer.py [--repeat 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import numpy as np

from kpd.commands.bench import median_ms


def _sphere_rig(target_vertices: int, k: int = 12):
    import open3d as o3d

    from kpd.geometry import Normalizer
    from kpd.io import Mesh
    from kpd.rig import Rig

    resolution = int(np.sqrt(target_vertices / 2)) + 1
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    mesh = Mesh(vertices=np.asarray(sphere.vertices).copy(), triangles=np.asarray(sphere.triangles).astype(np.int64))
    rng = np.random.default_rng(0)
    keypoints = rng.normal(size=(k, 3))
    keypoints = 0.8 * keypoints / np.linalg.norm(keypoints, axis=1, keepdims=True)
    return Rig.bind(mesh, keypoints, None, normalizer=Normalizer().fit(mesh.vertices))


def bench(vertices: int, repeat: int, renderer) -> dict:
    import open3d as o3d
    from open3d.visualization import rendering

    from kpd.viewer.render import Frame, RigScene, ViewSettings

    rig = _sphere_rig(vertices)
    v = len(rig.mesh.vertices)
    rng = np.random.default_rng(1)
    buffer = np.empty((v, 3))
    keypoints = rig.keypoints

    def deform():
        moved = keypoints + 0.01 * rng.normal(size=keypoints.shape)
        rig.deform(moved, out=buffer)

    deform_ms = median_ms(deform, repeat, warmup=1)

    scene = renderer.scene
    scene.clear_geometry()
    rig_scene = RigScene(rig.mesh, rig.num_keypoints, None, settings=ViewSettings())
    frame = Frame(rig.deform(keypoints), keypoints, None, ())
    rig_scene.attach(scene, frame)
    mesh_upload_ms = median_ms(lambda: rig_scene.update(frame, normals=True), repeat, warmup=1)

    # the fast path: a tensor point cloud whose positions and normals are replaced in place
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(buffer.astype(np.float32)))
    cloud.point.colors = o3d.core.Tensor(np.full((v, 3), 0.7, np.float32))
    material = rendering.MaterialRecord()
    material.shader = "defaultUnlit"
    scene.scene.add_geometry("fast", cloud, material)
    flags = rendering.Scene.UPDATE_POINTS_FLAG  # with UPDATE_NORMALS_FLAG Open3D 0.20 raises _Map_base::at

    def upload_points():
        cloud.point.positions = o3d.core.Tensor(buffer.astype(np.float32))
        scene.scene.update_geometry("fast", cloud, flags)

    points_upload_ms = median_ms(upload_points, repeat, warmup=1)
    return {
        "vertices": v,
        "triangles": int(len(rig.mesh.triangles)),
        "keypoints": rig.num_keypoints,
        "deform_ms": round(deform_ms, 3),
        "upload_mesh_ms": round(mesh_upload_ms, 3),
        "upload_points_ms": round(points_upload_ms, 3),
        "total_mesh_ms": round(deform_ms + mesh_upload_ms, 3),
        "total_points_ms": round(deform_ms + points_upload_ms, 3),
    }


def main() -> None:
    import subprocess
    import sys

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--sizes", default="10000,100000")
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # internal: one size, this process
    args = parser.parse_args()
    if args.one is not None:
        from open3d.visualization import rendering

        from kpd.viewer.render import _quiet_native_output

        with _quiet_native_output():
            renderer = rendering.OffscreenRenderer(320, 240)
            result = bench(args.one, args.repeat, renderer)
        print(json.dumps(result))
        sys.stdout.flush()
        os._exit(0)  # one renderer per process: Open3D aborts when a second scene is built after clearing the first
    results = []
    for n in args.sizes.split(","):
        done = subprocess.run([sys.executable, __file__, "--one", n, "--repeat", str(args.repeat)], capture_output=True,
                              text=True, check=True)
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print(json.dumps({
        "benchmark": "viewer drag step (Rig.deform + one geometry upload; rendering excluded)",
        "note": "upload times are the CPU cost of the Open3D calls; Filament copies to the GPU on the next frame",
        "target_ms_at_100k": 16.0,
        "repeat": args.repeat,
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
        "results": results,
    }, indent=2))


if __name__ == "__main__":
    main()
