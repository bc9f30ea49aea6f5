"""Fault injection for every command that writes: failing disks, races, --force, damaged files and bad options.

Every fault case (:func:`assert_fault`) asserts exit status 2, exactly one line on stderr, no traceback, nothing left
behind in the folders involved (no partial output, no temporary file or folder) and every file that existed before
byte for byte unchanged. The environments are real where the machine allows it:

- a **full disk** is a small tmpfs filled to its last byte (as root; where mounting is not allowed, the one writer's
  fsync is patched to fail with ENOSPC);
- a **read-only folder** is a tmpfs remounted read-only (else a folder without write permission);
- **permission denied** is a folder without write permission (as root, the command runs without the capability to
  ignore permissions: ``setpriv --bounding-set -dac_override``);
- **races** are two real processes writing one output, and a file created at the output path while a command runs;
- **SIGKILL** kills a process in the middle of a write; the next command in that folder cleans up after it.

Commands run in-process through :func:`kpd.cli.main` (seconds each) on tiny procedural meshes, the torch-free toy
bundle of test_bundle and one tiny training run. Run them alone with ``pytest tests/test_faults.py``.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import kpd as helpers_kpd
from helpers import make_toy_bundle

from kpd.cli import main
from kpd.errors import InputError
from kpd.io import Mesh, write_mesh, write_points

REPO = Path(__file__).resolve().parents[1]
KPD = str(Path(sys.executable).with_name("kpd"))


# --- the contract -------------------------------------------------------------------------------------------------


def snapshot(*folders: Path) -> dict[str, str]:
    """sha256 of every file under the folders (hidden ones included), and every folder, by path."""
    state = {}
    for folder in folders:
        for root, dirs, files in os.walk(folder):
            for d in dirs:
                state[os.path.join(root, d)] = "folder"
            for f in files:
                p = os.path.join(root, f)
                with open(p, "rb") as fh:
                    state[p] = hashlib.sha256(fh.read()).hexdigest()
    return state


def kpd(capfd, *argv) -> tuple[int, str, str]:
    """:func:`helpers.kpd` with what it printed: (status, stdout, stderr)."""
    return helpers_kpd(*argv, capture=capfd)


def error_lines(err: str) -> list[str]:
    """The lines of stderr, progress bars (carriage-return redraws) reduced to what they end with."""
    return [s.rsplit("\r", 1)[-1] for s in err.split("\n") if s.rsplit("\r", 1)[-1].strip()]


def assert_fault(result: tuple[int, str, str], before: dict, *folders: Path, match: str) -> str:
    """Exit 2, one stderr line containing ``match``, no traceback, the folders exactly as ``before``."""
    code, _, err = result
    lines = error_lines(err)
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("kpd "), err
    assert "Traceback" not in err
    assert match in lines[0], lines[0]
    assert snapshot(*folders) == before, "files were left behind or changed"
    return lines[0]


# --- environments -------------------------------------------------------------------------------------------------


def _mount(folder: Path, options: str) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True)
    return result.returncode == 0


def _umount(folder: Path) -> None:
    subprocess.run(["umount", "-l", str(folder)], capture_output=True)


@pytest.fixture
def full_disk(tmp_path, monkeypatch):
    """A folder on a file system with no free byte, holding ``keep.txt`` (written before it filled up)."""
    folder = tmp_path / "full"
    folder.mkdir()
    mounted = _mount(folder, "size=512k")
    (folder / "keep.txt").write_text("kept\n")
    if mounted:
        with open(folder / "filler", "wb", buffering=0) as fh:  # fill the file system to its last byte
            for size in (1 << 16, 1 << 12, 1):
                try:
                    while True:
                        fh.write(b"\0" * size)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
    else:  # no tmpfs: the one writer's fsync fails as on a full disk
        import kpd.io.atomic as atomic

        def no_space(path):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

        monkeypatch.setattr(atomic, "_fsync", no_space)
    try:
        yield folder
    finally:
        if mounted:
            _umount(folder)


@pytest.fixture
def read_only(tmp_path, monkeypatch):
    """A read-only folder holding ``keep.txt``."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if _mount(folder, "size=64k"):
        (folder / "keep.txt").write_text("kept\n")
        subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=True)
        try:
            yield folder
        finally:
            _umount(folder)
        return
    (folder / "keep.txt").write_text("kept\n")
    folder.chmod(0o555)
    if os.geteuid() == 0:  # root ignores permission bits: the writer's folder check sees the folder as read-only
        import kpd.io.atomic as atomic

        real = os.access
        monkeypatch.setattr(atomic.os, "access", lambda p, mode: real(p, mode) and Path(p) != folder)
    yield folder
    folder.chmod(0o755)


# --- inputs -------------------------------------------------------------------------------------------------------


def textured(mesh: Mesh) -> Mesh:
    """The mesh with per-corner UVs from its x, z position and a 4x4 checker texture."""
    v = mesh.vertices[mesh.triangles.reshape(-1)]
    uv = (v[:, [0, 2]] - v[:, [0, 2]].min(0)) / np.ptp(v[:, [0, 2]], axis=0)
    checker = np.kron(np.indices((2, 2)).sum(0) % 2, np.ones((2, 2)))[..., None] * np.array([200, 60, 30])
    return Mesh(vertices=mesh.vertices, triangles=mesh.triangles, triangle_uvs=uv,
                textures=[checker.astype(np.uint8) + 40])


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """chair.ply (432 vertices), tex.obj (textured, with .mtl and PNG), toy.kpd, rig.npz, data/chair/ (8 chairs,
    for training: ``data --category chair``), flat/ (15 chairs: a flat folder whose carved test split has 2)."""
    from kpd.procedural import procedural_chair
    from kpd.runtime import Model

    root = tmp_path_factory.mktemp("inputs")
    os.chmod(root, 0o755)
    chair = procedural_chair(edge=4.0)
    write_mesh(root / "chair.ply", chair)
    write_mesh(root / "tex.obj", textured(chair))
    make_toy_bundle(root / "toy.kpd", template=False)  # no template: no frame warning for these chairs
    model = Model.load(root / "toy.kpd")
    model.rig(chair).save(root / "rig.npz")
    (root / "data" / "chair").mkdir(parents=True)
    (root / "flat").mkdir()
    for i in range(15):
        stretch = 1 + 0.05 * i * np.array([1.0, 0.5, -0.3])
        for folder in ("data/chair", "flat") if i < 8 else ("flat",):
            write_mesh(root / folder / f"c{i}.ply", chair.with_vertices(chair.vertices * stretch))
    return root


TINY_TRAIN = ("--category", "chair", "--keypoints", "4", "--iterations", "2", "--batch", "2", "--points", "64",
              "--samples", "1", "--save-every", "1", "--val-pairs", "0", "--processes", "1", "--threads", "1",
              "--quiet", "--warmup", "0")


