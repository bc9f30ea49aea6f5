"""The deployment commands (keypoints, deform, align, sample, demo): results, and exit 2 with one line on bad input.

They run in-process through ``kpd.cli.main`` with a torch-free toy bundle (helpers.make_toy_bundle) on real ModelNet
meshes; the shipped chair model is used where it exists.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import kpd, make_toy_bundle

from kpd.cli import build_parser, main
from kpd.io import Mesh, read_mesh, write_mesh
from kpd.runtime import Model


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> Path:
    return make_toy_bundle(tmp_path_factory.mktemp("bundles") / "bare.kpd", prior=False, template=False)


@pytest.fixture(scope="module")
def other_chair(data_dir) -> Path:
    return data_dir / "modelnet10" / "chair" / "test" / "chair_0891.ply"


def test_keypoints_printed_and_written(toy, chair_file, tmp_path, capsys):
    assert kpd("keypoints", toy, chair_file) == 0
    printed = json.loads(capsys.readouterr().out)
    expected = Model.load(toy).keypoints(read_mesh(chair_file))
    np.testing.assert_allclose(printed["keypoints"], expected, rtol=1e-12)
    assert printed["category"] == "toy" and printed["frame"] == "input"
    assert kpd("keypoints", toy, chair_file, "--out", tmp_path / "kp.json") == 0
    written = json.loads((tmp_path / "kp.json").read_text())
    assert written["keypoints"] == printed["keypoints"]
    assert kpd("keypoints", toy, chair_file, "--out", tmp_path / "kp.txt") == 0
    rows = (tmp_path / "kp.txt").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("000 ")


def test_zero_move_reproduces_the_input(toy, chair_file, tmp_path):
    out = tmp_path / "same.ply"
    assert kpd("deform", toy, chair_file, "--move", "0:0,0,0", "--out", out) == 0
    original, again = read_mesh(chair_file), read_mesh(out)
    np.testing.assert_array_equal(again.vertices, original.vertices)
    np.testing.assert_array_equal(again.triangles, original.triangles)


def test_scan_option(toy, chair_file, tmp_path):
    """--scan orients the input to the bundle's template first and maps results back onto the input."""
    from scipy.spatial.transform import Rotation

    mesh = read_mesh(chair_file)
    rotation = Rotation.from_euler("zyx", [70, 20, -30], degrees=True).as_matrix()
    scan = tmp_path / "scan.ply"
    write_mesh(scan, mesh.with_vertices(mesh.vertices @ rotation.T * 3 + 5))
    assert kpd("deform", toy, scan, "--scan", "--move", "0:0,0,0", "--out", tmp_path / "same.ply") == 0
    np.testing.assert_array_equal(read_mesh(tmp_path / "same.ply").vertices, read_mesh(scan).vertices)


def test_keypoints_of_a_turned_scan_follow_the_scan(chair_file, tmp_path, capsys):
    """The shipped chair model on a real chair and on the same chair lying on its side, turned, scaled and moved:
    with --scan (and the scan's up axis) the keypoints come back on the scan, where the chair's keypoints went."""
    from scipy.spatial.transform import Rotation

    def keypoints(*argv) -> np.ndarray:
        assert kpd("keypoints", "chair", *argv) == 0
        return np.array(json.loads(capsys.readouterr().out)["keypoints"])

    mesh = read_mesh(chair_file)
    upright = keypoints(chair_file)
    # z (the chair's up) -> x, then a turn of 50 degrees about the new up axis
    rotation = Rotation.from_euler("yx", [90, 50], degrees=True).as_matrix()  # extrinsic: y by 90, then x by 50
    assert np.allclose(rotation @ [0, 0, 1], [1, 0, 0])
    scan = tmp_path / "scan.ply"
    write_mesh(scan, mesh.with_vertices(mesh.vertices @ rotation.T * 3 + 5))
    found = keypoints(scan, "--scan", "--up", "x")
    expected = upright @ rotation.T * 3 + 5
    size = np.linalg.norm(np.ptp(mesh.vertices, axis=0)) * 3
    assert np.abs(found - expected).max() < 0.02 * size  # measured: 0.009
    # without --up the search is over all rotations, with the model's up axis as the support prior (as kpd scan)
    found = keypoints(scan, "--scan")
    assert np.abs(found - expected).max() < 0.04 * size  # measured: 0.027 (0.037 without the support prior)
    # without --scan the model sees a chair on its side: its keypoints are elsewhere
    unaligned = keypoints(scan)
    assert np.abs(unaligned - expected).max() > 0.1 * size


