"""Bundles: writing, reading, and refusing tampered, incomplete or foreign ones with a clear message.

``make_toy_bundle`` builds a small bundle without torch (a hand-made PointNet-like ONNX graph pair that follows
kpd.onnx_contract); test_runtime and test_commands import it. test_export covers bundles exported from torch.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from kpd import onnx_contract as contract
from kpd.bundle import build_manifest, manifest_checksum, read_bundle, resolve_bundle, shipped_bundles, write_bundle
from kpd.cage import icosphere
from kpd.errors import BundleError, InputError
from kpd.prior import KeypointPrior

HIDDEN = 16


def toy_weights(k: int = 4, c: int = 42, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "w1": rng.normal(0, 1.0, (3, HIDDEN)).astype(np.float32),
        "b1": rng.normal(0, 0.1, HIDDEN).astype(np.float32),
        "w2": rng.normal(0, 0.3, (HIDDEN, 3 * k)).astype(np.float32),
        "b2": rng.normal(0, 0.1, 3 * k).astype(np.float32),
        "w3": rng.normal(0, 0.3, (HIDDEN, k * c)).astype(np.float32),
        "b3": rng.normal(0, 0.1, k * c).astype(np.float32),
    }


def toy_reference(points: np.ndarray, w: dict, k: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    """numpy twin of the toy graphs: points (B, N, 3) -> keypoints (B, K, 3), influence (B, K, C)."""
    h = np.maximum(points.astype(np.float64) @ w["w1"] + w["b1"], 0).max(axis=1)  # (B, H)
    keypoints = np.clip((h @ w["w2"] + w["b2"]).reshape(-1, 3, k).transpose(0, 2, 1), -1, 1)
    influence = (h @ w["w3"] + w["b3"]).reshape(-1, k, c)
    return keypoints, influence


def _toy_graph(spec: contract.GraphSpec, w: dict, k: int, c: int, meta: dict) -> bytes:
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    init = [numpy_helper.from_array(w["w1"], "w1"), numpy_helper.from_array(w["b1"], "b1"),
            numpy_helper.from_array(np.array([1], np.int64), "axis1")]
    nodes = [helper.make_node("MatMul", ["points", "w1"], ["h0"]), helper.make_node("Add", ["h0", "b1"], ["h1"]),
             helper.make_node("Relu", ["h1"], ["h2"]),
             helper.make_node("ReduceMax", ["h2", "axis1"], ["h"], keepdims=0)]
    if spec is contract.KEYPOINTS_GRAPH:
        init += [numpy_helper.from_array(w["w2"], "w2"), numpy_helper.from_array(w["b2"], "b2"),
                 numpy_helper.from_array(np.array([-1, 3, k], np.int64), "shape"),
                 numpy_helper.from_array(np.array(-1, np.float32), "lo"),
                 numpy_helper.from_array(np.array(1, np.float32), "hi")]
        nodes += [helper.make_node("MatMul", ["h", "w2"], ["f0"]), helper.make_node("Add", ["f0", "b2"], ["f1"]),
                  helper.make_node("Reshape", ["f1", "shape"], ["f2"]),
                  helper.make_node("Transpose", ["f2"], ["f3"], perm=[0, 2, 1]),
                  helper.make_node("Clip", ["f3", "lo", "hi"], [spec.output])]
        out_shape = [contract.BATCH_AXIS, k, 3]
    else:
        init += [numpy_helper.from_array(w["w3"], "w3"), numpy_helper.from_array(w["b3"], "b3"),
                 numpy_helper.from_array(np.array([-1, k, c], np.int64), "shape")]
        nodes += [helper.make_node("MatMul", ["h", "w3"], ["f0"]), helper.make_node("Add", ["f0", "b3"], ["f1"]),
                  helper.make_node("Reshape", ["f1", "shape"], [spec.output])]
        out_shape = [contract.BATCH_AXIS, k, c]
    graph = helper.make_graph(
        nodes, spec.key,
        [helper.make_tensor_value_info(contract.INPUT_NAME, TensorProto.FLOAT,
                                       [contract.BATCH_AXIS, contract.POINTS_AXIS, 3])],
        [helper.make_tensor_value_info(spec.output, TensorProto.FLOAT, out_shape)], init)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", contract.OPSET)])
    model.ir_version = 10
    for key, value in {**meta, contract.META_GRAPH: spec.key}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    return model.SerializeToString()


def make_toy_bundle(path, *, k: int = 4, c: int = 42, seed: int = 0, prior: bool = True, template: bool = True,
                    graph_k: int | None = None, meta_version: str | None = None, up: str | None = "+z") -> Path:
    """Write a small valid bundle (or, with ``graph_k`` / ``meta_version``, one whose graphs disagree with it)."""
    w = toy_weights(graph_k or k, c, seed)
    meta = {contract.META_FORMAT: contract.FORMAT_NAME,
            contract.META_FORMAT_VERSION: meta_version or str(contract.FORMAT_VERSION),
            contract.META_KEYPOINTS: str(graph_k or k), contract.META_CAGE_VERTICES: str(c)}
    graphs = [_toy_graph(spec, w, graph_k or k, c, meta) for spec in contract.GRAPHS]
    rng = np.random.default_rng(seed + 1)
    fitted = None
    if prior:
        base = rng.uniform(-0.8, 0.8, (k, 3))
        fitted = KeypointPrior(n_components=3).fit(base + 0.05 * rng.standard_normal((30, k, 3)))
    cage = icosphere(1, 1.4) if c == 42 else icosphere(2, 1.4)
    _, files = build_manifest(
        category="toy", keypoints_onnx=graphs[0], influence_onnx=graphs[1], cage=cage,
        shared_influence=rng.uniform(0, 1, (k, c)), m=5, point_count=256,
        cage_fit={"distance": 0.4, "iterations": 100, "step": 0.01}, prior=fitted,
        template_points=rng.uniform(-1, 1, (100, 3)) if template else None, template_source="random",
        up=up, training={"data": "none", "command": "make_toy_bundle", "seed": seed, "iterations": 0, "metrics": {}},
    )
    return write_bundle(path, files)


@pytest.fixture
def toy(tmp_path) -> Path:
    return make_toy_bundle(tmp_path / "toy.kpd")


def test_roundtrip_folder_and_zip(tmp_path, toy):
    bundle = read_bundle(toy)
    assert (bundle.num_keypoints, bundle.num_cage_vertices, bundle.m, bundle.point_count) == (4, 42, 5, 256)
    assert bundle.category == "toy" and bundle.cage.vertices.shape == (42, 3) and bundle.cage.faces.shape == (80, 3)
    assert bundle.shared_influence.shape == (4, 42)
    assert bundle.prior.components_.shape == (3, 4, 3)
    assert bundle.template_points.shape == (100, 3)
    assert bundle.training["command"] == "make_toy_bundle"
    assert bundle.manifest["files"].keys() == {"keypoints.onnx", "influence.onnx", "template.npy"}
    zipped = tmp_path / "toy.zip"
    files = {p.name: p.read_bytes() for p in toy.iterdir()}
    write_bundle(zipped, files)
    again = read_bundle(zipped)
    assert again.manifest == bundle.manifest and again.files == bundle.files
    # a zip of the folder itself (files under one top-level folder) is read too
    nested = tmp_path / "nested.zip"
    with zipfile.ZipFile(nested, "w") as archive:
        for p in toy.iterdir():
            archive.write(p, f"toy.kpd/{p.name}")
    assert read_bundle(nested).manifest == bundle.manifest


def test_without_prior_and_template(tmp_path):
    bundle = read_bundle(make_toy_bundle(tmp_path / "bare.kpd", prior=False, template=False))
    assert bundle.prior is None and bundle.template_points is None
    assert set(bundle.manifest["files"]) == {"keypoints.onnx", "influence.onnx"}


def test_changed_bytes_refused(toy):
    path = toy / "influence.onnx"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"influence.onnx was modified: sha256 \w+ expected, \w+ found"):
        read_bundle(toy)


@pytest.mark.parametrize("name", ["keypoints.onnx", "template.npy", "manifest.json"])
def test_missing_file_refused(toy, name):
    (toy / name).unlink()
    with pytest.raises(BundleError, match=f"{name} is missing"):
        read_bundle(toy)


def _rewrite_manifest(path: Path, change, *, fix_checksum: bool = True) -> None:
    manifest = json.loads((path / "manifest.json").read_text())
    change(manifest)
    if fix_checksum:
        manifest["manifest_sha256"] = manifest_checksum(manifest)
    (path / "manifest.json").write_text(json.dumps(manifest))


def test_other_format_version_refused(toy):
    _rewrite_manifest(toy, lambda m: m.update(format_version=2))
    with pytest.raises(BundleError, match="bundle format version 2; this kpd reads version 1"):
        read_bundle(toy)


def test_foreign_format_refused(toy):
    _rewrite_manifest(toy, lambda m: m.update(format="something-else"))
    with pytest.raises(BundleError, match="format must be 'kpd-bundle'; got 'something-else'"):
        read_bundle(toy)


def test_edited_manifest_refused(toy):
    _rewrite_manifest(toy, lambda m: m["model"].update(m=6), fix_checksum=False)
    with pytest.raises(BundleError, match="manifest.json was modified"):
        read_bundle(toy)


def test_not_json_refused(toy):
    (toy / "manifest.json").write_text("{not json")
    with pytest.raises(BundleError, match="not valid JSON"):
        read_bundle(toy)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda m: m.update(shared_influence=[[0.0] * 42] * 3), r"shared_influence \(W_C\) must be finite with shape"),
        (lambda m: m["cage"].update(faces=[[0, 1, 99]] * 80), "cage faces must be integers in"),
        (lambda m: m["model"].update(keypoints=0), "keypoints must be a positive integer"),
        (lambda m: m["input"].update(normalization="unit-sphere"), "normalization must be"),
        (lambda m: m["prior"].update(components=[[[0.0] * 3] * 4] * 2), "prior components must have shape"),
        (lambda m: m.pop("cage"), "lacks 'cage'"),
    ],
)
def test_inconsistent_manifest_refused(toy, change, message):
    _rewrite_manifest(toy, change)
    with pytest.raises(BundleError, match=message):
        read_bundle(toy)


def test_file_without_hash_refused(toy):
    _rewrite_manifest(toy, lambda m: m["files"].pop("template.npy"))
    with pytest.raises(BundleError, match="manifest has no sha256 for template.npy"):
        read_bundle(toy)


def test_pickled_template_refused(toy):
    import io

    buffer = io.BytesIO()
    np.save(buffer, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    (toy / "template.npy").write_bytes(buffer.getvalue())
    _rewrite_manifest(toy, lambda m: m["files"].update({"template.npy": hashlib.sha256(buffer.getvalue()).hexdigest()}))
    with pytest.raises(BundleError, match="not a plain .npy array"):
        read_bundle(toy)


def test_not_a_bundle(tmp_path):
    with pytest.raises(BundleError, match="no such bundle"):
        read_bundle(tmp_path / "nothing.kpd")
    with pytest.raises(BundleError, match="no such bundle .* shipped name"):
        read_bundle("no-such-category")
    (tmp_path / "empty.kpd").mkdir()
    with pytest.raises(BundleError, match="manifest.json is missing"):
        read_bundle(tmp_path / "empty.kpd")
    (tmp_path / "plain.txt").write_text("hello")
    with pytest.raises(BundleError, match="a .kpd folder or a .zip"):
        read_bundle(tmp_path / "plain.txt")


def test_write_is_atomic_and_refuses_overwrite(tmp_path, toy):
    files = {p.name: p.read_bytes() for p in toy.iterdir()}
    with pytest.raises(InputError, match="exists"):
        write_bundle(toy, files)
    before = sorted(p.name for p in tmp_path.iterdir())
    write_bundle(toy, files, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no temporary left behind
    assert read_bundle(toy).files == {k: v for k, v in files.items() if k != "manifest.json"}


def test_shipped_bundles_resolve_and_validate():
    names = shipped_bundles()
    assert {"chair", "table"} <= set(names)
    for name in names:
        bundle = read_bundle(name)
        assert resolve_bundle(name).name == f"{name}.kpd"
        assert bundle.prior is not None and bundle.template_points is not None
        record = bundle.training
        for key in ("data", "command", "seed", "iterations", "metrics"):
            assert key in record, f"{name}: training record lacks {key}"


def test_copy_keeps_validity(tmp_path, toy):
    copy = tmp_path / "copy.kpd"
    shutil.copytree(toy, copy)
    assert read_bundle(copy).manifest == read_bundle(toy).manifest