@pytest.fixture(scope="module")
def tiny_run(inputs, tmp_path_factory) -> Path:
    """A two-iteration training run on the 8 chairs of ``inputs/data`` (its sample cache in ``inputs/cache``)."""
    run = tmp_path_factory.mktemp("runs") / "run"
    assert main(["train", str(inputs / "data"), "--out", str(run), "--cache", str(inputs / "cache"),
                 *TINY_TRAIN]) == 0
    return run


# --- failing writes: a full disk, for every command that writes ----------------------------------------------------


def _full_disk_cases(i: Path, f: Path, run: Path) -> dict:
    return {
        "keypoints": ["keypoints", i / "toy.kpd", i / "chair.ply", "--out", f / "kp.json"],
        "deform ply": ["deform", i / "toy.kpd", i / "chair.ply", "--move", "0:0,0,1", "--out", f / "d.ply"],
        "deform obj+mtl+png": ["deform", i / "toy.kpd", i / "tex.obj", "--move", "0:0,0,1", "--out", f / "d.obj"],
        "deform glb": ["deform", i / "toy.kpd", i / "tex.obj", "--out", f / "d.glb"],
        "deform --rig": ["deform", "--rig", i / "rig.npz", "--move", "1:1,0,0", "--out", f / "r.off"],
        "align": ["align", i / "toy.kpd", i / "chair.ply", i / "flat" / "c3.ply", "--out", f / "a.ply",
                  "--keypoints", f / "a.json"],
        "sample": ["sample", i / "toy.kpd", i / "chair.ply", "--n", "2", "--out", f / "variants"],
        "demo": ["demo", "--model", i / "toy.kpd", "--mesh", i / "chair.ply", "--out", f / "demo"],
        "scan": ["scan", i / "chair.ply", "--out", f / "s.ply", "--report", f / "s.json", "--no-pieces"],
        "bench": ["bench", i / "toy.kpd", "--vertices", "1000", "--repeats", "1", "--out", f / "b.json"],
        "eval chamfer": ["eval", "chamfer", i / "flat", "--model", i / "toy.kpd", "--pairs", "4", "--quiet",
                         "--out", f / "e.json"],
        "export": ["export", run, "--out", f / "run.kpd", "--no-prior"],
        "train": ["train", i / "data", "--out", f / "run", "--cache", i / "cache", *TINY_TRAIN],
        "train cache": ["train", i / "data", "--out", f / "run", "--cache", f / "cache", *TINY_TRAIN],
        "render": ["render", "--rig", i / "rig.npz", "--move", "0:0,0,2", "--size", "160x120", "--out", f / "r.png"],
        # a glTF rig's morph targets are written as they are made, block by block, seeking within the file
        "rig glb": ["rig", i / "toy.kpd", i / "tex.obj", "--out", f / "r.glb"],
        "rig gltf": ["rig", i / "toy.kpd", i / "tex.obj", "--out", f / "r.gltf"],
    }


FULL_DISK = ["keypoints", "deform ply", "deform obj+mtl+png", "deform glb", "deform --rig", "align", "sample", "demo",
             "scan", "bench", "eval chamfer", "export", "train", "train cache", "render", "rig glb", "rig gltf"]


@pytest.mark.parametrize("case", FULL_DISK)
def test_full_disk(case, inputs, tiny_run, full_disk, capfd):
    argv = _full_disk_cases(inputs, full_disk, tiny_run)[case]
    before = snapshot(full_disk, inputs, tiny_run)
    line = assert_fault(kpd(capfd, *argv), before, full_disk, inputs, tiny_run, match="cannot write")
    assert "disk is full" in line


def test_full_disk_library_writers(full_disk):
    """The library writers themselves (what every command calls, and the benchmarks' JSON) end in WriteError and leave
    nothing."""
    from kpd.benchmark import write_json
    from kpd.errors import WriteError
    from kpd.io import write_keypoints
    from kpd.viewer.session import EditSession

    before = snapshot(full_disk)
    points = np.random.default_rng(0).uniform(size=(5000, 3))
    for write in (lambda: write_points(full_disk / "p.pcd", points), lambda: write_points(full_disk / "p.xyz", points),
                  lambda: write_keypoints(full_disk / "k.txt", points[:4]),
                  lambda: EditSession(points[:4]).save(full_disk / "session.json"),
                  lambda: write_json(full_disk / "bench.json", {"points": points.tolist()})):
        with pytest.raises(WriteError, match="disk is full"):
            write()
        assert snapshot(full_disk) == before


def test_browser_page_with_a_full_temporary_folder(inputs, full_disk, capfd, monkeypatch):
    """kpd view --browser keeps the page's GLB in a temporary file without a name: a full temporary folder ends in
    one line naming it, before the server starts, and leaves nothing there."""
    import tempfile

    from kpd.viewer.browser import BrowserEditor, page_files_missing

    if page_files_missing():
        pytest.skip("three.js is not installed (make web)")
    if os.statvfs(full_disk).f_bavail * os.statvfs(full_disk).f_frsize >= 1 << 16:
        pytest.skip("no tmpfs to fill here (not root)")
    served = []
    monkeypatch.setattr(BrowserEditor, "serve_forever", lambda self: served.append(self))  # no endless server
    monkeypatch.setattr(tempfile, "tempdir", str(full_disk))
    before = snapshot(full_disk, inputs)
    line = assert_fault(kpd(capfd, "view", inputs / "toy.kpd", inputs / "chair.ply", "--browser", "--port", "0"),
                        before, full_disk, inputs, match="disk is full")
    assert str(full_disk) in line and "TMPDIR" in line and not served
    monkeypatch.setattr(tempfile, "tempdir", str(inputs.parent))
    assert kpd(capfd, "view", inputs / "toy.kpd", inputs / "chair.ply", "--browser", "--port", "0")[0] == 0
    assert len(served) == 1 and served[0].glb is None  # let go when the command ends


# --- read-only and forbidden folders ------------------------------------------------------------------------------


def _folder_cases(i: Path, f: Path) -> dict:
    return {
        "keypoints": ["keypoints", i / "toy.kpd", i / "chair.ply", "--out", f / "kp.json"],
        "deform": ["deform", i / "toy.kpd", i / "chair.ply", "--out", f / "d.obj"],
        "sample": ["sample", i / "toy.kpd", i / "chair.ply", "--n", "2", "--out", f / "variants"],
        "scan": ["scan", i / "chair.ply", "--out", i / "never.ply", "--report", f / "r.json"],
        "train": ["train", i / "data", "--out", f / "run", "--cache", i / "cache", *TINY_TRAIN],
    }


@pytest.mark.parametrize("case", ["keypoints", "deform", "sample", "scan", "train"])
def test_read_only_folder(case, inputs, read_only, capfd):
    before = snapshot(read_only, inputs)
    line = assert_fault(kpd(capfd, *_folder_cases(inputs, read_only)[case]), before, read_only, inputs,
                        match=f"cannot write in folder {read_only}")
    assert "--out" in line or "--report" in line