def textured_chair(path: Path) -> Mesh:
    """The procedural demo chair with per-corner UVs, a texture and vertex colours, written to ``path``."""
    from kpd.procedural import procedural_chair

    mesh = procedural_chair()
    t = len(mesh.triangles)
    uvs = np.random.default_rng(0).uniform(0, 1, (3 * t, 2))
    texture = np.random.default_rng(1).integers(0, 255, (8, 8, 3), dtype=np.uint8)
    mesh = Mesh(vertices=mesh.vertices, triangles=mesh.triangles, vertex_colors=mesh.vertex_colors,
                triangle_uvs=uvs, textures=[texture], triangle_material_ids=np.zeros(t, np.int64))
    write_mesh(path, mesh)
    return read_mesh(path)


def test_deform_keeps_topology_uvs_and_colours(toy, tmp_path):
    source = tmp_path / "chair.ply"
    from kpd.procedural import procedural_chair

    write_mesh(source, procedural_chair())
    original = read_mesh(source)
    out = tmp_path / "moved.ply"
    assert kpd("deform", toy, source, "--move", "1:0,0,4", "--move", "2:1,0,0", "--out", out) == 0
    moved = read_mesh(out)
    np.testing.assert_array_equal(moved.triangles, original.triangles)
    np.testing.assert_allclose(moved.vertex_colors, original.vertex_colors, atol=1 / 255)
    assert np.abs(moved.vertices - original.vertices).max() > 0.1
    # the same edit through the API
    model = Model.load(toy)
    rig = model.rig(original)
    np.testing.assert_allclose(moved.vertices, rig.deform(rig.moved({1: [0, 0, 4], 2: [1, 0, 0]})), atol=1e-9)
    # UVs and the texture survive an OBJ round trip through deform
    obj = tmp_path / "textured.obj"
    textured = textured_chair(obj)
    assert kpd("deform", toy, obj, "--move", "0:0,0,2", "--out", tmp_path / "textured_out.obj") == 0
    result = read_mesh(tmp_path / "textured_out.obj")
    np.testing.assert_array_equal(result.triangles, textured.triangles)
    np.testing.assert_allclose(result.triangle_uvs, textured.triangle_uvs, atol=1e-6)
    assert len(result.textures) == 1 and np.array_equal(result.textures[0], textured.textures[0])


def test_deform_with_prior(toy, chair_file, tmp_path):
    out = tmp_path / "prior.ply"
    assert kpd("deform", toy, chair_file, "--move", "1:0,0,3", "--prior", "--out", out) == 0
    model = Model.load(toy)
    mesh = read_mesh(chair_file)
    rig = model.rig(mesh)
    targets = model.sync(rig, {1: rig.keypoints[1] + [0, 0, 3]})
    np.testing.assert_allclose(read_mesh(out).vertices, rig.deform(targets), atol=1e-9)
    plain = tmp_path / "plain.ply"
    assert kpd("deform", toy, chair_file, "--move", "1:0,0,3", "--out", plain) == 0
    assert not np.allclose(read_mesh(plain).vertices, read_mesh(out).vertices)


def test_deform_with_rig_still_works(toy, chair_file, tmp_path):
    rig = Model.load(toy).rig(read_mesh(chair_file))
    rig.save(tmp_path / "rig.npz")
    out = tmp_path / "out.ply"
    assert kpd("deform", "--rig", tmp_path / "rig.npz", "--move", "0:0,0,1", "--out", out) == 0
    np.testing.assert_allclose(read_mesh(out).vertices, rig.deform(rig.moved({0: [0, 0, 1]})), atol=1e-9)


def test_align(toy, chair_file, other_chair, tmp_path):
    out = tmp_path / "aligned.ply"
    assert kpd("align", toy, chair_file, other_chair, "--out", out, "--keypoints", tmp_path / "kp.json") == 0
    source = read_mesh(chair_file)
    aligned = read_mesh(out)
    assert aligned.triangles.shape == source.triangles.shape
    expected = Model.load(toy).align(source, read_mesh(other_chair))
    np.testing.assert_allclose(aligned.vertices, expected.vertices, atol=1e-9)
    record = json.loads((tmp_path / "kp.json").read_text())
    assert np.shape(record["target_keypoints"]) == (4, 3)


