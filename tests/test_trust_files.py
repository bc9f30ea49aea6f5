"""Files from others: the files an OBJ, its MTL or a glTF names are read only inside the input's folder tree, only
when they are what they claim, and never copied otherwise (kpd.io.references); every size a glTF declares is checked
before memory is taken for it.

Each hostile case is a regression test of issue 51: nothing outside the folder is read or copied beside the output,
and each such reference is exactly one warning line naming it, through the library and through ``kpd deform``.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from helpers import make_toy_bundle, peak_of

from kpd.cage import icosphere
from kpd.errors import InputError
from kpd.io import read_mesh, references, write_mesh

SECRET = b"SECRET-7f3a"


def png(rgb=(200, 30, 30), size=(4, 4)) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", size, rgb).save(buffer, format="PNG")
    return buffer.getvalue()


def sphere_obj_lines() -> list[str]:
    """An icosphere as OBJ lines with UVs, its faces using material ``m``."""
    cage = icosphere(1, 1.0)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in cage.vertices]
    lines += [f"vt {0.5 + 0.5 * x:.6f} {0.5 + 0.5 * y:.6f}" for x, y, _ in cage.vertices]
    lines += ["usemtl m"] + [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in cage.faces + 1]
    return lines


def hostile_obj(tmp_path: Path) -> tuple[Path, list[str]]:
    """``tmp/a/in/chair.obj`` naming files that must not be read: returns the OBJ and the references (each must be
    named by exactly one warning). Outside the folder: ``tmp/a/victim/.ssh/id_rsa``, ``tmp/x``, a decodable
    ``tmp/a/victim/real.png`` (reached through a symlink inside the folder)."""
    folder = tmp_path / "a" / "in"
    (tmp_path / "a" / "victim" / ".ssh").mkdir(parents=True)
    folder.mkdir()
    (tmp_path / "a" / "victim" / ".ssh" / "id_rsa").write_bytes(SECRET + b" private key\n")
    (tmp_path / "x").write_bytes(png((1, 2, 3)) + SECRET)
    (tmp_path / "a" / "victim" / "real.png").write_bytes(png((9, 9, 9)) + SECRET)
    (folder / "link.png").symlink_to(tmp_path / "a" / "victim" / "real.png")
    (folder / "environ.png").symlink_to("/proc/self/environ")
    (folder / "zero.png").symlink_to("/dev/zero")
    os.mkfifo(folder / "fifo.png")  # not a regular file: reading it would wait for a writer forever
    (folder / "notes.png").write_bytes(b"not an image " + SECRET)
    with open(folder / "big.png", "wb") as fh:  # sparse: larger than the bound, without taking the disk
        fh.truncate(references.IMAGE_BYTES + 1)
    (folder / "binary.mtl").write_bytes(b"newmtl b\n\0\1\2" + SECRET)
    (folder / "good.png").write_bytes(png((20, 200, 20)))
    (folder / "chair.mtl").write_text(
        "newmtl m\nKd 0.5 0.5 0.5\nmap_Kd /etc/passwd\nmap_Ks ../../x\nbump /proc/self/environ\n"
        "map_Ka link.png\nmap_Pr environ.png\nmap_Pm zero.png\nmap_d fifo.png\nnorm notes.png\nmap_Ke big.png\n"
        "disp good.png\n")
    lines = ["mtllib ../victim/.ssh/id_rsa", "mtllib binary.mtl", "mtllib chair.mtl"] + sphere_obj_lines()
    (folder / "chair.obj").write_text("\n".join(lines) + "\n")
    named = ["../victim/.ssh/id_rsa", "binary.mtl", "/etc/passwd", "../../x", "/proc/self/environ", "link.png",
             "environ.png", "zero.png", "fifo.png", "notes.png", "big.png"]
    return folder / "chair.obj", named


def warnings_naming(lines: list[str], named: list[str]) -> dict[str, int]:
    return {name: sum(repr(name) in line and "is not read" in line for line in lines) for name in named}


def assert_nothing_leaked(out: Path, allowed: set[str]) -> None:
    assert {p.name for p in out.parent.iterdir()} == allowed
    for p in out.parent.iterdir():
        assert SECRET not in p.read_bytes(), p
        assert b"private key" not in p.read_bytes()


def test_an_obj_reads_and_copies_nothing_outside_its_folder(tmp_path, caplog):
    path, named = hostile_obj(tmp_path)
    with caplog.at_level(logging.WARNING):
        mesh = read_mesh(path)
    lines = [r.getMessage() for r in caplog.records]
    assert warnings_naming(lines, named) == {name: 1 for name in named}, lines
    assert len(lines) == len(named), lines  # nothing else: no "missing", no second line for the same file
    reasons = {name: next(line for line in lines if repr(name) in line) for name in named}
    assert "outside the input's folder" in reasons["../victim/.ssh/id_rsa"] and "outside" in reasons["link.png"]
    assert "an absolute path" in reasons["/etc/passwd"] and "a system file" in reasons["environ.png"]
    assert "a system file" in reasons["zero.png"] and "not a regular file" in reasons["fifo.png"]
    assert "not an image" in reasons["notes.png"] and "not a text file" in reasons["binary.mtl"]
    assert f"over the {references.IMAGE_BYTES}" in reasons["big.png"]
    out = tmp_path / "out" / "edited.obj"
    out.parent.mkdir()
    write_mesh(out, mesh.with_vertices(mesh.vertices * 1.5))
    assert_nothing_leaked(out, {"edited.obj", "edited.mtl", "edited_good.png"})
    library = (out.parent / "edited.mtl").read_text()
    assert "map_Kd" not in library.replace("# map_Kd /etc/passwd (not read by kpd)", "")
    assert "disp edited_good.png" in library
    text = (out.parent / "edited.obj").read_text()
    assert "# mtllib ../victim/.ssh/id_rsa (not read by kpd)" in text and "mtllib edited.mtl" in text


def test_kpd_deform_reads_and_copies_nothing_outside_the_folder(tmp_path):
    """The same OBJ through the real command in its own process: exit 0, one stderr line per reference."""
    path, named = hostile_obj(tmp_path)
    toy = make_toy_bundle(tmp_path / "toy.kpd")
    out = tmp_path / "out" / "edited.obj"
    out.parent.mkdir()
    done = subprocess.run([sys.executable, "-m", "kpd.cli", "deform", str(toy), str(path), "--move", "0:0,0,0.2",
                           "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert warnings_naming(lines, named) == {name: 1 for name in named}, done.stderr
    assert_nothing_leaked(out, {"edited.obj", "edited.mtl", "edited_good.png"})


@pytest.mark.parametrize("command", ["align", "scan"])
def test_the_other_commands_share_the_rule(tmp_path, command):
    """``kpd align`` and ``kpd scan`` write the hostile OBJ back in its own structure too: the same warnings, once
    each, and nothing of the victim's beside the output."""
    path, named = hostile_obj(tmp_path)
    plain = tmp_path / "plain.obj"
    plain.write_text("\n".join(line for line in sphere_obj_lines() if line != "usemtl m") + "\n")
    out = tmp_path / "out" / "edited.obj"
    out.parent.mkdir()
    argv = {"align": ["align", str(make_toy_bundle(tmp_path / "toy.kpd")), str(path), str(plain)],
            "scan": ["scan", str(path), "--reference", str(plain), "--report", str(tmp_path / "report.json")]}
    done = subprocess.run([sys.executable, "-m", "kpd.cli", *argv[command], "--out", str(out)], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert warnings_naming(done.stderr.splitlines(), named) == {name: 1 for name in named}, done.stderr
    assert_nothing_leaked(out, {"edited.obj", "edited.mtl", "edited_good.png"})


def gltf_with_images(folder: Path, uris: list[str]) -> Path:
    """A textured .gltf (its buffer a data: URI) whose images are ``uris``, one material each."""
    from kpd.mesh import Mesh

    cage = icosphere(1, 1.0)
    T = len(cage.faces)
    mesh = Mesh(cage.vertices, cage.faces, triangle_uvs=np.full((3 * T, 2), 0.5),
                textures=[np.full((2, 2, 3), 90, np.uint8), np.full((2, 2, 3), 10, np.uint8)],
                triangle_material_ids=np.arange(T) % 2)
    path = folder / "shape.gltf"
    write_mesh(path, mesh)
    doc = json.loads(path.read_text())
    for p in folder.glob("shape_*"):
        p.unlink()
    doc["images"] = [{"uri": uri} for uri in uris]
    doc["textures"] = [{"source": i} for i in range(len(uris))]
    for i, material in enumerate(doc["materials"]):
        material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": i % len(uris)}
    path.write_text(json.dumps(doc))
    return path


HOSTILE_URIS = ["/etc/passwd", "../secret.png", "%2Fetc%2Fpasswd", "..%2Fsecret.png", "%00x.png",
                "file:///etc/passwd", "link.png", "%2e%2e/secret.png"]


def test_gltf_image_uris_stay_inside_the_folder(tmp_path, caplog):
    folder = tmp_path / "in"
    folder.mkdir()
    (tmp_path / "secret.png").write_bytes(png((7, 7, 7)) + SECRET)
    (folder / "link.png").symlink_to(tmp_path / "secret.png")
    (folder / "ok.png").write_bytes(png((30, 60, 90)))
    path = gltf_with_images(folder, HOSTILE_URIS + ["ok.png"])
    with caplog.at_level(logging.WARNING):
        mesh = read_mesh(path)
    lines = [r.getMessage() for r in caplog.records]
    assert warnings_naming(lines, HOSTILE_URIS) == {uri: 1 for uri in HOSTILE_URIS}, lines
    assert len(lines) == len(HOSTILE_URIS), lines
    out = tmp_path / "out" / "edited.gltf"
    out.parent.mkdir()
    write_mesh(out, mesh.with_vertices(mesh.vertices * 2))
    assert_nothing_leaked(out, {"edited.gltf", "edited_ok.png"})
    assert (out.parent / "edited_ok.png").read_bytes() == (folder / "ok.png").read_bytes()


def test_kpd_deform_of_a_gltf_with_hostile_uris(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    (tmp_path / "secret.png").write_bytes(png((7, 7, 7)) + SECRET)
    (folder / "link.png").symlink_to(tmp_path / "secret.png")
    path = gltf_with_images(folder, HOSTILE_URIS)
    toy = make_toy_bundle(tmp_path / "toy.kpd")
    out = tmp_path / "out" / "edited.gltf"
    out.parent.mkdir()
    done = subprocess.run([sys.executable, "-m", "kpd.cli", "deform", str(toy), str(path), "--move", "0:0,0,0.2",
                           "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert warnings_naming(done.stderr.splitlines(), HOSTILE_URIS) == {uri: 1 for uri in HOSTILE_URIS}, done.stderr
    assert_nothing_leaked(out, {"edited.gltf"})


def test_a_data_uri_image_still_reads(tmp_path, caplog):
    uri = "data:image/png;base64," + base64.b64encode(png((30, 60, 90))).decode()
    path = gltf_with_images(tmp_path, [uri])
    with caplog.at_level(logging.WARNING):
        mesh = read_mesh(path)
    assert not caplog.records
    assert mesh.textures[0].shape == (4, 4, 3) and mesh.textures[0][0, 0].tolist() == [30, 60, 90]


@pytest.mark.parametrize("uri, reason", [("../blob.bin", "outside the input's folder"),
                                         ("/etc/passwd", "an absolute path"), ("%00.bin", "control character")])
def test_a_gltf_buffer_outside_the_folder_is_an_error(tmp_path, uri, reason):
    folder = tmp_path / "in"
    folder.mkdir()
    (tmp_path / "blob.bin").write_bytes(bytes(4096))
    path = gltf_with_images(folder, ["a.png"])
    doc = json.loads(path.read_text())
    doc["buffers"][0]["uri"] = uri
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=f"its buffer {uri!r} is not read \\(.*{reason}"):
        read_mesh(path)


# --- sizes a glTF declares ------------------------------------------------------------------------------------------


def tiny_gltf(path: Path, count: int) -> Path:
    """A glTF of a few hundred bytes whose POSITION accessor claims ``count`` vertices and has no data at all."""
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 4}]}],
           "accessors": [{"componentType": 5126, "count": count, "type": "VEC3"}]}
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("power", [26, 28])
def test_a_tiny_gltf_claiming_millions_of_vertices_is_one_line(tmp_path, power):
    path = tiny_gltf(tmp_path / "tiny.gltf", 2**power)
    assert path.stat().st_size < 300
    toy = make_toy_bundle(tmp_path / "toy.kpd")
    done, peak = peak_of([sys.executable, "-m", "kpd.cli", "deform", str(toy), str(path), "--move", "0:0,0,1",
                          "--out", str(tmp_path / "out.obj")])
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and f"declares {2**power} elements" in done.stderr, done.stderr
    assert peak < 0.5 * 2**30, peak
    assert not (tmp_path / "out.obj").exists()


