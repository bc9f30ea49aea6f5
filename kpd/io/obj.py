"""OBJ, read by kpd itself so that nothing of the file is lost, and written back in the file's own structure.

Reading (:func:`read`) keeps the file's vertex order: vertex ``i`` of the :class:`~kpd.mesh.Mesh` is the file's
``i``-th ``v`` line (Assimp, inside Open3D, splits vertices where UVs or normals differ, reorders them by first use
and drops every UV of a file that mixes faces with and without texture coordinates; measured in docs/formats.md).
Faces with texture coordinates get them, faces without them are marked in ``Mesh.triangle_uv_mask``. Every material
of the ``.mtl`` that the faces use becomes one entry of ``Mesh.textures``: its ``map_Kd`` image as in the file, or
a 1x1 image of its ``Kd`` colour (what the drawing code shows, shaded, as the material's colour).

Writing a mesh read from an OBJ (:func:`write`, directly or after :meth:`~kpd.mesh.Mesh.with_vertices`) rewrites
only the ``v`` lines (and the ``vn`` lines, turned with the surface) of the input's own text: groups, smoothing
groups, lines, comments, materials and face order stay as they were; the ``.mtl`` is copied as ``<stem>.mtl`` with
its maps renamed, and every image it names is copied byte for byte as ``<stem>_<its name>`` (a JPEG stays a JPEG),
so that the outputs of one folder never collide. Any other mesh is written by :func:`write` from its arrays: ``v``
(with ``r g b`` when it has vertex colours), ``vt`` on the faces that have UVs, ``vn``, one material per texture
(a 1x1 texture as a plain ``Kd`` colour, others as ``<stem>_<i>.png``).

Faces must be triangles (kpd refuses polygons rather than triangulating them behind the user's back).
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kpd.errors import InputError, WriteError
from kpd.io.atomic import atomic_files
from kpd.io.common import incomplete, verify_companion
from kpd.io.images import read_image
from kpd.mesh import Mesh, PointSet, count_phrase

__all__ = ["read", "write", "companions", "check_faces", "ObjSource"]

log = logging.getLogger("kpd.io.obj")

_OBJ_POLYGON = re.compile(rb"^[ \t]*f[ \t]+\S+[ \t]+\S+[ \t]+\S+[ \t]+[^\s#]", re.M)
_OBJ_SHORT_FACE = re.compile(rb"^[ \t]*f(?:[ \t]+[^\s#]+){0,2}[ \t]*(?:#.*)?\r?$", re.M)
# MTL statements that name a file (the file name is the last token, after any options)
_MAP_KEYS = (b"map_kd", b"map_ka", b"map_ks", b"map_ns", b"map_d", b"map_bump", b"bump", b"disp", b"decal",
             b"refl", b"norm", b"map_pr", b"map_pm", b"map_ps", b"map_ke", b"map_rma", b"map_orm")
_DEFAULT_KD = (0.8, 0.8, 0.8)  # faces without a material (and materials without Kd), as the drawing code's grey


def check_faces(p: Path, data: bytes) -> None:
    """Refuse OBJ faces that are not triangles."""
    polygons = len(_OBJ_POLYGON.findall(data))
    if polygons:
        raise InputError(
            f"{p}: {count_phrase(polygons, 'faces')} more than 3 vertices; kpd reads triangle meshes only "
            "(triangulate it first, e.g. Blender: Triangulate Faces)"
        )
    short = len(_OBJ_SHORT_FACE.findall(data))
    if short:
        raise InputError(f"{p}: {count_phrase(short, 'faces')} fewer than 3 vertices")


# --- reading -------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class ObjSource:
    """An OBJ file as read: its bytes, where its ``v``/``vn`` lines are, and its materials' files.

    Attributes
    ----------
    path : the file.
    data : its bytes.
    v_spans : (V, 2) int64, start and end (before the line break) of each ``v`` line.
    v_tails : bytes after the three coordinates of each ``v`` line (``w`` or ``r g b``), or None when all are empty.
    vn_spans : (N, 2) int64, likewise for the ``vn`` lines.
    corner_normals : (T, 3) int64, the ``vn`` index of each corner, -1 where the corner has none.
    vertices : (V, 3) float64, the positions as read (a write of unchanged positions copies the text as it is).
    libraries : the ``mtllib`` statements as (start, end) spans with their file names (resolved paths or None).
    """

    path: Path
    data: bytes
    v_spans: np.ndarray
    v_tails: list | None
    vn_spans: np.ndarray
    corner_normals: np.ndarray
    normals: np.ndarray
    vertices: np.ndarray
    libraries: list = field(default_factory=list)


def _lines(data: bytes) -> tuple[list[bytes], np.ndarray]:
    """The lines of ``data`` (without the line break) and the byte offset of each."""
    lines = data.split(b"\n")
    lengths = np.fromiter((len(s) + 1 for s in lines), dtype=np.int64, count=len(lines))
    starts = np.zeros(len(lines), dtype=np.int64)
    np.cumsum(lengths[:-1], out=starts[1:])
    return lines, starts


def _numbers(p: Path, payload: list[bytes], kind: str, dtype) -> np.ndarray:
    if not payload:
        return np.zeros(0, dtype=dtype)
    try:
        return np.fromstring(b" ".join(payload), dtype=dtype, sep=" ")  # noqa: NPY201 (text mode is not deprecated)
    except ValueError:
        raise InputError(f"{p}: a {kind} line holds something that is not a number") from None


def _table(p: Path, payload: list[bytes], line_numbers: list[int], kind: str, least: int) -> tuple[np.ndarray, list]:
    """(n, least) float64 of the first ``least`` numbers of each line; the text after them per line (or None)."""
    values = _numbers(p, payload, kind, np.float64)
    n = len(payload)
    if values.size == least * n:
        return values.reshape(n, least), None
    rows, tails = [], []
    for number, text in zip(line_numbers, payload):
        parts = text.split()
        if len(parts) < least:
            raise InputError(f"{p}: line {number}: a '{kind}' line needs {least} numbers; got {len(parts)}")
        try:
            rows.append([float(x) for x in parts[:least]])
            [float(x) for x in parts[least:]]
        except ValueError:
            raise InputError(f"{p}: line {number}: a '{kind}' line holds something that is not a number") from None
        tails.append(parts[least:])
    return np.array(rows, dtype=np.float64).reshape(n, least), tails


def _colors(tails: list | None) -> np.ndarray | None:
    """(V, 3) vertex colours of ``v x y z r g b`` lines (0-1, or 0-255 scaled down), or None."""
    if not tails or not all(len(t) in (3, 4) for t in tails):
        return None
    colors = np.array([[float(x) for x in t[:3]] for t in tails], dtype=np.float64)
    if colors.min() < 0.0:
        return None
    if colors.max() > 1.0 + 1e-6:
        return colors / 255.0 if colors.max() <= 255.0 else None
    return colors


def _strip_comment(s: bytes) -> bytes:
    i = s.find(b"#")
    return s if i < 0 else s[:i]


def parse(p: Path, data: bytes, points: bool = False) -> tuple[dict, ObjSource | None]:
    """Parse an OBJ's geometry; returns the arrays of :func:`read` and the :class:`ObjSource` for writing."""
    check_faces(p, data)
    lines, starts = _lines(data)
    v_rows, vt_rows, vn_rows, f_rows, mtl_rows, lib_rows = [], [], [], [], [], []
    for i, line in enumerate(lines):
        s = line.lstrip(b" \t")
        if not s:
            continue
        c = s[:1]
        if c == b"v":
            t = s[1:2]
            if t in (b" ", b"\t"):
                v_rows.append(i)
            elif t == b"t":
                vt_rows.append(i)
            elif t == b"n":
                vn_rows.append(i)
        elif c == b"f" and s[1:2] in (b" ", b"\t"):
            f_rows.append(i)
        elif c == b"u" and s.startswith(b"usemtl"):
            mtl_rows.append(i)
        elif c == b"m" and s.startswith(b"mtllib"):
            lib_rows.append(i)

    def payload(rows: list[int], skip: int) -> list[bytes]:
        return [_strip_comment(lines[i].lstrip(b" \t")[skip:]).strip() for i in rows]

    v_text = payload(v_rows, 1)
    vertices, v_tails = _table(p, v_text, [i + 1 for i in v_rows], "v", 3)
    if not len(vertices):
        raise InputError(f"{p}: no vertices (empty geometry)")
    if not f_rows:
        if points:
            return {"vertices": vertices, "colors": _colors(v_tails)}, None
        raise InputError(f"{p}: has {len(vertices)} vertices but no triangles (a point cloud? use read_points or "
                         "read_shape)")
    colors = _colors(v_tails)
    vt = _table(p, [b" ".join(s.split()[:2]) for s in payload(vt_rows, 2)], [i + 1 for i in vt_rows], "vt", 2)[0] \
        if vt_rows else np.zeros((0, 2))
    vn = _table(p, payload(vn_rows, 2), [i + 1 for i in vn_rows], "vn", 3)[0] if vn_rows else np.zeros((0, 3))

    # faces: corners 'a', 'a/b', 'a/b/c' or 'a//c'; '//' becomes '/0/' so each form has a fixed count of numbers
    faces = payload(f_rows, 1)
    T = len(faces)
    corner = np.zeros((T, 3, 3), dtype=np.int64)  # v, vt, vn per corner (1-based, negative relative, 0 none)
    kinds: dict[int, list[int]] = {0: [], 3: [], 6: []}
    texts: dict[int, list[bytes]] = {0: [], 3: [], 6: []}
    for j, text in enumerate(faces):
        text = text.replace(b"//", b"/0/")
        slashes = text.count(b"/")
        if slashes not in kinds:
            raise InputError(f"{p}: line {f_rows[j] + 1}: the corners of a face must all have the same form "
                             f"(v, v/vt, v/vt/vn or v//vn); got {faces[j].decode(errors='replace')!r}")
        kinds[slashes].append(j)
        texts[slashes].append(text.replace(b"/", b" "))
    for slashes, rows in kinds.items():
        if not rows:
            continue
        k = slashes // 3 + 1
        numbers = _numbers(p, texts[slashes], "f", np.int64)
        if numbers.size != 3 * k * len(rows):
            raise InputError(f"{p}: a face line does not hold 3 corners of {k} indices")
        corner[rows, :, :k] = numbers.reshape(len(rows), 3, k)

    f_lines = np.asarray(f_rows, dtype=np.int64)

    def resolve(index: np.ndarray, rows: list[int], kind: str, n: int, optional: bool) -> np.ndarray:
        out = index - 1
        negative = index < 0
        if negative.any():  # relative to the elements defined before the face
            before = np.searchsorted(np.asarray(rows, dtype=np.int64), f_lines)[:, None]
            out = np.where(negative, before + index, out)
        missing = index == 0
        if not optional and missing.any():
            raise InputError(f"{p}: a face has the vertex index 0 (OBJ counts from 1)")
        bad = ~missing & ((out < 0) | (out >= n))
        if bad.any():
            raise InputError(f"{p}: {count_phrase(int(bad.any(axis=1).sum()), 'faces', 'name', 'names')} a "
                             f"{kind} outside 1..{n}")
        return np.where(missing, -1, out)

    triangles = resolve(corner[:, :, 0], v_rows, "vertex", len(vertices), False)
    uv_index = resolve(corner[:, :, 1], vt_rows, "texture coordinate", len(vt), True)
    normal_index = resolve(corner[:, :, 2], vn_rows, "normal", len(vn), True)
    has_uv = (uv_index >= 0).all(axis=1)  # (T,) a face with coordinates on some corners only counts as without
    uvs = None
    if has_uv.any():
        uvs = np.zeros((T, 3, 2), dtype=np.float64)
        uvs[has_uv] = vt[uv_index[has_uv]]
        uvs = uvs.reshape(-1, 2)

    normals = None
    if (normal_index >= 0).any():
        normals = np.zeros_like(vertices)
        used = normal_index >= 0
        np.add.at(normals, triangles[used], vn[normal_index[used]])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        from kpd.triangles import vertex_normals

        fallback = vertex_normals(vertices, triangles)
        normals = np.where(length > 1e-12, normals / np.maximum(length, 1e-300), fallback)

    # materials: the last 'usemtl' before each face
    mtl_names = [_strip_comment(lines[i].lstrip(b" \t")[6:]).strip().decode("utf-8", "replace") for i in mtl_rows]
    which = np.searchsorted(np.asarray(mtl_rows, dtype=np.int64), f_lines) - 1 if mtl_rows else np.full(T, -1)
    face_material = [None if w < 0 else mtl_names[w] for w in which] if mtl_rows else None

    libraries = []
    for i in lib_rows:
        names = _strip_comment(lines[i].lstrip(b" \t")[6:]).strip()
        libraries.append((int(starts[i]), int(starts[i] + len(lines[i].rstrip(b"\r"))),
                          names.decode("utf-8", "replace")))

    v_spans = np.stack([starts[v_rows], starts[v_rows] + [len(lines[i].rstrip(b"\r")) for i in v_rows]], axis=1)
    vn_spans = (np.stack([starts[vn_rows], starts[vn_rows] + [len(lines[i].rstrip(b"\r")) for i in vn_rows]], axis=1)
                if vn_rows else np.zeros((0, 2), dtype=np.int64))
    source = ObjSource(path=p, data=data, v_spans=v_spans,
                       v_tails=None if v_tails is None else [b" ".join(t) for t in v_tails],
                       vn_spans=vn_spans, corner_normals=normal_index, normals=vn, vertices=vertices,
                       libraries=libraries)
    arrays = {"vertices": vertices, "triangles": triangles, "vertex_normals": normals, "vertex_colors": colors,
              "triangle_uvs": uvs, "uv_mask": has_uv if uvs is not None and not has_uv.all() else None,
              "face_material": face_material}
    return arrays, source


