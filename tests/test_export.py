"""Export (torch): ONNX vs torch parity through the runtime, the bundle's contents, refusal of a failing bundle, and
the import of the authors' checkpoints (docs/method.md §16)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import onnx  # noqa: E402 - the [train] extra, which make test installs
import torch  # noqa: E402

from kpd import onnx_contract as contract  # noqa: E402
from kpd.bundle import read_bundle  # noqa: E402
from kpd.errors import BundleError, InputError  # noqa: E402
from kpd.runtime import Model  # noqa: E402

K_RUN = 4


def _build_run(base: Path, data_dir: Path) -> Path:
    """A real (tiny) training run: a few iterations of the trainer on seven ModelNet chairs."""
    from kpd.data import SampleSettings, prepare
    from kpd.train.trainer import TrainConfig, Trainer

    root = base / "data"
    (root / "chair" / "train").mkdir(parents=True)
    source = data_dir / "modelnet10" / "chair" / "train"
    for path in sorted(source.glob("*.ply"))[:7]:
        os.symlink(path, root / "chair" / "train" / path.name)
    settings = SampleSettings(points=256, samples=2)
    data = prepare(root, "chair", settings=settings, cache_dir=base / "cache", splits=("train",), progress=False,
                   processes=1)
    config = TrainConfig(keypoints=K_RUN, iterations=4, batch=2, warmup=2, save_every=4, val_pairs=0)
    Trainer(config, data, base / "run", device="cpu", command="pytest tiny run").run(progress=False)
    return base / "run"


@pytest.fixture(scope="session")
def artifacts(tmp_path_factory, data_dir) -> tuple[Path, Path]:
    """(run folder, exported bundle), built once per test session, shared by pytest-xdist workers (file lock)."""
    from filelock import FileLock

    from kpd.export.build import export_checkpoint

    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent
    base = shared / "kpd-export-artifacts"
    with FileLock(str(base) + ".lock"):
        run, bundle = base / "run", base / "chair.kpd"
        if not bundle.is_dir():
            base.mkdir(exist_ok=True)
            if not (run / "checkpoint.pt").is_file():
                shutil.rmtree(run, ignore_errors=True)
                shutil.rmtree(base / "data", ignore_errors=True)
                _build_run(base, data_dir)
            export_checkpoint(run, bundle, progress=False)
    return run, bundle


@pytest.fixture
def run_dir(artifacts) -> Path:
    return artifacts[0]


@pytest.fixture
def exported(artifacts) -> Path:
    return artifacts[1]


@pytest.fixture
def reuse_graphs(exported, monkeypatch):
    """Skip the (slow) ONNX export in tests that only exercise what happens around it: reuse the exported graphs."""
    from kpd.export import build
    from kpd.export.onnx import Graphs

    bundle = read_bundle(exported)
    graphs = Graphs(bundle.graph(contract.KEYPOINTS_GRAPH), bundle.graph(contract.INFLUENCE_GRAPH))
    monkeypatch.setattr(build, "export_graphs", lambda model, category="": graphs)


def _torch_model(run_dir):
    from kpd.export.build import model_from_checkpoint
    from kpd.train.trainer import load_checkpoint

    return model_from_checkpoint(load_checkpoint(run_dir))


def test_parity_onnx_vs_torch_dynamic_batch_and_points(exported, run_dir, data_dir):
    """onnxruntime (through the torch-free runtime) equals torch within 1e-5 on real shapes, for any B and N."""
    from kpd.export.onnx import torch_outputs
    from kpd.io import read_mesh

    model = Model.load(exported)
    net = _torch_model(run_dir)
    files = sorted((data_dir / "modelnet10" / "chair" / "test").glob("*.ply"))[:3]
    for n in (1, 100, 1024, 3000):
        clouds = np.stack([model.sample(read_mesh(f), seed=n)[1] for f in files]).astype(np.float32)[:, :n]
        for batch in (clouds[:1], clouds):
            got_k, got_w = model.run(batch)
            want_k, want_w = torch_outputs(net, batch)
            assert got_k.shape == (len(batch), K_RUN, 3) and got_w.shape == (len(batch), K_RUN, 42)
            assert np.abs(got_k - want_k).max() <= 1e-5
            assert np.abs(got_w - want_w).max() <= 1e-5
    measured = read_bundle(exported).training["export"]["parity_max_abs"]
    assert max(measured["keypoints"], measured["influence"]) <= 1e-5


def test_graphs_follow_the_contract(exported):
    bundle = read_bundle(exported)
    for spec in contract.GRAPHS:
        graph = onnx.load_from_string(bundle.graph(spec))
        (entry,), (result,) = graph.graph.input, graph.graph.output
        dims = [d.dim_param or d.dim_value for d in entry.type.tensor_type.shape.dim]
        assert entry.name == contract.INPUT_NAME and dims == [contract.BATCH_AXIS, contract.POINTS_AXIS, 3]
        out_dims = [d.dim_param or d.dim_value for d in result.type.tensor_type.shape.dim]
        assert result.name == spec.output and out_dims[0] == contract.BATCH_AXIS
        meta = {p.key: p.value for p in graph.metadata_props}
        assert meta[contract.META_GRAPH] == spec.key
        assert meta[contract.META_FORMAT_VERSION] == str(contract.FORMAT_VERSION)
        assert {n.op_type for n in graph.graph.node} <= {"MatMul", "Gemm", "Add", "Relu", "LeakyRelu", "ReduceMax",
                                                           "Reshape", "Transpose", "Clip", "Squeeze", "Constant"}


def test_manifest_contents(exported, run_dir):
    bundle = read_bundle(exported)
    manifest = bundle.manifest
    assert manifest["category"] == "chair" and manifest["input"]["points"] == 256 and manifest["input"]["up"] == "+z"
    assert (bundle.num_keypoints, bundle.num_cage_vertices, bundle.m) == (K_RUN, 42, 10)  # max(5, 42 // 4)
    net = _torch_model(run_dir)
    np.testing.assert_array_equal(bundle.shared_influence, net.influence_param.detach().double().numpy())
    np.testing.assert_allclose(bundle.cage.vertices, net.template_vertices[0].T.double().numpy())
    record = bundle.training
    assert record["command"] == "pytest tiny run" and record["seed"] == 0 and record["iterations"] == 4
    assert "metrics" in record and record["data"]["category"] == "chair"
    assert record["checkpoint"]["iteration"] == 4
    assert record["export"]["parity_max_abs"]["keypoints"] <= 1e-5
    # prior fitted on Φ's keypoints of the training shapes (6 after the validation carve-out) -> 5 components
    prior = bundle.prior
    assert prior.n_samples_ == 6 and prior.components_.shape == (5, K_RUN, 3)
    template = bundle.template_points
    assert template.shape == (512, 3) and np.abs(template).max() <= 1 + 1e-6
    assert manifest["template"]["source"].startswith("chair_")
    assert manifest["cage"]["fit"] == {"distance": 0.4, "iterations": 100, "step": 0.01}


def test_zip_export(run_dir, tmp_path, reuse_graphs):
    from kpd.export.build import export_model, model_from_checkpoint, synthetic_clouds
    from kpd.train.trainer import load_checkpoint

    net = model_from_checkpoint(load_checkpoint(run_dir / "checkpoint.pt"))
    result = export_model(net, tmp_path / "chair.zip", category="chair", point_count=256,
                          parity_points=synthetic_clouds(3, 256))
    assert read_bundle(result.path).prior is None
    keypoints, influence = Model.load(tmp_path / "chair.zip").run(np.zeros((5, 3)))
    assert keypoints.shape == (K_RUN, 3) and influence.shape == (K_RUN, 42)


def test_failing_bundle_is_not_left_behind(run_dir, tmp_path, monkeypatch, reuse_graphs):
    from kpd.export import build

    monkeypatch.setattr(build, "PARITY_SHAPES", 2)
    net = _torch_model(run_dir)
    with pytest.raises(BundleError, match="differ from torch by .* tolerance 0; nothing was written"):
        build.export_model(net, tmp_path / "bad.kpd", category="chair", point_count=256,
                           parity_points=build.synthetic_clouds(2, 256), tolerance=0.0)
    assert list(tmp_path.iterdir()) == []
    # an existing bundle is refused without force
    (tmp_path / "there.kpd").mkdir()
    with pytest.raises(InputError, match="exists"):
        build.export_model(net, tmp_path / "there.kpd", category="chair", point_count=256,
                           parity_points=build.synthetic_clouds(2, 256))


# --- the authors' checkpoints ----------------------------------------------------------------------------------------

def authors_state(k: int, c: int = 42, seed: int = 0) -> dict:
    """A state dict laid out exactly as docs/method.md §16, built by hand (not from kpd's networks)."""
    from kpd.cage import icosphere

    g = torch.Generator().manual_seed(seed)

    def t(*shape, scale=0.2):
        return torch.randn(*shape, generator=g) * scale

    cage = icosphere(1, 1.4)
    kc = k * c
    s = {"influence_param": t(k, c),
         "template_vertices": torch.from_numpy(cage.vertices.T[None].copy()).float(),
         "template_faces": torch.from_numpy(cage.faces[None].copy()).long()}
    for net, last in (("keypoint_predictor", 256), ("influence_predictor", kc)):
        for i, (a, b) in enumerate(((3, 64), (64, 128), (128, last)), 1):
            s[f"{net}.0.0.conv{i}.conv.weight"] = t(b, a, 1)
            s[f"{net}.0.0.conv{i}.conv.bias"] = t(b)
    for name, (b, a) in {"keypoint_predictor.0.1": (256, 256), "keypoint_predictor.1.layers.0": (512, 256),
                         "keypoint_predictor.1.layers.1": (256, 512), "keypoint_predictor.1.layers.2": (3 * k, 256),
                         "influence_predictor.0.1": (kc, kc), "influence_predictor.1.0": (kc, kc),
                         "influence_predictor.1.1": (kc, kc)}.items():
        s[f"{name}.linear.weight"] = t(b, a, scale=0.1)
        s[f"{name}.linear.bias"] = t(b)
    return s


def authors_forward(s: dict, points: torch.Tensor, k: int, c: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The authors' forward written channel-first as in their code: (B, 3, N) -> (B, 3, K) -> clamp; (B, K, C)."""
    import torch.nn.functional as F

    def pointnet(net, x):
        x = F.relu(F.conv1d(x, s[f"{net}.0.0.conv1.conv.weight"], s[f"{net}.0.0.conv1.conv.bias"]))
        x = F.relu(F.conv1d(x, s[f"{net}.0.0.conv2.conv.weight"], s[f"{net}.0.0.conv2.conv.bias"]))
        x = F.conv1d(x, s[f"{net}.0.0.conv3.conv.weight"], s[f"{net}.0.0.conv3.conv.bias"])
        return torch.max(x, dim=2)[0]

    def linear(name, x, act=True):
        y = F.linear(x, s[f"{name}.linear.weight"], s[f"{name}.linear.bias"])
        return F.leaky_relu(y, 0.1) if act else y

    x = points.transpose(1, 2)  # (B, 3, N)
    h = linear("keypoint_predictor.0.1", pointnet("keypoint_predictor", x))
    h = linear("keypoint_predictor.1.layers.1", linear("keypoint_predictor.1.layers.0", h))
    flat = linear("keypoint_predictor.1.layers.2", h, act=False)
    keypoints = torch.clamp(flat.reshape(-1, 3, k), -1, 1).transpose(1, 2)  # (B, K, 3)
    w = linear("influence_predictor.0.1", pointnet("influence_predictor", x))
    w = linear("influence_predictor.1.1", linear("influence_predictor.1.0", w), act=False)
    return keypoints, w.reshape(-1, k, c)


def test_authors_checkpoint_import(tmp_path, data_dir):
    from kpd.export.build import export_authors
    from kpd.io import read_mesh

    k, c = 8, 42
    state = authors_state(k, c)
    path = tmp_path / "net_final.pth"
    torch.save({"states": state, "optimizer": {"lr": torch.tensor(1e-3)}}, path)
    result = export_authors(path, tmp_path / "airplane.kpd", category="airplane", progress=False)
    model = Model.load(result.path)
    assert model.category == "airplane" and model.prior is None and model.template_points is None
    assert (model.num_keypoints, model.num_cage_vertices, model.m) == (k, c, 5)
    np.testing.assert_array_equal(model.shared_influence, state["influence_param"].double().numpy())
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")
    _, points = model.sample(mesh)
    points = points.astype(np.float32)[None]
    got_k, got_w = model.run(points)
    with torch.no_grad():
        want_k, want_w = authors_forward(state, torch.from_numpy(points), k, c)
    assert np.abs(got_k - want_k.numpy()).max() <= 1e-5
    assert np.abs(got_w - want_w.numpy()).max() <= 1e-5
    manifest = read_bundle(result.path).manifest
    assert manifest["prior"] is None and manifest["training"]["source"].startswith("authors'")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.pop("influence_predictor.1.1.linear.bias"),
         r"lacks 1 key\(s\) of the docs/method.md §16 layout, first 'influence_predictor.1.1.linear.bias' "
         r"\(expected shape \(336,\)\)"),
        (lambda s: s.update({"keypoint_predictor.1.layers.2.linear.weight": torch.zeros(30, 256)}),
         r"key 'keypoint_predictor.1.layers.2.linear.weight' has shape \(30, 256\); expected \(24, 256\) for K=8"),
        (lambda s: s.update({"keypoint_predictor.0.0.conv1.conv.weight": torch.zeros(64, 3)}),
         r"key 'keypoint_predictor.0.0.conv1.conv.weight' has shape \(64, 3\); expected \(64, 3, 1\)"),
        (lambda s: s.pop("influence_param"), "lacks 'influence_param'"),
    ],
)
def test_authors_checkpoint_errors_name_the_key(tmp_path, edit, message):
    from kpd.export.authors import load_authors_checkpoint

    state = authors_state(8)
    edit(state)
    path = tmp_path / "net_final.pth"
    torch.save({"states": state}, path)
    with pytest.raises(InputError, match=message):
        load_authors_checkpoint(path)


