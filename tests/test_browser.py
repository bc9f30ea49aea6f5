"""kpd view --browser: the page in real headless Chromium (SwiftShader WebGL), driven by real mouse events."""

from __future__ import annotations

import contextlib
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

from kpd.io import read_mesh
from kpd.morph import MorphRig
from kpd.runtime import Model

from helpers import REPO, TOLERANCE, corresponding, needs, validate

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
# what works here as root without a display; SwiftShader is Chromium's software WebGL
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1200,800"]


def start_chromium(user_data_dir: str, *flags: str):
    """A selenium session in Debian's headless Chromium (installed by make system), with ``flags`` besides
    :data:`CHROMIUM_FLAGS`."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    needs(CHROMIUM, "Debian's chromium")
    needs(CHROMEDRIVER, "Debian's chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in [*CHROMIUM_FLAGS, *flags, f"--user-data-dir={user_data_dir}"]:
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


def start_editor(*argv: str) -> tuple[subprocess.Popen, str]:
    """``kpd view ... --browser`` in a process of its own; returns it and the URL it printed."""
    process = subprocess.Popen([sys.executable, "-m", "kpd.cli", "view", *argv, "--browser"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, cwd=REPO)
    line = process.stdout.readline()
    match = re.search(r"(http://\S+/)", line)
    if match is None:
        process.kill()
        raise AssertionError(f"no URL printed: {line!r} {process.stderr.read()}")
    return process, match.group(1)


def wait(driver, script: str, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {script}")


def ask(url: str, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
        raw: bytes | None = None) -> tuple[int, dict, bytes]:
    """One request to the server of ``url`` as written (no client rewrites it: any path, Host or header; or the
    bytes ``raw``); returns the answer's status, headers and body. A header given as None is not sent (Host too)."""
    address = urlsplit(url)
    sent = {"Host": address.netloc, **({} if body is None else {"Content-Length": str(len(body))}), **(headers or {})}
    if raw is None:
        lines = [f"{method} {path} HTTP/1.1", *(f"{k}: {v}" for k, v in sent.items() if v is not None), "", ""]
        raw = "\r\n".join(lines).encode("latin-1") + (body or b"")
    with socket.create_connection((address.hostname, address.port), timeout=60) as connection:
        connection.sendall(raw)
        answer = b""
        while chunk := connection.recv(1 << 16):  # one request a connection: the server closes it
            answer += chunk
    head, _, content = answer.partition(b"\r\n\r\n")
    status_line, *header_lines = head.decode("latin-1").split("\r\n")
    answered = dict(line.split(": ", 1) for line in header_lines)
    return int(status_line.split()[1]), answered, content


def save(url: str, value: dict | bytes, **headers: str | None) -> tuple[int, dict]:
    """A save as the editor's page sends it (its secret in the path and the Authorization header, its Origin,
    JSON), with ``headers`` changed; returns the status and the JSON answer."""
    import json

    address = urlsplit(url)
    secret = address.path.strip("/")
    body = value if isinstance(value, bytes) else json.dumps(value).encode()
    sent = {"Authorization": f"Bearer {secret}", "Origin": f"http://{address.netloc}",
            "Content-Type": "application/json", **{k.replace("_", "-"): v for k, v in headers.items()}}
    status, answered, content = ask(url, "POST", f"/{secret}/save", body, sent)
    assert answered["Content-Type"] == "application/json"
    return status, json.loads(content)


@pytest.fixture(scope="module")
def page(chair_file, tmp_path_factory):
    """The editor serving the real chair with the shipped model, a browser on its page, and the output path."""
    needs(REPO / "viewer" / "web" / "vendor" / "three" / "build" / "three.module.js", "three.js (make web)")
    out = tmp_path_factory.mktemp("browser") / "edited.obj"
    with editor_in_chromium("chair", str(chair_file), "--port", "0", "--out", str(out)) as (driver, url):
        yield driver, out, url


@contextlib.contextmanager
def editor_in_chromium(*argv: str):
    """``kpd view ARGV --browser`` and a headless Chromium beside it: yields (driver, the page's URL); both are
    stopped after."""
    process, url = start_editor(*argv)
    profile = tempfile.mkdtemp(prefix="kpd-chromium-")
    driver = None
    try:
        driver = start_chromium(profile)
        yield driver, url
    finally:
        if driver is not None:
            driver.quit()
        process.terminate()
        process.wait(timeout=10)
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="module")
def reference(chair_file):
    model = Model.load("chair")
    mesh = read_mesh(chair_file)
    rig = model.rig(mesh)
    return rig, MorphRig.from_rig(rig, model.prior), mesh


def open_page(driver, url: str) -> None:
    """Load the page afresh and wait for its first picture."""
    driver.get(url)
    wait(driver, "return window.kpd && (window.kpd.ready || window.kpd.error)")
    assert driver.execute_script("return window.kpd.error") is None
    wait(driver, "return window.kpd.stats.firstPicture !== null")


