"""The runtime never imports torch: fresh interpreters import the torch-free modules (and run a command) and check
``sys.modules``; the core never imports the viewer or the commands; every subcommand the CLI lists exists."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from kpd.commands import COMMANDS

TORCH_FREE = [
    "kpd", "kpd.errors", "kpd.geometry", "kpd.io", "kpd.cage", "kpd.mvc", "kpd.rig", "kpd.cli", "kpd.prior",
    "kpd.bundle", "kpd.runtime", "kpd.onnx_contract", "kpd.scan", "kpd.metrics", "kpd.annotations", "kpd.data",
    "kpd.collection", "kpd.frame", "kpd.morph", "kpd.mesh", "kpd.grouping", "kpd.triangles", "kpd.procedural",
    "kpd.benchmark", "kpd.augment", "kpd.amplify", "kpd.variants", "kpd.viewer", "kpd.viewer.session",
    "kpd.viewer.render", "kpd.viewer.app", "kpd.viewer.figures", "kpd.viewer.browser",
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


ROOT = Path(__file__).resolve().parents[1]
UPPER = ("kpd.viewer", "kpd.commands", "kpd.cli", "kpd.export")  # what the core may not import, not even lazily


def imported_names(path: Path, package: str) -> set[str]:
    """Every module an import statement in ``path`` names (function-level imports included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against the module's package
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def upward_imports(root: Path) -> list[str]:
    found = []
    for path in sorted((root / "kpd").rglob("*.py")):
        relative = path.relative_to(root).with_suffix("")
        module = ".".join(relative.parts).removesuffix(".__init__")
        if module.startswith(("kpd.commands", "kpd.cli")):
            continue
        package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
        for name in imported_names(path, package):
            if name.startswith(UPPER):
                found.append(f"{module} imports {name}")
    return found


def test_the_core_never_imports_the_viewer_or_the_commands():
    assert upward_imports(ROOT) == []


def test_the_upward_import_check_can_fail(tmp_path):
    (tmp_path / "kpd" / "deep").mkdir(parents=True)
    (tmp_path / "kpd" / "scan.py").write_text("def f():\n    from kpd.viewer.pictures import point_panels\n")
    (tmp_path / "kpd" / "deep" / "x.py").write_text("from ..commands import view\nimport kpd.cli\n")
    (tmp_path / "kpd" / "commands.py").write_text("import kpd.viewer\n")  # the commands may
    assert sorted(upward_imports(tmp_path)) == ["kpd.deep.x imports kpd.cli", "kpd.deep.x imports kpd.commands",
                                                "kpd.deep.x imports kpd.commands.view",
                                                "kpd.scan imports kpd.viewer.pictures",
                                                "kpd.scan imports kpd.viewer.pictures.point_panels"]


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
        "demo": [], "train": [".", "--out", "runs/x"], "export": ["run", "--out", "x.kpd"],
        "keypoints": ["chair", "s.ply"],
        "deform": ["chair", "s.ply", "--out", "o.ply"], "align": ["chair", "a.ply", "b.ply", "--out", "o.ply"],
        "sample": ["chair", "s.ply", "--out", "d"], "scan": ["s.ply", "--out", "a.ply", "--report", "r.json"],
        "view": ["chair", "s.ply"],
        "render": ["chair", "s.ply", "--out", "v.png"], "eval": ["alignment", ".", "--out", "a.json"],
        "bench": ["chair"],
        "rig": ["chair", "s.ply", "--out", "s.glb"], "amplify": ["chair", ".", "--out", "d"],
    }[name]


def test_cli_help_does_not_import_torch():
    assert not torch_loaded_after("from kpd.cli import build_parser\nbuild_parser()")



def test_the_cli_parser_and_the_mesh_readers_leave_scipy_spatial_unloaded():
    """Importing scipy.spatial takes about 0.3 s: the parser (every command's start, and --help) and the readers
    (which commands run beside the model's load) do without it; what needs it imports it."""
    code = ("import sys\nfrom kpd.cli import build_parser\nbuild_parser()\nimport kpd.io, kpd.geometry, kpd.cage\n"
            "print('scipy.spatial' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False"
    code = ("import sys, numpy as np\nfrom kpd.geometry import chamfer\n"
            "a = np.random.default_rng(0).normal(size=(3000, 3))\nchamfer(a, a + 1e-3)\n"
            "print('scipy.spatial' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "True"

def test_cli_help_exits_zero():
    out = subprocess.run([sys.executable, "-m", "kpd.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "usage: kpd" in out.stdout
    assert all(name in out.stdout for name in COMMANDS)


@pytest.mark.parametrize("module, name", [("kpd.scan", "alignment_picture"), ("kpd.collection", "contact_sheet"),
                                          ("kpd.train.evaluate", "alignment_gallery")])
def test_moved_drawing_functions_say_where_they_went(module, name):
    import importlib

    with pytest.raises(AttributeError, match=f"moved to kpd.viewer.figures.{name}"):
        getattr(importlib.import_module(module), name)
    from kpd.viewer import figures

    assert callable(getattr(figures, name))
