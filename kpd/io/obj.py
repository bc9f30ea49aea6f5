"""OBJ: faces must be triangles (Assimp inside Open3D drops polygons silently), missing material libraries and
texture maps are reported, and writing checks what Open3D wrote (vertex and face counts, the ``.mtl`` and one PNG per
texture)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

from kpd.errors import InputError, WriteError
from kpd.io.atomic import atomic_files
from kpd.io.capture import open3d_module, open3d_write
from kpd.io.common import incomplete, verify_companion
from kpd.mesh import Mesh, count_phrase

__all__ = ["check_faces", "warn_missing_textures", "write", "companions"]

log = logging.getLogger(__name__)

_OBJ_POLYGON = re.compile(rb"^[ \t]*f[ \t]+\S+[ \t]+\S+[ \t]+\S+[ \t]+[^\s#]", re.M)


_OBJ_SHORT_FACE = re.compile(rb"^[ \t]*f(?:[ \t]+[^\s#]+){0,2}[ \t]*(?:#.*)?\r?$", re.M)



def check_faces(p: Path, data: bytes) -> None:
    """Refuse OBJ faces that are not triangles: Assimp (inside Open3D) drops such faces and their objects silently."""
    polygons = len(_OBJ_POLYGON.findall(data))
    if polygons:
        raise InputError(
            f"{p}: {count_phrase(polygons, 'faces')} more than 3 vertices; kpd reads triangle meshes only "
            "(triangulate it first, e.g. Blender: Triangulate Faces)"
        )
    short = len(_OBJ_SHORT_FACE.findall(data))
    if short:
        raise InputError(f"{p}: {count_phrase(short, 'faces')} fewer than 3 vertices")


def warn_missing_textures(p: Path, data: bytes) -> None:
    folder = p.parent
    for match in re.finditer(rb"^[ \t]*mtllib[ \t]+(.+?)[ \t]*\r?$", data, re.M):
        name = match.group(1).decode("utf-8", errors="replace")
        mtl = folder / name
        if not mtl.is_file():
            log.warning("%s: material library %r is missing; read without materials and textures", p, name)
            continue
        mtl_data = mtl.read_bytes()
        missing = []
        for tex in re.finditer(rb"^[ \t]*map_Kd[ \t]+(.+?)[ \t]*\r?$", mtl_data, re.M):
            tex_name = tex.group(1).split()[-1].decode("utf-8", errors="replace").replace("\\", "/")
            if not (folder / tex_name).is_file() and not (folder / Path(tex_name).name).is_file():
                missing.append(tex_name)
        if missing:
            log.warning(
                "%s: texture file(s) %s named in %s are missing; read without them",
                p, ", ".join(dict.fromkeys(missing)), name,
            )



def write(p: Path, mesh: Mesh) -> None:
    """Write ``mesh`` to ``p`` through Open3D (with ``<stem>.mtl`` and ``<stem>_<i>.png`` per texture when the mesh
    has UVs), atomically, and check the result."""
    m = mesh.to_open3d()
    textured = mesh.triangle_uvs is not None
    with atomic_files(p) as target:
        open3d_write(lambda: open3d_module().io.write_triangle_mesh(str(target), m), p, target)
        expected = [target.with_suffix(".mtl")] if textured else []
        expected += [target.parent / f"{target.stem}_{i}.png" for i in range(len(mesh.textures) if textured else 0)]
        missing = [f.name for f in expected if not f.is_file()]
        if missing:
            raise WriteError(f"cannot write {p}: Open3D did not write {', '.join(missing)}")
        _verify(p, target, mesh)


def companions(p: Path, mesh: Mesh) -> list[str]:
    """The files :func:`write` adds beside ``p``."""
    if mesh.triangle_uvs is not None:
        return [p.stem + ".mtl"] + [f"{p.stem}_{i}.png" for i in range(len(mesh.textures))]
    return []


def _verify(p: Path, tmp: Path, mesh: Mesh) -> None:
    V, T = len(mesh.vertices), len(mesh.triangles)
    data = tmp.read_bytes()
    v, f = len(re.findall(rb"^v ", data, re.M)), len(re.findall(rb"^f ", data, re.M))
    if v != V or f != T or not data.endswith(b"\n"):
        raise incomplete(p, f"{v} of {V} vertices and {f} of {T} faces")
    for companion in tmp.parent.iterdir():
        if companion != tmp:
            verify_companion(p.parent / companion.name, companion)