@pytest.mark.parametrize("change, message", [
    (lambda d: d["bufferViews"][0].update(byteLength=1 << 40), "bufferView 0 reaches byte"),
    (lambda d: d["accessors"][0].update(count=1 << 30), "accessor 0 reaches past the end of its buffer view"),
    (lambda d: d["accessors"][0].update(count=-1), "accessor 0's count must be a non-negative integer"),
    (lambda d: d["bufferViews"][0].update(byteStride=4), "overlap"),
    (lambda d: d["buffers"][0].update(byteLength=1 << 40), "holds .* of its 1099511627776 bytes"),
])
def test_declared_sizes_are_checked_against_the_data(tmp_path, change, message):
    path = gltf_with_images(tmp_path, ["a.png"])
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=message):
        read_mesh(path)


def test_a_wider_files_root_is_the_callers_choice(tmp_path, caplog):
    """``files_root`` names the tree a dataset's maps may come from (ShapeNet's ``../images``); nothing outside it,
    and never a system file, is read even then."""
    folder = tmp_path / "model" / "models"
    folder.mkdir(parents=True)
    (tmp_path / "model" / "images").mkdir()
    (tmp_path / "model" / "images" / "tex.png").write_bytes(png((10, 120, 240)))
    (tmp_path / "secret.png").write_bytes(png((7, 7, 7)) + SECRET)
    path = gltf_with_images(folder, ["../images/tex.png", "../../secret.png", "/proc/self/environ"])
    with caplog.at_level(logging.WARNING):
        mesh = read_mesh(path, files_root=tmp_path / "model")
    assert warnings_naming([r.getMessage() for r in caplog.records], ["../../secret.png", "/proc/self/environ"]) == \
        {"../../secret.png": 1, "/proc/self/environ": 1}
    assert mesh.textures[0][0, 0].tolist() == [10, 120, 240]
    out = tmp_path / "out" / "edited.gltf"
    out.parent.mkdir()
    write_mesh(out, mesh.with_vertices(mesh.vertices + 1))
    assert_nothing_leaked(out, {"edited.gltf", "edited_tex.png"})


