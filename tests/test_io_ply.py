"""kpd.io.ply: binary PLY read through numpy and ASCII PLY by compiled passes as Open3D reads them (to the bit), a
malformed ASCII row named by its line, files beyond these readers left to Open3D, and meshes written byte for byte as
Open3D writes them."""

from __future__ import annotations

import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.errors import InputError
from kpd.io import Mesh, numbers, off, ply, read_mesh

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
    head = ["ply", f"format {fmt} 1.0", "comment written by a test", f"element vertex {len(vertex_columns[0])}"]
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
    ascii_path = tmp_path / "ascii.ply"  # ASCII quads
    ascii_path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                          "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                          "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
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
    assert ply.read_vertices(ascii_path) is not None


def test_read_mesh_refuses_what_mesh_refuses(tmp_path):
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


# --- ASCII ---------------------------------------------------------------------------------------------------------

_WHOLE_TYPES = ("char", "uchar", "short", "ushort", "int", "uint", "int8", "uint8", "int16", "uint16", "int32",
                "uint32")
_FLOATING_TYPES = ("float", "double", "float32", "float64")


def _open3d_cloud(path) -> dict:
    c = _open3d().io.read_point_cloud(str(path))
    return {"vertices": np.asarray(c.points), "normals": np.asarray(c.normals) if c.has_normals() else None,
            "colors": np.asarray(c.colors) if c.has_colors() else None}


def _word(rng: random.Random, kind: str, low: float, high: float) -> str:
    """A number for a property of type ``kind`` within [low, high], as files write them: signs, leading zeros, long
    mantissas beyond the compiled fast path, exponents."""
    from helpers import random_words

    if kind in _WHOLE_TYPES:
        limits = np.iinfo(ply._PLY_NUMPY[kind])
        value = rng.randint(int(max(limits.min, low)), int(min(limits.max, high)))
        return rng.choice([str(value), f"{value:+d}", f"{value:05d}", "-0" if value == 0 else str(value)])
    while True:
        word = random_words(rng, 1)[0]
        if low <= float(word) <= high and (kind not in ("float", "float32") or abs(float(word)) < 3.4e38):
            return word


def _random_ascii(rng: random.Random, path) -> dict:
    """An ASCII PLY of a random layout that Open3D reads: x y z of any type, maybe normals and colours of their
    types, other vertex properties, a face list of 3 corners with other face properties before or after it; runs of
    blanks between the words and around them, blank lines, comments in the header, ``\\n`` or ``\\r\\n``."""
    V, T = rng.randint(3, 30), rng.randint(1, 40)
    props = [(rng.choice(["float", "double", "int", "short", "float32", "float64"]), name) for name in "xyz"]
    if rng.random() < 0.5:
        props += [(rng.choice(["float", "double"]), name) for name in ("nx", "ny", "nz")]
    if rng.random() < 0.5:
        props += [(rng.choice(["uchar", "float", "int", "ushort", "double"]), name)
                  for name in ("red", "green", "blue")]
    props += [(rng.choice(_WHOLE_TYPES + _FLOATING_TYPES), name)
              for name in rng.sample(["alpha", "quality", "label", "confidence", "u", "v"], rng.randint(0, 3))]
    rng.shuffle(props)
    for group in (("x", "y", "z"), ("nx", "ny", "nz")):  # Open3D wants the third after the other two
        places = [i for i, (_, name) in enumerate(props) if name in group]
        if places:
            last = max(places)
            kinds = {name: kind for kind, name in props}
            others = list(group[:2])
            rng.shuffle(others)
            for i, name in zip([i for i in places if i != last] + [last], others + [group[2]]):
                props[i] = (kinds[name], name)
    rows = []
    for _ in range(V):
        row = []
        for kind, name in props:
            low, high = {"red": (0, 255), "green": (0, 255), "blue": (0, 255)}.get(name, (-1e15, 1e15))
            if name in ("alpha", "quality", "label", "confidence", "u", "v"):
                low, high = -1e300, 1e300
            row.append(_word(rng, kind, low, high))
        rows.append(row)
    count = rng.choice(["uchar", "int", "ushort", "char", "uint8"])
    index = rng.choice(["int", "uint", "int32", "uint32", "ushort", "uchar" if V < 256 else "int"])
    face_props = [("list", count, index, rng.choice(["vertex_indices", "vertex_index"]))]
    for name, kind in rng.sample([("flags", "uchar"), ("quality", "float"), ("material", "int"),
                                  ("area", "double")], rng.randint(0, 2)):
        face_props.insert(rng.randint(0, len(face_props)), (kind, name))
    for _ in range(T):
        row = []
        for prop in face_props:
            if prop[0] == "list":
                row += ["3"] + [str(rng.randrange(V)) for _ in range(3)]
            else:
                row.append(_word(rng, prop[0], 0, 100))
        rows.append(row)
    eol = rng.choice(["\n", "\r\n"])
    head = ["ply", "format ascii 1.0", "comment written by a test", f"element vertex {V}"]
    head += [f"property {kind} {name}" for kind, name in props]
    head += ["obj_info a line", f"element face {T}"]
    head += [" ".join(["property", *prop]) for prop in face_props] + ["comment between", "end_header"]
    lines = []
    for row in rows:
        if rng.random() < 0.05:
            lines.append(rng.choice(["", " ", "\t "]))
        text = "".join(word + rng.choice([" ", "  ", "\t", " \t "]) for word in row[:-1]) + row[-1]
        lines.append(rng.choice(["", " ", "\t"]) + text + rng.choice(["", " ", "\t", " \r"]))
    path.write_bytes(eol.join(head + lines).encode() + (eol.encode() if rng.random() < 0.8 else b""))
    return {"props": props, "face_props": face_props}


