"""Content hashes of what kpd writes and reads back (checkpoints, rigs, edit sessions), and safe numpy loading.

A file kpd wrote carries the sha256 of its content (:func:`content_hash`), computed over the values themselves
(arrays as dtype, shape and bytes; numbers, strings and nested containers in a canonical order), not over the
container's bytes: the hash survives the container (a zip, a torch checkpoint, JSON) and a flipped byte anywhere
in the data is refused on load (:func:`check_hash`) instead of being used.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from kpd.errors import InputError

__all__ = ["HASH_KEY", "content_hash", "json_hash", "check_hash", "load_numpy", "checkpoint_failure"]

HASH_KEY = "sha256"


def content_hash(value: Any) -> str:
    """sha256 (hex) of a nested value: dicts (keys sorted), lists and tuples, numpy arrays and tensors (anything
    with ``.detach().cpu().numpy()``), numbers, strings, bytes, None. The key :data:`HASH_KEY` of the top-level
    mapping is left out, so a mapping can hold its own hash."""
    h = hashlib.sha256()
    _feed(h, value, top=True)
    return h.hexdigest()


def _feed(h, value: Any, top: bool = False) -> None:
    if isinstance(value, Mapping):
        items = [(k, v) for k, v in value.items() if not (top and k == HASH_KEY)]
        h.update(b"{%d" % len(items))
        for key, item in sorted(items, key=lambda kv: (type(kv[0]).__name__, str(kv[0]))):
            _feed(h, key)
            _feed(h, item)
        h.update(b"}")
    elif isinstance(value, (list, tuple)):
        h.update(b"[%d" % len(value))
        for item in value:
            _feed(h, item)
        h.update(b"]")
    elif hasattr(value, "detach") and hasattr(value, "numpy"):  # a torch tensor, without importing torch
        _feed(h, value.detach().cpu().contiguous().numpy())
    elif isinstance(value, np.ndarray) or isinstance(value, np.generic):
        a = np.ascontiguousarray(value)
        if a.dtype.kind in "OV":
            raise TypeError(f"cannot hash a {a.dtype} array")
        h.update(f"a{a.dtype.str}{a.shape}".encode())
        h.update(a.reshape(-1).view(np.uint8) if a.dtype.itemsize else a.tobytes())  # its bytes, not a copy of them
    elif isinstance(value, bool) or value is None:
        h.update(f"c{value!r}".encode())
    elif isinstance(value, int):
        h.update(f"i{value}".encode())
    elif isinstance(value, float):
        h.update(f"f{value!r}".encode() if math.isfinite(value) else f"f{value}".encode())
    elif isinstance(value, str):
        data = value.encode("utf-8")
        h.update(b"s%d:" % len(data) + data)
    elif isinstance(value, (bytes, bytearray)):
        h.update(b"b%d:" % len(value) + bytes(value))
    else:
        raise TypeError(f"cannot hash a {type(value).__name__}")


def check_hash(data: Mapping, stored: Any, where: str, what: str) -> None:
    """Raise :class:`InputError` unless ``stored`` is the :func:`content_hash` of ``data``."""
    if stored is None:
        raise InputError(f"{where}: this {what} has no content hash (written by an older kpd?); write it again")
    if isinstance(stored, np.ndarray):
        stored = str(stored)
    try:
        actual = content_hash(data)
    except TypeError as exc:
        raise InputError(f"{where}: this {what} holds a value kpd does not write ({exc})") from exc
    if actual != stored:
        raise InputError(f"{where}: this {what} is damaged: its content does not match its sha256 hash "
                         "(changed or corrupted after kpd wrote it)")


_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


def load_numpy(path: str | os.PathLike, what: str = "numpy file") -> Any:
    """Read a ``.npy`` array or every array of a ``.npz`` (a dict), without pickle, with one-line errors.

    An empty, truncated or non-numpy file, a zip with a bad CRC or a broken member, and pickled data each raise
    :class:`InputError` saying which.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a {what}")
    if not p.is_file():
        raise InputError(f"{p}: no such {what}")
    with open(p, "rb") as fh:
        head = fh.read(8)
    if not head:
        raise InputError(f"{p}: the file is empty; not a {what}")
    if head.startswith(_ZIP_MAGIC):
        try:
            with np.load(p, allow_pickle=False) as data:
                for info in data.zip.infolist():
                    _check_member(p, data.zip, info)
                return _members(data)
        except InputError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, KeyError, struct.error) as exc:
            raise InputError(f"{p}: damaged .npz (zip) file: {_reason(exc)}") from exc
        except (NotImplementedError, RuntimeError) as exc:  # a compression method or an encryption zipfile lacks
            raise InputError(f"{p}: damaged .npz (zip) file: {_reason(exc)}") from exc
        except ValueError as exc:
            if "pickle" in str(exc):
                raise InputError(f"{p}: the .npz holds pickled objects, which kpd never reads") from exc
            raise InputError(f"{p}: damaged .npz file: {exc}") from exc
    if head.startswith(_NPY_MAGIC):
        try:
            with open(p, "rb") as fh:
                _check_declared(p, fh, p.stat().st_size, "the file")
            return np.load(p, allow_pickle=False)
        except InputError:
            raise
        except ValueError as exc:
            if "pickle" in str(exc):
                raise InputError(f"{p}: the .npy holds pickled objects, which kpd never reads") from exc
            raise InputError(f"{p}: damaged .npy file: {exc}") from exc
        except (OSError, EOFError) as exc:
            raise InputError(f"{p}: damaged .npy file: {_reason(exc)}") from exc
    if head.startswith(b"\x80"):
        raise InputError(f"{p}: a Python pickle, which kpd never reads; not a {what}")
    kind = "a text file" if _is_text(p) else "neither a .npy nor a .npz file"
    raise InputError(f"{p}: {kind}, not a {what} (no numpy header)")


