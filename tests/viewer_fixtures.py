"""The viewer tests' shared fixtures (a rig of a chair, a dense mesh to draw), taken by a test module with
``pytest_plugins = ["viewer_fixtures"]``; the shared functions are in ``viewer_helpers``."""

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


@pytest.fixture(scope="module")
def chair_rig(data_dir, tmp_path_factory):
    """A rig of the first ModelNet10 test chair by the shipped chair model, saved (its path)."""
    from kpd.runtime import Model

    mesh = sorted((data_dir / "modelnet10" / "chair" / "test").glob("chair_*"))[0]
    rig = Model.load("chair").rig(mesh)
    path = tmp_path_factory.mktemp("rig") / "chair_rig.npz"
    rig.save(path)
    return path
