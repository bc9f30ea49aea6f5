"""kpd.morph and kpd rig: glTF morph targets that reproduce the rig, read back, and checked by the Khronos validator."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from helpers import TOLERANCE, corresponding, kpd, validate

from kpd import morph
from kpd.io import Mesh, read_mesh, write_mesh
from kpd.morph import MorphRig, read_gltf, up_rotation, write_gltf
from kpd.runtime import Model


@pytest.fixture(scope="module")
def model() -> Model:
    return Model.load("chair")


@pytest.fixture(scope="module")
def written(chair_file, tmp_path_factory):
    """The chair's rig written by ``kpd rig`` as .glb, and the same rig made through the API."""
    out = tmp_path_factory.mktemp("rig") / "chair.glb"
    assert kpd("rig", "chair", chair_file, "--out", out) == 0
    return out


def test_glb_names_counts_and_exact_edits(written, chair_file, model):
    gltf = read_gltf(written)
    mesh = read_mesh(chair_file)
    rig = model.rig(mesh)
    k, m = model.num_keypoints, len(model.prior.components_)
    expected = ([f"keypoint_{i}_{a}" for i in range(k) for a in "xyz"]
                + [f"prior_{i}_{a}" for i in range(k) for a in "xyz"] + [f"pca_{c}" for c in range(m)])
    assert gltf.names == expected
    assert gltf.document["meshes"][0]["extras"]["targetNames"] == expected
    assert len(gltf.targets[0]) == len(expected) == 6 * k + m
    extras = gltf.document["asset"]["extras"]["kpd"]
    assert (extras["model"], extras["category"]) == ("chair", "chair") and extras["version"]
    names = [n["name"] for n in gltf.document["nodes"]]
    assert [f"keypoint_{i}" for i in range(k)] == [n for n in names if n.startswith("keypoint_")]
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    np.testing.assert_allclose(gltf.keypoints, rig.keypoints, atol=1e-9 * diagonal)
    assert sum(len(t) for t in gltf.indices) == len(mesh.triangles)
    index = corresponding(gltf.positions[0], mesh)

    def error(weights: dict, vertices: np.ndarray) -> float:
        return float(np.abs(gltf.morphed(weights)[0] - vertices[index]).max() / diagonal)

    rng = np.random.default_rng(0)
    for scale in (0.02, 0.2):  # random offsets of every keypoint, in user units
        offsets = rng.normal(size=(k, 3)) * scale * diagonal
        weights = {f"keypoint_{i}_{a}": offsets[i, j] for i in range(k) for j, a in enumerate("xyz")}
        assert error(weights, rig.deform(rig.keypoints + offsets)) < TOLERANCE
    # prior targets: one keypoint's move with the others following Model.sync
    move = rng.normal(size=3) * 0.1 * diagonal
    synced = model.sync(rig, {4: rig.keypoints[4] + move})
    assert np.abs(synced - rig.keypoints).max() > 0.01 * diagonal  # other keypoints did follow
    weights = {f"prior_4_{a}": move[j] for j, a in enumerate("xyz")}
    assert error(weights, rig.deform(synced)) < TOLERANCE
    # pca targets: weight 1 = one standard deviation of the component, mapped into the user's units
    prior = model.prior
    for c in (0, m - 1):
        component = rig.normalizer.invert_vectors(np.sqrt(prior.explained_variance_[c]) * prior.components_[c])
        for weight in (1.0, -2.5):
            assert error({f"pca_{c}": weight}, rig.deform(rig.keypoints + weight * component)) < TOLERANCE
    # everything at once: the sum of the targets' keypoint offsets, deformed
    morph = MorphRig.from_rig(rig, prior)
    weights = dict(zip(morph.names, rng.normal(size=len(morph.names))))
    assert error(weights, rig.deform(morph.keypoints_at(weights))) < TOLERANCE
    np.testing.assert_allclose(morph.vertices_at(weights), rig.deform(morph.keypoints_at(weights)), atol=1e-9)