@pytest.mark.parametrize("halves", [False, True])
def test_ascii_is_open3d_to_the_bit(tmp_path, monkeypatch, halves):
    if halves:  # the compiled passes in two halves on two threads, at any size
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
    for seed in range(60):
        path = tmp_path / f"{seed}.ply"
        layout = _random_ascii(random.Random(seed), path)
        ply.check_complete(path)
        mesh = ply.read_mesh(path, "a.ply")
        assert mesh is not None, (seed, layout)
        _assert_same(mesh, _open3d_mesh(path))
        points, normals, colors = ply.read_vertices(path)
        cloud = _open3d_cloud(path)
        for ours, theirs in ((points, cloud["vertices"]), (normals, cloud["normals"]), (colors, cloud["colors"])):
            assert (ours is None) == (theirs is None), (seed, layout)
            if ours is not None:
                assert ours.view(np.int64).tolist() == theirs.view(np.int64).tolist(), (seed, layout)


def test_ascii_cloud(tmp_path):
    """A vertex element alone: its points, normals and colours as Open3D's point cloud reader gives them."""
    rng = random.Random(5)
    rows = [[_word(rng, "float", -10, 10) for _ in range(6)] + [str(rng.randint(0, 255)) for _ in range(3)]
            for _ in range(50)]
    head = ["ply", "format ascii 1.0", "element vertex 50"] + [f"property float {name}" for name in ("x", "y", "z",
            "nx", "ny", "nz")] + [f"property uchar {name}" for name in ("red", "green", "blue")] + ["end_header"]
    path = tmp_path / "cloud.ply"
    path.write_text("\n".join(head + [" ".join(row) for row in rows]) + "\n")
    cloud = _open3d_cloud(path)
    for ours, theirs in zip(ply.read_vertices(path), (cloud["vertices"], cloud["normals"], cloud["colors"])):
        assert ours.view(np.int64).tolist() == theirs.view(np.int64).tolist()
    assert ply.read_mesh(path) is None  # no faces: Open3D's reader says what is missing


@pytest.mark.parametrize("block", [64, 1000])
def test_ascii_rows_across_blocks(tmp_path, monkeypatch, block):
    """Blocks of a few rows: rows that a block splits, the vertices' end and the faces' start in one block, a line
    longer than a block."""
    monkeypatch.setattr(off, "_BLOCK", block)
    for seed in range(8):
        path = tmp_path / f"{seed}.ply"
        _random_ascii(random.Random(100 + seed), path)
        _assert_same(ply.read_mesh(path), _open3d_mesh(path))


