"""kpd's compiled kernels and numba: the decorator every kernel is defined with (:func:`njit`: numba's cache, failing
softly), kernels made on their first call so that importing a module that defines them does not import numba
(:func:`compiled_on_first_call`), and the note that a first run compiles (:func:`announce_compiling`)."""

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
CACHE_FAILED = "numba's cache of kpd's compiled kernels could not be {} ({}); kpd goes on without it"
_said: set = set()
_said_lock = threading.Lock()


def _warn_once(key: str, line: str) -> None:
    """``line`` as a warning of logger ``kpd``, the first time ``key`` comes in this process."""
    with _said_lock:
        if key in _said:
            return
        _said.add(key)
    import logging

    logging.getLogger("kpd").warning(line)


def njit(**options) -> Callable:
    """``numba.njit(cache=True, **options)``: a kernel compiled once per processor and kept in numba's cache (beside
    its source file, else in the user cache folder, or in ``NUMBA_CACHE_DIR``).

    The cache is kpd's to keep working, not the user's to mend, so a failing one is a warning (logger ``kpd``, once
    per process and kind), never the command's end:

    * where numba finds no writable folder for it (a read-only installation and home folder, as in a container with
      a read-only root file system), ``cache=True`` is refused when the kernel is defined: the kernel is compiled
      without the cache, on each run;
    * a cache file that cannot be read back (damaged, truncated) is compiled again, and written anew;
    * a cache file that cannot be written (a full disk) is left unwritten: the kernel runs as compiled."""
    import numba

    def decorate(function: Callable) -> Callable:
        if _announce is not None:  # every kernel is defined here, before its first compile
            _listen()
        tolerant = _tolerant_cache_class()
        try:
            if tolerant is None:
                return numba.njit(cache=True, **options)(function)
            dispatcher = numba.njit(**options)(function)
            dispatcher._cache = tolerant(function)  # what cache=True does (enable_caching), with that cache
            return dispatcher
        except RuntimeError as exc:
            if "no locator available" not in str(exc):
                raise
        _warn_once("uncached", UNCACHED)
        return numba.njit(**options)(function)

    return decorate


@functools.cache
def _tolerant_cache_class():
    """numba's cache of a function, its reads and writes failing softly (see :func:`njit`), where numba lets a
    damaged file's unpickling error or a full disk's error end the program. None where this numba's cache has not
    the two methods the dispatcher calls."""
    try:
        from numba.core.caching import FunctionCache
    except ImportError:
        return None
    if not all(hasattr(FunctionCache, name) for name in ("load_overload", "save_overload")):
        return None

    class TolerantCache(FunctionCache):
        def load_overload(self, sig, target_context):
            try:
                return super().load_overload(sig, target_context)
            except Exception as exc:  # a cache's failure, whatever it is: None, and the kernel is compiled
                _warn_once("read", CACHE_FAILED.format("read", f"{type(exc).__name__}: {exc}"))
                return None

        def save_overload(self, sig, data):
            try:
                super().save_overload(sig, data)
            except Exception as exc:  # the kernel runs as compiled
                _warn_once("write", CACHE_FAILED.format("written", f"{type(exc).__name__}: {exc}"))

    return TolerantCache


def compiled_on_first_call(function: Callable) -> Callable:
    """``njit(nogil=True)(function)``, made on the first call: importing a module whose kernels are defined this
    way (every mesh reader imports this one) does not import numba, which takes half a second. The kernel is
    compiled once per processor and cached as :func:`njit` says."""
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
    first run. A kernel loaded from the
    cache says nothing. The ``kpd`` command passes a writer to its standard error when that is a terminal.

    numba is not imported here: where no kernel is defined yet, :func:`njit` installs the listener with the first."""
    global _announce
    with _announce_lock:
        _announce = write
    if "numba" in sys.modules:
        _listen()


_listening = False


def _listen() -> None:
    """Listen to numba's compile event, once per process."""
    global _listening
    with _announce_lock:
        if _listening:
            return
        _listening = True
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
