"""kpd amplify: a collection's variants, the same bytes on any engine, resumable after a kill, failures recorded."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import kpd, peak_of

from kpd.amplify import MANIFEST, find_meshes, output_names, variant_seed
from kpd.io import Mesh, read_mesh, write_mesh
from kpd.io.atomic import TEMP_MARK
from kpd.variants import FOLDED_LIMIT, TYPICAL_SIGMA, attempt_sequence

VARIANTS = 2


def _chair(stretch: tuple[float, float, float]) -> Mesh:
    from kpd.procedural import procedural_chair

    mesh = procedural_chair()
    return mesh.with_vertices(mesh.vertices * np.asarray(stretch))


@pytest.fixture(scope="module")
def collection(tmp_path_factory) -> Path:
    """Three chairs in nested folders (a PLY, a textured OBJ, an OFF) and a file that is not a mesh."""
    root = tmp_path_factory.mktemp("collection") / "chairs"
    (root / "b" / "c").mkdir(parents=True)
    (root / "a").mkdir()
    write_mesh(root / "a" / "one.ply", _chair((1.0, 1.0, 1.0)))
    mesh = _chair((1.2, 0.9, 1.0))
    t = len(mesh.triangles)
    write_mesh(root / "a" / "two.obj", Mesh(
        vertices=mesh.vertices, triangles=mesh.triangles,
        triangle_uvs=np.random.default_rng(0).uniform(0, 1, (3 * t, 2)),
        textures=[np.random.default_rng(1).integers(0, 255, (8, 8, 3), dtype=np.uint8)],
        triangle_material_ids=np.zeros(t, np.int64)))
    write_mesh(root / "b" / "c" / "three.off", _chair((0.9, 1.1, 1.15)))
    (root / "b" / "broken.ply").write_text("ply\nthis is not a mesh\n")
    return root


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / MANIFEST).read_text().splitlines()]


@pytest.fixture(scope="module")
def reference(collection, tmp_path_factory) -> Path:
    """The collection amplified by one local process, with a contact sheet."""
    out = tmp_path_factory.mktemp("runs") / "reference"
    assert kpd("amplify", "chair", collection, "--variants", VARIANTS, "--out", out, "--sheet", "2") == 2
    return out


def test_every_mesh_is_amplified_in_its_format_with_its_labels(collection, reference):
    records = _records(reference)
    failed = [r for r in records if "error" in r]
    assert [r["source"] for r in failed] == ["b/broken.ply"]  # recorded; the others finished
    variants = [r for r in records if "error" not in r]
    assert sorted({r["source"] for r in variants}) == ["a/one.ply", "a/two.obj", "b/c/three.off"]
    assert sorted(r["file"] for r in variants) == [
        "a/one_000.ply", "a/one_001.ply", "a/two_000.obj", "a/two_001.obj", "b/c/three_000.off", "b/c/three_001.off"]
    from kpd.runtime import Model

    model = Model.load("chair", threads=1)
    for r in variants:
        source = read_mesh(collection / r["source"])
        variant = read_mesh(reference / r["file"])
        np.testing.assert_array_equal(variant.triangles, source.triangles)
        assert r["seed"] == variant_seed(0, r["source"], r["variant"])
        keypoints = np.asarray(r["keypoints"])
        assert keypoints.shape == (model.num_keypoints, 3)
        assert len(r["coefficients"]) == model.prior.components_.shape[0]
        # the labels travel with the variant: its vertices are the source's rig deformed to them
        rig = model.rig(source, seed=0)
        np.testing.assert_allclose(variant.vertices, rig.deform(keypoints), atol=1e-5 * np.ptp(source.vertices))
        # seed, attempt and shrink redraw it (kpd.variants.draw_plausible)
        base = rig.normalizer.apply(rig.keypoints)
        rng = np.random.default_rng(attempt_sequence(r["seed"], r["attempt"]))
        drawn = model.prior.sample(1, seed=rng, scale=0.5, base=base, limit=TYPICAL_SIGMA)[0]
        centre = model.prior.typical_base(base, TYPICAL_SIGMA)
        drawn = centre + r["shrink"] * (drawn - centre) if r["shrink"] != 1.0 else drawn
        np.testing.assert_allclose(keypoints, rig.normalizer.invert(drawn), atol=1e-9)
        assert 0 <= r["folded"] <= FOLDED_LIMIT and 0 < r["sigma"] <= TYPICAL_SIGMA + 1e-9
        if r["file"].endswith(".obj"):  # UVs and the texture kept, as kpd deform keeps them
            np.testing.assert_allclose(variant.triangle_uvs, source.triangle_uvs, atol=1e-6)
            assert np.array_equal(variant.textures[0], source.textures[0])
    from PIL import Image

    sheet = np.asarray(Image.open(reference / "contact_sheet.png").convert("RGB"))
    assert sheet.shape[0] > 300 and (sheet < 200).any(axis=2).mean() > 0.02  # two rows drawn, not blank


def test_names_and_seeds():
    assert output_names(["x/chair.obj", "x/chair.ply", "y/chair.off"], 2, ".ply") == {
        "x/chair.obj": ("x/chair_obj_000.ply", "x/chair_obj_001.ply"),
        "x/chair.ply": ("x/chair_ply_000.ply", "x/chair_ply_001.ply"),
        "y/chair.off": ("y/chair_000.ply", "y/chair_001.ply")}
    seeds = {variant_seed(s, p, i) for s in (0, 1) for p in ("a.ply", "b.ply") for i in (0, 1)}
    assert len(seeds) == 8 and variant_seed(0, "a.ply", 1) == variant_seed(0, "a.ply", 1)


def test_two_processes_write_the_same_bytes(collection, reference, tmp_path):
    out = tmp_path / "two"
    assert kpd("amplify", "chair", collection, "--variants", VARIANTS, "--out", out, "--processes", "2",
               "--sheet", "0") == 2
    expected = {k: v for k, v in _files(reference).items() if k != "contact_sheet.png"}
    assert _files(out) == expected


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            children.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(entry))
    found, stack = [], [pid]
    while stack:
        for child in children.get(stack.pop(), []):
            found.append(child)
            stack.append(child)
    return found


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def test_ray_writes_the_same_bytes_and_survives_a_killed_worker(collection, reference, tmp_path):
    pytest.importorskip("ray")
    out = tmp_path / "ray"
    killed: list[int] = []
    stop = threading.Event()

    def kill_one_worker() -> None:  # a worker of this test's own local cluster, while it runs a shape
        while not stop.is_set() and not killed:
            for pid in _descendants(os.getpid()):
                if _cmdline(pid).startswith("ray::_ray_shape"):
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    break
            time.sleep(0.02)

    killer = threading.Thread(target=kill_one_worker, daemon=True)
    killer.start()
    try:
        status = kpd("amplify", "chair", collection, "--variants", VARIANTS, "--out", out, "--engine", "ray",
                     "--processes", "2", "--sheet", "0")
    finally:
        stop.set()
        killer.join()
    assert killed, "no Ray worker was seen running a shape"
    assert status == 2  # the broken file only
    expected = {k: v for k, v in _files(reference).items() if k != "contact_sheet.png"}
    assert _files(out) == expected


def test_a_killed_run_continues_to_the_same_bytes(collection, reference, tmp_path):
    out = tmp_path / "killed"
    argv = [sys.executable, "-m", "kpd.cli", "amplify", "chair", str(collection), "--variants", str(VARIANTS),
            "--out", str(out), "--sheet", "0"]
    process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while process.poll() is None:
            if (out / MANIFEST).exists() and (out / MANIFEST).read_text().count("\n") >= VARIANTS:
                process.send_signal(signal.SIGKILL)
                break
            time.sleep(0.005)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    done_before = {r["source"] for r in _records(out)}
    assert 1 <= len(done_before) < 4
    again = subprocess.run(argv, capture_output=True, text=True, check=False)
    assert again.returncode == 2, again.stderr
    assert f"continuing: {len(done_before)} shape(s) already done" in again.stderr
    expected = {k: v for k, v in _files(reference).items() if k != "contact_sheet.png"}
    assert _files(out) == expected
    assert not [p for p in out.rglob("*") if TEMP_MARK in p.name]  # nothing half-written left


def test_the_same_command_again_does_nothing_and_another_is_refused(collection, reference, tmp_path, capfd):
    out = tmp_path / "again"
    args = ["amplify", "chair", collection, "--variants", VARIANTS, "--out", out, "--sheet", "0"]
    assert kpd(*args) == 2
    before = _files(out)
    capfd.readouterr()
    assert kpd(*args) == 2
    assert _files(out) == before
    assert "continuing: 4 shape(s) already done" in capfd.readouterr().err
    assert kpd(*args, "--scale", "0.7") == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a run with other settings (scale)" in err[0] and "--force" in err[0]
    assert _files(out) == before
    assert kpd(*args, "--scale", "0.7", "--variants", "1", "--force") == 2
    assert sorted(p.name for p in (out / "a").iterdir()) == ["one_000.ply", "two_000.mtl", "two_000.obj",
                                                             "two_000_two_0.png"]


@pytest.mark.parametrize("where", ["inside", "holds", "same", "model"])
def test_out_never_touches_an_input(collection, tmp_path, where, capfd):
    import shutil

    from kpd.bundle import resolve_bundle

    model = "chair"
    out = {"inside": collection / "a" / "variants", "holds": collection.parent, "same": collection,
           "model": tmp_path / "models"}[where]
    if where == "model":  # a bundle inside the folder --force would empty
        model = tmp_path / "models" / "chair.kpd"
        shutil.copytree(resolve_bundle("chair"), model)
    before = _files(collection), _files(tmp_path)
    assert kpd("amplify", model, collection, "--out", out, "--force") == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("model" if where == "model" else "collection") in err[0]
    assert (_files(collection), _files(tmp_path)) == before


def test_ray_missing_is_one_line(collection, tmp_path, monkeypatch, capfd):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    assert kpd("amplify", "chair", collection, "--out", tmp_path / "r", "--engine", "ray") == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'pip install "kpd[cluster]"' in err[0]
    assert not (tmp_path / "r").exists()


def test_find_meshes_is_recursive_and_sorted(collection):
    assert find_meshes(collection) == ["a/one.ply", "a/two.obj", "b/broken.ply", "b/c/three.off"]


def test_an_unreachable_cluster_is_one_line_and_leaves_nothing(collection, tmp_path, capfd):
    pytest.importorskip("ray")
    import socket

    with socket.socket() as closed:  # a port nothing listens on
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    assert kpd("amplify", "chair", collection, "--out", tmp_path / "r", "--engine", "ray", "--ray-address",
               f"127.0.0.1:{port}") == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cannot reach the Ray cluster at 127.0.0.1:{port}" in err[0]
    assert not (tmp_path / "r").exists()


def _record(source: str, variant: int, rng) -> dict:
    return {"source": source, "variant": variant, "file": f"{source}_{variant:03d}.ply", "seed": 1, "attempt": 0,
            "shrink": 1.0, "coefficients": rng.normal(size=8).tolist(), "keypoints": rng.normal(size=(12, 3)).tolist(),
            "sigma": float(rng.uniform(0, 3)), "folded": float(rng.uniform(0, 0.005))}


def test_a_damaged_manifest_keeps_its_finished_shapes_and_is_sorted_at_the_end(tmp_path):
    from kpd.amplify import Manifest, ShapeResult

    rng = np.random.default_rng(0)
    whole = {name: [_record(name, v, rng) for v in range(3)] for name in ("c.ply", "a.ply", "b.ply")}
    lines = [json.dumps(r) for name in ("c.ply", "a.ply") for r in whole[name]]
    lines += [json.dumps(whole["b.ply"][0]), "not json", json.dumps({"source": "e.ply", "error": "unreadable"})]
    (tmp_path / MANIFEST).write_text("\n".join(lines) + "\n" + json.dumps(whole["b.ply"][1])[:40])  # a kill mid-line
    manifest = Manifest(tmp_path, 3)
    assert manifest.done() == {"a.ply", "c.ply", "e.ply"}  # b.ply's records incomplete: to be done again
    assert manifest.read("a.ply") == whole["a.ply"] and manifest.error("e.ply") == "unreadable"
    assert (tmp_path / MANIFEST).read_text().endswith("\n")  # appends start on a line of their own
    manifest.append(ShapeResult("b.ply", list(reversed(whole["b.ply"]))))
    assert manifest.read("b.ply") == whole["b.ply"]
    measures, failures = manifest.measures(["a.ply", "b.ply", "e.ply", "z.ply"])
    assert failures == [("e.ply", "unreadable")] and measures.shape == (6, 2)
    manifest.finish()
    expected = [json.dumps(r) for name in ("a.ply", "b.ply", "c.ply") for r in whole[name]]
    text = (tmp_path / MANIFEST).read_text().splitlines()
    assert [json.loads(t)["source"] for t in text] == ["a.ply"] * 3 + ["b.ply"] * 3 + ["c.ply"] * 3 + ["e.ply"]
    assert text[:9] == expected
    assert Manifest(tmp_path, 3).read("c.ply") == whole["c.ply"]  # read back after the rewrite


def test_the_manifest_of_a_large_collection_is_not_held_in_memory(tmp_path):
    """50,000 records (5,000 shapes x 10, 57 MB of JSON): the driver keeps an index of them, not the records."""
    rng = np.random.default_rng(0)
    template = [_record("x", v, rng) for v in range(10)]
    with open(tmp_path / MANIFEST, "w") as file:
        for i in reversed(range(5000)):  # in the reverse order, so that the end sorts them all again
            for r in template:
                file.write(json.dumps({**r, "source": f"s{i:05d}.ply"}) + "\n")
    size = (tmp_path / MANIFEST).stat().st_size
    code = ("import sys\nfrom kpd.amplify import Manifest, _summary\nm = Manifest(sys.argv[1], 10)\n"
            "s = _summary(m, sorted(m.done()), 0, 0.0)\nm.finish()\nprint(s.done, s.variants)")
    baseline, base_peak = peak_of([sys.executable, "-c", "import kpd.amplify"])
    done, peak = peak_of([sys.executable, "-c", code, str(tmp_path)])
    assert done.returncode == 0 and baseline.returncode == 0, done.stderr
    assert done.stdout.split()[:2] == ["5000", "50000"]
    assert peak - base_peak < 0.5 * size, (peak - base_peak) / 2**20  # the records would take ~6x the file's size
    first = (tmp_path / MANIFEST).open().readline()
    assert json.loads(first)["source"] == "s00000.ply"
