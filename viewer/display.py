"""Where OpenGL draws: a private Xvfb server, the current display or a headless EGL context; and screenshots of a
private server's screen.

The backends of :func:`kpd.viewer.render.render_rig` (:data:`BACKENDS`): ``egl`` (what ``auto`` means) draws in a
headless EGL context in this process, ``xvfb`` in a hidden window on a private Xvfb server, ``window`` on the current
``$DISPLAY``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import shutil
import signal
import struct
import subprocess
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from kpd.errors import InputError, KpdError

__all__ = ["BACKENDS", "resolve_backend", "gl_display", "private_display", "grab_screen"]

log = logging.getLogger(__name__)

BACKENDS = ("auto", "egl", "xvfb", "window")


def resolve_backend(backend: str) -> str:
    """The backend ``auto`` stands for (``egl``), after checking that the one asked for can run here."""
    if backend == "auto":
        return "egl"
    if backend == "xvfb" and not shutil.which("Xvfb"):
        raise KpdError("the xvfb backend needs the Xvfb program (Debian/Ubuntu: apt-get install xvfb); or use "
                       "--backend egl")
    if backend == "window" and not os.environ.get("DISPLAY"):
        raise KpdError("the window backend needs a display ($DISPLAY is not set); use --backend egl or xvfb")
    return backend


@contextlib.contextmanager
def gl_display(backend: str, width: int, height: int) -> Iterator[None]:
    """Make ``$DISPLAY`` point at an X server for the OpenGL path for the duration of the block: a private Xvfb
    (``backend="xvfb"``) or the current display (``"window"``)."""
    backend = resolve_backend(backend)
    if backend == "window":
        yield
        return
    if backend == "egl":  # no X server: Open3D's legacy renderer then draws into a headless EGL context
        hidden = {name: os.environ.pop(name) for name in ("DISPLAY", "WAYLAND_DISPLAY") if name in os.environ}
        try:
            yield
        finally:
            os.environ.update(hidden)
        return
    if backend != "xvfb":
        raise InputError(f"the OpenGL path needs the egl, xvfb or window backend; got {backend!r}")
    saved = os.environ.get("DISPLAY")
    with private_display(width + 64, height + 64) as display:
        os.environ["DISPLAY"] = display
        try:
            yield
        finally:
            if saved is None:
                os.environ.pop("DISPLAY", None)
            else:
                os.environ["DISPLAY"] = saved


@contextlib.contextmanager
def private_display(width: int = 1280, height: int = 1024, *, timeout: float = 20.0,
                    fbdir: str | os.PathLike | None = None) -> Iterator[str]:
    """Run a private ``Xvfb`` server for the duration of the block; yields its ``DISPLAY`` string (``":N"``).

    The server picks a free display number itself (``-displayfd``) and is stopped (its process only) on exit.
    With ``fbdir`` the server keeps its screen in ``fbdir/Xvfb_screen0`` (XWD format), which :func:`grab_screen`
    reads: a screenshot of every window on it, the editor's panel included.
    """
    program = shutil.which("Xvfb")
    if program is None:
        raise KpdError("Xvfb is not installed (Debian/Ubuntu: apt-get install xvfb)")
    read_fd, write_fd = os.pipe()
    process = subprocess.Popen(
        [program, "-displayfd", str(write_fd), "-screen", "0", f"{int(width)}x{int(height)}x24", "-nolisten", "tcp",
         "-noreset", *(["-fbdir", str(fbdir)] if fbdir is not None else [])],
        pass_fds=(write_fd,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )
    os.close(write_fd)
    try:
        number = b""
        deadline = time.monotonic() + timeout
        while not number.endswith(b"\n"):
            remaining = deadline - time.monotonic()
            if remaining <= 0 or process.poll() is not None:
                raise KpdError("the private Xvfb server did not start")
            ready, _, _ = select.select([read_fd], [], [], remaining)
            if ready:
                chunk = os.read(read_fd, 16)
                if not chunk:
                    raise KpdError("the private Xvfb server did not start")
                number += chunk
        display = ":" + number.decode().strip()
        log.debug("private Xvfb on %s (pid %d)", display, process.pid)
        yield display
    finally:
        os.close(read_fd)
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def grab_screen(fbdir: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8: the screen of an Xvfb server started with ``-fbdir`` (see :func:`private_display`)."""
    path = Path(fbdir) / "Xvfb_screen0"
    data = path.read_bytes()
    header = struct.unpack(">25I", data[:100])
    size, width, height, bits, line, colours = header[0], header[4], header[5], header[11], header[12], header[19]
    if header[1] != 7 or bits != 32:
        raise KpdError(f"{path}: not a 32-bit XWD screen (version {header[1]}, {bits} bits per pixel)")
    pixels = np.frombuffer(data, np.uint8, count=line * height, offset=size + 12 * colours)
    bgrx = pixels.reshape(height, line)[:, :width * 4].reshape(height, width, 4)
    return np.ascontiguousarray(bgrx[:, :, [2, 1, 0]])
