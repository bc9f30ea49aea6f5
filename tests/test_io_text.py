"""kpd.io.text: numbers written by compiled code are the bytes Python's ``%`` writes (millions of random float64 over
every magnitude, the hard cases, real meshes' coordinates), splicing and line counting equal their plain twins, and
the OBJ writer built on them writes the bytes the plain Python writer wrote."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.errors import InputError
from kpd.io import Mesh, obj, read_mesh, text, write_mesh
from kpd.triangles import turned_normals

SHAPENET = "shapenetcore_obj"


def assert_rows(values, precision=9, **options):
    """float_rows and its plain twin give the same bytes and row offsets; a failure names the first row apart."""
    got, offsets = text.float_rows(values, precision, **options)
    want = text.float_rows_reference(values, precision, **options)
    if got.tobytes() != b"".join(want):
        rows = [got[offsets[i]:offsets[i + 1]].tobytes() for i in range(len(want))]
        i = next(i for i in range(len(want)) if rows[i] != want[i])
        pytest.fail(f"row {i}, values {np.asarray(values)[i].tolist()!r}: {rows[i]!r} instead of {want[i]!r}")
    np.testing.assert_array_equal(np.diff(offsets), [len(row) for row in want])


def rows_of_three(values) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64).ravel()
    return np.resize(values, (len(values) + 2) // 3 * 3).reshape(-1, 3)


def random_bits(rng, n) -> np.ndarray:
    """n float64 of uniformly random bit patterns: every exponent alike, NaN and inf among them."""
    return rng.integers(0, 2**64, n, dtype=np.uint64).view(np.float64)


def log_uniform(rng, n, low=-330, high=308) -> np.ndarray:
    return rng.choice([-1.0, 1.0], n) * rng.uniform(1, 10, n) * 10.0 ** rng.integers(low, high, n).astype(float)


def halfway(rng, n, digits=9, low=-320, high=300) -> np.ndarray:
    """The float64 nearest ``d.dddddddd5 10^k`` (a decimal half-way point at ``digits`` digits) and both neighbours."""
    mantissas = rng.integers(10 ** (digits - 1), 10**digits, n).tolist()
    exponents = rng.integers(low, high, n).tolist()
    nearest = np.array([float(f"{d}5e{k}") for d, k in zip(mantissas, exponents)])
    return np.concatenate([nearest, np.nextafter(nearest, np.inf), np.nextafter(nearest, -np.inf)])


def exact_ties(rng, n) -> np.ndarray:
    """Values whose 10th significant digit is an exact 5 and nothing follows: ten-digit integers ending in 5, nine
    digits and a half, and float32 values with few bits (k / 2^j) that end there."""
    integers = rng.integers(10**8, 10**9, n) * 10 + 5
    halves = rng.integers(10**8, 10**9, n) + 0.5
    dyadic = rng.integers(1, 2**20, n) / 2.0 ** rng.integers(1, 30, n)
    return np.concatenate([integers.astype(float), halves, -halves, dyadic, integers * 10.0**rng.integers(1, 6, n)])


def nines(rng, step, exponents, n=100_000) -> np.ndarray:
    """Values just below a power of ten, ``10 - k step`` times ``10^e``: most round up to the next power."""
    return (10 - rng.integers(1, 10**4, n) * step) * 10.0 ** rng.integers(-exponents, exponents, n)


HARD = [0.0, -0.0, 1.0, -1.0, 0.5, 5e-324, -5e-324, 2.2250738585072014e-308, 2.225073858507201e-308,
        1.7976931348623157e308, -1.7976931348623157e308, 9.99999999951, 9.9999999995, 9.99999999949999, 99999999.95,
        999999999.5, 999999999.4999999, 1e-5, 1.0000000005, 0.12345678950000001, 0.1234567895, 1000000005.0,
        1000000015.0, 123456789.5, 123456788.5, 1e20, 1e21, 1e16, 123456789.0, 1234567890.0, 0.0001, 0.00001,
        0.000123456789, 0.0000123456789, 1e-4 - 1e-20, 9.9999999996e-5, 100000000.0, 1e9 - 0.5, 1e9 - 1,
        float("nan"), -float("nan"), float("inf"), -float("inf"), 3.0000000000000004, 0.30000000000000004]


def test_hard_cases():
    powers = np.array([float(f"1e{k}") for k in range(-323, 309)])
    values = np.concatenate([HARD, powers, np.nextafter(powers, 0), np.nextafter(powers, np.inf), -powers,
                             9.999999995 * powers[:-1], np.nextafter(9.999999995 * powers[:-1], 0)])
    for precision in (6, 9):
        assert_rows(rows_of_three(values), precision)


@pytest.mark.parametrize("kind", ["bits", "magnitudes", "coordinates", "halfway", "ties", "subnormal", "nines"])
def test_millions_of_random_values_are_written_as_python_writes_them(kind):
    rng = np.random.default_rng(sorted(["bits", "magnitudes", "coordinates", "halfway", "ties", "subnormal",
                                        "nines"]).index(kind))
    values = {
        "bits": lambda: random_bits(rng, 900_000),
        "magnitudes": lambda: log_uniform(rng, 600_000),
        "coordinates": lambda: rng.standard_normal(600_000) * 10.0 ** rng.integers(-6, 6, 600_000),
        "halfway": lambda: np.concatenate([halfway(rng, 150_000), halfway(rng, 50_000, 6)]),
        "ties": lambda: exact_ties(rng, 60_000),
        "subnormal": lambda: rng.integers(1, 2**52, 300_000, dtype=np.int64).view(np.float64) * rng.choice([-1, 1]),
        "nines": lambda: np.concatenate([nines(rng, 1e-13, 300), nines(rng, 1e-9, 30)]),
    }[kind]()
    assert_rows(rows_of_three(values), 9)
    if kind in ("coordinates", "halfway", "ties", "nines"):
        assert_rows(rows_of_three(values[: len(values) // 2]), 6)


@pytest.mark.parametrize("precision", [1, 2, 3, 5, 7, 8, 10, 12, 15])
def test_every_precision(precision):
    rng = np.random.default_rng(precision)
    values = np.concatenate([random_bits(rng, 30_000), log_uniform(rng, 30_000), halfway(rng, 5000, precision),
                             HARD])
    assert_rows(rows_of_three(values), precision)


def test_real_meshes_coordinates(data_dir):
    arrays = []
    for name in ("scans/sneaker.ply", "modelnet10/chair/test/chair_0890.ply",
                 "scans/ycb/banana/textured_simple_reoriented.obj"):
        mesh = read_mesh(data_dir / name)
        arrays += [mesh.vertices, mesh.vertices * 1.01, mesh.vertices.astype(np.float32).astype(np.float64)]
        arrays += [a for a in (mesh.vertex_normals, mesh.vertex_colors) if a is not None]
        if mesh.triangle_uvs is not None:
            arrays.append(rows_of_three(mesh.triangle_uvs))
    for path in sorted((data_dir / SHAPENET).glob("*/*/models/model_normalized.obj")):
        mesh = read_mesh(path)
        arrays += [mesh.vertices, mesh.vertices * 1.01]
    values = np.concatenate(arrays)
    assert len(values) > 300_000
    assert_rows(values, 9)
    assert_rows(values, 6)


def test_values_near_a_tie_go_to_python_on_a_second_pass():
    rng = np.random.default_rng(11)
    values = rows_of_three(np.concatenate([log_uniform(rng, 30_000, -30, 30), HARD, exact_ties(rng, 1000)]))
    got = text._rows(values, 9, b"v ", b"\n", None, 0.5)[0]  # every value but the exact ties: Python's
    assert got.tobytes() == b"".join(text.float_rows_reference(values, prefix=b"v "))


def test_two_threads_write_what_one_thread_writes(monkeypatch):
    rng = np.random.default_rng(12)
    near = rows_of_three(np.concatenate([log_uniform(rng, 29_997, -30, 30), HARD, exact_ties(rng, 1000)]))
    assert len(near) % 2  # halves of unequal length
    tails = [b"" if i % 3 else b"%d 0.5" % i for i in range(len(near))]
    integers_first = np.concatenate([rng.integers(-999, 999, near.shape), near])  # tie 0.5: its second half to Python
    cases = [(near, 9, b"v ", b"\n", None), (integers_first, 9, b"v ", b"\n", None), (near, (9, 6, 3), b"", b"", tails)]
    single = [text._rows(*case, tie) for case in cases for tie in (text._TIE, 0.5)]
    monkeypatch.setattr(text, "_THREADED_ROWS", 2)
    monkeypatch.setattr(text.os, "cpu_count", lambda: 2)
    threaded = [text._rows(*case, tie) for case in cases for tie in (text._TIE, 0.5)]
    for (want, want_offsets), (got, offsets) in zip(single, threaded):
        assert got.tobytes() == want.tobytes()
        np.testing.assert_array_equal(offsets, want_offsets)
    assert_rows(near, (9, 6, 3), prefix=b"v ", tails=tails)


def test_per_column_precisions_prefixes_and_tails():
    rng = np.random.default_rng(2)
    values = rng.standard_normal((5000, 6)) * 10.0 ** rng.integers(-8, 8, (5000, 6))
    tails = [b"" if i % 3 else b"1 0.5 0.25" for i in range(len(values))]
    assert_rows(values, (9, 9, 9, 6, 6, 6), prefix=b"v ", suffix=b"", tails=tails)
    assert_rows(values[:, :2], 9, prefix=b"vt ")
    assert_rows(values[:, :1], 3, suffix=b" 255\n")
    assert_rows(np.zeros((0, 3)))
    for bad in (0, 16, (9, 9)):
        with pytest.raises(InputError, match="precision must be one number or 3, each in 1..15"):
            text.float_rows(values[:, :3], bad)
    with pytest.raises(InputError, match=r"values must have shape \(n, k\); got \(6,\)"):
        text.float_rows(values[0])


@pytest.mark.parametrize("form", ["v", "v/vt", "v//vn", "v/vt/vn"])
def test_index_rows_are_python_s(form):
    rng = np.random.default_rng(len(form))
    corners = rng.integers(0, 2**31, (3000, 3)) // 10 ** rng.integers(0, 10, (3000, 3))
    uv = rng.integers(-5, 2**62, (3000, 3)) if "vt" in form else None
    normal = corners[::-1].copy() if "vn" in form else None
    for prefix, base in ((b"f ", 1), (b"3 ", 0), (b"", 7)):
        options = {"prefix": prefix, "base": base, "uv": uv, "normal": normal}
        assert text.index_rows(corners, **options).tobytes() == text.index_rows_reference(corners, **options)
    quads = rng.integers(0, 10**6, (100, 4))
    assert text.index_rows(quads).tobytes() == text.index_rows_reference(quads)
    assert text.index_rows(np.array([[0, -1, -123456789012]]), base=0).tobytes() == b"f 0 -1 -123456789012\n"


def test_blocks_are_written_a_chunk_at_a_time(monkeypatch):
    rng = np.random.default_rng(4)
    a, b = rng.standard_normal((100, 3)), rng.random((100, 3))
    corners, uv = rng.integers(0, 1000, (100, 3)), rng.integers(0, 1000, (100, 3))
    whole = io.BytesIO()
    text.write_float_rows(whole, [a, b], (9, 9, 9, 6, 6, 6), prefix=b"v ")
    text.write_index_rows(whole, corners, uv=uv, normal=corners)
    monkeypatch.setattr(text, "_ROWS", 7)
    pieces = io.BytesIO()
    text.write_float_rows(pieces, [a, b], (9, 9, 9, 6, 6, 6), prefix=b"v ")
    text.write_index_rows(pieces, corners, uv=uv, normal=corners)
    want = b"".join(text.float_rows_reference(np.hstack([a, b]), (9, 9, 9, 6, 6, 6), prefix=b"v "))
    want += text.index_rows_reference(corners, uv=uv, normal=corners)
    assert whole.getvalue() == pieces.getvalue() == want


def random_streams(rng, size: int, count: int):
    """Non-overlapping spans of a ``size``-byte text dealt to ``count`` streams, each with texts of 0-40 bytes."""
    cuts = np.sort(rng.choice(size + 1, 2 * (size // 10), replace=False)).reshape(-1, 2)
    which = rng.integers(0, count, len(cuts))
    streams = []
    for s in range(count):
        spans = cuts[which == s]
        pieces = [bytes(rng.integers(65, 91, rng.integers(0, 40)).astype(np.uint8)) for _ in range(len(spans))]
        streams.append((spans, *text.joined(pieces)))
    return streams


@pytest.mark.parametrize("chunk", [1 << 24, 64])
def test_splicing_equals_its_plain_twin(monkeypatch, chunk):
    monkeypatch.setattr(text, "_CHUNK", chunk)
    rng = np.random.default_rng(chunk)
    for size, count in ((1, 1), (100, 1), (5000, 2), (20000, 3)):
        data = bytes(rng.integers(97, 123, size).astype(np.uint8))
        streams = random_streams(rng, size, count)
        out = io.BytesIO()
        last = text.write_spliced(out, data, streams)
        assert out.getvalue() == text.splice_reference(data, streams)
        assert last == out.getvalue()[-1:]
    edges = [(np.array([[0, 3], [7, 10]]), *text.joined([b"", b"ab\n"]))]
    out = io.BytesIO()
    assert text.write_spliced(out, b"0123456789", edges) == b"\n" and out.getvalue() == b"3456ab\n"


PIECES = [b"v", b"vt", b"vn", b"f", b"fo", b"u", b" ", b"\t", b"\n", b"\r", b"\r\n", b"#", b"1", b"x",
          b"v 1 2 3\n", b"f 1 2 3\n", b"a long comment line that crosses chunks\n"]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from(PIECES), max_size=60), st.sampled_from([8, 16, 64, 1 << 24]))
def test_line_counts_equal_a_line_by_line_reading_and_the_reader(tmp_path_factory, pieces, chunk):
    data = b"".join(pieces)
    path = tmp_path_factory.mktemp("count") / "lines.obj"
    path.write_bytes(data)
    old = text._CHUNK
    text._CHUNK = chunk
    try:
        got = text.count_obj_lines(path)
    finally:
        text._CHUNK = old
    assert got == text.count_obj_lines_reference(data)
    if data:
        kind = obj._scan(data)[3]
        assert got[:2] == (int((kind == 1).sum()), int((kind == 4).sum()))


# --- the OBJ writer: the bytes the plain Python writer wrote ----------------------------------------------------------


def arrays_reference(mesh: Mesh, stem: str) -> bytes:
    """The OBJ text kpd's writer wrote from a mesh's arrays with Python's % per row (before kpd.io.text)."""
    from kpd.grouping import first_occurrence_groups

    T = len(mesh.triangles)
    out = [b"# written by kpd\n"]
    materials = bool(mesh.textures)
    if materials:
        out.append(f"mtllib {stem}.mtl\n".encode())
    v = [b"%.9g %.9g %.9g" % tuple(r) for r in mesh.vertices.tolist()]
    if mesh.vertex_colors is not None:
        v = [t + b" %.6g %.6g %.6g" % tuple(c) for t, c in zip(v, mesh.vertex_colors.tolist())]
    out.append(b"".join(b"v " + t + b"\n" for t in v))
    uv_index = None
    mask = np.ones(T, dtype=bool) if mesh.triangle_uv_mask is None else mesh.triangle_uv_mask
    if mesh.triangle_uvs is not None and mask.any():
        corners = mesh.triangle_uvs.reshape(T, 3, 2)[mask].reshape(-1, 2)
        first, index = first_occurrence_groups(corners)
        out.append(b"".join(b"vt %.9g %.9g\n" % (a, b) for a, b in corners[first].tolist()))
        uv_index = np.full((T, 3), -1, dtype=np.int64)
        uv_index[mask] = index.reshape(-1, 3)
    if mesh.vertex_normals is not None:
        out.append(b"".join(b"vn %.9g %.9g %.9g\n" % tuple(r) for r in mesh.vertex_normals.tolist()))
    ids = mesh.triangle_material_ids
    if materials and ids is None:
        ids = np.zeros(T, dtype=np.int64)
    has_uv = np.zeros(T, dtype=bool) if uv_index is None else uv_index[:, 0] >= 0
    key = has_uv.astype(np.int64) if ids is None else ids * 2 + has_uv
    cuts = np.concatenate([[0], np.flatnonzero(np.diff(key)) + 1, [T]]).tolist()
    normals = mesh.vertex_normals is not None
    tri = mesh.triangles + 1
    lines, current = [], None
    for a, b in zip(cuts[:-1], cuts[1:]):
        if materials and ids[a] != current:
            current = int(ids[a])
            lines.append(f"usemtl material_{current}".encode())
        v = tri[a:b]
        if has_uv[a]:
            t = uv_index[a:b] + 1
            table, form = (np.stack([v, t, v], axis=2), b"%d/%d/%d") if normals else (np.stack([v, t], axis=2),
                                                                                        b"%d/%d")
        elif normals:
            table, form = np.stack([v, v], axis=2), b"%d//%d"
        else:
            table, form = v, b"%d"
        row = b"f " + b" ".join([form] * 3)
        lines.append(b"\n".join(row % tuple(r) for r in table.reshape(b - a, -1).tolist()))
    out.append(b"\n".join(lines) + b"\n")
    return b"".join(out)


