"""Bundles: writing, reading, and refusing tampered, incomplete or foreign ones with a clear message.

``helpers.make_toy_bundle`` builds a small bundle without torch (a hand-made PointNet-like ONNX graph pair that
follows kpd.onnx_contract). test_export covers bundles exported from torch.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import HIDDEN, make_toy_bundle

from kpd.bundle import manifest_checksum, read_bundle, resolve_bundle, shipped_bundles, write_bundle
from kpd.errors import BundleError, InputError


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


# --- bundles from others: sizes checked before reading, graphs that stay inside the bundle ----------------------------


def _deflated_zeros(nbytes: int) -> tuple[bytes, int]:
    """A raw deflate stream of ``nbytes`` zero bytes (a multiple of 16 MiB) and its CRC-32, made from one compressed
    block repeated (a full flush makes each block stand alone), so that a bomb costs a second to build."""
    import zlib

    piece = 16 << 20
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = compressor.compress(bytes(piece)) + compressor.flush(zlib.Z_FULL_FLUSH)
    crc = 0
    zeros = bytes(piece)
    for _ in range(nbytes // piece):
        crc = zlib.crc32(zeros, crc)
    return block * (nbytes // piece) + b"\x03\x00", crc


def _write_zip(path: Path, members: dict) -> None:
    """A zip of ``members`` {name: bytes, or (deflate stream, crc, size)} written by hand: deflated members are
    stored as given, the others as they are (method 0)."""
    import struct
    import zlib

    local, central = bytearray(), bytearray()
    for name, data in members.items():
        raw = name.encode()
        if isinstance(data, tuple):
            body, crc, size, method = *data, 8
        else:
            body, crc, size, method = data, zlib.crc32(data), len(data), 0
        offset = len(local)
        local += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0x5221, crc, len(body), size, len(raw), 0)
        local += raw + body
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0x5221, crc, len(body), size,
                               len(raw), 0, 0, 0, 0, 0o644 << 16, offset)
        central += raw
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(central), len(local), 0)
    path.write_bytes(bytes(local + central + end))


@pytest.fixture(scope="module")
def bomb() -> tuple[bytes, int, int]:
    body, crc = _deflated_zeros(2 << 30)
    return body, crc, 2 << 30


def test_zip_members_inflating_to_gigabytes_are_refused_before_they_are_read(tmp_path, bomb):
    """A zip of a few megabytes whose listed members inflate to 2 GiB each: one line, nothing inflated."""
    toy = make_toy_bundle(tmp_path / "toy.kpd")
    members = {p.name: p.read_bytes() for p in toy.iterdir()}
    members.update({"keypoints.onnx": bomb, "influence.onnx": bomb, "template.npy": bomb})
    path = tmp_path / "bomb.zip"
    _write_zip(path, members)
    assert path.stat().st_size < 8 << 20
    with pytest.raises(BundleError, match=r"influence.onnx inflates to 2147483648 bytes, over the 1073741824"):
        read_bundle(path)


def test_a_zip_member_the_manifest_does_not_list_is_never_read(tmp_path, bomb):
    toy = make_toy_bundle(tmp_path / "toy.kpd")
    members = {p.name: p.read_bytes() for p in toy.iterdir()}
    members["extra.bin"] = bomb
    _write_zip(tmp_path / "extra.zip", members)
    bundle = read_bundle(tmp_path / "extra.zip")
    assert set(bundle.files) == {"keypoints.onnx", "influence.onnx", "template.npy"}


def test_a_highly_compressed_member_is_refused_by_its_ratio(tmp_path):
    import zlib

    toy = make_toy_bundle(tmp_path / "toy.kpd")
    members = {p.name: p.read_bytes() for p in toy.iterdir()}
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    zeros = bytes(64 << 20)
    members["template.npy"] = (compressor.compress(zeros) + compressor.flush(), zlib.crc32(zeros), len(zeros))
    _write_zip(tmp_path / "dense.zip", members)
    with pytest.raises(BundleError, match=r"template.npy inflates \d+ times .* more than the 100 of a bundle"):
        read_bundle(tmp_path / "dense.zip")


def test_the_bomb_through_the_command_is_one_line_and_little_memory(tmp_path, bomb):
    from helpers import peak_of

    toy = make_toy_bundle(tmp_path / "toy.kpd")
    members = {p.name: p.read_bytes() for p in toy.iterdir()}
    members.update({"keypoints.onnx": bomb, "influence.onnx": bomb, "template.npy": bomb})
    _write_zip(tmp_path / "bomb.zip", members)
    (tmp_path / "points.xyz").write_text("\n".join(f"{x} {x * 2} {x * 3}" for x in np.linspace(-1, 1, 64)))
    import sys

    done, peak = peak_of([sys.executable, "-m", "kpd.cli", "keypoints", str(tmp_path / "bomb.zip"),
                          str(tmp_path / "points.xyz")])
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "inflates to 2147483648" in done.stderr
    assert peak < 0.5 * 2**30, peak


@pytest.mark.parametrize("name", ["../manifest.json", "sub/x.onnx", ".."])
def test_a_manifest_naming_a_path_is_refused(toy, name):
    _rewrite_manifest(toy, lambda m: m["files"].update({name: "0" * 64}))
    with pytest.raises(BundleError, match="not a plain file name of the bundle"):
        read_bundle(toy)


def test_a_bundle_file_that_is_a_symlink_out_is_refused(tmp_path, toy):
    outside = tmp_path / "elsewhere.npy"
    shutil.move(toy / "template.npy", outside)
    (toy / "template.npy").symlink_to(outside)
    with pytest.raises(BundleError, match="template.npy is not read \\(outside the input's folder\\)"):
        read_bundle(toy)


def _external_w1(spec, model) -> None:
    """Store the first layer's weights outside the graph, in ``blob.bin`` of the current folder."""
    from onnx import TensorProto
    from onnx.external_data_helper import set_external_data

    tensor = next(t for t in model.graph.initializer if t.name == "w1")
    set_external_data(tensor, location="blob.bin", offset=0, length=len(tensor.raw_data))
    tensor.data_location = TensorProto.EXTERNAL
    tensor.ClearField("raw_data")


