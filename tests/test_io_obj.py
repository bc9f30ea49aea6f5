"""kpd.io.obj's compiled reading: its lines, numbers and faces equal a plain line-by-line reading of the same text,
every number is the correctly rounded value Python's float() gives, and a scan-sized OBJ reads in one pass."""

from __future__ import annotations

import random
import re
from decimal import localcontext
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from helpers import random_words

from kpd.errors import InputError
from kpd.io import numbers, obj, read_mesh


def lines_reference(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What ``obj._scan`` finds, line by line in Python: starts, ends (before ``\\r\\n``), first non-blank, kind."""
    pieces = data.split(b"\n")
    if len(pieces) > 1 and pieces[-1] == b"":
        pieces.pop()
    rows, at = [], 0
    for piece in pieces:
        start, end = at, at + len(piece)
        at = end + 1
        if end > start and data[end - 1] == 13:
            end -= 1
        j = start
        while j < end and data[j] in b" \t":
            j += 1
        line, kind = data[j:end], 0
        if line[:2] in (b"v ", b"v\t"):
            kind = 1
        elif line[:3] in (b"vt ", b"vt\t"):
            kind = 2
        elif line[:3] in (b"vn ", b"vn\t"):
            kind = 3
        elif line[:2] in (b"f ", b"f\t"):
            kind = 4
        elif data[j:j + 6] in (b"usemtl", b"mtllib") and (j + 6 == len(data) or data[j + 6] in b" \t"):
            kind = 5 if data[j:j + 6] == b"usemtl" else 6
        rows.append((start, end, j, kind))
    return tuple(np.array(column, dtype=np.int64) for column in zip(*rows))


PIECES = [b"v", b"vt", b"vn", b"f", b"u", b"m", b"usemtl", b"mtllib", b" ", b"\t", b"\n", b"\r", b"\r\n", b"#", b"1",
          b"x"]


@settings(max_examples=400, deadline=None)
@given(st.lists(st.sampled_from(PIECES), max_size=40))
def test_lines_equal_a_line_by_line_reading(pieces):
    data = b"".join(pieces)
    for got, want in zip(obj._scan(data), lines_reference(data)):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("halves", [False, True])
def test_lines_of_real_files_equal_a_line_by_line_reading(data_dir, monkeypatch, halves):
    if halves:  # the kernels' two halves on two threads, at any size
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
    files = sorted((data_dir / "shapenetcore_obj").rglob("*.obj"))[:6] + sorted((data_dir / "scans").rglob("*.obj"))[:2]
    assert len(files) >= 6
    for f in files:
        data = f.read_bytes()
        for got, want in zip(obj._scan(data), lines_reference(data)):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("halves", [False, True])
def test_numbers_are_the_values_python_reads_to_the_bit(tmp_path, monkeypatch, halves):
    if halves:
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
    rng = random.Random(7)
    with localcontext() as context:
        context.prec = 80  # the half-way decimals exactly
        words = random_words(rng, 60000)
    rows = [words[i:i + 3] for i in range(0, len(words), 3)]
    text = "".join(f"v {' '.join(row)}\n" for row in rows) + "f 1 2 3\n"
    path = tmp_path / "numbers.obj"
    path.write_text(text)
    arrays, _ = obj.parse(path, path.read_bytes())
    want = np.array([[float(w) for w in row] for row in rows])
    got = arrays["vertices"]
    assert got.view(np.int64).tolist() == want.view(np.int64).tolist()  # the same bits: -0.0 and subnormals too


def faces_reference(lines: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, 3) v, vt, vn of each triangle (1-based as written, 0 none), a fan per polygon, read word by word."""
    out = []
    for line in lines:
        words = line.split("#")[0].split()[1:]
        corners = []
        for word in words:
            parts = word.split("/")
            corners.append([int(x) if x else 0 for x in parts] + [0] * (3 - len(parts)))
        for k in range(1, len(corners) - 1):
            out.append([corners[0], corners[k], corners[k + 1]])
    table = np.array(out, dtype=np.int64)  # (T, 3, 3)
    return table[:, :, 0], table[:, :, 1], table[:, :, 2]


@pytest.mark.parametrize("halves", [False, True])
@pytest.mark.parametrize("sides", [[3], [4], [3, 3, 3, 4, 5, 8]])  # triangles or quads only: one pass; mixed: two
@pytest.mark.parametrize("form", ["v", "v/vt", "v/vt/vn", "v//vn"])
def test_faces_equal_a_word_by_word_reading(tmp_path, monkeypatch, form, sides, halves):
    if halves:
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
    rng = random.Random(form)
    n = 50
    head = [f"v {i} {i % 7} {i % 3}" for i in range(n)] + [f"vt {i / n} 0.5" for i in range(n)] + \
        [f"vn 0 0 {1 + i}" for i in range(n)]
    faces = []
    for _ in range(400):
        c = rng.choice(sides)
        words = []
        for _ in range(c):
            v, t, m = (rng.randint(1, n) if rng.random() < 0.9 else -rng.randint(1, n) for _ in range(3))
            words.append({"v": f"{v}", "v/vt": f"{v}/{t}", "v/vt/vn": f"{v}/{t}/{m}", "v//vn": f"{v}//{m}"}[form])
        faces.append(rng.choice(["f ", "f\t", "  f "]) + rng.choice([" ", "\t", "  "]).join(words)
                     + rng.choice(["", " ", " # a comment", "#x", "\r"]))
    path = tmp_path / "faces.obj"
    path.write_bytes(("\n".join(head + faces) + "\n").encode())
    arrays, source = obj.parse(path, path.read_bytes())
    v, t, m = faces_reference(faces)
    # a negative index counts back from the face: -1 is the last element defined before it
    np.testing.assert_array_equal(arrays["triangles"], np.where(v < 0, n + v, v - 1))
    if "vn" in form:
        np.testing.assert_array_equal(source.corner_normals, np.where(m < 0, n + m, m - 1))
    else:
        assert (source.corner_normals == -1).all()
    if "vt" in form:
        uv = np.array([i / n for i in range(n)])[np.where(t < 0, n + t, t - 1)]
        np.testing.assert_array_equal(arrays["triangle_uvs"].reshape(-1, 3, 2)[:, :, 0], uv)
    else:
        assert arrays["triangle_uvs"] is None
    assert source.face_lines == len(faces)


@pytest.mark.parametrize("halves", [False, True])
@pytest.mark.parametrize("odd, error", [
    ("f 4 5 6 7", None), ("f 4/1 5/2 6/3", None), ("f 4//1 5//2 6//3", None), ("f 4/1/2 5/3/4 6/5/6", None),
    ("f 4 5 -6 # a comment", None), ("f\t4 5 6\r", None), ("f 4 5 6 7 8 9", None), ("f 4 5 6 7 8 9 1 2 3", None),
    ("f 4 5", "1 face has fewer than 3 vertices (first: line {line})"),
    ("f 4/1 5 6", "line {line}: the corners of a face must all have the same form"),
    ("f 4/ 5/ 6/", "line {line}: a face line does not hold 3 corners of 2 indices"),
    ("f 4 5 6x", "line {line}: a face line holds something that is not an index"),
])
@pytest.mark.parametrize("form", ["{} {} {}", "{}//1 {}//1 {}//1", "{} {} {} 9"])
def test_a_line_unlike_the_first_reads_as_any_file(tmp_path, monkeypatch, form, odd, error, halves):
    """Triangles of the first line's form are read in one pass; a line that is not one, first, between or last,
    gives the faces of a word-by-word reading (the two passes), or the error naming its line."""
    if halves:
        monkeypatch.setattr(numbers, "THREADED_ROWS", 1)
    head = [f"v {i} 0 {i % 3}" for i in range(9)] + [f"vt {i / 9} 0.5" for i in range(9)] + ["vn 0 0 1"] * 9
    plain = ["f " + form.format(1 + i % 7, 2 + i % 7, 3 + i % 7) for i in range(40)]
    for at in (0, 17, 40):
        faces = plain[:at] + [odd] + plain[at:]
        path = tmp_path / f"odd{at}.obj"
        path.write_bytes(("\n".join(head + faces) + "\n").encode())
        if error is not None:
            with pytest.raises(InputError, match=re.escape(error.format(line=len(head) + at + 1))):
                obj.parse(path, path.read_bytes())
            continue
        v = faces_reference(faces)[0]
        np.testing.assert_array_equal(obj.parse(path, path.read_bytes())[0]["triangles"], np.where(v < 0, 9 + v, v - 1))


@pytest.mark.parametrize("text, message", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3x\n", r"line 4: a face line holds something that is not an index"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/ 2/ 3/\n", r"line 4: a face line does not hold 3 corners of 2 indices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n", r"line 4: a face line holds something that is not an"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\nf 1 2 3 4 5/5\n", r"1 face has fewer than 3 vertices \(first: line 4\)"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n\nf 1 2/2 3\n\nf 1 2\n", r"line 6: the corners of a face must"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r"1 face names a vertex outside 1..3"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"vertex index 0"),
    ("v 0 0 0\nv 1 0 zero\nv 0 1 0\nf 1 2 3\n", r"line 2: a 'v' line holds something that is not a number"),
    ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", r"line 2: a 'v' line needs 3 numbers; got 2"),
])
def test_malformed_lines_are_one_line_naming_the_line(tmp_path, text, message):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_mesh(path)


