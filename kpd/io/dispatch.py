"""Reading and writing by file extension: the entry points :func:`read_mesh`, :func:`read_points`,
:func:`read_shape`, :func:`write_mesh`, :func:`write_points`, each handing the format's own work to its module
(:mod:`kpd.io.ply`, :mod:`kpd.io.obj`, :mod:`kpd.io.gltf`, ...) and Open3D."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kpd.errors import InputError
from kpd.io import gltf, obj, off, pcd, ply, stl
from kpd.io.atomic import atomic_output, user_path
from kpd.io.capture import failures, open3d_log, open3d_module, open3d_write
from kpd.io.common import (MESH_FORMATS, POINT_FORMATS, check_header_counts, describe, incomplete, input_path,
                           output_path, read_table)
from kpd.mesh import Mesh, PointSet

if TYPE_CHECKING:  # pragma: no cover
    import open3d

__all__ = ["file_up", "read_mesh", "read_points", "read_shape", "write_mesh", "write_points", "mesh_companions"]

log = logging.getLogger(__name__)


# --- reading -------------------------------------------------------------------------------------------------------


def file_up(path: str | os.PathLike | None) -> str | None:
    """The up axis a file's format defines: ``"+y"`` for ``.gltf``/``.glb`` (glTF 2.0 is y up), else None."""
    if path is None:
        return None
    return "+y" if Path(path).suffix.lower() in (".gltf", ".glb") else None


def read_mesh(path: str | os.PathLike, *, files_root: str | os.PathLike | None = None) -> Mesh:
    """Read a triangle mesh.

    Parameters
    ----------
    path : ``.obj``, ``.ply``, ``.off``, ``.stl``, ``.gltf`` or ``.glb``
    files_root : the folder tree the files an OBJ or glTF names (material libraries, maps, images, buffers) must lie
        in; the file's own folder when None. Name a wider one only when you trust all of it (a dataset that keeps
        maps beside its models' folders, as ShapeNet's ``../images``); see :mod:`kpd.io.references`.

    Returns
    -------
    Mesh
        With normals, colours, UVs, textures and material ids when the file has them.

    Raises
    ------
    InputError
        For a missing file, an unknown extension, an unreadable, truncated or empty file, a file without triangles,
        NaN or inf coordinates, or triangles that index missing vertices. A texture file that is missing, or one
        that is not read (outside ``files_root``, not a regular file, not an image), is not an error: the mesh is read
        without it and one warning naming it is logged.
    """
    p, ext = input_path(path, MESH_FORMATS, "mesh")
    root = None if files_root is None else Path(files_root)
    if ext == ".obj":
        return obj.read(p, os.fspath(path), root=root)
    if ext in (".gltf", ".glb"):
        return gltf.read(p, os.fspath(path), root=root)
    if ext == ".ply":  # a PLY by kpd (numpy; compiled passes for ASCII), as Open3D reads it; the rest by Open3D
        ply.check_complete(p)
        mesh = ply.read_mesh(p, os.fspath(path)) if _has_faces(p) else None
        if mesh is not None:
            return mesh
    if ext == ".stl":  # a binary STL through numpy, welded as Open3D's reader and stl.weld weld it; ASCII by Open3D
        welded = stl.read(p)
        if welded is not None:
            return Mesh(*welded, path=os.fspath(path))
    if ext == ".off":  # text OFF by kpd, its numbers exact; binary OFF and words kpd leaves to Open3D by Open3D
        mesh = off.read_mesh(p, os.fspath(path))
        if mesh is not None:
            return mesh
    m = _read_open3d_mesh(p, ext)
    if len(m.triangles) == 0:
        raise InputError(
            f"{p}: has {len(m.vertices)} vertices but no triangles (a point cloud? use read_points or read_shape)"
        )
    return Mesh.from_open3d(m, path=os.fspath(path))


def _has_faces(p: Path) -> bool:
    """Whether a PLY's header declares a non-empty ``face`` element."""
    return any(element.name == "face" and element.count > 0 for element in ply.read_header(p).elements)


