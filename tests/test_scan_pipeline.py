"""kpd.scan.pipeline: preprocess maps a scan into the model frame and back exactly."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scan_shapes import rotation

from kpd.geometry import Normalizer, sample_surface
from kpd.io import Mesh
from kpd.scan import (
    preprocess,
    rotation_angle,
)


def test_preprocess_round_trip_is_exact(sneaker):
    scan = sample_surface(sneaker.vertices, sneaker.triangles, 3000, seed=0).points @ rotation(9).T * 250.0 + 40.0
    reference = sample_surface(sneaker.vertices, sneaker.triangles, 3000, seed=1).points
    result = preprocess(scan, reference, clean_params={"outliers": False})
    assert len(result.points) == len(scan)
    assert np.abs(result.points).max() == pytest.approx(1.0)
    np.testing.assert_allclose(result.to_original(result.points), scan, rtol=0, atol=1e-9 * np.abs(scan).max())
    np.testing.assert_allclose(result.to_aligned(scan), result.points, atol=1e-12)
    np.testing.assert_allclose(result.inverse @ result.transform, np.eye(4), atol=1e-12)
    assert rotation_angle(result.rotation @ rotation(9)) < 5.0
    # the aligned scan lies in the reference's frame: same layout after both are normalised
    ref_box = Normalizer().fit(reference).apply(reference)
    assert np.abs(np.ptp(result.points, axis=0) - np.ptp(ref_box, axis=0)).max() < 0.1
    record = json.loads(json.dumps(result.to_dict()))
    assert record["orientation"]["ambiguous"] is False and len(record["transform"]) == 4


def test_preprocess_mesh_keeps_topology_and_turns_normals(sneaker):
    result = preprocess(sneaker)  # no reference: clean + normalise only
    assert isinstance(result.shape, Mesh) and result.orientation is None
    np.testing.assert_array_equal(result.shape.triangles, sneaker.triangles)
    np.testing.assert_allclose(result.to_original(result.shape.vertices), sneaker.vertices, atol=1e-9)


def test_mesh_scan_is_oriented_by_its_surface_not_its_vertices():
    # a box with a finely tessellated ball on one corner: 7000 of the vertices are on the ball, most of the area on
    # the box; oriented by its vertices the scan looks round (wrong and ambiguous), by its surface it is not
    import open3d as o3d

    shape = o3d.geometry.TriangleMesh.create_box(3.0, 1.5, 0.6)
    shape += o3d.geometry.TriangleMesh.create_sphere(0.35, resolution=60).translate((2.6, 1.2, 0.9))
    vertices, triangles = np.asarray(shape.vertices), np.asarray(shape.triangles)
    reference = sample_surface(vertices, triangles, 5000, seed=1).points
    for seed in range(2):
        true = rotation(seed)
        result = preprocess(Mesh(vertices=vertices @ true.T, triangles=triangles), reference)
        assert rotation_angle(result.rotation @ true) < 3.0 and not result.orientation.ambiguous
        assert isinstance(result.shape, Mesh) and len(result.shape.vertices) == len(vertices)
