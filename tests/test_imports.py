"""The runtime never imports torch: a fresh interpreter imports the torch-free modules and checks sys.modules."""

import importlib.util
import subprocess
import sys

import pytest

TORCH_FREE = ["kpd", "kpd.errors", "kpd.geometry", "kpd.io", "kpd.cage", "kpd.mvc", "kpd.rig", "kpd.cli",
              "kpd.prior", "kpd.bundle", "kpd.runtime", "kpd.scan", "kpd.metrics", "kpd.viewer"]


def existing(names):
    return [n for n in names if importlib.util.find_spec(n) is not None]


def test_runtime_modules_do_not_import_torch():
    modules = existing(TORCH_FREE)
    assert "kpd.geometry" in modules
    code = f"import sys\nfor m in {modules!r}: __import__(m)\nprint('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_cli_help_does_not_import_torch():
    code = "import sys\nfrom kpd.cli import build_parser\nbuild_parser()\nprint('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


@pytest.mark.parametrize("argv", [["--help"]])
def test_cli_help_exits_zero(argv):
    out = subprocess.run([sys.executable, "-m", "kpd.cli", *argv], capture_output=True, text=True)
    assert out.returncode == 0 and "usage: kpd" in out.stdout
