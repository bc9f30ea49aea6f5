"""kpd.io.stl: STL's unshared corners are welded back into one vertex per position; a binary STL is read through
numpy into the mesh Open3D's reader and :func:`stl.weld` give (to the bit), an ASCII one by Open3D, and a damaged
binary file is refused in one InputError naming it; a mesh is written through numpy in the bytes Open3D writes."""

from __future__ import annotations

import errno
import re

import numpy as np
import open3d as o3d
import pytest

from kpd.errors import InputError, WriteError
from kpd.io import read_mesh, read_points, read_shape, stl, write_mesh
from kpd.io.capture import failures, open3d_log
from kpd.mesh import Mesh


def test_weld_merges_equal_positions_and_keeps_the_triangles():
    soup = o3d.geometry.TriangleMesh()
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)  # two triangles
    soup.vertices = o3d.utility.Vector3dVector(corners)
    soup.triangles = o3d.utility.Vector3iVector(np.arange(6).reshape(2, 3))
    welded = stl.weld(soup)
    v, t = np.asarray(welded.vertices), np.asarray(welded.triangles)
    assert len(v) == 4
    np.testing.assert_array_equal(v[t], corners.reshape(2, 3, 3))  # every triangle where it was


def test_stl_file_round_trip_is_welded(tmp_path):
    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij"), -1).reshape(-1, 2)
    vertices = np.c_[grid, np.zeros(16)]
    quads = [(i * 4 + j, i * 4 + j + 4, i * 4 + j + 5, i * 4 + j + 1) for i in range(3) for j in range(3)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    write_mesh(tmp_path / "g.stl", Mesh(vertices, triangles))
    back = read_mesh(tmp_path / "g.stl")
    assert len(back.vertices) == 16 and len(back.triangles) == 18  # not 3 corners per triangle
    np.testing.assert_allclose(back.vertices[back.triangles], vertices[triangles], atol=1e-6)


# --- the numpy reader and its twin, Open3D's reader then weld ------------------------------------------------------


def open3d_welded(path) -> Mesh:
    """The mesh every STL gave before the numpy reader: Open3D's reader (Assimp), then :func:`stl.weld`."""
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        m = o3d.io.read_triangle_mesh(str(path))
    return Mesh.from_open3d(stl.weld(m), path=str(path))


def open3d_refuses(path) -> bool:
    with open3d_log() as messages:
        m = o3d.io.read_triangle_mesh(str(path))
    return bool(failures(messages)) and len(m.vertices) == 0


def assert_same(mesh: Mesh, expected: Mesh) -> None:
    """The same mesh to the bit: vertex bits (the sign of a zero included), triangles, and nothing else."""
    assert mesh.vertices.dtype == np.float64 and mesh.triangles.dtype == np.int64
    assert mesh.vertices.shape == expected.vertices.shape
    np.testing.assert_array_equal(mesh.vertices.view(np.int64), expected.vertices.view(np.int64))
    np.testing.assert_array_equal(mesh.triangles, expected.triangles)
    for name in ("vertex_normals", "vertex_colors", "triangle_uvs", "triangle_material_ids"):
        assert getattr(mesh, name) is None and getattr(expected, name) is None, name
    assert mesh.textures == expected.textures == []
    assert mesh.path == expected.path


def binary_stl(corners, *, header: bytes = b"", normals=None, attributes=None, count: int | None = None) -> bytes:
    """A binary STL of ``corners`` (n, 3, 3): the 80-byte header, the count (``count`` if given) and the records."""
    corners = np.asarray(corners, dtype=np.float32).reshape(-1, 3, 3)
    records = np.zeros(len(corners), dtype=stl._RECORD)
    records["corners"] = corners
    if normals is not None:
        records["normal"] = normals
    if attributes is not None:
        records["attribute"] = attributes
    head = header.ljust(80, b"\0")[:80] + np.uint32(len(corners) if count is None else count).tobytes()
    return head + records.tobytes()


def resave_with_header(path, header: bytes):
    """A copy of a binary STL whose 80-byte header is ``header``, padded with spaces (no NUL byte in it)."""
    data = bytearray(path.read_bytes())
    data[:80] = header.ljust(80, b" ")
    copy = path.with_name(f"solid_{path.name}")
    copy.write_bytes(bytes(data))
    return copy


REAL = ["shapenetcore_obj/piano/b549a0c108ff0272e4b68d3b17c43658/models/model_normalized.obj",  # 15 materials
        "scans/ycb/banana/textured_simple_reoriented.obj", "scans/sneaker.ply", "modelnet10/chair/test/chair_0890.ply",
        "modelnet10/table/test/table_0393.ply", "gso_shoes/11pro_SL_TRX_FG/model.obj"]


@pytest.mark.parametrize("name", REAL)
def test_binary_stl_is_open3d_and_weld_to_the_bit_on_real_meshes(name, data_dir, tmp_path):
    # STLs written by Open3D (header "Created by Open3D") and by kpd, and one whose binary header starts with "solid"
    source = data_dir / name
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        m = o3d.io.read_triangle_mesh(str(source))
        m.compute_triangle_normals()
        o3d.io.write_triangle_mesh(str(tmp_path / "open3d.stl"), m)
    write_mesh(tmp_path / "kpd.stl", read_mesh(source))
    paths = [tmp_path / "open3d.stl", tmp_path / "kpd.stl"]
    paths.append(resave_with_header(paths[0], b"solid exported in binary by a CAD tool"))
    for path in paths:
        want = open3d_welded(path)
        assert_same(read_mesh(path), want)
        assert_same(read_shape(path), want)  # through the numpy reader made an Open3D mesh
        np.testing.assert_array_equal(read_points(path).points, want.vertices)
        assert len(want.vertices) < 3 * len(want.triangles)  # welded


def test_binary_stl_is_open3d_and_weld_to_the_bit_on_edge_records(tmp_path):
    rng = np.random.default_rng(7)
    corners = [
        [[-0.0, 0, 0], [1, 0, 0], [0, 1, 0]],  # the first corner at the origin is -0.0: the vertex keeps its sign
        [[0.0, 0, 0], [0, 1, 0], [1, 1, -0.0]],  # 0.0 is that position too; (1, 1, -0.0) comes first as -0.0
        [[1, 1, 0], [1, 1, 0], [2, 2, 2]],  # degenerate: two corners at one position
        [[2, 2, 2], [2, 2, 2], [2, 2, 2]],  # all three
        [[-0.0, 0, 0], [1, 0, 0], [0, 1, 0]],  # the first triangle again, with another facet normal below
        [[0, 0, 0], [0.5, 0.5, 0], [1, 1, 0]],  # collinear
    ]
    near = rng.uniform(-1, 1, (200, 3, 3)).astype(np.float32)
    corners = np.concatenate([np.array(corners, np.float32), near, np.nextafter(near, np.float32(2)), near[::-1]])
    normals = rng.normal(size=(len(corners), 3)).astype(np.float32)
    normals[::3] = 0  # some facets without a normal, as Blender writes them
    colours = np.where(np.arange(len(corners)) % 2 == 0, 0x8000 | 0x7C1F, 0).astype(np.uint16)  # colour bit
    files = {"plain": binary_stl(corners),
             "normals": binary_stl(corners, normals=normals),
             "colours": binary_stl(corners, normals=normals, attributes=colours),
             "materialise": binary_stl(corners, header=b"COLOR=\x10\x20\x30\xff MATERIAL=\x01\x02\x03\xff",
                                       attributes=colours),
             "solid": binary_stl(corners, header=b"solid " + b"x" * 74)}
    for name, data in files.items():
        path = tmp_path / f"{name}.stl"
        path.write_bytes(data)
        want = open3d_welded(path)
        got = read_mesh(path)
        assert_same(got, want)
        assert np.signbit(got.vertices[0, 0]) and np.signbit(got.vertices[3, 2])  # -0.0 kept where it came first
        np.testing.assert_array_equal(got.vertices[got.triangles], corners.astype(np.float64))


def test_binary_stl_with_nan_or_inf_is_refused_as_before(tmp_path):
    corners = [[[0, 0, np.nan], [1, np.inf, 0], [0, 1, 0]], [[1, np.inf, 0], [0, 1, 0], [np.nan, 1, 1]],
               [[0, 0, np.nan], [0, 1, 0], [5, 5, 5]]]
    path = tmp_path / "nan.stl"
    path.write_bytes(binary_stl(corners))
    with pytest.raises(InputError) as theirs:
        open3d_welded(path)
    for read in (read_mesh, read_shape):
        with pytest.raises(InputError) as ours:
            read(path)
        assert str(ours.value) == str(theirs.value)
    assert str(ours.value).startswith(f"{path}: 3 vertices have NaN or inf coordinates")


def test_ascii_stl_is_read_by_open3d(chair, tmp_path):
    corners = chair.vertices[chair.triangles]  # (T, 3, 3)
    facets = "".join("facet normal 0 0 0\nouter loop\n" + "".join("vertex %.9g %.9g %.9g\n" % tuple(c) for c in t)
                     + "endloop\nendfacet\n" for t in corners.tolist())
    path = tmp_path / "a.stl"
    path.write_text(f"solid chair\n{facets}endsolid chair\n")
    assert stl.read(path) is None
    got = read_mesh(path)
    assert_same(got, open3d_welded(path))
    assert len(got.vertices) < 3 * len(got.triangles)


def damaged(tmp_path) -> dict:
    """Damaged binary STLs, each with the message that names its damage."""
    three = [[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 0, 1], [1, 0, 1], [0, 1, 1]]]
    whole = binary_stl(three)  # 84 + 150 bytes
    truncated = "the file is truncated: its header declares {} triangles ({} bytes) but the file has {} bytes"
    other = "the file is longer than its header declares: {} triangles ({} bytes) but the file has {} bytes"
    cases = {
        "truncated": (whole[:-10], truncated.format(3, 234, 224)),
        "solid_truncated": (binary_stl(three, header=b"solid part")[:-10], truncated.format(3, 234, 224)),
        "count_above": (binary_stl(three, count=5), truncated.format(5, 334, 234)),
        "count_below": (binary_stl(three, count=2), other.format(2, 184, 234)),
        "trailing_bytes": (whole + b"\0" * 7, other.format(3, 234, 241)),
        "count_zero": (binary_stl([]), "no triangles (a binary STL whose header declares 0)"),
        "short": (b"\0" * 50, "not an STL file: 50 bytes, fewer than a binary STL's 84-byte header, and not ASCII "
                              "STL text (which starts with 'solid')"),
    }
    out = {}
    for name, (data, message) in cases.items():
        path = tmp_path / f"{name}.stl"
        path.write_bytes(data)
        out[path] = message
    return out