def drag(driver, keypoint: int, dx: int, dy: int, steps: int = 8) -> tuple[float, float]:
    """Press on a keypoint's marker, move the mouse by (dx, dy) pixels in steps, release; returns the end point."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    canvas = driver.find_element(By.TAG_NAME, "canvas")
    x, y = driver.execute_script(f"return window.kpd.keypointScreen({keypoint})")
    width, height = driver.execute_script("const r = arguments[0].getBoundingClientRect(); return [r.width, r.height]",
                                          canvas)
    actions = ActionChains(driver, duration=10)
    actions.move_to_element_with_offset(canvas, round(x - width / 2), round(y - height / 2)).click_and_hold()
    for _ in range(steps):
        actions.move_by_offset(dx // steps, dy // steps)
    actions.release().perform()
    return round(x) + (dx // steps) * steps, round(y) + (dy // steps) * steps


def page_state(driver):
    weights = driver.execute_script("return window.kpd.weights()")
    keypoints = np.array(driver.execute_script("return window.kpd.keypoints()"))
    positions = np.array(driver.execute_script("return window.kpd.positions()")[0]).reshape(-1, 3)
    rest = np.array(driver.execute_script("return window.kpd.restPositions()")[0]).reshape(-1, 3)
    return weights, keypoints, positions, rest


def test_drag_moves_the_keypoint_and_the_mesh_as_the_rig_does(page, reference):
    driver, _, url = page
    rig, morph, mesh = reference
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    open_page(driver, url)
    end = drag(driver, 8, 0, -64)  # the backrest's top corner, up on the screen
    weights, keypoints, positions, rest = page_state(driver)
    moved = {name for name, value in weights.items() if value}
    assert moved and moved <= {"keypoint_8_x", "keypoint_8_y", "keypoint_8_z"}
    # the keypoint is under the mouse where it was released
    assert np.hypot(*(np.array(driver.execute_script("return window.kpd.keypointScreen(8)")) - end)) < 2.0
    np.testing.assert_allclose(keypoints, morph.keypoints_at(weights), atol=1e-9 * diagonal)
    assert np.linalg.norm(keypoints[8] - rig.keypoints[8]) > 0.05 * diagonal
    assert np.abs(np.delete(keypoints - rig.keypoints, 8, axis=0)).max() == 0.0
    index = corresponding(rest, mesh)
    expected = rig.deform(keypoints)[index]
    assert np.abs(positions - expected).max() < TOLERANCE * diagonal
    assert np.abs(positions - rest).max() > 0.05 * diagonal


def test_prior_switch_sliders_undo_redo_reset_and_save(page, reference):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    driver, out, url = page
    rig, morph, mesh = reference
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    open_page(driver, url)
    index = corresponding(page_state(driver)[3], mesh)
    driver.find_element(By.ID, "prior").click()  # the prior switch on: the partner leg follows
    drag(driver, 1, -48, 0)
    weights, keypoints, positions, _ = page_state(driver)
    assert {n for n, v in weights.items() if v} <= {"prior_1_x", "prior_1_y", "prior_1_z"}
    follows = np.linalg.norm(morph.offsets[morph.names.index("prior_1_x")], axis=1)  # (K,)
    follows[1] = 0.0
    partner = int(follows.argmax())  # the keypoint that follows keypoint 1 most (its mirror partner)
    assert np.linalg.norm(keypoints[partner] - rig.keypoints[partner]) > 0.2 * np.linalg.norm(
        keypoints[1] - rig.keypoints[1])
    np.testing.assert_allclose(keypoints, morph.keypoints_at(weights), atol=1e-9 * diagonal)
    assert np.abs(positions - rig.deform(keypoints)[index]).max() < TOLERANCE * diagonal
    after_prior = weights
    slider = driver.find_element(By.CSS_SELECTOR, "#sliders input[data-target='pca_0']")
    slider.send_keys(Keys.ARROW_RIGHT * 30)  # 30 steps of 0.01 standard deviations
    weights = page_state(driver)[0]
    assert weights["pca_0"] == pytest.approx(0.3)
    driver.find_element(By.ID, "undo").click()  # each slider step is one edit
    assert page_state(driver)[0]["pca_0"] == pytest.approx(0.29)
    driver.find_element(By.TAG_NAME, "body").send_keys(Keys.CONTROL + "z" * 29)  # Ctrl+Z, 29 times
    assert page_state(driver)[0] == after_prior
    while driver.find_element(By.ID, "redo").is_enabled():
        driver.find_element(By.ID, "redo").click()
    weights, keypoints, positions, _ = page_state(driver)
    assert weights["pca_0"] == pytest.approx(0.3)
    driver.find_element(By.ID, "save").click()
    message = wait(driver, "return window.kpd.lastSave && window.kpd.lastSave.message")
    assert message.startswith("saved"), message
    saved = read_mesh(out)
    np.testing.assert_array_equal(saved.triangles, mesh.triangles)
    np.testing.assert_allclose(saved.vertices, rig.deform(morph.keypoints_at(weights)), atol=1e-6 * diagonal)
    assert np.abs(saved.vertices[index] - positions).max() < TOLERANCE * diagonal  # the mesh the page showed
    driver.find_element(By.ID, "reset").click()
    weights, keypoints, positions, rest = page_state(driver)
    assert not any(weights.values()) and np.abs(positions - rest).max() == 0.0
    driver.find_element(By.ID, "save").click()  # a second save replaces what this editor wrote
    wait(driver, "return window.kpd.lastSave && window.kpd.lastSave.message.includes('saved') && "
                 "document.getElementById('status').textContent.startsWith('saved')")
    np.testing.assert_allclose(read_mesh(out).vertices, mesh.vertices, atol=1e-6 * diagonal)


def picture(driver) -> np.ndarray:
    """(H, W, 3) the page's WebGL picture as drawn now."""
    import base64
    import io

    from PIL import Image

    url = driver.execute_script("return window.kpd.snapshot()")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB"), dtype=np.int16)


