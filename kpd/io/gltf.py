"""glTF 2.0: kpd's own writer, and the base-colour images Open3D leaves out when it reads.

Open3D 0.20 writes neither UVs nor textures to glTF and writes ``.glb`` files without their binary chunk, so kpd
writes glTF itself: one primitive per material, vertices split where UVs differ, PNG textures (embedded in ``.glb``,
beside a ``.gltf``). Reading goes through Open3D (Assimp), after which the images inside a ``.glb`` or a data URI are
filled in here.
"""

from __future__ import annotations

import base64
import json
import logging
import struct
import tempfile
import urllib.parse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kpd.grouping import first_occurrence_groups
from kpd.io.atomic import atomic_files, atomic_output
from kpd.io.capture import open3d_log, open3d_module
from kpd.io.common import verify_companion
from kpd.io.images import encode_png
from kpd.mesh import Mesh

if TYPE_CHECKING:  # pragma: no cover
    import open3d

__all__ = ["write", "companions", "fill_textures", "read_gltf_json", "GLB_MAGIC"]

log = logging.getLogger(__name__)

_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


_FLOAT, _UINT = 5126, 5125

GLB_MAGIC = _GLB_MAGIC


def write(p: Path, mesh: Mesh) -> None:
    """Write ``mesh`` to ``p`` (``.gltf`` or ``.glb``) atomically, with a ``.gltf``'s PNGs beside it."""
    binary = p.suffix.lower() == ".glb"
    if not binary and mesh.textures:
        with atomic_files(p) as target:
            _write_gltf(target, mesh, binary=False)
            for companion in target.parent.iterdir():
                if companion != target:
                    verify_companion(p.parent / companion.name, companion)
    else:
        with atomic_output(p) as target:
            _write_gltf(target, mesh, binary=binary)


def companions(p: Path, mesh: Mesh) -> list[str]:
    """The files :func:`write` adds beside ``p``."""
    if p.suffix.lower() == ".gltf" and mesh.textures and mesh.triangle_uvs is not None:
        return [f"{p.stem}_{i}.png" for i in range(len(mesh.textures))]
    return []


def _write_gltf(target: Path, mesh: Mesh, *, binary: bool) -> None:
    """Write glTF 2.0: one primitive per material, vertices split where UVs differ, PNG textures (embedded in .glb,
    beside a .gltf)."""
    blob = bytearray()
    views: list[dict] = []
    accessors: list[dict] = []

    def add_view(data: bytes, target_kind: int | None = None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        view = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)}
        if target_kind:
            view["target"] = target_kind
        blob.extend(data)
        views.append(view)
        return len(views) - 1

    def add_accessor(a: np.ndarray, kind: str, component: int, target_kind: int, bounds: bool = False) -> int:
        acc = {"bufferView": add_view(a.tobytes(), target_kind), "componentType": component, "count": len(a)}
        acc["type"] = kind
        if bounds:
            acc["min"], acc["max"] = a.min(axis=0).tolist(), a.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    textured = bool(mesh.textures) and mesh.triangle_uvs is not None
    ids = mesh.triangle_material_ids
    if textured and ids is None:
        ids = np.zeros(len(mesh.triangles), dtype=np.int64)
    groups = [(int(u), np.flatnonzero(ids == u)) for u in np.unique(ids)] if textured else [(None, None)]
    primitives = []
    for material, rows in groups:
        tri = mesh.triangles if rows is None else mesh.triangles[rows]  # (t, 3)
        corner_vertex = tri.reshape(-1)  # (3t,)
        if mesh.triangle_uvs is not None:
            uv = mesh.triangle_uvs.reshape(-1, 3, 2)
            corner_uv = (uv if rows is None else uv[rows]).reshape(-1, 2)  # (3t, 2)
            first, index = first_occurrence_groups(np.hstack([corner_vertex[:, None], corner_uv]))
        else:
            corner_uv = None
            first, index = first_occurrence_groups(corner_vertex[:, None])
        source = corner_vertex[first]  # (n,) vertex of each written vertex
        attributes = {
            "POSITION": add_accessor(mesh.vertices[source].astype(np.float32), "VEC3", _FLOAT, 34962, bounds=True)
        }
        if mesh.vertex_normals is not None:
            attributes["NORMAL"] = add_accessor(mesh.vertex_normals[source].astype(np.float32), "VEC3", _FLOAT, 34962)
        if mesh.vertex_colors is not None:
            attributes["COLOR_0"] = add_accessor(mesh.vertex_colors[source].astype(np.float32), "VEC3", _FLOAT, 34962)
        if corner_uv is not None:
            st = corner_uv[first] * [1.0, -1.0] + [0.0, 1.0]  # glTF puts the UV origin at the top left
            attributes["TEXCOORD_0"] = add_accessor(st.astype(np.float32), "VEC2", _FLOAT, 34962)
        indices = add_accessor(index.astype(np.uint32), "SCALAR", _UINT, 34963)
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
        images = []
        for i, texture in enumerate(mesh.textures):
            png = encode_png(texture)
            if binary:
                images.append({"bufferView": add_view(png), "mimeType": "image/png"})
            else:
                name = f"{target.stem}_{i}.png"
                (target.parent / name).write_bytes(png)
                images.append({"uri": urllib.parse.quote(name)})
        doc["images"] = images
        doc["textures"] = [{"source": i} for i in range(len(images))]
        doc["materials"] = [
            {
                "name": f"{target.stem}_{i}",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": i}, "metallicFactor": 0.0, "roughnessFactor": 1.0
                },
            }
            for i in range(len(images))
        ]
    blob.extend(b"\0" * (-len(blob) % 4))
    doc["bufferViews"] = views
    doc["accessors"] = accessors
    buffer: dict[str, Any] = {"byteLength": len(blob)}
    if binary:
        doc["buffers"] = [buffer]
        text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        text += b" " * (-len(text) % 4)
        out = struct.pack("<III", _GLB_MAGIC, 2, 12 + 8 + len(text) + 8 + len(blob))
        out += struct.pack("<II", len(text), _GLB_JSON) + text + struct.pack("<II", len(blob), _GLB_BIN) + bytes(blob)
        target.write_bytes(out)
    else:
        buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode("ascii")
        doc["buffers"] = [buffer]
        target.write_text(json.dumps(doc, indent=1), encoding="utf-8")



