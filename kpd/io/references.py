"""Files named by a file: an OBJ's material libraries and the maps they name, a glTF's external images and buffers.

A file may come from someone else, and the names inside it are theirs to choose. kpd reads a named file only when

- its name is relative (no absolute path, no drive, no control character; for a glTF URI, no scheme but ``data:``),
- it lies inside the input's own folder tree once every symlink is followed (``os.path.realpath``, then
  :meth:`pathlib.Path.is_relative_to` the folder's real path): a ``..`` or a symlink that leaves the folder is not
  followed, and nothing under ``/proc``, ``/dev`` or ``/sys`` is read wherever the input lies (a caller may name a
  wider tree it trusts: ``read_mesh(..., files_root=)``; ShapeNetCore's layout, maps in the ``images`` folder
  beside a ``models`` folder, is accepted as it is),
- it is a regular file (not a device, a FIFO or a socket) no larger than the bound of its kind, checked on the open
  file before it is read,
- and it is what it claims to be: an image that decodes, a material library that is text.

Anything else is not read, and so never copied beside an output: the reader logs one warning naming the file and the
reason, and goes on without it (a glTF buffer, which holds the geometry, is an error instead). Readers keep the bytes
they accepted, and writers copy those bytes only, never the path again.
"""

from __future__ import annotations

import logging
import os
import stat
import urllib.parse
from pathlib import Path
from typing import NamedTuple

__all__ = ["MTL_BYTES", "IMAGE_BYTES", "Named", "locate", "locate_uri", "read_named", "is_text", "warn_refused"]

log = logging.getLogger("kpd.io")

MTL_BYTES = 16 << 20  # a material library is a few kilobytes of text; this leaves room for thousands of materials
IMAGE_BYTES = 256 << 20  # a map file (compressed): a 16k x 16k texture's PNG fits
_SYSTEM = (Path("/proc"), Path("/dev"), Path("/sys"))
_CONTROL = bytes(b for b in range(32) if b not in b"\t\n\r\x0b\x0c\x1b")
_NOT_CONTROL = bytes(b for b in range(256) if b not in _CONTROL)


class Named(NamedTuple):
    """Where a name in a file leads: ``path``, the real path of a regular file inside the input's folder; or
    ``refused``, why it is not read; both None when no such file exists."""

    path: Path | None
    refused: str | None = None


def locate(root: Path, folder: Path, name: str, *, dataset_layouts: bool = True) -> Named:
    """The file ``name`` (relative to ``folder``) names, judged against the input's folder ``root`` (see the module
    notes). Reads nothing and logs nothing.

    ``dataset_layouts``: also accept ShapeNetCore's layout, a ``models`` folder whose maps lie in the ``images``
    folder beside it (``<model>/models/model_normalized.obj`` naming ``../images/texture0.jpg``): that sibling
    folder only, never the rest of the parent."""
    if not name.strip():
        return Named(None)
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return Named(None, "its name holds a control character")
    if name.startswith(("/", "\\")) or (len(name) > 1 and name[1] == ":" and name[0].isalpha()):
        return Named(None, "an absolute path")
    try:
        real = Path(os.path.realpath(folder / name))
        top = Path(os.path.realpath(root))
    except (OSError, ValueError) as exc:
        return Named(None, f"its path cannot be resolved ({exc})")
    if any(real == s or real.is_relative_to(s) for s in _SYSTEM):
        return Named(None, "a system file")
    trees = [top]
    if dataset_layouts and top.name == "models":
        trees.append(top.parent / "images")
    if not any(real.is_relative_to(tree) for tree in trees):
        return Named(None, "outside the input's folder")
    try:
        st = os.stat(real)
    except FileNotFoundError:
        return Named(None)
    except OSError as exc:
        return Named(None, f"it cannot be examined ({exc.strerror or exc})")
    if not stat.S_ISREG(st.st_mode):
        return Named(None, "not a regular file")
    return Named(real)


def locate_uri(root: Path, folder: Path, uri: str) -> Named:
    """:func:`locate` of a glTF URI that is not a ``data:`` URI: percent-decoded first (RFC 3986), and refused when it
    has a scheme (``file:``, ``http:``) or decodes to a control character (``%00``)."""
    scheme = urllib.parse.urlsplit(uri).scheme if ":" in uri else ""
    if len(scheme) > 1:  # one letter is a drive, which locate refuses as absolute
        return Named(None, f"a URI of scheme {scheme!r}")
    return locate(root, folder, urllib.parse.unquote(uri, errors="replace"))


def read_named(path: Path, limit: int) -> bytes | str:
    """The bytes of an accepted file, or why they are not read: it is checked again once open (still a regular file,
    at most ``limit`` bytes) and read only then, without following a symlink put in its place meanwhile."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        return f"it cannot be opened ({exc.strerror or exc})"
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            return "not a regular file"
        if st.st_size > limit:
            return f"{st.st_size} bytes, over the {limit} kpd reads for one"
        data = fh.read(st.st_size + 1)  # not limit + 1: a read allocates what it is asked for first
    if len(data) > st.st_size:
        return "it grew while it was read"
    return data


def is_text(data: bytes) -> bool:
    """True unless ``data`` holds a byte that text does not (NUL and the other controls but tab, line breaks, form
    feed and escape)."""
    return not data.translate(None, _NOT_CONTROL)


def warn_refused(owner: Path | str, what: str, name: str, reason: str, said: set | None = None) -> None:
    """The one warning of a named file that is not read (nor copied); ``said`` holds what was already said while
    reading ``owner``, so that a name several statements repeat is said once."""
    if said is not None:
        if (what, name) in said:
            return
        said.add((what, name))
    log.warning("%s: %s %r is not read (%s); read without it", owner, what, name, reason)