def test_three_morph_targets_and_the_packed_basis_draw_the_same(page, reference):
    """The same edit drawn by three.js's own morph targets (?morph=three) and by the page's packed basis: the same
    positions as Rig.deform, and the same picture from the GPU."""
    driver, _, url = page
    rig, morph, mesh = reference
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    rng = np.random.default_rng(3)
    weights = {n: float(rng.normal() * (0.04 * diagonal if n.startswith(("keypoint_", "prior_")) else 1.0))
               for n in morph.names if rng.uniform() < 0.3}
    pictures = {}
    for mode in ("three", "basis"):
        open_page(driver, url + ("?morph=three" if mode == "three" else ""))
        rest_picture = picture(driver)
        driver.execute_script("window.kpd.setWeights(arguments[0])", weights)
        _, keypoints, positions, rest = page_state(driver)
        np.testing.assert_allclose(keypoints, morph.keypoints_at(weights), atol=1e-9 * diagonal)
        index = corresponding(rest, mesh)
        assert np.abs(positions - rig.deform(keypoints)[index]).max() < TOLERANCE * diagonal
        pictures[mode] = picture(driver)
        assert (np.abs(pictures[mode] - rest_picture).max(axis=2) > 32).mean() > 0.01  # the edit shows
    differs = (np.abs(pictures["three"] - pictures["basis"]).max(axis=2) > 32).mean()
    assert differs < 0.002, differs  # a few edge pixels at most


def test_a_textured_mesh_of_six_materials_moves_in_each_primitive_as_the_rig_does(data_dir):
    """A ShapeNet bench of six textured materials (six glTF primitives, vertices split where UVs differ): each
    primitive carries its own rows of the basis, and both ways of drawing give Rig.deform's positions."""
    needs(REPO / "viewer" / "web" / "vendor" / "three" / "build" / "three.module.js", "three.js (make web)")
    shape = data_dir / "shapenetcore_obj" / "bench" / "50c0de8fb13d6421dbbc9440457e303e" / "models" / \
        "model_normalized.obj"
    model = Model.load("chair")
    mesh = read_mesh(shape)
    assert len(np.unique(mesh.triangle_material_ids)) == 6 and mesh.triangle_uvs is not None
    rig = model.rig(mesh)
    morph = MorphRig.from_rig(rig, model.prior)
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    rng = np.random.default_rng(1)
    weights = {n: float(rng.normal() * (0.04 * diagonal if n.startswith(("keypoint_", "prior_")) else 1.0))
               for n in morph.names if rng.uniform() < 0.3}
    with editor_in_chromium("chair", str(shape), "--port", "0") as (driver, url):
        for mode in ("", "?morph=three"):
            open_page(driver, url + mode)
            driver.execute_script("window.kpd.setWeights(arguments[0])", weights)
            keypoints = np.array(driver.execute_script("return window.kpd.keypoints()"))
            np.testing.assert_allclose(keypoints, morph.keypoints_at(weights), atol=1e-9 * diagonal)
            expected = rig.deform(keypoints)
            positions = driver.execute_script("return window.kpd.positions()")
            rests = driver.execute_script("return window.kpd.restPositions()")
            assert len(positions) == len(rests) == 6
            for moved, rest in zip(positions, rests):
                index = corresponding(np.array(rest).reshape(-1, 3), mesh)
                assert np.abs(np.array(moved).reshape(-1, 3) - expected[index]).max() < TOLERANCE * diagonal


