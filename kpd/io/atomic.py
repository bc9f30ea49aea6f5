"""One way to write a file: every output kpd writes goes through this module.

The rules it enforces, for files, folders and the companion files some formats carry (an OBJ's ``.mtl`` and
textures, a ``.gltf``'s images):

- **Checked before any work** (:func:`check_output`): the output's folder exists and is writable, the output is
  not one of the command's inputs nor a folder that holds one (so ``--force`` can never delete an input), and it
  does not exist unless ``force``.
- **Written under a temporary name** in the output's folder (``.<name>.kpd-tmp-<pid>-<hex>...``), flushed and
  fsynced, checked by the writer (size, re-read header) and only then renamed to its final name. Companion files
  are written with their final names into a temporary folder, so they reference each other by the names they end
  up with, and are placed together (companions first, the named output last). A writer given a path inside such a
  staging folder (:meth:`Outputs.stage`) writes there directly: the folder's placement is the atomic write, so each
  output is written and fsynced once.
- **Exclusive placement**: without ``force`` the rename refuses to replace anything (``renameat2(RENAME_NOREPLACE)``,
  or a hard link where that is missing), so of two commands writing the same output one wins and the other fails
  with one line, and a file that appears at the output path while a command runs is never clobbered.
- **Failures** (a full disk, a read-only or forbidden folder) raise :class:`~kpd.errors.WriteError` with one line
  naming the file and the cause, after removing every temporary file; nothing that existed is changed.
- **Killed runs**: a temporary left by a process that no longer exists (SIGKILL during a write) is removed by the
  next kpd command that writes into that folder (:func:`remove_stale_temporaries`; ``kpd train --resume`` runs it
  on the run folder).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import os
import re
import secrets
import shutil
from pathlib import Path
from typing import Callable, Iterable, Iterator

from kpd import _signals
from kpd.errors import InputError, WriteError

__all__ = ["TEMP_MARK", "Outputs", "user_path", "atomic_output", "atomic_files", "check_output",
           "remove_stale_temporaries",
           "describe_os_error", "disk_full", "incomplete"]

log = logging.getLogger(__name__)

TEMP_MARK = ".kpd-tmp-"
_TEMP_NAME = re.compile(r"^\..*\.kpd-tmp-(\d+)-[0-9a-f]{8}")

_REASONS = {
    errno.ENOSPC: "the disk is full (no space left on device)",
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EROFS: "the file system is read-only",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EFBIG: "the file is too large for the file system",
    errno.EIO: "input/output error (a failing disk?)",
}


def describe_os_error(exc: OSError, path: str | os.PathLike) -> str:
    """One line for a failed write: ``cannot write out.ply: the disk is full (no space left on device)``."""
    reason = _REASONS.get(exc.errno or -1) or exc.strerror or str(exc)
    return f"cannot write {path}: {reason}"


def disk_full(folder: str | os.PathLike) -> bool:
    """True when the file system of ``folder`` has less than 64 KiB free (a write there just ran out of space)."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < 1 << 16


def incomplete(p: Path, detail: str) -> WriteError:
    """The error of a written file that a check found short (``detail`` says what it holds), with its likely cause."""
    cause = "the disk is full" if disk_full(p.parent) else "the writer stopped early"
    return WriteError(f"cannot write {p}: the written file is incomplete ({detail}; {cause})")


def _nothing_written(p: Path) -> WriteError:
    cause = "the disk is full (no space left on device)" if disk_full(p.parent) else "nothing was written"
    return WriteError(f"cannot write {p}: {cause}")


def _temp_name(target: Path, suffix: str = "") -> Path:
    return target.with_name(f".{target.name}{TEMP_MARK}{os.getpid()}-{secrets.token_hex(4)}{suffix}")