def _foreign_import(spec, model) -> None:
    model.opset_import.add(domain="com.microsoft", version=1)


def _foreign_node(spec, model) -> None:
    model.graph.node[2].domain = "custom.evil"


def _constant_weights(spec, model) -> None:
    """The weights as a Constant node whose tensor is external: a tensor inside a node's attribute."""
    from onnx import TensorProto, helper
    from onnx.external_data_helper import set_external_data

    tensor = next(t for t in model.graph.initializer if t.name == "b1")
    model.graph.initializer.remove(tensor)
    set_external_data(tensor, location="blob.bin")
    tensor.data_location = TensorProto.EXTERNAL
    tensor.ClearField("raw_data")
    model.graph.node.insert(0, helper.make_node("Constant", [], ["b1"], value=tensor))


def _sparse_external(spec, model) -> None:
    """A sparse initializer whose values are external: a tensor inside a SparseTensorProto."""
    from onnx import TensorProto, helper
    from onnx.external_data_helper import set_external_data

    values = helper.make_tensor("s_values", TensorProto.FLOAT, [1], np.ones(1, np.float32).tobytes(), raw=True)
    set_external_data(values, location="blob.bin")
    values.data_location = TensorProto.EXTERNAL
    values.ClearField("raw_data")
    indices = helper.make_tensor("s_indices", TensorProto.INT64, [1], [0])
    model.graph.sparse_initializer.append(helper.make_sparse_tensor(values, indices, [4]))


@pytest.mark.parametrize("edit, message", [
    (_external_w1, "tensor 'w1' keeps its data outside the model"),
    (_sparse_external, "tensor 's_values' keeps its data outside the model"),
    (_constant_weights, "tensor 'b1' keeps its data outside the model"),
    (_foreign_import, "imports the operator set 'com.microsoft'"),
    (_foreign_node, "node 'Relu' is of the operator set 'custom.evil'"),
])
def test_graphs_that_reach_outside_the_bundle_are_refused(tmp_path, monkeypatch, edit, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "blob.bin").write_bytes(np.ones(3 * HIDDEN, np.float32).tobytes())  # where onnxruntime would look
    path = make_toy_bundle(tmp_path / "hostile.kpd", edit=edit)
    with pytest.raises(BundleError, match=f"hostile.kpd: keypoints.onnx is refused: .*{message}"):
        read_bundle(path)


def test_not_a_protobuf_graph_is_refused(tmp_path):
    def garbage(spec, model) -> None:
        model.graph.name = "x"

    path = make_toy_bundle(tmp_path / "odd.kpd", edit=garbage)
    (path / "keypoints.onnx").write_bytes(b"\xff\xff\xff")
    _rewrite_manifest(path, lambda m: m["files"].update(
        {"keypoints.onnx": hashlib.sha256(b"\xff\xff\xff").hexdigest()}))
    with pytest.raises(BundleError, match="keypoints.onnx is refused: not an ONNX model"):
        read_bundle(path)


def _huge_constant(spec, model) -> None:
    """A ConstantOfShape of 2^33 floats added to the output: onnxruntime fails to allocate it when the graph runs."""
    from onnx import TensorProto, helper, numpy_helper

    model.graph.initializer.append(numpy_helper.from_array(np.array([2**33], np.int64), "huge_shape"))
    last = model.graph.node[-1]
    last.output[0] = "before_huge"
    model.graph.node.extend([
        helper.make_node("ConstantOfShape", ["huge_shape"], ["huge"],
                         value=helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0])),
        helper.make_node("ReduceMax", ["huge"], ["huge_max"], keepdims=0),
        helper.make_node("Add", ["before_huge", "huge_max"], [spec.output])])


def test_an_allocation_onnxruntime_cannot_make_is_one_line_naming_the_bundle(tmp_path):
    import sys

    from kpd.runtime import Model

    path = make_toy_bundle(tmp_path / "huge.kpd", edit=_huge_constant)
    model = Model.load(path)
    with pytest.raises(BundleError, match=r"huge.kpd: (keypoints|influence).onnx failed in onnxruntime \(.*"
                                          r"allocate"):
        model.run(np.zeros((8, 3)))
    (tmp_path / "points.xyz").write_text("\n".join(f"{x} {x * 2} {x * 3}" for x in np.linspace(-1, 1, 64)))
    done = subprocess.run([sys.executable, "-m", "kpd.cli", "keypoints", str(path), str(tmp_path / "points.xyz")],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "huge.kpd" in done.stderr and "failed in onnxruntime" in done.stderr


@pytest.mark.parametrize("number", ["1e309", "-1e309", "NaN", "Infinity"])
def test_a_manifest_number_beyond_float64_is_one_error(tmp_path, toy, number):
    """A manifest holding a number that is not finite (found by the reader fuzz): one BundleError, not the ValueError
    of the checksum's canonical JSON."""
    bundle = tmp_path / "copy.kpd"
    shutil.copytree(toy, bundle)
    text = (bundle / "manifest.json").read_text()
    (bundle / "manifest.json").write_text(text.replace("{", '{"x": ' + number + ", ", 1))
    with pytest.raises(BundleError, match="not valid JSON"):
        read_bundle(bundle)
