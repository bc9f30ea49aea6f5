"""kpd.io: real files, round trips through every format, clear errors, atomic writes, keypoint files."""

import errno
import logging
import os
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from helpers import TRIANGLE, corners, finite, sphere_mesh, texels, write_text

import kpd.io.ply
from kpd.errors import InputError, KpdError
from kpd.io import (
    Mesh,
    PointSet,
    read_mesh,
    read_points,
    read_shape,
    write_mesh,
    write_points,
)

BANANA = "scans/ycb/banana/textured_simple_reoriented.obj"
DRILL = "scans/ycb/power_drill/textured_simple_reoriented.obj"
KEYPOINTNET_PCD = "keypointnet/pcds/03001627/88382b877be91b2a572f8e1c1caad99e.pcd"

# --- helpers ---------------------------------------------------------------------------------------------------------


def ply_binary(vertices, faces):
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\n"
        f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face_bytes = b"".join(np.uint8(3).tobytes() + np.asarray(f, "<i4").tobytes() for f in faces)
    return head.encode() + np.asarray(vertices, "<f4").tobytes() + face_bytes


def ply_ascii(vertices, faces):
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return head + "".join(" ".join(map(str, v)) + "\n" for v in vertices) + "".join(
        f"3 {a} {b} {c}\n" for a, b, c in faces
    )


# --- real data -------------------------------------------------------------------------------------------------------


def test_every_modelnet10_test_mesh_reads(data_dir):
    files = sorted(data_dir.glob("modelnet10/*/test/*.ply"))
    assert len(files) >= 190
    for f in files:
        m = read_mesh(f)
        assert m.vertices.dtype == np.float64 and m.triangles.dtype == np.int64, f
        assert len(m.vertices) > 0 and len(m.triangles) > 0, f
        assert np.isfinite(m.vertices).all(), f
        assert m.triangles.min() >= 0 and m.triangles.max() < len(m.vertices), f
        assert m.path == str(f)


def test_sneaker_scan_counts(data_dir):
    m = read_mesh(data_dir / "scans/sneaker.ply")
    assert m.vertices.shape == (22043, 3) and m.triangles.shape == (39326, 3)
    assert isinstance(read_shape(data_dir / "scans/sneaker.ply"), Mesh)


def test_banana_has_uvs_and_the_texture_as_in_the_file(banana, data_dir):
    assert banana.triangle_uvs.shape == (3 * len(banana.triangles), 2)
    assert len(banana.textures) == 1
    on_disk = np.asarray(o3d.io.read_image(str(data_dir / "scans/ycb/banana/texture_map.png")))
    np.testing.assert_array_equal(banana.textures[0], on_disk)
    np.testing.assert_array_equal(banana.triangle_material_ids, 0)
    # kpd reads OBJ vertices as the file's v lines, in order (Assimp would split them into 10,710 where UVs differ)
    v_lines = [line.split()[1:4] for line in (data_dir / BANANA).read_text().splitlines() if line.startswith("v ")]
    assert len(banana.vertices) == len(v_lines) == 7866
    np.testing.assert_array_equal(banana.vertices, np.array(v_lines, dtype=float))


def test_banana_obj_round_trip_keeps_uvs_and_texture(banana, tmp_path):
    write_mesh(tmp_path / "banana.obj", banana)
    assert sorted(os.listdir(tmp_path)) == ["banana.mtl", "banana.obj", "banana_texture_map.png"]
    back = read_mesh(tmp_path / "banana.obj")
    np.testing.assert_allclose(back.triangle_uvs, banana.triangle_uvs, atol=1e-6)
    assert len(back.textures) == 1
    np.testing.assert_array_equal(back.textures[0], banana.textures[0])
    np.testing.assert_allclose(back.vertices, banana.vertices, rtol=1e-5, atol=1e-9)
    np.testing.assert_array_equal(back.triangles, banana.triangles)
    np.testing.assert_allclose(back.vertex_normals, banana.vertex_normals, atol=1e-5)


def test_missing_texture_is_a_warning_not_an_error(data_dir, caplog, capfd):
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        m = read_mesh(data_dir / DRILL)
    assert len(m.triangles) == 15728 and m.triangle_uvs is not None
    assert m.textures == [] and m.triangle_material_ids is None
    assert any("texture_map.png" in r.getMessage() and "missing" in r.getMessage() for r in caplog.records)
    out, err = capfd.readouterr()
    assert "Open3D WARNING" not in out + err  # Open3D's own chatter is silenced


