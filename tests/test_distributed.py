"""kpd.train.distributed: kpd train under torchrun (2 gloo ranks) against one process, resume across world sizes, the
sample cache filled in turns, and the checks of the torchrun environment. Real ModelNet10 chairs, short runs."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap

import numpy as np
import pytest
import torch

from kpd.errors import InputError
from kpd.train import distributed
from kpd.train.nets import KeypointDeformer, ModelConfig
from kpd.train.trainer import load_checkpoint

ENV = {"RANK": "0", "LOCAL_RANK": "0", "WORLD_SIZE": "2", "LOCAL_WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1",
       "MASTER_PORT": "29500"}


@pytest.fixture(scope="module")
def shapes(data_dir, tmp_path_factory):
    """16 real chairs in a flat folder with a split file: 12 train, 4 val."""
    root = tmp_path_factory.mktemp("dist_chairs")
    files = sorted((data_dir / "modelnet10" / "chair" / "train").glob("*.ply"))[:16]
    for f in files:
        shutil.copy(f, root / f.name)
    stems = [f.stem for f in files]
    (root / "split.json").write_text(json.dumps({"train": stems[:12], "val": stems[12:]}))
    return root


def train_args(shapes, out, cache, iterations=12, batch=4):
    return ["train", str(shapes), "--split-file", str(shapes / "split.json"), "--out", str(out), "--keypoints", "4",
            "--iterations", str(iterations), "--batch", str(batch), "--warmup", "4", "--save-every", "6",
            "--val-pairs", "4", "--points", "256", "--samples", "2", "--cache", str(cache), "--processes", "1",
            "--quiet", "--threads", "1"]


def clean_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in distributed.VARIABLES}
    env["OMP_NUM_THREADS"] = "1"
    return env


def torchrun(args, nproc=2, module=("-m", "kpd.cli")) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc_per_node N -m kpd.cli ARGS`` (a free local port; one node)."""
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc),
               *module, *args]
    with tempfile.TemporaryDirectory(prefix="kpd-torchrun-") as temporary:  # torchrun leaves its log folder there
        return subprocess.run(command, capture_output=True, text=True, env=dict(clean_env(), TMPDIR=temporary),
                              timeout=600)


def single(args) -> None:
    from kpd.cli import main

    assert main(args) == 0


@pytest.fixture(scope="module")
def reference(shapes, tmp_path_factory):
    """One process, batch 4, 12 iterations (4 of warm-up), checkpoints at 6 and 12; fills the module's cache."""
    base = tmp_path_factory.mktemp("dist_runs")
    cache = base / "cache"
    single(train_args(shapes, base / "one", cache))
    return base / "one", cache


def assert_same_run(got, want) -> None:
    """Loss curve, validation and every weight tensor of two checkpoints agree to float32 rounding.

    Weights are compared by how far they moved from the common initial weights: a rank that skipped the gradient
    average, or trained on other pairs, would differ by the order of that motion; rounding (one batch mean against
    the mean of two half-batch means) differs by ~1e-6 of it in Φ and up to ~3e-3 in Γ's last PointNet layer, whose
    max-pool can pick another point after a rounding-sized change.
    """
    a, b = load_checkpoint(got), load_checkpoint(want)
    assert a["iteration"] == b["iteration"] == 12
    ha, hb = a["history"]["train"].numpy(), b["history"]["train"].numpy()
    np.testing.assert_array_equal(np.isnan(ha), np.isnan(hb))  # the warm-up rows have no sim / inf terms
    np.testing.assert_allclose(ha, hb, rtol=2e-4)
    np.testing.assert_allclose(a["history"]["val"].numpy(), b["history"]["val"].numpy(), rtol=2e-4)
    config = ModelConfig.from_dict(b["model_config"])
    states = b["states"]
    init = KeypointDeformer(config, states["template_vertices"][0].T, states["template_faces"][0], seed=0).state_dict()
    for name, value in states.items():
        if name.startswith("template"):
            assert torch.equal(a["states"][name], value), name
            continue
        moved = float((value - init[name]).norm())
        assert moved > 0, name
        assert float((a["states"][name] - value).norm()) <= 1e-2 * moved, name


