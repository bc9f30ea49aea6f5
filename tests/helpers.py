"""What several test modules share: the ``kpd`` command run in this process or in a fresh one, small meshes and
files made here, the torch-free toy bundle, and the checks of files by the consumers the project installs.

Fixtures live in ``conftest.py``; helpers of one topic in ``viewer_helpers``, ``rig_shapes``, ``scan_shapes`` and
``fuzzing``.
"""

from __future__ import annotations

import io
import json
import os
import random
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from hypothesis import strategies as st

from kpd import onnx_contract as contract
from kpd.bundle import build_manifest, write_bundle
from kpd.cage import icosphere
from kpd.cli import main
from kpd.io import Mesh
from kpd.prior import KeypointPrior

REPO = Path(__file__).resolve().parents[1]
TOLERANCE = 1e-5  # of the box diagonal: float32 positions and displacements
TRIANGLE = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
TURN_ONTO_SIDE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z (up) -> y


# --- the command ---------------------------------------------------------------------------------------------------


def kpd(*argv, capture=None):
    """``kpd ARGV`` through ``kpd.cli.main`` in this process: its exit status, or with ``capture`` (pytest's
    ``capfd`` or ``capsys``) the tuple (status, stdout, stderr) it printed."""
    code = main([str(a) for a in argv])
    if capture is None:
        return code
    out, err = capture.readouterr()
    return code, out, err


def kpd_process(*argv: str, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """``kpd ARGV`` run in a fresh interpreter from the repository's root."""
    return subprocess.run([sys.executable, "-m", "kpd.cli", *map(str, argv)], capture_output=True, text=True,
                          env=env, timeout=timeout, cwd=REPO)


def peak_of(argv: list[str]) -> tuple[subprocess.CompletedProcess, float]:
    """Run ``argv`` under a Python parent that reports the child's peak resident memory (bytes) on stdout."""
    probe = ("import resource, subprocess, sys; done = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
             "sys.stderr.write(done.stderr); sys.stdout.write(done.stdout); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024); sys.exit(done.returncode)")
    done = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, timeout=600)
    return done, float(done.stdout.splitlines()[-1])


# --- small meshes --------------------------------------------------------------------------------------------------


BOX_TRIANGLES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                          [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)