@dataclass
class Material:
    """One ``newmtl`` of a material library: its ``Kd`` colour and its ``map_Kd`` image file (resolved)."""

    name: str
    kd: tuple = _DEFAULT_KD
    map_kd: Path | None = None
    map_kd_name: str | None = None


def _map_file(statement: bytes) -> bytes:
    """The file name of a map statement's arguments (the last token, after options such as ``-s 1 1 1``)."""
    parts = statement.split()
    return parts[-1] if parts else b""


def read_library(p: Path, mtl: Path) -> dict[str, Material]:
    """The materials of one ``.mtl`` file, by name."""
    materials: dict[str, Material] = {}
    current = None
    for raw in mtl.read_bytes().split(b"\n"):
        s = _strip_comment(raw).strip()
        if not s:
            continue
        key, _, rest = s.partition(b" ")
        key = key.lower()
        rest = rest.strip()
        if key == b"newmtl":
            current = Material(rest.decode("utf-8", "replace"))
            materials[current.name] = current
        elif current is None:
            continue
        elif key == b"kd":
            try:
                values = [float(x) for x in rest.split()[:3]]
                if len(values) == 1:
                    values *= 3
                if len(values) == 3:
                    current.kd = tuple(min(max(x, 0.0), 1.0) for x in values)
            except ValueError:
                log.warning("%s: material %s has an unreadable Kd %r; drawn grey", p, current.name,
                            rest.decode("utf-8", "replace"))
        elif key == b"map_kd":
            name = _map_file(rest).decode("utf-8", "replace").replace("\\", "/")
            current.map_kd_name = name
            current.map_kd = _find_map(mtl.parent, name, rest.decode("utf-8", "replace").replace("\\", "/"))
    return materials


