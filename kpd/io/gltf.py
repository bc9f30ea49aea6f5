"""glTF 2.0, read and written by kpd itself.

Reading (:func:`read`) takes every triangle primitive (strips and fans turned into triangles) of every node with a
mesh in the default scene, in world coordinates (node matrices applied), each primitive's vertices in the file's
order; UVs on the faces of primitives that have ``TEXCOORD_0`` (``Mesh.triangle_uv_mask`` marks the others); vertex
colours from ``COLOR_0``; one texture per used material, its base-colour image or a 1x1 image of its
``baseColorFactor`` (sRGB). glTF is y up; :func:`kpd.io.file_up` says so to the commands.

Writing a mesh read from a glTF file of the same kind (``.glb`` to ``.glb``, ``.gltf`` to ``.gltf``) keeps that file
whole (:func:`write_from_source`): only the POSITION (and NORMAL) data change, in place where they are plain float32
data, every node, primitive, material, image, sampler, extension and morph target stays; a ``.gltf``'s external
buffers and images are written beside it as ``<stem>_<name>`` (the files kpd read: inside the input's folder tree,
:mod:`kpd.io.references`). Any other mesh is written from its arrays: one
primitive per material and per presence of UVs, a 1x1 texture as a plain ``baseColorFactor``, an image read from a
JPEG file embedded or copied as that JPEG, others as PNG. (Open3D 0.20 writes neither UVs nor textures to glTF and
writes ``.glb`` files without their binary chunk; its reader, Assimp, merges primitives and drops base colours.)
"""

from __future__ import annotations

import base64
import io
import json
import logging
import struct
import urllib.parse
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from kpd.errors import InputError
from kpd.grouping import first_occurrence_groups, vertex_value_groups
from kpd.io.atomic import atomic_files, atomic_output
from kpd.io import references
from kpd.io.common import memory_free, verify_companion
from kpd.io.images import decode_image, encode_png
from kpd.io.references import IMAGE_BYTES
from kpd.mesh import Mesh, PointSet

__all__ = ["read", "write", "companions", "read_gltf_json", "read_buffers", "read_accessor", "GltfSource",
           "GLB_MAGIC", "GlbBuffer", "write_glb", "Primitive", "primitive_groups"]

log = logging.getLogger(__name__)

_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


_FLOAT, _UINT = 5126, 5125

GLB_MAGIC = _GLB_MAGIC


def write(p: Path, mesh: Mesh) -> None:
    """Write ``mesh`` to ``p`` (``.gltf`` or ``.glb``) atomically, with a ``.gltf``'s images beside it.

    A mesh read from a glTF file of the same kind is written in that file's own structure with new positions
    (:func:`write_from_source`); any other mesh from its arrays (one primitive per material and per presence of
    UVs, a 1x1 texture as a plain base colour, images as their original files where kpd read them, else PNG)."""
    binary = p.suffix.lower() == ".glb"
    source = own_source(mesh, p)
    if source is not None:
        with atomic_files(p) as target:
            write_from_source(target, mesh, source)
            for companion in target.parent.iterdir():
                if companion != target:
                    verify_companion(p.parent / companion.name, companion)
        return
    if not binary and mesh.textures:
        with atomic_files(p) as target:
            _write_gltf(target, mesh, binary=False, name=p.stem)
            for companion in target.parent.iterdir():
                if companion != target:
                    verify_companion(p.parent / companion.name, companion)
    else:
        with atomic_output(p) as target:
            _write_gltf(target, mesh, binary=binary, name=p.stem)


def companions(p: Path, mesh: Mesh) -> list[str]:
    """The files :func:`write` adds beside ``p``."""
    source = own_source(mesh, p)
    if source is not None:
        return [name for _, name in source_companions(p, source).values()]
    if p.suffix.lower() == ".gltf" and mesh.textures and mesh.triangle_uvs is not None:
        return [f"{p.stem}_{i}{_image_suffix(mesh, i)}" for i, t in enumerate(mesh.textures)
                if t.shape[0] * t.shape[1] > 1]
    return []


def _image_suffix(mesh: Mesh, i: int) -> str:
    """'.jpg' when texture ``i`` was read from a JPEG file (copied as it is), else '.png'."""
    return ".jpg" if _original_jpeg(mesh, i) is not None else ".png"


def _original_jpeg(mesh: Mesh, i: int) -> bytes | None:
    files = getattr(mesh, "_texture_files", None) or []
    f = files[i] if i < len(files) else None
    if f is None or Path(f).suffix.lower() not in (".jpg", ".jpeg") or not Path(f).is_file():
        return None
    return Path(f).read_bytes()


class Primitive(NamedTuple):
    """One primitive of a written mesh: triangles of one material, all with UVs or all without."""

    material: int | None  # index into the mesh's textures, or None
    source: np.ndarray  # (n,) int64, the mesh vertex of each written vertex
    triangles: np.ndarray  # (t, 3) int64, into the written vertices
    uvs: np.ndarray | None  # (n, 2) float64 of the written vertices, OBJ convention (origin bottom left)