def user_path(path: str | os.PathLike) -> Path:
    """The path a user named for ``path``: a file inside a staging folder (``.<name>.kpd-tmp-<pid>-<hex>/<name>``,
    see :class:`Outputs`) or a temporary file (``.<name>.kpd-tmp-<pid>-<hex>.ext``) is given its final name, so
    that messages never name kpd's temporary files."""
    p = Path(path)
    if _TEMP_NAME.match(p.parent.name):
        return p.parent.parent / p.name
    match = re.match(r"^\.(.*)\.kpd-tmp-\d+-[0-9a-f]{8}", p.name)
    return p.with_name(match.group(1)) if match else p


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and folders that killed kpd processes left in ``folder``; returns them.

    Only names kpd makes (``.<name>.kpd-tmp-<pid>-<hex>...``) whose process no longer runs are touched.
    """
    folder = Path(folder)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = _TEMP_NAME.match(entry.name)
        if match is None or _alive(int(match.group(1))):
            continue
        path = Path(entry.path)
        try:
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(path)
            else:
                path.unlink()
        except OSError as exc:  # another process removed it first, or the folder is read-only
            log.debug("could not remove stale temporary %s: %s", path, exc)
            continue
        log.info("removed %s, left by an interrupted kpd run", path)
        removed.append(path)
    return removed


# --- checks before any work ----------------------------------------------------------------------------------------


def _named(option: str | None, path: Path) -> str:
    return f"{option} {path}" if option else str(path)


def check_folder_writable(folder: Path, what: str) -> None:
    """Raise :class:`InputError` unless ``folder`` is an existing folder this process may create files in."""
    if not folder.exists():
        raise InputError(f"{what}: folder {folder} does not exist")
    if not folder.is_dir():
        raise InputError(f"{what}: {folder} is a file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        try:
            read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
        except OSError:
            read_only = False
        cause = "the file system is read-only" if read_only else "permission denied"
        raise InputError(f"{what}: cannot write in folder {folder} ({cause})")


def check_output(path: str | os.PathLike, *, option: str | None = "--out", force: bool = False,
                 inputs: Iterable = (), kind: str = "file", formats: tuple | None = None,
                 what: str = "") -> Path:
    """Check an output before any work; return it as a Path.

    Parameters
    ----------
    path : the file (or folder, ``kind="folder"``) the command will write.
    option : the option that named it, for messages (``--out``, ``--report``...).
    force : allow replacing an existing output (never an input).
    inputs : paths the command reads (None entries are ignored); the output may be none of them and, when it is
        an existing folder, may hold none of them.
    formats : allowed suffixes (``(".ply", ".obj")``), checked when given; ``what`` names the kind in the message.

    Raises
    ------
    InputError
        With one line naming ``option`` and the problem.
    """
    p = Path(path)
    named = _named(option, p)
    if kind == "file" and p.is_dir():
        raise InputError(f"{named} is a folder; give a file name")
    if formats is not None and p.suffix.lower() not in formats:
        raise InputError(f"{named}: a {what or 'output'} file must end in one of {' '.join(formats)}")
    if kind == "folder" and p.exists() and not p.is_dir():
        raise InputError(f"{named} is a file; this command writes a folder")
    check_folder_writable(p.parent, named)
    resolved = p.resolve()
    for source in inputs:
        if source is None or not Path(source).exists():
            continue
        source_resolved = Path(source).resolve()
        if source_resolved == resolved:
            raise InputError(f"{named} is also an input of this command; choose another {option or 'output'}")
        if p.is_dir() and resolved in source_resolved.parents:
            raise InputError(f"{named} holds the input {source}; replacing it would delete that input, so choose "
                             f"another {option or 'output'}")
        if p.exists() and Path(source).is_dir() and source_resolved in resolved.parents:
            raise InputError(f"{named} lies inside the input {source}; replacing it would change that input, so "
                             f"choose another {option or 'output'}")
    if p.exists() and not force:
        raise InputError(f"{named} exists; pass --force to replace it")
    remove_stale_temporaries(p.parent)
    return p


# --- placing -------------------------------------------------------------------------------------------------------

_RENAME_NOREPLACE = 1
_AT_FDCWD = -100
_libc = None


def _renameat2():
    global _libc
    if _libc is None:
        try:
            _libc = ctypes.CDLL(None, use_errno=True)
        except OSError:
            _libc = False
    return getattr(_libc, "renameat2", None) if _libc else None


def _rename_noreplace(source: Path, target: Path) -> None:
    """Rename ``source`` onto ``target`` only if nothing is there; FileExistsError otherwise (atomic)."""
    rename = _renameat2()
    if rename is not None:
        if rename(_AT_FDCWD, os.fsencode(source), _AT_FDCWD, os.fsencode(target), _RENAME_NOREPLACE) == 0:
            return
        code = ctypes.get_errno()
        if code not in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
            raise OSError(code, os.strerror(code), str(target))
    if source.is_dir():  # no atomic way without renameat2: check, then rename
        if os.path.lexists(target):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(target))
        os.rename(source, target)
    else:
        os.link(source, target)  # fails if target exists
        os.unlink(source)


def _replace(source: Path, target: Path, aside: Path) -> Path | None:
    """Rename ``source`` onto ``target``, replacing what is there; an old folder (or a file replaced by a folder)
    is moved into ``aside`` first and returned for deletion."""
    if os.path.lexists(target) and (target.is_dir() or source.is_dir()) and not target.is_symlink():
        old = aside / f".old-{target.name}"
        os.rename(target, old)
        os.rename(source, target)
        return old
    os.replace(source, target)
    return None


def _fsync(path: Path) -> None:
    if path.is_dir():
        for child in path.iterdir():
            if not child.is_symlink():
                _fsync(child)
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems cannot fsync folders; the files themselves are synced
        pass
    finally:
        os.close(fd)


def _place(staging: Path, folder: Path, main: list[str], *, force: bool) -> None:
    """Move every entry of ``staging`` into ``folder``: companions first, the ``main`` names last. Without
    ``force`` nothing is replaced: if any name exists, nothing is moved (and what this call moved is taken back)."""
    names = sorted(e.name for e in staging.iterdir() if not e.name.startswith(".old-"))
    order = [n for n in names if n not in main] + [n for n in main if n in names]
    _fsync(staging)
    if not force:
        for name in order:
            if os.path.lexists(folder / name):
                raise WriteError(_clash(folder / name, name in main))
    placed, old = [], []
    try:
        for name in order:
            if force:
                moved = _replace(staging / name, folder / name, staging)
                if moved is not None:
                    old.append(moved)
            else:
                try:
                    _rename_noreplace(staging / name, folder / name)
                except FileExistsError:
                    raise WriteError(_clash(folder / name, name in main)) from None
            placed.append(folder / name)
    except BaseException:
        if not force:
            for p in placed:  # ours, just placed: take them back so nothing half-written stays
                with contextlib.suppress(OSError):
                    shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        raise
    _fsync_folder(folder)
    for p in old:
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


def _clash(path: Path, main: bool) -> str:
    if main:
        return (f"{path} appeared while kpd was running (another process writing the same output?); it was left "
                "as it is and nothing was written")
    return f"companion file {path} exists; pass --force to replace it (nothing was written)"


def _staging_folder(folder: Path, name: str) -> Path:
    staging = folder / f".{name}{TEMP_MARK}{os.getpid()}-{secrets.token_hex(4)}"
    os.mkdir(staging)
    return staging


@contextlib.contextmanager
def _as_write_error(path: Path) -> Iterator[None]:
    try:
        yield
    except WriteError:
        raise
    except OSError as exc:
        raise WriteError(describe_os_error(exc, path)) from exc


# --- single outputs ------------------------------------------------------------------------------------------------


def _check_target(path: str | os.PathLike) -> Path:
    p = Path(path)
    if not p.parent.is_dir():
        raise InputError(f"{p}: folder {p.parent} does not exist")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a file")
    return p


def _staged(p: Path) -> bool:
    """Whether ``p`` lies in a staging folder (:class:`Outputs`, :func:`atomic_files`), whose placement is the atomic
    write: a writer inside one writes there directly, so that each output is written and fsynced once."""
    return _TEMP_NAME.match(p.parent.name) is not None


@contextlib.contextmanager
def _staged_output(p: Path, force: bool, verify: Callable[[Path], None] | None = None, *,
                   companions: bool = False) -> Iterator[Path]:
    """Write ``p`` straight into its staging folder (with ``companions``, what else the block adds beside it); on a
    failure that is removed, so that the staging folder's owner places nothing of it."""
    with _as_write_error(p):
        if not force and os.path.lexists(p):
            raise WriteError(_clash(p, True))
        before = set(os.listdir(p.parent)) if companions else set()
        try:
            yield p
            if not p.is_file() or p.stat().st_size == 0:
                raise _nothing_written(p)
            if verify is not None:
                verify(p)
        except BaseException:
            added = set(os.listdir(p.parent)) - before if companions else {p.name}
            for name in added:
                q = p.parent / name
                shutil.rmtree(q, ignore_errors=True) if q.is_dir() and not q.is_symlink() else q.unlink(missing_ok=True)
            raise


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, force: bool = True,
                  verify: Callable[[Path], None] | None = None) -> Iterator[Path]:
    """Write one file atomically: yield a temporary path in the same folder, put it at ``path`` when complete.

    The temporary name keeps ``path``'s extension (writers that pick the format by extension work) and is hidden.
    After the block, the file is fsynced, checked by ``verify(tmp)`` (which raises :class:`WriteError` for an
    incomplete file) and renamed to ``path``: replacing an existing file only when ``force`` (the library default;
    commands check ``--force`` first, see :class:`Outputs`). If anything fails the temporary file is removed and
    ``path`` is untouched.

    Example
    -------
    >>> with atomic_output("out.npz") as tmp:          # doctest: +SKIP
    ...     np.savez(tmp, points=points)

    Raises
    ------
    InputError
        If the target folder does not exist or ``path`` is a folder.
    WriteError
        If the disk is full, the folder is read-only or forbidden, nothing was written, the writer wrote an
        incomplete file, or (without ``force``) a file appeared at ``path`` meanwhile.
    """
    p = _check_target(path)
    if _staged(p):
        with _staged_output(p, force, verify) as target:
            yield target
        return
    tmp = _temp_name(p, p.suffix)
    try:
        with _as_write_error(p):
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            yield tmp
            if not tmp.is_file() or tmp.stat().st_size == 0:
                raise _nothing_written(p)
            _fsync(tmp)
            if verify is not None:
                verify(tmp)
            if p.exists():
                shutil.copymode(p, tmp)
            if force:
                os.replace(tmp, p)
            else:
                try:
                    _rename_noreplace(tmp, p)
                except FileExistsError:
                    raise WriteError(_clash(p, True)) from None
            _fsync_folder(p.parent)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_files(path: str | os.PathLike, *, force: bool = True) -> Iterator[Path]:
    """Write a file and its companions atomically: yield ``<temporary folder>/<name of path>``.

    Everything written into that folder (an OBJ's ``.mtl`` and textures, written under their final names) is
    fsynced and moved beside ``path`` together, companions first and ``path`` last; without ``force`` nothing is
    replaced (see :func:`atomic_output`).
    """
    p = _check_target(path)
    if _staged(p):
        with _staged_output(p, force, companions=True) as target:
            yield target
        return
    staging = None
    try:
        with _as_write_error(p):
            staging = _staging_folder(p.parent, p.name)
            target = staging / p.name
            yield target
            if not target.is_file() or target.stat().st_size == 0:
                raise _nothing_written(p)
            if p.exists():
                shutil.copymode(p, target)
            _place(staging, p.parent, [p.name], force=force)
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)