def test_real_files_as_ascii_equal_their_binary_read(data_dir, tmp_path):
    """Real binary PLYs written as ASCII by Open3D (six significant digits, ``%g``): the ASCII read is Open3D's, and
    the binary read's values as ``%g`` writes them."""
    o3d = _open3d()
    files = [data_dir / "scans" / "sneaker.ply"] + sorted((data_dir / "modelnet10").rglob("*.ply"))[:3]
    printed = np.vectorize(lambda x: float("%g" % x))
    for k, f in enumerate(files):
        binary = ply.read_mesh(f)
        assert binary is not None, f
        m = o3d.io.read_triangle_mesh(str(f))
        if k == 0:  # normals and colours too
            m.compute_vertex_normals()
            m.vertex_colors = o3d.utility.Vector3dVector(_RNG.random((len(m.vertices), 3)))
        path = tmp_path / f.name
        o3d.io.write_triangle_mesh(str(path), m, write_ascii=True)
        ply.check_complete(path)
        mesh = read_mesh(path)
        _assert_same(mesh, _open3d_mesh(path))
        np.testing.assert_array_equal(mesh.triangles, binary.triangles)
        np.testing.assert_array_equal(mesh.vertices, printed(binary.vertices))
        if k == 0:
            np.testing.assert_array_equal(mesh.vertex_normals, printed(np.asarray(m.vertex_normals)))


_ROWS = ["0 0 0 255 0 0", "1 0 0 0 255 0", "0 1 0 0 0 255", "0 0 1 9 9 9", "3 0 1 2", "3 0 2 3"]


def _small(path, rows=_ROWS, eol="\n"):
    head = ["ply", "format ascii 1.0", "comment c", "element vertex 4", "property float x", "property float y",
            "property float z", "property uchar red", "property uchar green", "property uchar blue", "element face 2",
            "property list uchar int vertex_indices", "end_header"]  # the rows start on line 14
    path.write_bytes(eol.join(head + list(rows)).encode() + eol.encode())
    return path


@pytest.mark.parametrize("eol", ["\n", "\r\n"])
@pytest.mark.parametrize("line, row, message", [
    (15, "1 0 0 0 255", r"a 'vertex' row holds 5 values; the header declares 6 \(x y z red green blue\)"),
    (15, "1 0 0 0 255 0 7", r"a 'vertex' row holds 7 values"),
    (16, "0 one 0 0 0 255", r"the 'vertex' property 'y' \(float\) holds 'one', not a number"),
    (16, "0 1 0 0 0 256", r"the 'vertex' property 'blue' \(uchar\) holds '256', beyond the range of uchar "
                          r"\(0 to 255\)"),
    (16, "0 1 0 0 0 2.5", r"the 'vertex' property 'blue' \(uchar\) holds '2.5', not a whole number"),
    (16, "0 1 0 0 -1 2", r"the 'vertex' property 'green' \(uchar\) holds '-1', beyond the range of uchar"),
    (14, "0 0 1e39 255 0 0", r"the 'vertex' property 'z' \(float\) holds '1e39', beyond the range of float"),
    (14, "0 0 1.2.3 255 0 0", r"the 'vertex' property 'z' \(float\) holds '1.2.3', not a number"),
    (17, "0 0 1 9 9 9 # a comment", r"a 'vertex' row holds 9 values"),
    (17, "0 0 1 9 9 9#", r"the 'vertex' property 'blue' \(uchar\) holds '9#', not a whole number"),
    (18, "3 0 1", r"a 'face' row holds 3 values; a triangle takes 4: vertex_indices \(3 and three corners\)"),
    (18, "3 0 1 2 3", r"a 'face' row holds 5 values"),
    (18, "3 0 1 x", r"the 'face' property 'vertex_indices' \(int\) holds 'x', not a whole number"),
    (18, "x 0 1 2", r"the 'face' property 'vertex_indices' \(uchar\) holds 'x', not a whole number"),
])
def test_a_malformed_ascii_row_names_its_line(tmp_path, eol, line, row, message):
    rows = list(_ROWS)
    rows[line - 14] = row
    path = _small(tmp_path / "bad.ply", rows, eol)
    with pytest.raises(InputError, match=rf"bad\.ply: line {line}: {message}"):
        read_mesh(path)
    if line < 18:
        with pytest.raises(InputError, match=rf"line {line}: {message}"):
            ply.read_vertices(path)