def primitive_groups(mesh: Mesh) -> list[Primitive]:
    """The primitives glTF needs for ``mesh``: one per material, split where some faces have UVs and others have
    none (``Mesh.triangle_uv_mask``), with a vertex written once per distinct (vertex, UV) pair in order of first
    use."""
    textured = bool(mesh.textures) and mesh.triangle_uvs is not None
    ids = mesh.triangle_material_ids
    if textured and ids is None:
        ids = np.zeros(len(mesh.triangles), dtype=np.int64)
    groups = [(int(u), np.flatnonzero(ids == u)) for u in np.unique(ids)] if textured else [(None, None)]
    mask = mesh.triangle_uv_mask
    if mask is not None:  # faces without UVs get primitives without TEXCOORD_0
        if groups == [(None, None)]:
            groups = [(None, np.arange(len(mesh.triangles)))]
        groups = [(m, r[sel], flag) for m, r in groups for flag, sel in ((True, mask[r]), (False, ~mask[r]))
                  if sel.any()]
    else:
        groups = [(m, r, True) for m, r in groups]
    out = []
    for material, rows, has_uv in groups:
        if rows is not None and len(rows) == len(mesh.triangles):
            rows = None  # every triangle, in order: read in place, not copied
        tri = mesh.triangles if rows is None else mesh.triangles[rows]  # (t, 3)
        corner_vertex = tri.reshape(-1)  # (3t,)
        if mesh.triangle_uvs is not None and has_uv:
            uv = mesh.triangle_uvs.reshape(-1, 3, 2)
            corner_uv = (uv if rows is None else uv[rows]).reshape(-1, 2)  # (3t, 2)
            first, index = vertex_value_groups(corner_vertex, corner_uv)
            uvs = corner_uv[first]
        else:
            first, index = first_occurrence_groups(corner_vertex[:, None])
            uvs = None
        out.append(Primitive(material, corner_vertex[first], index.reshape(-1, 3), uvs))
    return out


class GlbBuffer:
    """A glTF binary buffer built piece by piece (numpy arrays or bytes, each 4-byte aligned, not copied) with its
    buffer views and accessors. A piece may also be a region written only when the buffer is (:meth:`region`): data
    made block by block as it is written, never held whole (a rig's morph targets at scan size)."""

    def __init__(self) -> None:
        self.pieces: list[Any] = []
        self.length = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: Any, target: int | None = None) -> int:
        """A buffer view of ``data``; returns its index."""
        nbytes = data.nbytes if isinstance(data, np.ndarray) else len(data)
        index = self._view_at(self.length, nbytes, target)
        self.pieces.append(data)
        self._advance(nbytes)
        return index

    def _view_at(self, offset: int, nbytes: int, target: int | None) -> int:
        view = {"buffer": 0, "byteOffset": int(offset), "byteLength": int(nbytes)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        return len(self.views) - 1

    def _advance(self, nbytes: int) -> None:
        self.length += nbytes
        pad = -nbytes % 4
        if pad:
            self.pieces.append(b"\0" * pad)
            self.length += pad

    def region(self, nbytes: int, write: Callable[[Any], None]) -> int:
        """Reserve ``nbytes`` of the buffer, filled when the buffer is written by ``write(fh)``: ``fh`` is at the
        region's start and seekable (a file, or :class:`io.BytesIO`), and ``write`` leaves it at the region's end
        (it may seek within the region). Returns the region's offset in the buffer, for :meth:`accessor_at`."""
        offset = self.length
        self.pieces.append(_Region(int(nbytes), write))
        self._advance(int(nbytes))
        return offset

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None,
                 bounds: bool | tuple = False) -> int:
        """An accessor of ``array``; ``bounds``: write its min and max (True: computed here, or given as a pair)."""
        array = np.ascontiguousarray(array)
        if bounds is True:
            bounds = (array.min(axis=0), array.max(axis=0))
        return self._accessor(self.view(array, target), len(array), kind, component, bounds)

    def accessor_at(self, offset: int, nbytes: int, count: int, kind: str, component: int, target: int | None,
                    bounds: tuple | None = None) -> int:
        """An accessor of ``count`` elements at ``offset`` of the buffer (within a :meth:`region`), ``nbytes``
        long; ``bounds``: its (min, max), or None."""
        return self._accessor(self._view_at(offset, nbytes, target), count, kind, component,
                              False if bounds is None else bounds)

    def _accessor(self, view: int, count: int, kind: str, component: int, bounds: bool | tuple) -> int:
        entry = {"bufferView": view, "componentType": component, "count": int(count), "type": kind}
        if bounds is not False:
            entry["min"], entry["max"] = [float(x) for x in bounds[0]], [float(x) for x in bounds[1]]
        self.accessors.append(entry)
        return len(self.accessors) - 1

    def write(self, fh) -> None:
        for piece in self.pieces:
            if isinstance(piece, _Region):
                start = fh.tell()
                piece.write(fh)
                if fh.tell() != start + piece.nbytes:  # a bug in the region's writer, not the user's input
                    raise RuntimeError(f"a glTF buffer region wrote {fh.tell() - start} bytes of {piece.nbytes}")
            else:
                fh.write(memoryview(piece).cast("B") if isinstance(piece, np.ndarray) else piece)

    def to_bytes(self) -> bytes:
        out = io.BytesIO()
        self.write(out)
        return out.getvalue()


