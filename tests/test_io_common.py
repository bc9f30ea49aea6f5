"""kpd.io.common: input and output paths checked at the door; number tables read with clear refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.io.common import MESH_FORMATS, count_lines, input_path, output_path, read_table


def test_input_path_refusals(tmp_path):
    (tmp_path / "folder.obj").mkdir()
    with pytest.raises(InputError, match="is a folder, not a mesh file"):
        input_path(tmp_path / "folder.obj", MESH_FORMATS, "mesh")
    with pytest.raises(InputError, match=r"unknown mesh format '\.abc'"):
        input_path(tmp_path / "x.abc", MESH_FORMATS, "mesh")
    with pytest.raises(InputError, match="no such file"):
        input_path(tmp_path / "x.obj", MESH_FORMATS, "mesh")
    (tmp_path / "e.obj").write_bytes(b"")
    with pytest.raises(InputError, match=r"the file is empty \(0 bytes\)"):
        input_path(tmp_path / "e.obj", MESH_FORMATS, "mesh")
    (tmp_path / "m.OBJ").write_text("v 0 0 0\n")
    assert input_path(tmp_path / "m.OBJ", MESH_FORMATS, "mesh") == (tmp_path / "m.OBJ", ".obj")
    with pytest.raises(InputError, match="unknown point format"):
        output_path(tmp_path / "p.abc", (".ply",), "point")


def test_read_table_and_count_lines(tmp_path):
    path = tmp_path / "t.pts"
    path.write_text("3\n# comment\n0 0 0\n\n1 2 3\n4 5 6")
    np.testing.assert_array_equal(read_table(path, count_header=True), [[0, 0, 0], [1, 2, 3], [4, 5, 6]])
    assert count_lines(path, 0) == 6  # the last line has no newline and still counts
    path.write_text("1 2 3\n4 5\n")
    with pytest.raises(InputError, match="line 2 has 2 columns; line 1 has 3"):
        read_table(path)
    path.write_text("1 2 x\n")
    with pytest.raises(InputError, match="not a table of numbers"):
        read_table(path)
    path.write_text("5\n1 2 3\n")
    with pytest.raises(InputError, match="first line '5' is not the row count 1"):
        read_table(path, count_header=True)
    path.write_bytes(b"\xff\xfe1 2 3\n")
    with pytest.raises(InputError, match="not a text file"):
        read_table(path)


def test_images_do_not_import_the_common_module_that_checks_them():
    """kpd.io.common checks written PNGs through kpd.io.images, so images must not import common (no circle)."""
    import ast

    import kpd.io.images

    tree = ast.parse(Path(kpd.io.images.__file__).read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert "kpd.io.common" not in imported and "kpd.io.atomic" in imported
