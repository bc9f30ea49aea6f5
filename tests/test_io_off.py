"""kpd.io.off: its writer writes what Open3D's OFF writer writes (header, colours, faces) with 9 significant digits
instead of 6, atomically, and a file that stops early is caught; its reader gives the mesh Open3D's reader gives
(vertices, faces cut as Open3D cuts them, normals, colours, in order) except that every number is the file's decimal
as Python's float() reads it, to the bit, where Open3D rounds it to float32; it equals a plain line-by-line reading,
reads ModelNet's header, and names the line of a bad row."""

from __future__ import annotations

import logging
import os
import random
import re
import tempfile
from decimal import Decimal, localcontext
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.errors import InputError, WriteError
from kpd.io import Mesh, PointSet, numbers, off, read_mesh, read_points, read_shape, text, write_mesh


def grid_mesh(normals: bool, colors: bool, n: int = 12, seed: int = 0) -> Mesh:
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(0, 3, n))
    vertices = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x).ravel()], axis=1) * 10.0 ** rng.integers(-3, 3)
    vertices = vertices + rng.standard_normal(vertices.shape) * 1e-4
    quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j)
             for i in range(n - 1) for j in range(n - 1)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    vn = rng.standard_normal(vertices.shape)
    return Mesh(vertices, triangles, vertex_normals=vn / np.linalg.norm(vn, axis=1, keepdims=True) if normals else None,
                vertex_colors=rng.random(vertices.shape) if colors else None)


def open3d_written(mesh: Mesh, path) -> list[str]:
    import open3d as o3d

    assert o3d.io.write_triangle_mesh(str(path), mesh.to_open3d())
    return path.read_text().splitlines()


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("colors", [False, True])
def test_what_open3d_writes_with_nine_digits(tmp_path, normals, colors):
    mesh = grid_mesh(normals, colors)
    write_mesh(tmp_path / "kpd.off", mesh)
    ours = (tmp_path / "kpd.off").read_text().splitlines()
    theirs = open3d_written(mesh, tmp_path / "open3d.off")
    V, T = len(mesh.vertices), len(mesh.triangles)
    assert ours[0] == theirs[0] == ("C" if colors else "") + ("N" if normals else "") + "OFF"
    assert ours[1] == theirs[1] == f"{V} {T} 0"
    assert len(ours) == len(theirs) == 2 + V + T
    assert ours[2 + V:] == theirs[2 + V:]  # faces: "3 a b c"
    floats = [mesh.vertices] + ([mesh.vertex_normals] if normals else [])
    rows = [line.split() for line in ours[2 : 2 + V]]
    expected = text.float_rows_reference(np.hstack(floats), 9, suffix=b"")
    assert [" ".join(r[: 3 * len(floats)]).encode() for r in rows] == expected
    a = np.array([line.split() for line in theirs[2 : 2 + V]], dtype=float)
    b = np.array(rows, dtype=float)
    np.testing.assert_allclose(b[:, : 3 * len(floats)], a[:, : 3 * len(floats)], rtol=5e-6, atol=1e-300)
    np.testing.assert_array_equal(b[:, 3 * len(floats):], a[:, 3 * len(floats):])  # colours: r g b 255