def test_two_gloo_ranks_follow_one_process(shapes, reference, tmp_path):
    one, cache = reference
    out = tmp_path / "two"
    done = torchrun(train_args(shapes, out, cache))
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("done: 12 iterations") == 1  # rank 0 alone reports
    assert "2 ranks (gloo), 2 pairs each" in done.stdout
    assert_same_run(out, one)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in one.iterdir())  # rank 0 alone writes
    record = json.loads((out / "record.json").read_text())
    assert record["world_size"] == 2 and record["world_sizes"] == [[0, 2]]
    assert record["distributed"] == {"world_size": 2, "local_world_size": 2, "backend": "gloo", "device_type": "cpu"}
    assert record["train_config"]["batch"] == 4  # the global batch
    solo = json.loads((one / "record.json").read_text())
    assert solo["world_size"] == 1 and solo["distributed"] is None and solo["world_sizes"] == [[0, 1]]


@pytest.mark.parametrize("first, then", [(1, 2), (2, 1)])
def test_resume_with_another_world_size(shapes, reference, tmp_path, first, then):
    one, cache = reference
    out = tmp_path / "run"
    for ranks, iterations, extra in ((first, 6, []), (then, 12, ["--resume"])):
        args = train_args(shapes, out, cache, iterations=iterations) + extra
        if ranks == 1:
            single(args)
        else:
            done = torchrun(args, ranks)
            assert done.returncode == 0, done.stderr[-3000:]
        assert load_checkpoint(out)["iteration"] == iterations
    assert_same_run(out, one)
    record = json.loads((out / "record.json").read_text())
    assert record["world_sizes"] == [[0, first], [6, then]] and record["world_size"] == then


SCRIPT = """
    import json, sys
    from pathlib import Path
    from kpd.data import SampleSettings, prepare
    from kpd.train import distributed

    shapes, cache, log = (Path(a) for a in sys.argv[1:4])
    world = distributed.from_environment(4, "cpu")
    distributed.init(world)

    def fill():
        found = sorted(p.name for p in (cache / "samples").glob("*.npz")) if (cache / "samples").is_dir() else []
        data = prepare(shapes, None, settings=SampleSettings(points=128, samples=1), cache_dir=cache,
                       split_file=shapes / "split.json", processes=1, progress=False)
        return found, {k: len(v) for k, v in data.samples.items()}

    found, counts = distributed.in_turn(world, fill)
    (log / f"rank{world.rank}.json").write_text(json.dumps({"found": found, "counts": counts}))
    distributed.shutdown()
"""


def test_sample_cache_is_filled_by_rank_zero_first(shapes, tmp_path):
    script = tmp_path / "fill.py"
    script.write_text(textwrap.dedent(SCRIPT))
    cache = tmp_path / "cache"
    done = torchrun([str(shapes), str(cache), str(tmp_path)], module=(str(script),))
    assert done.returncode == 0, done.stderr[-3000:]
    rank0, rank1 = (json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1))
    entries = sorted(p.name for p in (cache / "samples").glob("*.npz"))
    assert len(entries) == 16 and not list((cache / "samples").glob("*.tmp"))
    assert rank0["found"] == [] and rank1["found"] == entries  # rank 1 started after rank 0 had sampled everything
    assert rank0["counts"] == rank1["counts"] == {"train": 12, "val": 4}


# ----------------------------------------------------------------------------------------------- environment checks

def test_no_torchrun_means_one_process():
    assert distributed.from_environment(16, "auto", {}) is None
    assert distributed.from_environment(16, "auto", {"MASTER_ADDR": "x", "MASTER_PORT": "1"}) is None


def test_torchrun_environment_is_read():
    world = distributed.from_environment(16, "cpu", {**ENV, "RANK": "1", "LOCAL_RANK": "1"})
    assert world == distributed.World(1, 1, 2, 2, "gloo", torch.device("cpu"))
    assert world.share(16) == slice(8, 16) and not world.main