def test_materials_are_numbered_in_order_of_first_use(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 0 0\nnewmtl b\nKd 0 1 0\nnewmtl c\nKd 0 0 1\n")
    text = ("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl c\nusemtl b\nf 1 2 3\nf 1 2 3\nusemtl a\nf 1 2 3\n"
            "usemtl b\nf 1 2 3\nusemtl c\n")
    (tmp_path / "m.obj").write_text(text)
    mesh = read_mesh(tmp_path / "m.obj")
    np.testing.assert_array_equal(mesh.triangle_material_ids, [0, 0, 1, 0])  # b, b, a, b: c names no face
    np.testing.assert_array_equal([t.reshape(-1)[:3] for t in mesh.textures], [[0, 255, 0], [255, 0, 0]])


def test_a_large_obj_reads_as_written(tmp_path):
    """A hundred thousand vertices with UVs and twice as many faces, as numpy writes them: the same mesh back."""
    rng = np.random.default_rng(3)
    V, T = 100_000, 200_000
    vertices = rng.normal(size=(V, 3)).round(6)
    triangles = rng.integers(0, V, size=(T, 3))
    with open(tmp_path / "big.obj", "w") as fh:
        np.savetxt(fh, vertices, fmt="v %.6f %.6f %.6f")
        np.savetxt(fh, vertices[:, :2], fmt="vt %.6f %.6f")
        np.savetxt(fh, np.repeat(triangles + 1, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
    mesh = read_mesh(tmp_path / "big.obj")
    np.testing.assert_array_equal(mesh.vertices, vertices)
    np.testing.assert_array_equal(mesh.triangles, triangles)
    np.testing.assert_array_equal(mesh.triangle_uvs.reshape(T, 3, 2), vertices[triangles, :2])


def test_numbers_beyond_the_fast_path_are_still_exact(tmp_path):
    """Words the compiled reader hands to Python: long mantissas, far exponents, nan is refused by the mesh."""
    path = tmp_path / "long.obj"
    words = ["0.12345678901234567890123", "1e-320", "123456789012345678901234567890", "1.5e300"]
    path.write_text(f"v {words[0]} {words[1]} {words[2]}\nv {words[3]} 0 0\nv 0 1 0\nf 1 2 3\n")
    arrays, _ = obj.parse(Path(path), path.read_bytes())
    assert arrays["vertices"][0].tolist() == [float(w) for w in words[:3]]
    assert arrays["vertices"][1, 0] == float(words[3])