def test_sample_writes_variants_and_sheet(toy, chair_file, tmp_path):
    out = tmp_path / "variants"
    assert kpd("sample", toy, chair_file, "--n", "3", "--out", out) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["contact_sheet.png", "keypoints.json", "variant_000.ply", "variant_001.ply", "variant_002.ply"]
    record = json.loads((out / "keypoints.json").read_text())
    source = read_mesh(chair_file)
    for variant in record["variants"]:
        mesh = read_mesh(out / variant["file"])
        np.testing.assert_array_equal(mesh.triangles, source.triangles)
        assert np.abs(mesh.vertices - source.vertices).max() > 0
    from PIL import Image

    image = np.asarray(Image.open(out / "contact_sheet.png").convert("RGB"))
    assert image.shape[0] > 200 and (image < 200).any(axis=2).mean() > 0.02  # not blank
    assert kpd("sample", toy, chair_file, "--n", "2", "--out", out, "--force") == 0
    assert len(list(out.glob("variant_*"))) == 2  # replaced, not merged


def test_demo_with_a_given_model(toy, tmp_path, capsys):
    out = tmp_path / "demo"
    assert kpd("demo", "--model", toy, "--out", out) == 0
    assert sorted(p.name for p in out.iterdir()) == ["deformed.ply", "deformed_alone.ply", "demo.png", "input.ply",
                                                     "keypoints.json", "rig.npz"]
    before, after = read_mesh(out / "input.ply"), read_mesh(out / "deformed.ply")
    np.testing.assert_array_equal(before.triangles, after.triangles)
    record = json.loads((out / "keypoints.json").read_text())
    moved = record["moved"]
    np.testing.assert_array_equal(record["moved_with_prior"][moved], record["target"])
    assert "kpd deform" in capsys.readouterr().out
    bare = tmp_path / "bare_demo"
    assert kpd("demo", "--model", make_toy_bundle(tmp_path / "np.kpd", prior=False), "--out", bare) == 0
    assert not (bare / "deformed.ply").exists() and (bare / "deformed_alone.ply").is_file()


def test_demo_with_shipped_chair(tmp_path, capsys, monkeypatch):
    out = tmp_path / "demo"
    assert kpd("demo", "--out", out) == 0
    before, alone, synced = (read_mesh(out / f"{name}.ply") for name in ("input", "deformed_alone", "deformed"))
    width = np.ptp(before.vertices[:, :2], axis=0)
    assert (np.ptp(alone.vertices[:, :2], axis=0) > width * 1.02).any()  # a leg was pulled outward
    assert (np.ptp(synced.vertices[:, :2], axis=0) > width * 1.02).any()
    np.testing.assert_allclose(synced.vertex_colors, before.vertex_colors, atol=1 / 255)
    from PIL import Image

    image = np.asarray(Image.open(out / "demo.png").convert("RGB"))
    assert (image < 200).any(axis=2).mean() > 0.02
    # the suggested next command works and does what its output name says: the backrest rises, the feet stay put
    suggestion = [line for line in capsys.readouterr().out.splitlines() if line.startswith("next: kpd deform ")]
    assert len(suggestion) == 1
    monkeypatch.chdir(tmp_path)
    assert kpd(*suggestion[0].split()[2:]) == 0
    taller = read_mesh(tmp_path / "taller_back.ply").vertices
    height = np.ptp(before.vertices[:, 2])
    assert taller[:, 2].max() > before.vertices[:, 2].max() + 0.1 * height
    assert abs(taller[:, 2].min() - before.vertices[:, 2].min()) < 0.02 * height


def test_bench_times_the_deployment_path(toy, chair_file, tmp_path):
    out = tmp_path / "bench.json"
    assert kpd("bench", toy, "--vertices", "2000", "--mesh", chair_file, "--repeats", "3", "--out", out) == 0
    result = json.loads(out.read_text())
    assert result["K"] == Model.load(toy).num_keypoints
    (row,) = result["meshes"]  # --mesh replaces the procedural chairs
    assert row["vertices"] == len(read_mesh(chair_file).vertices)
    assert all(row[key] > 0 for key in ("predict_ms", "bind_ms", "edit_ms"))
    assert kpd("bench", toy, "--vertices", "3000", "--repeats", "3", "--out", out, "--force") == 0
    (row,) = json.loads(out.read_text())["meshes"]
    assert abs(row["vertices"] - 3000) < 600  # procedural chair near the asked size