def test_authors_checkpoint_not_a_checkpoint(tmp_path):
    from kpd.export.authors import load_authors_checkpoint

    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match=r"cannot load the authors' checkpoint: a text file, not a PyTorch checkpoint"):
        load_authors_checkpoint(tmp_path / "junk.pth")
    (tmp_path / "empty.pth").write_bytes(b"")
    with pytest.raises(InputError, match=r"the file is empty \(0 bytes\)$"):
        load_authors_checkpoint(tmp_path / "empty.pth")
    torch.save({"model": {}}, tmp_path / "other.pth")
    with pytest.raises(InputError, match=r"expected the authors' layout \{'states': state_dict\}"):
        load_authors_checkpoint(tmp_path / "other.pth")


def test_export_command_errors(tmp_path, capsys):
    from kpd.cli import main

    cases = [
        ["export", "--out", str(tmp_path / "x.kpd")],
        ["export", str(tmp_path / "missing_run"), "--out", str(tmp_path / "x.kpd")],
        ["export", "--from-authors", str(tmp_path / "missing.pth"), "--category", "airplane", "--out",
         str(tmp_path / "x.kpd")],
    ]
    for argv in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("kpd export: error:") and "\n" not in err
    assert list(tmp_path.iterdir()) == []


def test_export_command(run_dir, tmp_path, capsys, reuse_graphs):
    from kpd.cli import main

    assert main(["export", str(run_dir), "--out", str(tmp_path / "c.zip")]) == 0
    assert "onnxruntime vs torch max |diff|" in capsys.readouterr().out
    assert read_bundle(tmp_path / "c.zip").prior is not None
    assert main(["export", str(run_dir), "--out", str(tmp_path / "c.zip")]) == 2  # exists, no --force
    assert "exists" in capsys.readouterr().err
    assert Path(tmp_path / "c.zip").is_file()