def test_a_file_named_by_several_statements_is_one_warning(tmp_path, caplog):
    (tmp_path / "m.mtl").write_text("newmtl a\nmap_Kd ../t.png\nmap_d ../t.png\nnewmtl b\nmap_Kd ../t.png\n")
    (tmp_path / "m.obj").write_text("\n".join(["mtllib m.mtl", "mtllib ../x.mtl", "mtllib ../x.mtl"]
                                              + sphere_obj_lines()) + "\n")
    with caplog.at_level(logging.WARNING):
        read_mesh(tmp_path / "m.obj")
    lines = [r.getMessage() for r in caplog.records]
    assert warnings_naming(lines, ["../t.png", "../x.mtl"]) == {"../t.png": 1, "../x.mtl": 1} and len(lines) == 2


def test_deeply_nested_json_is_one_error(tmp_path):
    (tmp_path / "deep.gltf").write_text("[" * 100_000)
    with pytest.raises(InputError, match="could not be read as glTF"):
        read_mesh(tmp_path / "deep.gltf")


@pytest.mark.parametrize("field, value", [
    ("asset", [[]]), ("asset", 4294967295), ("scenes", ["AAAA"]), ("nodes", [7]), ("buffers", [None]),
    ("materials", [1.5]), ("meshes", [{"primitives": [{"attributes": {"POSITION": 2 ** 70}}]}]),
])
def test_a_gltf_of_the_wrong_json_types_is_one_error(tmp_path, field, value):
    """An object where the specification has a number, a list or a string, anywhere in the JSON (found by the reader
    fuzz): one InputError, never an AttributeError or an OverflowError."""
    path = gltf_with_images(tmp_path, ["a.png"])
    (tmp_path / "a.png").write_bytes(png())
    doc = json.loads(path.read_text())
    doc[field] = value
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="glTF"):
        read_mesh(path)


def test_a_named_file_is_read_by_its_size_not_by_the_limit(tmp_path):
    """A read asks for the file's own size: asking for the limit (a bundle member may be up to 1 GiB) allocated the
    whole limit first, a MemoryError under a tight address-space limit (found by the reader fuzz)."""
    (tmp_path / "small.bin").write_bytes(b"12345")
    assert references.read_named(tmp_path / "small.bin", 1 << 50) == b"12345"
