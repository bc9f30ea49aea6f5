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

import numpy as np
import pytest

from kpd.io import read_mesh
from kpd.morph import MorphRig
from kpd.runtime import Model

from test_morph import REPO, TOLERANCE, corresponding, needs, validate

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
# what works here as root without a display; SwiftShader is Chromium's software WebGL
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1200,800"]


def start_chromium(user_data_dir: str):
    """A selenium session in Debian's headless Chromium (installed by make system)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    needs(CHROMIUM, "Debian's chromium")
    needs(CHROMEDRIVER, "Debian's chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in [*CHROMIUM_FLAGS, f"--user-data-dir={user_data_dir}"]:
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


@pytest.fixture(scope="module")
def chair_file(data_dir) -> Path:
    return data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply"


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
    import urllib.error
    import urllib.request

    out = tmp_path / "later.ply"
    process, url = start_editor("chair", str(chair_file), "--port", "0", "--out", str(out))
    try:
        out.write_text("someone else's")
        request = urllib.request.Request(url + "save", data=json.dumps({"weights": {"keypoint_0_z": 1.0}}).encode(),
                                         headers={"Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as failure:
            urllib.request.urlopen(request, timeout=30)
        answer = json.loads(failure.value.read())
        assert not answer["ok"] and "exists; pass --force" in answer["message"]
        assert out.read_text() == "someone else's"
        import http.client
        from urllib.parse import urlsplit

        address = urlsplit(url)
        for path in ("/../browser.py", "/vendor/../../browser.py", "/%2e%2e/browser.py", "/nothing.js"):
            connection = http.client.HTTPConnection(address.hostname, address.port, timeout=30)
            connection.request("GET", path)  # sent as written: nothing outside the page's folder is served
            assert connection.getresponse().status == 404, path
            connection.close()
        bad = urllib.request.Request(url + "save", data=json.dumps({"weights": {"nose_x": 1.0}}).encode())
        with pytest.raises(urllib.error.HTTPError) as failure:
            urllib.request.urlopen(bad, timeout=30)
        assert "unknown morph target 'nose_x'" in json.loads(failure.value.read())["message"]
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
            with urllib.request.urlopen(editor.url + ("rig.glb?morph=three" if i % 2 else "rig.glb"),
                                        timeout=60) as response:
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