def _find_map(folder: Path, name: str, whole: str) -> Path | None:
    for candidate in (folder / name, folder / whole, folder / Path(name).name):
        if candidate.is_file():
            return candidate
    return None


def _library_files(p: Path, names: str) -> list[tuple[str, Path | None]]:
    """The files of one ``mtllib`` statement (several names may follow it; a name may hold spaces)."""
    whole = p.parent / names
    if whole.is_file():
        return [(names, whole)]
    out = []
    for name in names.split():
        f = p.parent / name
        out.append((name, f if f.is_file() else None))
    return out


def read(p: Path, name: str | None = None, *, points: bool = False) -> "Mesh | PointSet":
    """Read an OBJ file (see the module notes); ``name`` is the path as the user gave it, for messages. With
    ``points``, a file without faces gives a :class:`~kpd.mesh.PointSet` of its vertices instead of an error."""
    data = p.read_bytes()
    if b"\0" in data[:4096]:
        raise InputError(f"{p}: not a text OBJ file (it holds binary data)")
    arrays, source = parse(p, data, points)
    if source is None:
        return PointSet(arrays["vertices"], None, arrays["colors"], path=name if name is not None else os.fspath(p))
    T = len(arrays["triangles"])
    materials: dict[str, Material] = {}
    missing_maps = []
    for _, _, names in source.libraries:
        for lib_name, lib in _library_files(p, names):
            if lib is None:
                log.warning("%s: material library %r is missing; read without materials and textures", p, lib_name)
                continue
            for material in read_library(p, lib).values():
                materials.setdefault(material.name, material)
                if material.map_kd_name and material.map_kd is None:
                    missing_maps.append(material.map_kd_name)
    if missing_maps:
        log.warning("%s: texture file(s) %s named in the material library are missing; read without them",
                    p, ", ".join(dict.fromkeys(missing_maps)))
    textures, ids, texture_files = [], None, []
    face_material = arrays["face_material"]
    if face_material is not None and materials:
        used = list(dict.fromkeys(face_material))
        index = {m: i for i, m in enumerate(used)}
        images, colors = [], []
        cache: dict[Path, np.ndarray | None] = {}
        for m in used:
            material = materials.get(m) if m is not None else None
            image = None
            if material is not None and material.map_kd is not None:
                if material.map_kd not in cache:
                    cache[material.map_kd] = read_image(material.map_kd)
                image = cache[material.map_kd]
            kd = material.kd if material is not None else _DEFAULT_KD
            colors.append(kd)
            images.append(image)
            texture_files.append(material.map_kd if image is not None else None)
        if any(i is not None for i in images) or len(set(colors)) > 1:
            for image, kd in zip(images, colors):
                if image is None:
                    image = np.round(np.array(kd, dtype=np.float64) * 255).astype(np.uint8).reshape(1, 1, 3)
                textures.append(image)
            ids = np.array([index[m] for m in face_material], dtype=np.int64)
    uvs, mask = arrays["triangle_uvs"], arrays["uv_mask"]
    if textures and uvs is None:
        uvs = np.zeros((3 * T, 2), dtype=np.float64)  # plain colours only: every face samples its 1x1 texture
        mask = np.zeros(T, dtype=bool)
    mesh = Mesh(vertices=arrays["vertices"], triangles=arrays["triangles"], vertex_normals=arrays["vertex_normals"],
                vertex_colors=arrays["vertex_colors"], triangle_uvs=uvs, textures=textures,
                triangle_material_ids=ids, triangle_uv_mask=mask, path=name if name is not None else os.fspath(p))
    mesh._source = source
    mesh._texture_files = texture_files if textures else []
    return mesh