@pytest.mark.parametrize("change, device, match", [
    ({}, "cpu", None),  # batch 6 / 2 ranks: fine; the cases below are not
    ({"WORLD_SIZE": "4", "LOCAL_WORLD_SIZE": "4"}, "cpu", r"--batch 6 does not split over WORLD_SIZE=4"),
    ({"WORLD_SIZE": None}, "cpu", r"incomplete torchrun environment: RANK, LOCAL_RANK, LOCAL_WORLD_SIZE, MASTER_ADDR, "
                                  r"MASTER_PORT set but WORLD_SIZE missing"),
    ({"WORLD_SIZE": "two"}, "cpu", r"WORLD_SIZE must be an integer; got 'two'"),
    ({"RANK": "2"}, "cpu", r"RANK must lie in \[0, WORLD_SIZE\); got RANK=2, WORLD_SIZE=2"),
    ({"LOCAL_RANK": "2"}, "cpu", r"LOCAL_RANK=2, LOCAL_WORLD_SIZE=2"),
    ({"LOCAL_WORLD_SIZE": "3"}, "cpu", r"LOCAL_WORLD_SIZE=3, WORLD_SIZE=2"),
    ({"MASTER_PORT": "70000"}, "cpu", r"MASTER_PORT must lie in \[1, 65535\]; got 70000"),
    ({}, "cuda:1", r"--device cuda:1: under torchrun each rank uses the GPU of its LOCAL_RANK"),
    ({}, "mps", r"runs on cpu \(gloo\) or cuda \(nccl\)"),
])
def test_inconsistent_torchrun_environment_is_refused(change, device, match):
    env = {k: v for k, v in {**ENV, **change}.items() if v is not None}
    if match is None:
        assert distributed.from_environment(6, device, env).size == 2
        return
    with pytest.raises(InputError, match=match):
        distributed.from_environment(6, device, env)


def test_what_every_rank_finds_is_reported_by_rank_zero_alone():
    with pytest.raises(distributed.Stopped):
        distributed.from_environment(3, "cpu", {**ENV, "RANK": "1", "LOCAL_RANK": "1"})
    with pytest.raises(distributed.Stopped):
        distributed.from_environment(4, "cuda:0", {**ENV, "RANK": "1", "LOCAL_RANK": "1"})


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
def test_cuda_without_a_gpu_is_refused():
    with pytest.raises(InputError, match="CUDA is not available"):
        distributed.from_environment(6, "cuda", ENV)


def test_incomplete_environment_ends_the_command_with_one_line(shapes, tmp_path):
    out = tmp_path / "run"
    env = {**clean_env(), "RANK": "0", "WORLD_SIZE": "2"}
    done = subprocess.run([sys.executable, "-m", "kpd.cli", *train_args(shapes, out, tmp_path / "cache")],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "kpd train: error: incomplete torchrun environment: RANK, WORLD_SIZE set but LOCAL_RANK, LOCAL_WORLD_SIZE, "
        "MASTER_ADDR, MASTER_PORT missing; start kpd train with torchrun "
        "(docs/training.md: Training on more machines) or "
        "unset them"]
    assert not out.exists()


def worker_lines(stderr: str) -> list[str]:
    """What the ranks printed (torchrun's own report of the failure, with its traceback, follows them)."""
    assert "/kpd/" not in stderr  # no traceback through kpd's code
    return [line for line in stderr.splitlines() if line.startswith("kpd train")]


def test_torchrun_refuses_a_batch_the_ranks_cannot_share_and_an_occupied_output(shapes, reference, tmp_path):
    one, cache = reference
    out = tmp_path / "run"
    done = torchrun(train_args(shapes, out, cache, batch=3))
    # the worker ended with status 2 (torchrun stops the other rank once one has ended, so it may report only one)
    assert done.returncode != 0 and "exitcode  : 2" in done.stderr
    assert worker_lines(done.stderr) == [  # said once, by rank 0
        "kpd train: error: --batch 3 does not split over WORLD_SIZE=2 ranks: each rank takes batch / world size "
        "pairs, so pass a multiple of 2"]
    assert not out.exists()
    before = {p.name: p.stat().st_mtime_ns for p in one.iterdir()}
    done = torchrun(train_args(shapes, one, cache))  # rank 0 finds the output taken; rank 1 stops without a word
    assert done.returncode != 0 and "exitcode  : 2" in done.stderr
    assert worker_lines(done.stderr) == [
        f"kpd train: error: output {one} exists and is not empty; pass --resume to continue or --force to start over"]
    assert {p.name: p.stat().st_mtime_ns for p in one.iterdir()} == before