def test_keypointnet_pcd_has_2048_points_with_packed_rgb(data_dir):
    path = data_dir / KEYPOINTNET_PCD
    ps = read_points(path)
    assert ps.points.shape == (2048, 3) and ps.colors.shape == (2048, 3)
    first = path.read_text().split("DATA ascii")[1].split()[:4]
    np.testing.assert_allclose(ps.points[0], [float(x) for x in first[:3]], rtol=1e-6)
    assert isinstance(read_shape(path), PointSet)
    rows = [line.split() for line in path.read_text().split("DATA ascii")[1].splitlines() if line.strip()]
    rgb = np.array([int(r[3]) for r in rows])
    expected = np.stack([(rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255], axis=1) / 255.0
    np.testing.assert_allclose(ps.colors, expected, atol=1e-9)


def test_shapenetpart_pts_point_counts_match_the_labels(data_dir):
    files = sorted(data_dir.glob("shapenetpart_sample/*/points/*.pts"))
    assert len(files) == 16
    for f in files:
        labels = (f.parent.parent / "points_label" / f.with_suffix(".seg").name).read_text().split()
        ps = read_points(f)
        assert len(ps) == len(labels) > 2000, f
        assert ps.normals is None


def test_mesh_file_read_as_points_gives_its_vertices(data_dir):
    mesh = read_mesh(data_dir / "scans/sneaker.ply")
    ps = read_points(data_dir / "scans/sneaker.ply")
    np.testing.assert_array_equal(ps.points, mesh.vertices)


# --- mesh round trips ------------------------------------------------------------------------------------------------

# format: (vertex tolerance kind, keeps normals, keeps colors, keeps uvs+textures, colour atol)
MESH_FORMATS = {
    "obj": ("text6", True, True, True, 1e-5),
    "ply": ("float64", True, True, False, 0.5 / 255 + 1e-9),
    "off": ("text6", True, True, False, 0.5 / 255 + 1e-9),
    "stl": ("float32", False, False, False, None),
    "gltf": ("float32", True, True, True, 1e-7),
    "glb": ("float32", True, True, True, 1e-7),
}


def assert_close_as_stored(got, want, kind):
    if kind == "float64":
        np.testing.assert_array_equal(got, want)
    elif kind == "float32":
        np.testing.assert_array_equal(got, want.astype(np.float32))
    else:  # six significant digits
        np.testing.assert_allclose(got, want, rtol=5e-6, atol=1e-12)


@pytest.mark.parametrize("ext", sorted(MESH_FORMATS))
def test_mesh_round_trip(ext, tmp_path, caplog):
    kind, has_normals, has_colors, has_uvs, color_atol = MESH_FORMATS[ext]
    mesh = sphere_mesh(textures=2 if has_uvs else 0)
    path = tmp_path / f"shape.{ext}"
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        write_mesh(path, mesh)
    assert (len(caplog.records) > 0) == (ext == "stl")  # STL drops normals and colours: said so
    back = read_mesh(path)
    assert len(back.triangles) == len(mesh.triangles)
    assert_close_as_stored(corners(back, "xyz"), corners(mesh, "xyz"), kind)
    if has_normals:
        np.testing.assert_allclose(corners(back, "normals"), corners(mesh, "normals"), atol=1e-5)
    else:
        assert back.vertex_normals is None
    if has_colors:
        np.testing.assert_allclose(corners(back, "colors"), corners(mesh, "colors"), atol=color_atol)
    else:
        assert back.vertex_colors is None
    if has_uvs:
        np.testing.assert_allclose(corners(back, "uvs"), corners(mesh, "uvs"), atol=1e-6)
        assert len(back.textures) == 2
        for a, b in zip(back.textures, mesh.textures):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(back.triangle_material_ids, mesh.triangle_material_ids)
        np.testing.assert_array_equal(texels(back), texels(mesh))
    else:
        assert back.triangle_uvs is None and back.textures == []
    leftovers = [f for f in os.listdir(tmp_path) if f.startswith(".")]
    assert leftovers == []


def test_stl_vertices_are_welded(tmp_path):
    mesh = sphere_mesh(normals=False, colors=False)
    write_mesh(tmp_path / "s.stl", mesh)
    back = read_mesh(tmp_path / "s.stl")
    assert len(back.vertices) == len(mesh.vertices)  # not 3 per triangle
    np.testing.assert_array_equal(corners(back, "xyz"), corners(mesh, "xyz").astype(np.float32))


def test_gltf_and_obj_keep_vertex_order_of_a_mesh_read_by_assimp(tmp_path):
    mesh = sphere_mesh(textures=1)
    write_mesh(tmp_path / "a.glb", mesh)
    first = read_mesh(tmp_path / "a.glb")  # vertices now in first-use order, split at UV seams
    for ext in ("obj", "gltf", "glb"):
        write_mesh(tmp_path / f"b.{ext}", first)
        again = read_mesh(tmp_path / f"b.{ext}")
        assert len(again.vertices) == len(first.vertices), ext
        np.testing.assert_array_equal(again.triangles, first.triangles)


def test_uv_only_and_plain_meshes_round_trip_through_obj(tmp_path):
    plain = sphere_mesh(normals=False, colors=False)
    write_mesh(tmp_path / "plain.obj", plain)
    assert sorted(os.listdir(tmp_path)) == ["plain.obj"]
    back = read_mesh(tmp_path / "plain.obj")
    assert back.vertex_normals is None and back.triangle_uvs is None and back.textures == []
    uv_only = sphere_mesh(uvs=True)
    write_mesh(tmp_path / "uv.obj", uv_only)
    back = read_mesh(tmp_path / "uv.obj")
    np.testing.assert_allclose(corners(back, "uvs"), corners(uv_only, "uvs"), atol=1e-6)
    assert back.textures == []


def test_gltf_with_a_missing_texture_file_reads_with_a_warning(tmp_path, caplog):
    mesh = sphere_mesh(textures=1)
    write_mesh(tmp_path / "a.gltf", mesh)
    assert sorted(os.listdir(tmp_path)) == ["a.gltf", "a_0.png"]
    (tmp_path / "a_0.png").unlink()
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        back = read_mesh(tmp_path / "a.gltf")
    assert "'a_0.png' is missing" in caplog.text
    assert back.textures == [] and back.triangle_uvs is not None
    np.testing.assert_array_equal(corners(back, "xyz"), corners(mesh, "xyz").astype(np.float32))


def test_textures_in_ply_are_dropped_with_a_warning(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        write_mesh(tmp_path / "t.ply", sphere_mesh(textures=1))
    assert any("UVs and textures" in r.getMessage() for r in caplog.records)


@st.composite
def meshes(draw):
    V = draw(st.integers(3, 30))
    T = draw(st.integers(1, 40))
    vertices = draw(arrays(np.float64, (V, 3), elements=finite))
    triangles = draw(arrays(np.int64, (T, 3), elements=st.integers(0, V - 1)))
    return Mesh(vertices, triangles)


@settings(max_examples=25, deadline=None)
@given(mesh=meshes())
def test_any_mesh_round_trips_exactly_through_ply_and_to_float32_through_glb(mesh, tmp_path_factory):
    folder = tmp_path_factory.mktemp("prop")
    write_mesh(folder / "m.ply", mesh)
    back = read_mesh(folder / "m.ply")
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    write_mesh(folder / "m.glb", mesh)
    back = read_mesh(folder / "m.glb")
    np.testing.assert_array_equal(corners(back, "xyz"), corners(mesh, "xyz").astype(np.float32))


# --- mesh read errors ------------------------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"chair\.obj: no such file"):
        read_mesh(tmp_path / "chair.obj")
    with pytest.raises(InputError, match=r"chair\.pcd: no such file"):
        read_points(tmp_path / "chair.pcd")


def test_unknown_extension(tmp_path):
    path = write_text(tmp_path / "chair.abc", "v 0 0 0\n")
    with pytest.raises(InputError, match=r"chair\.abc: unknown mesh format '\.abc'; expected one of \.obj"):
        read_mesh(path)
    with pytest.raises(InputError, match="unknown point format"):
        read_points(path)
    with pytest.raises(InputError, match="unknown mesh format"):
        write_mesh(tmp_path / "out.xyz", sphere_mesh())
    with pytest.raises(InputError, match="unknown point format"):
        write_points(tmp_path / "out.stl", np.zeros((1, 3)))


@pytest.mark.parametrize("ext", ["obj", "ply", "off", "stl", "glb"])
def test_empty_file(ext, tmp_path):
    path = write_text(tmp_path / f"chair.{ext}", "")
    with pytest.raises(InputError, match=rf"chair\.{ext}: the file is empty \(0 bytes\)"):
        read_mesh(path)


def test_empty_geometry(tmp_path):
    path = write_text(tmp_path / "chair.ply", ply_ascii([], []))
    with pytest.raises(InputError, match=r"chair\.ply: could not be read as a mesh \(Open3D: .*number of vertex <= 0"):
        read_mesh(path)
    path = write_text(tmp_path / "cloud.ply", ply_ascii(TRIANGLE, []))
    with pytest.raises(InputError, match="has 3 vertices but no triangles"):
        read_mesh(path)
    assert isinstance(read_shape(path), PointSet)
    path = write_text(tmp_path / "only_vertices.obj", "v 0 0 0\nv 1 0 0\n")
    with pytest.raises(InputError, match=r"only_vertices\.obj: has 2 vertices but no triangles"):
        read_mesh(path)


def stl_binary(vertices, faces):
    rows = [np.concatenate([[0, 0, 0], np.ravel(np.asarray(vertices, float)[f])]) for f in faces]
    body = b"".join(np.asarray(r, "<f4").tobytes() + b"\0\0" for r in rows)
    return b"\0" * 80 + np.uint32(len(faces)).tobytes() + body


@pytest.mark.parametrize("ext", ["obj", "ply", "stl"])
def test_nan_and_inf_coordinates(ext, tmp_path):
    vertices = [[0, 0, "nan"], [1, "inf", 0], [0, 1, 0], ["nan", 1, 1]]
    faces = [[0, 1, 2], [1, 2, 3]]
    path = tmp_path / f"chair.{ext}"
    if ext == "obj":
        path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in vertices) + "f 1 2 3\nf 2 3 4\n")
    elif ext == "ply":
        path.write_bytes(ply_binary(np.array(vertices, dtype=float), faces))
    else:
        path.write_bytes(stl_binary(np.array(vertices, dtype=float), faces))
    with pytest.raises(InputError, match=rf"chair\.{ext}: 3 vertices have NaN or inf coordinates"):
        read_mesh(path)