def test_colours_round_half_away_from_zero_as_open3d(tmp_path):
    mesh = grid_mesh(False, True, n=8)
    halves = (np.arange(len(mesh.vertices) * 3) % 255 + 0.5) / 255  # k + 1/2 once scaled, as near as float64 goes
    colors = np.concatenate([[0.3, 0.5, 1 / 510, 0.7, 1.0, 0.0], halves])[: len(mesh.vertices) * 3].reshape(-1, 3)
    mesh = Mesh(mesh.vertices, mesh.triangles, vertex_colors=colors)
    write_mesh(tmp_path / "kpd.off", mesh)
    ours = (tmp_path / "kpd.off").read_text().splitlines()
    theirs = open3d_written(mesh, tmp_path / "open3d.off")
    assert [line.split()[3:] for line in ours[2:]] == [line.split()[3:] for line in theirs[2:]]
    assert ours[2].split()[3:] == ["77", "128", "1", "255"]
    signed = Mesh(mesh.vertices, mesh.triangles, vertex_colors=np.where(colors == 0, -0.0, colors))
    write_mesh(tmp_path / "signed.off", signed)  # a colour of -0.0 (Open3D writes "-0") is written 0
    assert (tmp_path / "signed.off").read_text() == "\n".join(ours) + "\n"


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("colors", [False, True])
def test_read_back_exactly_by_kpd_and_within_float32_by_open3d(tmp_path, normals, colors):
    import open3d as o3d

    mesh = grid_mesh(normals, colors, seed=3)
    f32 = Mesh(mesh.vertices.astype(np.float32).astype(np.float64), mesh.triangles,
               vertex_normals=mesh.vertex_normals, vertex_colors=mesh.vertex_colors)
    for m, name in ((mesh, "a.off"), (f32, "b.off")):
        write_mesh(tmp_path / name, m)
        back = read_mesh(tmp_path / name)
        np.testing.assert_array_equal(back.vertices, [[float("%.9g" % x) for x in row] for row in m.vertices])
        o3d_back = o3d.io.read_triangle_mesh(str(tmp_path / name))
        np.testing.assert_array_equal(np.asarray(o3d_back.vertices), back.vertices.astype(np.float32))
        np.testing.assert_array_equal(back.triangles, m.triangles)
        if m is f32:  # a float32 coordinate's 9 digits round back to it
            np.testing.assert_array_equal(back.vertices.astype(np.float32), m.vertices)
        assert (np.abs(back.vertices - m.vertices) <= 5e-9 * np.abs(m.vertices)).all()
        if normals:
            np.testing.assert_allclose(back.vertex_normals, m.vertex_normals, atol=5e-9)
        else:
            assert back.vertex_normals is None
        if colors:
            scaled = m.vertex_colors * 255
            np.testing.assert_array_equal(back.vertex_colors * 255, np.floor(scaled + 0.5))
        else:
            assert back.vertex_colors is None


def test_real_meshes_round_trip(data_dir, tmp_path):
    for name in ("scans/sneaker.ply", "scans/ycb/banana/textured_simple_reoriented.obj"):
        mesh = read_mesh(data_dir / name)
        mesh = Mesh(mesh.vertices, mesh.triangles, vertex_normals=mesh.vertex_normals)
        out = tmp_path / (os.path.basename(name) + ".off")
        write_mesh(out, mesh)
        back = read_mesh(out)
        np.testing.assert_array_equal(back.triangles, mesh.triangles)
        assert (np.abs(back.vertices - mesh.vertices) <= 5e-9 * np.abs(mesh.vertices)).all(), name
        if mesh.vertices.astype(np.float32).astype(np.float64).tolist() == mesh.vertices.tolist():
            back32 = back.vertices.astype(np.float32)  # the sneaker scan's float32 coordinates, rounded back
            np.testing.assert_array_equal(back32, mesh.vertices)


def test_textures_are_dropped_with_a_warning(tmp_path, caplog):
    mesh = grid_mesh(True, False, n=4)
    T = len(mesh.triangles)
    textured = Mesh(mesh.vertices, mesh.triangles, triangle_uvs=np.zeros((3 * T, 2)),
                    textures=[np.zeros((2, 2, 3), np.uint8)])
    with caplog.at_level(logging.WARNING, logger="kpd.io"):
        write_mesh(tmp_path / "t.off", textured)
    assert "cannot store UVs and textures" in caplog.text
    assert (tmp_path / "t.off").read_text().startswith("OFF\n16 18 0\n")