def test_a_large_mesh_is_dragged_as_its_stand_in_without_a_gpu(tmp_path):
    """A primitive of more than PROXY_TRIANGLES triangles comes with the window editor's coarse stand-in over its own
    vertices (extras.kpdStandIn); on a software renderer (SwiftShader here) the page draws it while a keypoint is
    held and dragged, and the whole mesh again on release, where the mesh is Rig.deform's."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    from kpd.io import write_mesh
    from kpd.procedural import procedural_chair
    from kpd.viewer.gl import PROXY_TRIANGLES, proxy_triangles

    needs(REPO / "viewer" / "web" / "vendor" / "three" / "build" / "three.module.js", "three.js (make web)")
    mesh = procedural_chair(edge=0.3)  # 29,336 vertices, 54,224 triangles
    assert len(mesh.triangles) > PROXY_TRIANGLES
    shape = tmp_path / "chair.ply"
    write_mesh(shape, mesh)
    kept, faces = proxy_triangles(mesh.vertices, mesh.triangles, PROXY_TRIANGLES)
    with editor_in_chromium("chair", str(shape), "--port", "0") as (driver, url):
        open_page(driver, url)
        assert driver.execute_script("return window.kpd.standInTriangles()") == [len(faces)]
        assert driver.execute_script("return window.kpd.drawing()") == "whole"
        canvas = driver.find_element(By.TAG_NAME, "canvas")
        x, y = driver.execute_script("return window.kpd.keypointScreen(8)")
        width, height = driver.execute_script("const r = arguments[0].getBoundingClientRect(); "
                                              "return [r.width, r.height]", canvas)
        held = ActionChains(driver, duration=10)
        held.move_to_element_with_offset(canvas, round(x - width / 2), round(y - height / 2)).click_and_hold()
        for _ in range(8):
            held.move_by_offset(0, -5)
        held.perform()
        assert driver.execute_script("return window.kpd.drawing()") == "stand-in"
        ActionChains(driver).release().perform()
        assert driver.execute_script("return window.kpd.drawing()") == "whole"
        _, keypoints, positions, rest = page_state(driver)
        model = Model.load("chair")
        rig = model.rig(read_mesh(shape))
        diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
        assert np.abs(keypoints - rig.keypoints).max() > 0.01 * diagonal  # the drag moved keypoint 8
        assert np.abs(positions - rig.deform(keypoints)[corresponding(rest, mesh)]).max() < TOLERANCE * diagonal


def test_refusals_in_one_line(chair_file, tmp_path):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    try:
        port = busy.getsockname()[1]
        result = subprocess.run([sys.executable, "-m", "kpd.cli", "view", "chair", str(chair_file), "--browser",
                                 "--port", str(port)], capture_output=True, text=True, cwd=REPO, timeout=120)
    finally:
        busy.close()
    assert result.returncode == 2 and "in use" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    existing = tmp_path / "edited.obj"
    existing.write_text("mine")
    result = subprocess.run([sys.executable, "-m", "kpd.cli", "view", "chair", str(chair_file), "--browser",
                             "--port", "0", "--out", str(existing)], capture_output=True, text=True, cwd=REPO,
                            timeout=120)
    assert result.returncode == 2 and "exists; pass --force" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and existing.read_text() == "mine"


def test_save_refusals_and_nothing_served_outside_the_page(chair_file, tmp_path):
    """The save refuses (in the page's status line) to replace a file the editor did not write, without --force, and
    an unknown target; the server sends no file outside the page's folder."""
    import json

    out = tmp_path / "later.ply"
    process, url = start_editor("chair", str(chair_file), "--port", "0", "--out", str(out))
    try:
        out.write_text("someone else's")
        status, answer = save(url, {"weights": {"keypoint_0_z": 1.0}})
        assert status == 400 and not answer["ok"] and "exists; pass --force" in answer["message"]
        assert out.read_text() == "someone else's"
        secret = urlsplit(url).path.strip("/")
        for path in ("/../browser.py", "/vendor/../../browser.py", "/%2e%2e/browser.py", "/nothing.js"):
            # sent as written: nothing outside the page's folder is served
            assert ask(url, "GET", f"/{secret}{path}")[0] == 404, path
        status, answer = save(url, {"weights": {"nose_x": 1.0}})
        assert status == 400 and "unknown morph target 'nose_x'" in answer["message"]
        assert json.loads(ask(url, "GET", f"/{secret}/nothing.js")[2]) == {"ok": False, "message": "not found"}
    finally:
        process.terminate()
        process.wait(timeout=10)


def test_the_page_s_rig_is_sent_from_a_temporary_file_without_a_name(reference, tmp_path):
    """The GLB the page loads (the mesh with the basis as vertex attributes, no morph targets) waits in a temporary
    file without a name (not in memory) and is sent whole to requests at once, the same bytes as gltf_bytes; the
    keypoint targets' GLB (?morph=three) is made when first asked for; closing the editor lets both go."""
    import os
    import threading
    import urllib.request

    from kpd.io.gltf import read_accessor, read_buffers, read_gltf_json
    from kpd.morph import gltf_bytes
    from kpd.viewer.browser import BrowserEditor, page_files_missing

    if page_files_missing():
        pytest.skip("three.js is not installed (make web)")
    _, morph, _ = reference
    editor = BrowserEditor(port=0)
    server = threading.Thread(target=editor.serve_forever, daemon=True)
    server.start()
    try:
        editor.show(morph, name="chair_0890")
        assert os.fstat(editor.glb.fileno()).st_nlink == 0  # nothing to find, or to leave behind, in the folder
        page = gltf_bytes(morph, name="chair_0890", targets=[], basis=True)
        targets = gltf_bytes(morph, name="chair_0890", targets=[n for n in morph.names if n.startswith("keypoint_")])
        assert editor.glb_size == len(page) < len(targets) / 4
        answers = [None] * 6

        def fetch(i: int) -> None:
            request = urllib.request.Request(editor.url + ("rig.glb?morph=three" if i % 2 else "rig.glb"),
                                             headers={"Authorization": f"Bearer {editor.secret}"})
            with urllib.request.urlopen(request, timeout=60) as response:
                answers[i] = (response.headers["Content-Type"], response.read())

        readers = [threading.Thread(target=fetch, args=(i,)) for i in range(len(answers))]
        for reader in readers:
            reader.start()
        for reader in readers:
            reader.join(timeout=120)
        assert answers == [("model/gltf-binary", page), ("model/gltf-binary", targets)] * 3
        # the basis columns, four to an attribute, are the x components of the keypoint targets
        files = {}
        for label, content in (("page", page), ("targets", targets)):
            files[label] = tmp_path / f"{label}.glb"
            files[label].write_bytes(content)
        report = validate(files["page"])  # the Khronos validator: an application's attribute is valid glTF
        assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]
        doc, chunk = read_gltf_json(files["page"])
        buffers = read_buffers(files["page"], doc, chunk)
        primitive = doc["meshes"][0]["primitives"][0]
        assert "targets" not in primitive and "weights" not in doc["meshes"][0]
        assert "extras" not in primitive  # no stand-in for a mesh this small
        k = len(morph.keypoints)
        basis = np.concatenate([read_accessor(files["page"], doc, buffers, primitive["attributes"][f"_KPD_BASIS_{j}"])
                                for j in range(-(-k // 4))], axis=1)
        assert (basis[:, k:] == 0).all() and (basis[:, :k] != 0).any()
        doc, chunk = read_gltf_json(files["targets"])
        buffers = read_buffers(files["targets"], doc, chunk)
        names = doc["meshes"][0]["extras"]["targetNames"]
        for i in range(k):
            index = doc["meshes"][0]["primitives"][0]["targets"][names.index(f"keypoint_{i}_x")]["POSITION"]
            target = read_accessor(files["targets"], doc, buffers, index)
            np.testing.assert_array_equal(basis[:, i], target[:, 0])
            assert (target[:, 1:] == 0).all()
        glbs = [editor.glb, editor.targets_glb()[0]]
        editor.close()
        assert all(glb.closed for glb in glbs) and editor.glb is None
    finally:
        editor.shutdown()
        server.join(timeout=10)


# --- what the server trusts (docs/editor.md, "What the browser editor trusts") ------------------------------------


@pytest.fixture
def served(reference, tmp_path):
    """The editor in this process, serving the chair's rig and saving to ``tmp_path / "edited.obj"`` (absent)."""
    import threading

    from kpd.viewer.browser import BrowserEditor, page_files_missing

    if page_files_missing():
        pytest.skip("three.js is not installed (make web)")
    editor = BrowserEditor(out=tmp_path / "edited.obj", port=0)
    editor.show(reference[1], name="chair_0890")
    server = threading.Thread(target=editor.serve_forever, daemon=True)
    server.start()
    yield editor
    editor.shutdown()
    server.join(timeout=10)
    editor.close()


PAGE_PATHS = ("/", "/index.html", "/app.js", "/style.css", "/vendor/three/build/three.module.js",
              "/vendor/three/examples/jsm/loaders/GLTFLoader.js", "/info.json", "/rig.glb", "/rig.glb?morph=three")


def test_every_request_needs_this_launch_s_secret(served):
    """The page, its files, three.js, the rig, its info and the save: without the secret of this launch (another
    user of the machine, a page that guesses the port) each is refused, 403 with a JSON answer; the API (the rig,
    its info, the save) also needs it in the Authorization header; with it, each is served."""
    import json

    from kpd.viewer.browser import BrowserEditor

    url, secret = served.url, served.secret
    assert urlsplit(url).path == f"/{secret}/" and re.fullmatch(r"[A-Za-z0-9_-]{43}", secret)
    wrong = secret[:-1] + ("A" if secret[-1] != "A" else "B")
    api = {"Authorization": f"Bearer {secret}"}
    for path in PAGE_PATHS:
        for prefix in ("", f"/{wrong}", f"/{secret[:-1]}", f"/{secret}x", "/" + secret.lower()):
            status, headers, body = ask(url, "GET", prefix + path, headers=api)
            assert status == 403 and headers["Content-Type"] == "application/json", (prefix, path)
            assert json.loads(body)["ok"] is False
        status, _, body = ask(url, "GET", f"/{secret}{path}", headers=api)
        assert status == 200 and body, path
    for path in ("/info.json", "/rig.glb"):
        for headers in ({}, {"Authorization": f"Bearer {wrong}"}, {"Authorization": secret},
                        {"Authorization": f"Basic {secret}"}):
            assert ask(url, "GET", f"/{secret}{path}", headers=headers)[0] == 403, (path, headers)
    edit = json.dumps({"weights": {"keypoint_0_z": 0.01}}).encode()
    assert save(url, edit, Authorization=f"Bearer {wrong}") == (403, {"ok": False, "message": "/save is for the "
                                                                      "editor's page only"})
    assert save(url, edit, Authorization=None)[0] == 403
    status, _, _ = ask(url, "POST", f"/{wrong}/save", edit, {"Authorization": f"Bearer {secret}", "Origin":
                                                              f"http://{urlsplit(url).netloc}",
                                                              "Content-Type": "application/json"})
    assert status == 403 and not served.out.exists()
    assert ask(url, "GET", f"/{secret}", headers=api)[1]["Location"] == f"/{secret}/"  # the folder's slash
    other = BrowserEditor(port=0)  # a secret of each launch
    try:
        assert other.secret != secret and urlsplit(other.url).path == f"/{other.secret}/"
    finally:
        other.server.server_close()


def test_the_host_header_must_name_this_server(served):
    """DNS rebinding: a page of another name that resolves to this machine sends its own name as Host, and is
    refused (421) however right the rest of the request is; localhost, 127.0.0.1 and [::1] at any port (an SSH
    forward changes it) are this server's names."""
    url, secret = served.url, served.secret
    port = urlsplit(url).port
    api = {"Authorization": f"Bearer {secret}"}
    for host in ("attacker.example", f"attacker.example:{port}", f"127.0.0.1.attacker.example:{port}",
                 f"localhost.attacker.example:{port}", f"evil.localhost:{port}", f"127.0.0.1:{port}@attacker.example",
                 f"10.1.2.3:{port}", "", None):
        for path in ("/", "/rig.glb", "/info.json"):
            status, headers, _ = ask(url, "GET", f"/{secret}{path}", headers={**api, "Host": host})
            assert status == 421 and headers["Content-Type"] == "application/json", (host, path)
        status, _ = save(url, {"weights": {"keypoint_0_z": 0.01}}, Host=host, Origin=f"http://{host}")
        assert status == 421, host
    assert not served.out.exists()
    for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}", "localhost:9000", "LOCALHOST", "127.0.0.2"):
        assert ask(url, "GET", f"/{secret}/", headers={"Host": host})[0] == 200, host
    assert save(url, {"weights": {"keypoint_0_z": 0.01}}, Host="localhost:9000",
                Origin="http://localhost:9000")[0] == 200


def test_a_save_comes_only_from_the_page_s_origin_as_json(served):
    """What a page of another site can send without a preflight (a form, a no-cors fetch: text/plain, a form's
    types) or with another Origin is refused before anything is written; the page's own save is taken."""
    url = served.url
    edit = {"weights": {"keypoint_0_z": 0.01}}
    for origin in ("http://attacker.example", f"http://127.0.0.1:{urlsplit(url).port + 1}", "null", "", None,
                   f"https://{urlsplit(url).netloc}", f"http://{urlsplit(url).netloc}.attacker.example"):
        status, answer = save(url, edit, Origin=origin)
        assert status == 403 and "only the editor's own page" in answer["message"], origin
    assert save(url, edit, Sec_Fetch_Site="cross-site")[0] == 403
    assert save(url, edit, Sec_Fetch_Site="same-site")[0] == 403
    for kind in ("text/plain", "text/plain;charset=UTF-8", "application/x-www-form-urlencoded",
                 "multipart/form-data; boundary=x", "application/jsonx", "", None):
        status, answer = save(url, edit, Content_Type=kind)
        assert status == 415 and not answer["ok"], kind
    assert not served.out.exists()
    status, answer = save(url, edit, Content_Type="application/json; charset=utf-8")
    assert status == 200 and answer["ok"] and served.out.exists()


def test_bad_requests_are_answered_in_json_and_the_server_goes_on(served, capfd, caplog):
    """Each malformed request is a 4xx answer with a JSON body (never a traceback on the server, never a dropped
    connection), the server keeps serving, and nothing is written."""
    import json
    import logging

    url, secret = served.url, served.secret
    caplog.set_level(logging.WARNING, logger="kpd.viewer.browser")
    bodies = [b'{"weights": {"keypoint_0_z": null}}', b'{"weights": {"keypoint_0_z": ' + b"9" * 400 + b"}}",
              b"[" * 100_000, b"{" * 100_000, b'{"weights": ' * 50_000, b'{"weights": {"keypoint_0_z": "1"}}',
              b'{"weights": {"keypoint_0_z": true}}', b'{"weights": {"keypoint_0_z": [1]}}',
              b'{"weights": {"keypoint_0_z": NaN}}', b'{"weights": {"keypoint_0_z": -Infinity}}',
              b'{"weights": {"keypoint_0_z": 1e999}}', b'{"weights": {"keypoint_0_z": 1e300}}',
              b'{"weights": {"keypoint_0_z": 1, "keypoint_0_z": 2}}', b'{"weights": {"nose": 1}}',
              b'{"weights": {"\\u0000": 1}}', b'{"weights": {"' + b"k" * 5000 + b'": 1}}',
              b'{"weights": {}, "more": 1}', b'{"weights": []}', b"[]", b"null", b"1", b'"weights"', b"",
              b"\xff\xfe{}", b'{"weights": {"keypoint_0_z": 1}', b"{'weights': {}}", b"\x00",
              b'{"weights": {"keypoint_0_z": ' + b"[" * 900 + b"]" * 900 + b"}}"]
    for body in bodies:
        status, answer = save(url, body)
        assert status == 400 and answer["ok"] is False and answer["message"], body[:60]
    assert save(url, bodies[0])[1]["message"] == "the weight of keypoint_0_z must be a finite number; got null"
    page = ask(url, "GET", f"/{secret}/")
    host = urlsplit(url).netloc
    requests = {  # a path of no file, too long, too many headers, no method of the editor's, not HTTP: the status
        "a NUL in the path": (f"GET /{secret}/\x00 HTTP/1.1\r\nHost: {host}\r\n\r\n", 404),
        "an escaped NUL": (f"GET /{secret}/%00 HTTP/1.1\r\nHost: {host}\r\n\r\n", 404),
        "a path of 5,000 characters": (f"GET /{secret}/{'a' * 5000} HTTP/1.1\r\nHost: {host}\r\n\r\n", 404),
        "a path of 5,000 folders": (f"GET /{secret}/{'a/' * 5000} HTTP/1.1\r\nHost: {host}\r\n\r\n", 404),
        "a NUL in a save's path": (f"POST /{secret}/save\x00 HTTP/1.1\r\nHost: {host}\r\nOrigin: http://{host}\r\n\r\n",
                                   404),
        "a request line of 70,000": (f"GET /{secret}/{'a' * 70_000} HTTP/1.1\r\nHost: {host}\r\n\r\n", 414),
        "a header of 70,000": (f"GET /{secret}/ HTTP/1.1\r\nHost: {host}\r\nX: {'a' * 70_000}\r\n\r\n", 431),
        "200 headers": (f"GET /{secret}/ HTTP/1.1\r\nHost: {host}\r\n" + "X: 1\r\n" * 200 + "\r\n", 431),
        "another method": (f"DELETE /{secret}/ HTTP/1.1\r\nHost: {host}\r\n\r\n", 405),
        "a method of none": (f"FOO /{secret}/ HTTP/1.1\r\nHost: {host}\r\n\r\n", 405),
        "a preflight": (f"OPTIONS /{secret}/save HTTP/1.1\r\nHost: {host}\r\n\r\n", 405),
        "not HTTP": ("\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n", 400),
        "HTTP/0.9": (f"GET /{secret}/\r\n\r\n", 421),  # no Host
        "a version of none": (f"GET /{secret}/ HTTP/9.9\r\nHost: {host}\r\n\r\n", 400),
    }
    for what, (raw, expected) in requests.items():
        status, headers, body = ask(url, "", "", raw=raw.encode("latin-1"))
        assert status == expected and headers["Content-Type"] == "application/json", (what, status)
        assert json.loads(body)["ok"] is False, what
    api = {"Authorization": f"Bearer {secret}", "Origin": f"http://{urlsplit(url).netloc}",
           "Content-Type": "application/json"}
    for length, status in (("2000000", 413), (str(1 << 60), 413), ("9" * 5000, 413), ("-1", 400), ("1e3", 400),
                           ("0x10", 400), ("\u00b2", 400)):
        # the length alone, no body: refused before any byte of it is read
        assert ask(url, "POST", f"/{secret}/save", headers={**api, "Content-Length": length})[0] == status, length
    assert ask(url, "POST", f"/{secret}/save", headers={**api, "Transfer-Encoding": "chunked"})[0] == 411
    assert ask(url, "POST", f"/{secret}/save", b"x" * ((1 << 20) + 1), headers=api)[0] == 413
    assert ask(url, "GET", f"/{secret}/")[2] == page[2] and page[0] == 200  # the server goes on
    assert not served.out.exists()
    assert "Traceback" not in capfd.readouterr().err
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]  # no fault of the server's own


def test_slow_connections_do_not_exhaust_the_server(reference):
    """300 connections that send part of their headers and no more (slowloris), one that sends a byte now and
    then, and one whose body never comes: at most MAX_CONNECTIONS threads serve them at once (the others are
    answered 503 at once), each is cut at the editor's timeout (408 for a body), and the server serves again."""
    import json
    import select
    import threading

    from kpd.viewer.browser import MAX_CONNECTIONS, BrowserEditor

    editor = BrowserEditor(port=0, timeout=2.0)
    editor.show(reference[1])
    server = threading.Thread(target=editor.serve_forever, daemon=True)
    server.start()
    url, secret = editor.url, editor.secret
    address = urlsplit(url)
    held = []
    try:
        before = threading.active_count()
        for _ in range(300):
            connection = socket.create_connection((address.hostname, address.port), timeout=60)
            connection.sendall(f"GET /{secret}/ HTTP/1.1\r\nHost: {address.netloc}\r\nX-Slow: ".encode())
            held.append(connection)
        assert threading.active_count() - before <= MAX_CONNECTIONS
        answers = []
        for connection in held:  # each is answered or closed by the server: none is held for ever
            answer = b""
            with contextlib.suppress(ConnectionResetError):
                while chunk := connection.recv(4096):
                    answer += chunk
            answers.append(answer)
        busy = [a for a in answers if a]  # those beyond the threads, answered at once (or reset meanwhile)
        assert busy and all(a.startswith(b"HTTP/1.0 503 ") for a in busy)
        assert json.loads(busy[0].partition(b"\r\n\r\n")[2])["ok"] is False
        assert ask(url, "GET", f"/{secret}/")[0] == 200
        trickle = socket.create_connection((address.hostname, address.port), timeout=60)
        request = f"GET /{secret}/ HTTP/1.1\r\nHost: {address.netloc}\r\n" + "X-Slow: 1\r\n" * 1000
        sent = 0
        with contextlib.suppress(ConnectionError):
            while sent < len(request) and not select.select([trickle], [], [], 0.05)[0]:
                trickle.sendall(request[sent].encode())  # a byte every 50 ms: 12 s in all, were it let
                sent += 1
        assert sent < len(request)
        assert trickle.recv(4096) == b""  # cut, unanswered
        trickle.close()
        api = {"Authorization": f"Bearer {secret}", "Origin": f"http://{address.netloc}",
               "Content-Type": "application/json", "Content-Length": "100"}
        status, _, body = ask(url, "POST", f"/{secret}/save", headers=api)  # no body comes
        assert status == 408 and json.loads(body)["ok"] is False
        assert ask(url, "GET", f"/{secret}/")[0] == 200
    finally:
        for connection in held:
            connection.close()
        editor.shutdown()
        server.join(timeout=10)
        editor.close()


def test_a_host_others_can_reach_is_warned_of(chair_file):
    """--host 0.0.0.0 prints one warning line (stderr) that anyone who reaches the port with the address can edit;
    the server then takes this machine's names and any IP address as Host (an IP address cannot be rebound), but
    no other name; on loopback (the default) there is no warning."""
    exposed, url = start_editor("chair", str(chair_file), "--port", "0", "--host", "0.0.0.0")
    quiet, _ = start_editor("chair", str(chair_file), "--port", "0")
    try:
        warning = exposed.stderr.readline()
        port = urlsplit(url).port
        assert warning.startswith(f"warning: --host 0.0.0.0 is not a loopback address: anyone who can reach port "
                                  f"{port} and has the address printed next can use this editor")
        assert urlsplit(url).hostname == socket.gethostname()
        secret = urlsplit(url).path.strip("/")
        local = f"http://127.0.0.1:{port}/{secret}/"
        for host in (f"192.0.2.7:{port}", f"[2001:db8::1]:{port}", f"{socket.gethostname()}:{port}", "localhost"):
            assert ask(local, "GET", f"/{secret}/", headers={"Host": host})[0] == 200, host
        assert ask(local, "GET", f"/{secret}/", headers={"Host": f"attacker.example:{port}"})[0] == 421
    finally:
        for process in (exposed, quiet):
            process.terminate()
        for process in (exposed, quiet):
            process.wait(timeout=60)
    assert exposed.stderr.read().count("warning") == 0  # the one line only
    assert "warning" not in quiet.stderr.read()


ATTACK = """<!doctype html>
<html><body>
<iframe name="sink" id="sink"></iframe>
<form id="form" method="POST" enctype="text/plain" action="{editor}save" target="sink">
<input name='{{"weights": {{"keypoint_0_z": 0.05}}, "x": "' value='"}}'></form>
<script>
// what a page of another origin can try on the editor, knowing even its secret
window.results = {{}};
const editor = '{editor}';
const body = JSON.stringify({{weights: {{keypoint_0_z: 0.05}}}});
async function attempt(name, work) {{
  try {{ results[name] = await work(); }} catch (error) {{ results[name] = `failed: ${{error}}`; }}
}}
(async () => {{
  await attempt('noCorsSave', async () => {{
    const r = await fetch(editor + 'save', {{ method: 'POST', mode: 'no-cors', body,
      headers: {{ 'Content-Type': 'text/plain' }} }});
    return `${{r.type}} ${{r.status}}`;
  }});
  await attempt('noCorsSaveWithoutSecret', async () => {{
    const r = await fetch(new URL('/save', editor), {{ method: 'POST', mode: 'no-cors', body }});
    return `${{r.type}} ${{r.status}}`;
  }});
  await attempt('corsSave', async () => {{
    const r = await fetch(editor + 'save', {{ method: 'POST', body, headers: {{ 'Content-Type': 'application/json',
      Authorization: `Bearer {secret}` }} }});
    return `read ${{r.status}}`;
  }});
  await attempt('readRig', async () => `read ${{(await (await fetch(editor + 'rig.glb')).arrayBuffer()).byteLength}}`);
  await attempt('readRigWithHeader', async () => {{
    const r = await fetch(editor + 'rig.glb', {{ headers: {{ Authorization: `Bearer {secret}` }} }});
    return `read ${{(await r.arrayBuffer()).byteLength}}`;
  }});
  await attempt('noCorsRig', async () => {{
    const r = await fetch(editor + 'rig.glb', {{ mode: 'no-cors' }});
    return `${{r.type}} ${{(await r.arrayBuffer()).byteLength}}`;
  }});
  await attempt('readPage', async () => `read ${{(await (await fetch(editor)).text()).length}}`);
  document.getElementById('sink').addEventListener('load', () => {{ results.formDone = true; }});
  results.fetchesDone = true;
  document.getElementById('form').submit();
}})();
</script></body></html>"""


def test_a_page_of_another_origin_can_neither_save_nor_read(served, caplog, tmp_path):
    """In real Chromium, a page served from another origin beside the editor (another port of 127.0.0.1, as another
    user's server would be) tries what a browser lets any page do: a no-cors POST of text/plain to /save, an
    auto-submitted form of enctype text/plain, CORS fetches of the rig, the page and a save (refused at their
    preflight), a no-cors fetch of the rig (opaque); and a page at a name that DNS resolves to this machine
    (rebinding) asks for the editor. None saves (the output stays absent: the server refused each with 403 or
    421) and none reads a byte; then the editor's own page, in the same browser, loads and saves."""
    import http.server
    import logging
    import threading

    from selenium.webdriver.common.by import By

    caplog.set_level(logging.DEBUG, logger="kpd.viewer.browser")
    url, secret = served.url, served.secret
    page = ATTACK.format(editor=url, secret=secret).encode()

    class Attacker(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *args) -> None:
            pass

    attacker = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Attacker)
    threading.Thread(target=attacker.serve_forever, daemon=True).start()
    port = urlsplit(url).port
    driver = start_chromium(str(tmp_path / "chromium"), "--host-resolver-rules=MAP attacker.example 127.0.0.1")
    try:
        driver.get(f"http://127.0.0.1:{attacker.server_address[1]}/")
        results = wait(driver, "return window.results.fetchesDone && window.results.formDone && window.results")
        # sent, but nothing came back to the page: no-cors answers are blocked by Cross-Origin-Resource-Policy
        for name in ("noCorsSave", "noCorsSaveWithoutSecret", "corsSave", "readRig", "readRigWithHeader",
                     "noCorsRig", "readPage"):
            assert results[name].startswith("failed: TypeError"), (name, results[name])
        driver.get(f"http://attacker.example:{port}/{secret}/")  # DNS rebinding: the name is the attacker's
        assert "answers only to the address" in driver.find_element(By.TAG_NAME, "body").text
        assert not served.out.exists()
        answers = [r.getMessage() for r in caplog.records if r.getMessage().startswith("127.0.0.1 ")]
        statuses = [a.split('" ')[-1].split()[0] for a in answers]
        # the three POSTs (two no-cors fetches, the form), the GETs: refused; the preflights: no CORS allowed
        assert sum('"POST ' in a for a in answers) == 3 and sum('"GET ' in a for a in answers) >= 4, answers
        rebound = statuses.index("421")  # the page at the attacker's name, and its icon
        assert all(status == ("405" if '"OPTIONS ' in a else "403") for a, status in
                   zip(answers[:rebound], statuses[:rebound])), answers
        assert rebound >= 8 and set(statuses[rebound:]) == {"421"}, answers
        open_page(driver, url)  # the editor's own page still works
        driver.find_element(By.ID, "save").click()
        message = wait(driver, "return window.kpd.lastSave && window.kpd.lastSave.message")
        assert message.startswith("saved") and served.out.exists()
    finally:
        driver.quit()
        attacker.shutdown()
        attacker.server_close()
