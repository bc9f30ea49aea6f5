"""OFF: the completeness check Open3D leaves out (it keeps the vertices it got from a truncated file)."""

from __future__ import annotations

import re
from pathlib import Path

from kpd.errors import InputError
from kpd.io.common import count_lines

__all__ = ["check_complete"]


def check_complete(p: Path) -> None:
    """Raise if a text OFF file has fewer rows than its header declares (Open3D keeps the vertices it got)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    header = re.match(rb"[ \t]*[A-Z]*OFF[ \t]*\r?\n(?:[ \t]*(?:#[^\n]*)?\n)*[ \t]*(\d+)[ \t]+(\d+)[^\n]*\n", head)
    if not header:
        return  # binary OFF, counts on the first line, or not OFF at all: Open3D decides
    n_vertices, n_faces = int(header.group(1)), int(header.group(2))
    rows = count_lines(p, header.end())
    if rows < n_vertices + n_faces:
        raise InputError(
            f"{p}: the file is truncated: its header declares {n_vertices} vertices and {n_faces} faces "
            f"({n_vertices + n_faces} rows) but {rows} rows follow"
        )