# --- writing -------------------------------------------------------------------------------------------------------


def _own_source(mesh: Mesh) -> ObjSource | None:
    """The OBJ the mesh was read from, when its topology is still that file's."""
    source = getattr(mesh, "_source", None)
    if not isinstance(source, ObjSource) or len(source.vertices) != len(mesh.vertices):
        return None
    if len(source.corner_normals) != len(mesh.triangles):
        return None
    return source


def write(p: Path, mesh: Mesh) -> None:
    """Write ``mesh`` to ``p`` with its companions, atomically, and check the result (see the module notes)."""
    source = _own_source(mesh)
    with atomic_files(p) as target:
        if source is not None:
            _write_from_source(target, mesh, source)
        else:
            _write_arrays(target, mesh)
        _verify(p, target, mesh)


def companions(p: Path, mesh: Mesh) -> list[str]:
    """The files :func:`write` adds beside ``p``."""
    source = _own_source(mesh)
    if source is not None:
        return [name for name, _ in _source_companions(p.stem, source)[0].values()] + \
            list(_source_companions(p.stem, source)[1].values())
    if not mesh.textures:
        return []
    return [p.stem + ".mtl"] + [f"{p.stem}_{i}.png" for i, t in enumerate(mesh.textures) if _is_image(t)]


def _is_image(texture: np.ndarray) -> bool:
    return texture.shape[0] * texture.shape[1] > 1


