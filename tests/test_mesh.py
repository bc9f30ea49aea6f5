"""kpd.mesh: the Mesh and PointSet types check every field at the door, convert to and from Open3D, and move their
vertices with normals, seams and everything else kept."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from helpers import TRIANGLE, corners, sphere_mesh

from kpd.errors import InputError
from kpd.io import read_mesh, write_mesh
from kpd.mesh import Mesh, PointSet

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=64)


def test_open3d_conversion_round_trip_flips_textures():
    mesh = sphere_mesh(textures=2)
    m = mesh.to_open3d()
    np.testing.assert_array_equal(np.asarray(m.textures[1]), mesh.textures[1][::-1])  # Open3D's convention
    back = Mesh.from_open3d(m)
    for name in ("xyz", "normals", "colors", "uvs"):
        np.testing.assert_array_equal(corners(back, name), corners(mesh, name))
    for a, b in zip(back.textures, mesh.textures):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.triangle_material_ids, mesh.triangle_material_ids)


def test_from_open3d_compacts_materials_and_fills_imageless_ones():
    mesh = sphere_mesh(textures=1).to_open3d()
    tex = np.asarray(mesh.textures[0])
    mesh.textures = [o3d.geometry.Image(), o3d.geometry.Image(tex), o3d.geometry.Image(tex)]  # like Assimp's
    ids = np.ones(len(mesh.triangles), np.int32)
    ids[:5] = 0
    mesh.triangle_material_ids = o3d.utility.IntVector(ids)
    m = Mesh.from_open3d(mesh)
    assert len(m.textures) == 2  # material 2 is unused
    np.testing.assert_array_equal(m.textures[0], 255)  # used but image-less: white
    assert m.textures[0].shape == (1, 1, 3)
    np.testing.assert_array_equal(m.triangle_material_ids, ids)


# --- with_vertices ---------------------------------------------------------------------------------------------------


def test_with_vertices_shares_everything_but_vertices_and_normals():
    mesh = sphere_mesh(textures=1)
    moved = mesh.with_vertices(mesh.vertices * 2.0)
    np.testing.assert_array_equal(moved.vertices, mesh.vertices * 2.0)
    assert moved.triangles is mesh.triangles and moved.vertex_colors is mesh.vertex_colors
    assert moved.triangle_uvs is mesh.triangle_uvs and moved.textures is mesh.textures
    assert moved.triangle_material_ids is mesh.triangle_material_ids
    assert moved.vertex_normals is not mesh.vertex_normals
    np.testing.assert_array_equal(mesh.vertices, sphere_mesh().vertices)  # the original is untouched


def test_mesh_fields_are_the_public_attributes_only():
    names = [f.name for f in dataclasses.fields(Mesh)]
    assert names == ["vertices", "triangles", "vertex_normals", "vertex_colors", "triangle_uvs", "textures",
                     "triangle_material_ids", "triangle_uv_mask", "path"]
    moved = sphere_mesh(textures=1).with_vertices(sphere_mesh().vertices + 1)
    copy = Mesh(**{n: getattr(moved, n) for n in names})  # what a serialiser iterating the fields does
    np.testing.assert_array_equal(copy.vertex_normals, moved.vertex_normals)


def test_with_vertices_recomputes_normals_only_when_present():
    plain = sphere_mesh(normals=False)
    assert plain.with_vertices(plain.vertices + 1).vertex_normals is None
    mesh = sphere_mesh(resolution=12)
    centre = mesh.vertices.mean(axis=0)
    moved = mesh.with_vertices(mesh.vertices)
    radial = mesh.vertices - centre
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(moved.vertex_normals, axis=1), 1.0)
    assert (np.einsum("ij,ij->i", moved.vertex_normals, radial) > 0.5).all()  # outward on a closed surface


@settings(max_examples=20, deadline=None)
@given(angles=arrays(np.float64, 3, elements=st.floats(-np.pi, np.pi)), shift=arrays(np.float64, 3, elements=finite))
def test_with_vertices_normals_follow_a_rigid_motion(angles, shift):
    mesh = sphere_mesh()
    a, b, c = angles
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    r = rz @ ry @ rx
    before = mesh.with_vertices(mesh.vertices).vertex_normals
    after = mesh.with_vertices(mesh.vertices @ r.T + shift).vertex_normals
    np.testing.assert_allclose(after, before @ r.T, atol=1e-6)


def test_with_vertices_keeps_uv_seams_smooth(banana, tmp_path):
    write_mesh(tmp_path / "banana.glb", banana)
    banana = read_mesh(tmp_path / "banana.glb")  # Assimp splits vertices at UV seams
    moved = banana.with_vertices(banana.vertices * [1.0, 2.0, 0.5])
    key = np.hstack([banana.vertices, banana.vertex_normals])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    assert len(first) < len(banana.vertices)  # the banana has seam copies
    np.testing.assert_array_equal(moved.vertex_normals, moved.vertex_normals[first][inverse.reshape(-1)])


def test_with_vertices_checks_its_input():
    mesh = sphere_mesh()
    with pytest.raises(InputError, match=r"shape \(\d+, 3\); got \(3, 3\)"):
        mesh.with_vertices(np.zeros((3, 3)))
    bad = mesh.vertices.copy()
    bad[[1, 4, 7], 2] = np.nan
    with pytest.raises(InputError, match="3 vertices have NaN or inf coordinates"):
        mesh.with_vertices(bad)


# --- Mesh and PointSet checks ----------------------------------------------------------------------------------------


def test_mesh_constructor_checks_fields():
    v, t = np.array(TRIANGLE, float), np.array([[0, 1, 2]])
    with pytest.raises(InputError, match=r"vertices must have shape \(N, 3\)"):
        Mesh(np.zeros((3, 2)), t)
    with pytest.raises(InputError, match="no triangles"):
        Mesh(v, np.zeros((0, 3), int))
    with pytest.raises(InputError, match=r"1 triangle indexes vertices outside \[0, 3\)"):
        Mesh(v, [[0, 1, 3]])
    with pytest.raises(InputError, match=r"triangle_uvs must have shape \(3, 2\)"):
        Mesh(v, t, triangle_uvs=np.zeros((2, 2)))
    with pytest.raises(InputError, match=r"vertex_colors must lie in \[0, 1\]"):
        Mesh(v, t, vertex_colors=np.full((3, 3), 2.0))
    with pytest.raises(InputError, match=r"triangle_material_ids must lie in \[0, 1\)"):
        Mesh(v, t, textures=[np.zeros((2, 2, 3), np.uint8)], triangle_material_ids=[1])
    with pytest.raises(InputError, match="texture 0 must have shape"):
        Mesh(v, t, textures=[np.zeros((2, 2, 2), np.uint8)])
    m = Mesh(v, np.array([[0.0, 1.0, 2.0]]), vertex_colors=np.full((3, 3), 255, np.uint8))  # demo-file style input
    assert m.triangles.dtype == np.int64 and (m.vertex_colors == 1.0).all()


def test_pointset_checks_fields():
    with pytest.raises(InputError, match="points: 1 point has NaN or inf coordinates"):
        PointSet([[0, 0, np.inf]])
    with pytest.raises(InputError, match=r"normals must have shape \(1, 3\)"):
        PointSet([[0, 0, 0]], normals=[[0, 0, 1], [0, 1, 0]])
    with pytest.raises(InputError, match="no points"):
        PointSet(np.zeros((0, 3)))


def test_position_groups_are_found_once_and_follow_new_positions():
    import copy
    import pickle

    from kpd.grouping import first_occurrence_groups

    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [1, 0, 0]])
    mesh = Mesh(vertices, np.array([[0, 1, 2], [3, 4, 2]]))
    first, index = mesh.position_groups()
    np.testing.assert_array_equal(first, [0, 1, 2])
    np.testing.assert_array_equal(index, [0, 1, 2, 0, 1])
    assert mesh.position_groups() is mesh.position_groups()  # kept
    moved = mesh.with_vertices(vertices + [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1], [0, 0, 0]])
    np.testing.assert_array_equal(moved.position_groups()[1], [0, 1, 2, 3, 1])  # its own positions
    np.testing.assert_array_equal(mesh.position_groups()[1], [0, 1, 2, 0, 1])
    for again in (copy.deepcopy(moved), pickle.loads(pickle.dumps(moved))):
        np.testing.assert_array_equal(again.position_groups()[1], first_occurrence_groups(again.vertices)[1])
