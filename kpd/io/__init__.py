"""Read and write meshes, point clouds and keypoints; clear errors, atomic writes.

Formats
-------
=========================  ==========================================================================================
meshes                     ``.obj .ply .off .stl .gltf .glb``  (:func:`read_mesh`, :func:`write_mesh`)
point sets                 ``.ply .pcd .xyz .pts .npy .npz``, and any mesh format (its vertices) (:func:`read_points`,
                           :func:`write_points`)
keypoints                  ``.json`` (``{"keypoints": [[x, y, z], ...], ...}`` or a bare list) and ``.txt`` (rows
                           ``x y z`` or the authors' ``%03d x y z``) (:func:`read_keypoints`, :func:`write_keypoints`)
=========================  ==========================================================================================

OBJ and glTF are read and written by kpd itself, so that a user's file comes back whole (see docs/formats.md): an
OBJ's vertices are its ``v`` lines in order, its faces keep their texture coordinates (faces without them are marked
in ``Mesh.triangle_uv_mask``), every material is kept (its map, or its ``Kd`` colour as a 1x1 texture), and a mesh
read from an OBJ or glTF file is written back in that file's own structure with only the positions (and the normals,
turned with the surface) changed, its material library and images copied beside the output under the output's
name (only files kpd read inside the input's folder tree: :mod:`kpd.io.references`). PLY (binary and ASCII), text OFF
and binary STL are read (and PLY and OFF written) by kpd too, by numpy or
compiled passes that give Open3D's mesh (OFF's decimals read exactly, not as float32), fast at the size of a scan
(docs/scale.md); other PLY, OFF and STL files and point clouds go through Open3D, with the checks Open3D leaves
out: Open3D returns an empty or half-read geometry with a console warning for a missing, broken or truncated file,
and kpd raises :class:`~kpd.errors.InputError` naming the file and the problem instead.

Layout
------
The types :class:`~kpd.mesh.Mesh` and :class:`~kpd.mesh.PointSet` live in :mod:`kpd.mesh` (with the conventions for
UVs, textures and material ids) and are re-exported here. :mod:`kpd.io.dispatch` reads and writes by extension and
hands each format's own work to its module: :mod:`kpd.io.ply`, :mod:`kpd.io.pcd`, :mod:`kpd.io.off`,
:mod:`kpd.io.stl`, :mod:`kpd.io.obj` (with :mod:`kpd.io.mtl` for its material libraries), :mod:`kpd.io.gltf`,
:mod:`kpd.io.keypoints`, :mod:`kpd.io.images` (PNG); :mod:`kpd.io.numbers` is the compiled number scanner of the
text readers, :mod:`kpd.io.references` decides which files a file may name (inside its own folder tree only),
:mod:`kpd.io.capture` holds Open3D's log and stderr capture, :mod:`kpd.io.atomic` the one writer,
:mod:`kpd.io.integrity` content hashes and safe numpy loading.

Conventions
-----------
- OBJ faces of more than three corners are read as fans of triangles (and written back as the polygons they are, in
  the file's own structure). STL vertices are welded back by position (STL stores no shared vertices). glTF files are y
  up (:func:`file_up`).
- Precision: PLY keeps float64, PCD and glTF float32, OBJ and OFF nine significant digits (float32-exact), and
  the text formats kpd writes (``.xyz``, ``.pts``) nine significant digits (float32-exact).

Writes are atomic (:mod:`kpd.io.atomic`, the one writer every kpd output goes through): everything is written
under a temporary name in the target folder, fsynced, checked (Open3D's writers report a full disk only on stderr
and return success, so the file is re-read: PLY/PCD/OFF headers against the bytes that follow, OBJ vertex and face
counts, STL size, PNG end chunk) and renamed into place only when complete; a failed write raises
:class:`~kpd.errors.WriteError` and leaves nothing behind. Formats with companion files (OBJ: its ``.mtl`` and maps;
``.gltf``: its images and buffers) are written under their final names into a temporary folder first, then moved
together; messages name the final paths, never the temporary ones.
"""

from __future__ import annotations

from kpd.io.atomic import Outputs, atomic_files, atomic_output, check_output, remove_stale_temporaries
from kpd.io.atomic import _check_target, disk_full  # noqa: F401  (kept importable from kpd.io)
from kpd.io.common import KEYPOINT_FORMATS, MESH_FORMATS, POINT_FORMATS
from kpd.io.dispatch import file_up, mesh_companions, read_mesh, read_points, read_shape, write_mesh, write_points
from kpd.io.images import verify_png
from kpd.io.keypoints import read_keypoints, write_keypoints
from kpd.mesh import Mesh, PointSet

__all__ = [
    "MESH_FORMATS",
    "POINT_FORMATS",
    "KEYPOINT_FORMATS",
    "Mesh",
    "PointSet",
    "read_mesh",
    "write_mesh",
    "file_up",
    "read_points",
    "write_points",
    "read_shape",
    "atomic_output",
    "atomic_files",
    "Outputs",
    "check_output",
    "remove_stale_temporaries",
    "verify_png",
    "mesh_companions",
    "write_keypoints",
    "read_keypoints",
]
