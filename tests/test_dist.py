"""The release as users get it (``make dist``): the sdist, and the wheel built from it, carry the shipped bundles, the
browser page and three.js; the wheel installed by pip into a new venv without torch runs every runtime command from an
empty folder on shapes a user has; the commands that need torch end in one line naming the train extra."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import threading
import zipfile
from pathlib import Path
from urllib.parse import urljoin, urlsplit
from urllib.request import urlopen

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "viewer" / "web"
ON_CI = os.environ.get("CI", "").lower() == "true"
TRAIN_EXTRA_HINT = ('pip install "kpd[train]"', "pip install torch --index-url https://download.pytorch.org/whl/cpu")


def _missing(what: str) -> None:
    """A tool of make system / make web absent: skipped here, a failure under CI, where make test installs it."""
    (pytest.fail if ON_CI else pytest.skip)(f"{what} (make test installs it)")


def _run(argv: list, *, cwd: Path, env: dict | None = None, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def _ok(done: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert done.returncode == 0, f"{' '.join(done.args)} ended with {done.returncode}:\n{done.stderr[-3000:]}"
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    return done


def _refused_for_the_train_extra(done: subprocess.CompletedProcess | tuple[int, str], module: str = "torch") -> None:
    code, err = (done.returncode, done.stderr) if isinstance(done, subprocess.CompletedProcess) else done
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert f"{module} is not installed" in lines[0] and all(hint in lines[0] for hint in TRAIN_EXTRA_HINT), lines[0]


# --- without torch, in this process: the check before any work, and the line for a module found missing later ----


@pytest.fixture()
def no_torch(monkeypatch):
    """torch as if not installed: ``import torch`` fails and :func:`importlib.util.find_spec` finds nothing."""
    monkeypatch.setitem(sys.modules, "torch", None)


def test_commands_that_need_torch_name_the_train_extra_in_one_line(no_torch, tmp_path, capsys):
    from kpd.cli import main

    (tmp_path / "data").mkdir()
    (tmp_path / "run").mkdir()
    (tmp_path / "net_final.pth").write_bytes(b"not read")
    for argv in (["train", tmp_path / "data", "--out", tmp_path / "new_run"],
                 ["export", tmp_path / "run", "--out", tmp_path / "chair.kpd"],
                 ["export", "--from-authors", tmp_path / "net_final.pth", "--category", "chair", "--out",
                  tmp_path / "authors.kpd"],
                 ["eval", "alignment", tmp_path / "run", "--out", tmp_path / "alignment.json"],
                 ["eval", "keypoints", tmp_path / "run", "--out", tmp_path / "keypoints.json"]):
        code = main([str(a) for a in argv])
        _refused_for_the_train_extra((code, capsys.readouterr().err))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "net_final.pth", "run"]  # nothing written


@pytest.mark.parametrize("module", ["onnx", "onnxscript"])
def test_export_names_the_exporter_s_modules_of_the_train_extra(module, monkeypatch, tmp_path, capsys):
    from kpd.cli import main

    monkeypatch.setitem(sys.modules, module, None)
    (tmp_path / "run").mkdir()
    code = main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "chair.kpd")])
    _refused_for_the_train_extra((code, capsys.readouterr().err), module)
    assert not (tmp_path / "chair.kpd").exists()


def test_a_train_extra_module_missing_past_the_check_is_the_same_line(tmp_path):
    """A command that imports torch where no check came first (here kpd train with its check taken out) still ends
    in the line that names the extra; in a process of its own, whose modules are imported afresh without torch."""
    (tmp_path / "data").mkdir()
    script = ("import sys; sys.modules['torch'] = None\n"
              "import kpd.commands.train as command; command.require_train_extra = lambda *modules: None\n"
              "from kpd.cli import main; sys.exit(main(sys.argv[1:]))")
    done = _run([sys.executable, "-c", script, "train", tmp_path / "data", "--out", tmp_path / "run"], cwd=tmp_path)
    _refused_for_the_train_extra(done)
    assert not (tmp_path / "run").exists()


def test_a_bundle_is_written_again_without_torch(no_torch, tmp_path, capsys):
    from kpd.cli import main

    assert main(["export", "chair", "--rig-cage-distance", "0", "--out", str(tmp_path / "loose.kpd")]) == 0
    assert (tmp_path / "loose.kpd" / "manifest.json").is_file()


# --- the release, installed as a user installs it -----------------------------------------------------------------


def _shipped_files() -> list[str]:
    """The package's data files as a wheel names them: the bundles, the page and what make web copied into it."""
    if not (WEB / "vendor" / "three" / "build" / "three.module.js").is_file():
        _missing("three.js is not in viewer/web/vendor (make web)")
    files = [f"kpd/models/{p.relative_to(REPO / 'kpd' / 'models').as_posix()}"
             for p in (REPO / "kpd" / "models").rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    files += [f"kpd/viewer/web/{p.relative_to(WEB).as_posix()}" for p in WEB.rglob("*")
              if p.is_file() and not p.name.startswith(".")]
    assert any(f.endswith(".onnx") for f in files) and any(f.endswith("GLTFLoader.js") for f in files)
    return sorted(files)


def _build(out: Path) -> tuple[Path, Path]:
    """``make dist``'s build: the sdist, then the wheel built from that sdist (as pip builds one from an sdist)."""
    _ok(_run([sys.executable, "-m", "build", "--outdir", out, REPO], cwd=REPO))
    (sdist,), (wheel,) = out.glob("kpd-*.tar.gz"), out.glob("kpd-*.whl")
    return sdist, wheel


def _install(wheel: Path, venv: Path, wheelhouse: Path) -> Path:
    """A new venv with the wheel and the dependencies it declares, and nothing else; returns its ``bin``.

    pip installs from a wheelhouse of those dependencies (``pip download`` of the wheel fills it on the first run and
    whenever it no longer satisfies them): pip's own cache keeps a downloaded wheel only when the index's answer says
    it may, so the wheelhouse is what keeps the install offline and quick from the second run on."""
    _ok(_run([sys.executable, "-m", "venv", venv], cwd=venv.parent))
    pip = [venv / "bin" / "python", "-m", "pip", "install", "--no-index", "--find-links", wheelhouse, wheel]
    if _run(pip, cwd=venv.parent).returncode != 0:
        _ok(_run([venv / "bin" / "python", "-m", "pip", "download", "--dest", wheelhouse, wheel], cwd=venv.parent))
        for copy in wheelhouse.glob("kpd-*"):  # the wheel itself is given by path
            copy.unlink()
        _ok(_run(pip, cwd=venv.parent))
    return venv / "bin"


def _user_env(home: Path) -> dict:
    """The environment of a user of the new venv: its own home (caches, settings), no display, nothing of this one's
    Python set-up."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "VIRTUAL_ENV", "DISPLAY", "WAYLAND_DISPLAY", "KPD_CACHE", "NUMBA_CACHE_DIR")}
    home.mkdir()
    env["HOME"] = str(home)
    return env


def _check_window(kpd: Path, work: Path, env: dict, chair: Path) -> None:
    """``kpd view`` in a real window on a private Xvfb: a keypoint picked with the mouse, nudged with the arrow key,
    a screenshot (P) and the edited mesh saved (S)."""
    from kpd.io import read_mesh
    from kpd.viewer.app import read_events, wait_for
    from kpd.viewer.render import private_display, project

    events = work / "view_events.jsonl"

    def last(name: str) -> dict | None:
        found = [e for e in read_events(events) if e["event"] == name]
        return found[-1] if found else None

    with private_display(1400, 900) as display:
        window_env = dict(env, DISPLAY=display)
        window = subprocess.Popen([str(kpd), "view", "chair", str(chair), "--scan", "--up", "y", "--size", "480x400",
                                   "--out", "chair_edited.obj", "--screenshot", "chair_view.png", "--events",
                                   str(events)], cwd=work, env=window_env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True)

        def xdo(*argv: object) -> str:
            return _ok(_run(["xdotool", *argv], cwd=work, env=window_env, timeout=60)).stdout

        try:
            ready = wait_for(lambda: last("ready"), 300, "the editor window")
            wid = wait_for(lambda: _run(["xdotool", "search", "--name", f"^{ready['title']}$"], cwd=work,
                                        env=window_env).stdout.split(), 30, "the X window")[-1]
            geometry = dict(line.split("=") for line in xdo("getwindowgeometry", "--shell", wid).split())
            vx, vy, w, h = ready["viewport"]
            keypoints = np.array(ready["keypoints"])
            pixels, _ = project(keypoints, np.array(ready["view"]), np.array(ready["projection"]), w, h)
            inside = (pixels[:, 0] > 40) & (pixels[:, 0] < w - 40) & (pixels[:, 1] > 40) & (pixels[:, 1] < h - 40)
            gaps = np.linalg.norm(pixels[:, None] - pixels[None], axis=2) + np.eye(len(pixels)) * 1e9
            index = int(np.argmax(np.where(inside, gaps.min(axis=1), -1)))  # the one farthest from the others
            x, y = np.rint(pixels[index] + [int(geometry["X"]) + vx, int(geometry["Y"]) + vy]).astype(int)
            xdo("mousemove", x, y)
            xdo("click", 1)
            assert wait_for(lambda: last("select"), 60, "the selection")["picked"] == index
            xdo("key", "Up")
            wait_for(lambda: last("nudge"), 60, "the nudge")
            xdo("key", "p")
            shot = wait_for(lambda: last("screenshot"), 60, "the screenshot")
            xdo("key", "s")
            saved = wait_for(lambda: last("save"), 120, "the saved mesh")
        finally:
            window.terminate()
            try:
                window.wait(30)
            except subprocess.TimeoutExpired:
                window.kill()
                window.wait()
        assert "Traceback" not in window.stderr.read()
    moved = np.flatnonzero(np.abs(np.array(saved["keypoints"]) - keypoints).max(axis=1) > 0)
    assert moved.tolist() == [index]  # the prior is off: the nudge moved the picked keypoint alone
    edited, original = read_mesh(work / "chair_edited.obj"), read_mesh(chair)
    assert len(edited.triangles) == len(original.triangles)
    assert np.abs(edited.vertices - original.vertices).max() > 0
    assert (work / shot["path"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the path as given, in the folder


def _check_browser(kpd: Path, work: Path, env: dict, chair: Path) -> None:
    """``kpd view --browser``: the page at the address the command prints, and three.js as the page's import map
    names it, both served over HTTP."""
    server = subprocess.Popen([str(kpd), "view", "chair", str(chair), "--scan", "--up", "y", "--browser", "--port",
                               "0"], cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    printed: list[str] = []
    reader = threading.Thread(target=lambda: printed.extend(server.stdout), daemon=True)
    reader.start()
    try:
        from kpd.viewer.app import wait_for

        url = wait_for(lambda: next((m.group(0) for line in printed if (m := re.search(r"http://\S+", line))), None),
                       300, "the page's address")
        with urlopen(url, timeout=60) as answer:
            assert answer.status == 200
            page = answer.read().decode("utf-8")
        importmap = json.loads(re.search(r'<script type="importmap">(.*?)</script>', page, re.S).group(1))
        three = urljoin(url, importmap["imports"]["three"])
        query = urlsplit(url).query
        if query and not urlsplit(three).query:
            three += "?" + query
        with urlopen(three, timeout=60) as answer:
            assert answer.status == 200
            assert "javascript" in answer.headers["Content-Type"]
            assert answer.read() == (WEB / "vendor" / "three" / "build" / "three.module.js").read_bytes()
    finally:
        server.terminate()
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
    assert "Traceback" not in server.stderr.read()


@pytest.mark.slow
def test_the_wheel_without_torch_runs_every_runtime_command_from_an_empty_folder(data_dir, tmp_path, pytestconfig):
    if shutil.which("Xvfb") is None or shutil.which("xdotool") is None:
        _missing("Xvfb and xdotool are not installed (make system)")
    shipped = _shipped_files()
    sdist, wheel = _build(tmp_path / "dist")
    with tarfile.open(sdist) as archive:
        root = archive.getnames()[0].split("/")[0]
        in_sdist = set(archive.getnames())
    sources = {f.replace("kpd/viewer/", "viewer/", 1) for f in shipped}
    assert not {f"{root}/{f}" for f in sources} - in_sdist, "the sdist lacks files of the package"
    with zipfile.ZipFile(wheel) as archive:
        assert not set(shipped) - set(archive.namelist()), "the wheel lacks files of the package"

    bin_ = _install(wheel, tmp_path / "venv", pytestconfig.cache.mkdir("kpd-wheelhouse"))
    _ok(_run([bin_ / "python", "-m", "pip", "check"], cwd=tmp_path))
    found = _ok(_run([bin_ / "python", "-c", "import importlib.util as u, kpd, sys; "
                                             "print(u.find_spec('torch') is None, 'torch' in sys.modules)"],
                     cwd=tmp_path)).stdout.split()
    assert found == ["True", "False"], "torch came with the wheel's dependencies"

    data = data_dir
    chair = data / "keypointnet" / "models" / "03001627" / "88382b877be91b2a572f8e1c1caad99e" / "model_normalized.obj"
    other_chair = data / "keypointnet" / "models" / "03001627" / "eaf231f17fccb96d81dff5c2e57ad46e" / "model.obj"
    shoes = sorted((data / "gso_shoes").iterdir())[:4]
    work = tmp_path / "work"
    work.mkdir()
    my_shoes = work / "my_shoes"  # a user's folder of shoes, all of them to test on
    my_shoes.mkdir()
    for shoe in shoes:
        shutil.copyfile(shoe / "model.obj", my_shoes / f"{shoe.name}.obj")
    (my_shoes / "test.txt").write_text("".join(f"{s.name}\n" for s in shoes))
    shoe = my_shoes / f"{shoes[0].name}.obj"
    env = _user_env(tmp_path / "home")
    kpd = bin_ / "kpd"

    def run(*argv: object) -> subprocess.CompletedProcess:
        return _ok(_run([kpd, *argv], cwd=work, env=env))

    from kpd.io import read_mesh

    run("demo", "--out", "demo")
    assert {"demo.png", "rig.npz", "deformed.ply"} <= {p.name for p in (work / "demo").iterdir()}
    original = read_mesh(chair)
    low, high = original.vertices.min(axis=0), original.vertices.max(axis=0)
    run("keypoints", "chair", chair, "--scan", "--up", "y", "--out", "chair_keypoints.json")
    keypoints = np.array(json.loads((work / "chair_keypoints.json").read_text())["keypoints"])
    assert keypoints.shape == (12, 3)
    margin = 0.1 * (high - low)
    assert ((keypoints > low - margin) & (keypoints < high + margin)).all()  # in the file's own frame and units
    run("deform", "chair", chair, "--scan", "--up", "y", "--move", "8:0,0.05,0", "--out", "chair_taller.obj")
    run("align", "chair", chair, other_chair, "--out", "chair_aligned.obj")
    for name in ("chair_taller.obj", "chair_aligned.obj"):
        edited = read_mesh(work / name)
        assert len(edited.triangles) == len(original.triangles)
        assert np.abs(edited.vertices - original.vertices).max() > 1e-3 * np.linalg.norm(high - low)
    run("sample", "chair", chair, "--n", "2", "--out", "chair_variants")
    assert {"variant_000.obj", "variant_001.obj", "contact_sheet.png"} <= set(os.listdir(work / "chair_variants"))
    variants = [read_mesh(work / "chair_variants" / f"variant_00{i}.obj").vertices for i in (0, 1)]
    assert np.abs(variants[0] - variants[1]).max() > 0
    run("render", "chair", chair, "--scan", "--up", "y", "--out", "chair.png")
    assert (work / "chair.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    run("rig", "shoe", shoe, "--out", "shoe.glb")
    assert (work / "shoe.glb").read_bytes()[:4] == b"glTF"
    run("scan", shoe, "--model", "shoe", "--out", "shoe_aligned.ply", "--report", "shoe_report.json")
    aligned = read_mesh(work / "shoe_aligned.ply").vertices
    assert np.abs(aligned).max() <= 1 + 1e-6  # normalised to the [-1, 1] box
    assert np.array(json.loads((work / "shoe_report.json").read_text())["transform"]).shape == (4, 4)
    run("eval", "chamfer", my_shoes, "--model", "shoe", "--pairs", "2", "--out", "shoe_chamfer.json", "--quiet")
    scores = json.loads((work / "shoe_chamfer.json").read_text())
    assert scores["data"]["test_shapes"] == len(shoes) and scores["settings"]["pairs"] == 2
    chamfer = scores["results"]["chamfer_x1e3"]
    assert chamfer["model"]["mean"] < chamfer["no_deformation"]["mean"]  # the model brings a shoe nearer another
    run("amplify", "shoe", my_shoes, "--scan", "--variants", "2", "--out", "shoes_x2", "--sheet", "1")
    records = [json.loads(line) for line in (work / "shoes_x2" / "manifest.jsonl").read_text().splitlines()]
    assert len(records) == 2 * len(shoes) and (work / "shoes_x2" / "contact_sheet.png").exists()
    for r in records:  # in each shoe's own frame and units (not turned, not normalised)
        source = read_mesh(my_shoes / r["source"]).vertices
        variant = read_mesh(work / "shoes_x2" / r["file"]).vertices
        size = np.ptp(source, axis=0)  # (3,), the long axis along z
        assert variant.shape == source.shape and np.abs(variant - source).max() < 0.5 * size.max()
        assert np.argmax(np.ptp(variant, axis=0)) == np.argmax(size)
    from kpd.frame import bind_shape
    from kpd.runtime import Model

    first = [r for r in records if r["source"] == shoe.name]  # the scan rig, deformed to the labels: the variant
    rig = bind_shape(Model.load("shoe"), read_mesh(shoe), scan=True, seed=0)
    for r in first:
        variant = read_mesh(work / "shoes_x2" / r["file"]).vertices
        np.testing.assert_allclose(variant, rig.deform(np.asarray(r["keypoints"])), atol=1e-5 * np.ptp(variant))
    run("bench", "chair", "--vertices", "2000", "--repeats", "1", "--out", "bench.json")
    assert json.loads((work / "bench.json").read_text())["meshes"]
    _check_window(kpd, work, env, chair)
    _check_browser(kpd, work, env, chair)

    (work / "my_run").mkdir()
    _refused_for_the_train_extra(_run([kpd, "train", my_shoes, "--out", "shoe_run"], cwd=work, env=env))
    _refused_for_the_train_extra(_run([kpd, "export", "my_run", "--out", "mine.kpd"], cwd=work, env=env))
    assert not (work / "shoe_run").exists() and not (work / "mine.kpd").exists()