def test_nan_in_text_off_is_an_open3d_read_error(tmp_path):
    path = write_text(tmp_path / "chair.off", "OFF\n3 1 0\n0 0 nan\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(InputError, match=r"chair\.off: could not be read as a mesh \(Open3D: Read OFF failed"):
        read_mesh(path)


def test_out_of_range_face_indices(tmp_path):
    path = write_text(tmp_path / "chair.ply", ply_ascii(TRIANGLE, [[0, 1, 7], [0, 1, 2]]))
    with pytest.raises(InputError, match=r"chair\.ply: 1 triangle indexes vertices outside \[0, 3\)"):
        read_mesh(path)
    path = write_text(tmp_path / "chair.off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 5 9\n")
    message = r"chair\.off: 1 triangle indexes vertices outside \[0, 3\) \(indices from 0 to 9\)"
    with pytest.raises(InputError, match=message):
        read_mesh(path)
    path = write_text(tmp_path / "chair.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(InputError, match=r"chair\.obj: 1 face names a vertex outside 1\.\.3"):
        read_mesh(path)


def test_polygon_obj_faces_are_read_as_fans_not_dropped(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3 4\nf 1 2 5\n"
    path = write_text(tmp_path / "quad.obj", text)
    np.testing.assert_array_equal(read_mesh(path).triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 4]])


def test_off_polygons_are_triangulated(tmp_path):
    path = write_text(tmp_path / "quad.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    assert read_mesh(path).triangles.shape == (2, 3)


def test_truncated_files(tmp_path, data_dir):
    sneaker = (data_dir / "scans/sneaker.ply").read_bytes()
    path = tmp_path / "sneaker.ply"
    path.write_bytes(sneaker[: len(sneaker) // 2])
    with pytest.raises(InputError, match=r"sneaker\.ply: the file is truncated: its header declares 22043 'vertex'"):
        read_mesh(path)
    with pytest.raises(InputError, match="truncated"):
        read_points(path)
    pcd = (data_dir / KEYPOINTNET_PCD).read_bytes()
    path = tmp_path / "chair.pcd"
    path.write_bytes(pcd[: len(pcd) // 3])
    with pytest.raises(InputError, match=r"chair\.pcd: the file is truncated: its header declares 2048 points"):
        read_points(path)
    path = write_text(tmp_path / "chair.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n")
    with pytest.raises(InputError, match=r"chair\.off: the file is truncated"):
        read_mesh(path)


def test_garbage_files(tmp_path):
    path = write_text(tmp_path / "chair.ply", "this is not a mesh\n")
    with pytest.raises(InputError, match=r"chair\.ply: not a PLY file"):
        read_mesh(path)
    path = tmp_path / "chair.obj"
    path.write_bytes(b"\x00\x01\x02 garbage")
    with pytest.raises(InputError, match=r"chair\.obj: not a text OBJ file"):
        read_mesh(path)
    path = write_text(tmp_path / "chair.glb", "not a glb")
    with pytest.raises(InputError, match=r"chair\.glb: could not be read as glTF"):
        read_mesh(path)


# --- points ----------------------------------------------------------------------------------------------------------

# format: (coordinate tolerance kind, keeps normals, keeps colors, colour atol)
POINT_FORMATS = {
    "ply": ("float64", True, True, 0.5 / 255 + 1e-9),
    "pcd": ("float32", True, True, 0.5 / 255 + 1e-9),
    "xyz": ("text9", False, False, None),
    "pts": ("text9", True, False, None),
    "npy": ("float64", True, False, None),
    "npz": ("float64", True, True, 0.0),
}


def assert_points_close(got, want, kind):
    if kind == "text9":
        np.testing.assert_allclose(got, want, rtol=5e-9, atol=0)
    else:
        assert_close_as_stored(got, want, kind)


@pytest.mark.parametrize("ext", sorted(POINT_FORMATS))
def test_points_round_trip(ext, tmp_path):
    kind, has_normals, has_colors, color_atol = POINT_FORMATS[ext]
    rng = np.random.default_rng(1)
    points, normals, colors = rng.normal(size=(500, 3)) * 37.1, rng.normal(size=(500, 3)), rng.random((500, 3))
    write_points(tmp_path / f"cloud.{ext}", points, normals, colors)
    back = read_points(tmp_path / f"cloud.{ext}")
    assert_points_close(back.points, points, kind)
    if has_normals:
        assert_points_close(back.normals, normals, kind)
    else:
        assert back.normals is None
    if has_colors:
        np.testing.assert_allclose(back.colors, colors, atol=color_atol)
    else:
        assert back.colors is None
    assert sorted(os.listdir(tmp_path)) == [f"cloud.{ext}"]


@settings(max_examples=25, deadline=None)
@given(points=st.integers(1, 50).flatmap(lambda n: arrays(np.float64, (n, 3), elements=finite)),
       ext=st.sampled_from(["pts", "npz", "ply"]))
def test_any_points_round_trip(points, ext, tmp_path_factory):
    path = tmp_path_factory.mktemp("pts") / f"p.{ext}"
    write_points(path, PointSet(points, normals=points[::-1]))
    back = read_points(path)
    kind = "text9" if ext == "pts" else "float64"
    assert_points_close(back.points, points, kind)
    assert_points_close(back.normals, points[::-1], kind)


def test_pts_formats(tmp_path):
    six = write_text(tmp_path / "a.pts", "0 0 0 0 0 1\n1 2 3 0 1 0\n")
    ps = read_points(six)
    np.testing.assert_array_equal(ps.normals, [[0, 0, 1], [0, 1, 0]])
    counted = write_text(tmp_path / "b.pts", "2\n0 0 0\n1 2 3\n")
    assert len(read_points(counted)) == 2
    with pytest.raises(InputError, match=r"c\.pts: line 2 has 2 columns; line 1 has 3"):
        read_points(write_text(tmp_path / "c.pts", "0 0 0\n1 2\n"))
    with pytest.raises(InputError, match=r"d\.pts: rows must have 3 \(x y z\) or 6"):
        read_points(write_text(tmp_path / "d.pts", "0 0 0 1\n"))
    with pytest.raises(InputError, match=r"e\.pts: not a table of numbers"):
        read_points(write_text(tmp_path / "e.pts", "0 0 zero\n"))
    with pytest.raises(InputError, match=r"f\.pts: 1 point has NaN or inf coordinates"):
        read_points(write_text(tmp_path / "f.pts", "0 0 0\n0 nan 0\n"))
    with pytest.raises(InputError, match=r"g\.xyz: no rows"):
        read_points(write_text(tmp_path / "g.xyz", "# only a comment\n\n"))


def test_numpy_point_files(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((4, 2)))
    message = r"a\.npy: expected a numeric \(N, 3\) or \(N, 6\) array; got float64 array of shape \(4, 2\)"
    with pytest.raises(InputError, match=message):
        read_points(tmp_path / "a.npy")
    np.savez(tmp_path / "b.npz", xyz=np.zeros((4, 3)))
    with pytest.raises(InputError, match=r"b\.npz: expected the key 'points'; found \['xyz'\]"):
        read_points(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", points=np.zeros((4, 3)), colors=np.full((4, 3), 255, np.uint8))
    assert (read_points(tmp_path / "c.npz").colors == 1.0).all()
    np.save(tmp_path / "d.npy", np.array([{"a": 1}], dtype=object))
    with pytest.raises(InputError, match=r"d\.npy: the \.npy holds pickled objects"):
        read_points(tmp_path / "d.npy")  # pickles are refused


def test_drop_nonfinite_points(tmp_path, caplog):
    path = write_text(tmp_path / "scan.xyz", "0 0 0\nnan 0 0\n1 1 1\n")
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        ps = read_points(path, drop_nonfinite=True)
    np.testing.assert_array_equal(ps.points, [[0, 0, 0], [1, 1, 1]])
    assert "dropped 1 of 3 points" in caplog.text


def test_write_points_warns_for_what_the_format_drops(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        write_points(tmp_path / "a.xyz", np.zeros((2, 3)), normals=np.ones((2, 3)), colors=np.ones((2, 3)))
    assert "cannot store normals and colors" in caplog.text


# --- a failed write ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", ["obj", "ply", "gltf"])
def test_failed_mesh_write_leaves_existing_files_untouched(ext, tmp_path, monkeypatch):
    mesh = sphere_mesh(textures=1)
    write_mesh(tmp_path / f"chair.{ext}", mesh)
    before = {f: (tmp_path / f).read_bytes() for f in os.listdir(tmp_path)}

    def fail_write(filename, *args, **kwargs):
        with open(filename, "w") as fh:
            fh.write("half")
        return False

    def fail_bytes(self, data):  # kpd's own glTF writer: the disk fills up halfway through a file
        with open(self, "wb") as fh:
            fh.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    def fail_ply(p, mesh):  # kpd's own PLY writer: the disk fills up after the header
        with open(p, "wb") as fh:
            fh.write(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError(errno.ENOSPC, "No space left on device", str(p))

    monkeypatch.setattr(o3d.io, "write_triangle_mesh", fail_write)
    monkeypatch.setattr(o3d.io, "write_image", fail_write)
    monkeypatch.setattr(Path, "write_bytes", fail_bytes)
    monkeypatch.setattr(kpd.io.ply, "write_mesh", fail_ply)
    reason = "the disk is full|no space left" if ext in ("gltf", "obj", "ply") else "Open3D failed"
    with pytest.raises(KpdError, match=rf"cannot write .*({reason})"):
        write_mesh(tmp_path / f"chair.{ext}", mesh.with_vertices(mesh.vertices + 1))
    assert {f: (tmp_path / f).read_bytes() for f in os.listdir(tmp_path)} == before


def test_glb_materials_are_named_after_the_users_file(tmp_path):
    from kpd.io.gltf import read_gltf_json

    write_mesh(tmp_path / "chair.glb", sphere_mesh(uvs=True, textures=2))
    doc, _ = read_gltf_json(tmp_path / "chair.glb")
    assert [m["name"] for m in doc["materials"]] == ["chair_0", "chair_1"]  # not the temporary file's name