class _Region(NamedTuple):
    """Bytes of a :class:`GlbBuffer` made as the buffer is written."""

    nbytes: int
    write: Callable[[Any], None]


def write_glb(fh, doc: dict, buffer: GlbBuffer | bytes) -> None:
    """A binary glTF file: the header, the JSON chunk (``doc``) and the binary chunk (``buffer``, 4-byte aligned;
    left out when empty)."""
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    length = buffer.length if isinstance(buffer, GlbBuffer) else len(buffer)
    fh.write(struct.pack("<III", _GLB_MAGIC, 2, 12 + 8 + len(text) + (8 + length if length else 0)))
    fh.write(struct.pack("<II", len(text), _GLB_JSON) + text)
    if length:
        fh.write(struct.pack("<II", length, _GLB_BIN))
        if isinstance(buffer, GlbBuffer):
            buffer.write(fh)
        else:
            fh.write(buffer)


def _write_gltf(target: Path, mesh: Mesh, *, binary: bool, name: str) -> None:
    """Write glTF 2.0: one primitive per material, vertices split where UVs differ, PNG textures (embedded in .glb,
    beside a .gltf). ``name``, the stem of the user's path, names the materials (``target`` may be a temporary
    file)."""
    buffer = GlbBuffer()
    textured = bool(mesh.textures) and mesh.triangle_uvs is not None
    primitives = []
    for material, source, triangles, uvs in primitive_groups(mesh):
        attributes = {
            "POSITION": buffer.accessor(mesh.vertices[source].astype(np.float32), "VEC3", _FLOAT, 34962, bounds=True)
        }
        if mesh.vertex_normals is not None:
            attributes["NORMAL"] = buffer.accessor(mesh.vertex_normals[source].astype(np.float32), "VEC3", _FLOAT,
                                                   34962)
        if mesh.vertex_colors is not None:
            attributes["COLOR_0"] = buffer.accessor(mesh.vertex_colors[source].astype(np.float32), "VEC3", _FLOAT,
                                                    34962)
        if uvs is not None:
            st = uvs * [1.0, -1.0] + [0.0, 1.0]  # glTF puts the UV origin at the top left
            attributes["TEXCOORD_0"] = buffer.accessor(st.astype(np.float32), "VEC2", _FLOAT, 34962)
        indices = buffer.accessor(triangles.reshape(-1).astype(np.uint32), "SCALAR", _UINT, 34963)
        primitive = {"attributes": attributes, "indices": indices, "mode": 4}  # mode 4: triangles
        if material is not None:
            primitive["material"] = material
        primitives.append(primitive)

    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "kpd"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": primitives}],
    }
    if textured:
        images, materials = [], []
        for i, texture in enumerate(mesh.textures):
            material: dict[str, Any] = {"name": f"{name}_{i}",
                                        "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0}}
            materials.append(material)
            if texture.shape[0] * texture.shape[1] == 1:  # a plain colour (sRGB in the image, linear in glTF)
                rgb = texture.reshape(-1)[:3] if texture.shape[2] >= 3 else np.repeat(texture.reshape(-1)[:1], 3)
                factor = _srgb_to_linear(rgb / 255.0).tolist()
                material["pbrMetallicRoughness"]["baseColorFactor"] = [*factor, 1.0]
                continue
            jpeg = _original_jpeg(mesh, i)
            data, mime = (jpeg, "image/jpeg") if jpeg is not None else (encode_png(texture), "image/png")
            if binary:
                images.append({"bufferView": buffer.view(data), "mimeType": mime})
            else:
                name = f"{target.stem}_{i}{'.jpg' if jpeg is not None else '.png'}"
                (target.parent / name).write_bytes(data)
                images.append({"uri": urllib.parse.quote(name)})
            material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": len(images) - 1}
        if images:
            doc["images"] = images
            doc["textures"] = [{"source": i} for i in range(len(images))]
        doc["materials"] = materials
    doc["bufferViews"] = buffer.views
    doc["accessors"] = buffer.accessors
    if binary:
        doc["buffers"] = [{"byteLength": buffer.length}]
        with open(target, "wb") as fh:
            write_glb(fh, doc, buffer)
    else:  # the buffer as a data URI, the document's last value, written in pieces of base64 into the JSON text
        prefix = "data:application/octet-stream;base64,"
        doc["buffers"] = [{"byteLength": buffer.length, "uri": prefix}]
        text = json.dumps(doc, indent=1)
        cut = text.rindex(prefix) + len(prefix)
        data = memoryview(buffer.to_bytes())
        with open(target, "w", encoding="utf-8") as fh:
            fh.write(text[:cut])
            for start in range(0, len(data), _BASE64_PIECE):
                fh.write(base64.b64encode(data[start : start + _BASE64_PIECE]).decode("ascii"))
            fh.write(text[cut:])


_BASE64_PIECE = 3 << 20  # bytes of the buffer encoded at a time (a multiple of 3: the pieces join without padding)


def read_gltf_json(p: Path) -> tuple[dict, bytes | None]:
    data = p.read_bytes()
    if p.suffix.lower() != ".glb":
        return json.loads(data.decode("utf-8")), None
    magic, _, _ = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC:
        raise ValueError("not a binary glTF file")
    doc, chunk, offset = None, None, 12
    while offset + 8 <= len(data):
        length, kind = struct.unpack_from("<II", data, offset)
        body = data[offset + 8 : offset + 8 + length]
        if kind == _GLB_JSON:
            doc = json.loads(body.decode("utf-8"))
        elif kind == _GLB_BIN:
            chunk = body
        offset += 8 + length
    if doc is None:
        raise ValueError("no JSON chunk")
    return doc, chunk


def _gltf_uri_bytes(p: Path, uri: str, limit: int = IMAGE_BYTES, root: Path | None = None) -> bytes | str | None:
    """The bytes a URI of the glTF ``p`` names: a ``data:`` URI's own, or a file's as :mod:`kpd.io.references`
    allows (inside the file's folder, a regular file of at most ``limit`` bytes); else why it is not read (a str), or
    None when the file is missing."""
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    found = references.locate_uri(p.parent if root is None else root, p.parent, uri)
    if found.path is None:
        return found.refused
    return references.read_named(found.path, limit)


def _image_files(p: Path, doc: dict, root: Path | None = None) -> dict[int, tuple[bytes, np.ndarray]]:
    """{image index: (its file's bytes, its pixels)} of the images the glTF ``p`` keeps in files beside it that
    :mod:`kpd.io.references` allows and that decode: the only image files a write copies. One warning for each
    other one."""
    out = {}
    said: set = set()
    for i, image in enumerate(doc.get("images", [])):
        uri = image.get("uri") if isinstance(image, dict) else None
        if not isinstance(uri, str) or uri.startswith("data:"):
            continue
        raw = _gltf_uri_bytes(p, uri, IMAGE_BYTES, root)
        if raw is None:
            log.warning("%s: texture file %r is missing; read without it", p, uri)
            continue
        pixels = decode_image(raw) if isinstance(raw, bytes) else None
        if pixels is None:
            references.warn_refused(p, "image", uri, raw if isinstance(raw, str) else "not an image that decodes",
                                    said)
            continue
        out[i] = (raw, pixels)
    return out


# --- kpd's own reader and the writer that keeps the file ------------------------------------------------------------

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class GltfSource:
    """A glTF file as read: its JSON, its buffers, and where each of the mesh's vertices came from.

    ``blocks`` lists, per (node, POSITION accessor) pair, the node's world matrix (4, 4), the accessor, the NORMAL
    accessor (or None) and the first row of the block in the mesh's vertices; the mesh's vertex rows are the
    blocks' accessor rows, in order. ``image_files`` holds the image files kpd read beside it (the only ones a write
    copies).
    """

    def __init__(self, path: Path, doc: dict, buffers: list, blocks: list, vertices: np.ndarray,
                 triangles: np.ndarray, normals: np.ndarray | None, image_files: dict | None = None) -> None:
        self.path, self.doc, self.buffers, self.blocks = path, doc, buffers, blocks
        self.vertices, self.triangles, self.normals = vertices, triangles, normals
        self.image_files = {} if image_files is None else image_files  # {index: (bytes, pixels)}, _image_files


def read_buffers(p: Path, doc: dict, chunk: bytes | None, root: Path | None = None) -> list:
    """The bytes of every buffer: the ``.glb``'s binary chunk, a ``data:`` URI's, or a file's beside the glTF as
    :mod:`kpd.io.references` allows (at most the memory kpd may take: checked before it is read)."""
    out = []
    for i, buffer in enumerate(doc.get("buffers", [])):
        declared = buffer.get("byteLength", 0)
        if isinstance(declared, bool) or not isinstance(declared, int) or declared < 0:
            raise InputError(f"{p}: buffer {i} declares a byteLength of {declared!r}")
        if "uri" in buffer:
            uri = buffer["uri"]
            if not isinstance(uri, str):
                raise InputError(f"{p}: buffer {i} has a uri that is not a string")
            data = _gltf_uri_bytes(p, uri, memory_free(), root)
            if data is None:
                raise InputError(f"{p}: its buffer {uri!r} is missing")
            if isinstance(data, str):
                raise InputError(f"{p}: its buffer {uri!r} is not read ({data})")
        elif i == 0 and chunk is not None:
            data = chunk
        else:
            raise InputError(f"{p}: buffer {i} has no data (a .glb without its binary chunk?)")
        if len(data) < declared:
            raise InputError(f"{p}: buffer {i} holds {len(data)} of its {declared} bytes (truncated)")
        out.append(data)
    return out


def _count(p: Path, what: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise InputError(f"{p}: {what} must be a non-negative integer; got {value!r}")
    return value


def _view_range(p: Path, doc: dict, buffers: list, index: Any) -> tuple[bytes, int, int, int | None]:
    """(the buffer, the view's first byte, its length, its byteStride) of a buffer view, checked to lie inside its
    buffer."""
    view = doc["bufferViews"][index]
    buffer = _count(p, f"bufferView {index}'s buffer", view["buffer"])
    if buffer >= len(buffers):
        raise InputError(f"{p}: bufferView {index} names buffer {buffer} of {len(buffers)}")
    start = _count(p, f"bufferView {index}'s byteOffset", view.get("byteOffset", 0))
    length = _count(p, f"bufferView {index}'s byteLength", view["byteLength"])
    if start + length > len(buffers[buffer]):
        raise InputError(f"{p}: bufferView {index} reaches byte {start + length} of its buffer's "
                         f"{len(buffers[buffer])} (truncated file?)")
    stride = view.get("byteStride")
    return buffers[buffer], start, length, None if stride is None else _count(p, f"bufferView {index}'s byteStride",
                                                                                stride)


def _held_elements(p: Path, doc: dict) -> int:
    """The most elements any accessor with data in a buffer view can hold: the bound of an accessor without one
    (zeros and its sparse values), so that a file declares no more than it carries."""
    most = 0
    views = doc.get("bufferViews", [])
    for acc in doc.get("accessors", []):
        if not isinstance(acc, dict) or not isinstance(acc.get("bufferView"), int) or \
                not 0 <= acc["bufferView"] < len(views) or not isinstance(views[acc["bufferView"]], dict):
            continue
        size = np.dtype(_COMPONENTS.get(acc.get("componentType"), np.uint8)).itemsize
        size *= _WIDTH.get(acc.get("type"), 1)
        length = views[acc["bufferView"]].get("byteLength", 0)
        count = acc.get("count", 0)
        if isinstance(length, int) and isinstance(count, int):
            most = max(most, min(count, length // size))
    return most


def read_accessor(p: Path, doc: dict, buffers: list, index: int) -> np.ndarray:
    """(count, width) array of an accessor (float64 for floats and normalized integers)."""
    acc = doc["accessors"][index]
    dtype = np.dtype(_COMPONENTS[acc["componentType"]]).newbyteorder("<")
    width = _WIDTH[acc["type"]]
    count = _count(p, f"accessor {index}'s count", acc["count"])
    element = dtype.itemsize * width
    if "bufferView" in acc:
        data, start, length, stride = _view_range(p, doc, buffers, acc["bufferView"])
        offset = _count(p, f"accessor {index}'s byteOffset", acc.get("byteOffset", 0))
        stride = stride or element
        if stride < element:
            raise InputError(f"{p}: accessor {index}'s elements of {element} bytes overlap (byteStride {stride})")
        if count and offset + stride * (count - 1) + element > length:
            raise InputError(f"{p}: accessor {index} reaches past the end of its buffer view (truncated file?)")
        raw = np.ndarray((count, width), dtype=dtype, buffer=data, offset=start + offset,
                         strides=(stride, dtype.itemsize))
        out = np.array(raw)
    else:
        if count > _held_elements(p, doc):
            raise InputError(f"{p}: accessor {index} declares {count} elements and holds no data (no bufferView); "
                             "no accessor of the file holds that many")
        if count * width * (8 + dtype.itemsize) > memory_free():
            raise InputError(f"{p}: accessor {index} declares {count} elements, more than the memory left can hold")
        out = np.zeros((count, width), dtype=dtype)
    sparse = acc.get("sparse")
    if sparse:
        idx_view = doc["bufferViews"][sparse["indices"]["bufferView"]]
        idx_type = np.dtype(_COMPONENTS[sparse["indices"]["componentType"]]).newbyteorder("<")
        n = _count(p, f"accessor {index}'s sparse count", sparse["count"])
        if n > count:
            raise InputError(f"{p}: accessor {index} has {n} sparse values for its {count} elements")
        idx = np.frombuffer(buffers[idx_view["buffer"]], dtype=idx_type, count=n,
                            offset=idx_view.get("byteOffset", 0) + sparse["indices"].get("byteOffset", 0))
        val_view = doc["bufferViews"][sparse["values"]["bufferView"]]
        values = np.frombuffer(buffers[val_view["buffer"]], dtype=dtype, count=n * width,
                               offset=val_view.get("byteOffset", 0) + sparse["values"].get("byteOffset", 0))
        out[idx.astype(np.int64)] = values.reshape(n, width)
    if out.dtype.kind == "f":
        return out.astype(np.float64)
    if acc.get("normalized"):
        info = np.iinfo(out.dtype)
        return np.maximum(out.astype(np.float64) / info.max, -1.0)
    return out.astype(np.int64)


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major in the file
    m = np.eye(4)
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m[:3, :3] = rotation * np.asarray(node.get("scale", [1.0, 1.0, 1.0]), dtype=np.float64)
    m[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return m


def _mesh_nodes(doc: dict) -> list[tuple[int, np.ndarray]]:
    """(node index, world matrix) of every node with a mesh in the default scene (all root nodes without one)."""
    nodes = doc.get("nodes", [])
    scenes = doc.get("scenes", [])
    if scenes:
        roots = scenes[doc.get("scene", 0)].get("nodes", [])
    else:
        children = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out = []
    stack = [(r, np.eye(4)) for r in reversed(roots)]
    seen = set()
    while stack:
        i, parent = stack.pop()
        if i in seen:
            continue
        seen.add(i)
        world = parent @ _node_matrix(nodes[i])
        if "mesh" in nodes[i]:
            out.append((i, world))
        stack.extend((c, world) for c in reversed(nodes[i].get("children", [])))
    if not out and not nodes and doc.get("meshes"):
        out = [(None, np.eye(4))]
    return out


def _primitive_triangles(p: Path, doc: dict, buffers: list, prim: dict, n: int) -> np.ndarray | None:
    mode = prim.get("mode", 4)
    index = (read_accessor(p, doc, buffers, prim["indices"]).reshape(-1) if "indices" in prim
             else np.arange(n, dtype=np.int64))
    if mode == 4:
        tri = index[: len(index) // 3 * 3].reshape(-1, 3)
    elif mode == 5:  # strip: every other triangle turned to keep the winding
        tri = np.stack([index[:-2], index[1:-1], index[2:]], axis=1)
        tri[1::2] = tri[1::2][:, [1, 0, 2]]
    elif mode == 6:  # fan
        tri = np.stack([np.full(len(index) - 2, index[0]), index[1:-1], index[2:]], axis=1)
    else:
        return None
    if len(tri) and (tri.min() < 0 or tri.max() >= n):
        raise InputError(f"{p}: a primitive's indices reach vertex {int(tri.max())} of {n}")
    return tri


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, np.power((c + 0.055) / 1.055, 2.4))


def read(p: Path, name: str | None = None, *, points: bool = False, root: Path | None = None) -> "Mesh | PointSet":
    """Read a ``.gltf``/``.glb`` (every triangle primitive of every mesh node of the default scene, in world
    coordinates, each primitive's vertices in the file's order), with its materials' base colours and images; the
    files it names are read inside ``root`` only (its own folder when None; :mod:`kpd.io.references`)."""
    from kpd.io.images import read_image_bytes
    from kpd.mesh import PointSet

    try:
        doc, chunk = read_gltf_json(p)
    except (ValueError, KeyError, struct.error, UnicodeDecodeError, RecursionError) as exc:
        raise InputError(f"{p}: could not be read as glTF ({exc})") from None
    asset = doc.get("asset", {}) if isinstance(doc, dict) else None
    if not isinstance(asset, dict) or str(asset.get("version", "2.0")).split(".")[0] != "2":
        raise InputError(f"{p}: not a glTF 2.0 file")
    try:
        return _read(p, doc, chunk, name if name is not None else str(p), points, read_image_bytes, PointSet, root)
    except InputError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        # an object where the specification has a number, a list or a string (or the other way round), anywhere
        raise InputError(f"{p}: a malformed glTF file ({type(exc).__name__}: {exc})") from None


def _read(p, doc, chunk, name, points, read_image_bytes, PointSet, root=None):
    buffers = read_buffers(p, doc, chunk, root)
    blocks, vertices, normals, colors, tris, corner_uvs, has_uv, materials = [], [], [], [], [], [], [], []
    offset = 0
    skipped = 0
    meshes = doc.get("meshes", [])
    for node, world in _mesh_nodes(doc):
        mesh_index = doc["nodes"][node]["mesh"] if node is not None else 0
        placed: dict[int, int] = {}
        normal_matrix = np.linalg.inv(world[:3, :3]).T
        for prim in meshes[mesh_index]["primitives"]:
            attributes = prim["attributes"]
            position = attributes["POSITION"]
            if position not in placed:
                local = read_accessor(p, doc, buffers, position)[:, :3]
                placed[position] = offset
                vertices.append(local @ world[:3, :3].T + world[:3, 3])
                normal = attributes.get("NORMAL")
                if normal is not None:
                    n = read_accessor(p, doc, buffers, normal)[:, :3] @ normal_matrix.T
                    length = np.linalg.norm(n, axis=1, keepdims=True)
                    normals.append(np.divide(n, length, out=np.zeros_like(n), where=length > 0))
                else:
                    normals.append(None)
                color = attributes.get("COLOR_0")
                colors.append(None if color is None else np.clip(read_accessor(p, doc, buffers, color)[:, :3], 0, 1))
                blocks.append({"node": node, "world": world, "position": position, "normal": normal,
                               "start": offset, "count": len(local)})
                offset += len(local)
            start = placed[position]
            count = doc["accessors"][position]["count"]
            tri = _primitive_triangles(p, doc, buffers, prim, count)
            if tri is None:
                skipped += 1
                continue
            if np.linalg.det(world[:3, :3]) < 0:
                tri = tri[:, [0, 2, 1]]  # a mirroring node turns the winding
            tris.append(tri + start)
            uv = attributes.get("TEXCOORD_0")
            if uv is not None:
                st = read_accessor(p, doc, buffers, uv)[:, :2]
                corner_uvs.append((st * [1.0, -1.0] + [0.0, 1.0])[tri].reshape(-1, 2))
                has_uv.append(np.ones(len(tri), dtype=bool))
            else:
                corner_uvs.append(np.zeros((3 * len(tri), 2)))
                has_uv.append(np.zeros(len(tri), dtype=bool))
            materials.append(np.full(len(tri), prim.get("material", -1), dtype=np.int64))
    if skipped:
        log.warning("%s: %d primitive(s) of points or lines read without them (kpd reads triangles)", p, skipped)
    if not vertices:
        raise InputError(f"{p}: no vertices (empty geometry)")
    V = np.vstack(vertices)
    if not tris or not sum(len(t) for t in tris):
        if points:
            return PointSet(V, path=name)
        raise InputError(f"{p}: has {len(V)} vertices but no triangles (a point cloud? use read_points or "
                         "read_shape)")
    T = np.vstack(tris)
    N = None
    if any(n is not None for n in normals):
        from kpd.triangles import vertex_normals

        computed = vertex_normals(V, T)
        N = np.vstack([n if n is not None else computed[b["start"]:b["start"] + b["count"]]
                       for n, b in zip(normals, blocks)])
    C = None
    if any(c is not None for c in colors):
        C = np.vstack([c if c is not None else np.ones((b["count"], 3)) for c, b in zip(colors, blocks)])
    mask = np.concatenate(has_uv)
    uvs = np.vstack(corner_uvs) if mask.any() else None
    ids = np.concatenate(materials)
    files = _image_files(p, doc, root)
    textures, texture_ids = _materials(p, doc, buffers, ids, read_image_bytes, files)
    if textures and uvs is None:
        uvs = np.zeros((3 * len(T), 2))
    mesh = Mesh(vertices=V, triangles=T, vertex_normals=N, vertex_colors=C, triangle_uvs=uvs, textures=textures,
                triangle_material_ids=texture_ids, triangle_uv_mask=mask if uvs is not None else None, path=name)
    mesh_uses = [n.get("mesh") for n in doc.get("nodes", []) if "mesh" in n]
    if len(mesh_uses) == len(set(mesh_uses)):  # an instanced mesh cannot take two deformations: written anew
        mesh._source = GltfSource(p, doc, buffers, blocks, V, T, N, files)
    return mesh


def _materials(p: Path, doc: dict, buffers: list, ids: np.ndarray, read_image_bytes,
               files: dict) -> tuple[list, np.ndarray | None]:
    """One texture per used material: its base-colour image, or a 1x1 image of its base colour (sRGB). ``files``:
    the image files read beside the glTF (:func:`_image_files`)."""
    used, compact = np.unique(ids, return_inverse=True)
    images, colors = [], []
    cache: dict[int, np.ndarray | None] = {}
    for m in used:
        material = doc["materials"][m] if 0 <= m < len(doc.get("materials", [])) else {}
        pbr = material.get("pbrMetallicRoughness", {})
        factor = pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0])
        image = None
        ref = pbr.get("baseColorTexture")
        if ref is not None:
            try:
                source = doc["textures"][ref["index"]]["source"]
                if source in files:
                    cache[source] = files[source][1]
                elif source not in cache:
                    raw = _image_bytes(p, doc, buffers, doc["images"][source])
                    cache[source] = None if raw is None else read_image_bytes(raw, f"{p} image {source}")
                image = cache[source]
            except (KeyError, IndexError, TypeError) as exc:
                log.warning("%s: the texture of material %d cannot be read (%s); read without it", p, m, exc)
        color = _linear_to_srgb(factor[:3]) if m >= 0 else np.array([0.8, 0.8, 0.8])
        images.append(image)
        colors.append(tuple(np.round(color * 255).astype(int)))
    if not any(i is not None for i in images) and len(set(colors)) <= 1:
        return [], None
    textures = [i if i is not None else np.array(c, dtype=np.uint8).reshape(1, 1, 3) for i, c in zip(images, colors)]
    return textures, compact.reshape(-1).astype(np.int64)


def _image_bytes(p: Path, doc: dict, buffers: list, image: dict) -> bytes | None:
    """The bytes of an image kept in the glTF itself (a buffer view, a ``data:`` URI); None for a file beside it
    (read by :func:`_image_files`, or not at all)."""
    if "bufferView" in image:
        data, start, length, _ = _view_range(p, doc, buffers, image["bufferView"])
        return bytes(data[start : start + length])
    uri = image["uri"]
    return base64.b64decode(uri.split(",", 1)[1]) if uri.startswith("data:") else None


def own_source(mesh: Mesh, p: Path) -> GltfSource | None:
    """The glTF the mesh was read from, when it can be written again in its own structure to ``p``."""
    source = getattr(mesh, "_source", None)
    if not isinstance(source, GltfSource) or len(source.vertices) != len(mesh.vertices):
        return None
    if source.path.suffix.lower() != p.suffix.lower() or len(source.triangles) != len(mesh.triangles):
        return None
    return source


def source_companions(p: Path, source: GltfSource) -> dict:
    """{index of an external buffer or image: (its uri, the output's name for it)} of a ``.gltf``'s files."""
    out = {}
    taken = {p.name.lower()}
    for kind in ("buffers", "images"):
        for i, item in enumerate(source.doc.get(kind, [])):
            uri = item.get("uri")
            if uri is None or uri.startswith("data:") or (kind == "images" and i not in source.image_files):
                continue  # kept in the file, or an image file kpd did not read: not copied
            name = f"{p.stem}_{Path(urllib.parse.unquote(uri)).name}"
            base, suffix = name.rsplit(".", 1) if "." in name else (name, "")
            k = 2
            while name.lower() in taken:
                name = f"{base}_{k}.{suffix}" if suffix else f"{base}_{k}"
                k += 1
            taken.add(name.lower())
            out[(kind, i)] = (uri, name)
    return out


def write_from_source(target: Path, mesh: Mesh, source: GltfSource) -> None:
    """Write the source's glTF again with the mesh's positions (and normals turned with them): every node,
    primitive, material, image and extension as it was."""
    import copy

    from kpd.triangles import turned_normals

    doc = copy.deepcopy(source.doc)
    buffers = [bytearray(b) for b in source.buffers]
    changed = not np.array_equal(mesh.vertices, source.vertices)
    written: dict[tuple, np.ndarray] = {}  # data region -> rows written there (data shared by two placements)
    normals_new = None
    if changed and any(b["normal"] is not None for b in source.blocks):
        normals_new = turned_normals(source.vertices, mesh.vertices, source.triangles, source.triangles,
                                     source.normals)
    for block in source.blocks:
        if not changed:
            break
        rows = slice(block["start"], block["start"] + block["count"])
        world = block["world"]
        local = (mesh.vertices[rows] - world[:3, 3]) @ np.linalg.inv(world[:3, :3]).T
        _put(doc, buffers, block, "POSITION", block["position"], local, written, bounds=True)
        if block["normal"] is not None and normals_new is not None:
            n = normals_new[rows] @ world[:3, :3]  # back through the inverse-transpose
            length = np.linalg.norm(n, axis=1, keepdims=True)
            n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
            _put(doc, buffers, block, "NORMAL", block["normal"], n, written, bounds=False)
    binary = target.suffix.lower() == ".glb"
    for i, buffer in enumerate(doc.get("buffers", [])):
        buffer["byteLength"] = len(buffers[i])
        uri = buffer.get("uri")
        if uri is not None and uri.startswith("data:"):
            buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(buffers[i])).decode()
    for (kind, i), (_, name) in source_companions(target, source).items():
        doc[kind][i]["uri"] = urllib.parse.quote(name)
        data = bytes(buffers[i]) if kind == "buffers" else source.image_files[i][0]
        (target.parent / name).write_bytes(data)
    if binary:
        blob = bytes(buffers[0]) if buffers and "uri" not in doc["buffers"][0] else b""
        blob += b"\0" * (-len(blob) % 4)
        if blob:
            doc["buffers"][0]["byteLength"] = len(blob)
        with open(target, "wb") as fh:
            write_glb(fh, doc, blob)
    else:
        target.write_text(json.dumps(doc, indent=1), encoding="utf-8")


def _put(doc: dict, buffers: list, block: dict, attribute: str, accessor: int, rows: np.ndarray, written: dict,
         *, bounds: bool) -> None:
    """Store ``rows`` (n, 3) as the accessor's data: in place when it is plain float32 data of its own, else as a
    new accessor that this node's primitives use."""
    acc = doc["accessors"][accessor]
    values = rows.astype(np.float32)
    region = (acc.get("bufferView"), acc.get("byteOffset", 0), accessor if "bufferView" not in acc else None)
    if region in written and not np.array_equal(written[region], values):
        new = _new_accessor(doc, buffers, values, bounds)  # one accessor in two meshes placed apart: split
        for prim in _block_primitives(doc, block):
            if prim["attributes"].get(attribute) == accessor:
                prim["attributes"][attribute] = new
        return
    written[region] = values
    plain = (acc["componentType"] == _FLOAT and "sparse" not in acc and "bufferView" in acc)
    if plain:
        view = doc["bufferViews"][acc["bufferView"]]
        stride = view.get("byteStride") or 12
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        target = np.ndarray((len(values), 3), dtype="<f4", buffer=buffers[view["buffer"]], offset=start,
                            strides=(stride, 4))
        target[...] = values
    else:
        new = _new_accessor(doc, buffers, values, bounds)
        for prim in _block_primitives(doc, block):
            if prim["attributes"].get(attribute) == accessor:
                prim["attributes"][attribute] = new
        acc = doc["accessors"][new]
    if bounds:
        acc["min"], acc["max"] = values.min(axis=0).tolist(), values.max(axis=0).tolist()


def _block_primitives(doc: dict, block: dict) -> list:
    mesh = doc["nodes"][block["node"]]["mesh"] if block["node"] is not None else 0
    return doc["meshes"][mesh]["primitives"]


def _new_accessor(doc: dict, buffers: list, values: np.ndarray, bounds: bool) -> int:
    if not buffers:
        buffers.append(bytearray())
        doc.setdefault("buffers", []).append({"byteLength": 0})
    blob = buffers[0]
    blob.extend(b"\0" * (-len(blob) % 4))
    doc.setdefault("bufferViews", []).append({"buffer": 0, "byteOffset": len(blob), "byteLength": values.nbytes,
                                              "target": 34962})
    blob.extend(values.astype("<f4").tobytes())
    acc = {"bufferView": len(doc["bufferViews"]) - 1, "componentType": _FLOAT, "count": len(values), "type": "VEC3"}
    if bounds:
        acc["min"], acc["max"] = values.min(axis=0).tolist(), values.max(axis=0).tolist()
    doc.setdefault("accessors", []).append(acc)
    return len(doc["accessors"]) - 1