def test_textured_gltf_with_bin_validates_and_keeps_uvs(model, tmp_path):
    from kpd.procedural import procedural_chair

    chair = procedural_chair(edge=2.0)
    t = len(chair.triangles)
    uvs = np.random.default_rng(0).uniform(0, 1, (3 * t, 2))
    texture = np.random.default_rng(1).integers(0, 255, (8, 8, 3), dtype=np.uint8)
    mesh = Mesh(vertices=chair.vertices + [1000.0, -500.0, 20.0], triangles=chair.triangles,
                vertex_colors=chair.vertex_colors, triangle_uvs=uvs, textures=[texture],
                triangle_material_ids=np.zeros(t, np.int64))  # far from the origin: positions stay exact
    rig = model.rig(mesh)
    out = tmp_path / "textured.gltf"
    write_gltf(out, MorphRig.from_rig(rig, model.prior))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["textured.bin", "textured.gltf"]
    gltf = read_gltf(out)
    doc = gltf.document
    assert doc["buffers"][0]["uri"] == "textured.bin" and len(doc["images"]) == 1
    import io

    from PIL import Image

    view = doc["bufferViews"][doc["images"][0]["bufferView"]]
    png = (tmp_path / "textured.bin").read_bytes()[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(png))), texture)  # the texture, as it was
    attributes = doc["meshes"][0]["primitives"][0]["attributes"]
    assert {"POSITION", "COLOR_0", "TEXCOORD_0"} <= set(attributes) and "NORMAL" not in attributes
    assert len(gltf.positions[0]) > len(np.unique(mesh.triangles))  # split where the UVs differ
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    index = corresponding(gltf.positions[0], mesh)
    offsets = np.random.default_rng(2).normal(size=(rig.num_keypoints, 3)) * 0.05 * diagonal
    weights = {f"keypoint_{i}_{a}": offsets[i, j] for i in range(rig.num_keypoints) for j, a in enumerate("xyz")}
    expected = rig.deform(rig.keypoints + offsets)[index]
    assert np.abs(gltf.morphed(weights)[0] - expected).max() < TOLERANCE * diagonal
    report = validate(out)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]


def test_validator_finds_no_error_or_warning(written):
    report = validate(written)
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]
    # the validator read what kpd wrote: one draw call with morph targets, every triangle
    info = report["info"]
    assert info["hasMorphTargets"] and info["drawCallCount"] == 1 and info["totalTriangleCount"] == 2996
    # and it does report real problems: a target count that differs from the weights' is an error
    doc, rest = _split_glb(written.read_bytes())
    doc["meshes"][0]["weights"] = doc["meshes"][0]["weights"][:-1]
    broken = written.with_name("broken.glb")
    broken.write_bytes(_join_glb(doc, rest))
    assert validate(broken)["issues"]["numErrors"] > 0


def _split_glb(raw: bytes) -> tuple[dict, bytes]:
    import struct

    length = struct.unpack_from("<I", raw, 12)[0]
    return json.loads(raw[20:20 + length]), raw[20 + length:]


def _join_glb(doc: dict, rest: bytes) -> bytes:
    import struct

    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    return struct.pack("<IIIII", 0x46546C67, 2, 20 + len(text) + len(rest), len(text), 0x4E4F534A) + text + rest


def test_scan_rig_is_in_the_scans_frame(chair_file, tmp_path):
    """kpd rig --scan writes targets in the scan's own frame: weights give what kpd deform --scan writes."""
    mesh = read_mesh(chair_file)
    angle = np.radians(70.0)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    scan = tmp_path / "turned.ply"
    write_mesh(scan, mesh.with_vertices(mesh.vertices @ turn.T * 0.01 + [3.0, 1.0, 0.5]))  # metres, elsewhere
    out = tmp_path / "turned.glb"
    assert kpd("rig", "chair", scan, "--scan", "--up", "z", "--out", out) == 0
    deformed = tmp_path / "deformed.ply"
    assert kpd("deform", "chair", scan, "--scan", "--up", "z", "--move", "8:0.01,0,0.05", "--move", "2:0,-0.02,0",
               "--out", deformed) == 0
    gltf = read_gltf(out)
    original = read_mesh(scan)
    index = corresponding(gltf.positions[0], original)
    diagonal = np.linalg.norm(np.ptp(original.vertices, axis=0))
    weights = {"keypoint_8_x": 0.01, "keypoint_8_z": 0.05, "keypoint_2_y": -0.02}
    expected = read_mesh(deformed).vertices[index]
    assert np.abs(expected - original.vertices[index]).max() > 0.01 * diagonal
    assert np.abs(gltf.morphed(weights)[0] - expected).max() < TOLERANCE * diagonal
    # the browser editor's rig of a scan (kpd view --scan --browser): kpd.frame.ScanRig, in the scan's frame too
    from kpd.commands.rig import morph_rig
    from kpd.frame import ScanFrame, ScanRig

    model = Model.load("chair")
    frame = ScanFrame(model, original, "z")
    scan_rig = ScanRig(model.rig(original.with_vertices(frame.to_aligned(original.vertices))), original, frame)
    morph = morph_rig(scan_rig, model.prior, {})
    np.testing.assert_allclose(morph.keypoints, scan_rig.keypoints, atol=1e-9 * diagonal)
    everything = {name: 0.01 * np.sin(j) for j, name in enumerate(morph.names)}  # every kind of target
    np.testing.assert_allclose(morph.vertices_at(everything), scan_rig.deform(morph.keypoints_at(everything)),
                               atol=1e-9 * diagonal)
    np.testing.assert_allclose(morph.vertices_at(weights)[index], expected, atol=TOLERANCE * diagonal)
    move = np.array([0.02, -0.01, 0.03])  # a prior target in the scan's frame is Model.sync of the scan's rig
    synced = model.sync(scan_rig, {5: scan_rig.keypoints[5] + move})
    prior_weights = {f"prior_5_{a}": move[j] for j, a in enumerate("xyz")}
    np.testing.assert_allclose(morph.keypoints_at(prior_weights), synced, atol=1e-9 * diagonal)