def test_export_rig_cage_distance(run_dir, tmp_path, capsys, reuse_graphs):
    """--rig-cage-distance: recorded in the bundle, and the runtime fits every rig's cage that tight."""
    from kpd.cli import main
    from kpd.io import Mesh
    from kpd.runtime import Model

    assert main(["export", str(run_dir), "--out", str(tmp_path / "loose.kpd")]) == 0
    assert main(["export", str(run_dir), "--out", str(tmp_path / "tight.kpd"), "--rig-cage-distance", "0.2"]) == 0
    capsys.readouterr()
    assert read_bundle(tmp_path / "tight.kpd").manifest["cage"]["rig"] == {"distance": 0.2}
    assert "rig" not in read_bundle(tmp_path / "loose.kpd").manifest["cage"]
    # a box, rigged by both: the tight cage ends closer to the shape
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-0.5, 0.5) for z in (-0.3, 0.3)], dtype=float)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    box = Mesh(corners, faces)
    radius = [np.linalg.norm(Model.load(tmp_path / name).rig(box, enclose=False).cage.vertices, axis=1).mean()
              for name in ("loose.kpd", "tight.kpd")]
    assert radius[1] < radius[0]
    assert main(["export", str(run_dir), "--out", str(tmp_path / "bad.kpd"), "--rig-cage-distance", "2"]) == 2
    assert "--rig-cage-distance must lie in (0, 1.4)" in capsys.readouterr().err