# --- bad input: exit 2, one line, nothing written ---------------------------------------------------------------------

def _nan_mesh(path: Path) -> Path:
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\nnan 1 0\n0 0 1\n"
                    "3 0 1 2\n")
    return path


def _tampered(toy: Path, folder: Path) -> Path:
    copy = folder / "tampered.kpd"
    shutil.copytree(toy, copy)
    data = bytearray((copy / "keypoints.onnx").read_bytes())
    data[-10] ^= 1
    (copy / "keypoints.onnx").write_bytes(bytes(data))
    return copy


BAD = [
    ("keypoints", lambda e: [e.toy, e.work / "missing.ply"]),
    ("keypoints", lambda e: [e.toy, _nan_mesh(e.work / "nan.ply")]),
    ("keypoints", lambda e: [e.work / "nothing.kpd", e.chair]),
    ("keypoints", lambda e: [_tampered(e.toy, e.work), e.chair, "--out", e.work / "kp.json"]),
    ("keypoints", lambda e: [e.toy, e.chair, "--out", e.work / "kp.csv"]),
    ("keypoints", lambda e: [e.toy, e.chair, "--out", e.existing]),
    ("keypoints", lambda e: [e.toy, e.chair, "--out", e.work / "no" / "kp.json"]),
    ("keypoints", lambda e: [e.bare, e.chair, "--scan", "--out", e.work / "kp.json"]),
    ("deform", lambda e: [e.toy, e.chair, "--move", "0:1,2", "--out", e.work / "o.ply"]),
    ("deform", lambda e: [e.toy, e.chair, "--move", "7:0,0,1", "--out", e.work / "o.ply"]),
    ("deform", lambda e: [e.toy, e.chair, "--move", "0:nan,0,1", "--out", e.work / "o.ply"]),
    ("deform", lambda e: [e.toy, e.chair, "--move", "0:0,0,1", "--out", e.work / "o.xyz"]),
    ("deform", lambda e: [e.toy, e.chair, "--rig", e.work / "r.npz", "--out", e.work / "o.ply"]),
    ("deform", lambda e: [e.toy, "--move", "0:0,0,1", "--out", e.work / "o.ply"]),
    ("deform", lambda e: [e.bare, e.chair, "--move", "0:0,0,1", "--prior", "--out", e.work / "o.ply"]),
    ("deform", lambda e: [e.toy, e.existing, "--move", "0:0,0,1", "--out", e.existing, "--force"]),
    ("deform", lambda e: [e.toy, _nan_mesh(e.work / "nan.ply"), "--out", e.work / "o.ply"]),
    ("align", lambda e: [e.toy, e.chair, e.work / "missing.ply", "--out", e.work / "o.ply"]),
    ("align", lambda e: [e.toy, e.empty, e.chair, "--out", e.work / "o.ply"]),
    ("sample", lambda e: [e.toy, e.chair, "--n", "0", "--out", e.work / "v"]),
    ("sample", lambda e: [e.bare, e.chair, "--out", e.work / "v"]),
    ("sample", lambda e: [e.toy, e.chair, "--format", "xyz", "--out", e.work / "v"]),
    ("demo", lambda e: ["--model", e.toy, "--out", e.existing]),
    ("demo", lambda e: ["--model", e.work / "nothing.kpd", "--out", e.work / "d"]),
    ("demo", lambda e: ["--model", e.toy, "--mesh", e.empty, "--out", e.work / "d"]),
    ("bench", lambda e: [e.toy, "--vertices", "5", "--out", e.work / "b.json"]),
    ("bench", lambda e: [e.toy, "--mesh", e.work / "missing.ply", "--repeats", "1", "--out", e.work / "b.json"]),
    ("bench", lambda e: [e.toy, "--repeats", "0"]),
    ("bench", lambda e: [e.toy, "--out", e.existing]),
]