def test_truncated_file_is_caught(tmp_path, monkeypatch):
    mesh = grid_mesh(True, True)
    write_mesh(tmp_path / "whole.off", mesh)
    data = (tmp_path / "whole.off").read_bytes()
    (tmp_path / "cut.off").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.off: the file is truncated"):
        read_mesh(tmp_path / "cut.off")

    def stops_early(fh, corners, **options):  # a writer that stops halfway through the faces
        fh.write(text.index_rows(corners[: len(corners) // 2], **options))

    monkeypatch.setattr(text, "write_index_rows", stops_early)
    with pytest.raises(WriteError, match=r"cannot write .*early\.off: the written file is incomplete"):
        write_mesh(tmp_path / "early.off", mesh)
    assert sorted(os.listdir(tmp_path)) == ["cut.off", "whole.off"]


# --- reading -------------------------------------------------------------------------------------------------------


def off_reference(data: bytes) -> tuple:
    """What kpd's reader reads of a good text OFF, in plain Python, line by line: (V, 3) vertices, (V, 3) normals or
    None, (V, 3) colours or None, (T, 3) triangles, a polygon cut by ``off._cut_polygon_reference``."""
    rows = [s for s in (line.strip() for line in data.split(b"\n")) if s and not s.startswith(b"#")]
    keyword, counts = re.fullmatch(rb"(C?N?OFF)[ \t]*(.*)", rows[0], re.S).groups()
    if not counts:  # not ModelNet's header: the counts on a line of their own
        counts, rows = rows[1], rows[1:]
    V, F = (int(w) for w in counts.split()[:2])
    rows = rows[1:]
    normals, colors = b"N" in keyword, keyword.startswith(b"C")
    width = 3 + 3 * normals + 4 * colors
    table = np.array([[float(w) for w in row.split()[:width]] for row in rows[:V]])
    triangles = []
    for row in rows[V : V + F]:
        words = row.split()
        corners = [int(w) for w in words[1 : int(words[0]) + 1]]
        triangles += [tuple(corners)] if len(corners) == 3 else off._cut_polygon_reference(table[:, :3], corners)
    return (table[:, :3], table[:, 3:6] if normals else None, table[:, width - 4 : width - 1] / 255 if colors else None,
            np.array(triangles, dtype=np.int64).reshape(-1, 3))


def open3d_read(path: Path):
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(path))
    return (np.asarray(m.vertices), np.asarray(m.vertex_normals) if m.has_vertex_normals() else None,
            np.asarray(m.vertex_colors) if m.has_vertex_colors() else None, np.asarray(m.triangles))


def assert_read_as_open3d_reads_it(path: Path, open3d_path: Path | None = None) -> Mesh:
    """kpd's mesh of ``path`` is its plain reading, to the bit, and Open3D's (of ``open3d_path``, the same rows under
    a header Open3D reads) rounded to float32: the same triangles, normals and colours."""
    mesh = read_mesh(path)
    vertices, normals, colors, triangles = off_reference(path.read_bytes())
    assert mesh.vertices.view(np.int64).tolist() == vertices.view(np.int64).tolist()  # the bits: -0.0 too
    np.testing.assert_array_equal(mesh.triangles, triangles)
    for got, want in ((mesh.vertex_normals, normals), (mesh.vertex_colors, colors)):
        assert (got is None) == (want is None)
        if got is not None:
            np.testing.assert_array_equal(got, want)
    o3d_vertices, o3d_normals, o3d_colors, o3d_triangles = open3d_read(open3d_path or path)
    np.testing.assert_array_equal(o3d_vertices, mesh.vertices.astype(np.float32))
    np.testing.assert_array_equal(o3d_triangles, mesh.triangles)
    if normals is not None:
        np.testing.assert_array_equal(o3d_normals, mesh.vertex_normals.astype(np.float32))
    else:
        assert o3d_normals is None
    if colors is not None:  # Open3D divides the float32 channel by 255 in float32
        np.testing.assert_array_equal(o3d_colors, (colors * 255).astype(np.float32) / np.float32(255))
    else:
        assert o3d_colors is None
    return mesh


REAL_MESHES = ("scans/sneaker.ply", "scans/ycb/banana/textured_simple_reoriented.obj",
               "modelnet10/chair/test/chair_0890.ply")


@pytest.mark.parametrize("name", REAL_MESHES)
@pytest.mark.parametrize("writer", ["kpd", "open3d"])
def test_real_meshes_read_as_open3d_reads_them_but_exact(data_dir, tmp_path, name, writer):
    import open3d as o3d

    mesh = read_mesh(data_dir / name)
    rng = np.random.default_rng(len(name))
    colors = np.round(rng.random(mesh.vertices.shape) * 255) / 255
    for normals in (None, mesh.vertex_normals):
        for color in (None, colors):
            m = Mesh(mesh.vertices, mesh.triangles, vertex_normals=normals, vertex_colors=color)
            path = tmp_path / "m.off"
            if writer == "kpd":
                write_mesh(path, m)
            else:
                assert o3d.io.write_triangle_mesh(str(path), m.to_open3d())
            back = assert_read_as_open3d_reads_it(path)
            assert back.vertex_colors is None if color is None else np.array_equal(back.vertex_colors, color)


def test_modelnet_header_with_the_counts_on_its_line(data_dir, tmp_path):
    """ModelNet's files put the counts on the header's line; Open3D refuses them, kpd reads them as the same rows
    under a proper header."""
    write_mesh(tmp_path / "proper.off", read_mesh(data_dir / REAL_MESHES[2]))
    header, counts, rows = (tmp_path / "proper.off").read_bytes().split(b"\n", 2)
    for joined in (header + counts, header + b" " + counts):
        (tmp_path / "modelnet.off").write_bytes(joined + b"\n" + rows)
        assert_read_as_open3d_reads_it(tmp_path / "modelnet.off", tmp_path / "proper.off")
    with pytest.raises(InputError, match=r"modelnet\.off: could not be read as a mesh \(Open3D: .*header keyword"):
        Mesh.from_open3d(_open3d_mesh(tmp_path / "modelnet.off"))
    cut = (header + counts + b"\n" + rows)[: -len(rows) // 2]
    (tmp_path / "modelnet.off").write_bytes(cut)
    with pytest.raises(InputError, match=r"modelnet\.off: the file is truncated: its header declares 1658 vertices"):
        read_mesh(tmp_path / "modelnet.off")


def _open3d_mesh(path: Path):
    from kpd.io.dispatch import _read_open3d_mesh

    return _read_open3d_mesh(path, ".off")


def test_comments_blank_lines_and_what_follows_a_row(tmp_path):
    text = ("# written by hand\n\n  COFF \r\n# the counts\n 4 2 0 \n\n0 0 0 255 0 0 255 # red\n"
            "\t1 0 0\t0 255 0 255 extra words\n# between rows\n1 1 0 0 0 255 128\r\n0.25 1 0 12.5 0 7 1\n"
            "\n3 0 1 2 255 0 0\n  3\t0 2 3 # a comment\nthe lines after the last face are not read\n")
    path = tmp_path / "hand.off"
    path.write_text(text)
    mesh = assert_read_as_open3d_reads_it(path)
    np.testing.assert_array_equal(mesh.vertex_colors[3], [12.5 / 255, 0, 7 / 255])


def polygon_file(path: Path, seed: int, count: int = 60) -> None:
    """Polygons of 4 to 9 corners around a centre, some concave, in tilted planes, as 6-digit decimals."""
    rng = np.random.default_rng(seed)
    vertices, faces = [], []
    for _ in range(count):
        n = int(rng.integers(4, 10))
        angles = np.sort(rng.uniform(0, 2 * np.pi, n)) * rng.choice([1, -1])
        radii = rng.uniform(0.2, 1.0, n) if rng.random() < 0.5 else np.ones(n)
        plane = np.linalg.qr(rng.normal(size=(3, 3)))[0] if rng.random() < 0.7 else np.eye(3)
        points = np.stack([radii * np.cos(angles), radii * np.sin(angles), np.zeros(n)], axis=1) @ plane.T
        faces.append([n] + list(range(len(vertices), len(vertices) + n)))
        vertices += (points + rng.normal(size=3) * 3).tolist()
    lines = [f"OFF\n{len(vertices)} {len(faces)} 0"] + ["%.6f %.6f %.6f" % tuple(v) for v in vertices] + \
        [" ".join(map(str, f)) for f in faces]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("seed", range(6))
def test_polygons_are_cut_as_open3d_cuts_them(tmp_path, seed):
    """Every polygon Open3D's ear clipping cuts is cut into the same triangles; where it finds no ear, Open3D refuses
    the file and kpd names the polygon's line."""
    path = tmp_path / "polygons.off"
    polygon_file(path, seed)
    lines = path.read_text().splitlines()
    V = int(lines[1].split()[0])
    good, bad = [], []
    for number, line in enumerate(lines[2 + V:], start=3 + V):
        corners = [int(w) for w in line.split()[1:]]
        points = np.array([[float(w) for w in lines[2 + c].split()] for c in corners])
        alone = tmp_path / "one.off"
        alone.write_text(f"OFF\n{len(corners)} 1 0\n" + "\n".join(lines[2 + c] for c in corners) + "\n" +
                         " ".join(map(str, [len(corners)] + list(range(len(corners))))) + "\n")
        cut = off._cut_polygon_reference(points, list(range(len(corners))))
        if cut is None:
            with pytest.raises(InputError, match=rf"one\.off: line {3 + len(corners)}: a face of \d corners has no"):
                read_mesh(alone)
            with pytest.raises(InputError, match=r"A polygon in the mesh could not be decomposed"):
                _open3d_mesh(alone)
            bad.append(number)
        else:
            assert_read_as_open3d_reads_it(alone)
            good.append(line)
    assert len(good) > len(bad)
    if bad:
        with pytest.raises(InputError, match=rf"polygons\.off: line {bad[0]}: a face of \d corners has no ear"):
            read_mesh(path)
    lines[1] = f"{V} {len(good)} 0"
    path.write_text("\n".join(lines[: 2 + V] + good) + "\n")
    assert_read_as_open3d_reads_it(path)


def test_a_polygon_beyond_the_vertices_is_refused_by_the_mesh(tmp_path):
    path = tmp_path / "far.off"
    path.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 7\n")
    with pytest.raises(InputError, match=r"far\.off: 1 triangle indexes vertices outside \[0, 4\) \(indices from 0 to"):
        read_mesh(path)


def plain_words(rng: random.Random, n: int) -> list[str]:
    """Plain decimals as files write them, with signs, leading zeros, long mantissas, exponents near float32's
    ends and beyond float64's, subnormals, and decimals half-way between two neighbouring float64 values."""
    formats = ["%.9g", "%.17g", "%.6f", "%e", "%.3f", "%g", "%.20f", "%+.4e", "%.0f", "%.12E", "%.15g", "%r"]
    words = []
    for _ in range(n):
        r = rng.random()
        if r < 0.05:
            words.append(rng.choice(["0", "-0", "0.0", "-0.000", "+0", "00012.5000", ".5", "5.", "-.25e1", "1e22",
                                     "1e23", "9007199254740993", "123456789012345678901234", "1e-22", "1e-23",
                                     "4.9e-324", "1e-400", "3.4e38", "-3.4028234e38", "0.1", "0.30000000000000004",
                                     "0.000000000000000000000000001", "1E5", "1e+05", "1e-05", "+3.25"]))
        elif r < 0.15:
            x = rng.uniform(-1e6, 1e6) * 10.0 ** rng.randint(-5, 5)
            words.append(str((Decimal(x) + Decimal(float(np.nextafter(x, np.inf)))) / 2))
        else:
            x = rng.uniform(-10, 10) * 10.0 ** rng.randint(-40, 37)
            words.append(rng.choice(formats) % x)
    return words


@pytest.mark.parametrize("halves", [False, True])
def test_numbers_are_the_values_python_reads_to_the_bit(tmp_path, monkeypatch, halves):
    """Every word as Python's float() reads it, across blocks of a few hundred bytes (the same rows whatever the
    block size), on one thread or two."""
    if halves:
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
        monkeypatch.setattr(off, "_BLOCK", 300)
    rng = random.Random(11)
    with localcontext() as context:
        context.prec = 80
        words = plain_words(rng, 30000)
    small = [w for w in words if abs(float(w)) < 1e17]  # positions a mesh takes; any number as a normal
    rows = [small[i : i + 3] + words[2 * i : 2 * i + 3] for i in range(len(small) // 3)]
    body = "".join(f"{' '.join(row)}\n" for row in rows)
    path = tmp_path / "numbers.off"
    path.write_text(f"NOFF\n{len(rows)} 1 0\n{body}3 0 1 2\n")
    shape = off.read_mesh(path, points=True)
    want = np.array([[float(w) for w in row] for row in rows])
    assert shape.vertices.view(np.int64).tolist() == want[:, :3].view(np.int64).tolist()
    assert shape.vertex_normals.view(np.int64).tolist() == want[:, 3:].view(np.int64).tolist()


@pytest.mark.parametrize("halves", [False, True])
def test_a_large_off_reads_as_written(tmp_path, monkeypatch, halves):
    """A hundred thousand vertices and twice as many faces, written by kpd: the 9-digit decimals back exactly, in
    blocks of 64 KiB on two threads as in one block."""
    if halves:
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
        monkeypatch.setattr(off, "_BLOCK", 1 << 16)
    rng = np.random.default_rng(3)
    V, T = 100_000, 200_000
    mesh = Mesh(rng.normal(size=(V, 3)), rng.integers(0, V, size=(T, 3)))
    write_mesh(tmp_path / "big.off", mesh)
    back = read_mesh(tmp_path / "big.off")
    words = np.array((tmp_path / "big.off").read_text().split("\n")[2 : 2 + V])
    np.testing.assert_array_equal(back.vertices, np.array([row.split() for row in words], dtype=np.float64))
    assert (np.abs(back.vertices - mesh.vertices) <= 5e-9 * np.abs(mesh.vertices)).all()
    np.testing.assert_array_equal(back.triangles, mesh.triangles)


DECORATIONS = ["", " ", "\t", "\r", "  \t", "\x0b", "\x0c"]


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_any_layout_reads_as_a_line_by_line_reading(data):
    """Blank and comment lines anywhere, blanks around and between words, CRLF, words after a row, no last line
    break, in blocks of a few bytes on two threads: the rows of a plain line-by-line reading."""
    draw = data.draw
    V, F = draw(st.integers(3, 12)), draw(st.integers(1, 12))
    keyword = draw(st.sampled_from(["OFF", "COFF", "NOFF", "CNOFF"]))
    width = 3 + 3 * ("N" in keyword) + 4 * keyword.startswith("C")
    number = st.sampled_from(["0", "-1.5", "2e-3", "+7", ".25", "1E2", "0.30000000000000004", "123456789012345678"])
    channel = st.sampled_from(["0", "255", "12.5", "+7", "1E2", ".25", "0.30000000000000004"])
    space = st.sampled_from([" ", "\t", "  ", " \x0b"])

    def line(words: list[str]) -> str:
        parts = [draw(st.sampled_from(DECORATIONS))]
        for w in words:
            parts += [w, draw(space)]
        tail = draw(st.sampled_from(["", "# a comment", "255 0 0", "x"]))
        return "".join(parts) + tail + draw(st.sampled_from(["", "\r"]))

    rows = [line([draw(number) for _ in range(width - 4 * keyword.startswith("C"))] +
                 [draw(channel) for _ in range(4 * keyword.startswith("C"))]) for _ in range(V)]
    rows += [line([str(n)] + [str(draw(st.integers(0, V - 1))) for _ in range(n)])
             for n in (draw(st.sampled_from([3, 3, 3, 4])) for _ in range(F))]
    lines = [keyword, f"{V} {F} 0"] + rows
    for _ in range(draw(st.integers(0, 6))):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(["", "  ", "# note", " \t# x", "\r"])))
    text = "\n".join(lines) + draw(st.sampled_from(["", "\n"]))
    with tempfile.TemporaryDirectory() as folder, pytest.MonkeyPatch.context() as patch:
        patch.setattr(numbers, "THREADED_ROWS", 1)
        patch.setattr(off, "_BLOCK", draw(st.sampled_from([7, 64, 1 << 22])))
        path = Path(folder) / "any.off"
        path.write_text(text)
        try:
            mesh = off.read_mesh(path)
        except InputError as exc:  # the polygon's corners may lie on a line or repeat: no ear
            assert "has no ear" in str(exc)
            return
        vertices, normals, colors, triangles = off_reference(text.encode())
        np.testing.assert_array_equal(mesh.vertices, vertices)
        np.testing.assert_array_equal(mesh.triangles, triangles)
        for got, want in ((mesh.vertex_normals, normals), (mesh.vertex_colors, colors)):
            assert (got is None) == (want is None) and (got is None or np.array_equal(got, want))


def test_a_line_longer_than_a_block(tmp_path, monkeypatch):
    monkeypatch.setattr(off, "_BLOCK", 8)
    path = tmp_path / "long.off"
    path.write_text("OFF\n3 1 0\n0.1000000000000000000000000000000055511151231257827 0 0\n1 0 0\n0 1 0\n3 0 1 2")
    np.testing.assert_array_equal(read_mesh(path).vertices, [[0.1, 0, 0], [1, 0, 0], [0, 1, 0]])


@pytest.mark.parametrize("word", ["3abc", "1.2.3", "0x10", "2.5e", "1,5"])
def test_words_that_are_not_plain_decimals_are_open3ds(tmp_path, word):
    """A C++ stream reads the number a word starts with: Open3D reads such a file as before (float32)."""
    path = tmp_path / "odd.off"
    path.write_text(f"OFF\n3 1 0\n0.3 0 {word}\n1 0 0\n0 1 0\n3 0 1 2.5\n")
    assert off.read_mesh(path) is None
    try:
        want = Mesh.from_open3d(_open3d_mesh(path), path=str(path))
    except InputError as exc:
        with pytest.raises(InputError, match=re.escape(str(exc))):
            read_mesh(path)
    else:
        got = read_mesh(path)
        np.testing.assert_array_equal(got.vertices, want.vertices)
        assert got.vertices[0, 0] == np.float32(0.3)


@pytest.mark.parametrize("text, message", [
    ("OFF\n3 1\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
     r"line 2: the counts line must start with the numbers of vertices, faces and edges \(three whole numbers\); "
     r"got '3 1'"),
    ("# c\nOFF\n-3 1 0\n0 0 0\n", r"line 3: the counts line must start with the numbers of vertices"),
    ("OFF\n0 1 0\n3 0 1 2\n", r"line 2: the header declares 0 vertices \(empty geometry\)"),
    ("COFF\n3 1 0\n0 0 0 255 0 0\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n3 0 1 2\n",
     r"line 3: a vertex needs 7 numbers under the header COFF \(x y z r g b a\); got 6"),
    ("NOFF\n# c\n\n3 1 0\n0 0 0 0 0 1\n1 0 0 0 0\n0 1 0 0 0 1\n3 0 1 2\n",
     r"line 6: a vertex needs 6 numbers under the header NOFF \(x y z nx ny nz\); got 5"),
    ("OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n2 0 1\n", r"line 7: a face needs 3 corners or more; got 2"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n0\n", r"line 6: a face needs 3 corners or more; got 0"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1\n", r"line 6: a face of 3 corners needs 3 vertex indices after its "
     r"count; got 2"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2\n", r"line 6: a face of 4 corners needs 4 vertex indices"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3.0 0 1 2\n", r"line 6: a face line must start with its number of corners; "
     r"got '3.0 0 1 2'"),
    ("OFF\n4 1 0\n0 0 0\n1 0 0\n2 0 0\n3 0 0\n4 0 1 2 3\n", r"line 7: a face of 4 corners has no ear"),
    ("OFF\n3 1 0\n0 0 0\n1 0\n0 1 0\n3 0 1\n", r"line 4: a vertex needs 3 numbers"),  # the first bad line
    ("OFF\n3 1 0\n0 0 nan\n1 0 0\n0 1 0\n3 0 1\n", r"could not be read as a mesh \(Open3D: Read OFF failed: could "
     r"not read all vertex values"),  # the first bad line is Open3D's to judge
    ("OFF\n3 1 0\n0 0 1e39\n1 0 0\n0 1 0\n3 0 1 2\n",
     r"could not be read as a mesh \(Open3D: Read OFF failed: could not read all vertex values"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 -2\n", r"1 triangle indexes vertices outside \[0, 3\) \(indices from -2"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n", r"the file is truncated: its header declares 3 vertices and 1 faces "
     r"\(4 rows\) but 3 rows follow"),
    ("OFF\n3 2 0\n0 0 0\n1 0\n# c\n\n", r"the file is truncated: .* but 2 rows follow"),  # before its bad row
])
def test_bad_files_are_one_line_naming_the_line(tmp_path, text, message):
    path = tmp_path / "bad.off"
    path.write_text(text)
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: {message}") as caught:
        read_mesh(path)
    assert "\n" not in str(caught.value)


def test_a_file_without_faces_is_a_point_set(tmp_path):
    path = tmp_path / "points.off"
    path.write_text("COFF\n3 0 0\n0 0 0.3 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n")
    with pytest.raises(InputError, match=r"points\.off: has 3 vertices but no triangles \(a point cloud\?"):
        read_mesh(path)
    shape = read_shape(path)
    assert isinstance(shape, PointSet) and shape.points[0, 2] == 0.3
    np.testing.assert_array_equal(shape.colors, np.eye(3))
    np.testing.assert_array_equal(read_points(path).points, shape.points)


def test_points_of_a_mesh_file_are_its_exact_vertices(tmp_path):
    path = tmp_path / "m.off"
    path.write_text("NOFF\n3 1 0\n0 0 0.3 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0.1 1\n3 0 1 2\n")
    points = read_points(path)
    assert points.points[0, 2] == 0.3 and points.normals[2, 1] == 0.1
    np.testing.assert_array_equal(read_shape(path).vertices, points.points)


@pytest.mark.parametrize("header", ["STOFF", "OFF BINARY", "off", "4OFF"])
def test_other_headers_are_open3ds(tmp_path, header):
    path = tmp_path / "other.off"
    path.write_text(f"{header}\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert off.read_mesh(path) is None
    with pytest.raises(InputError, match=r"other\.off: could not be read as a mesh \(Open3D: Read OFF failed: header"):
        read_mesh(path)
