"""glTF rigs (``kpd rig``) and the browser editor (``kpd view --browser``) at 10k, 100k and 1M vertices; prints JSON.

For the procedural chair (``kpd.procedural``) at about 10k, 100k and 1M vertices, rigged with the shipped chair model:

1. ``kpd rig chair chair.ply --out chair.glb``: wall time of the whole command (a process of its own: start, model,
   mesh, bind, targets, file) and its peak memory; the binding alone (``Model.rig``) and the targets and file alone
   (``MorphRig.from_rig`` + ``write_gltf``) timed in this process. Target: 100k vertices in <= 3 s.
2. File sizes: the ``.glb`` (every target: 3K keypoint, 3K prior, M components), the ``.gltf`` + ``.bin``, the GLB
   with the keypoint targets only (what the page loads with ``?morph=three``) and the GLB the page loads by default
   (the mesh and its basis as vertex attributes, no targets).
3. Exactness: the largest distance, over all vertices, between the file's morphed positions (float32 data, summed in
   float64 as :meth:`kpd.morph.GltfRig.morphed` does) and ``Rig.deform`` of the same edit, as a share of the box
   diagonal, for random weights of every target (offsets of 5% of the diagonal per keypoint, +-1 on the rest).
4. The page in headless Chromium on SwiftShader (software WebGL, this machine's 2 cores): the first picture (ms from
   the page's start to its first finished frame, the GLB downloaded and parsed and its attributes uploaded), and
   a drag of a keypoint by real mouse events: per step, the latency from the pointer event to its finished frame
   (median; it includes waiting for a frame in progress), the interval between the drag's frames (median) and the
   page's own work for a step. Targets at 100k: first picture <= 3 s, a drag step <= 50 ms. At 100k
   the same drag is also drawn by three.js's own morph targets (``?morph=three``) and with no deformation at all
   (``?morph=none``: what drawing the mesh costs on this renderer, the floor of a drag step).

Usage: ``.venv/bin/python benchmarks/bench_morph.py [--sizes 10k,100k,1M] > benchmarks/results/morph.json``
(needs ``make web`` and Debian's chromium and chromium-driver).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from kpd.io import write_mesh  # noqa: E402
from kpd.morph import MorphRig, gltf_bytes, read_gltf, write_gltf  # noqa: E402
from kpd.procedural import procedural_chair  # noqa: E402
from kpd.runtime import Model  # noqa: E402

SIZES = {"10k": 0.52, "100k": 0.16, "1M": 0.05}  # the procedural chair's grid spacing -> vertex count
DRAG_STEPS = 30


def peak_mib(pid: int) -> float:
    """A running process's peak resident memory since it started its program (``VmHWM``), MiB; 0 once it is gone.
    (``ru_maxrss`` from ``wait4`` would also count the benchmark's own memory, which the child shares until exec.)"""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def run_command(argv: list[str]) -> tuple[float, float]:
    """Wall seconds and peak resident MiB of a command run as a process of its own (the peak read every 20 ms)."""
    start = time.perf_counter()
    process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=REPO)
    peak = 0.0
    while process.poll() is None:
        peak = max(peak, peak_mib(process.pid))
        time.sleep(0.02)
    seconds = time.perf_counter() - start
    if process.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {process.stderr.read().decode()}")
    return seconds, peak


def page_figures(shape: Path, workdir: Path, modes: tuple = ("basis",)) -> dict:
    """First picture and drag steps of kpd view --browser on ``shape`` in headless Chromium, for each way of
    drawing: the page's packed basis (its default), three.js's morph targets (``?morph=three``) and the rest mesh
    without deformation (``?morph=none``, the draw's own cost)."""
    from test_browser import start_chromium, start_editor

    process, url = start_editor("chair", str(shape), "--port", "0")
    profile = tempfile.mkdtemp(prefix="kpd-chromium-", dir=workdir)
    driver = None
    figures = {}
    try:
        driver = start_chromium(profile)
        for mode in modes:
            figures[mode] = _page_mode(driver, url + "?timing=1" + ("" if mode == "basis" else f"&morph={mode}"))
    finally:
        if driver is not None:
            driver.quit()
        peak = peak_mib(process.pid)
        process.terminate()
        process.wait(timeout=30)
    for entry in figures.values():  # the server: the rig, its GLB for the page, the HTTP server
        entry["server_peak_mib"] = round(peak)
    return figures if len(modes) > 1 else figures[modes[0]]