_PARALLEL_BYTES = 16 << 20
# a member this large that inflates more than _RATIO times is refused unread: kpd's own arrays (floats stored, indices
# and images deflated) stay far below, a member of zeros made to exhaust memory (a zip bomb) reaches about 1000
_RATIO, _RATIO_FLOOR = 100, 16 << 20


def _check_member(p: Path, archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """Refuse an .npz member before it is inflated: one that inflates more than :data:`_RATIO` times (beyond
    :data:`_RATIO_FLOOR` bytes), or whose .npy header declares another size than the member holds (numpy would take
    the memory the header declares first)."""
    if info.file_size > _RATIO_FLOOR and info.file_size > _RATIO * max(info.compress_size, 1):
        raise InputError(f"{p}: the member {info.filename} inflates {info.compress_size} bytes to {info.file_size}, "
                         f"more than {_RATIO} times (as a zip bomb does); it is not read")
    if not info.filename.endswith(".npy"):
        return
    with archive.open(info) as fh:
        _check_declared(p, fh, info.file_size, f"the member {info.filename}")


def _check_declared(p: Path, fh, size: int, what: str) -> None:
    """Raise unless the .npy at ``fh`` (its header next) declares an array of ``size`` bytes with its header."""
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise InputError(f"{p}: {what} is an .npy of version {version[0]}.{version[1]}, which kpd does not read")
    except (ValueError, EOFError) as exc:
        raise InputError(f"{p}: {what} has a damaged .npy header ({exc})") from exc
    if dtype.hasobject:
        return  # pickled objects: numpy refuses them, and load_numpy says so
    declared = math.prod(shape) * dtype.itemsize + fh.tell()
    if declared != size:
        raise InputError(f"{p}: {what} declares a {dtype} array of shape {tuple(shape)} ({declared} bytes with its "
                         f"header) but holds {size} bytes")



def _members(data) -> dict:
    """Every array of an open ``.npz`` in its order. A large file's members are read on two threads, the largest
    first (inflating and checking a member's CRC let go of the interpreter's lock): a 1.37M-vertex rig's 66 MB of
    deflated triangles beside its stored basis and vertices."""
    names = data.files
    sizes = {info.filename[:-4] if info.filename.endswith(".npy") else info.filename: info.file_size
             for info in data.zip.infolist()}
    if len(names) < 2 or sum(sizes.values()) < _PARALLEL_BYTES:
        return {k: data[k] for k in names}
    from concurrent.futures import ThreadPoolExecutor

    largest_first = sorted(names, key=lambda k: -sizes.get(k, 0))
    with ThreadPoolExecutor(2, thread_name_prefix="kpd-npz") as pool:
        read = dict(zip(largest_first, pool.map(data.__getitem__, largest_first)))
    return {k: read[k] for k in names}


def _is_text(p: Path) -> bool:
    with open(p, "rb") as fh:
        chunk = fh.read(4096)
    try:
        chunk.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return b"\0" not in chunk


def _reason(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if isinstance(exc, zipfile.BadZipFile) and "CRC" in text:
        return f"a member fails its CRC check ({text})"
    if isinstance(exc, EOFError) or "truncated" in text.lower() or "end of" in text.lower():
        return f"truncated ({text})"
    return text


def json_hash(data: Mapping) -> str:
    """:func:`content_hash` of JSON data as read back (floats and ints as JSON gives them)."""
    return content_hash(json.loads(json.dumps(data)))



def checkpoint_failure(path: str | os.PathLike, exc: BaseException) -> str:
    """Why ``torch.load(path, weights_only=True)`` failed, in one short clause, from the file itself and the
    exception (torch says ``101`` for a text file, nothing for an empty one, a paragraph for pickled objects).

    Parameters
    ----------
    path : the checkpoint file.
    exc : what ``torch.load`` raised.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            head = fh.read(64)
    except OSError as error:
        return error.strerror or str(error)
    if size == 0:
        return "the file is empty (0 bytes)"
    pickled = "Weights only load failed" in str(exc)
    objects = ("it holds pickled Python objects, which kpd never loads (they can run code); only tensors and "
               "plain data are read: save the state dicts alone with torch.save")
    if head.startswith(b"PK\x03\x04"):
        try:
            with zipfile.ZipFile(p) as archive:
                archive.namelist()
        except (zipfile.BadZipFile, OSError, ValueError):
            return f"the file is truncated or damaged ({size} bytes; its zip directory cannot be read)"
        return objects if pickled else f"a damaged PyTorch archive ({type(exc).__name__})"
    if head[:1] == b"\x80":
        return objects if pickled else f"the file is truncated or damaged ({size} bytes of an old-style PyTorch pickle)"
    if _is_text(p):  # before torch's verdict: it reads the first byte of a text file as a pickle opcode
        first = head.split(b"\n", 1)[0].decode("utf-8", "replace").strip()
        return f"a text file, not a PyTorch checkpoint (it starts with {first[:40]!r})"
    if pickled:
        return objects
    return "not a PyTorch checkpoint (neither a zip archive nor a pickle)"
