"""The runtime never imports torch: fresh interpreters import the torch-free modules (and run a command) and check
``sys.modules``; every subcommand the CLI lists exists."""

import subprocess
import sys

import pytest

from kpd.commands import COMMANDS

TORCH_FREE = [
    "kpd", "kpd.errors", "kpd.geometry", "kpd.io", "kpd.cage", "kpd.mvc", "kpd.rig", "kpd.cli", "kpd.prior",
    "kpd.bundle", "kpd.runtime", "kpd.onnx_contract", "kpd.scan", "kpd.metrics", "kpd.annotations", "kpd.data",
    "kpd.viewer", "kpd.viewer.session", "kpd.viewer.render", "kpd.viewer.app",
    *(module for name, module in COMMANDS.items() if name not in ("train", "export")),
]


def torch_loaded_after(code: str) -> bool:
    out = subprocess.run([sys.executable, "-c", f"import sys\n{code}\nprint('torch' in sys.modules)"],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1] == "True"


def test_runtime_modules_do_not_import_torch():
    assert not torch_loaded_after(f"for m in {TORCH_FREE!r}: __import__(m)")


def test_torch_check_sees_torch():  # the check above can fail: importing the trainer does load torch
    assert torch_loaded_after("import kpd.train.nets")


def test_a_command_runs_without_torch(tmp_path):
    from kpd.procedural import procedural_chair
    from kpd.io import write_mesh

    mesh = tmp_path / "chair.ply"
    write_mesh(mesh, procedural_chair())
    out = tmp_path / "deformed.ply"
    code = (f"from kpd.cli import main\nassert main(['deform', 'chair', {str(mesh)!r}, '--move', '0:0,0,1', '--prior', "
            f"'--out', {str(out)!r}]) == 0")
    assert not torch_loaded_after(code)
    assert out.exists()


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_listed_command_exists(name):
    from kpd.cli import build_parser

    parser = build_parser()
    assert parser.parse_args([name, *_minimal_args(name)]).command == name


def _minimal_args(name: str) -> list[str]:
    """Arguments that satisfy each command's parser (nothing runs)."""
    return {
        "demo": [], "train": [".", "--out", "runs/x"], "export": ["run", "--out", "x.kpd"], "keypoints": ["chair", "s.ply"],
        "deform": ["chair", "s.ply", "--out", "o.ply"], "align": ["chair", "a.ply", "b.ply", "--out", "o.ply"],
        "sample": ["chair", "s.ply", "--out", "d"], "scan": ["s.ply", "--out", "a.ply", "--report", "r.json"], "view": ["chair", "s.ply"],
        "render": ["chair", "s.ply", "--out", "v.png"], "eval": ["alignment", ".", "--out", "a.json"], "bench": ["chair"],
    }[name]


def test_cli_help_does_not_import_torch():
    assert not torch_loaded_after("from kpd.cli import build_parser\nbuild_parser()")


def test_cli_help_exits_zero():
    out = subprocess.run([sys.executable, "-m", "kpd.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "usage: kpd" in out.stdout
    assert all(name in out.stdout for name in COMMANDS)
