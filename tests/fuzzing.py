"""Fuzzing kpd's readers: real files of every format, mutated at random, read by the public readers in a worker
process that watches for what a stranger's file must never cause.

Shared by ``tests/test_fuzz.py`` (a seeded sample in the suite) and ``benchmarks/bench_fuzz.py`` (a long run).

The inputs are written at run time by kpd's own writers from a small real mesh (ModelNet10's chair_0890 decimated,
with UVs and a texture; kpd's procedural chair when the data is absent): PLY binary and ASCII, OBJ with its MTL and
map, OFF, STL, glTF with its images and buffer, GLB, PCD, keypoints as JSON and text, a rig (:meth:`kpd.rig.Rig.save`)
and the shipped shoe bundle as a folder and as a zip. Case ``i`` of seed ``s`` is one format (in turn), one reader
and one to three mutations, drawn from ``numpy.random.default_rng([s, i])``: :func:`make_case` rebuilds it alone.

Mutations: bytes flipped, runs cut out, repeated or inserted, the file truncated; a number of the text (biased to the
header) or a 32-bit field of the binary header set to a huge, negative or boundary value; a line repeated or
dropped; a JSON value (glTF, keypoints, the bundle's manifest) replaced by a huge count, a negative number, a wrong
type or a deep nesting; references redirected (``mtllib``, MTL maps, glTF ``uri``) to files outside the input's
folder, ``/proc/self/environ``, absolute paths, devices, a symlink out of the folder, a FIFO; rigs and bundles changed
with their hashes recomputed (so that the checks behind the hash are reached: arrays of the wrong shape, type or
value, an ``.npy`` header declaring a huge shape), and a member that inflates to more than a GiB.

Each case runs in a worker process (:class:`Runner`) that reports, per case: an exception that is not a
:class:`kpd.errors.KpdError` (``traceback``), no answer within the time limit (``hang``, the worker is replaced and
the stack it hung in kept), an address space above its start plus 1 GiB (``memory``: ``RLIMIT_AS`` turns the
allocation into a ``MemoryError``; the peak resident size is measured per case through ``VmHWM``, reset before each
case), a file opened outside the input's folder (``outside``: an audit hook on ``open`` events, paths resolved
through symlinks; the Python installation, kpd's own package and a few system files are allowed), or the worker
dying (``crash``: a native fault). Each failure names the innermost frame in ``kpd`` (its file and line), so that a
finding points at the module to fix.
"""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import re
import shutil
import struct
import sys
import time
import zipfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

FORMATS = ("ply_binary", "ply_ascii", "obj", "off", "stl", "gltf", "glb", "pcd", "keypoints_json", "keypoints_txt",
           "rig", "bundle_dir", "bundle_zip")
READERS = {
    "ply_binary": ("read_mesh", "read_points", "read_shape"),
    "ply_ascii": ("read_mesh", "read_points", "read_shape"),
    "obj": ("read_mesh", "read_points", "read_shape"),
    "off": ("read_mesh", "read_points", "read_shape"),
    "stl": ("read_mesh", "read_points", "read_shape"),
    "gltf": ("read_mesh", "read_points", "read_shape"),
    "glb": ("read_mesh", "read_points", "read_shape"),
    "pcd": ("read_points",),
    "keypoints_json": ("read_keypoints",),
    "keypoints_txt": ("read_keypoints",),
    "rig": ("Rig.load",),
    "bundle_dir": ("read_bundle",),
    "bundle_zip": ("read_bundle",),
}
MAIN = {"ply_binary": "mesh.ply", "ply_ascii": "mesh.ply", "obj": "mesh.obj", "off": "mesh.off", "stl": "mesh.stl",
        "gltf": "mesh.gltf", "glb": "mesh.glb", "pcd": "points.pcd", "keypoints_json": "keypoints.json",
        "keypoints_txt": "keypoints.txt", "rig": "rig.npz", "bundle_dir": "shoe.kpd", "bundle_zip": "shoe.kpd.zip"}
MEMORY_LIMIT = 1 << 30  # bytes of address space a case may add to the worker's
TIMEOUT = 30.0  # seconds a case may take
BOMB_BYTES = 3 << 29  # 1.5 GiB of zeros, deflated to about 1.5 MB: more than a case may hold

# the values a declared count, size or index is set to
HUGE_INTS = (0, 1, -1, 2, 3, 255, 256, 65535, 65536, 2**24, 2**26, 2**28, 2**31 - 1, 2**31, -(2**31), 2**32 - 1, 2**32,
             2**33, 2**53 + 1, 2**63 - 1, 2**63, 2**64, -(2**63), 10**30)
NUMBER_WORDS = [str(v) for v in HUGE_INTS] + ["-0", "1e308", "-1e308", "1e309", "nan", "inf", "-inf", "0x10", "1.5",
                                             "1" + "0" * 400, "-" + "9" * 60, "3abc", ""]
U32 = (0, 1, 2, 3, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 0xFFFFFFFE, 0x10000, 0x4000000, 0x10000000)
JSON_VALUES = [*HUGE_INTS, 1e308, -1e308, 0.5, -0.5, None, True, False, "", "x", "../secret.png", "/proc/self/environ",
               [], {}, [[]], [None], {"x": 1}, ["a", 1], "A" * 5000, [0] * 1000]