def _fmt(rows: np.ndarray) -> list[bytes]:
    return [b"%.9g %.9g %.9g" % (a, b, c) for a, b, c in rows.tolist()]


def _source_companions(stem: str, source: ObjSource) -> tuple[dict, dict]:
    """Output names: {library path: (new name, its map renames)} and {image path: new name}."""
    libs: dict[Path, tuple[str, dict]] = {}
    images: dict[Path, str] = {}
    taken = {f"{stem}.obj".lower()}
    for _, _, names in source.libraries:
        for lib_name, lib in _library_files(source.path, names):
            if lib is None or lib in libs:
                continue
            new = f"{stem}.mtl" if not libs else _unique(f"{stem}_{Path(lib_name).name}", taken)
            taken.add(new.lower())
            renames = {}
            for statement in _map_statements(lib.read_bytes()):
                name = _map_file(statement[1]).decode("utf-8", "replace").replace("\\", "/")
                f = _find_map(lib.parent, name, statement[1].decode("utf-8", "replace").replace("\\", "/"))
                if f is None:
                    continue
                f = f.resolve()
                if f not in images:
                    images[f] = _unique(f"{stem}_{f.name}", taken)
                    taken.add(images[f].lower())
                renames[name] = images[f]
            libs[lib] = (new, renames)
    return libs, images