class _Env:
    def __init__(self, work: Path, toy: Path, bare: Path, chair: Path) -> None:
        self.work, self.toy, self.bare, self.chair = work, toy, bare, chair
        self.existing = work / "existing.ply"
        shutil.copy(chair, self.existing)
        self.empty = work / "empty.obj"
        self.empty.write_text("")


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case", range(len(BAD)), ids=[f"{c}-{i}" for i, (c, _) in enumerate(BAD)])
def test_bad_input_exits_2_with_one_line(case, toy, bare, chair_file, tmp_path, capfd):
    command, make = BAD[case]
    env = _Env(tmp_path, toy, bare, chair_file)
    argv = [command, *map(str, make(env))]
    before = _snapshot(tmp_path)
    assert main(argv) == 2, argv
    out, err = capfd.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"kpd {command}: error: "), err
    assert out == ""
    assert _snapshot(tmp_path) == before  # nothing written, nothing replaced


_PROGRAM = """
import atexit, sys, threading, time
from pathlib import Path
from kpd.cli import main

out = Path(sys.argv[1])
atexit.register(lambda: (out / "atexit").write_text("ran"))

def slow():  # a thread still at work when the command ends
    time.sleep(0.5)
    (out / "thread").write_text("done")

threading.Thread(target=slow).start()
sys.argv = ["kpd", *sys.argv[2:]]
sys.exit(main())
"""


@pytest.mark.parametrize("argv, status", [(["keypoints", "--help"], 0), (["keypoints", "chair", "missing.ply"], 2)])
def test_the_program_ends_as_the_interpreter_would_without_its_teardown(argv, status, tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _PROGRAM, str(tmp_path), *argv], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert done.returncode == status
    assert (tmp_path / "thread").read_text() == "done"  # waited for
    assert (tmp_path / "atexit").read_text() == "ran"
    if status == 0:
        assert "example:\n  kpd keypoints " in done.stdout  # the whole help, flushed
    else:
        assert done.stderr == "kpd keypoints: error: missing.ply: no such file\n"


def _kpd_with_stderr_on_a_terminal(argv: list, env: dict) -> tuple[int, str]:
    """``kpd argv`` in a fresh process whose standard error is a pseudo-terminal: its exit status and what it wrote
    there."""
    import os
    import pty
    import subprocess
    import sys

    controller, terminal = pty.openpty()
    try:
        process = subprocess.Popen([sys.executable, "-m", "kpd.cli", *map(str, argv)], stdout=subprocess.DEVNULL,
                                   stderr=terminal, env=env)
        os.close(terminal)
        terminal = None
        written = b""
        while True:
            try:
                chunk = os.read(controller, 4096)
            except OSError:  # the process ended and closed its side
                break
            if not chunk:
                break
            written += chunk
        return process.wait(timeout=300), written.decode()
    finally:
        os.close(controller)
        if terminal is not None:
            os.close(terminal)


def test_a_first_run_says_once_that_it_compiles_and_a_cached_run_says_nothing(toy, chair_file, tmp_path):
    import os
    import subprocess
    import sys

    from kpd._compiled import COMPILING

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))  # numba's cache, empty: a first run
    status, written = _kpd_with_stderr_on_a_terminal(["keypoints", toy, chair_file], env)
    assert status == 0
    assert written.replace("\r\n", "\n") == f"note: {COMPILING}\n"
    assert any((tmp_path / "numba-cache").rglob("*.nbi"))  # the kernels were compiled and cached
    status, written = _kpd_with_stderr_on_a_terminal(["keypoints", toy, chair_file], env)
    assert status == 0 and written == ""  # loaded from the cache
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "another-cache")
    piped = subprocess.run([sys.executable, "-m", "kpd.cli", "keypoints", str(toy), str(chair_file)], env=env,
                           capture_output=True, text=True, timeout=300)
    assert piped.returncode == 0 and piped.stderr == ""  # not a terminal (a log, a test): no note


def test_version(capsys):
    from importlib.metadata import version

    from kpd import __version__

    assert __version__ == version("kpd")  # the package's and the installed distribution's: one source
    assert "version" in pyproject()["project"]["dynamic"] and "version" not in pyproject()["project"]
    with pytest.raises(SystemExit) as stopped:  # argparse's version action ends as --help does
        build_parser().parse_args(["--version"])
    assert stopped.value.code == 0
    assert capsys.readouterr().out == f"kpd {__version__}\n"
    assert kpd("--version") == 0


def pyproject() -> dict:
    import tomllib

    with open(Path(__file__).resolve().parents[1] / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)
