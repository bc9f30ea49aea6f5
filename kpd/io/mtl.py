"""MTL, the material libraries of OBJ files: their materials' colours and images, and the statements that name files.

kpd reads of a library what it draws (each material's ``Kd`` colour and its ``map_Kd`` image) and keeps the rest as
text: a library written beside an output is the input's own text with the files its map statements name renamed to
the copies written beside it (:func:`renamed_library`). The files a library or its OBJ names are found as
:mod:`kpd.io.references` allows: inside the OBJ's own folder tree only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from kpd.io.references import Named, locate

__all__ = ["MAP_KEYS", "DEFAULT_KD", "Material", "read_library", "map_file", "map_name", "map_statements",
           "renamed_library", "find_map", "locate_map", "library_files", "library_references", "strip_comment"]

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
    """One ``newmtl`` of a material library: its ``Kd`` colour and its ``map_Kd`` image file (its real path), or why
    that file is not read."""

    name: str
    kd: tuple = DEFAULT_KD
    map_kd: Path | None = None
    map_kd_name: str | None = None
    map_kd_refused: str | None = None


def map_file(statement: bytes) -> bytes:
    """The file name of a map statement's arguments (the last token, after options such as ``-s 1 1 1``)."""
    parts = statement.split()
    return parts[-1] if parts else b""


def map_name(arguments: bytes) -> tuple[str, str]:
    """The file name of a map statement's arguments, and its whole argument text (a name may hold spaces), with
    backslashes as slashes."""
    return (map_file(arguments).decode("utf-8", "replace").replace("\\", "/"),
            arguments.decode("utf-8", "replace").replace("\\", "/"))


def read_library(p: Path, mtl: Path, data: bytes | None = None, root: Path | None = None) -> dict[str, Material]:
    """The materials of one ``.mtl`` file (its bytes ``data``, read here when None), by name; their maps are found
    inside ``root``, the OBJ's folder (the library's own folder when None)."""
    materials: dict[str, Material] = {}
    current = None
    for raw in (mtl.read_bytes() if data is None else data).split(b"\n"):
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
            name, whole = map_name(strip_comment(rest).strip())
            current.map_kd_name = name
            current.map_kd, current.map_kd_refused = locate_map(mtl.parent if root is None else root, mtl.parent,
                                                                name, whole)
    return materials


def locate_map(root: Path, folder: Path, name: str, whole: str) -> Named:
    """The file a map statement names: its last token, else its whole argument text (a name with spaces), else the
    token's base name (a map named by a path of another machine), in ``folder``; the first candidate inside ``root``
    (:func:`kpd.io.references.locate`), else why the first refused one is not read."""
    refused = None
    for candidate in (name, whole, name.rsplit("/", 1)[-1]):
        found = locate(root, folder, candidate)
        if found.path is not None:
            return found
        refused = refused or found.refused
    return Named(None, refused)


def find_map(folder: Path, name: str, whole: str) -> Path | None:
    """:func:`locate_map` inside ``folder``: the file's real path, or None."""
    return locate_map(folder, folder, name, whole).path


def library_references(p: Path, names: str, root: Path | None = None) -> list[tuple[str, Named]]:
    """The files of one ``mtllib`` statement of the OBJ ``p`` (several names may follow it; a name may hold spaces),
    judged by :func:`kpd.io.references.locate` inside ``root`` (the OBJ's folder when None)."""
    root = p.parent if root is None else root
    whole = locate(root, p.parent, names)
    if whole.path is not None or len(names.split()) < 2:
        return [(names, whole)]
    return [(name, locate(root, p.parent, name)) for name in names.split()]


def library_files(p: Path, names: str, root: Path | None = None) -> list[tuple[str, Path | None]]:
    """:func:`library_references` as (name, real path or None)."""
    return [(name, found.path) for name, found in library_references(p, names, root)]


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
    """A library's bytes with the file names of its map statements replaced by ``renames`` ({old: new}); a statement
    whose name maps to None (a file kpd did not read) is kept as a comment, so that the copy names no file beside it."""
    lines = data.split(b"\n")
    for i, arguments in map_statements(data):
        name = map_file(arguments)
        key = name.decode("utf-8", "replace").replace("\\", "/")
        if key not in renames:
            continue
        new = renames[key]
        line = lines[i]
        if new is None:
            lines[i] = b"# " + line.rstrip(b"\r") + b" (not read by kpd)" + (b"\r" if line.endswith(b"\r") else b"")
            continue
        cut = line.rfind(name)
        lines[i] = line[:cut] + new.encode("utf-8") + line[cut + len(name):]
    return b"\n".join(lines)
