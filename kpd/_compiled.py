"""Compiled kernels made on their first call, so that importing a module that defines them does not import numba."""

from __future__ import annotations

import functools
import sys
import threading
from typing import Callable

__all__ = ["njit", "compiled_on_first_call", "announce_compiling"]

COMPILING = ("compiling kpd's kernels for this processor, once: later runs load them from numba's cache (up to "
             "about 25 s on a 2-core machine)")


UNCACHED = ("numba finds no folder to keep kpd's compiled kernels in (kpd's own folder and the user cache folder "
            "are read-only), so each run compiles them again (up to 25 s): set NUMBA_CACHE_DIR to a writable folder")
_uncached_said = False


def njit(**options) -> Callable:
    """``numba.njit(cache=True, **options)``: a kernel compiled once per processor and kept in numba's cache (beside
    its source file, else in the user cache folder, or in ``NUMBA_CACHE_DIR``).

    Where numba finds none of those writable (a read-only installation and home folder, as in a container with a
    read-only root file system), ``cache=True`` is refused when the kernel is defined: the kernel is then compiled
    without the cache, on each run, and a warning says so once per process (logger ``kpd``)."""
    import numba

    def decorate(function: Callable) -> Callable:
        try:
            return numba.njit(cache=True, **options)(function)
        except RuntimeError as exc:
            if "no locator available" not in str(exc):
                raise
        global _uncached_said
        if not _uncached_said:
            _uncached_said = True
            import logging

            logging.getLogger("kpd").warning(UNCACHED)
        return numba.njit(**options)(function)

    return decorate


def compiled_on_first_call(function: Callable) -> Callable:
    """``numba.njit(cache=True, nogil=True)(function)``, made on the first call: importing a module whose kernels
    are defined this way (every mesh reader imports this one) does not import numba, which takes half a second.

    The kernel is compiled once per machine and cached next to its source file, as numba's ``cache=True`` does.
    """
    dispatcher = None

    @functools.wraps(function)
    def call(*args):
        nonlocal dispatcher
        if dispatcher is None:
            dispatcher = njit(nogil=True)(function)
        return dispatcher(*args)

    return call


_announce: Callable[[str], None] | None = None
_announce_lock = threading.Lock()


def announce_compiling(write: Callable[[str], None]) -> None:
    """Call ``write(COMPILING)`` once, the first time numba compiles a kernel in this process from now on.

    A compile means numba's cache had no kernel for this processor. That happens on the first run after
    installing, after an upgrade of kpd or numba, or with a new type of input. It takes seconds for each command's
    first run (``kpd render`` of a 10k-vertex chair: 15 s against 1.4 s once cached). A kernel loaded from the
    cache says nothing. The ``kpd`` command passes a writer to its standard error when that is a terminal.

    numba is not imported here: where it is not imported yet, the listener is installed when it is."""
    global _announce
    with _announce_lock:
        _announce = write
    if "numba" in sys.modules:
        _listen()
    elif not any(type(finder).__name__ == "NumbaImported" for finder in sys.meta_path):
        sys.meta_path.insert(0, _numba_imported())


def _listen() -> None:
    from numba.core import event

    class Compiling(event.Listener):
        def on_start(self, ev) -> None:
            global _announce
            with _announce_lock:
                write, _announce = _announce, None
            if write is not None:
                write(COMPILING)

        def on_end(self, ev) -> None:
            pass

    event.register("numba:compile", Compiling())


def _numba_imported():
    """A finder for ``sys.meta_path`` that finds ``numba`` as the path finder does, with a loader that installs the
    listener once numba's own import is done; it leaves ``sys.meta_path`` at its first use. (Made when asked for: the
    import machinery's modules are not loaded for ``kpd --help``.)"""
    import importlib.abc
    import importlib.machinery

    class NumbaImported(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name != "numba":
                return None
            try:
                sys.meta_path.remove(self)
            except ValueError:
                pass
            spec = importlib.machinery.PathFinder.find_spec(name, path)
            if spec is None or spec.loader is None:
                return spec
            exec_module = spec.loader.exec_module

            def exec_then_listen(module) -> None:
                exec_module(module)
                _listen()

            spec.loader.exec_module = exec_then_listen
            return spec

    return NumbaImported()