# --- every output of a command -------------------------------------------------------------------------------------


class Outputs:
    """The outputs of one command: checked before any work, written into a staging area, placed together.

    Parameters
    ----------
    force : replace existing outputs (``--force``); inputs are never replaced either way.
    inputs : the paths the command reads.

    Example
    -------
    >>> with Outputs(force=args.force, inputs=(args.shape,)) as outputs:      # doctest: +SKIP
    ...     out = outputs.file(args.out, "--out", formats=MESH_FORMATS, what="mesh")
    ...     mesh = ...                                   # the work
    ...     write_mesh(outputs.stage(out), mesh)         # written under its final name, in a staging folder
    >>> print(f"wrote {out}")                            # only now is every byte on disk, at its final name

    Leaving the ``with`` block normally places every staged output (companions first, fsynced, exclusively unless
    ``force``); leaving it with an exception removes the staging area and leaves every existing file as it was.
    """

    def __init__(self, *, force: bool = False, inputs: Iterable = ()) -> None:
        self.force = bool(force)
        self.inputs = tuple(Path(i) for i in inputs if i is not None)
        self._options: dict[Path, str] = {}  # absolute final path -> option that named it
        self._staging: dict[Path, Path] = {}  # final folder -> its staging folder

    def file(self, path: str | os.PathLike, option: str = "--out", *, formats: tuple | None = None,
             what: str = "") -> Path:
        """Check and register an output file (see :func:`check_output`); returns its path."""
        return self._add(path, option, "file", formats, what)

    def folder(self, path: str | os.PathLike, option: str = "--out") -> Path:
        """Check and register an output folder: staged whole, it replaces an existing folder only with ``force``."""
        return self._add(path, option, "folder", None, "")

    def companions(self, path: Path, names: Iterable[str]) -> None:
        """Check the companion files a writer will add beside ``path`` (an OBJ's ``.mtl`` and textures)."""
        option = self._options.get(Path(path).absolute(), "--out")
        for name in names:
            c = Path(path).parent / name
            if any(c.resolve() == i.resolve() for i in self.inputs if i.exists()):
                raise InputError(f"{option} {path}: its companion file {c} is an input of this command; choose "
                                 f"another {option}")
            if c.exists() and not self.force:
                raise InputError(f"{option} {path}: its companion file {c} exists; pass --force to replace it")

    def _add(self, path, option, kind, formats, what) -> Path:
        p = check_output(path, option=option, force=self.force, inputs=self.inputs, kind=kind, formats=formats,
                         what=what)
        key = p.absolute()
        for other, other_option in self._options.items():
            if other == key or other.resolve() == p.resolve():
                raise InputError(f"{option} and {other_option} name the same file {p}")
        self._options[key] = option
        return p

    def stage(self, path: str | os.PathLike) -> Path:
        """The path to write a registered output to: its final name, inside a staging folder beside it."""
        p = Path(path).absolute()
        if p not in self._options:
            raise ValueError(f"{path} is not a registered output")  # a programming error, not a user's
        folder = p.parent
        if folder not in self._staging:
            with _as_write_error(p):
                self._staging[folder] = _staging_folder(folder, p.name)
        return self._staging[folder] / p.name

    def commit(self) -> None:
        """Place every staged output (see the class notes); nothing when the program was asked to stop by a signal
        whose exception compiled code lost (:mod:`kpd._signals`): that stop is raised instead."""
        try:
            _signals.raise_requested()
            for p in self._options:  # everything checked before anything is placed
                staging = self._staging.get(p.parent)
                if staging is None or not os.path.lexists(staging / p.name):
                    raise _nothing_written(p)
                if not self.force and os.path.lexists(p):
                    raise WriteError(_clash(p, True))
            for folder, staging in self._staging.items():
                main = [p.name for p in self._options if p.parent == folder]
                with _as_write_error(folder / main[0]):
                    _place(staging, folder, main, force=self.force)
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove the staging folders and everything in them."""
        for staging in self._staging.values():
            shutil.rmtree(staging, ignore_errors=True)
        self._staging.clear()

    def __enter__(self) -> "Outputs":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.commit()
            return
        staging = dict(self._staging)
        self.discard()
        if isinstance(value, OSError):  # a writer inside the block failed: one line naming the file and the cause
            where = value.filename or next(iter(self._options), "an output")
            raise WriteError(self._final_names(describe_os_error(value, where), staging)) from value
        if isinstance(value, WriteError):  # name the outputs by their final paths, not the staging folder's
            message = self._final_names(str(value), staging)
            if message != str(value):
                raise WriteError(message) from value

    @staticmethod
    def _final_names(message: str, staging: dict) -> str:
        for folder, stage in staging.items():
            message = message.replace(str(stage), str(folder))
        return message
