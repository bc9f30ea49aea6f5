"""Meshes and rigs the rig tests share (test_rig, test_rig_scale, test_straighten, test_basis, test_memory,
test_demo_format)."""

from __future__ import annotations

import helpers
import numpy as np

from kpd.geometry import Normalizer, farthest_point_sampling, sample_surface
from kpd.io import Mesh, read_mesh
from kpd.rig import Rig


def box_mesh(size=(2.0, 1.0, 0.5), offset=(10.0, -3.0, 5.0)):
    """The rig tests' box: sides of three lengths, away from the origin."""
    return helpers.box_mesh(size, offset)


def corner_rig(mesh=None):
    mesh = mesh or box_mesh()
    norm = Normalizer().fit(mesh.vertices)
    keypoints = norm.apply(mesh.vertices)  # one keypoint per box corner
    return Rig.bind(mesh, keypoints, normalizer=norm)


def fps_rig(mesh, k=12, straighten=True):
    norm = Normalizer().fit(mesh.vertices)
    points = sample_surface(norm.apply(mesh.vertices), mesh.triangles, 2048, seed=0).points
    keypoints = points[farthest_point_sampling(points, k, seed=0)]
    influence = np.random.default_rng(0).uniform(0.5, 1.5, (k, 42))
    return Rig.bind(mesh, keypoints, influence, normalizer=norm, straighten=straighten)


def subdivided_unstraightened(path, levels, model):
    """``path`` subdivided ``levels`` times (Open3D midpoint) and bound by a shipped model without straightening:
    (mesh, rig, rest vertices in the model frame, the (V, K) float64 basis)."""
    import open3d as o3d

    from kpd.runtime import Model

    source = read_mesh(path)
    fine = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(source.vertices),
                                     o3d.utility.Vector3iVector(source.triangles.astype(np.int32)))
    fine = fine.subdivide_midpoint(levels)
    mesh = Mesh(vertices=np.asarray(fine.vertices), triangles=np.asarray(fine.triangles, dtype=np.int64))
    rig = Model.load(model, threads=1).rig(mesh, straighten=False)
    return mesh, rig, rig.normalizer.apply(mesh.vertices), np.asarray(rig.basis, dtype=np.float64)