def read_points(path: str | os.PathLike, *, drop_nonfinite: bool = False) -> PointSet:
    """Read a point cloud, or the vertices of a mesh file.

    Parameters
    ----------
    path : ``.ply``, ``.pcd``, ``.xyz``, ``.pts``, ``.npy``, ``.npz`` or a mesh format (its vertices).
        ``.xyz``: whitespace-separated text, the first three columns are coordinates. ``.pts``: text with 3 or 6
        columns (xyz or xyz + normals, as in ShapeNetPart and the authors' demo); an optional first line holding
        only the point count is skipped. ``.npy``: an (N, 3) or (N, 6) (xyz + normals) array. ``.npz``: key
        ``points``, optional ``normals`` and ``colors``.
    drop_nonfinite : drop points whose coordinates or normals are NaN or inf (with a logged warning) instead of
        raising; for raw scans.

    Returns
    -------
    PointSet

    Raises
    ------
    InputError
        For a missing, unknown, unreadable, truncated or empty file, malformed rows or arrays, or non-finite points
        (unless ``drop_nonfinite``).
    """
    p, ext = input_path(path, tuple(dict.fromkeys(POINT_FORMATS + MESH_FORMATS)), "point")
    name = os.fspath(path)
    points, normals, colors = _read_point_arrays(p, ext)
    if drop_nonfinite:
        bad = ~np.isfinite(points).all(axis=1)
        if normals is not None:
            bad |= ~np.isfinite(normals).all(axis=1)
        if bad.any():
            log.warning("%s: dropped %d of %d points with NaN or inf values", name, int(bad.sum()), len(points))
            keep = ~bad
            points = points[keep]
            normals = None if normals is None else normals[keep]
            colors = None if colors is None else colors[keep]
    return PointSet(points, normals, colors, path=name)


def read_shape(path: str | os.PathLike, *, files_root: str | os.PathLike | None = None) -> Mesh | PointSet:
    """Read a file as a :class:`Mesh` if it has triangles, else as a :class:`PointSet`.

    Mesh formats (``.obj .off .stl .gltf .glb`` and ``.ply`` with faces) give a Mesh; ``.ply`` without faces and
    the point formats give a PointSet. ``files_root`` and errors as in :func:`read_mesh` and :func:`read_points`.
    """
    p, ext = input_path(path, tuple(dict.fromkeys(MESH_FORMATS + POINT_FORMATS)), "shape")
    root = None if files_root is None else Path(files_root)
    if ext not in MESH_FORMATS:
        return read_points(path)
    if ext == ".obj":
        return obj.read(p, os.fspath(path), points=True, root=root)
    if ext in (".gltf", ".glb"):
        return gltf.read(p, os.fspath(path), points=True, root=root)
    if ext == ".off":  # text OFF by kpd, as in read_mesh
        shape = off.read_mesh(p, os.fspath(path), points=True)
        if shape is not None:
            return shape
    if ext == ".ply":  # by kpd, as in read_mesh; a PLY without faces as Open3D's mesh reader gives its vertices
        ply.check_complete(p)
        if _has_faces(p):
            mesh = ply.read_mesh(p, os.fspath(path))
            if mesh is not None:
                return mesh
        else:
            arrays = ply.read_vertices(p)
            if arrays is not None:
                if len(arrays[0]) == 0:
                    raise InputError(f"{p}: no vertices (empty geometry)")
                return PointSet(*arrays, path=os.fspath(path))
    if ext == ".stl":  # a binary STL through numpy, as in read_mesh
        welded = stl.read(p)
        if welded is not None:
            return Mesh(*welded, path=os.fspath(path))
    m = _read_open3d_mesh(p, ext)
    if len(m.triangles) == 0:
        return PointSet(
            np.array(m.vertices, dtype=np.float64),
            np.array(m.vertex_normals, dtype=np.float64) if m.has_vertex_normals() else None,
            np.array(m.vertex_colors, dtype=np.float64) if m.has_vertex_colors() else None,
            path=os.fspath(path),
        )
    return Mesh.from_open3d(m, path=os.fspath(path))


