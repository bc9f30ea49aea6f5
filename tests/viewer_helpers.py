"""What the viewer's tests share: meshes to draw and an editor window to drive (fixtures are imported by name)."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def dense_chair(data_dir):
    """The unseen ShapeNet chair subdivided twice (86k vertices, 344k triangles, half of them stored twice)."""
    import open3d as o3d

    from kpd.io import Mesh, read_mesh

    mesh = read_mesh(data_dir / "keypointnet" / "models" / "03001627" / "fe6b3c001a86d844d5767a0de8dd037e" /
                     "model.obj")
    fine = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                     o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32))).subdivide_midpoint(2)
    return Mesh(np.asarray(fine.vertices), np.asarray(fine.triangles, dtype=np.int64))
