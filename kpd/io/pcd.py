"""PCD: the completeness check Open3D leaves out (it pads a truncated file with zeros)."""

from __future__ import annotations

import re
from pathlib import Path

from kpd.errors import InputError
from kpd.io.common import count_lines

__all__ = ["check_complete"]


def check_complete(p: Path) -> None:
    """Raise if a PCD file holds fewer points than its header declares (Open3D pads such files with zeros)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    end = re.search(rb"^DATA[ \t]+(\w+)[ \t]*\r?\n", head, re.M)
    if not end:
        return
    header = {}
    for s in head[: end.start()].decode("ascii", errors="replace").splitlines():
        tokens = s.split()
        if tokens and not tokens[0].startswith("#"):
            header[tokens[0].upper()] = tokens[1:]
    try:
        n = int(header["POINTS"][0])
        sizes = [int(x) for x in header["SIZE"]]
        counts = [int(x) for x in header.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError):
        return
    kind = end.group(1).decode()
    if kind == "binary":
        need = n * sum(s * c for s, c in zip(sizes, counts))
        have = p.stat().st_size - end.end()
        if have < need:
            raise InputError(
                f"{p}: the file is truncated: its header declares {n} points ({need} bytes) but {have} bytes follow"
            )
    elif kind == "ascii":
        rows = count_lines(p, end.end())
        if rows < n:
            raise InputError(f"{p}: the file is truncated: its header declares {n} points but {rows} rows follow")
