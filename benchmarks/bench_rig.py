"""Speed of binding a mesh and of one keypoint edit; prints one JSON object.

For a procedural chair mesh at about 10k and 100k vertices, rigged with the shipped chair model
(``Model.rig``: predicted keypoints and influence, the authors' cage rule grown to enclose every vertex, MVC):

1. ``Model.rig`` time for a predicted shape (the training cage and the closer rig cage fitted, the influence
   transferred to it, MVC weights of every vertex against the rig cage, the edit basis and its straightening of
   slivers), best of a few repeats. Target: 100k vertices in <= 1.0 s on two cores (set when the rig was ``Rig.bind``
   on a 42-vertex cage).
2. One edit, ``rig.deform(keypoints, out=buffer)`` (``V0 + B @ dp``), median of many warm calls. Target: 100k
   vertices in <= 1 ms.
3. Machine-limit references measured in the same run on the same arrays: a plain numpy ``(V, K) @ (K, 3)`` matmul into
   a buffer, and a copy of the ``(V, 3)`` vertex array. ``edit / (matmul + copy)`` says how close an edit is to what
   the machine can do with those arrays at all (this machine is shared, so ratios travel better than times).

Usage: ``.venv/bin/python benchmarks/bench_rig.py [--repeats 500] > benchmarks/results/rig.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import numpy as np

from kpd.benchmark import best_seconds, median_ms
from kpd.procedural import procedural_chair
from kpd.runtime import Model

# grid spacing of the procedural chair's faces -> vertex count (0.52: 10,400; 0.16: about 100k)
SIZES = {"10k": 0.52, "100k": 0.16}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=500, help="timed edits per size (median reported)")
    parser.add_argument("--bind-repeats", type=int, default=3, help="timed binds per size (best reported)")
    args = parser.parse_args()

    model = Model.load("chair")
    result = {
        "benchmark": "kpd.rig bind and edit",
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count()},
        "model": f"chair (shipped bundle, K={model.num_keypoints}, C={model.num_cage_vertices})",
        "sizes": {},
    }
    for name, edge in SIZES.items():
        mesh = procedural_chair(edge=edge)
        prediction = model.predict(mesh)
        rig = model.rig(mesh, prediction=prediction)
        bind_s = best_seconds(lambda: model.rig(mesh, prediction=prediction), args.bind_repeats)
        plain_s = best_seconds(lambda: model.rig(mesh, prediction=prediction, straighten=False), args.bind_repeats)

        edited = rig.keypoints
        edited[0] += [0.0, 0.0, 1.0]  # one keypoint moved by 1 unit (the chair is 36 units tall)
        out = np.empty_like(mesh.vertices)
        edit_ms = median_ms(lambda: rig.deform(edited, out=out), args.repeats, warmup=20)

        basis = np.ascontiguousarray(rig.basis)
        offsets = np.ascontiguousarray(np.random.default_rng(0).normal(size=(basis.shape[1], 3)))
        product = np.empty((basis.shape[0], 3))
        matmul_ms = median_ms(lambda: np.matmul(basis, offsets, out=product), args.repeats)
        rest = np.ascontiguousarray(mesh.vertices)
        copy_ms = median_ms(lambda: np.copyto(out, rest), args.repeats)

        result["sizes"][name] = {
            "vertices": len(mesh.vertices),
            "bind_s": round(bind_s, 3),
            "bind_without_straightening_s": round(plain_s, 3),
            "slivers_straightened": bool(rig.correction is not None),
            "edit_ms": round(edit_ms, 4),
            "numpy_matmul_ms": round(matmul_ms, 4),
            "numpy_copy_ms": round(copy_ms, 4),
            "edit_over_matmul_plus_copy": round(edit_ms / (matmul_ms + copy_ms), 2),
        }
    big = result["sizes"]["100k"]
    result["targets"] = {
        "bind_100k_s": 1.0, "edit_100k_ms": 1.0,
        "met": {"bind_100k": big["bind_s"] <= 1.0, "edit_100k": big["edit_ms"] <= 1.0},
    }
    result["machine"]["load_average_1min"] = round(os.getloadavg()[0], 2)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