def _read_open3d_mesh(p: Path, ext: str) -> "open3d.geometry.TriangleMesh":
    """Open3D's mesh for a mesh file, after kpd's own checks; vertices may lack triangles (a .ply point cloud)."""
    o3d = open3d_module()
    if ext == ".ply":
        ply.check_complete(p)
    elif ext == ".off":
        off.check_complete(p)
    elif ext == ".stl":  # a binary STL through numpy (stl.read), ASCII by Open3D
        welded = stl.read(p)
        if welded is not None:
            return stl.to_open3d(*welded)
    m = _open3d_read(lambda: o3d.io.read_triangle_mesh(str(p)), p, "a mesh")
    if len(m.vertices) == 0:
        raise InputError(f"{p}: no vertices (empty geometry)")
    if ext == ".stl":
        m = stl.weld(m)
    return m


def _open3d_read(read, p: Path, what: str):
    """``read()`` with Open3D's log captured; a failure it reports there is an :class:`InputError` naming ``p``."""
    with open3d_log() as messages:
        geometry = read()
    failed = failures(messages)
    if failed:
        raise InputError(f"{p}: could not be read as {what} (Open3D: {'; '.join(failed)})")
    return geometry


def _read_point_arrays(p: Path, ext: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Raw (unchecked) points, normals, colours of a point file."""
    if ext == ".ply":  # by kpd (numpy; compiled passes for ASCII), as Open3D's point cloud reader reads it
        ply.check_complete(p)
        arrays = ply.read_vertices(p)
        if arrays is not None:
            if len(arrays[0]) == 0:
                raise InputError(f"{p}: no points (empty geometry)")
            return arrays
    if ext in (".ply", ".pcd"):
        o3d = open3d_module()
        (ply.check_complete if ext == ".ply" else pcd.check_complete)(p)
        pc = _open3d_read(lambda: o3d.io.read_point_cloud(str(p)), p, "a point cloud")
        if len(pc.points) == 0:
            raise InputError(f"{p}: no points (empty geometry)")
        return (
            np.array(pc.points, dtype=np.float64),
            np.array(pc.normals, dtype=np.float64) if pc.has_normals() else None,
            np.array(pc.colors, dtype=np.float64) if pc.has_colors() else None,
        )
    if ext == ".off":  # text OFF by kpd; what it leaves to Open3D (None) is read below
        shape = off.read_mesh(p, os.fspath(p), points=True)
        if isinstance(shape, PointSet):
            return shape.points, shape.normals, shape.colors
        if shape is not None:
            return shape.vertices, shape.vertex_normals, shape.vertex_colors
    if ext in (".obj", ".gltf", ".glb"):
        shape = (obj if ext == ".obj" else gltf).read(p, os.fspath(p), points=True)
        if isinstance(shape, PointSet):
            return shape.points, shape.normals, shape.colors
        return shape.vertices, shape.vertex_normals, shape.vertex_colors
    if ext in MESH_FORMATS:
        m = _read_open3d_mesh(p, ext)
        return (
            np.array(m.vertices, dtype=np.float64),
            np.array(m.vertex_normals, dtype=np.float64) if m.has_vertex_normals() else None,
            np.array(m.vertex_colors, dtype=np.float64) if m.has_vertex_colors() else None,
        )
    if ext == ".xyz":
        table = read_table(p)
        if table.shape[1] < 3:
            raise InputError(f"{p}: rows must have at least 3 columns (x y z); got {table.shape[1]}")
        if table.shape[1] > 3:
            log.debug("%s: ignoring %d columns after x y z", p, table.shape[1] - 3)
        return table[:, :3], None, None
    if ext == ".pts":
        table = read_table(p, count_header=True)
        if table.shape[1] not in (3, 6):
            raise InputError(f"{p}: rows must have 3 (x y z) or 6 (x y z nx ny nz) columns; got {table.shape[1]}")
        return table[:, :3], (table[:, 3:] if table.shape[1] == 6 else None), None
    if ext == ".npy":
        a = _load_numpy(p)
        if not isinstance(a, np.ndarray) or a.ndim != 2 or a.shape[1] not in (3, 6) or a.dtype.kind not in "iuf":
            raise InputError(f"{p}: expected a numeric (N, 3) or (N, 6) array; got {describe(a)}")
        return a[:, :3].astype(np.float64), (a[:, 3:].astype(np.float64) if a.shape[1] == 6 else None), None
    # .npz
    z = _load_numpy(p)
    if not isinstance(z, dict):
        raise InputError(f"{p}: expected an .npz archive with the key 'points'; got a single {describe(z)}")
    if "points" not in z:
        raise InputError(f"{p}: expected the key 'points'; found {sorted(z.keys()) or 'no arrays'}")
    arrays = {}
    for key in ("points", "normals", "colors"):
        if key in z:
            a = z[key]
            if a.ndim != 2 or a.shape[1] != 3 or a.dtype.kind not in "iuf":
                raise InputError(f"{p}: '{key}' must be a numeric (N, 3) array; got {describe(a)}")
            arrays[key] = a
    colors = arrays.get("colors")
    return (
        arrays["points"].astype(np.float64),
        arrays["normals"].astype(np.float64) if "normals" in arrays else None,
        colors if colors is None or colors.dtype == np.uint8 else colors.astype(np.float64),
    )


def _load_numpy(p: Path):
    from kpd.io.integrity import load_numpy

    return load_numpy(p, "point file")



# --- writing -------------------------------------------------------------------------------------------------------


def write_mesh(path: str | os.PathLike, mesh: Mesh) -> None:
    """Write a mesh atomically.

    Parameters
    ----------
    path : ``.obj`` (with ``<stem>.mtl`` and its maps), ``.ply`` (binary, float64), ``.off``, ``.stl`` (binary),
        ``.gltf`` (images beside it) or ``.glb``. A mesh read from an OBJ or glTF file (and moved by
        :meth:`~kpd.mesh.Mesh.with_vertices`) is written in that file's own structure (:mod:`kpd.io.obj`,
        :mod:`kpd.io.gltf`).
    mesh : Mesh

    Attributes the format cannot store (UVs and textures in PLY, OFF, STL; colours and normals in STL) are dropped
    with a logged warning.

    Raises
    ------
    InputError
        For an unknown extension or a missing target folder.
    WriteError
        If the file cannot be written whole (a full disk, a read-only folder): no partial file is left, and a file
        already at ``path`` stays as it was.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a kpd.io.Mesh; got {type(mesh).__name__}")
    p = output_path(path, MESH_FORMATS, "mesh")
    ext = p.suffix.lower()
    dropped = [
        name
        for name, present, kept_in in (
            ("UVs and textures", mesh.triangle_uvs is not None or bool(mesh.textures), (".obj", ".gltf", ".glb")),
            ("vertex colors", mesh.vertex_colors is not None, (".obj", ".ply", ".off", ".gltf", ".glb")),
            ("vertex normals", mesh.vertex_normals is not None, (".obj", ".ply", ".off", ".gltf", ".glb")),
        )
        if present and ext not in kept_in
    ]
    if ext == ".obj" and mesh.triangle_uvs is None and any(t.shape[0] * t.shape[1] > 1 for t in mesh.textures):
        dropped.append("texture images (the mesh has no UVs)")
    if dropped:
        log.warning("%s: %s cannot store %s; written without them", user_path(p), ext, " and ".join(dropped))
    if ext in (".gltf", ".glb"):
        gltf.write(p, mesh)
        return
    if ext == ".obj":
        obj.write(p, mesh)
        return
    if ext == ".ply":  # through numpy, byte for byte what Open3D writes
        with atomic_output(p, verify=lambda tmp: _verify_mesh_file(p, tmp, mesh, ext)) as target:
            ply.write_mesh(target, mesh)
        return
    if ext == ".off":  # by kpd.io.text, what Open3D writes with 9 significant digits instead of 6
        with atomic_output(p, verify=lambda tmp: _verify_mesh_file(p, tmp, mesh, ext)) as target:
            off.write_mesh(target, mesh)
        return
    if ext == ".stl":  # through numpy, byte for byte what Open3D writes after compute_triangle_normals
        with atomic_output(p, verify=lambda tmp: _verify_mesh_file(p, tmp, mesh, ext)) as target:
            stl.write(target, mesh.vertices, mesh.triangles)