def box(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """The closed, outward-facing box [lo, hi]: vertices (8, 3) float64 and triangles (12, 3) int64."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return v, BOX_TRIANGLES.copy()


def box_mesh(size=(1.0, 1.0, 1.0), offset=(0.0, 0.0, 0.0)) -> Mesh:
    """The box of ``size`` with its lowest corner at ``offset``: 8 vertices, 12 triangles."""
    offset = np.asarray(offset, float)
    return Mesh(*box(offset, offset + np.asarray(size, float)))


def subdivided_box(size, subdivisions: int, shift) -> Mesh:
    """Open3D's box of ``size`` (lowest corner at the origin) with its triangles split ``subdivisions`` times at
    their midpoints, moved by ``-shift``: enough vertices to sample and to draw."""
    import open3d as o3d

    made = o3d.geometry.TriangleMesh.create_box(*size).subdivide_midpoint(subdivisions)
    return Mesh(np.asarray(made.vertices) - shift, np.asarray(made.triangles, dtype=np.int64))


def tall_box(height_axis: int) -> Mesh:
    """A box three times taller than wide along ``height_axis``."""
    box = subdivided_box((0.3, 0.3, 0.3), 3, 0.15)  # enough points to scan
    vertices = box.vertices.copy()
    vertices[:, height_axis] *= 3.0
    return Mesh(vertices, box.triangles)


def two_sided_box(green_out: bool, green_first: bool) -> Mesh:
    """``tall_box(2)`` with each face stored twice, once each way round (as ShapeNet stores a cup's label over its
    inside): green (material 1) on the side facing out when ``green_out`` (else in), white (material 0) on the other;
    the green copies first in the file when ``green_first``."""
    box = tall_box(2)
    t = len(box.triangles)
    outward = np.cross(*(box.vertices[box.triangles[:, k]] - box.vertices[box.triangles[:, 0]] for k in (1, 2)))
    out = np.where(((outward * box.vertices[box.triangles].mean(axis=1)).sum(axis=1) > 0)[:, None],
                   box.triangles, box.triangles[:, ::-1])  # every triangle wound to face out
    green, white = (out, out[:, ::-1]) if green_out else (out[:, ::-1], out)
    textures = [np.full((1, 1, 3), 235, np.uint8), np.array([[[40, 200, 40]]], np.uint8)]  # white, green
    return Mesh(box.vertices, np.vstack([green, white] if green_first else [white, green]),
                triangle_uvs=np.zeros((6 * t, 2)), textures=textures,
                triangle_material_ids=np.repeat([1, 0] if green_first else [0, 1], t))


def sphere_mesh(seed=0, *, normals=True, colors=True, uvs=False, textures=0, resolution=4):
    """A closed mesh with irregular coordinates; UVs sit on texel centres so lookups survive float32 rounding."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    base = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    v = np.asarray(base.vertices) * [1.7, 0.9, 1.3] + rng.normal(scale=0.01, size=(len(base.vertices), 3)) + 3.21
    t = np.asarray(base.triangles).astype(np.int64)
    mesh_textures, ids, tri_uvs = [], None, None
    if uvs or textures:
        h, w = 8, 16
        texel = rng.integers(0, [w, h], size=(3 * len(t), 2))
        tri_uvs = (texel + 0.5) / [w, h]
    if textures:
        mesh_textures = [rng.integers(0, 256, size=(8, 16, 3), dtype=np.uint8) for _ in range(textures)]
        ids = np.sort(rng.integers(0, textures, size=len(t)))  # sorted: every writer keeps this triangle order
        ids[:textures] = np.arange(textures)
        ids = np.sort(ids)
    return Mesh(
        vertices=v,
        triangles=t,
        vertex_normals=v / np.linalg.norm(v, axis=1, keepdims=True) if normals else None,
        vertex_colors=rng.random((len(v), 3)) if colors else None,
        triangle_uvs=tri_uvs,
        textures=mesh_textures,
        triangle_material_ids=ids,
    )


def height_field(n=6):
    """A bumpy (n x n) height field: vertices (n*n, 3), triangles (2(n-1)^2, 3)."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    vertices = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j) for i in range(n - 1)
             for j in range(n - 1)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return vertices, triangles


def star_cage(radii):
    """The level-1 icosphere with each vertex moved along its ray to radius ``radii[j]``."""
    template = icosphere(1)
    return template.vertices / 1.4 * np.asarray(radii, dtype=float)[:, None], template.faces


def points_near_the_cage(v, f, rng, distance, n, *, exact=False):
    """Points at ``distance`` from ``n`` random vertices, edges and faces of the cage: near a vertex, near an edge,
    just outside and just inside a face, near a face's plane beyond the face; with ``exact``, also points exactly on
    vertices, edges and faces."""
    faces = rng.integers(0, len(f), n)
    p0, p1, p2 = (v[f[faces, k]] for k in range(3))
    normal = np.cross(p1 - p0, p2 - p0)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    t = rng.uniform(0, 1, (n, 1))
    on_face = np.einsum("nk,nki->ni", rng.dirichlet([1, 1, 1], n), np.stack([p0, p1, p2], axis=1))
    near = [p0 + distance * direction, t * p0 + (1 - t) * p1 + distance * direction, on_face + distance * normal,
            on_face - distance * normal, 1.3 * p0 - 0.15 * p1 - 0.15 * p2 + distance * normal]
    on = [p0[:5], (t * p0 + (1 - t) * p2)[:5], on_face[:5]] if exact else []
    return np.concatenate(near + on)


# --- reading meshes back -------------------------------------------------------------------------------------------


def corners(mesh, name):
    """Per-triangle-corner values (T, 3, d): independent of vertex order and of vertices split at UV seams."""
    if name == "uvs":
        return None if mesh.triangle_uvs is None else mesh.triangle_uvs.reshape(-1, 3, 2)
    values = {"xyz": mesh.vertices, "normals": mesh.vertex_normals, "colors": mesh.vertex_colors}[name]
    return None if values is None else values[mesh.triangles]


def texels(mesh):
    """The texel colour at every triangle corner: (3T, C) uint8."""
    ids = np.zeros(len(mesh.triangles), int) if mesh.triangle_material_ids is None else mesh.triangle_material_ids
    out = []
    for corner, (u, v) in enumerate(mesh.triangle_uvs):
        tex = mesh.textures[ids[corner // 3]]
        h, w = tex.shape[:2]
        out.append(tex[int((1 - v) * h), int(u * w)])
    return np.array(out)


def corresponding(rest_positions: np.ndarray, mesh: Mesh, tolerance: float = 1e-6) -> np.ndarray:
    """Index of the mesh vertex at each written position (coincident vertices deform alike), which must lie within
    ``tolerance`` of the box diagonal of it."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(mesh.vertices).query(rest_positions)
    assert distance.max() < tolerance * np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    return index


# --- files made here -----------------------------------------------------------------------------------------------


def write_text(path, text):
    path.write_text(text)
    return path


def image_bytes(color, size=(16, 8), fmt="JPEG") -> bytes:
    """A JPEG (or ``fmt``) picture of one colour whose top half is red, so its orientation shows."""
    from PIL import Image

    image = np.zeros((size[1], size[0], 3), np.uint8)
    image[:] = color
    image[: size[1] // 2, :, 0] = 255  # top half differs: orientation is visible
    out = io.BytesIO()
    Image.fromarray(image).save(out, format=fmt)
    return out.getvalue()


def make_obj(folder: Path) -> Path:
    """An OBJ as exporters write them: two materials with maps in a folder of their own (a JPEG and a PNG), one with a
    colour only, faces without texture coordinates beside faces with them, groups, smoothing groups, a polyline,
    comments, CRLF-free text with tabs."""
    models = folder / "models"
    maps = models / "images"  # inside the OBJ's folder tree: kpd reads nothing outside it (kpd.io.references)
    maps.mkdir(parents=True)
    (maps / "wood.jpg").write_bytes(image_bytes((120, 80, 40)))
    (maps / "label.png").write_bytes(image_bytes((20, 60, 200), fmt="PNG"))
    (models / "thing.mtl").write_text(
        "# made by a test\nnewmtl wood\nKd 1 1 1\nKs 0.2 0.2 0.2\nmap_Kd images/wood.jpg\n\n"
        "newmtl red\nKd 0.9 0.1 0.1\nillum 2\n\nnewmtl label\nKd 1 1 1\nmap_Kd -s 1 1 1 images/label.png\n"
        "bump images/wood.jpg\n")
    vertices, triangles = height_field()
    rng = np.random.default_rng(0)
    lines = ["# exported by a test", "mtllib thing.mtl", "o thing"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in rng.random((len(vertices), 2))]
    face_normals = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                            vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
    lines += [f"vn {a:.6f} {b:.6f} {c:.6f}" for a, b, c in face_normals]
    T = len(triangles)
    for j, (a, b, c) in enumerate(triangles + 1):
        if j == 0:
            lines += ["g seat", "usemtl wood", "s 1"]
        if j == T // 3:
            lines += ["g legs", "usemtl red", "s off"]
        if j == 2 * T // 3:
            lines += ["g label", "usemtl label"]
        n = j + 1
        if T // 3 <= j < 2 * T // 3 or j % 5 == 0:  # no texture coordinates: the red part, and some others
            lines.append(f"f\t{a}//{n} {b}//{n} {c}//{n}")
        else:
            lines.append(f"f {a}/{a}/{n} {b}/{b}/{n} {c}/{c}/{n}")
    lines.append("l 1 2 3")
    (models / "thing.obj").write_text("\n".join(lines) + "\n")
    return models / "thing.obj"


def random_words(rng: random.Random, n: int) -> list[str]:
    """Numbers as files write them: every common format, signs, leading zeros, long mantissas, exponents near the
    ends of float64's range, subnormals, and decimals half-way between two neighbouring float64 values."""
    formats = ["%.9g", "%.17g", "%.6f", "%e", "%.3f", "%g", "%.20f", "%+.4e", "%.0f", "%.12E", "%.15g", "%.16g", "%r"]
    words = []
    for _ in range(n):
        r = rng.random()
        if r < 0.05:
            words.append(rng.choice(["0", "-0", "0.0", "-0.000", "+0", "00012.5000", ".5", "5.", "-.25e1", "1e22",
                                     "1e23", "9007199254740993", "9007199254740992", "123456789012345678901234",
                                     "1e-22", "1e-23", "4.9e-324", "2.2250738585072014e-308", "1.7976931348623157e308",
                                     "1e308", "1e-310", "0.1", "0.30000000000000004", "1.0000000000000002",
                                     "0.000000000000000000000000001", "1E5", "1e+05", "1e-05", "+3.25"]))
            continue
        if r < 0.15:  # the decimal half-way between two float64 values: only exact rounding gets it right
            x = rng.uniform(-1e6, 1e6) * 10.0 ** rng.randint(-5, 5)
            words.append(str((Decimal(x) + Decimal(float(np.nextafter(x, np.inf)))) / 2))
            continue
        x = rng.uniform(-10, 10) * 10.0 ** rng.randint(-40, 40)
        words.append((rng.choice(formats) % x) if rng.random() < 0.97 else repr(x))
    return words


finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=64)  # coordinates for hypothesis


# --- the toy bundle ------------------------------------------------------------------------------------------------


HIDDEN = 16


def toy_weights(k: int = 4, c: int = 42, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "w1": rng.normal(0, 1.0, (3, HIDDEN)).astype(np.float32),
        "b1": rng.normal(0, 0.1, HIDDEN).astype(np.float32),
        "w2": rng.normal(0, 0.3, (HIDDEN, 3 * k)).astype(np.float32),
        "b2": rng.normal(0, 0.1, 3 * k).astype(np.float32),
        "w3": rng.normal(0, 0.3, (HIDDEN, k * c)).astype(np.float32),
        "b3": rng.normal(0, 0.1, k * c).astype(np.float32),
    }


def toy_reference(points: np.ndarray, w: dict, k: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    """numpy twin of the toy graphs: points (B, N, 3) -> keypoints (B, K, 3), influence (B, K, C)."""
    h = np.maximum(points.astype(np.float64) @ w["w1"] + w["b1"], 0).max(axis=1)  # (B, H)
    keypoints = np.clip((h @ w["w2"] + w["b2"]).reshape(-1, 3, k).transpose(0, 2, 1), -1, 1)
    influence = (h @ w["w3"] + w["b3"]).reshape(-1, k, c)
    return keypoints, influence


def _toy_graph(spec: contract.GraphSpec, w: dict, k: int, c: int, meta: dict, edit=None) -> bytes:
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    init = [numpy_helper.from_array(w["w1"], "w1"), numpy_helper.from_array(w["b1"], "b1"),
            numpy_helper.from_array(np.array([1], np.int64), "axis1")]
    nodes = [helper.make_node("MatMul", ["points", "w1"], ["h0"]), helper.make_node("Add", ["h0", "b1"], ["h1"]),
             helper.make_node("Relu", ["h1"], ["h2"]),
             helper.make_node("ReduceMax", ["h2", "axis1"], ["h"], keepdims=0)]
    if spec is contract.KEYPOINTS_GRAPH:
        init += [numpy_helper.from_array(w["w2"], "w2"), numpy_helper.from_array(w["b2"], "b2"),
                 numpy_helper.from_array(np.array([-1, 3, k], np.int64), "shape"),
                 numpy_helper.from_array(np.array(-1, np.float32), "lo"),
                 numpy_helper.from_array(np.array(1, np.float32), "hi")]
        nodes += [helper.make_node("MatMul", ["h", "w2"], ["f0"]), helper.make_node("Add", ["f0", "b2"], ["f1"]),
                  helper.make_node("Reshape", ["f1", "shape"], ["f2"]),
                  helper.make_node("Transpose", ["f2"], ["f3"], perm=[0, 2, 1]),
                  helper.make_node("Clip", ["f3", "lo", "hi"], [spec.output])]
        out_shape = [contract.BATCH_AXIS, k, 3]
    else:
        init += [numpy_helper.from_array(w["w3"], "w3"), numpy_helper.from_array(w["b3"], "b3"),
                 numpy_helper.from_array(np.array([-1, k, c], np.int64), "shape")]
        nodes += [helper.make_node("MatMul", ["h", "w3"], ["f0"]), helper.make_node("Add", ["f0", "b3"], ["f1"]),
                  helper.make_node("Reshape", ["f1", "shape"], [spec.output])]
        out_shape = [contract.BATCH_AXIS, k, c]
    graph = helper.make_graph(
        nodes, spec.key,
        [helper.make_tensor_value_info(contract.INPUT_NAME, TensorProto.FLOAT,
                                       [contract.BATCH_AXIS, contract.POINTS_AXIS, 3])],
        [helper.make_tensor_value_info(spec.output, TensorProto.FLOAT, out_shape)], init)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", contract.OPSET)])
    model.ir_version = 10
    for key, value in {**meta, contract.META_GRAPH: spec.key}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    if edit is not None:  # a hostile variant (the tests of self-contained bundles)
        edit(spec, model)
        return model.SerializeToString()
    onnx.checker.check_model(model)
    return model.SerializeToString()


def make_toy_bundle(path, *, k: int = 4, c: int = 42, seed: int = 0, prior: bool = True, template: bool = True,
                    graph_k: int | None = None, meta_version: str | None = None, up: str | None = "+z",
                    edit=None) -> Path:
    """Write a small valid bundle (or, with ``graph_k`` / ``meta_version``, one whose graphs disagree with it; with
    ``edit(spec, model)``, one whose graphs ``edit`` changed in place, the manifest sealed over them)."""
    w = toy_weights(graph_k or k, c, seed)
    meta = {contract.META_FORMAT: contract.FORMAT_NAME,
            contract.META_FORMAT_VERSION: meta_version or str(contract.FORMAT_VERSION),
            contract.META_KEYPOINTS: str(graph_k or k), contract.META_CAGE_VERTICES: str(c)}
    graphs = [_toy_graph(spec, w, graph_k or k, c, meta, edit) for spec in contract.GRAPHS]
    rng = np.random.default_rng(seed + 1)
    fitted = None
    if prior:
        base = rng.uniform(-0.8, 0.8, (k, 3))
        fitted = KeypointPrior(n_components=3).fit(base + 0.05 * rng.standard_normal((30, k, 3)))
    cage = icosphere(1, 1.4) if c == 42 else icosphere(2, 1.4)
    _, files = build_manifest(
        category="toy", keypoints_onnx=graphs[0], influence_onnx=graphs[1], cage=cage,
        shared_influence=rng.uniform(0, 1, (k, c)), m=5, point_count=256,
        cage_fit={"distance": 0.4, "iterations": 100, "step": 0.01}, prior=fitted,
        template_points=rng.uniform(-1, 1, (100, 3)) if template else None, template_source="random",
        up=up, training={"data": "none", "command": "make_toy_bundle", "seed": seed, "iterations": 0, "metrics": {}},
    )
    return write_bundle(path, files)


# --- consumers the project installs --------------------------------------------------------------------------------


def needs(path: Path, what: str) -> None:
    """A consumer installed by the project's set-up (make web / make blender): missing fails under CI."""
    if not path.exists():
        message = f"{what} not installed at {path} (run make test, which installs it)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)


def validate(path: Path) -> dict:
    """The Khronos glTF Validator's report of a file (resources beside a .gltf are read)."""
    needs(REPO / "node_modules" / "gltf-validator", "the Khronos glTF Validator (npm gltf-validator)")
    script = """
    const validator = require(process.argv[1]);
    const fs = require('fs'), path = require('path');
    const file = process.argv[2];
    validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {uri: path.basename(file), maxIssues: 1000,
        externalResourceFunction: (uri) => new Promise((resolve, reject) => {
            try { resolve(new Uint8Array(fs.readFileSync(path.join(path.dirname(file), decodeURIComponent(uri))))); }
            catch (error) { reject(error.toString()); } })})
      .then((report) => console.log(JSON.stringify(report)), (error) => { console.error(error); process.exit(1); });
    """
    result = subprocess.run(["node", "-e", script, str(REPO / "node_modules" / "gltf-validator"), str(path)],
                            capture_output=True, text=True, timeout=120, check=True)
    return json.loads(result.stdout)
