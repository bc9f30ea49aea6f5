"""PCD: the checks Open3D leaves out: completeness (it pads a truncated file with zeros), the normal's three fields
(a file naming some of them ends the process in Open3D's reader), the DATA line and the number of points (without
them Open3D's reader allocates by a number it never set)."""

from __future__ import annotations

import re
from pathlib import Path

from kpd.errors import InputError
from kpd.io.common import count_lines

__all__ = ["check_complete"]

_NORMALS = ("normal_x", "normal_y", "normal_z")


def check_complete(p: Path) -> None:
    """Raise if a PCD file holds fewer points than its header declares (Open3D pads such files with zeros), if its
    ``FIELDS`` name some but not all of ``normal_x normal_y normal_z`` (Open3D's reader then reads the missing ones
    from nowhere: a segmentation fault), or if its header lacks the ``DATA`` line or the number of points (``POINTS``,
    or ``WIDTH`` and ``HEIGHT``), or gives ``HEIGHT`` before ``WIDTH``: Open3D's reader then sizes the cloud by a
    number it never set (garbage points, or an allocation of any size)."""
    with open(p, "rb") as fh:
        head = fh.read(1 << 16)
    end = re.search(rb"^DATA[ \t]+(\w+)[ \t]*\r?\n", head, re.M)
    if not end:
        raise InputError(f"{p}: not a PCD file: no DATA line in its first 64 KiB")
    header, order = {}, []
    for line in head[: end.start()].split(b"\n"):  # lines and words as Open3D splits them, not as str does
        tokens = [t.decode("ascii", errors="replace") for t in re.split(rb"[ \t\r]+", line.strip(b" \t\r")) if t]
        if tokens and not tokens[0].startswith("#"):
            header[tokens[0].upper()] = tokens[1:]
            order.append(tokens[0].upper())
    if "HEIGHT" in order and ("WIDTH" not in order or order.index("HEIGHT") < order.index("WIDTH")):
        raise InputError(f"{p}: its HEIGHT line comes before any WIDTH line; a PCD header gives WIDTH, then HEIGHT")
    normals = [name for name in _NORMALS if name in header.get("FIELDS", [])]
    if normals and len(normals) < 3:
        missing = " ".join(name for name in _NORMALS if name not in normals)
        raise InputError(f"{p}: its FIELDS name {' '.join(normals)} without {missing}; a normal takes all three")
    if "POINTS" not in header and not {"WIDTH", "HEIGHT"} <= set(header):
        raise InputError(f"{p}: its header declares no POINTS (nor WIDTH and HEIGHT): how many points is not said")
    try:
        n = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        sizes = [int(x) for x in header["SIZE"]]
        counts = [int(x) for x in header.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError):  # Open3D's reader reads such numbers as garbage (std::bad_alloc)
        raise InputError(f"{p}: its header's POINTS (or WIDTH and HEIGHT), SIZE and COUNT must be whole numbers; "
                         f"got {' '.join(header.get('POINTS', []))[:40]!r}, {' '.join(header.get('SIZE', []))[:40]!r} "
                         f"and {' '.join(header.get('COUNT', []))[:40]!r}") from None
    if n < 0 or any(size not in (1, 2, 4, 8) for size in sizes) or any(not 0 <= c <= 1 << 16 for c in counts):
        raise InputError(f"{p}: its header declares {n} points with fields of SIZE {' '.join(map(str, sizes))[:60]} "
                         f"and COUNT {' '.join(map(str, counts))[:60]}; a field is 1, 2, 4 or 8 bytes")
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
