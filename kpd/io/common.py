"""What every format module shares: the format lists, checked input and output paths, completeness helpers and
whitespace-separated number tables."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from kpd.errors import InputError
from kpd.io.atomic import incomplete

__all__ = ["MESH_FORMATS", "POINT_FORMATS", "KEYPOINT_FORMATS", "input_path", "output_path", "incomplete",
           "verify_companion", "check_header_counts", "count_lines", "describe", "read_table", "memory_free"]

MESH_FORMATS = (".obj", ".ply", ".off", ".stl", ".gltf", ".glb")
POINT_FORMATS = (".ply", ".pcd", ".xyz", ".pts", ".npy", ".npz")
KEYPOINT_FORMATS = (".json", ".txt")


def input_path(path: str | os.PathLike, formats: tuple, kind: str) -> tuple[Path, str]:
    try:
        p = Path(path)
    except TypeError as exc:
        raise InputError(f"{kind} path must be a string or path; got {type(path).__name__}") from exc
    ext = p.suffix.lower()
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a {kind} file")
    if ext not in formats:
        raise InputError(
            f"{p}: unknown {kind} format {ext or '(no extension)'!r}; expected one of {' '.join(formats)}"
        )
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if not p.is_file():
        raise InputError(f"{p}: not a regular file")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: the file is empty (0 bytes)")
    return p, ext


def output_path(path: str | os.PathLike, formats: tuple, kind: str) -> Path:
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in formats:
        raise InputError(f"{p}: unknown {kind} format {ext or '(no extension)'!r}; expected one of {' '.join(formats)}")
    return p


def verify_companion(p: Path, tmp: Path) -> None:
    """Raise :class:`~kpd.errors.WriteError` for ``p`` unless its written companion ``tmp`` holds something (and, for a
    PNG, ends with its end chunk)."""
    if tmp.stat().st_size == 0:
        raise incomplete(p, "empty")
    if tmp.suffix.lower() == ".png":
        from kpd.io.images import check_png

        check_png(p, tmp)


def memory_free() -> int:
    """Bytes of memory a process could still take now (Linux's MemAvailable, else the free pages): the bound of what
    one size a file declares may take before it is read."""
    try:
        with open("/proc/meminfo", "rb") as fh:
            for line in fh:
                if line.startswith(b"MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return 1 << 62


def check_header_counts(tmp: Path, *pairs) -> None:
    with open(tmp, "rb") as fh:
        head = fh.read(1 << 14)
    for pattern, expected in zip(pairs[::2], pairs[1::2]):
        m = re.search(pattern, head)
        if m is None or int(m.group(1)) != expected:
            raise InputError(f"the header declares {m.group(1) if m else 'no'} of {expected} elements")


def count_lines(p: Path, start: int) -> int:
    """Number of lines from byte ``start`` on (a last line without a newline counts)."""
    count, last = 0, b"\n"
    with open(p, "rb") as fh:
        fh.seek(start)
        while chunk := fh.read(1 << 22):
            count += chunk.count(b"\n")
            last = chunk[-1:]
    return count + (last != b"\n")


def describe(a: Any) -> str:
    return f"{a.dtype} array of shape {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__


def read_table(p: Path, *, count_header: bool = False) -> np.ndarray:
    """Whitespace-separated numbers, one row per line; '#' comments and blank lines are skipped."""
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not a text file ({exc.reason} at byte {exc.start})") from exc
    lines = [(i + 1, s) for i, s in enumerate(text.splitlines()) if s.strip() and not s.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{p}: no rows (empty geometry)")
    if count_header and len(lines[0][1].split()) == 1 and len(lines) > 1:
        declared = lines[0][1].strip()
        if not declared.isdigit() or int(declared) != len(lines) - 1:
            raise InputError(f"{p}: first line {declared!r} is not the row count {len(lines) - 1}")
        lines = lines[1:]
    rows = [s.split() for _, s in lines]
    ncol = len(rows[0])
    for (number, _), row in zip(lines, rows):
        if len(row) != ncol:
            raise InputError(f"{p}: line {number} has {len(row)} columns; line {lines[0][0]} has {ncol}")
    try:
        table = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"{p}: not a table of numbers ({exc})") from exc
    return table.reshape(len(lines), ncol)