@pytest.mark.parametrize("faces, message", [
    (["3 0 1 2", "3 0 2 4"], r"1 triangle indexes vertices outside \[0, 4\) \(indices from 0 to 4; .* line 19"),
    (["3 0 -1 2", "3 0 9 3"], r"2 triangles index vertices outside \[0, 4\) \(indices from -1 to 9; .* line 18"),
    (["3 0 -1 2", "3 0 x 3"], r"1 triangle indexes vertices outside \[0, 4\) \(indices from -1 to 2; .* line 18"),
    (["3 0 -1 2", "4 0 1 2 3"], r"1 triangle indexes vertices outside \[0, 4\) .*the first on line 18\)"),
])
def test_corners_outside_the_vertices_name_the_first_line(tmp_path, faces, message):
    """Counted over the faces (as the mesh counts them), the first named by its line; a row wrong in another way
    after it, or one for Open3D, ends the reading there."""
    path = _small(tmp_path / "far.ply", _ROWS[:4] + faces)
    with pytest.raises(InputError, match=rf"far\.ply: {message}"):
        read_mesh(path)


def test_the_first_wrong_row_decides(tmp_path):
    rows = list(_ROWS)
    rows[1], rows[4] = "1 0 0 0 255 0 7", "4 0 1 2 3"  # a wrong vertex row, then a polygon: the error
    with pytest.raises(InputError, match=r"line 15: a 'vertex' row holds 7 values"):
        ply.read_mesh(_small(tmp_path / "a.ply", rows))
    rows = list(_ROWS)
    rows[4], rows[5] = "4 0 1 2 3", "3 0 x 3"  # a polygon, then a wrong face row: Open3D reads the file
    assert ply.read_mesh(_small(tmp_path / "b.ply", rows)) is None
    rows = list(_ROWS)
    rows[0], rows[3] = "nan 0 0 255 0 0", "0 0 1 9 9 x"  # a word only C reads, then a wrong row: Open3D
    assert ply.read_mesh(_small(tmp_path / "c.ply", rows)) is None


def test_ascii_beyond_the_reader_is_open3ds(tmp_path):
    """Polygons, other elements, words only C reads (nan, inf, hexadecimal floats), corners of a floating type:
    :func:`ply.read_mesh` leaves them to Open3D, whose mesh (or refusal) kpd gives as before."""
    cases = {}
    rows = list(_ROWS)
    rows[4] = "4 0 1 2 3"
    cases["polygon"] = _small(tmp_path / "polygon.ply", rows)
    rows = list(_ROWS)
    rows[0] = "0x1p-1 0 0 255 0 0"
    cases["hexadecimal"] = _small(tmp_path / "hexadecimal.ply", rows)
    text = _small(tmp_path / "x.ply").read_text()
    cases["edges"] = tmp_path / "edges.ply"
    cases["edges"].write_text(text.replace("end_header\n", "element edge 1\nproperty int vertex1\n"
                                           "property int vertex2\nend_header\n") + "0 1\n")
    cases["float corners"] = tmp_path / "float.ply"
    cases["float corners"].write_text(text.replace("uchar int vertex_indices", "uchar float vertex_indices"))
    for name, path in cases.items():
        assert ply.read_mesh(path) is None, name
        _assert_same(read_mesh(path), _open3d_mesh(path))
    rows = list(_ROWS)
    rows[0] = "nan 0 0 255 0 0"
    path = _small(tmp_path / "nan.ply", rows)
    assert ply.read_mesh(path) is None
    with pytest.raises(InputError, match="NaN or inf coordinates"):  # Open3D reads the NaN, the mesh refuses it
        read_mesh(path)
    rows[0] = "inf 0 0 255 0 0"
    path = _small(tmp_path / "inf.ply", rows)
    assert ply.read_mesh(path) is None
    with pytest.raises(InputError, match="could not be read as a mesh"):  # rply refuses inf
        read_mesh(path)