# what a reference is pointed at; {secret} is an absolute path outside the input's folder
REFERENCES = ("../secret.png", "../secret.txt", "{secret}", "/proc/self/environ", "/etc/passwd", "/dev/zero",
              "/dev/urandom", "link.png", "fifo.png", "sub/../../secret.png", "%2E%2E/secret.png", "..%2Fsecret.png",
              "%2Fetc%2Fpasswd", "file:///etc/passwd", "http://example.invalid/x.png", ".", "", "folder", "missing.png",
              "%00x.png", "x\u0000.png", "C:\\secret.png", "A" * 5000 + ".png", "data:image/png;base64,!!!",
              "data:application/octet-stream;base64,AAAA", "texture.png")


# --- the inputs -----------------------------------------------------------------------------------------------------


def small_mesh(data_dir: Path | None = None):
    """A small real mesh (:class:`kpd.mesh.Mesh`, about 200 triangles) with normals, colours, UVs and a 4x4 texture:
    ModelNet10's chair_0890 decimated when ``data_dir`` holds it, else kpd's procedural chair decimated."""
    import open3d as o3d

    from kpd.io import Mesh, read_mesh
    from kpd.procedural import procedural_chair

    source = None if data_dir is None else Path(data_dir) / "modelnet10" / "chair" / "test" / "chair_0890.ply"
    mesh = read_mesh(source) if source is not None and source.is_file() else procedural_chair()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                  o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    m = m.simplify_quadric_decimation(200)
    m.remove_unreferenced_vertices()
    m.compute_vertex_normals()
    vertices, triangles = np.asarray(m.vertices), np.asarray(m.triangles).astype(np.int64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    unit = (vertices - lo) / np.maximum(hi - lo, 1e-9)
    texture = (np.arange(48, dtype=np.uint8).reshape(4, 4, 3) * 5).astype(np.uint8)
    return Mesh(vertices=vertices, triangles=triangles, vertex_normals=np.asarray(m.vertex_normals),
                vertex_colors=np.clip(unit, 0.0, 1.0), triangle_uvs=unit[triangles.reshape(-1)][:, :2],
                textures=[texture], triangle_material_ids=np.zeros(len(triangles), np.int64))


def make_seeds(root: Path, data_dir: Path | None = None) -> Path:
    """Write one real file (with its companions) of every format under ``root/seeds/<format>/``, the secrets a
    redirected reference points at, and the members that inflate beyond the memory limit; returns ``root``."""
    import open3d as o3d

    from kpd.bundle import MODELS_DIR
    from kpd.geometry import Normalizer
    from kpd.io import Mesh, write_keypoints, write_mesh, write_points
    from kpd.io.images import encode_png
    from kpd.rig import Rig

    root = Path(root)
    seeds = root / "seeds"
    mesh = small_mesh(data_dir)
    plain = Mesh(vertices=mesh.vertices, triangles=mesh.triangles, vertex_normals=mesh.vertex_normals,
                 vertex_colors=mesh.vertex_colors)
    for fmt in FORMATS:
        (seeds / fmt).mkdir(parents=True, exist_ok=True)
    write_mesh(seeds / "ply_binary" / MAIN["ply_binary"], plain)
    ascii_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(plain.vertices),
                                           o3d.utility.Vector3iVector(plain.triangles.astype(np.int32)))
    ascii_mesh.vertex_normals = o3d.utility.Vector3dVector(plain.vertex_normals)
    ascii_mesh.vertex_colors = o3d.utility.Vector3dVector(plain.vertex_colors)
    o3d.io.write_triangle_mesh(str(seeds / "ply_ascii" / MAIN["ply_ascii"]), ascii_mesh, write_ascii=True)
    for fmt in ("obj", "gltf", "glb"):
        write_mesh(seeds / fmt / MAIN[fmt], mesh)
    write_mesh(seeds / "off" / MAIN["off"], plain)
    write_mesh(seeds / "stl" / MAIN["stl"], plain)
    write_points(seeds / "pcd" / MAIN["pcd"], plain.vertices, plain.vertex_normals, plain.vertex_colors)
    normalizer = Normalizer().fit(mesh.vertices)
    keypoints = normalizer.apply(mesh.vertices[np.linspace(0, len(mesh.vertices) - 1, 8).astype(int)])
    write_keypoints(seeds / "keypoints_json" / MAIN["keypoints_json"], normalizer.invert(keypoints),
                    category="chair", note="fuzz seed")
    write_keypoints(seeds / "keypoints_txt" / MAIN["keypoints_txt"], normalizer.invert(keypoints))
    Rig.bind(plain, keypoints, normalizer=normalizer).save(seeds / "rig" / MAIN["rig"])
    shipped = MODELS_DIR / "shoe.kpd"
    shutil.copytree(shipped, seeds / "bundle_dir" / MAIN["bundle_dir"], dirs_exist_ok=True)
    with zipfile.ZipFile(seeds / "bundle_zip" / MAIN["bundle_zip"], "w", zipfile.ZIP_STORED) as archive:
        for p in sorted(shipped.iterdir()):
            archive.write(p, f"shoe.kpd/{p.name}")
    png = encode_png(np.full((8, 8, 3), 200, np.uint8))
    (root / "secret.png").write_bytes(png)
    (root / "secret.txt").write_text("SECRET=fuzz\n")
    (root / "bombs").mkdir(exist_ok=True)
    _write_bombs(root / "bombs")
    return root