def _unique(name: str, taken: set) -> str:
    if name.lower() not in taken:
        return name
    base, suffix = os.path.splitext(name)
    k = 2
    while f"{base}_{k}{suffix}".lower() in taken:
        k += 1
    return f"{base}_{k}{suffix}"


def _map_statements(data: bytes) -> list[tuple[int, bytes]]:
    """(line index, arguments) of each map statement of an ``.mtl``."""
    out = []
    for i, raw in enumerate(data.split(b"\n")):
        s = raw.strip()
        key, _, rest = s.partition(b" ")
        if key.lower() in _MAP_KEYS and rest.strip():
            out.append((i, _strip_comment(rest).strip()))
    return out


def turned_normals(old_vertices: np.ndarray, new_vertices: np.ndarray, triangles: np.ndarray,
                   corner_normals: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3) the file's normals turned with the surface around them.

    Each normal ``n`` is turned by the smallest rotation that takes the area-weighted normal of the faces whose
    corners use it, before the edit, to the same after the edit: a normal that was the faces' own (flat or smooth)
    becomes the new faces' own, and an artist's normal keeps its offset from the surface.
    """
    from kpd.triangles import cross

    used = corner_normals >= 0
    index = corner_normals[used]
    n = len(normals)

    def around(vertices: np.ndarray) -> np.ndarray:
        face = cross(vertices, triangles)  # (T, 3)
        per_corner = np.repeat(face[:, None, :], 3, axis=1)[used]  # (c, 3)
        out = np.stack([np.bincount(index, weights=per_corner[:, k], minlength=n) for k in range(3)], axis=1)
        length = np.linalg.norm(out, axis=1, keepdims=True)
        return np.divide(out, length, out=np.zeros_like(out), where=length > 0)

    a, b = around(old_vertices), around(new_vertices)
    valid = (np.linalg.norm(a, axis=1) > 0) & (np.linalg.norm(b, axis=1) > 0)
    out = normals.copy()
    # Rodrigues with axis a x b: R v = v cos + (k x v) sin + k (k . v)(1 - cos), written without dividing by sin
    k = np.cross(a, b)  # |k| = sin
    c = np.einsum("ij,ij->i", a, b)
    v = normals
    kv = np.cross(k, v)
    kdotv = np.einsum("ij,ij->i", k, v)
    factor = np.divide(1.0, 1.0 + c, out=np.zeros_like(c), where=(1.0 + c) > 1e-12)
    turned = v * c[:, None] + kv + k * (kdotv * factor)[:, None]
    opposite = valid & ((1.0 + c) <= 1e-12)
    turned[opposite] = -v[opposite]
    out[valid] = turned[valid]
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, length, out=normals.copy(), where=length > 0)


def _write_from_source(target: Path, mesh: Mesh, source: ObjSource) -> None:
    data = source.data
    libs, images = _source_companions(target.stem, source)
    changed = not np.array_equal(mesh.vertices, source.vertices)
    edits: list[tuple[int, int, bytes]] = []
    if changed:
        text = _fmt(mesh.vertices)
        if source.v_tails is not None:
            text = [t + (b" " + tail if tail else b"") for t, tail in zip(text, source.v_tails)]
        edits += [(int(s), int(e), b"v " + t) for (s, e), t in zip(source.v_spans, text)]
        if len(source.vn_spans):
            normals = turned_normals(source.vertices, mesh.vertices, mesh.triangles, source.corner_normals,
                                     source.normals)
            referenced = np.zeros(len(normals), dtype=bool)
            referenced[source.corner_normals[source.corner_normals >= 0]] = True
            text = _fmt(normals)
            edits += [(int(s), int(e), b"vn " + t)
                      for (s, e), t, r in zip(source.vn_spans, text, referenced) if r]
    lib_names = {}
    for _, _, names in source.libraries:
        for lib_name, lib in _library_files(source.path, names):
            if lib is not None:
                lib_names[lib_name] = libs[lib][0]
    for start, end, names in source.libraries:
        files = [lib_names[n] for n, lib in _library_files(source.path, names) if lib is not None]
        edits.append((start, end, ("mtllib " + " ".join(files)).encode("utf-8") if files else b"# mtllib " +
                      names.encode("utf-8") + b" (missing when kpd read the file)"))
    edits.sort()
    parts, at = [], 0
    for start, end, new in edits:
        parts.append(data[at:start])
        parts.append(new)
        at = end
    parts.append(data[at:])
    out = b"".join(parts)
    if not out.endswith(b"\n"):
        out += b"\n"
    target.write_bytes(out)
    for lib, (new, renames) in libs.items():
        target.parent.joinpath(new).write_bytes(_renamed_library(lib.read_bytes(), renames))
    for image, new in images.items():
        target.parent.joinpath(new).write_bytes(image.read_bytes())


def _renamed_library(data: bytes, renames: dict) -> bytes:
    lines = data.split(b"\n")
    for i, arguments in _map_statements(data):
        name = _map_file(arguments)
        new = renames.get(name.decode("utf-8", "replace").replace("\\", "/"))
        if new is None:
            continue
        line = lines[i]
        cut = line.rfind(name)
        lines[i] = line[:cut] + new.encode("utf-8") + line[cut + len(name):]
    return b"\n".join(lines)


def _write_arrays(target: Path, mesh: Mesh) -> None:
    """An OBJ (and its .mtl and PNGs) from the mesh's arrays alone."""
    stem = target.stem
    T = len(mesh.triangles)
    out: list[bytes] = [b"# written by kpd\n"]
    materials = bool(mesh.textures)
    if materials:
        out.append(f"mtllib {stem}.mtl\n".encode("utf-8"))
    v = _fmt(mesh.vertices)
    if mesh.vertex_colors is not None:
        v = [t + b" %.6g %.6g %.6g" % tuple(c) for t, c in zip(v, mesh.vertex_colors.tolist())]
    out.append(b"".join(b"v " + t + b"\n" for t in v))
    uv_index = None
    mask = np.ones(T, dtype=bool) if mesh.triangle_uv_mask is None else mesh.triangle_uv_mask
    if mesh.triangle_uvs is not None and mask.any():
        corners = mesh.triangle_uvs.reshape(T, 3, 2)[mask].reshape(-1, 2)
        from kpd.grouping import first_occurrence_groups

        first, index = first_occurrence_groups(corners)
        out.append(b"".join(b"vt %.9g %.9g\n" % (a, b) for a, b in corners[first].tolist()))
        uv_index = np.full((T, 3), -1, dtype=np.int64)
        uv_index[mask] = index.reshape(-1, 3)
    if mesh.vertex_normals is not None:
        out.append(b"".join(b"vn " + t + b"\n" for t in _fmt(mesh.vertex_normals)))
    ids = mesh.triangle_material_ids
    if materials and ids is None:
        ids = np.zeros(T, dtype=np.int64)
    tri = (mesh.triangles + 1).tolist()
    uvs = None if uv_index is None else (uv_index + 1).tolist()
    normals = mesh.vertex_normals is not None
    current = None
    lines = []
    for j in range(T):
        if materials and ids[j] != current:
            current = int(ids[j])
            lines.append(f"usemtl material_{current}".encode())
        a = tri[j]
        if uvs is not None and uvs[j][0] > 0:
            b = uvs[j]
            lines.append(b"f %d/%d/%d %d/%d/%d %d/%d/%d" % (a[0], b[0], a[0], a[1], b[1], a[1], a[2], b[2], a[2])
                         if normals else b"f %d/%d %d/%d %d/%d" % (a[0], b[0], a[1], b[1], a[2], b[2]))
        elif normals:
            lines.append(b"f %d//%d %d//%d %d//%d" % (a[0], a[0], a[1], a[1], a[2], a[2]))
        else:
            lines.append(b"f %d %d %d" % tuple(a))
    out.append(b"\n".join(lines) + b"\n")
    target.write_bytes(b"".join(out))
    if materials:
        from kpd.io.images import encode_png

        mtl = []
        for i, texture in enumerate(mesh.textures):
            mtl.append(f"newmtl material_{i}")
            if _is_image(texture):
                mtl += ["Kd 1 1 1", f"map_Kd {stem}_{i}.png"]
                target.parent.joinpath(f"{stem}_{i}.png").write_bytes(encode_png(texture))
            else:
                rgb = texture.reshape(-1)[:3] / 255.0 if texture.shape[2] >= 3 else [texture.reshape(-1)[0] / 255.0] * 3
                mtl.append("Kd %.6g %.6g %.6g" % tuple(rgb))
            mtl.append("")
        target.parent.joinpath(f"{stem}.mtl").write_text("\n".join(mtl), encoding="utf-8")


def _verify(p: Path, tmp: Path, mesh: Mesh) -> None:
    V, T = len(mesh.vertices), len(mesh.triangles)
    data = tmp.read_bytes()
    v = len(re.findall(rb"^[ \t]*v[ \t]", data, re.M))
    f = len(re.findall(rb"^[ \t]*f[ \t]", data, re.M))
    if v != V or f != T or not data.endswith(b"\n"):
        raise incomplete(p, f"{v} of {V} vertices and {f} of {T} faces")
    for companion in tmp.parent.iterdir():
        if companion != tmp:
            verify_companion(p.parent / companion.name, companion)
    if not (tmp.parent / tmp.name).is_file():
        raise WriteError(f"cannot write {p}: nothing was written")