def test_permission_denied(inputs, tmp_path, capfd, monkeypatch):
    """A folder without write permission (as root: the command runs without CAP_DAC_OVERRIDE, so the permission
    bits apply to it as to any user): refused before any work, in one line."""
    denied = tmp_path / "denied"
    denied.mkdir()
    (denied / "keep.txt").write_text("kept\n")
    argv = ["keypoints", inputs / "toy.kpd", inputs / "chair.ply", "--out", denied / "kp.json"]
    before = snapshot(denied, inputs)
    denied.chmod(0o555)
    try:
        if os.geteuid() == 0 and shutil.which("setpriv"):  # root without the capability to ignore permissions
            drop = "-dac_override,-dac_read_search"
            proc = subprocess.run(["setpriv", "--bounding-set", drop, "--inh-caps", drop, KPD, *map(str, argv)],
                                  capture_output=True, text=True, timeout=120)
            result = (proc.returncode, proc.stdout, proc.stderr)
        else:
            if os.geteuid() == 0:  # root with no way to drop the capability: the folder check sees it as denied
                import kpd.io.atomic as atomic

                real = os.access
                monkeypatch.setattr(atomic.os, "access", lambda p, mode: real(p, mode) and Path(p) != denied)
            result = kpd(capfd, *argv)
    finally:
        denied.chmod(0o755)
    assert_fault(result, before, denied, inputs, match="permission denied")


# --- memory and threads running out mid-command ----------------------------------------------------------------------


@pytest.mark.parametrize("failure", ["memory", "thread"])
def test_memory_or_threads_refused_mid_command(failure, inputs, tmp_path, capfd, monkeypatch):
    """Memory or a thread refused where kpd could not tell beforehand (other programs' use, ``ulimit -v`` or ``-u``):
    one line naming it, exit 2, nothing written. The memory is a real allocation numpy cannot make."""
    from kpd.rig import Rig

    def refused(cls, *args, **kwargs):
        if failure == "memory":
            return np.empty(1 << 56)  # 512 PiB, beyond any address space: numpy's own MemoryError, with its size
        raise RuntimeError("can't start new thread")  # what threading.Thread.start raises when refused

    monkeypatch.setattr(Rig, "bind", classmethod(refused))
    before = snapshot(tmp_path, inputs)
    result = kpd(capfd, "deform", inputs / "toy.kpd", inputs / "chair.ply", "--move", "0:0,0,1", "--out",
                 tmp_path / "d.ply")
    match = "out of memory: Unable to allocate 512. PiB" if failure == "memory" else "would not start another thread"
    assert_fault(result, before, tmp_path, inputs, match=match)


def test_other_runtime_errors_are_not_taken_for_a_failing_environment(inputs, tmp_path, monkeypatch):
    """A RuntimeError that is not a refused thread is a defect: it keeps its traceback."""
    from kpd.rig import Rig

    monkeypatch.setattr(Rig, "bind", classmethod(lambda cls, *a, **k: (_ for _ in ()).throw(
        RuntimeError("a defect"))))
    with pytest.raises(RuntimeError, match="a defect"):
        main(["deform", str(inputs / "toy.kpd"), str(inputs / "chair.ply"), "--out", str(tmp_path / "d.ply")])
    assert not (tmp_path / "d.ply").exists()


# --- companion files ----------------------------------------------------------------------------------------------


def test_companion_file_is_refused_without_force(inputs, tmp_path, capfd):
    (tmp_path / "out.mtl").write_text("newmtl mine\n")
    before = snapshot(tmp_path, inputs)
    assert_fault(kpd(capfd, "deform", inputs / "toy.kpd", inputs / "tex.obj", "--out", tmp_path / "out.obj"),
                 before, tmp_path, inputs, match="companion file")


def test_companions_written_together_under_final_names(inputs, tmp_path, capfd):
    """Not a fault: a textured OBJ names its .mtl and texture by their final names, and nothing else is left."""
    code, _, _ = kpd(capfd, "deform", inputs / "toy.kpd", inputs / "tex.obj", "--out", tmp_path / "out.obj")
    assert code == 0
    # the input's own map (tex_0.png), copied under the output's name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mtl", "out.obj", "out_tex_0.png"]
    assert "mtllib out.mtl" in (tmp_path / "out.obj").read_text()
    assert "out_tex_0.png" in (tmp_path / "out.mtl").read_text()
    # --force replaces the output and its companions, nothing else
    (tmp_path / "other.txt").write_text("mine\n")
    assert kpd(capfd, "deform", inputs / "toy.kpd", inputs / "tex.obj", "--move", "0:0,0,2", "--out",
               tmp_path / "out.obj", "--force")[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.txt", "out.mtl", "out.obj", "out_tex_0.png"]
    # kpd scan of a textured mesh: the same, next to its report
    scans = tmp_path / "scan"
    scans.mkdir()
    code, _, err = kpd(capfd, "scan", inputs / "tex.obj", "--out", scans / "s.obj", "--report", scans / "s.json",
                       "--no-pieces")
    assert code == 0, err
    assert sorted(p.name for p in scans.iterdir()) == ["s.json", "s.mtl", "s.obj", "s_tex_0.png"]
    assert "mtllib s.mtl" in (scans / "s.obj").read_text() and "s_tex_0.png" in (scans / "s.mtl").read_text()


# --- --force never touches an input -------------------------------------------------------------------------------


def test_force_never_deletes_inputs(inputs, tiny_run, tmp_path, capfd):
    work = tmp_path / "W"
    work.mkdir()
    shutil.copy(inputs / "chair.ply", work / "chair.ply")
    cases = [
        (["sample", inputs / "toy.kpd", work / "chair.ply", "--out", work, "--force"], "holds the input"),
        (["demo", "--model", inputs / "toy.kpd", "--mesh", work / "chair.ply", "--out", work, "--force"],
         "holds the input"),
        (["export", tiny_run / "checkpoint.pt", "--out", tiny_run, "--force"], "holds the input"),
        (["deform", inputs / "toy.kpd", work / "chair.ply", "--out", work / "chair.ply", "--force"],
         "is also an input"),
        (["scan", work / "chair.ply", "--reference", inputs / "chair.ply", "--out", inputs / "chair.ply",
          "--report", work / "r.json", "--force"], "is also an input"),
        (["train", inputs / "data", "--out", inputs / "data", "--force", *TINY_TRAIN], "is also an input"),
        (["eval", "alignment", tiny_run, "--out", tiny_run / "record.json", "--force"], "lies inside the input"),
    ]
    for argv, message in cases:
        before = snapshot(work, inputs, tiny_run)
        assert_fault(kpd(capfd, *argv), before, work, inputs, tiny_run, match=message)


# --- concurrent writers -------------------------------------------------------------------------------------------


def test_two_processes_writing_one_output(inputs, tmp_path):
    """Both start before the output exists: one wins, the other ends with one line; the file is the winner's."""
    out = tmp_path / "kp.json"
    argv = [KPD, "keypoints", str(inputs / "toy.kpd"), str(inputs / "chair.ply"), "--out", str(out)]
    procs = [subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=120), *p.communicate()) for p in procs]
    codes = sorted(code for code, _, _ in results)
    assert codes == [0, 2], results
    loser = next(err for code, _, err in results if code == 2)
    assert len(error_lines(loser)) == 1 and ("appeared while kpd was running" in loser or "exists" in loser)
    assert json.loads(out.read_text())["keypoints"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kp.json"]


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_output_appearing_during_the_run_is_not_clobbered(kind, inputs, tmp_path, capfd, monkeypatch):
    from kpd.runtime import Model

    out = tmp_path / ("kp.json" if kind == "file" else "variants")
    real = Model.rig

    def rig_and_intrude(self, *args, **kwargs):  # another process creates the output while kpd works
        if kind == "file":
            out.write_text("someone else's\n")
        else:
            out.mkdir()
            (out / "theirs.txt").write_text("someone else's\n")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Model, "rig", rig_and_intrude)
    monkeypatch.setattr(Model, "keypoints", lambda self, shape, seed=0: (out.write_text("someone else's\n"),
                                                                         np.zeros((4, 3)))[1])
    argv = (["keypoints", inputs / "toy.kpd", inputs / "chair.ply", "--out", out] if kind == "file" else
            ["sample", inputs / "toy.kpd", inputs / "chair.ply", "--n", "2", "--out", out])
    code = main([str(a) for a in argv])
    _, err = capfd.readouterr()
    assert code == 2 and len(error_lines(err)) == 1 and "appeared while kpd was running" in err
    theirs = out if kind == "file" else out / "theirs.txt"
    assert theirs.read_text() == "someone else's\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


