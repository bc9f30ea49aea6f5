"""The ``kpd`` command: a thin shell over the library (see ``kpd.commands``)."""

from __future__ import annotations

import argparse
import atexit
import gc
import importlib
import logging
import os
import signal
import sys
import threading

from kpd import __version__, _signals
from kpd._compiled import announce_compiling
from kpd.commands import COMMANDS, TRAIN_EXTRA, run_checks, train_extra_missing
from kpd.errors import KpdError
from kpd.io.atomic import describe_os_error


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``kpd train: error: argument --samples: must be at least 1; got 0``."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="kpd",
        description="Unsupervised 3D keypoints and keypoint-driven shape deformation (KeypointDeformer).",
        epilog="Run 'kpd COMMAND --help' for a command's options and an example.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("--version", action="version", version=f"kpd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        cmd = sub.add_parser(
            name,
            help=module.HELP,
            description=module.HELP,
            epilog="example:\n  " + module.EXAMPLE,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    code = _main(argv)
    if argv is None:  # the program itself
        for signum, previous in _HANDLED.items():  # from here on a signal ends the program as it did before
            signal.signal(signum, previous)
        _end_program(code)
    return code


def _end_program(code: int) -> None:
    """End the program now, without the interpreter's teardown.

    The teardown frees every object one by one and collects the cycles among them (numba's, SciPy's and Open3D's
    modules, a dense mesh's arrays), a noticeable part of a short command, while the operating system frees the
    process's memory at once anyway. What the interpreter's exit does before it is done here the same way: the threads
    still at work are waited for (and idle pool workers woken to end: ``threading._shutdown``, which the interpreter
    calls first), the functions registered with :mod:`atexit` run (logging's flush, multiprocessing's children), and
    both output streams are flushed. An interpreter without ``threading._shutdown`` ends as usual."""
    shutdown = getattr(threading, "_shutdown", None)
    if shutdown is None:
        return
    shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (kpd ... | head): what was not read is lost either way
            code = code or 120  # the interpreter's own status when it cannot flush
    os._exit(code)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option (2, one line already printed)
        return int(exc.code or 0)
    if argv is None:  # the program itself (not a caller's process, whose objects are not ours to freeze)
        # the objects made so far (the commands' modules, the parser) live as long as the process: the cyclic
        # garbage collector need not go through them again at each collection
        gc.freeze()
        _keep_freed_memory()
        if args.command != "train":  # torchrun stops its ranks itself
            _end_on_termination()
        if args.command is not None and sys.stderr.isatty():
            # a first run compiles for seconds without a word otherwise
            announce_compiling(_note)
    handler = logging.StreamHandler()
    handler.setFormatter(_Formatter())
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, handlers=[handler])
    if args.command is None:
        parser.print_help()
        return 2
    try:
        run_checks(args)
        return int(args._run(args) or 0)
    except KpdError as exc:
        _close_progress_bars()
        print(f"kpd {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:  # a module of the train extra, imported where no command checked for it first
        missing = _missing_extra(exc)
        if missing is None:
            raise
        _close_progress_bars()
        print(f"kpd {args.command}: error: {train_extra_missing(missing)}", file=sys.stderr)
        return 2
    except OSError as exc:  # the environment failed (a disk, a folder's permissions) where kpd did not expect it
        _close_progress_bars()
        print(f"kpd {args.command}: error: {_one_line(describe_os_error(exc, exc.filename or 'a file'))}",
              file=sys.stderr)
        return 2
    except MemoryError as exc:  # the memory ran out where kpd could not tell beforehand (what else runs, ulimit -v)
        _close_progress_bars()
        detail = _one_line(exc)
        print(f"kpd {args.command}: error: out of memory{': ' + detail if detail else ''} (free memory, raise the "
              f"limit, or give a smaller input)", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        if "can't start new thread" not in str(exc):
            raise
        _close_progress_bars()
        print(f"kpd {args.command}: error: the system would not start another thread (a limit on threads or on "
              f"memory: ulimit -u, ulimit -v)", file=sys.stderr)
        return 2
    except SystemError:
        # numba's dispatcher returns with a handler's exception pending when the signal came during its call: the
        # interrupt is the cause (see kpd._signals)
        if _signals.requested() is None:
            raise
        return _stopped(args.command, _signals.requested())
    except KeyboardInterrupt:
        return _stopped(args.command, signal.SIGINT)
    except _signals.Terminated as exc:
        return _stopped(args.command, exc.signum)


def _missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The module of the train extra that ``exc`` says is missing and that is indeed not installed, else None (a
    module missing inside an installed torch is a broken installation, shown as it is)."""
    top = (exc.name or "").partition(".")[0]
    if top not in TRAIN_EXTRA:
        return None
    import importlib.util

    return top if importlib.util.find_spec(top) is None else None


def _note(line: str) -> None:
    """``note: line`` on standard error, above any progress bar being drawn."""
    tqdm = sys.modules.get("tqdm")
    if tqdm is not None:
        tqdm.tqdm.write(f"note: {line}", file=sys.stderr)
    else:
        print(f"note: {line}", file=sys.stderr, flush=True)


def _stopped(command: str, signum: int) -> int:
    """The line and status of a command stopped by a signal: Ctrl+C's (130), or 128 + the signal's."""
    _close_progress_bars()
    if signum == signal.SIGINT:
        print(f"kpd {command}: interrupted", file=sys.stderr)
        return 130
    print(f"kpd {command}: stopped by signal {signum} ({signal.Signals(signum).name})", file=sys.stderr)
    return 128 + signum


_HANDLED: dict = {}  # signal -> the handler it had before _end_on_termination


def _end_on_termination() -> None:
    """SIGTERM and SIGHUP (a ``kill``, the end of a session or terminal) end a command as Ctrl+C does, with status
    128 + the signal, instead of at once (which left a window's temporary folder and any output half written). A
    signal the program was started to ignore (``nohup``) stays ignored. Each signal, Ctrl+C's too, is also noted
    (:mod:`kpd._signals`), so that one whose exception compiled code lost still stops the command before its outputs
    are placed."""

    def stop(signum: int, frame) -> None:
        _signals.note(signum)
        raise _signals.Terminated(signum)

    def interrupt(signum: int, frame) -> None:
        _signals.note(signum)
        raise KeyboardInterrupt

    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is not None and signal.getsignal(signum) == signal.SIG_DFL:
            _HANDLED[signum] = signal.signal(signum, stop)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        _HANDLED[signal.SIGINT] = signal.signal(signal.SIGINT, interrupt)


_MMAP_THRESHOLD = 1 << 30


def _keep_freed_memory() -> None:
    """Let glibc's malloc serve blocks of up to 1 GB from its heap rather than from a mapping of their own each
    (``mallopt(M_MMAP_THRESHOLD)``; its default moves between 128 kB and 32 MB): a large array freed then stays in the
    process, and the next one reuses its pages instead of asking the kernel for fresh ones, which it zeroes and a
    virtual machine's host may first have to find (seen here at 0.3 GB/s). kpd render of a 1.37M-vertex mesh faults
    in a sixth fewer pages; its peak memory grows by about a tenth. Not glibc: nothing to do."""
    import ctypes

    if not sys.platform.startswith("linux"):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the interpreter runs on
    except (OSError, AttributeError):  # a C library without mallopt (musl has none)
        return
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mallopt(-3, _MMAP_THRESHOLD)  # M_MMAP_THRESHOLD


class _Formatter(logging.Formatter):
    """Warnings and errors as the commands print theirs (``warning: ...``); details (``-v``) with their logger."""

    def format(self, record: logging.LogRecord) -> str:
        if record.levelno >= logging.WARNING:
            return f"{record.levelname.lower()}: {record.getMessage()}"
        return f"{record.levelname} {record.name}: {record.getMessage()}"


def _close_progress_bars() -> None:
    """Erase the progress bars still on the screen, so that an error starts on a line of its own."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ()) or ()):
        try:
            bar.leave = False
            bar.close()
        except Exception:  # noqa: BLE001 (a bar that cannot close must not hide the error)
            pass


def _one_line(message) -> str:
    return " ".join(str(message).split())


if __name__ == "__main__":
    sys.exit(main())
