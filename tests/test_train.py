"""kpd.train: networks (docs/method.md §2-3, §16), torch kernels vs numpy, gradients, training, resume,
checkpoints."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from kpd.cage import fit_cage, icosphere, influence_mask
from kpd.data import SampleSettings, prepare
from kpd.geometry import chamfer as np_chamfer
from kpd.geometry import farthest_point_sampling as np_fps
from kpd.geometry import sample_surface
from kpd.mvc import mvc_weights as np_mvc
from kpd.train import ops
from kpd.train.losses import influence_loss
from kpd.train.nets import KeypointDeformer, ModelConfig, count_parameters
from kpd.train.predictor import CheckpointPredictor
from kpd.train.trainer import Trainer, TrainConfig, load_checkpoint

ICO = icosphere(1, 1.4)


def make_model(k: int = 12, source: str = "learned", seed: int = 0) -> KeypointDeformer:
    config = ModelConfig(keypoints=k, cage_vertices=42, cage_faces=80, m=5, keypoint_source=source)
    return KeypointDeformer(config, torch.from_numpy(ICO.vertices), torch.from_numpy(ICO.faces), seed=seed)


# ----------------------------------------------------------------------------------------------- networks

@pytest.mark.parametrize("k, phi, gamma", [(8, 376_472, 391_616), (12, 379_556, 837_152)])
def test_parameter_counts_match_the_authors(k, phi, gamma):
    model = make_model(k)
    assert count_parameters(model.keypoint_predictor) == phi
    assert count_parameters(model.influence_predictor) == gamma
    assert count_parameters(model) == phi + gamma + k * 42


def test_state_dict_layout_is_the_authors():
    k, c, kc = 12, 42, 12 * 42
    states = make_model(k).state_dict()
    expected = {
        "influence_param": (k, c), "template_vertices": (1, 3, c), "template_faces": (1, 80, 3),
        "keypoint_predictor.0.0.conv1.conv.weight": (64, 3, 1),
        "keypoint_predictor.0.0.conv2.conv.weight": (128, 64, 1),
        "keypoint_predictor.0.0.conv3.conv.weight": (256, 128, 1), "keypoint_predictor.0.1.linear.weight": (256, 256),
        "keypoint_predictor.1.layers.0.linear.weight": (512, 256),
        "keypoint_predictor.1.layers.1.linear.weight": (256, 512),
        "keypoint_predictor.1.layers.2.linear.weight": (3 * k, 256),
        "influence_predictor.0.0.conv3.conv.weight": (kc, 128, 1), "influence_predictor.0.1.linear.weight": (kc, kc),
        "influence_predictor.1.0.linear.weight": (kc, kc), "influence_predictor.1.1.linear.weight": (kc, kc),
    }
    for key, shape in expected.items():
        assert tuple(states[key].shape) == shape, key
    assert len(states) == 3 + 2 * (7 + 6)
    assert states["template_faces"].dtype == torch.int64


def test_initialisation_xavier_zero_bias_zero_wc_and_seeded():
    a, b, c = make_model(seed=0), make_model(seed=0), make_model(seed=1)
    assert torch.equal(a.influence_param, torch.zeros(12, 42))
    w = a.keypoint_predictor[1].layers[1].linear.weight  # 512 -> 256
    bound = (6.0 / (512 + 256)) ** 0.5
    assert w.abs().max() <= bound and w.abs().max() > 0.9 * bound
    assert all(float(p.detach().abs().sum()) == 0 for n, p in a.named_parameters() if n.endswith("bias"))
    for (n, p), (_, q), (_, r) in zip(a.named_parameters(), b.named_parameters(), c.named_parameters()):
        assert torch.equal(p, q)
        if n.endswith("weight"):
            assert not torch.equal(p, r)


def test_keypoint_head_order_and_clamp():
    model = make_model(4)
    x = torch.rand(3, 64, 3)
    flat = torch.nn.Sequential(*model.keypoint_predictor)(x)  # (B, 3K) [x..., y..., z...]
    raw = model.keypoint_predictor(x)
    assert torch.equal(raw[:, :, 0], flat[:, :4]) and torch.equal(raw[:, :, 2], flat[:, 8:])
    with torch.no_grad():
        model.keypoint_predictor[1].layers[2].linear.bias.fill_(5.0)
        assert float(model.keypoints(x).max()) == 1.0


# ----------------------------------------------------------------------------------------------- kernels vs numpy

@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 40), st.integers(1, 40))
def test_chamfer_matches_numpy(seed, n, m):
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(m, 3))
    got = ops.chamfer(torch.from_numpy(a)[None], torch.from_numpy(b)[None])
    assert got.item() == pytest.approx(np_chamfer(a, b), rel=1e-9, abs=1e-12)


def test_chamfer_large_clouds_and_gradient_match_dense_min():
    rng = np.random.default_rng(1)
    a = torch.from_numpy(rng.normal(size=(3, 400, 3))).requires_grad_()
    b = torch.from_numpy(rng.normal(size=(3, 300, 3)))
    got = ops.chamfer(a, b)
    for i in range(3):
        assert got[i].item() == pytest.approx(np_chamfer(a[i].detach().numpy(), b[i].numpy()), rel=1e-9)
    got.sum().backward()
    a2 = a.detach().clone().requires_grad_()
    d = ((a2[:, :, None] - b[:, None]) ** 2).sum(-1)
    (d.min(2).values.mean(1) + d.min(1).values.mean(1)).sum().backward()
    assert torch.allclose(a.grad, a2.grad, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 60))
def test_fps_matches_numpy(seed, n):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(2, n, 3))
    k = min(n, 1 + seed % 12)
    start = rng.integers(n, size=2)
    got = ops.farthest_point_sampling(torch.from_numpy(points), k, torch.from_numpy(start))
    for i in range(2):
        np.testing.assert_array_equal(got[i].numpy(), np_fps(points[i], k, start=int(start[i])))


def _chair_sample(data_dir, name="chair_0003", n=512):
    from kpd.geometry import Normalizer
    from kpd.io import read_mesh

    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "train" / f"{name}.ply")
    v = Normalizer().fit(mesh.vertices).apply(mesh.vertices)
    return sample_surface(v, mesh.triangles, n, seed=0).points


def test_mvc_matches_numpy(data_dir):
    points = _chair_sample(data_dir)
    cage = fit_cage(points)
    rng = np.random.default_rng(0)
    inside = rng.uniform(-0.5, 0.5, size=(200, 3))
    for query in (points, inside):
        want = np_mvc(query, cage.vertices, cage.faces)
        got = ops.mvc_weights(torch.from_numpy(query)[None], torch.from_numpy(cage.vertices)[None],
                              torch.from_numpy(cage.faces)).numpy()[0]
        np.testing.assert_allclose(got, want, atol=1e-9)
    got = ops.mvc_weights(torch.from_numpy(inside)[None], torch.from_numpy(cage.vertices)[None],
                          torch.from_numpy(cage.faces)).numpy()[0]
    np.testing.assert_allclose(got @ cage.vertices, inside, atol=1e-10)


def test_influence_mask_matches_numpy():
    rng = np.random.default_rng(3)
    kp = rng.uniform(-1, 1, size=(12, 3))
    cage = ICO.vertices * rng.uniform(0.4, 1.0, size=(42, 1))
    for m in (1, 3, 5, 42):
        got = ops.influence_mask(torch.from_numpy(kp)[None], torch.from_numpy(cage)[None], m).numpy()[0]
        np.testing.assert_array_equal(got, influence_mask(kp, cage, m))
        assert (got.sum(1) >= m).all()


def test_zero_keypoint_offset_is_identity():
    model = make_model(8)
    rng = np.random.default_rng(0)
    points = torch.from_numpy(rng.uniform(-0.6, 0.6, size=(2, 100, 3))).float()
    cage = torch.from_numpy(ICO.vertices).float()[None].repeat(2, 1, 1)
    weights = ops.mvc_weights(points, cage, torch.from_numpy(ICO.faces))
    kp = torch.rand(2, 8, 3)
    with torch.no_grad():
        model.influence_param.normal_()
        out = model.deform(points, cage, weights, kp, kp)
    assert torch.equal(out.new_cage, cage)
    assert torch.allclose(out.deformed, points, atol=1e-5)


def test_influence_loss_forms():
    w = torch.full((2, 3, 4), 2.0)
    assert influence_loss(w, "code").item() == 4.0
    assert influence_loss(w, "paper").item() == pytest.approx(2.0 * 12 ** 0.5)
    with pytest.raises(ValueError, match="code"):
        influence_loss(w, "other")


# ----------------------------------------------------------------------------------------------- training

SMALL = SampleSettings(points=256, samples=2)


@pytest.fixture(scope="module")
def chairs(data_dir, tmp_path_factory):
    """A dozen real chairs (train) and four (val), 256 points, 2 samples, cached in a temporary folder."""
    root = tmp_path_factory.mktemp("chairs")
    src = data_dir / "modelnet10" / "chair" / "train"
    for _, name in enumerate(sorted(src.glob("*.ply"))[:16]):
        shutil.copy(name, root / name.name)
    split = {"train": [f"chair_{i:04d}" for i in range(1, 13)], "val": [f"chair_{i:04d}" for i in range(13, 17)]}
    (root / "split.json").write_text(json.dumps(split))
    return prepare(root, None, settings=SMALL, cache_dir=tmp_path_factory.mktemp("cache"),
                   split_file=root / "split.json", processes=1, progress=False)


def small_config(**kw) -> TrainConfig:
    base = dict(keypoints=4, iterations=40, batch=4, warmup=10, save_every=40, val_pairs=8)
    base.update(kw)
    return TrainConfig(**base)


def test_gradients_reach_phi_gamma_wc_and_nothing_else(chairs, tmp_path):
    trainer = Trainer(small_config(), chairs, tmp_path, device="cpu", command="test")
    out = trainer.losses(trainer.config.warmup)  # past the warm-up: full loss
    for name in ("cage", "weights"):
        assert not out[name].requires_grad
    assert out["new_cage"].requires_grad and out["deformed"].requires_grad
    out["loss"].backward()
    for name, p in trainer.model.named_parameters():
        assert p.grad is not None and float(p.grad.abs().sum()) > 0, name
    assert {n for n, _ in trainer.model.named_parameters()} >= {"influence_param"}
    for name, buf in trainer.model.named_buffers():
        assert buf.grad is None and not buf.requires_grad, name
    for name, t in trainer.train_set.items():
        assert not t.requires_grad and t.grad is None, name


def test_warmup_trains_only_the_keypoint_predictor(chairs, tmp_path):
    trainer = Trainer(small_config(), chairs, tmp_path, device="cpu", command="test")
    before = {n: p.detach().clone() for n, p in trainer.model.named_parameters()}
    trainer.step(0)
    for name, p in trainer.model.named_parameters():
        changed = not torch.equal(p, before[name])
        assert changed == name.startswith("keypoint_predictor"), name


@pytest.mark.parametrize("source, t", [("learned", 0), ("learned", 10), ("fps", 0)])
def test_step_reads_no_value_on_the_host(chairs, tmp_path, source, t):
    """GPU-ready: a whole step (batch, forward, backward, both optimisers) runs on the meta device, where tensors have
    no values: any .item(), float(), .cpu(), .numpy(), bool() or value-dependent shape in it (a host round trip on a
    GPU) would raise."""
    trainer = Trainer(small_config(keypoint_source=source), chairs, tmp_path, device="cpu", command="test")
    meta = torch.device("meta")
    trainer.model.to(meta)
    trainer.train_set = {k: v.to(meta) for k, v in trainer.train_set.items()}
    trainer.device = meta
    terms = trainer.step(t)  # warm-up (t=0) and full loss (t=10 = warmup)
    assert terms.device == meta and terms.shape == (4,)
    phi = {id(p) for p in trainer.model.phi_parameters()}
    trained = [p for p in trainer.model.parameters() if t >= 10 or source == "fps" or id(p) in phi]
    assert trained and all(p.grad is not None and p.grad.device == meta for p in trained)
    with pytest.raises(RuntimeError, match="meta"):
        float(terms[0])  # the check can fail


def test_short_run_lowers_the_losses(chairs, tmp_path):
    trainer = Trainer(small_config(iterations=50, warmup=5, save_every=50), chairs, tmp_path, device="cpu",
                      command="test")
    record = trainer.run(progress=False)
    h = np.asarray(trainer.history)
    assert h[:5, 3].mean() > 1.3 * h[-10:, 3].mean()  # keypoint regulariser
    sim = h[~np.isnan(h[:, 2]), 2]
    assert sim[-10:].mean() < sim[:5].mean()
    assert record["metrics"]["val_chamfer"] < record["metrics"]["val_chamfer_undeformed"]
    assert (tmp_path / "losses.png").stat().st_size > 1000
    lines = (tmp_path / "losses.csv").read_text().splitlines()
    assert lines[0] == "iteration,loss,sim,kpt,inf" and len(lines) == 51


def test_resume_equals_uninterrupted_bitwise(chairs, tmp_path):
    config = small_config(iterations=16, warmup=4, save_every=8)
    full = Trainer(config, chairs, tmp_path / "full", device="cpu", command="test")
    full.run(progress=False)
    first = Trainer(config, chairs, tmp_path / "cut", device="cpu", command="test")
    first.run(progress=False, stop_at=8)
    del first  # "killed"
    resumed = Trainer(config, chairs, tmp_path / "cut", device="cpu", command="test")
    resumed.load_state(load_checkpoint(tmp_path / "cut"))
    assert resumed.iteration == 8
    resumed.run(progress=False)
    for (name, p), (_, q) in zip(full.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(p, q), name
    np.testing.assert_array_equal(np.asarray(full.history), np.asarray(resumed.history))
    a = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)
    for key in a["optimizers"]["deformer"]["state"]:
        for name, value in a["optimizers"]["deformer"]["state"][key].items():
            assert torch.equal(value, b["optimizers"]["deformer"]["state"][key][name])


def test_resume_refuses_another_recipe(chairs, tmp_path):
    Trainer(small_config(iterations=2, warmup=1, save_every=2), chairs, tmp_path, device="cpu").run(progress=False)
    other = Trainer(small_config(iterations=4, alpha_kpt=1.0), chairs, tmp_path, device="cpu")
    with pytest.raises(Exception, match="alpha_kpt"):
        other.load_state(load_checkpoint(tmp_path))


def test_checkpoint_is_weights_only_and_predictor_loads(chairs, tmp_path):
    Trainer(small_config(iterations=12, warmup=5, save_every=6), chairs, tmp_path, device="cpu").run(progress=False)
    ckpt = torch.load(tmp_path / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert ckpt["format"] == "kpd-checkpoint" and ckpt["iteration"] == 12
    assert ckpt["history"]["train"].shape == (12, 5) and ckpt["history"]["val"].shape == (2, 3)
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))
    record = json.loads((tmp_path / "record.json").read_text())
    assert record["seed"] == 0 and record["iterations"] == 12 and record["data"]["usable"]["train"] == 12
    predictor = CheckpointPredictor.load(tmp_path)
    assert (predictor.K, predictor.C, predictor.m, predictor.keypoint_source) == (4, 42, 10, "learned")
    np.testing.assert_allclose(predictor.template.vertices, ICO.vertices, atol=1e-6)
    points = chairs.samples["val"].points[:3, 0]
    kp = predictor.keypoints(points)
    w = predictor.influence(points)
    assert kp.shape == (3, 4, 3) and kp.dtype == np.float32 and np.abs(kp).max() <= 1
    assert w.shape == (3, 4, 42)
    with torch.no_grad():
        offset = predictor.model.influence_offset(torch.from_numpy(points)).numpy()
    np.testing.assert_allclose(w, predictor.influence_param + offset, atol=1e-6)  # unmasked W_C + W_I


def test_fps_keypoint_baseline_trains_only_the_deformer(chairs, tmp_path):
    trainer = Trainer(small_config(iterations=6, keypoint_source="fps"), chairs, tmp_path, device="cpu")
    assert trainer.model.keypoint_predictor is None and trainer.opt_keypoints is None
    before = trainer.model.influence_param.detach().clone()
    trainer.run(progress=False)
    assert not torch.equal(before, trainer.model.influence_param)
    predictor = CheckpointPredictor.load(tmp_path)
    points = chairs.samples["train"].points[:2, 0]
    kp = predictor.keypoints(points)
    idx = np_fps(points[0].astype(np.float64), 4, start=int(np.argmax((points[0] ** 2).sum(1))))
    np.testing.assert_allclose(kp[0], points[0][idx])


# ----------------------------------------------------------------------------------------------- command line

def test_train_command_reports_skipped_meshes_and_resumes(data_dir, tmp_path, capsys):
    from kpd.cli import main

    shapes = tmp_path / "shapes"
    shapes.mkdir()
    for name in sorted((data_dir / "modelnet10" / "chair" / "train").glob("*.ply"))[:7]:
        shutil.copy(name, shapes / name.name)
    (shapes / "empty.ply").write_bytes(b"")
    (shapes / "corrupt.obj").write_text("v 0 0\nf 1 2 3\n")
    out = tmp_path / "run"
    args = ["train", str(shapes), "--keypoints", "4", "--out", str(out), "--iterations", "6", "--batch", "4",
            "--points", "256", "--samples", "2", "--warmup", "2", "--save-every", "3", "--val-pairs", "4",
            "--cache", str(tmp_path / "cache"), "--processes", "1", "--quiet", "--threads", "1"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "empty.ply" in err and "corrupt.obj" in err
    record = json.loads((out / "record.json").read_text())
    skipped = {s["path"].rsplit("/", 1)[1] for s in record["skipped"]}
    assert skipped <= {"empty.ply", "corrupt.obj"} and "empty.ply" in skipped
    assert record["metrics"]["iterations_done"] == 6 and record["data"]["layout"] == "flat"
    assert json.loads((out / "model.json").read_text())["model_config"]["keypoints"] == 4
    assert main(args) == 2  # exists: refuses without --resume / --force
    assert "pass --resume" in capsys.readouterr().err
    assert main([a if a != "6" else "9" for a in args] + ["--resume"]) == 0
    assert load_checkpoint(out)["iteration"] == 9
    assert main(args[:-2] + ["--resume", "--alpha-kpt", "1"]) == 2
    assert "alpha_kpt" in capsys.readouterr().err


def test_eval_commands_on_a_tiny_run(data_dir, tmp_path, capsys):
    from kpd.cli import main

    shapes = tmp_path / "shapes"
    shapes.mkdir()
    files = sorted((data_dir / "modelnet10" / "chair" / "train").glob("*.ply"))[:10]
    for name in files:
        shutil.copy(name, shapes / name.name)
    stems = [f.stem for f in files]
    (tmp_path / "split.json").write_text(json.dumps({"train": stems[:5], "val": stems[5:7], "test": stems[7:]}))
    common = ["--points", "256", "--samples", "2", "--cache", str(tmp_path / "cache"), "--processes", "1"]
    run = tmp_path / "run"
    assert main(["train", str(shapes), "--keypoints", "4", "--out", str(run), "--iterations", "4", "--batch", "2",
                 "--warmup", "1", "--split-file", str(tmp_path / "split.json"), "--quiet", "--threads", "1",
                 "--val-pairs", "2", *common]) == 0
    out = tmp_path / "align.json"
    assert main(["eval", "alignment", str(run), "--baseline", str(run), "--pairs", "5", "--out", str(out),
                 "--gallery", str(tmp_path / "g.png"), "--gallery-pairs", "2", "--quiet",
                 "--cache", str(tmp_path / "cache")]) == 0
    result = json.loads(out.read_text())
    assert result["test_shapes"] == 3 and len(result["per_pair"]) == 5
    assert all(p["source"] != p["target"] for p in result["per_pair"])
    assert result["chamfer_x1e3"]["model"]["mean"] == result["chamfer_x1e3"]["baseline"]["mean"]
    assert (tmp_path / "g.png").stat().st_size > 1000
    out = tmp_path / "kp.json"
    assert main(["eval", "keypoints", str(run), "--samples", "2", "--max-train", "4", "--out", str(out), "--quiet",
                 "--cache", str(tmp_path / "cache")]) == 0
    result = json.loads(out.read_text())
    assert result["test_shapes"] == 3 and result["stability"]["mean"] >= 0
    assert sorted(result["mirror"]["permutation"]) == [0, 1, 2, 3]
    assert main(["eval", "keypoints", str(run), "--out", str(out), "--quiet"]) == 2  # exists
    assert "--force" in capsys.readouterr().err


def test_recipe_flags_map_to_the_paper_values(tmp_path):
    import argparse

    from kpd.commands import train as cmd

    parser = argparse.ArgumentParser()
    cmd.add_arguments(parser)
    code = cmd.recipe(parser.parse_args([str(tmp_path), "--out", "x"]))
    assert (code.alpha_kpt, code.alpha_inf, code.inf_reg, code.warmup, code.wc_lr, code.clamp, code.paper_m) == (
        2.0, 1e6, "code", 200, 1e-2, True, False)
    paper = cmd.recipe(parser.parse_args([str(tmp_path), "--out", "x", "--paper"]))
    assert (paper.alpha_kpt, paper.alpha_inf, paper.inf_reg, paper.warmup, paper.wc_lr, paper.clamp,
            paper.paper_m) == (1.0, 1e-6, "paper", 0, 1e-3, False, True)
    mixed = cmd.recipe(parser.parse_args([str(tmp_path), "--out", "x", "--inf-reg", "paper", "--warmup", "0",
                                          "--no-clamp", "--paper-m", "--keypoint-source", "fps"]))
    assert (mixed.alpha_inf, mixed.warmup, mixed.clamp, mixed.paper_m, mixed.keypoint_source, mixed.alpha_kpt) == (
        1e-6, 0, False, True, "fps", 2.0)