def test_damaged_binary_stl_is_one_input_error_naming_the_file(tmp_path):
    for path, message in damaged(tmp_path).items():
        assert open3d_refuses(path), path.name  # no file Open3D read is refused now
        for read in (read_mesh, read_shape, read_points):
            with pytest.raises(InputError, match=f"^{re.escape(f'{path}: {message}')}$"):
                read(path)


# --- the numpy writer and its twin, Open3D's compute_triangle_normals then write_triangle_mesh ----------------------


def open3d_stl(path, vertices, triangles) -> bytes:
    """The binary STL every mesh gave before the numpy writer."""
    m = stl.to_open3d(vertices, triangles)
    m.compute_triangle_normals()
    assert o3d.io.write_triangle_mesh(str(path), m)
    return path.read_bytes()


@pytest.mark.parametrize("name", REAL)
def test_written_stl_is_open3d_byte_for_byte_on_real_meshes(name, data_dir, tmp_path):
    mesh = read_mesh(data_dir / name)
    write_mesh(tmp_path / "kpd.stl", mesh)
    want = open3d_stl(tmp_path / "open3d.stl", mesh.vertices, mesh.triangles)
    assert (tmp_path / "kpd.stl").read_bytes() == want
    assert want[:80] == b"Created by Open3D".ljust(80, b"\0") and len(want) == 84 + 50 * len(mesh.triangles)
    back = read_mesh(tmp_path / "kpd.stl")
    assert_same(back, open3d_welded(tmp_path / "kpd.stl"))  # read back as before
    np.testing.assert_array_equal(back.vertices[back.triangles],
                                  mesh.vertices[mesh.triangles].astype(np.float32).astype(np.float64))