# --- SIGKILL during a write ---------------------------------------------------------------------------------------


def test_sigkill_during_a_write_is_cleaned_by_the_next_run(inputs, tmp_path, capfd):
    script = textwrap.dedent(f"""
        import os, signal
        from kpd.io import Outputs
        outputs = Outputs()
        out = outputs.file({str(tmp_path / 'kp.json')!r})
        with open(outputs.stage(out), "w") as fh:
            fh.write('{{"keypoints": [[0, 0')
            fh.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and ".kpd-tmp-" in left[0]  # the killed write left its staging folder
    code, out, _ = kpd(capfd, "keypoints", inputs / "toy.kpd", inputs / "chair.ply", "--out", tmp_path / "kp.json")
    assert code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kp.json"]
    assert len(json.loads((tmp_path / "kp.json").read_text())["keypoints"]) == 4


@pytest.fixture
def no_stop_noted():
    from kpd import _signals

    _signals._requested.clear()
    yield _signals
    _signals._requested.clear()


@pytest.mark.parametrize("signum, line, status", [(signal.SIGTERM, "stopped by signal 15 (SIGTERM)", 143),
                                                  (signal.SIGINT, "interrupted", 130)])
def test_a_signal_whose_exception_was_lost_still_stops_before_any_output(signum, line, status, no_stop_noted, inputs,
                                                                        tmp_path, capfd, monkeypatch):
    """Python runs a signal's handler where it can, inside a compiled kernel's call too, and numba's dispatcher then
    loses its exception now and then (a Ctrl+C in ``kpd rig`` of a 1.37M-vertex chair let it write its whole file):
    the program's handlers also note the signal, and no output is placed once one was."""
    from kpd.runtime import Model

    def work(self, shape, seed=0):
        no_stop_noted.note(signum)  # the handler ran; its exception went nowhere
        return np.zeros((4, 3))

    monkeypatch.setattr(Model, "keypoints", work)
    out = tmp_path / "kp.json"
    code, _, err = kpd(capfd, "keypoints", inputs / "toy.kpd", inputs / "chair.ply", "--out", out)
    assert code == status and error_lines(err) == [f"kpd keypoints: {line}"]
    assert list(tmp_path.iterdir()) == []


def test_a_compiled_call_returning_with_the_interrupt_pending_ends_as_the_interrupt(no_stop_noted, inputs, tmp_path,
                                                                                     capfd, monkeypatch):
    """numba's dispatcher returning with a handler's exception pending raises SystemError with the interrupt as its
    cause: one line and the interrupt's status, no traceback; any other SystemError is not taken for one."""
    from kpd.runtime import Model

    def work(self, shape, seed=0):
        no_stop_noted.note(signal.SIGINT)
        raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set") \
            from KeyboardInterrupt()

    monkeypatch.setattr(Model, "keypoints", work)
    out = tmp_path / "kp.json"
    code, _, err = kpd(capfd, "keypoints", inputs / "toy.kpd", inputs / "chair.ply", "--out", out)
    assert code == 130 and error_lines(err) == ["kpd keypoints: interrupted"] and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []
    no_stop_noted._requested.clear()

    def broken(self, shape, seed=0):
        raise SystemError("a real bug")

    monkeypatch.setattr(Model, "keypoints", broken)
    with pytest.raises(SystemError, match="a real bug"):
        main([str(a) for a in ("keypoints", inputs / "toy.kpd", inputs / "chair.ply", "--out", out)])


def test_ctrl_c_in_the_program_is_noted_and_ends_the_command(inputs, tmp_path):
    """The program's own Ctrl+C handler (in the interpreter's place) raises KeyboardInterrupt and notes the signal:
    one line, status 130, nothing written."""
    script = textwrap.dedent(f"""
        import os, signal, sys, time
        from kpd.runtime import Model
        def work(self, shape, seed=0):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
            raise AssertionError("not interrupted")
        Model.keypoints = work
        sys.argv = ["kpd", "keypoints", {str(inputs / "toy.kpd")!r}, {str(inputs / "chair.ply")!r}, "--out",
                    {str(tmp_path / "kp.json")!r}]
        from kpd.cli import main
        main()
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130, proc.stderr
    assert error_lines(proc.stderr) == ["kpd keypoints: interrupted"]
    assert list(tmp_path.iterdir()) == []


def test_resume_removes_temporaries_of_a_killed_run(inputs, tiny_run, tmp_path, capfd):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    stale = run / f".checkpoint.pt.kpd-tmp-{2 ** 22 + 12345}-0badc0de.pt"  # no such process
    stale.write_bytes(b"half a checkpoint")
    code, _, err = kpd(capfd, "train", inputs / "data", "--out", run, "--cache", inputs / "cache", "--resume",
                       *TINY_TRAIN)
    assert code == 0, err
    assert not stale.exists() and "removed" in err
    assert not [p for p in run.iterdir() if ".kpd-tmp-" in p.name]


# --- the whole of stderr: one line, nothing before it -----------------------------------------------------------


@pytest.mark.parametrize("case", ["sample", "bench"])
def test_full_disk_leaves_no_progress_bar_on_stderr(case, inputs, full_disk, capfd):
    """stderr as a pipe gets it (error_lines reduces a bar's redraws, which a log file keeps)."""
    argv = _full_disk_cases(inputs, full_disk, full_disk)[case]
    before = snapshot(full_disk, inputs)
    code, _, err = kpd(capfd, *argv)
    assert code == 2 and err.count("\n") == 1 and "\r" not in err and err.startswith("kpd "), repr(err)
    assert "disk is full" in err
    assert snapshot(full_disk, inputs) == before


def test_bench_of_a_mesh_whose_points_coincide_prints_one_line(inputs, tmp_path, capfd):
    write_mesh(tmp_path / "point.ply", Mesh(vertices=np.ones((4, 3)), triangles=[[0, 1, 2], [0, 2, 3]]))
    before = snapshot(tmp_path, inputs)
    code, _, err = kpd(capfd, "bench", inputs / "toy.kpd", "--mesh", tmp_path / "point.ply", "--repeats", "1",
                       "--out", tmp_path / "b.json")
    assert code == 2 and err.count("\n") == 1 and "\r" not in err and err.startswith("kpd "), repr(err)
    assert snapshot(tmp_path, inputs) == before


# --- integrity: hashes and damaged files --------------------------------------------------------------------------


def _flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))


def _tensor_offset(checkpoint: Path) -> int:
    """An offset inside the largest tensor's bytes of a torch zip (stored uncompressed, so torch reads it as is)."""
    with zipfile.ZipFile(checkpoint) as archive:
        info = max(archive.infolist(), key=lambda i: i.file_size)
    with open(checkpoint, "rb") as fh:
        fh.seek(info.header_offset + 26)
        name_length, extra_length = np.frombuffer(fh.read(4), dtype="<u2")
    return info.header_offset + 30 + int(name_length) + int(extra_length) + info.file_size // 2


@pytest.mark.parametrize("command", ["export", "eval", "resume"])
def test_checkpoint_with_a_flipped_byte_is_refused(command, inputs, tiny_run, tmp_path, capfd):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    _flip(run / "checkpoint.pt", _tensor_offset(run / "checkpoint.pt"))
    argv = {"export": ["export", run, "--out", tmp_path / "x.kpd", "--no-prior"],
            "eval": ["eval", "keypoints", run, "--out", tmp_path / "e.json", "--cache", inputs / "cache", "--quiet"],
            "resume": ["train", inputs / "data", "--out", run, "--cache", inputs / "cache", "--resume",
                       *TINY_TRAIN]}[command]
    before = snapshot(tmp_path, inputs)
    assert_fault(kpd(capfd, *argv), before, tmp_path, inputs, match="damaged")


def test_rig_with_a_flipped_byte_or_changed_content_is_refused(inputs, tmp_path, capfd):
    flipped = tmp_path / "flipped.npz"
    shutil.copy(inputs / "rig.npz", flipped)
    _flip(flipped, flipped.stat().st_size // 2)
    changed = tmp_path / "changed.npz"  # valid zip, one keypoint moved, the stored hash kept
    with np.load(inputs / "rig.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["keypoints"] = arrays["keypoints"] + np.eye(len(arrays["keypoints"]), 3) * 1e-3
    np.savez_compressed(changed, **arrays)
    for rig, message in ((flipped, "damaged"), (changed, "does not match its sha256")):
        for argv in (["deform", "--rig", rig, "--move", "0:0,0,1", "--out", tmp_path / "d.ply"],
                     ["render", "--rig", rig, "--out", tmp_path / "r.png"]):
            before = snapshot(tmp_path)
            assert_fault(kpd(capfd, *argv), before, tmp_path, match=message)


def test_session_with_a_changed_value_is_refused(tmp_path):
    from kpd.viewer.session import EditSession, read_session_file

    session = EditSession(np.eye(4, 3))
    session.save(tmp_path / "s.json")
    assert read_session_file(tmp_path / "s.json")["sha256"]
    text = (tmp_path / "s.json").read_text()
    (tmp_path / "s.json").write_text(text.replace("1.0", "1.5", 1))
    with pytest.raises(InputError, match="damaged"):
        read_session_file(tmp_path / "s.json")


def _damaged_npz(tmp_path: Path) -> dict[str, Path]:
    good = tmp_path / "good.npz"
    np.savez_compressed(good, points=np.random.default_rng(0).uniform(-1, 1, (2000, 3)))
    data = good.read_bytes()
    files = {"empty": b"", "truncated": data[: len(data) // 2], "text": b"0 0 0\n1 1 1\n"}
    crc = bytearray(data)
    crc[60] ^= 0xFF  # inside the compressed member: zlib or the CRC check fails
    files["bad crc"] = bytes(crc)
    paths = {}
    for name, content in files.items():
        paths[name] = tmp_path / f"{name.replace(' ', '_')}.npz"
        paths[name].write_bytes(content)
    good.unlink()
    return paths


@pytest.mark.parametrize("damage, message", [("empty", "empty"), ("truncated", "damaged .npz"),
                                             ("text", "a text file, not a point file"),
                                             ("bad crc", "damaged .npz")])
def test_damaged_npz_points_and_rigs(damage, message, inputs, tmp_path, capfd):
    path = _damaged_npz(tmp_path)[damage]
    before = snapshot(tmp_path)
    line = assert_fault(kpd(capfd, "keypoints", inputs / "toy.kpd", path, "--out", tmp_path / "kp.json"), before,
                        tmp_path, match=message)
    assert "pickle" not in line
    assert_fault(kpd(capfd, "deform", "--rig", path, "--out", tmp_path / "d.ply"), before, tmp_path,
                 match="" if damage != "text" else "a text file")


# --- files made to harm the reader (found by tests/test_fuzz.py) ----------------------------------------------------


def _polygon_ply(path: Path, *, binary: bool, corner: int) -> None:
    """Four vertices and one quad whose last corner is ``corner``: kpd leaves polygons to Open3D's reader."""
    head = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\nelement vertex 4\n"
            "property float x\nproperty float y\nproperty float z\nelement face 1\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    corners = [0, 1, 2, corner]
    if binary:
        body = np.eye(4, 3, dtype="<f4").tobytes() + bytes([4]) + np.array(corners, "<i4").tobytes()
    else:
        body = b"".join(b"%g %g %g\n" % tuple(row) for row in np.eye(4, 3)) + b"4 %d %d %d %d\n" % tuple(corners)
    path.write_bytes(head + body)


@pytest.mark.parametrize("binary", [True, False])
def test_polygon_with_a_corner_beyond_the_vertices(binary, inputs, tmp_path):
    """Open3D's PLY reader ends the process on such a corner (a segmentation fault): a process of its own here."""
    _polygon_ply(tmp_path / "bad.ply", binary=binary, corner=2**31 - 7)
    before = snapshot(tmp_path, inputs)
    done = subprocess.run([KPD, "keypoints", str(inputs / "toy.kpd"), str(tmp_path / "bad.ply"), "--out",
                           str(tmp_path / "kp.json")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 2, done.stderr
    assert error_lines(done.stderr) == [done.stderr.strip()] and "face 0 has the corner 2147483641" in done.stderr
    assert snapshot(tmp_path, inputs) == before
    _polygon_ply(tmp_path / "good.ply", binary=binary, corner=3)  # within the vertices: Open3D reads it as before
    from kpd.io import read_mesh

    assert read_mesh(tmp_path / "good.ply").triangles.shape == (2, 3)


@pytest.mark.parametrize("binary", [True, False])
def test_face_of_fewer_than_three_corners_or_a_partial_normal_in_a_file_open3d_reads(binary, inputs, tmp_path):
    """Open3D's PLY reader reads on after a face of 0 to 2 corners (garbage or a segmentation fault later), its PCD
    reader ends the process on a normal of one or two fields (here ``normal_\x1d``: a line break for ``str``, not for
    Open3D): each is one line, exit 2."""
    _polygon_ply(tmp_path / "short.ply", binary=binary, corner=3)
    data = (tmp_path / "short.ply").read_bytes()
    (tmp_path / "short.ply").write_bytes(data[:-17] + bytes([2]) + data[-16:] if binary else
                                         data.replace(b"4 0 1 2 3", b"2 0 1"))
    (tmp_path / "count.ply").write_bytes(data.replace(b"element face 1", b"element face 1\xa2"))  # rply reads 1
    write_points(tmp_path / "p.pcd", np.eye(4, 3), normals=np.eye(4, 3))
    (tmp_path / "n.pcd").write_bytes((tmp_path / "p.pcd").read_bytes().replace(b"normal_x", b"normal_\x1d", 1))
    before = snapshot(tmp_path, inputs)
    for path, message in ((tmp_path / "short.ply", "face 0 has 2 corners"), (tmp_path / "n.pcd", "without normal_x"),
                          (tmp_path / "count.ply", "does not give an element's name and count")):
        done = subprocess.run([KPD, "keypoints", str(inputs / "toy.kpd"), str(path), "--out",
                               str(tmp_path / "kp.json")], capture_output=True, text=True, timeout=600)
        assert done.returncode == 2 and error_lines(done.stderr) == [done.stderr.strip()], done.stderr
        assert message in done.stderr
    assert snapshot(tmp_path, inputs) == before


def test_pcd_header_without_data_line_or_point_count(tmp_path):
    """Open3D's reader sized the cloud by a count it never set: garbage points, or std::bad_alloc."""
    from kpd.io import read_points

    write_points(tmp_path / "p.pcd", np.eye(4, 3))
    data = (tmp_path / "p.pcd").read_bytes()
    (tmp_path / "no_data.pcd").write_bytes(data[: data.index(b"DATA")] + b"COU F F F\n" * 20)
    (tmp_path / "no_count.pcd").write_bytes(re.sub(rb"(?m)^(POINTS|WIDTH|HEIGHT) .*\n", b"", data))
    height_first = re.sub(rb"(?m)^WIDTH .*\n", b"", data).replace(b"DATA", b"WIDTH 4\nDATA")
    (tmp_path / "height_first.pcd").write_bytes(height_first)
    (tmp_path / "huge_size.pcd").write_bytes(re.sub(rb"(?m)^SIZE 4", b"SIZE 1" + b"0" * 400, data))
    for name, message in (("no_data", "no DATA line"), ("no_count", "declares no POINTS"),
                          ("height_first", "HEIGHT line comes before any WIDTH"),
                          ("huge_size", "a field is 1, 2, 4 or 8 bytes")):
        with pytest.raises(InputError, match=message):
            read_points(tmp_path / f"{name}.pcd")


def test_off_with_bytes_that_are_not_text(tmp_path):
    """A header kpd leaves to Open3D, with bytes that are not UTF-8: Open3D's message quoting it ended in a
    UnicodeDecodeError."""
    from kpd.io import read_mesh, read_points

    write_mesh(tmp_path / "m.off", Mesh(vertices=np.eye(3), triangles=[[0, 1, 2]]))
    data = (tmp_path / "m.off").read_bytes()
    (tmp_path / "bad.off").write_bytes(b"CNOF\xfe\xff\xff\xff" + data[data.index(b"\n"):])
    for read in (read_mesh, read_points):
        with pytest.raises(InputError, match="not a text OFF file"):
            read(tmp_path / "bad.off")


def test_npz_member_declaring_a_huge_array_or_inflating_like_a_bomb(inputs, tmp_path, capfd):
    from kpd.io import read_points
    from kpd.rig import Rig

    lying = tmp_path / "lying.npz"  # the header of points.npy declares 2^28 x 3 doubles (6 GiB); 24 bytes follow
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (2**28, 3)})
    with zipfile.ZipFile(lying, "w") as archive:
        archive.writestr("points.npy", buf.getvalue() + bytes(24))
    bomb = tmp_path / "bomb.npz"  # 64 MiB of zeros deflated to 64 kB
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("points.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array(fh, np.zeros((1 << 23, 1)))
    for path, message in ((lying, "declares a float64 array of shape (268435456, 3)"), (bomb, "more than 100 times")):
        for read in (read_points, Rig.load):
            with pytest.raises(InputError, match=re.escape(message)):
                read(path)
        before = snapshot(tmp_path)
        assert_fault(kpd(capfd, "deform", "--rig", path, "--out", tmp_path / "d.ply"), before, tmp_path,
                     match=message)


def test_rig_with_arrays_of_another_shape_and_its_hash_recomputed(inputs, tmp_path):
    from kpd.io.integrity import HASH_KEY, content_hash
    from kpd.rig import Rig

    with np.load(inputs / "rig.npz") as data:
        arrays = {k: data[k] for k in data.files}
    for key, value in (("straightened", np.zeros(7, bool)), ("mesh_vertices", None), ("influence", np.zeros((2, 2))),
                       ("keypoints", np.zeros((4, 2))), ("normalizer_center", np.zeros(7))):
        changed = {k: v for k, v in arrays.items() if k != key}
        if value is not None:
            changed[key] = value
        changed[HASH_KEY] = np.array(content_hash(changed))
        np.savez(tmp_path / "r.npz", **changed)
        with pytest.raises(InputError, match="r.npz"):
            Rig.load(tmp_path / "r.npz")


def test_keypoint_json_nested_too_deeply_or_with_a_huge_number(tmp_path):
    from kpd.io import read_keypoints

    (tmp_path / "k.json").write_text('{"keypoints": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(InputError, match="nests lists or objects too deeply"):
        read_keypoints(tmp_path / "k.json")
    for digits in (25, 400, 5000):  # beyond float64; beyond Python's int-from-text limit
        (tmp_path / "k.json").write_text('{"keypoints": [[0, 0, 1' + "0" * digits + "]]}")
        with pytest.raises(InputError, match="k.json: 1 keypoint has (coordinates beyond 1e|NaN or inf coordinates)"):
            read_keypoints(tmp_path / "k.json")


def test_damaged_bundle_zip(inputs, tmp_path, capfd):
    files = {p.name: p.read_bytes() for p in (inputs / "toy.kpd").iterdir()}
    from kpd.bundle import write_bundle

    write_bundle(tmp_path / "toy.zip", files)
    data = (tmp_path / "toy.zip").read_bytes()
    (tmp_path / "toy.zip").write_bytes(data[: len(data) * 2 // 3])
    before = snapshot(tmp_path)
    assert_fault(kpd(capfd, "keypoints", tmp_path / "toy.zip", inputs / "chair.ply", "--out", tmp_path / "k.json"),
                 before, tmp_path, match="toy.zip")


# --- options checked before any work ------------------------------------------------------------------------------


def _option_cases(i: Path, t: Path) -> list:
    data, toy, chair = i / "data", i / "toy.kpd", i / "chair.ply"
    return [
        (["keypoints", toy, chair, "--seed", "-1"], "--seed"),
        (["deform", toy, chair, "--threads", "0", "--out", t / "d.ply"], "--threads"),
        (["train", data, "--out", t / "run", "--samples", "0"], "--samples"),
        (["train", data, "--out", t / "run", "--points", "0"], "--points"),
        (["train", data, "--out", t / "run", "--cage-level", "-1"], "--cage-level"),
        (["train", data, "--out", t / "run", "--cage-distance", "nan"], "--cage-distance"),
        (["train", data, "--out", t / "run", "--lr", "inf"], "--lr"),
        (["train", data, "--out", t / "run", "--val-fraction", "2"], "--val-fraction"),
        (["train", chair, "--out", t / "run"], "is a file"),
        (["train", data, "--out", t / "run", "--split-file", t / "none.txt"], "--split-file"),
        (["export", "--from-authors", chair, "--points", "0", "--out", t / "x.kpd"], "--points"),
        (["export", t, "--data", chair, "--out", t / "x.kpd"], "--data"),
        (["eval", "pck", data, "--category", "chair", "--model", toy, "--threshold", "nan", "--out", t / "e.json"],
         "--threshold"),
        (["eval", "chamfer", data, "--model", toy, "--pairs", "0", "--out", t / "e.json"], "--pairs"),
        (["eval", "chamfer", chair, "--model", toy, "--out", t / "e.json"], "is a file"),
        (["sample", toy, chair, "--n", "0", "--out", t / "s"], "--n"),
        (["sample", toy, chair, "--scale", "nan", "--out", t / "s"], "--scale"),
        (["scan", chair, "--reference-points", "5", "--out", t / "s.ply", "--report", t / "r.json"],
         "--reference-points"),
        (["bench", toy, "--vertices", "10"], "--vertices"),
        (["demo", "--amount", "nan", "--out", t / "demo"], "--amount"),
        (["keypoints", toy, chair, "--up", "z"], "--up goes with --scan"),
        (["deform", toy, chair, "--up", "z", "--out", t / "d.ply"], "--up goes with --scan"),
        (["render", toy, chair, "--up", "z", "--out", t / "r.png"], "--up goes with --scan"),
        (["view", toy, chair, "--up", "z"], "--up goes with --scan"),
        (["keypoints", toy, chair, "--scan", "--up", "sideways"], "--up"),
        (["align", toy, chair, chair, "--out", t / "a.ply", "--keypoints", t / "a.txt"], "--keypoints"),
        (["keypoints", toy, i / "toy.kpd" / "keypoints.onnx", "--out", t / "k.json"], "unknown"),
        (["keypoints", toy, i / "flat" / "c0.ply", "--out", data], "is a folder"),
        (["deform", toy, t, "--out", t / "d.ply"], "is a folder"),
    ]


def test_options_checked_before_any_work(inputs, tmp_path, capfd):
    work = tmp_path / "work"
    work.mkdir()
    (work / "keep.txt").write_text("kept\n")
    for argv, option in _option_cases(inputs, work):
        before = snapshot(work, inputs)
        assert_fault(kpd(capfd, *argv), before, work, inputs, match=option)


# --- training -----------------------------------------------------------------------------------------------------


def test_diverging_run_keeps_its_last_good_checkpoint(inputs, tmp_path, capfd):
    from kpd.train.trainer import load_checkpoint

    run = tmp_path / "run"
    argv = ["train", inputs / "data", "--out", run, "--cache", inputs / "cache", *TINY_TRAIN]
    argv[argv.index("--iterations") + 1] = "30"
    code, _, err = kpd(capfd, *argv, "--lr", "1e30")
    line = error_lines(err)[-1]
    assert code == 2 and "Traceback" not in err and "diverged" in line and "keeps the last good checkpoint" in line
    assert [s for s in error_lines(err) if s.startswith("kpd ")] == [line]
    kept = load_checkpoint(run)  # hash checked: a whole, good checkpoint
    assert 1 <= kept["iteration"] < 30
    assert not [p for p in run.iterdir() if ".kpd-tmp-" in p.name]


def test_refused_start_leaves_no_run_folder(inputs, tmp_path, capfd):
    before = snapshot(tmp_path, inputs)
    assert_fault(kpd(capfd, "train", inputs / "data", "--out", tmp_path / "new", "--cache", inputs / "cache",
                     "--device", "cuda", *TINY_TRAIN), before, tmp_path, inputs, match="cuda")


# --- honest evaluation (behaviour, not faults) --------------------------------------------------------------------


def test_tiny_validation_split_is_flagged_not_scored(inputs, tmp_path, capfd):
    """8 meshes leave 1 for validation: no "val chamfer 0.00000" from pairs of one shape, and it is said."""
    argv = ["train", inputs / "data", "--out", tmp_path / "run", "--cache", inputs / "cache", *TINY_TRAIN]
    argv[argv.index("--val-pairs") + 1] = "8"
    argv[argv.index("--iterations") + 1] = "1"
    code, out, err = kpd(capfd, *argv)
    assert code == 0, err
    assert "the validation split has 1 shape(s): no validation score" in err
    assert "no validation score" in out and "val chamfer 0.0" not in out
    record = json.loads((tmp_path / "run" / "record.json").read_text())
    score = record["metrics"].get("val_chamfer")
    assert record["data"]["counts"]["val"] == 1 and (score is None or score != score)  # absent or NaN, never 0


def test_flat_folder_chamfer_names_its_test_shapes_and_repeats_no_pair(inputs, tmp_path, capfd):
    code, out, err = kpd(capfd, "eval", "chamfer", inputs / "flat", "--model", inputs / "toy.kpd", "--pairs", "100",
                         "--quiet", "--out", tmp_path / "e.json")
    assert code == 0, err
    result = json.loads((tmp_path / "e.json").read_text())
    test = result["data"]["test_names"]
    assert len(test) == 2 and all(name in out for name in test)  # 10% of 15 carved, and said so
    pairs = [(p["source"], p["target"]) for p in result["results"]["per_pair"]]
    assert len(pairs) == len(set(pairs)) == 2 == result["settings"]["pairs"]
    assert result["settings"]["requested_pairs"] == 100
    assert "only 2 distinct pairs" in err and "only 2 test shapes" in err


def test_alignment_pairs_distinct_and_unchanged_without_repeats():
    from kpd.annotations import alignment_pairs

    for n, count in ((3, 100), (5, 20), (40, 200)):
        pairs = alignment_pairs(n, count, seed=1)
        assert len({tuple(p) for p in pairs}) == len(pairs) == min(count, n * (n - 1))
        assert (pairs[:, 0] != pairs[:, 1]).all()
    rng = np.random.default_rng([0, 3])  # the draws before duplicates were dropped, when there are none
    source = rng.integers(1000, size=5)
    target = (source + rng.integers(1, 1000, size=5)) % 1000
    np.testing.assert_array_equal(alignment_pairs(1000, 5, 0), np.stack([source, target], 1))


def test_split_lists_are_accepted(inputs, tmp_path):
    from kpd.data import discover

    flat = tmp_path / "flat"
    shutil.copytree(inputs / "data" / "chair", flat)
    (flat / "train.txt").write_text("\n".join(f"c{i}" for i in range(5)) + "\n")
    (flat / "test.txt").write_text("c5\nc6\nc7\n")
    found = discover(flat)  # beside the meshes
    assert [f.name for f in found.splits["test"]] == ["c5", "c6", "c7"]
    assert len(found.splits["train"]) + len(found.splits["val"]) == 5
    lists = tmp_path / "lists"
    lists.mkdir()
    for name in ("train.txt", "test.txt"):
        shutil.move(flat / name, lists / name)
    given = discover(flat, split_file=lists / "train.txt")  # one list given by itself
    assert [f.name for f in given.splits["test"]] == ["c5", "c6", "c7"]


# --- numba's cache ------------------------------------------------------------------------------------------------


def _kernel_for_the_cache_test(x):  # at module level: numba caches what it can find again by name
    return 2 * x + 1


def test_kernels_numba_cannot_cache_are_compiled_each_run_and_said_once(monkeypatch, caplog):
    import numba
    from numba.core import caching

    import kpd._compiled as compiled

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])  # no folder takes numba's cache
    monkeypatch.setattr(compiled, "_said", set())
    with pytest.raises(RuntimeError, match="no locator available"):  # what numba itself does then
        numba.njit(cache=True)(_kernel_for_the_cache_test)
    with caplog.at_level("WARNING", logger="kpd"):
        plus = compiled.njit(nogil=True)(_kernel_for_the_cache_test)
        again = compiled.njit()(_kernel_for_the_cache_test)
    assert plus(1) == 3 and again(3) == 7
    assert [record.getMessage() for record in caplog.records] == [compiled.UNCACHED]

    def failing(*args, **options):  # any other refusal is not taken for it
        raise RuntimeError("another failure")

    monkeypatch.setattr(numba, "njit", failing)
    with pytest.raises(RuntimeError, match="another failure"):
        compiled.njit()(_kernel_for_the_cache_test)


def test_a_read_only_installation_and_home_still_run_with_one_warning(inputs, tmp_path):
    """kpd installed where nothing can be written (a container's read-only root file system: its own folder and the
    home folder read-only, NUMBA_CACHE_DIR unset): a command works and says once that it compiles on each run."""
    from kpd._compiled import UNCACHED

    install, home = tmp_path / "site", tmp_path / "home"
    install.mkdir()
    home.mkdir()
    root = Path(__file__).resolve().parents[1]
    mounted = _mount(install, "size=64m") and _mount(home, "size=64k")
    shutil.copytree(root / "kpd", install / "kpd", ignore=shutil.ignore_patterns("__pycache__", "models"))
    if mounted:
        for folder in (install, home):
            subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=True)
    else:  # not root: permission bits do it
        for folder in (install, home):
            subprocess.run(["chmod", "-R", "a-w", str(folder)], check=True)
    env = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"), PYTHONPATH=str(install))
    try:
        done = subprocess.run([sys.executable, "-c", "import sys, kpd.cli; print(kpd.cli.__file__, file=sys.stderr); "
                               "sys.argv[0] = 'kpd'; kpd.cli.main()", "keypoints", str(inputs / "toy.kpd"),
                               str(inputs / "chair.ply")], capture_output=True, text=True, env=env, timeout=600,
                              cwd=tmp_path)
    finally:
        if mounted:
            _umount(install)
            _umount(home)
        else:
            subprocess.run(["chmod", "-R", "u+w", str(install), str(home)], check=True)
    lines = done.stderr.splitlines()
    assert done.returncode == 0, done.stderr
    assert lines == [str(install / "kpd" / "cli.py"), f"warning: {UNCACHED}"], done.stderr  # this copy, one line
    assert len(json.loads(done.stdout)["keypoints"]) == 4


def test_a_damaged_cache_file_is_compiled_again_with_one_warning(inputs, tmp_path):
    """A cache file of numba's that cannot be read back (truncated here) ended every later command in an unpickling
    traceback: now that command compiles its kernels again, says so in one line and writes the cache anew."""
    from kpd._compiled import CACHE_FAILED

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    argv = [sys.executable, "-m", "kpd.cli", "keypoints", str(inputs / "toy.kpd"), str(inputs / "chair.ply")]

    def run() -> subprocess.CompletedProcess:
        return subprocess.run(argv, capture_output=True, text=True, env=env, timeout=600)

    first = run()
    assert first.returncode == 0 and first.stderr == "", first.stderr
    kept = sorted((tmp_path / "cache").rglob("*.nbc"))
    assert kept
    for path in kept:
        with open(path, "r+b") as fh:
            fh.truncate(path.stat().st_size // 2)
    damaged = run()
    assert damaged.returncode == 0, damaged.stderr
    lines = damaged.stderr.splitlines()
    head, tail = CACHE_FAILED.format("read", "\0").split("\0")
    assert len(lines) == 1 and lines[0].startswith("warning: " + head) and lines[0].endswith(tail), damaged.stderr
    assert damaged.stdout == first.stdout  # the same keypoints
    again = run()
    assert again.returncode == 0 and again.stderr == "" and again.stdout == first.stdout  # written anew


def test_a_cache_that_cannot_be_written_leaves_the_kernel_running_with_one_warning(tmp_path, monkeypatch, caplog):
    """A full disk (as root) or a folder without write permission where numba keeps its cache: its write failed and
    ended the command ("cannot write an output: the disk is full"); now the kernel runs as compiled, with a warning."""
    import numba

    import kpd._compiled as compiled

    cache = tmp_path / "cache"
    cache.mkdir()
    mounted = _mount(cache, "size=64k")
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(cache))
    monkeypatch.setattr(compiled, "_said", set())
    try:
        kernel = compiled.njit()(_kernel_for_the_cache_test)  # numba checks here that it can write the folder
        if mounted:
            with open(cache / "filler", "wb", buffering=0) as fh:
                with pytest.raises(OSError):
                    while True:
                        fh.write(b"\0" * 4096)
        else:
            for folder in [cache, *cache.rglob("*")]:
                folder.chmod(0o555)
        with caplog.at_level("WARNING", logger="kpd"):
            assert kernel(20) == 41
            assert compiled.njit()(_kernel_for_the_cache_test)(1) == 3  # a second kernel: compiled, not said again
        messages = [record.getMessage() for record in caplog.records]
        head, tail = compiled.CACHE_FAILED.format("written", "\0").split("\0")
        assert len(messages) == 1 and messages[0].startswith(head + "OSError") and messages[0].endswith(tail)
        assert not list(cache.rglob("*.nbc"))
    finally:
        if mounted:
            _umount(cache)
        else:
            for folder in [cache, *cache.rglob("*")]:
                folder.chmod(0o755)