def fill_textures(p: Path, m: "open3d.geometry.TriangleMesh") -> None:
    """Load the base-colour images that Open3D leaves out (images inside a .glb or a data URI); warn for missing
    ones. Open3D's texture i belongs to glTF material i."""
    try:
        doc, chunk = read_gltf_json(p)
    except (ValueError, KeyError, struct.error, UnicodeDecodeError) as exc:
        log.warning("%s: could not inspect the glTF materials (%s); textures may be missing", p, exc)
        return
    o3d = open3d_module()
    textures = list(m.textures)
    changed = False
    for i, material in enumerate(doc.get("materials", [])):
        ref = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if ref is None or (i < len(textures) and not textures[i].is_empty()):
            continue
        try:
            image = doc["images"][doc["textures"][ref["index"]]["source"]]
            image_array = _gltf_image(p, doc, chunk, image)
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            log.warning("%s: the texture of material %d cannot be read (%s); read without it", p, i, exc)
            continue
        if image_array is None:
            continue
        while len(textures) <= i:
            textures.append(o3d.geometry.Image())
        textures[i] = o3d.geometry.Image(np.ascontiguousarray(image_array[::-1]))  # Open3D's flipped convention
        changed = True
    if changed:
        m.textures = textures


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


def _gltf_image(p: Path, doc: dict, chunk: bytes | None, image: dict) -> np.ndarray | None:
    """Decode one glTF image; None (with a warning) when its file is missing."""
    if "bufferView" in image:
        view = doc["bufferViews"][image["bufferView"]]
        buffer = doc["buffers"][view["buffer"]]
        data = _gltf_uri_bytes(p, buffer["uri"]) if "uri" in buffer else chunk
        if data is None:
            return None
        start = view.get("byteOffset", 0)
        raw = data[start : start + view["byteLength"]]
        suffix = ".jpg" if image.get("mimeType") == "image/jpeg" else ".png"
    else:
        raw = _gltf_uri_bytes(p, image["uri"])
        if raw is None:
            return None
        jpeg = image["uri"].lower().endswith((".jpg", ".jpeg")) or image["uri"].startswith("data:image/jpeg")
        suffix = ".jpg" if jpeg else ".png"
    o3d = open3d_module()
    with tempfile.TemporaryDirectory() as folder:
        f = Path(folder) / f"texture{suffix}"
        f.write_bytes(raw)
        with open3d_log():
            decoded = np.asarray(o3d.io.read_image(str(f)))
    if not decoded.size:
        raise ValueError("the image data cannot be decoded")
    return decoded.copy()


def _gltf_uri_bytes(p: Path, uri: str) -> bytes | None:
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    f = p.parent / urllib.parse.unquote(uri)
    if not f.is_file():
        log.warning("%s: texture file %r is missing; read without it", p, uri)
        return None
    return f.read_bytes()