def test_written_stl_is_open3d_byte_for_byte_on_random_and_degenerate_triangles(tmp_path, monkeypatch):
    monkeypatch.setattr(stl, "_BLOCK", 1000)  # many blocks, the last one short
    rng = np.random.default_rng(3)
    n = 20_000
    scale = 10.0 ** rng.integers(-170, 17, size=(n, 1))  # down to where the squared norm underflows to 0
    vertices = rng.normal(size=(n, 3)) * np.where(rng.random((n, 1)) < 0.5, 1.0, scale)
    vertices[::5] = np.round(vertices[::5])  # cross products that cancel exactly
    vertices[::9, 1] = -0.0
    vertices[::4, 2] = 0.0
    first = np.arange(3, 3000, 3)  # corners p, 2p, 3p: collinear, a cross product zero or nearly
    vertices[first + 1], vertices[first + 2] = 2 * vertices[first], 3 * vertices[first]
    triangles = rng.integers(0, n, size=(50_123, 3))
    triangles[::7, 2] = triangles[::7, 0]  # a repeated corner
    triangles[::11] = triangles[::11, :1]  # one corner three times
    triangles[::13, 1] = triangles[::13, 2]
    triangles[2::17][:len(first)] = first[:, None] + [0, 1, 2]
    vertices[[0, 1, 2]] = [[0.0, -0.0, 0.0], [-0.0, 0.0, 0.0], [0.0, 0.0, -0.0]]
    triangles[:2] = [[0, 1, 2], [2, 1, 0]]  # zero cross products with signed zeros
    write_mesh(tmp_path / "kpd.stl", Mesh(vertices, triangles))
    assert (tmp_path / "kpd.stl").read_bytes() == open3d_stl(tmp_path / "open3d.stl", vertices, triangles)
    records = np.fromfile(tmp_path / "kpd.stl", dtype=stl._RECORD, offset=84)
    assert (records["normal"] == 0).all(axis=1).sum() > len(triangles) // 10  # the degenerate ones
    back = read_mesh(tmp_path / "kpd.stl")
    np.testing.assert_array_equal(back.vertices[back.triangles], vertices[triangles].astype(np.float32))


