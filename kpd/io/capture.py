"""Open3D's log and C-level stderr, captured: the one place kpd reads what Open3D and RPly say.

Open3D's Python module prints its log through ``sys.stdout`` and reports most failures only there (a failed read
returns an empty or half-filled geometry, a failed write may return success), and RPly writes "Failed writing ..." to
file descriptor 2. kpd's readers and writers run Open3D inside these captures and turn what they hear into one clear
error.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from kpd.errors import WriteError
from kpd.io.atomic import disk_full

__all__ = ["open3d_module", "open3d_log", "failures", "c_stderr", "native_output", "Captured", "open3d_write",
           "FAILURE"]

log = logging.getLogger("kpd.io")


def open3d_module():
    """Open3D, imported on first use so that ``import kpd.io`` stays light."""
    import open3d

    return open3d


@contextlib.contextmanager
def open3d_log() -> Iterator[list[str]]:
    """Run Open3D calls with their warnings captured instead of printed; yields the list of captured lines.

    Open3D's Python module prints its log through ``sys.stdout`` and reports most failures only there (a failed read
    returns an empty or half-filled geometry), so kpd reads that log to tell success from failure. Lines that are
    not Open3D's (another thread printing meanwhile) are passed on to stdout.
    """
    o3d = open3d_module()
    lines: list[str] = []
    buffer = io.StringIO()
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Warning):
            with contextlib.redirect_stdout(buffer):
                yield lines
    finally:
        for s in _ANSI.sub("", buffer.getvalue()).splitlines():
            tag = next((t for t in ("[Open3D WARNING] ", "[Open3D ERROR] ") if s.startswith(t)), None)
            if tag:
                lines.append(s[len(tag):].strip())
            elif s.strip():
                sys.stdout.write(s + "\n")


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


# Open3D warnings that mean the geometry was not (fully) read or written. A texture image that cannot be loaded
# ("Read geometry::Image failed") is not one of them: kpd warns about missing textures itself.
FAILURE = re.compile(r"fail|unable|error|cannot|could not|invalid", re.I)


def failures(lines: list[str]) -> list[str]:
    failed = [s for s in lines if FAILURE.search(s) and "geometry::Image" not in s]
    for s in lines:
        if s not in failed:
            log.debug("Open3D: %s", s)
    return list(dict.fromkeys(failed))


def open3d_write(write: Callable[[], bool], p: Path, tmp: Path | None = None) -> None:
    """Run an Open3D writer and raise :class:`WriteError` if it failed, including the failures Open3D reports only
    in its log or on the C stderr ("RPly: Failed writing ...") while returning success."""
    with open3d_log() as messages, c_stderr() as c_lines:
        ok = write()
    failed = failures(messages) + [s for s in c_lines if FAILURE.search(s)]
    if not ok or failed:
        written = tmp if tmp is not None else p
        if disk_full(written.parent):
            raise WriteError(f"cannot write {p}: the disk is full (no space left on device)")
        raise WriteError(f"cannot write {p}: Open3D failed ({'; '.join(dict.fromkeys(failed)) or 'no reason given'})")


class Captured:
    """What native code wrote inside :func:`native_output` (``text`` is filled in when the block ends)."""

    text = ""

    @property
    def lines(self) -> list[str]:
        """The non-empty lines of ``text``, stripped, without terminal colour codes."""
        return [s.strip() for s in _ANSI.sub("", self.text).splitlines() if s.strip()]


@contextlib.contextmanager
def native_output(fds: tuple[int, ...] = (1, 2)) -> Iterator[Captured]:
    """Capture what native code (Open3D's C++, RPly, Mesa, GLFW) writes to the file descriptors ``fds`` while the
    block runs; the yielded :class:`Captured` holds it afterwards. Where no descriptor or no room for the capture is
    left, the block runs uncaptured."""
    captured = Captured()
    sys.stdout.flush()
    sys.stderr.flush()
    saved: list[int] = []
    try:
        sink = tempfile.TemporaryFile()
        saved = [os.dup(fd) for fd in fds]
    except OSError:
        for fd in saved:
            os.close(fd)
        yield captured
        return
    try:
        for fd in fds:
            os.dup2(sink.fileno(), fd)
        try:
            yield captured
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, copy in zip(fds, saved):
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            captured.text = sink.read().decode("utf-8", errors="replace")
    finally:
        sink.close()


@contextlib.contextmanager
def c_stderr() -> Iterator[list[str]]:
    """Capture what C code writes to file descriptor 2 (RPly's messages) while the block runs; yields the lines.
    Lines that are not about a failure are passed on to stderr."""
    lines: list[str] = []
    with native_output((2,)) as captured:
        yield lines
    lines.extend(captured.lines)
    rest = [s for s in lines if not FAILURE.search(s)]
    if rest:
        sys.stderr.write("\n".join(rest) + "\n")