def _write_bombs(folder: Path) -> None:
    """``extra.npy.zip`` and ``extra.bin.zip``: archives of one member (deflated, level 1) of :data:`BOMB_BYTES`
    zeros (the ``.npy`` with its header), which :func:`_zip_with` splices into a case's archive."""
    for name in ("extra.npy", "extra.bin"):
        out = folder / (name + ".zip")
        if out.exists():
            continue
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
            with archive.open(name, "w", force_zip64=True) as fh:
                if name.endswith(".npy"):
                    np.lib.format.write_array_header_2_0(
                        fh, {"descr": "<f8", "fortran_order": False, "shape": (BOMB_BYTES // 8,)})
                chunk = bytes(1 << 24)
                for _ in range(BOMB_BYTES // len(chunk)):
                    fh.write(chunk)


# --- one case -------------------------------------------------------------------------------------------------------


class Case(NamedTuple):
    """A case: its number, format, reader, the mutations made (their names), and its files: relative path -> bytes,
    or ``("symlink", target)``, ``("fifo",)``, ``("folder",)``, ``("hardlink", source path)``, ``("sparse", size)``."""

    index: int
    format: str
    reader: str
    mutations: list
    files: dict
    main: str


def make_case(seeds_root: Path, seed: int, index: int) -> Case:
    """Case ``index`` of ``seed``: deterministic (``numpy.random.default_rng([seed, index])``)."""
    rng = np.random.default_rng([seed, index])
    fmt = FORMATS[index % len(FORMATS)]
    reader = READERS[fmt][int(rng.integers(len(READERS[fmt])))]
    folder = Path(seeds_root) / "seeds" / fmt
    files: dict[str, Any] = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            files[p.relative_to(folder).as_posix()] = ("hardlink", str(p))
    mutations: list[str] = []
    for _ in range(1 + int(rng.integers(3)) if rng.random() < 0.5 else 1):
        try:
            mutations.append(_MUTATORS[fmt](rng, files, Path(seeds_root)))
        except Exception:  # noqa: BLE001 - an earlier mutation broke the structure the mutator parses: bytes then
            mutations.append(_bytes_mutation(rng, files, MAIN[fmt] if fmt != "bundle_dir" else None))
    return Case(index, fmt, reader, mutations, files, MAIN[fmt])


def _data(files: dict, name: str) -> bytes:
    value = files[name]
    if isinstance(value, bytes):
        return value
    if value[0] == "hardlink":
        return Path(value[1]).read_bytes()
    return b""


def _pristine(files: dict, name: str) -> bool:
    """Whether ``name`` is still the seed's file, unmutated."""
    return isinstance(files.get(name), tuple) and files[name][0] == "hardlink"


def _pick_file(rng, files: dict, prefer: str | None = None) -> str:
    names = [n for n, v in files.items() if isinstance(v, bytes) or v[0] == "hardlink"]
    if prefer is not None and prefer in names and rng.random() < 0.7:
        return prefer
    return names[int(rng.integers(len(names)))]


# byte-level mutations of one file's content


def _flip(rng, data: bytes) -> tuple[bytes, str]:
    if not data:
        return data, "flip(empty)"
    b = bytearray(data)
    n = int(rng.integers(1, 9))
    head = rng.random() < 0.5
    for _ in range(n):
        i = int(rng.integers(min(len(b), 512) if head else len(b)))
        b[i] ^= int(rng.integers(1, 256))
    return bytes(b), f"flip({n})"


def _truncate(rng, data: bytes) -> tuple[bytes, str]:
    at = int(rng.integers(len(data) + 1)) if data else 0
    return data[:at], f"truncate({at})"


def _splice(rng, data: bytes) -> tuple[bytes, str]:
    if len(data) < 2:
        return data + bytes(rng.integers(0, 256, 16, dtype=np.uint8)), "splice(append)"
    i = int(rng.integers(len(data)))
    j = min(len(data), i + int(rng.integers(1, 256)))
    kind = int(rng.integers(3))
    if kind == 0:
        return data[:i] + data[j:], f"splice(cut {i}:{j})"
    if kind == 1:
        return data[:j] + data[i:j] * int(rng.integers(2, 50)) + data[j:], f"splice(repeat {i}:{j})"
    return data[:i] + bytes(rng.integers(0, 256, j - i, dtype=np.uint8)) + data[i:], f"splice(insert {i})"


_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _number(rng, data: bytes) -> tuple[bytes, str]:
    spans = [m.span() for m in _NUMBER.finditer(data[: 1 << 16])]
    if not spans:
        return _flip(rng, data)
    i, j = _choose_span(rng, spans, [s for s in spans if s[0] < 512])
    word = NUMBER_WORDS[int(rng.integers(len(NUMBER_WORDS)))]
    return data[:i] + word.encode() + data[j:], f"number({data[i:j].decode('ascii', 'replace')}->{word[:24]})"


def _choose_span(rng, spans: list, head: list) -> tuple[int, int]:
    pool = head if head and rng.random() < 0.6 else spans
    return pool[int(rng.integers(len(pool)))]


def _field32(rng, data: bytes) -> tuple[bytes, str]:
    if len(data) < 4:
        return _truncate(rng, data)
    limit = min(len(data) - 4, 128) if rng.random() < 0.6 else len(data) - 4
    at = int(rng.integers(limit + 1)) // 4 * 4
    value = U32[int(rng.integers(len(U32)))]
    return data[:at] + struct.pack("<I", value) + data[at + 4:], f"field32({at}={value:#x})"


def _lines(rng, data: bytes) -> tuple[bytes, str]:
    lines = data.split(b"\n")
    if len(lines) < 2:
        return _splice(rng, data)
    i = int(rng.integers(min(len(lines), 24))) if rng.random() < 0.5 else int(rng.integers(len(lines)))
    kind = int(rng.integers(3))
    if kind == 0:
        del lines[i]
        what = "drop"
    elif kind == 1:  # up to 2,000 times, and 1 MiB in all (a binary file's "line" may be megabytes)
        lines[i:i] = [lines[i]] * min(int(rng.integers(1, 2000)), max(1, (1 << 20) // max(len(lines[i]), 1)))
        what = "repeat"
    else:
        j = int(rng.integers(len(lines)))
        lines[i], lines[j] = lines[j], lines[i]
        what = "swap"
    return b"\n".join(lines), f"line({what} {i})"


_BYTES = (_flip, _truncate, _splice, _number, _field32, _lines)


def _bytes_mutation(rng, files: dict, prefer: str) -> str:
    name = _pick_file(rng, files, prefer)
    mutate = _BYTES[int(rng.integers(len(_BYTES)))]
    files[name], what = mutate(rng, _data(files, name))
    return f"{name}:{what}"


# structured mutations


def _json_paths(value, path=()):
    yield path
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _json_paths(v, path + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value[:64]):
            yield from _json_paths(v, path + (i,))


def _mutate_json(rng, value) -> tuple[Any, str]:
    """``value`` with one node replaced (a value of :data:`JSON_VALUES`), removed, or nested 100,000 deep."""
    paths = list(_json_paths(value))
    path = paths[int(rng.integers(len(paths)))]
    kind = rng.random()
    if not path:
        return JSON_VALUES[int(rng.integers(len(JSON_VALUES)))], "json(root)"
    parent = value
    for key in path[:-1]:
        parent = parent[key]
    if kind < 0.15 and isinstance(parent, dict):
        del parent[path[-1]]
        return value, f"json(del {'/'.join(map(str, path))})"
    new = JSON_VALUES[int(rng.integers(len(JSON_VALUES)))] if kind < 0.95 else "__DEEP__"
    parent[path[-1]] = new
    return value, f"json({'/'.join(map(str, path))}={str(new)[:30]})"


def _dump_json(value) -> bytes:
    text = json.dumps(value)
    return text.replace('"__DEEP__"', "[" * 100000 + "]" * 100000).encode()


def _reference(rng, root: Path) -> str:
    ref = REFERENCES[int(rng.integers(len(REFERENCES)))]
    return ref.replace("{secret}", str(root / "secret.png"))


def _add_traps(files: dict) -> None:
    """The symlink out of the folder, the FIFO and the folder a redirected reference may name."""
    files["link.png"] = ("symlink", "../secret.png")
    files["fifo.png"] = ("fifo",)
    files["folder"] = ("folder",)


def _mutate_obj(rng, files: dict, root: Path) -> str:
    if rng.random() < 0.4:
        _add_traps(files)
        target = _reference(rng, root)
        if rng.random() < 0.4:
            text = _data(files, "mesh.obj")
            line = b"mtllib " + target.encode()
            files["mesh.obj"] = re.sub(rb"(?m)^mtllib .*$", lambda _: line, text)
            return f"mtllib->{target[:40]}"
        mtl = next(n for n in files if n.endswith(".mtl"))
        text = _data(files, mtl)
        keys = (b"map_Kd", b"map_Ks", b"map_Ka", b"bump", b"map_Bump", b"map_d", b"disp", b"norm")
        key = keys[int(rng.integers(len(keys)))]
        if re.search(rb"(?m)^map_Kd .*$", text) and key == b"map_Kd":
            files[mtl] = re.sub(rb"(?m)^map_Kd .*$", lambda _: b"map_Kd " + target.encode(), text)
        else:
            files[mtl] = text.rstrip(b"\n") + b"\n" + key + b" " + target.encode() + b"\n"
        return f"{mtl}:{key.decode()}->{target[:40]}"
    return _bytes_mutation(rng, files, "mesh.obj")


def _mutate_gltf(rng, files: dict, root: Path) -> str:
    name = "mesh.gltf"
    doc = json.loads(_data(files, name))
    if rng.random() < 0.35:
        _add_traps(files)
        target = _reference(rng, root)
        holders = [x for x in doc.get("images", []) + doc.get("buffers", []) if isinstance(x, dict)]
        holder = holders[int(rng.integers(len(holders)))]
        holder["uri"] = target
        files[name] = json.dumps(doc).encode()
        return f"uri->{target[:40]}"
    if rng.random() < 0.6:
        doc, what = _mutate_json(rng, doc)
        files[name] = _dump_json(doc)
        return what
    return _bytes_mutation(rng, files, name)


def _glb_parts(data: bytes) -> tuple[dict, bytes] | None:
    try:
        length = struct.unpack_from("<I", data, 12)[0]
        return json.loads(data[20:20 + length]), data[20 + length:]
    except (struct.error, ValueError):
        return None


def _mutate_glb(rng, files: dict, root: Path) -> str:
    name = "mesh.glb"
    data = _data(files, name)
    parts = _glb_parts(data)
    if parts is not None and rng.random() < 0.6:
        doc, rest = parts
        if rng.random() < 0.3:
            _add_traps(files)
            target = _reference(rng, root)
            images = doc.setdefault("images", [{}])
            images[0] = {"uri": target}
            what = f"uri->{target[:40]}"
        else:
            doc, what = _mutate_json(rng, doc)
        body = _dump_json(doc)
        body += b" " * (-len(body) % 4)
        chunk = struct.pack("<II", len(body), 0x4E4F534A) + body + rest
        files[name] = struct.pack("<4sII", b"glTF", 2, 12 + len(chunk)) + chunk
        return "glb:" + what
    return _bytes_mutation(rng, files, name)


def _mutate_text(main: str):
    def mutate(rng, files: dict, root: Path) -> str:
        return _bytes_mutation(rng, files, main)
    return mutate


def _mutate_keypoints_json(rng, files: dict, root: Path) -> str:
    name = MAIN["keypoints_json"]
    if rng.random() < 0.5:
        doc, what = _mutate_json(rng, json.loads(_data(files, name)))
        files[name] = _dump_json(doc)
        return what
    return _bytes_mutation(rng, files, name)


_DTYPES = ("<i1", "<u1", "<i4", "<i8", "<u8", "<f2", "<f4", "<c16", "|b1", "<U4", "|S3", "<M8[s]", "|V8")


def _mutate_array(rng, a: np.ndarray) -> tuple[np.ndarray, str]:
    kind = int(rng.integers(6))
    if kind == 0 and a.ndim:
        return a[: int(rng.integers(len(a) + 1))], "rows"
    if kind == 1:
        shapes = [(0,), (0, 3), (1,), (3, 2), (a.size,), (2, 2, 2), ()]
        shape = shapes[int(rng.integers(len(shapes)))]
        return np.resize(a, shape) if a.size else np.zeros(shape), f"shape{shape}"
    if kind == 2:
        dtype = _DTYPES[int(rng.integers(len(_DTYPES)))]
        try:
            return a.astype(dtype), f"dtype {dtype}"
        except (TypeError, ValueError):
            return np.zeros(a.shape, dtype), f"dtype {dtype}"
    if kind == 3 and a.size and a.dtype.kind in "iuf":
        b = a.copy().reshape(-1)
        i = int(rng.integers(b.size))
        values = [-1, 2**31 - 1, -(2**31), 10**6] if b.dtype.kind in "iu" else [np.nan, np.inf, -np.inf, 1e300, 0.0]
        value = values[int(rng.integers(len(values)))]
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                b[i] = value
        except OverflowError:
            b[i] = -1 if b.dtype.kind == "i" else 0
        return b.reshape(a.shape), f"value[{i}]={value}"
    if kind == 4:
        return np.array("kpd-rig/9" if a.dtype.kind == "U" else 0), "scalar"
    return np.zeros(a.shape[:1] + (7,) if a.ndim else (7,), a.dtype if a.dtype.kind in "iufb" else "<f8"), "columns"


def _npz(arrays: dict, *, headers: dict | None = None) -> bytes:
    """An .npz of ``arrays`` (stored, not deflated); ``headers`` replaces the .npy header's shape of a member by
    another (the data as it was: a header that lies)."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for key, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
            data = buf.getvalue()
            if headers and key in headers:
                data = _lying_header(data, headers[key])
            archive.writestr(key + ".npy", data)
    return out.getvalue()


def _lying_header(data: bytes, shape: tuple) -> bytes:
    """An .npy's bytes with its header's shape replaced by ``shape`` (the header's length kept, padded)."""
    length = struct.unpack_from("<H", data, 8)[0]
    header = data[10:10 + length].decode("latin1")
    new = re.sub(r"'shape': \([^)]*\)", lambda _: f"'shape': {shape!r}", header)
    new = new.rstrip("\n ")
    if len(new) + 1 > length:
        return data
    return data[:10] + (new + " " * (length - len(new) - 1) + "\n").encode("latin1") + data[10 + length:]


def _zip_with(zip_bytes: bytes, bomb: Path) -> bytes:
    """The archive ``zip_bytes`` with the bomb archive's member added (both archives stored as written)."""
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(zip_bytes)) as src, zipfile.ZipFile(bomb) as extra, \
            zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            dst.writestr(info, src.read(info.filename))
        info = extra.infolist()[0]
        # the member's local entry and compressed bytes copied as they are (zipfile has no public call for that):
        # no 1.5 GiB inflated here
        dst.fp.seek(dst.start_dir)
        header_offset = dst.start_dir
        extra.fp.seek(info.header_offset)
        local = extra.fp.read(30)
        name_len, extra_len = struct.unpack_from("<HH", local, 26)
        rest = extra.fp.read(name_len + extra_len + info.compress_size)
        dst.fp.write(local + rest)
        info.header_offset = header_offset
        dst.start_dir = dst.fp.tell()
        dst.filelist.append(info)
        dst.NameToInfo[info.filename] = info
        dst._didModify = True
    return out.getvalue()


def _mutate_rig(rng, files: dict, root: Path) -> str:
    from kpd.io.integrity import HASH_KEY, content_hash

    name = MAIN["rig"]
    choice = rng.random()
    if not _pristine(files, name):  # a mutated archive is not parsed here: it may declare or inflate to GiBs
        return _bytes_mutation(rng, files, name)
    if choice < 0.12:
        files[name] = _zip_with(_data(files, name), root / "bombs" / "extra.npy.zip")
        return "bomb member"
    if choice < 0.35:
        return _bytes_mutation(rng, files, name)
    with np.load(io.BytesIO(_data(files, name)), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    keys = [k for k in arrays if k != HASH_KEY]
    key = keys[int(rng.integers(len(keys)))]
    headers = None
    if choice < 0.5:
        shape = [(2**28, 3), (2**40,), (3, 2**61), (-1, 3), (2**31, 2**31)][int(rng.integers(5))]
        headers = {key: shape}
        what = f"header {key} {shape}"
    elif choice < 0.58:
        del arrays[key]
        what = f"drop {key}"
    else:
        arrays[key], change = _mutate_array(rng, arrays[key])
        what = f"{key}:{change}"
    if rng.random() < 0.85:
        try:
            arrays[HASH_KEY] = np.array(content_hash(arrays))
            what += " (rehashed)"
        except TypeError:
            pass
    files[name] = _npz(arrays, headers=headers)
    return what


def _bundle_files(files: dict, folder: str) -> dict:
    return {n[len(folder) + 1:]: n for n in files if n.startswith(folder + "/")}


def _mutate_bundle_members(rng, files: dict, root: Path, folder: str) -> str:
    """Mutate a bundle's members (``files`` keyed ``<folder>/<member>``); the manifest's hashes and checksum are
    recomputed after most structured changes."""
    import hashlib

    from kpd.bundle import manifest_checksum

    members = _bundle_files(files, folder)
    manifest_name = members["manifest.json"]
    manifest = json.loads(_data(files, manifest_name))
    choice = rng.random()
    if choice < 0.3:
        return _bytes_mutation(rng, files, manifest_name if rng.random() < 0.5 else None)
    if choice < 0.6:
        manifest, what = _mutate_json(rng, manifest)
    elif choice < 0.8 and _pristine(files, members["template.npy"]):
        array = np.load(io.BytesIO(_data(files, members["template.npy"])), allow_pickle=False)
        buf = io.BytesIO()
        new, what = _mutate_array(rng, array)
        np.lib.format.write_array(buf, new, allow_pickle=False)
        data = buf.getvalue()
        if rng.random() < 0.3:
            data = _lying_header(data, (2**28, 3))
            what = "header (2**28, 3)"
        files[members["template.npy"]] = data
        what = "template.npy:" + what
    elif choice < 0.9:
        victim = ("keypoints.onnx", "influence.onnx", "template.npy")[int(rng.integers(3))]
        files[members[victim]] = bytes(rng.integers(0, 256, int(rng.integers(1, 4096)), dtype=np.uint8))
        what = f"{victim}:random"
    else:
        files[f"{folder}/extra.bin"] = ("sparse", BOMB_BYTES)
        what = "sparse member of 1.5 GiB"
    if isinstance(manifest, dict) and rng.random() < 0.85:
        listed = manifest.get("files")
        if isinstance(listed, dict):
            for member, path in _bundle_files(files, folder).items():
                if member in listed and not (isinstance(files[path], tuple) and files[path][0] == "sparse"):
                    listed[member] = hashlib.sha256(_data(files, path)).hexdigest()
        try:
            manifest["checksum"] = manifest_checksum(manifest)
        except (TypeError, ValueError):
            pass
        what += " (rehashed)"
    files[manifest_name] = _dump_json(manifest)
    return what


def _mutate_bundle_dir(rng, files: dict, root: Path) -> str:
    if rng.random() < 0.1:
        _add_traps(files)
        name = ("link.png", "fifo.png", "folder")[int(rng.integers(3))]
        files[f"shoe.kpd/{name}"] = files.pop(name)
        return f"trap {name}"
    return _mutate_bundle_members(rng, files, root, "shoe.kpd")


def _mutate_bundle_zip(rng, files: dict, root: Path) -> str:
    name = MAIN["bundle_zip"]
    data = _data(files, name)
    choice = rng.random()
    if choice < 0.35 or not _pristine(files, name):  # a mutated archive is not parsed here (a bomb's GiBs)
        return _bytes_mutation(rng, files, name)
    if choice < 0.45:
        files[name] = _zip_with(data, root / "bombs" / "extra.bin.zip")
        return "bomb member"
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        inner = {"shoe.kpd/" + n.split("/", 1)[1]: archive.read(n) for n in archive.namelist()}
    what = _mutate_bundle_members(rng, inner, root, "shoe.kpd")
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for member, value in inner.items():
            if isinstance(value, tuple):  # a sparse member cannot be zipped: a bomb stands in
                continue
            archive.writestr(member, value)
    files[name] = out.getvalue()
    return "zip:" + what


_MUTATORS = {
    "ply_binary": _mutate_text("mesh.ply"),
    "ply_ascii": _mutate_text("mesh.ply"),
    "obj": _mutate_obj,
    "off": _mutate_text("mesh.off"),
    "stl": _mutate_text("mesh.stl"),
    "gltf": _mutate_gltf,
    "glb": _mutate_glb,
    "pcd": _mutate_text("points.pcd"),
    "keypoints_json": _mutate_keypoints_json,
    "keypoints_txt": _mutate_text("keypoints.txt"),
    "rig": _mutate_rig,
    "bundle_dir": _mutate_bundle_dir,
    "bundle_zip": _mutate_bundle_zip,
}


def write_case(case: Case, folder: Path, root: Path) -> Path:
    """Write ``case``'s files into ``folder/in`` (the input's folder) beside ``folder/secret.*``; returns the main
    file's path."""
    inside = folder / "in"
    inside.mkdir(parents=True)
    for secret in ("secret.png", "secret.txt"):
        os.link(root / secret, folder / secret)
    for name, value in case.files.items():
        p = inside / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(value, bytes):
            p.write_bytes(value)
        elif value[0] == "hardlink":
            os.link(value[1], p)
        elif value[0] == "symlink":
            os.symlink(value[1], p)
        elif value[0] == "fifo":
            os.mkfifo(p)
        elif value[0] == "folder":
            p.mkdir(exist_ok=True)
        elif value[0] == "sparse":
            with open(p, "wb") as fh:
                fh.truncate(value[1])
    return inside / case.main


# --- the worker -----------------------------------------------------------------------------------------------------


class Result(NamedTuple):
    """What one case did: ``outcome`` is ``ok``, ``error`` (a kpd error: what a bad file should give), or a failure:
    ``traceback``, ``hang``, ``memory``, ``outside``, ``crash``; ``detail`` the message or the last lines of the
    stack; ``where`` the innermost frame in kpd (``kpd/io/obj.py:123``) or ``""``; ``peak`` the case's peak resident
    size above the worker's before it (bytes); ``seconds`` its time."""

    index: int
    format: str
    reader: str
    mutations: list
    outcome: str
    detail: str
    where: str
    peak: int
    seconds: float


FAILURES = ("traceback", "hang", "memory", "outside", "crash")


def _kpd_frame(frames) -> str:
    """The innermost frame in the kpd package (``kpd/...:line``) of a list of ``FrameSummary``."""
    import kpd

    base = os.path.dirname(os.path.dirname(os.path.realpath(kpd.__file__)))
    for frame in reversed(frames):
        path = os.path.realpath(frame.filename)
        if path.startswith(base + os.sep) and os.sep + "tests" + os.sep not in path[len(base):]:
            return f"{os.path.relpath(path, base)}:{frame.lineno}"
    return ""


def _status(key: str) -> int:
    with open("/proc/self/status") as fh:
        return int(re.search(rf"{key}:\s+(\d+)", fh.read()).group(1)) * 1024


def _call(reader: str, path: Path):
    if reader.startswith("probe:"):  # what each failure looks like, for the tests of the worker itself
        return _probe(reader[6:], path)
    if reader == "Rig.load":
        from kpd.rig import Rig

        return Rig.load(path)
    if reader == "read_bundle":
        from kpd.bundle import read_bundle

        return read_bundle(path)
    import kpd.io

    return getattr(kpd.io, reader)(path)


def _probe(kind: str, path: Path) -> None:
    if kind == "outside":
        open(path.parent.parent / "secret.txt").close()
    elif kind == "traceback":
        raise ValueError("a probe's plain exception")
    elif kind == "memory":
        np.ones(3 << 28)  # 6 GiB
    elif kind == "hang":
        time.sleep(3600)
    elif kind == "crash":
        import ctypes

        ctypes.string_at(0)


def _worker(conn, hang_file: str) -> None:  # pragma: no cover - runs in the worker process
    import faulthandler
    import logging
    import resource
    import sysconfig
    import traceback

    import kpd
    from kpd.errors import KpdError

    logging.disable(logging.CRITICAL)
    # every reader once, so that later cases import and compile nothing
    warm = Path(conn.recv())
    for fmt in FORMATS:
        for reader in READERS[fmt]:
            try:
                _call(reader, warm / fmt / MAIN[fmt])
            except KpdError:
                pass
    allowed = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix,
                                             os.path.dirname(kpd.__file__), *sysconfig.get_paths().values())}
    allowed |= {os.path.realpath(p) for p in sys.path if p and os.path.isdir(p)}
    allowed_files = {"/proc/meminfo", "/dev/null", "/dev/urandom", "/proc/self/status", "/proc/self/cgroup",
                     "/sys/fs/cgroup", "/proc/cpuinfo", "/proc/self/clear_refs"}
    state = {"folder": None, "outside": []}

    def hook(event: str, args: tuple) -> None:
        folder = state["folder"]
        if folder is None or event != "open" or not isinstance(args[0], (str, bytes, os.PathLike)):
            return
        path = os.path.realpath(os.fsdecode(args[0]))
        if path == folder or path.startswith(folder + os.sep) or path in allowed_files \
                or path.startswith("/sys/fs/cgroup/") or any(path.startswith(a + os.sep) for a in allowed):
            return
        frames, frame = [], sys._getframe(1)
        while frame is not None:  # no source lines looked up: that would open files inside the hook
            frames.append(traceback.FrameSummary(frame.f_code.co_filename, frame.f_lineno, frame.f_code.co_name,
                                                 lookup_line=False))
            frame = frame.f_back
        state["outside"].append((path, _kpd_frame(frames[::-1])))

    sys.addaudithook(hook)
    conn.send("ready")
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    hang_fh = open(hang_file, "w")
    faulthandler.enable(file=hang_fh)  # a native fault's stack, for the parent to name its frame
    while True:
        message = conn.recv()
        if message is None:
            return
        index, fmt, reader, mutations, path = message
        path = Path(path)
        folder = os.path.realpath(path.parent)  # the input's folder (a bundle folder's parent: its members inside)
        resource.setrlimit(resource.RLIMIT_AS, (_status("VmSize") + MEMORY_LIMIT, hard))
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        base = _status("VmRSS")
        faulthandler.dump_traceback_later(TIMEOUT * 0.9, file=hang_fh)
        start = time.perf_counter()
        state["outside"], state["folder"] = [], folder
        try:
            _call(reader, path)
            outcome, detail, where = "ok", "", ""
        except KpdError as exc:
            outcome, detail, where = "error", f"{type(exc).__name__}: {exc}", ""
        except MemoryError as exc:
            tb = traceback.extract_tb(exc.__traceback__)
            outcome, detail, where = "memory", "".join(traceback.format_exception(exc)[-4:]), _kpd_frame(tb)
        except BaseException as exc:  # noqa: BLE001 - every other exception is what the fuzz looks for
            tb = traceback.extract_tb(exc.__traceback__)
            outcome, detail, where = "traceback", "".join(traceback.format_exception(exc)[-4:]), _kpd_frame(tb)
        finally:
            state["folder"] = None
            seconds = time.perf_counter() - start
            faulthandler.cancel_dump_traceback_later()
            resource.setrlimit(resource.RLIMIT_AS, (hard, hard))
        peak = max(0, _status("VmHWM") - base)
        if state["outside"] and outcome not in ("traceback", "memory"):
            outcome = "outside"
            detail = "; ".join(sorted({p for p, _ in state["outside"]}))[:2000]
            where = state["outside"][0][1]
        if peak > MEMORY_LIMIT and outcome not in FAILURES:
            outcome, detail = "memory", f"peak {peak / 2**30:.2f} GiB"
        conn.send(Result(index, fmt, reader, mutations, outcome, detail[-3000:], where, peak, seconds))


class Runner:
    """Runs cases in a worker process (spawned: a fresh interpreter), replacing it after a hang or a crash.

    Parameters
    ----------
    root : the folder of :func:`make_seeds`; the cases are written under ``root/cases`` and removed after their run
        (a failing case's files are kept under ``root/failures/<index>`` when ``keep`` is true)
    seed : the campaign's seed
    keep : keep the files of failing cases
    """

    def __init__(self, root: Path, seed: int = 0, *, keep: bool = False, timeout: float = TIMEOUT) -> None:
        self.root, self.seed, self.keep, self.timeout = Path(root), seed, keep, timeout
        self._process = None
        self._conn = None

    def _start(self) -> None:
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._hang_file = str(self.root / f"hang.{os.getpid()}.{id(self)}.txt")
        self._process = context.Process(target=_worker, args=(child, self._hang_file), daemon=True)
        self._process.start()
        child.close()
        self._conn.send(str(self.root / "seeds"))
        if not self._conn.poll(600) or self._conn.recv() != "ready":  # imports, and numba's first compilation
            raise RuntimeError("the fuzz worker did not start")

    def close(self) -> None:
        if self._process is not None:
            try:
                self._conn.send(None)
                self._process.join(10)
            except (BrokenPipeError, OSError):
                pass
            if self._process.is_alive():
                self._process.kill()
                self._process.join()
            self._process = None

    def __enter__(self) -> "Runner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def run(self, index: int) -> Result:
        """Make, write and run case ``index``."""
        case = make_case(self.root, self.seed, index)
        folder = self.root / "cases" / str(index)
        if folder.exists():
            shutil.rmtree(folder)
        path = write_case(case, folder, self.root)
        try:
            result = self._run(case, path)
            if self.keep and result.outcome in FAILURES:
                kept = self.root / "failures" / str(index)
                shutil.rmtree(kept, ignore_errors=True)
                # hard links: no byte copied (a case may hold a sparse file of 1.5 GiB)
                shutil.copytree(folder, kept, symlinks=True, ignore=_no_specials, copy_function=os.link)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        return result

    def probe(self, kind: str) -> Result:
        """Run the probe ``kind`` (``outside``, ``traceback``, ``memory``, ``hang``, ``crash``) as a case reading
        the PLY seed: the failure each stands for, as the worker reports it."""
        case = Case(-1, "ply_binary", f"probe:{kind}", [], {"mesh.ply": ("hardlink", str(self.root / "seeds" /
                                                                                      "ply_binary" / "mesh.ply"))},
                    "mesh.ply")
        folder = self.root / "cases" / f"probe-{kind}"
        shutil.rmtree(folder, ignore_errors=True)
        try:
            return self._run(case, write_case(case, folder, self.root))
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _run(self, case: Case, path: Path) -> Result:
        if self._process is None or not self._process.is_alive():
            self._start()
        self._conn.send((case.index, case.format, case.reader, case.mutations, str(path)))
        if self._conn.poll(self.timeout):
            try:
                return self._conn.recv()
            except (EOFError, ConnectionError):  # the worker died: a crash
                pass
        self._process.join(2)
        alive = self._process.is_alive()
        self._process.kill()
        self._process.join()
        self._process = None
        stack = Path(self._hang_file).read_text(errors="replace") if Path(self._hang_file).exists() else ""
        where = _hang_frame(stack)
        if alive:
            return Result(case.index, case.format, case.reader, case.mutations, "hang", stack[-3000:], where, 0,
                          self.timeout)
        return Result(case.index, case.format, case.reader, case.mutations, "crash", stack[-3000:], where, 0, 0.0)


def _no_specials(folder: str, names: list) -> list:
    return [n for n in names if Path(folder, n).is_fifo()]


def _hang_frame(stack: str) -> str:
    """The innermost kpd frame of a faulthandler dump (its first thread's stack, innermost first)."""
    for m in re.finditer(r'File "([^"]+)", line (\d+)', stack):
        path = m.group(1)
        if os.sep + "kpd" + os.sep in path and os.sep + "tests" + os.sep not in path:
            return f"{path[path.rindex(os.sep + 'kpd' + os.sep) + 1:]}:{m.group(2)}"
    return ""


def summary(results: list) -> dict:
    """Counts per format and outcome, and the failures (format, reader, mutations, outcome, where, detail)."""
    per_format: dict = {}
    for r in results:
        counts = per_format.setdefault(r.format, {"cases": 0})
        counts["cases"] += 1
        counts[r.outcome] = counts.get(r.outcome, 0) + 1
    failures = [r for r in results if r.outcome in FAILURES]
    return {
        "cases": len(results),
        "per_format": per_format,
        **{f"{kind}s" if not kind.endswith("s") else kind: sum(r.outcome == kind for r in results)
           for kind in FAILURES},
        "peak_bytes_max": max((r.peak for r in results), default=0),
        "failures": [{"index": r.index, "format": r.format, "reader": r.reader, "mutations": r.mutations,
                      "outcome": r.outcome, "where": r.where, "detail": headline(r)} for r in failures],
    }


def headline(result: Result) -> str:
    """One line for a result: the exception's last line, a native fault's name, the files read outside."""
    lines = [line for line in result.detail.strip().splitlines() if line.strip()]
    if result.outcome in ("crash", "hang"):
        return next((line for line in lines if line.startswith(("Fatal Python error", "Timeout"))),
                    result.outcome)[:300]
    return lines[-1][:300] if lines else ""
