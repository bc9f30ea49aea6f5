"""MTL, the material libraries of OBJ files: their materials' colours and images, and the statements that name files.

kpd reads of a library what it draws (each material's ``Kd`` colour and its ``map_Kd`` image) and keeps the rest as
text: a library written beside an output is the input's own text with the files its map statements name renamed to
the copies written beside it (:func:`renamed_library`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

__all__ = ["MAP_KEYS", "DEFAULT_KD", "Material", "read_library", "map_file", "map_statements", "renamed_library",
           "find_map", "library_files", "strip_comment"]

log = logging.getLogger("kpd.io.obj")

# MTL statements that name a file (the file name is the last token, after any options)
MAP_KEYS = (b"map_kd", b"map_ka", b"map_ks", b"map_ns", b"map_d", b"map_bump", b"bump", b"disp", b"decal",
            b"refl", b"norm", b"map_pr", b"map_pm", b"map_ps", b"map_ke", b"map_rma", b"map_orm")
DEFAULT_KD = (0.8, 0.8, 0.8)  # faces without a material (and materials without Kd), as the drawing code's grey


def strip_comment(s: bytes) -> bytes:
    """``s`` up to its first ``#``."""
    i = s.find(b"#")
    return s if i < 0 else s[:i]


@dataclass
class Material:
    """One ``newmtl`` of a material library: its ``Kd`` colour and its ``map_Kd`` image file (resolved)."""

    name: str
    kd: tuple = DEFAULT_KD
    map_kd: Path | None = None
    map_kd_name: str | None = None


def map_file(statement: bytes) -> bytes:
    """The file name of a map statement's arguments (the last token, after options such as ``-s 1 1 1``)."""
    parts = statement.split()
    return parts[-1] if parts else b""


def read_library(p: Path, mtl: Path) -> dict[str, Material]:
    """The materials of one ``.mtl`` file, by name."""
    materials: dict[str, Material] = {}
    current = None
    for raw in mtl.read_bytes().split(b"\n"):
        s = strip_comment(raw).strip()
        if not s:
            continue
        parts = s.split(None, 1)
        key, rest = parts[0].lower(), (parts[1].strip() if len(parts) > 1 else b"")
        if key == b"newmtl":
            current = Material(rest.decode("utf-8", "replace"))
            materials[current.name] = current
        elif current is None:
            continue
        elif key == b"kd":
            try:
                values = [float(x) for x in rest.split()[:3]]
                if len(values) == 1:
                    values *= 3
                if len(values) == 3:
                    current.kd = tuple(min(max(x, 0.0), 1.0) for x in values)
            except ValueError:
                log.warning("%s: material %s has an unreadable Kd %r; drawn grey", p, current.name,
                            rest.decode("utf-8", "replace"))
        elif key == b"map_kd":
            name = map_file(rest).decode("utf-8", "replace").replace("\\", "/")
            current.map_kd_name = name
            current.map_kd = find_map(mtl.parent, name, rest.decode("utf-8", "replace").replace("\\", "/"))
    return materials


def find_map(folder: Path, name: str, whole: str) -> Path | None:
    """The file a map statement names: its last token, else its whole argument text (a name with spaces), else the
    token's base name, in ``folder``."""
    for candidate in (folder / name, folder / whole, folder / Path(name).name):
        if candidate.is_file():
            return candidate
    return None


def library_files(p: Path, names: str) -> list[tuple[str, Path | None]]:
    """The files of one ``mtllib`` statement (several names may follow it; a name may hold spaces)."""
    whole = p.parent / names
    if whole.is_file():
        return [(names, whole)]
    out = []
    for name in names.split():
        f = p.parent / name
        out.append((name, f if f.is_file() else None))
    return out


def map_statements(data: bytes) -> list[tuple[int, bytes]]:
    """(line index, arguments) of each map statement of an ``.mtl``."""
    out = []
    for i, raw in enumerate(data.split(b"\n")):
        parts = raw.strip().split(None, 1)
        key, rest = (parts[0], parts[1]) if len(parts) == 2 else (b"", b"")
        if key.lower() in MAP_KEYS and rest.strip():
            out.append((i, strip_comment(rest).strip()))
    return out


def renamed_library(data: bytes, renames: dict) -> bytes:
    """A library's bytes with the file names of its map statements replaced by ``renames`` ({old: new})."""
    lines = data.split(b"\n")
    for i, arguments in map_statements(data):
        name = map_file(arguments)
        new = renames.get(name.decode("utf-8", "replace").replace("\\", "/"))
        if new is None:
            continue
        line = lines[i]
        cut = line.rfind(name)
        lines[i] = line[:cut] + new.encode("utf-8") + line[cut + len(name):]
    return b"\n".join(lines)
