"""A stop asked of the ``kpd`` program by a signal (Ctrl+C, ``kill``, the end of a terminal), remembered.

The program's handlers (:mod:`kpd.cli`) raise ``KeyboardInterrupt`` or :class:`Terminated` in the main thread, which
unwinds the command: outputs being written are taken back, windows close. Python runs a handler at the next point it
can, which may lie inside a compiled kernel's call: numba's dispatcher can then return with the exception pending
(a ``SystemError`` whose cause is the interrupt) or lose it (a Ctrl+C during the binding of a 1.37M-vertex mesh let
``kpd rig`` write its whole file in about half the tries). The handlers therefore also note the signal here, and
:meth:`kpd.io.Outputs.commit` asks :func:`raise_requested` before it places an output; the program takes a
``SystemError`` for the signal noted. Outside the program nothing is ever noted, and a library caller's own handlers
are not touched.
"""

from __future__ import annotations

import signal

__all__ = ["Terminated", "note", "requested", "raise_requested"]

_requested: list[int] = []  # the first signal noted, if any


class Terminated(BaseException):
    """Raised in the main thread when the program is asked to end (SIGTERM, SIGHUP): it unwinds as an interrupt does,
    so that outputs being written are taken back, windows close and the program's temporary folders go."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def note(signum: int) -> None:
    """Remember that ``signum`` asked the program to stop (the first one counts)."""
    if not _requested:
        _requested.append(signum)


def requested() -> int | None:
    """The signal that asked the program to stop, or None."""
    return _requested[0] if _requested else None


def raise_requested() -> None:
    """Raise the stop a signal asked for (``KeyboardInterrupt`` for SIGINT, else :class:`Terminated`), if one did."""
    if not _requested:
        return
    if _requested[0] == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(_requested[0])