def test_written_stl_normal_after_an_overflow_is_open3d_s(tmp_path):
    # beyond what a Mesh holds (|coordinate| <= 1e18): the cross product or its squared norm overflows
    vertices = np.array([[0, 0, 0], [1e200, 0, 0], [0, 1e200, 0], [1e308, 1e308, 0], [-1e308, 1e308, 1e308],
                         [4e38, 0, 0], [0, 5e38, 1]])
    triangles = np.array([[0, 1, 2], [0, 3, 4], [3, 4, 0], [4, 3, 1], [0, 5, 6]])
    stl.write(tmp_path / "kpd.stl", vertices, triangles)
    assert (tmp_path / "kpd.stl").read_bytes() == open3d_stl(tmp_path / "open3d.stl", vertices, triangles)
    normals = np.fromfile(tmp_path / "kpd.stl", dtype=stl._RECORD, offset=84)["normal"]
    assert (normals == [0, 0, 1]).all(axis=1).any() and np.isnan(normals).any()


def test_failed_stl_write_leaves_the_existing_file_untouched(tmp_path, monkeypatch):
    mesh = Mesh(np.eye(3), np.array([[0, 1, 2]]))
    write_mesh(tmp_path / "s.stl", mesh)
    before = (tmp_path / "s.stl").read_bytes()

    def fail(p, vertices, triangles):  # the disk fills up after the header
        p.write_bytes(b"\0" * 84)
        raise OSError(errno.ENOSPC, "No space left on device", str(p))

    monkeypatch.setattr(stl, "write", fail)
    with pytest.raises(WriteError, match="the disk is full"):
        write_mesh(tmp_path / "s.stl", mesh.with_vertices(mesh.vertices + 1))
    assert [f.name for f in tmp_path.iterdir()] == ["s.stl"] and (tmp_path / "s.stl").read_bytes() == before