def test_ascii_properties_in_any_order_read_by_name(tmp_path):
    """Open3D refuses a file whose ``z`` comes before ``x`` or ``y`` (its reader counts a vertex done at ``z``);
    kpd reads every order by name, as its binary reader does."""
    v, t = _grid(9)
    v = v.astype(np.float32).astype(np.float64)
    props = [("float", "z"), ("float", "nz"), ("float", "x"), ("float", "nx"), ("float", "y"), ("float", "ny")]
    n = _RNG.normal(size=v.shape).astype(np.float32).astype(np.float64)
    columns = {"x": v[:, 0], "y": v[:, 1], "z": v[:, 2], "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]}
    binary = _write_ply(tmp_path / "b.ply", props, [columns[name] for _, name in props], faces=t)
    head = ["ply", "format ascii 1.0", f"element vertex {len(v)}"] + [f"property {k} {name}" for k, name in props]
    head += [f"element face {len(t)}", "property list uchar int vertex_indices", "end_header"]
    rows = [" ".join(repr(float(columns[name][i])) for _, name in props) for i in range(len(v))]
    rows += [f"3 {a} {b} {c}" for a, b, c in t]
    path = tmp_path / "a.ply"
    path.write_text("\n".join(head + rows) + "\n")
    ours, theirs = ply.read_mesh(path), ply.read_mesh(binary)
    np.testing.assert_array_equal(ours.vertices, v)
    np.testing.assert_array_equal(ours.vertices, theirs.vertices)
    np.testing.assert_array_equal(ours.vertex_normals, theirs.vertex_normals)
    np.testing.assert_array_equal(ours.triangles, t)


def test_truncated_ascii(tmp_path):
    """Fewer lines than the header declares: the completeness check, as before; enough lines but fewer rows (blank
    lines among them): the reader, which counts the rows."""
    path = _small(tmp_path / "short.ply", _ROWS[:-1])
    with pytest.raises(InputError, match=r"short\.ply: the file is truncated: its header declares 4 'vertex' and 2 "
                                         r"'face' elements \(6 rows\) but 5 rows follow"):
        read_mesh(path)
    path = _small(tmp_path / "blank.ply", _ROWS[:2] + ["", "  "] + _ROWS[2:-1])
    ply.check_complete(path)
    with pytest.raises(InputError, match=r"blank\.ply: the file is truncated: its header declares 4 'vertex' and 2 "
                                         r"'face' elements \(6 rows\) but 5 rows follow"):
        read_mesh(path)


# per column of the layouts below, words that read (mostly) and words that are wrong or Open3D's
_ODD = [b"256", b"-1", b"x", b"#", b"3#", b"nan", b"0x1p3", b"1e39", b"1.2.3", b"\x0b5", b"12345678901234567890",
        b"0.5", b"4"]
_FLOATS = [b"0", b"-0", b"+3", b"007", b"0.1", b"-2.5e-3", b"1e5", b"9007199254740993", b"0.30000000000000004",
           b".5", b"5.", b"-1.7976931348623157e308"]
_INTS = [b"0", b"7", b"-0", b"+3", b"007", b"-40000", b"2147483647"]
_BYTES = [b"0", b"7", b"255", b"-0", b"+3", b"007"]
_VERTEX_PROPS = [("float", "x"), ("double", "y"), ("int", "z"), ("uchar", "red"), ("uchar", "green"), ("uchar", "blue")]
_VERTEX_WORDS = [_FLOATS[:-1], _FLOATS, _INTS, _BYTES, _BYTES, _BYTES]
_FACE_PROPS = [("uchar", "flags"), ("list", "uchar", "int", "vertex_indices"), ("float", "quality")]
_FACE_WORDS = [_BYTES, [b"3"], [b"0", b"1", b"2", b"+1", b"-0"], [b"0", b"1", b"2"], [b"0", b"1", b"2"], _FLOATS]


def _rows(columns: list) -> st.SearchStrategy:
    """Rows whose words are mostly what their column reads (one in twelve not), sometimes of one to eight words of
    any column, joined by runs of blanks."""
    word = [st.sampled_from(good * (12 * len(_ODD) // len(good)) + _ODD) for good in columns]
    row = st.one_of(*[st.tuples(*word).map(list)] * 4,
                    st.lists(st.sampled_from(sum(columns, []) + _ODD), min_size=1, max_size=8))
    gaps = st.lists(st.sampled_from([b" ", b"  ", b"\t", b" \r "]), min_size=8, max_size=8)
    return st.lists(st.tuples(row, gaps).map(lambda pair: b"".join(w + g for w, g in zip(*pair)).rstrip()),
                    min_size=1, max_size=8)


def _outcome(read, path):
    """What ``read(path)`` gives: its arrays' bits, None, or the message of its InputError."""
    try:
        got = read(path)
    except InputError as error:
        return str(error)
    if got is None:
        return None
    arrays = (got.vertices, got.triangles) if isinstance(got, Mesh) else got
    return [None if a is None else (a.dtype.str, a.view(np.uint8).tobytes()) for a in arrays]


@settings(max_examples=400, deadline=None)
@given(data=st.data(), faces=st.booleans())
def test_compiled_passes_read_what_python_reads(tmp_path_factory, data, faces):
    """Every row as the compiled passes read it equals the row read word by word in Python (the reader's own
    fallback, :meth:`ply._Rows.judge`, run on every row): the same values to the bit, the same error, or Open3D's."""
    rows = data.draw(_rows(_FACE_WORDS if faces else _VERTEX_WORDS))
    head = ["ply", "format ascii 1.0", f"element vertex {3 if faces else len(rows)}"]
    head += [f"property {kind} {name}" for kind, name in _VERTEX_PROPS]
    if faces:  # valid vertices, then the rows
        head += [f"element face {len(rows)}"] + [" ".join(["property", *prop]) for prop in _FACE_PROPS]
        rows = [b"0 0 0 1 2 3", b"1 0 0 4 5 6", b"0 1 0 7 8 9"] + rows
    path = tmp_path_factory.mktemp("rows") / "r.ply"
    path.write_bytes("\n".join(head + ["end_header"]).encode() + b"\n" + b"\n".join(rows) + b"\n")
    read = ply.read_mesh if faces else ply.read_vertices
    fast = _outcome(read, path)
    passes = ply._Rows.read

    def every_row(self, block, begin, stop, floats, out):
        passes(self, block, begin, stop, floats, out)
        return np.arange(len(begin))

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ply._Rows, "read", every_row)
        slow = _outcome(read, path)
    assert fast == slow


@pytest.mark.parametrize("ascii_", [False, True])
def test_read_shape_and_read_points_read_a_ply_by_kpd_as_open3d_does(data_dir, tmp_path, monkeypatch, ascii_):
    """read_shape (a mesh, or the points of a PLY without faces) and read_points of PLYs with normals and colours,
    binary and ASCII, are Open3D's arrays to the bit, read without Open3D (which took 1.1 s of kpd keypoints'
    3.6 s at 1.37M vertices)."""
    from kpd.io import dispatch, read_points, read_shape
    from kpd.mesh import PointSet

    o3d = _open3d()
    scan = o3d.io.read_triangle_mesh(str(data_dir / "scans" / "sneaker.ply"))
    scan.compute_vertex_normals()
    scan.vertex_colors = o3d.utility.Vector3dVector(np.random.default_rng(0).random((len(scan.vertices), 3)))
    mesh_path, cloud_path = tmp_path / "mesh.ply", tmp_path / "cloud.ply"
    o3d.io.write_triangle_mesh(str(mesh_path), scan, write_ascii=ascii_)
    cloud = o3d.geometry.PointCloud(scan.vertices)
    cloud.normals, cloud.colors = scan.vertex_normals, scan.vertex_colors
    o3d.io.write_point_cloud(str(cloud_path), cloud, write_ascii=ascii_)
    want_mesh, want_cloud = _open3d_mesh(mesh_path), _open3d_cloud(cloud_path)
    want_mesh_cloud = _open3d_cloud(mesh_path)

    def no_open3d():
        raise AssertionError("read by Open3D")

    monkeypatch.setattr(dispatch, "open3d_module", no_open3d)
    _assert_same(read_shape(mesh_path), want_mesh)
    shape = read_shape(cloud_path)
    assert isinstance(shape, PointSet)
    for got, key in ((shape.points, "vertices"), (shape.normals, "normals"), (shape.colors, "colors")):
        np.testing.assert_array_equal(got, want_cloud[key])
    for path, want in ((cloud_path, want_cloud), (mesh_path, want_mesh_cloud)):
        points = read_points(path)
        for got, key in ((points.points, "vertices"), (points.normals, "normals"), (points.colors, "colors")):
            np.testing.assert_array_equal(got, want[key])
