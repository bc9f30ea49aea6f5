"""kpd.commands._shared: what several commands share lives there, and no command imports another."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import kpd.commands
from kpd.commands import COMMANDS
from kpd.commands._shared import parse_move, parse_moves
from kpd.errors import InputError

ROOT = Path(kpd.commands.__file__).resolve().parents[2]


def _imported(path: Path) -> set[str]:
    """Every module an import statement of ``path`` names, lazy imports inside functions included."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def test_no_command_imports_another():
    commands = set(COMMANDS.values())
    for name, module in COMMANDS.items():
        path = Path(kpd.commands.__file__).parent / f"{module.rsplit('.', 1)[1]}.py"
        others = sorted(_imported(path) & (commands - {module}))
        assert not others, f"kpd {name} imports {others}; shared helpers belong in kpd.commands._shared"
    assert not _imported(Path(kpd.commands.__file__).parent / "_shared.py") & commands


def test_benchmarks_import_only_the_library():
    for path in sorted((ROOT / "benchmarks").glob("bench_*.py")):
        named = sorted(n for n in _imported(path) if n.startswith(("kpd.commands", "kpd.cli")))
        assert not named, f"{path.name} imports {named}"


def test_moves_add_up_per_keypoint():
    moves = parse_moves(["3:0,0.5,0", " 3 : 1,0,0 ", "0:-1e-3,2,3"])
    assert sorted(moves) == [0, 3]
    np.testing.assert_allclose(moves[3], [1, 0.5, 0])
    np.testing.assert_allclose(moves[0], [-1e-3, 2, 3])
    assert parse_moves([]) == {}


@pytest.mark.parametrize("text, match", [("3:0,0", "must look like"), ("a:0,0,0", "must look like"),
                                         ("1:x,0,0", "must be numbers"), ("1:nan,0,0", "must be finite")])
def test_bad_moves_name_the_form(text, match):
    with pytest.raises(InputError, match=match):
        parse_move(text)


def test_a_shape_that_fails_at_once_is_reported_before_the_model_loads(tmp_path):
    """A missing file or a header that declares what it cannot hold ends the command without the model's load (the
    issue's 243-byte glTF: under a second, not after onnxruntime's start); a good shape is read beside the load."""
    from kpd.commands._shared import model_beside_read
    from kpd.errors import InputError
    from kpd.io import write_mesh
    from kpd.procedural import procedural_chair

    loads = []
    with pytest.raises(InputError, match="no such file"):
        model_beside_read(lambda: loads.append(1), tmp_path / "missing.ply")
    assert loads == []
    write_mesh(tmp_path / "chair.ply", procedural_chair())
    model, mesh = model_beside_read(lambda: loads.append(1) or "model", tmp_path / "chair.ply")
    assert loads == [1] and model == "model" and len(mesh.vertices) > 0
