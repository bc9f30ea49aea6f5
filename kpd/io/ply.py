"""PLY: the completeness check Open3D leaves out (it returns a half-read geometry for a truncated file)."""

from __future__ import annotations

import re
from pathlib import Path

from kpd.errors import InputError
from kpd.io.common import count_lines

__all__ = ["check_complete"]

_PLY_TYPE_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}



def check_complete(p: Path) -> None:
    """Raise if a PLY file holds less data than its header declares (Open3D returns a half-read cloud for that)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 20)
    if not re.match(rb"ply[ \t]*\r?\n", head):
        raise InputError(f"{p}: not a PLY file (it does not start with the line 'ply')")
    end = re.search(rb"^end_header[ \t]*\r?\n", head, re.M)
    if not end:
        raise InputError(f"{p}: not a PLY file (no 'end_header' line in the first MiB)")
    lines = head[: end.end()].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []
    for s in lines[1:]:
        tokens = s.split()
        if not tokens:
            continue
        if tokens[0] == "format" and len(tokens) >= 2:
            fmt = tokens[1]
        elif tokens[0] == "element" and len(tokens) == 3 and tokens[2].isdigit():
            elements.append([tokens[1], int(tokens[2]), 0])
        elif tokens[0] == "property" and elements:
            if len(tokens) == 5 and tokens[1] == "list":
                sizes = (_PLY_TYPE_SIZES.get(tokens[2]), _PLY_TYPE_SIZES.get(tokens[3]))
                if None in sizes:
                    return
                items = 3 if tokens[4] in ("vertex_indices", "vertex_index") else 0
                elements[-1][2] += sizes[0] + items * sizes[1]
            elif len(tokens) == 3 and tokens[1] in _PLY_TYPE_SIZES:
                elements[-1][2] += _PLY_TYPE_SIZES[tokens[1]]
            else:
                return
    declared = " and ".join(f"{count} {name!r}" for name, count, _ in elements) + " elements"
    data_size = p.stat().st_size - end.end()
    if fmt in ("binary_little_endian", "binary_big_endian"):
        need = sum(count * size for _, count, size in elements)
        if data_size < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {declared} (at least {need} bytes of data) "
                f"but {data_size} bytes follow"
            )
    elif fmt == "ascii":
        rows = count_lines(p, end.end())
        need = sum(count for _, count, _ in elements)
        if rows < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {declared} ({need} rows) but {rows} rows follow"
            )