def test_export_a_bundle_with_other_rig_settings(tmp_path, capsys, data_dir):
    """kpd export BUNDLE --rig-cage-distance D: the same graphs, prior and record; the runtime fits each rig's
    cage at D and transfers the learned influence to it (kpd.rig.transfer_influence); 0 goes back to the
    training cage. Other options are refused for a bundle, and the source is never touched."""
    from kpd.bundle import resolve_bundle
    from kpd.cli import main
    from kpd.io import read_mesh
    from kpd.runtime import Model

    shipped = resolve_bundle("table")
    before = {p.name: p.read_bytes() for p in shipped.iterdir()}
    assert main(["export", str(shipped), "--rig-cage-distance", "0.3", "--out", str(tmp_path / "t3.kpd")]) == 0
    assert main(["export", str(tmp_path / "t3.kpd"), "--rig-cage-distance", "0",
                 "--out", str(tmp_path / "t0.kpd")]) == 0
    capsys.readouterr()
    b3, b0 = read_bundle(tmp_path / "t3.kpd"), read_bundle(tmp_path / "t0.kpd")
    assert b3.manifest["cage"]["rig"] == {"distance": 0.3} and "rig" not in b0.manifest["cage"]
    assert {n: d for n, d in b3.files.items() if n != "manifest.json"} == \
           {n: d for n, d in read_bundle(shipped).files.items() if n != "manifest.json"}
    assert b3.manifest["prior"] == read_bundle(shipped).manifest["prior"]
    mesh = read_mesh(data_dir / "modelnet10" / "table" / "test" / "table_0393.ply")
    tight, loose = Model.load(tmp_path / "t3.kpd", threads=1), Model.load(tmp_path / "t0.kpd", threads=1)
    assert tight.rig_settings["rig"] == {"distance": 0.3} and tight.rig_settings["transfer"]["sigma"] > 0
    assert loose.rig_settings["transfer"] is None
    r3, r0 = tight.rig(mesh), loose.rig(mesh)
    assert np.linalg.norm(r3.cage.vertices, axis=1).mean() < np.linalg.norm(r0.cage.vertices, axis=1).mean()
    np.testing.assert_array_equal(r3.deform(r3.keypoints), mesh.vertices)  # a zero edit is still the input
    assert not np.allclose(r3.influence, r0.influence)
    # refusals: one line, exit 2, nothing written
    assert main(["export", str(shipped), "--out", str(tmp_path / "x.kpd")]) == 2
    assert "give --rig-cage-distance" in capsys.readouterr().err
    assert main(["export", str(shipped), "--rig-cage-distance", "0.2", "--up", "z", "--out",
                 str(tmp_path / "x.kpd")]) == 2
    assert "only --rig-cage-distance, --out and --force apply" in capsys.readouterr().err
    assert main(["export", str(shipped), "--rig-cage-distance", "0.2", "--out", str(shipped)]) == 2
    capsys.readouterr()
    assert not (tmp_path / "x.kpd").exists()
    assert {p.name: p.read_bytes() for p in shipped.iterdir()} == before