def _page_mode(driver, url: str) -> dict:
    """The page's first picture and a keypoint drag's steps at ``url``."""
    from test_browser import drag, wait

    driver.get(url)
    wait(driver, "return window.kpd && (window.kpd.ready || window.kpd.error)", timeout=600)
    error = driver.execute_script("return window.kpd.error")
    if error:
        return {"error": error}
    wait(driver, "return window.kpd.stats.firstPicture !== null", timeout=600)
    stats = driver.execute_script("return window.kpd.stats")
    drag(driver, 8, 4 * DRAG_STEPS, 0, steps=DRAG_STEPS)
    steps = driver.execute_script("return window.kpd.stats.steps")
    latency = np.array([s["latency"] for s in steps])
    work = np.array([s["work"] for s in steps])
    return {
        "first_picture_ms": round(stats["firstPicture"], 1),
        "glb_parsed_ms": round(stats["loaded"], 1),
        "drag_steps": len(steps),
        "drag_step_latency_ms_median": round(float(np.median(latency)), 2),
        "drag_step_latency_ms_max": round(float(latency.max()), 2),
        "drag_step_work_ms_median": round(float(np.median(work)), 2),
        "drag_frame_interval_ms_median": round(float(np.median(np.diff([s["at"] for s in steps]))), 2),
        "page_js_heap_mib": round(driver.execute_script("return performance.memory.usedJSHeapSize") / 2**20),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(SIZES), help="comma-separated sizes among " + ", ".join(SIZES))
    parser.add_argument("--no-page", action="store_true", help="skip the browser figures")
    args = parser.parse_args()

    model = Model.load("chair")
    result = {
        "benchmark": "kpd rig (glTF morph targets) and kpd view --browser",
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count(),
                    "chromium": subprocess.run(["/usr/bin/chromium", "--version"], capture_output=True,
                                               text=True).stdout.strip(),
                    "webgl": "SwiftShader (headless Chromium, --use-angle=swiftshader)"},
        "model": f"chair (shipped bundle, K={model.num_keypoints}, M={len(model.prior.components_)})",
        "sizes": {},
    }
    workdir = Path(tempfile.mkdtemp(prefix="kpd-bench-morph-"))
    try:
        for name in args.sizes.split(","):
            mesh = procedural_chair(edge=SIZES[name])
            shape = workdir / f"chair_{name}.ply"
            write_mesh(shape, mesh)
            glb = workdir / f"chair_{name}.glb"
            command_s, command_mib = run_command([sys.executable, "-m", "kpd.cli", "rig", "chair", str(shape),
                                                  "--out", str(glb)])
            start = time.perf_counter()
            rig = model.rig(mesh)
            bind_s = time.perf_counter() - start
            start = time.perf_counter()
            morph = MorphRig.from_rig(rig, model.prior)
            write_gltf(workdir / "api.glb", morph)
            targets_s = time.perf_counter() - start
            write_gltf(workdir / f"chair_{name}.gltf", morph)
            keypoint_bytes = len(gltf_bytes(morph, targets=[n for n in morph.names if n.startswith("keypoint_")]))
            page_bytes = len(gltf_bytes(morph, targets=[], basis=True))

            rng = np.random.default_rng(0)
            diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
            weights = {n: float(rng.normal() * (0.05 * diagonal if n.startswith(("keypoint_", "prior_")) else 1.0))
                       for n in morph.names}
            gltf = read_gltf(glb)
            from scipy.spatial import cKDTree

            _, index = cKDTree(mesh.vertices).query(gltf.positions[0])
            expected = rig.deform(morph.keypoints_at(weights))[index]
            error = float(np.abs(gltf.morphed(weights)[0] - expected).max() / diagonal)
            del gltf, expected
            entry = {
                "load_average_1min": round(os.getloadavg()[0], 2),  # other work on the machine (2 cores)
                "vertices": len(mesh.vertices),
                "triangles": len(mesh.triangles),
                "targets": len(morph.names),
                "kpd_rig_command_s": round(command_s, 2),
                "kpd_rig_command_peak_mib": round(command_mib),
                "bind_s": round(bind_s, 2),
                "targets_and_glb_s": round(targets_s, 2),
                "glb_mib": round(glb.stat().st_size / 2**20, 1),
                "gltf_plus_bin_mib": round(((workdir / f"chair_{name}.gltf").stat().st_size
                                            + (workdir / f"chair_{name}.bin").stat().st_size) / 2**20, 1),
                "max_error_over_diagonal": float(f"{error:.3g}"),
                "keypoint_targets_glb_mib": round(keypoint_bytes / 2**20, 1),
                "page_glb_mib": round(page_bytes / 2**20, 1),
            }
            print(f"{name}: {entry}", file=sys.stderr)
            if not args.no_page:
                entry["page"] = page_figures(shape, workdir)
                if name == "100k":  # the same drag drawn by three.js's morph targets, and without deformation
                    entry["page_other_drawing"] = page_figures(shape, workdir, ("three", "none"))
                print(f"{name}: page {entry['page']}", file=sys.stderr)
            result["sizes"][name] = entry
            for f in workdir.glob("chair_*"):
                f.unlink()
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    big = result["sizes"].get("100k")
    if big is not None:
        page = big.get("page", {})
        result["targets"] = {
            "kpd_rig_100k_s": 3.0, "first_picture_100k_ms": 3000.0, "drag_step_100k_ms": 50.0,
            "met": {"kpd_rig_100k": big["kpd_rig_command_s"] <= 3.0,
                    "first_picture_100k": page.get("first_picture_ms", float("inf")) <= 3000.0,
                    "drag_step_100k": page.get("drag_step_latency_ms_median", float("inf")) <= 50.0},
        }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