def test_keypoint_targets_alone(written, chair_file, tmp_path):
    out = tmp_path / "keypoints.glb"
    assert kpd("rig", "chair", chair_file, "--out", out, "--targets", "keypoint") == 0
    small, full = read_gltf(out), read_gltf(written)
    assert small.names == [n for n in full.names if n.startswith("keypoint_")]
    assert small.document["asset"]["extras"]["kpd"]["targets"] == full.names  # every edit's offsets still listed
    np.testing.assert_array_equal(small.targets[0], full.targets[0][: len(small.names)])
    assert validate(out)["issues"]["numErrors"] == 0


def test_npz_is_kpds_rig(chair_file, model, tmp_path):
    from kpd.rig import Rig

    out = tmp_path / "chair.npz"
    assert kpd("rig", "chair", chair_file, "--out", out) == 0
    np.testing.assert_array_equal(Rig.load(out).basis, model.rig(read_mesh(chair_file)).basis)


def test_up_rotation_turns_the_axis_to_gltf_y():
    for axis, vector in {"+z": [0, 0, 1], "-z": [0, 0, -1], "x": [1, 0, 0], "-x": [-1, 0, 0], "-y": [0, -1, 0]}.items():
        x, y, z, w = up_rotation(axis)
        q = np.array([x, y, z])
        v = np.asarray(vector, dtype=float)
        turned = v + 2 * w * np.cross(q, v) + 2 * np.cross(q, np.cross(q, v))  # quaternion rotation
        np.testing.assert_allclose(turned, [0, 1, 0], atol=1e-12)
    assert up_rotation("+y") is None


@pytest.mark.parametrize("argv, message", [
    (["--out", "{tmp}/rig.fbx"], "a rig file must end in one of .glb .gltf .npz"),
    (["--out", "{tmp}/exists.glb"], "exists; pass --force to replace it"),
    (["--out", "{tmp}/companion.gltf"], "its companion file"),
    (["--out", "{tmp}/scan.npz", "--scan"], "holds no scan frame"),
    (["--out", "{tmp}/up.glb", "--view-up", "w"], "up axis must be one of"),
    (["--out", "{tmp}/kinds.glb", "--targets", "keypoint,nose"], "--targets must name some of keypoint, prior, pca"),
])
def test_refusals_are_one_line(argv, message, chair_file, tmp_path, capfd):
    (tmp_path / "exists.glb").write_bytes(b"mine")
    (tmp_path / "companion.bin").write_bytes(b"mine")
    before = sorted(p.name for p in tmp_path.iterdir())
    code = kpd("rig", "chair", chair_file, *[a.format(tmp=tmp_path) for a in argv])
    err = capfd.readouterr().err.strip()
    assert code == 2 and message in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert (tmp_path / "exists.glb").read_bytes() == b"mine"


@pytest.mark.parametrize("n", [1, 5000, 30001])  # one thread, and two (the halves meet mid-way)
@pytest.mark.parametrize("block_bytes", [120, 40_000, 32 * 2**20])  # a row a block, many blocks, one block
def test_displacements_are_the_product_written_target_after_target(n, block_bytes, monkeypatch):
    rng = np.random.default_rng(n)
    V, K, targets = n + 7, 12, 5
    basis = rng.normal(size=(V, K))
    source = rng.permutation(V)[:n]
    stacked = rng.normal(size=(K, 3 * targets))
    want = (basis[source] @ stacked).reshape(n, targets, 3).transpose(1, 0, 2)  # (targets, n, 3)
    displacements = morph._Displacements(basis, source, stacked)
    moved = displacements.block(0, n)
    assert moved.dtype == np.float32 and moved.shape == (targets, n, 3)
    np.testing.assert_allclose(moved, want, rtol=1e-6, atol=1e-6)
    low, high = displacements.bounds()
    np.testing.assert_allclose(low, want.min(axis=1), rtol=1e-6)
    np.testing.assert_allclose(high, want.max(axis=1), rtol=1e-6)
    assert (low <= moved.min(axis=1)).all() and (high >= moved.max(axis=1)).all()
    np.testing.assert_array_equal(low, moved.min(axis=1))  # float32 rounding keeps the order
    np.testing.assert_array_equal(high, moved.max(axis=1))
    # written block by block, each block's rows of every target in their places, after what came before
    monkeypatch.setattr(morph, "_WRITE_BYTES", block_bytes)
    out = io.BytesIO()
    out.write(b"head")
    displacements.write(out)
    assert out.tell() == 4 + displacements.nbytes == 4 + moved.nbytes
    out.write(b"tail")
    assert out.getvalue() == b"head" + moved.tobytes() + b"tail"