def mesh_companions(path: str | os.PathLike, mesh: "Mesh") -> list[str]:
    """Names of the companion files :func:`write_mesh` adds beside ``path`` for ``mesh`` (OBJ: the ``.mtl`` and the
    maps, ``<stem>_<name>``; ``.gltf``: its images and buffers), so that a command checks them before any work."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".obj":
        return obj.companions(p, mesh)
    if ext == ".gltf":
        return gltf.companions(p, mesh)
    return []


def write_points(
    path: str | os.PathLike,
    points: Any,
    normals: Any = None,
    colors: Any = None,
) -> None:
    """Write a point cloud atomically.

    Parameters
    ----------
    path : ``.ply`` (binary, float64), ``.pcd`` (binary, float32), ``.xyz`` (text x y z), ``.pts`` (text, 3 or 6
        columns), ``.npy`` ((N, 3), or (N, 6) with normals) or ``.npz`` (keys ``points``, ``normals``, ``colors``).
    points : (N, 3) array-like, or a :class:`PointSet` (then ``normals`` and ``colors`` come from it)
    normals : (N, 3) array-like or None
    colors : (N, 3) array-like in [0, 1] (or uint8) or None

    What the format cannot store (normals in ``.xyz``; colours in ``.xyz``, ``.pts``, ``.npy``) is dropped with a
    logged warning.
    """
    if isinstance(points, PointSet):
        if normals is not None or colors is not None:
            raise InputError("give normals and colors inside the PointSet, not as separate arguments")
        ps = points
    else:
        ps = PointSet(points, normals, colors)
    p = output_path(path, POINT_FORMATS, "point")
    ext = p.suffix.lower()
    keeps = {".ply": ("normals", "colors"), ".pcd": ("normals", "colors"), ".npz": ("normals", "colors"),
             ".pts": ("normals",), ".npy": ("normals",), ".xyz": ()}[ext]
    dropped = [n for n in ("normals", "colors") if getattr(ps, n) is not None and n not in keeps]
    if dropped:
        log.warning("%s: %s cannot store %s; written without them", user_path(p), ext, " and ".join(dropped))
    normals_kept = ps.normals if "normals" in keeps else None
    with atomic_output(p, verify=lambda tmp: _verify_points_file(p, tmp, len(ps.points), ext)) as target:
        if ext in (".ply", ".pcd"):
            o3d = open3d_module()
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ps.points))
            if ps.normals is not None:
                pc.normals = o3d.utility.Vector3dVector(ps.normals)
            if ps.colors is not None:
                pc.colors = o3d.utility.Vector3dVector(ps.colors)
            open3d_write(lambda: o3d.io.write_point_cloud(str(target), pc), p, target)
        elif ext in (".xyz", ".pts"):
            table = ps.points if normals_kept is None else np.hstack([ps.points, normals_kept])
            np.savetxt(target, table, fmt="%.9g")
        elif ext == ".npy":
            np.save(target, ps.points if normals_kept is None else np.hstack([ps.points, normals_kept]))
        else:
            arrays = {"points": ps.points}
            arrays.update({k: getattr(ps, k) for k in ("normals", "colors") if getattr(ps, k) is not None})
            np.savez(target, **arrays)


def _verify_mesh_file(p: Path, tmp: Path, mesh: "Mesh", ext: str) -> None:
    """Check a mesh file Open3D wrote: complete and holding what it was given (re-read header or counts)."""
    V, T = len(mesh.vertices), len(mesh.triangles)
    try:
        if ext == ".ply":
            ply.check_complete(tmp)
            check_header_counts(tmp, rb"element vertex (\d+)", V, rb"element face (\d+)", T)
        elif ext == ".off":
            off.check_complete(tmp)
        elif ext == ".stl":
            size = tmp.stat().st_size
            if size != 84 + 50 * T:
                raise InputError(f"{size} bytes instead of {84 + 50 * T}")
    except InputError as exc:
        raise incomplete(p, str(exc).removeprefix(f"{tmp}: ")) from None


def _verify_points_file(p: Path, tmp: Path, n: int, ext: str) -> None:
    try:
        if ext == ".ply":
            ply.check_complete(tmp)
            check_header_counts(tmp, rb"element vertex (\d+)", n)
        elif ext == ".pcd":
            pcd.check_complete(tmp)
            check_header_counts(tmp, rb"POINTS (\d+)", n)
    except InputError as exc:
        raise incomplete(p, str(exc).removeprefix(f"{tmp}: ")) from None