def source_reference(mesh: Mesh, stem: str) -> bytes:
    """The OBJ text kpd's writer wrote for a moved mesh read from an OBJ: the file's own text with its ``v`` and
    referenced ``vn`` lines formatted by Python's %, its ``mtllib`` lines naming the copies (before kpd.io.text)."""
    source = mesh._source
    libs, _ = obj._source_companions(stem, source)
    edits = []
    rows = [b"%.9g %.9g %.9g" % tuple(r) for r in mesh.vertices.tolist()]
    tails = source.v_tails or [b""] * len(rows)
    edits += [(s, e, b"v " + t + (b" " + tail if tail else b"")) for (s, e), t, tail in
              zip(source.v_spans.tolist(), rows, tails)]
    if len(source.vn_spans):
        normals = turned_normals(source.vertices, mesh.vertices, mesh.triangles, source.corner_normals,
                                 source.normals)
        referenced = np.zeros(len(normals), dtype=bool)
        referenced[source.corner_normals[source.corner_normals >= 0]] = True
        edits += [(s, e, b"vn %.9g %.9g %.9g" % tuple(n)) for (s, e), n, r in
                  zip(source.vn_spans.tolist(), normals.tolist(), referenced) if r]
    for start, end, names in source.libraries:
        files = [libs[lib][0] for _, lib in obj._library_files(source.path, names) if lib is not None]
        edits.append((start, end, ("mtllib " + " ".join(files)).encode() if files else
                      b"# mtllib " + names.encode() + b" (missing when kpd read the file)"))
    parts, at = [], 0
    for start, end, new in sorted(edits):
        parts += [source.data[at:start], new]
        at = end
    out = b"".join(parts) + source.data[at:]
    return out if out.endswith(b"\n") else out + b"\n"


