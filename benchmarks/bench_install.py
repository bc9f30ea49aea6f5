"""kpd as a user installs it: the wheel's size, pip's install into a new venv without torch, and each runtime
command's first run there from an empty folder; prints one JSON object.

* ``dist``: the sizes of the sdist and the wheel (``make dist``'s build: ``python -m build``, or ``--dist DIR`` of a
  build already made) and of the new venv once installed;
* ``pip_install_s``: ``pip install WHEEL`` into a new venv, wall time: from the package index (``index``, every
  dependency downloaded, as a first install does) and from a local folder of the same wheels (``wheelhouse``,
  ``pip install --no-index --find-links``: what a warm cache gives, with no download);
* ``commands``: each command from an empty folder in that venv, wall time, ``first_s`` with an empty compiled-kernel
  cache and home folder of its own (numba compiles every kernel the command needs, as on a first run after an
  install) and ``then_s`` with them filled. The shapes are a user's: a ShapeNet chair (y up, ``--scan --up y``)
  and a Google Scanned Objects shoe from the real data; ``view --browser`` until the page's address is printed.

Usage: ``.venv/bin/python benchmarks/bench_install.py [--dist dist] > benchmarks/results/install.json``
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

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KPD_DATA", ROOT.parent / "shared" / "data"))
CHAIR = DATA / "keypointnet" / "models" / "03001627" / "88382b877be91b2a572f8e1c1caad99e" / "model_normalized.obj"
OTHER_CHAIR = DATA / "keypointnet" / "models" / "03001627" / "eaf231f17fccb96d81dff5c2e57ad46e" / "model.obj"
SHOES = DATA / "gso_shoes"


def run(argv: list, **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run([str(a) for a in argv], capture_output=True, text=True, **kwargs)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, argv))} failed: {done.stderr.strip()[-2000:]}")
    return done


def timed(argv: list, **kwargs) -> float:
    start = time.perf_counter()
    run(argv, **kwargs)
    return round(time.perf_counter() - start, 1)


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file() and not p.is_symlink()]
    return round(sum(p.stat().st_size for p in files) / 1e6, 1)


def until_address(argv: list, **kwargs) -> float:
    """Wall seconds until ``kpd view --browser`` prints the page's address; the server is then stopped."""
    start = time.perf_counter()
    server = subprocess.Popen([str(a) for a in argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              **kwargs)
    try:
        for line in server.stdout:
            if "http://" in line:
                return round(time.perf_counter() - start, 1)
        raise SystemExit(f"kpd view --browser printed no address: {server.stderr.read()[-2000:]}")
    finally:
        server.terminate()
        server.wait(30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dist", type=Path, default=None, help="a folder with make dist's sdist and wheel "
                                                                "(default: build them)")
    args = parser.parse_args()
    from kpd.benchmark import machine_cpu

    result: dict = {
        "benchmark": "pip install of the wheel into a new venv without torch, and each command's first run there",
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "cpu": machine_cpu(),
                    "load_average_1min_start": round(os.getloadavg()[0], 2)},
    }
    with tempfile.TemporaryDirectory(prefix="kpd-bench-install-") as scratch:
        scratch = Path(scratch)
        dist = args.dist
        if dist is None:
            dist = scratch / "dist"
            result["build_s"] = timed([sys.executable, "-m", "build", "--outdir", dist, ROOT], cwd=ROOT)
        (sdist,), (wheel,) = dist.glob("kpd-*.tar.gz"), dist.glob("kpd-*.whl")
        result["dist"] = {"wheel": wheel.name, "wheel_mb": size_mb(wheel), "sdist_mb": size_mb(sdist)}

        times = {}
        venv = scratch / "venv-index"
        run([sys.executable, "-m", "venv", venv])
        times["index"] = timed([venv / "bin" / "python", "-m", "pip", "install", "-q", wheel])
        wheelhouse = scratch / "wheelhouse"
        run([venv / "bin" / "python", "-m", "pip", "download", "-q", "--dest", wheelhouse, wheel])
        shutil.rmtree(venv)
        venv = scratch / "venv"
        run([sys.executable, "-m", "venv", venv])
        times["wheelhouse"] = timed([venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-index",
                                     "--find-links", wheelhouse, wheel])
        result["pip_install_s"] = times
        print(f"pip install: {times}", file=sys.stderr)
        result["dist"]["venv_mb"] = size_mb(venv)
        torch = run([venv / "bin" / "python", "-c", "import importlib.util as u; print(u.find_spec('torch'))"])
        result["torch_installed"] = torch.stdout.strip() != "None"

        work = scratch / "work"
        work.mkdir()
        shoes = work / "my_shoes"
        shoes.mkdir()
        names = sorted(p.name for p in SHOES.iterdir())[:4]
        for name in names:
            shutil.copyfile(SHOES / name / "model.obj", shoes / f"{name}.obj")
        (shoes / "test.txt").write_text("".join(f"{n}\n" for n in names))
        shoe = shoes / f"{names[0]}.obj"
        cases = {
            "demo": ["demo", "--out", "demo", "--force"],
            "keypoints": ["keypoints", "chair", CHAIR, "--scan", "--up", "y", "--out", "kp.json", "--force"],
            "deform": ["deform", "chair", CHAIR, "--scan", "--up", "y", "--move", "8:0,0.05,0", "--out",
                       "taller.obj", "--force"],
            "align": ["align", "chair", CHAIR, OTHER_CHAIR, "--out", "aligned.obj", "--force"],
            "sample": ["sample", "chair", CHAIR, "--n", "2", "--out", "variants", "--force"],
            "render": ["render", "chair", CHAIR, "--scan", "--up", "y", "--out", "chair.png", "--force"],
            "rig": ["rig", "shoe", shoe, "--out", "shoe.glb", "--force"],
            "scan": ["scan", shoe, "--model", "shoe", "--out", "shoe_aligned.ply", "--report", "report.json",
                     "--force"],
            "eval chamfer": ["eval", "chamfer", shoes, "--model", "shoe", "--pairs", "2", "--out", "chamfer.json",
                             "--force", "--quiet"],
            "bench": ["bench", "chair", "--vertices", "2000", "--repeats", "1"],
            "view --browser": ["view", "chair", CHAIR, "--scan", "--up", "y", "--browser", "--port", "0"],
        }
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "DISPLAY",
                                                                "WAYLAND_DISPLAY", "KPD_CACHE")}
        commands = {}
        for name, argv in cases.items():
            home = scratch / f"home-{len(commands)}"
            home.mkdir()
            case_env = dict(env, HOME=str(home), NUMBA_CACHE_DIR=str(home / "numba"))
            measure = until_address if name == "view --browser" else timed
            first = measure([venv / "bin" / "kpd", *argv], cwd=work, env=case_env)
            commands[name] = {"first_s": first, "then_s": measure([venv / "bin" / "kpd", *argv], cwd=work,
                                                                  env=case_env)}
            print(f"{name}: {commands[name]}", file=sys.stderr)
        result["commands"] = commands
    result["machine"]["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
