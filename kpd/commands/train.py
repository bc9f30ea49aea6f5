"""kpd train: learn keypoints and the keypoint-driven cage deformation on one shape category."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from kpd.commands import existing, folder, integer, number, require_train_extra
from kpd.errors import InputError

HELP = "train KeypointDeformer on a shape category (PyTorch; cuda when available)"
EXAMPLE = ("kpd train data/modelnet10 --category chair --keypoints 12 --out runs/chair\n"
           "  torchrun --nproc_per_node 2 -m kpd.cli train data/modelnet10 --category chair --out runs/chair  "
           "# 2 ranks, 8 pairs each")

# The paper's values where the authors' code differs (docs/method.md §11).
PAPER = {"alpha_kpt": 1.0, "inf_reg": "paper", "alpha_inf": 1e-6, "warmup": 0, "wc_lr": None, "clamp": False,
         "paper_m": True}


_QUIET_RANK_GRACE = 3.0  # s a rank that stops without a message of its own waits before it ends

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", type=folder,
                        help="dataset folder (ModelNet, ShapeNet v1/v2, or a flat folder of meshes)")
    parser.add_argument("--category", help="class folder, ShapeNet synset id or name (e.g. chair)")
    parser.add_argument("--keypoints", type=integer(1), default=12, help="K, keypoints to discover (default 12)")
    parser.add_argument("--out", required=True, help="run folder for checkpoints, curves and the record")
    g = parser.add_argument_group("run")
    g.add_argument("--iterations", type=integer(1), default=2000, help="optimisation steps (default 2000)")
    g.add_argument("--batch", type=integer(1), default=16, help="source/target pairs per step (default 16)")
    g.add_argument("--seed", type=integer(0), default=0, help="seed of everything random (default 0)")
    g.add_argument("--device", default="auto",
                   help="auto (cuda if available), cpu, cuda, cuda:N (under torchrun: cpu or cuda, one GPU per rank)")
    g.add_argument("--threads", type=integer(1), default=None,
                   help="torch CPU threads (default: all cores, shared out among the ranks of a node under torchrun)")
    g.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    g.add_argument("--force", action="store_true", help="start over in an existing --out")
    g.add_argument("--save-every", type=integer(1), default=200, help="checkpoint interval in iterations (default 200)")
    g.add_argument("--val-pairs", type=integer(0), default=64, help="validation pairs scored at each checkpoint")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    g = parser.add_argument_group("data")
    g.add_argument("--points", type=integer(16), default=1024, help="N, surface points per sample (default 1024)")
    g.add_argument("--samples", type=integer(1), default=4, help="independent cached samples per mesh (default 4)")
    g.add_argument("--cache", default=None, help="sample cache folder (default $KPD_CACHE or ~/.cache/kpd)")
    g.add_argument("--split-file", type=existing, default=None,
                   help="split file (ShapeNet all.csv, JSON, train/val/test.txt)")
    g.add_argument("--val-fraction", type=number(0, 0.9), default=0.1, help="share of train held out for validation")
    g.add_argument("--processes", type=integer(1), default=2, help="processes for sampling meshes (default 2)")
    g.add_argument("--cage-distance", type=number(positive=True), default=0.4, help="cage stop distance (default 0.4)")
    g.add_argument("--cage-level", type=integer(0, 4), default=1, help="icosphere level of the cage (1: 42 vertices)")
    g.add_argument("--enclose-cage", action="store_true", help="grow the cage until it encloses every point")
    g.add_argument("--outer-surface", action="store_true",
                   help="sample the outer surface only: drop points inside the shape where overlapping or touching "
                        "pieces meet (convex decompositions such as ../shared/data/gso_shoes, CAD parts)")
    g = parser.add_argument_group("recipe (defaults: the authors' code; docs/method.md §11)")
    g.add_argument("--keypoint-source", choices=("learned", "fps"), default="learned",
                   help="fps: farthest-point keypoints of each shape, only the deformer is trained (baseline)")
    g.add_argument("--lr", type=number(positive=True), default=1e-3,
                   help="Adam learning rate of Φ and Γ (default 1e-3)")
    g.add_argument("--wc-lr", type=number(0), default=None, help="learning rate of W_C (code 1e-2; --paper: = --lr)")
    g.add_argument("--alpha-kpt", type=number(0), default=None, help="keypoint regulariser weight (code 2; paper 1)")
    g.add_argument("--inf-reg", choices=("code", "paper"), default=None,
                   help="influence regulariser: code = mean(W_I²), paper = ‖W_I‖_F")
    g.add_argument("--alpha-inf", type=number(0), default=None,
                   help="influence regulariser weight (default 1e6 for code, 1e-6 for paper)")
    g.add_argument("--warmup", type=integer(0), default=None, help="keypoint-only iterations first (code 200; paper 0)")
    g.add_argument("--no-clamp", action="store_true", help="do not clamp keypoints to [-1, 1] (paper)")
    g.add_argument("--paper-m", action="store_true", help="M = floor(C/K) (paper) instead of max(5, floor(C/K))")
    g.add_argument("--m", type=integer(1), default=None, help="M, nearest cage vertices per keypoint (overrides both)")
    g.add_argument("--fps-factor", type=integer(1), default=2, help="J = factor * K farthest points (default 2)")
    g.add_argument("--paper", action="store_true",
                   help="all paper values: alpha-kpt 1, inf-reg paper 1e-6, warmup 0, wc-lr = lr, no clamp, paper M")


def recipe(args: argparse.Namespace):
    """The TrainConfig an argument namespace asks for."""
    from kpd.train.trainer import TrainConfig

    paper = args.paper
    inf_reg = args.inf_reg or ("paper" if paper else "code")
    alpha_inf = args.alpha_inf if args.alpha_inf is not None else (1e-6 if inf_reg == "paper" else 1e6)
    alpha_kpt = args.alpha_kpt if args.alpha_kpt is not None else (PAPER["alpha_kpt"] if paper else 2.0)
    warmup = args.warmup if args.warmup is not None else (PAPER["warmup"] if paper else 200)
    wc_lr = args.wc_lr if args.wc_lr is not None else (args.lr if paper else 1e-2)
    return TrainConfig(
        keypoints=args.keypoints, iterations=args.iterations, batch=args.batch, seed=args.seed, lr=args.lr,
        wc_lr=wc_lr, alpha_kpt=alpha_kpt, alpha_inf=alpha_inf, inf_reg=inf_reg, fps_factor=args.fps_factor,
        warmup=warmup, clamp=not (args.no_clamp or paper), paper_m=args.paper_m or paper, m=args.m,
        keypoint_source=args.keypoint_source, save_every=args.save_every, val_pairs=args.val_pairs)


def check_output(args: argparse.Namespace, out: Path) -> None:
    """The run folder suits --resume / --force (checked by rank 0 alone under torchrun)."""
    if args.resume and not (out / "checkpoint.pt").is_file():
        raise InputError(f"--resume: no checkpoint in {out}")
    if not args.resume and out.is_dir() and any(out.iterdir()) and not args.force:
        raise InputError(f"output {out} exists and is not empty; pass --resume to continue or --force to start over")
    parent = out.parent
    while not parent.exists():  # a run folder's missing parents are made, as training tools do
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"--out {out}: {parent} is a file, not a folder")


# A validation split smaller than this gives no validation score (pairs of one shape score 0); fewer than
# FEW_VAL shapes are flagged.
MIN_VAL, FEW_VAL = 2, 5


def run(args: argparse.Namespace) -> int:
    require_train_extra("torch")
    out = Path(args.out)
    if args.resume and args.force:
        raise InputError("--resume and --force contradict each other; choose one")
    if args.points < args.keypoints:
        raise InputError(f"--points must be at least --keypoints ({args.keypoints}); got {args.points}")
    config = recipe(args)
    config.check()
    import time

    started = time.perf_counter()

    from kpd.train import distributed

    try:
        world = distributed.from_environment(config.batch, args.device)  # None unless started by torchrun
        if world is None:
            from kpd.train.config import resolve_device

            resolve_device(args.device)  # a device this machine lacks is refused before any sampling or folder
            check_run_folder(args, out)
            return _train(args, config, out, None, started)
        distributed.init(world)
        try:
            distributed.only_main(world, lambda: check_run_folder(args, out))
            return _train(args, config, out, world, started)
        finally:
            distributed.shutdown()
    except distributed.Stopped:
        # another rank prints the error. torchrun ends the whole job once one rank has exited: a quiet rank that
        # ended at once could stop the job before that line is out (seen since the program skips the interpreter's
        # teardown), so it waits a little first; torchrun ends it when the reporting rank is done
        time.sleep(_QUIET_RANK_GRACE)
        return 2


def check_run_folder(args: argparse.Namespace, out: Path) -> None:
    """--out suits --resume / --force and is a writable folder apart from the inputs (rank 0 alone under torchrun)."""
    from kpd.io import check_output as check_folder

    check_output(args, out)
    made = []
    parent = out.parent
    while not parent.exists():
        made.append(parent)
        parent = parent.parent
    for missing in reversed(made):
        missing.mkdir()
    try:
        _check_run_folder(args, out, check_folder)
    except BaseException:
        for missing in made:  # nothing left behind by a refused run
            try:
                missing.rmdir()
            except OSError:
                break
        raise


def _check_run_folder(args: argparse.Namespace, out: Path, check_folder) -> None:
    # the run folder is not replaced as a whole (checkpoints go into it as training runs), but it is checked like
    # every output: writable, and neither the data, the split file nor the cache nor a folder holding them
    check_folder(out, option="--out", force=True, kind="folder", inputs=(args.data, args.split_file, args.cache))


def _score(value) -> bool:
    """A validation chamfer was computed (not absent, not NaN)."""
    return value is not None and value == value


def _train(args: argparse.Namespace, config, out: Path, world, started: float) -> int:
    """Sample (once per cache), train and report; under torchrun rank 0 alone prints and writes."""
    import dataclasses
    import time

    import torch

    from kpd.data import SampleSettings, prepare
    from kpd.io import remove_stale_temporaries
    from kpd.train import distributed
    from kpd.train.trainer import train

    main = world is None or world.main
    per_node = 1 if world is None else world.local_size
    torch.set_num_threads(args.threads or max(1, (os.cpu_count() or 1) // per_node))
    settings = SampleSettings(points=args.points, samples=args.samples, cage_level=args.cage_level,
                              cage_distance=args.cage_distance, enclose=args.enclose_cage,
                              outer=args.outer_surface)
    data = distributed.in_turn(world, lambda: prepare(
        args.data, args.category, settings=settings, cache_dir=args.cache, split_file=args.split_file,
        val_fraction=args.val_fraction, seed=args.seed, processes=args.processes,
        progress=not args.quiet and (world is None or world.local_rank == 0)))
    say = print if main else (lambda *a, **k: None)
    for s in data.skipped:
        say(f"skipped {s.path}: {s.reason}", file=sys.stderr)
    counts = ", ".join(f"{k} {len(v)}" for k, v in data.samples.items())
    ranks = "" if world is None else f"; {world.size} ranks ({world.backend}), {config.batch // world.size} pairs each"
    say(f"{data.category.category} ({data.category.layout}): {counts} shapes; {len(data.skipped)} skipped{ranks}")
    val = len(data.samples["val"]) if "val" in data.samples else 0
    if config.val_pairs and val < MIN_VAL:
        say(f"warning: the validation split has {val} shape(s): no validation score (it needs pairs of distinct "
            f"shapes); give more data, a split file with a val list, or a larger --val-fraction", file=sys.stderr)
        config = dataclasses.replace(config, val_pairs=0)
    elif config.val_pairs and val < FEW_VAL:
        say(f"warning: the validation split has only {val} shapes; its chamfer says little", file=sys.stderr)
    command = "kpd " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if "train" in sys.argv[1:] else None
    created = main and not out.exists()
    if main:
        out.mkdir(exist_ok=True)
        if args.resume:
            for path in remove_stale_temporaries(out):
                print(f"removed {path.name}, left by the interrupted run", file=sys.stderr)
    try:
        record = train(data, config, out, device=args.device, resume=args.resume, progress=not args.quiet,
                       command=command, world=world)
    except BaseException:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # a refused or failed start leaves no empty run folder
        raise
    metrics = record["metrics"]
    score = (f"val chamfer {metrics['val_chamfer']:.5f} (undeformed {metrics['val_chamfer_undeformed']:.5f})"
             if _score(metrics.get("val_chamfer")) else "no validation score (the validation split is too small)")
    say(f"done: {record['metrics']['iterations_done']} iterations; {record['train_seconds']:.0f} s in steps, "
        f"{record['run_seconds']:.0f} s training loop, {time.perf_counter() - started:.0f} s in this command; "
        f"{score}; {out}")
    return 0