def shapenet_models(data_dir) -> list[Path]:
    return sorted((data_dir / SHAPENET).glob("*/*/models/model_normalized.obj"))


def test_obj_written_from_arrays_is_the_plain_writer_s_bytes(data_dir, tmp_path):
    rng = np.random.default_rng(0)
    cases = [read_mesh(data_dir / "scans/sneaker.ply")]
    for path in shapenet_models(data_dir)[::4]:
        mesh = read_mesh(path)
        T = len(mesh.triangles) - 1  # another topology: written from the arrays
        uvs = None if mesh.triangle_uvs is None else mesh.triangle_uvs[: 3 * T]
        mask = None if uvs is None else rng.random(T) < 0.8
        cases.append(Mesh(mesh.vertices * 1.01, mesh.triangles[:T], vertex_normals=mesh.vertex_normals,
                          vertex_colors=rng.random(mesh.vertices.shape), triangle_uvs=uvs, textures=mesh.textures,
                          triangle_material_ids=None if mesh.triangle_material_ids is None else
                          mesh.triangle_material_ids[:T], triangle_uv_mask=mask))
    assert any(m.textures and m.triangle_uvs is not None and m.vertex_normals is not None for m in cases)
    for i, mesh in enumerate(cases):
        out = tmp_path / f"a{i}.obj"
        write_mesh(out, mesh)
        assert out.read_bytes() == arrays_reference(mesh, out.stem), i


def test_obj_moved_in_its_own_structure_is_the_plain_writer_s_bytes(data_dir, tmp_path):
    models = shapenet_models(data_dir)
    assert models
    for i, path in enumerate(models):
        mesh = read_mesh(path)
        moved = mesh.with_vertices(mesh.vertices * 1.01 + [0, 0.25, 0])
        out = tmp_path / f"m{i}.obj"
        write_mesh(out, moved)
        assert out.read_bytes() == source_reference(moved, out.stem), path


def test_obj_with_vertex_tails_and_no_final_line_break(tmp_path):
    path = tmp_path / "t.obj"
    path.write_bytes(b"v 0 0 0 1 0 0\nv 1 0 0 0 1 0\n  v 0 1 0 0 0 1 # c\nvn 0 0 1\nf 1//1 2//1 3//1\nv 1 1 1 1 1 1")
    mesh = read_mesh(path)
    moved = mesh.with_vertices(mesh.vertices * 3 + 0.1)
    write_mesh(tmp_path / "out.obj", moved)
    assert (tmp_path / "out.obj").read_bytes() == source_reference(moved, "out")
