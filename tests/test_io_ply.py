"""kpd.io.ply: binary PLY read through numpy as Open3D reads it (to the bit), files beyond that reader left to Open3D,
and meshes written byte for byte as Open3D writes them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.io import Mesh, ply

_RNG = np.random.default_rng(0)
_SIZES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4", "float": "f4",
          "double": "f8"}


def _open3d():
    import open3d

    return open3d


def _open3d_mesh(path) -> dict:
    m = _open3d().io.read_triangle_mesh(str(path))
    return {"vertices": np.asarray(m.vertices), "triangles": np.asarray(m.triangles, dtype=np.int64),
            "normals": np.asarray(m.vertex_normals) if m.has_vertex_normals() else None,
            "colors": np.asarray(m.vertex_colors) if m.has_vertex_colors() else None}


def _write_ply(path, vertex_props, vertex_columns, face_props=(("list", "uchar", "uint", "vertex_indices"),),
               faces=None, face_columns=(), endian="<", extra=""):
    """A binary PLY with the given vertex properties [(type, name)] and columns, faces as [count, i, j, k] rows."""
    fmt = "binary_little_endian" if endian == "<" else "binary_big_endian"
    head = [f"ply", f"format {fmt} 1.0", "comment written by a test", f"element vertex {len(vertex_columns[0])}"]
    head += [f"property {kind} {name}" for kind, name in vertex_props]
    vertex_type = np.dtype([(name, endian + _SIZES[kind]) for kind, name in vertex_props])
    records = np.empty(len(vertex_columns[0]), dtype=vertex_type)
    for (_, name), column in zip(vertex_props, vertex_columns):
        records[name] = column
    body = records.tobytes()
    if faces is not None:
        head.append(f"element face {len(faces)}")
        fields = []
        for prop in face_props:
            if prop[0] == "list":
                head.append(f"property list {prop[1]} {prop[2]} {prop[3]}")
                fields += [("count", endian + _SIZES[prop[1]]), ("corners", endian + _SIZES[prop[2]], (3,))]
            else:
                head.append(f"property {prop[0]} {prop[1]}")
                fields.append((prop[1], endian + _SIZES[prop[0]]))
        rows = np.empty(len(faces), dtype=np.dtype(fields))
        rows["count"] = 3
        rows["corners"] = faces
        for prop, column in zip([p for p in face_props if p[0] != "list"], face_columns):
            rows[prop[1]] = column
        body += rows.tobytes()
    head.append(extra + "end_header")
    path.write_bytes(("\n".join(h for h in head if h) + "\n").encode() + body)
    return path


def _grid(n: int = 40):
    vertices = _RNG.normal(size=(n, 3))
    triangles = np.stack([np.arange(n - 2), np.arange(1, n - 1), np.arange(2, n)], axis=1)
    return vertices, triangles


def _assert_same(mesh, expected):
    np.testing.assert_array_equal(mesh.vertices, expected["vertices"])
    np.testing.assert_array_equal(mesh.triangles, expected["triangles"])
    for ours, theirs in ((mesh.vertex_normals, expected["normals"]), (mesh.vertex_colors, expected["colors"])):
        assert (ours is None) == (theirs is None)
        if ours is not None:
            np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("case", ["double", "float_rgba_quality", "big_endian", "face_extras", "vertex_index",
                                  "float_colors"])
def test_read_mesh_is_open3d_to_the_bit(tmp_path, case):
    v, t = _grid()
    n = len(v)
    if case == "double":
        props, cols = [("double", "x"), ("double", "y"), ("double", "z"), ("double", "nx"), ("double", "ny"),
                       ("double", "nz")], [*v.T, *_RNG.normal(size=(3, n))]
        path = _write_ply(tmp_path / "a.ply", props, cols, faces=t)
    elif case == "float_rgba_quality":  # a scanner's file: float positions, byte colours with alpha, a quality value
        props = [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "red"), ("uchar", "green"),
                 ("uchar", "blue"), ("uchar", "alpha"), ("float", "quality")]
        cols = [*v.T, *_RNG.integers(0, 256, size=(4, n)), _RNG.random(n)]
        path = _write_ply(tmp_path / "a.ply", props, cols, faces=t)
    elif case == "big_endian":
        props, cols = [("float", "x"), ("float", "y"), ("float", "z")], list(v.T)
        path = _write_ply(tmp_path / "a.ply", props, cols, faces=t, endian=">",
                          face_props=(("list", "int", "int", "vertex_indices"),))
    elif case == "face_extras":  # a face flag before the corners, short indices
        props, cols = [("double", "x"), ("double", "y"), ("double", "z")], list(v.T)
        path = _write_ply(tmp_path / "a.ply", props, cols, faces=t, face_columns=[_RNG.integers(0, 9, len(t))],
                          face_props=(("uchar", "flags"), ("list", "uchar", "ushort", "vertex_indices")))
    elif case == "vertex_index":
        props, cols = [("float", "x"), ("float", "y"), ("float", "z")], list(v.T)
        path = _write_ply(tmp_path / "a.ply", props, cols, faces=t,
                          face_props=(("list", "uchar", "int", "vertex_index"),))
    else:  # colours as floats in [0, 1]: Open3D divides them by 255 too
        props = [("float", "x"), ("float", "y"), ("float", "z"), ("float", "red"), ("float", "green"),
                 ("float", "blue")]
        path = _write_ply(tmp_path / "a.ply", props, [*v.T, *_RNG.random((3, n))], faces=t)
    ply.check_complete(path)
    mesh = ply.read_mesh(path, "a.ply")
    assert mesh is not None and mesh.path == "a.ply"
    _assert_same(mesh, _open3d_mesh(path))
    points, normals, colors = ply.read_vertices(path)
    cloud = _open3d().io.read_point_cloud(str(path))
    np.testing.assert_array_equal(points, np.asarray(cloud.points))
    assert (normals is None) == (not cloud.has_normals()) and (colors is None) == (not cloud.has_colors())
    if colors is not None:
        np.testing.assert_array_equal(colors, np.asarray(cloud.colors))


def test_read_mesh_of_a_file_written_by_open3d(tmp_path):
    v, t = _grid()
    m = _open3d().geometry.TriangleMesh(_open3d().utility.Vector3dVector(v),
                                        _open3d().utility.Vector3iVector(t.astype(np.int32)))
    m.vertex_normals = _open3d().utility.Vector3dVector(_RNG.normal(size=v.shape))
    m.vertex_colors = _open3d().utility.Vector3dVector(_RNG.random(v.shape))
    _open3d().io.write_triangle_mesh(str(tmp_path / "o.ply"), m)
    _assert_same(ply.read_mesh(tmp_path / "o.ply"), _open3d_mesh(tmp_path / "o.ply"))


def test_files_beyond_the_reader_are_left_to_open3d(tmp_path):
    v, t = _grid(6)
    xyz = [("float", "x"), ("float", "y"), ("float", "z")]
    ascii_path = tmp_path / "ascii.ply"
    ascii_path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                          "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                          "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    quads = tmp_path / "quads.ply"
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n").encode()
    quads.write_bytes(head + np.eye(4, 3, dtype="<f4").tobytes() + b"\x04" + np.arange(4, dtype="<i4").tobytes())
    edges = _write_ply(tmp_path / "edges.ply", xyz, list(v.T), faces=t, extra="element edge 0\nproperty int vertex1\n"
                                                                              "property int vertex2\n")
    red_only = _write_ply(tmp_path / "red.ply", [*xyz, ("uchar", "red")], [*v.T, np.arange(6)], faces=t)
    no_faces = _write_ply(tmp_path / "cloud.ply", xyz, list(v.T))
    for path in (ascii_path, quads, edges, red_only):
        assert ply.read_mesh(path) is None, path.name
    assert ply.read_mesh(no_faces) is None  # a point cloud: Open3D's reader says what is missing
    np.testing.assert_array_equal(ply.read_vertices(no_faces)[0], v.astype("f4"))
    assert ply.read_vertices(quads) is not None  # its vertices are within reach, its polygon is not
    assert ply.read_vertices(ascii_path) is None


def test_read_mesh_refuses_what_mesh_refuses(tmp_path):
    from kpd.errors import InputError

    v, t = _grid(6)
    v[2, 1] = np.nan
    path = _write_ply(tmp_path / "nan.ply", [("double", "x"), ("double", "y"), ("double", "z")], list(v.T), faces=t)
    with pytest.raises(InputError, match=r"nan\.ply: 1 vertex has NaN or inf coordinates"):
        ply.read_mesh(path, "nan.ply")
    v, t = _grid(6)
    t[1, 2] = 9
    path = _write_ply(tmp_path / "far.ply", [("double", "x"), ("double", "y"), ("double", "z")], list(v.T), faces=t)
    with pytest.raises(InputError, match=r"far\.ply: 1 triangle indexes vertices outside \[0, 6\)"):
        ply.read_mesh(path, "far.ply")


@pytest.mark.parametrize("normals, colors", [(False, False), (True, False), (False, True), (True, True)])
def test_write_mesh_writes_open3ds_bytes(tmp_path, normals, colors):
    v, t = _grid(300)
    c = _RNG.random(v.shape)
    c[:255, 0] = (np.arange(255) + 0.5) / 255  # halves: std::round takes them away from zero, numpy's to even
    c[:4, 1] = [0.0, 1.0, 1.0 - 1e-7, 1.0 + 5e-7]  # the last clipped (Mesh lets colours stray by 1e-6)
    mesh = Mesh(v, t, vertex_normals=_RNG.normal(size=v.shape) if normals else None,
                vertex_colors=c if colors else None)
    ply.write_mesh(tmp_path / "ours.ply", mesh)
    _open3d().io.write_triangle_mesh(str(tmp_path / "theirs.ply"), mesh.to_open3d())
    assert (tmp_path / "ours.ply").read_bytes() == (tmp_path / "theirs.ply").read_bytes()
    back = ply.read_mesh(tmp_path / "ours.ply")
    np.testing.assert_array_equal(back.vertices, v)
    np.testing.assert_array_equal(back.triangles, t)


@settings(max_examples=25, deadline=None)
@given(n=st.integers(3, 60), seed=st.integers(0, 2**16), normals=st.booleans(), colors=st.booleans())
def test_any_mesh_round_trips_exactly(tmp_path_factory, n, seed, normals, colors):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-6, 6)
    t = rng.integers(0, n, size=(2 * n, 3))
    c = np.rint(rng.random((n, 3)) * 255) / 255  # colours a byte holds
    mesh = Mesh(v, t, vertex_normals=rng.normal(size=(n, 3)) if normals else None, vertex_colors=c if colors else None)
    path = tmp_path_factory.mktemp("ply") / "m.ply"
    ply.write_mesh(path, mesh)
    ply.check_complete(path)
    back = ply.read_mesh(path)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    if normals:
        np.testing.assert_array_equal(back.vertex_normals, mesh.vertex_normals)
    if colors:
        np.testing.assert_allclose(back.vertex_colors, c, atol=1e-15)
