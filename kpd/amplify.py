"""Amplify a collection: variants of every mesh under a folder, drawn from the category prior (``kpd amplify``).

A run binds each source mesh once and writes ``variants`` deformations of it, each to keypoints drawn from the
model's prior around the source's own keypoints, plausible ones only (in the prior's typical range, folding at most
0.5% of the triangles: :mod:`kpd.variants`), in the source's format with its materials, UVs and textures,
sub-folders mirrored under the output folder. Its guarantees:

- **Reproducible.** Variant ``i`` of source ``s`` is drawn with the seed :func:`variant_seed` derives from ``--seed``,
  ``s``'s path relative to the collection and ``i``, and every shape is worked on with one thread (onnxruntime and
  BLAS), so a variant's bytes depend on the model, the source, the seed, the scale and its index only: never on the
  number of processes, the engine or the order of work.
- **All or nothing per shape.** A shape's files are written into a staging folder and placed together
  (:func:`kpd.io.atomic_files`); then its records are appended to ``manifest.jsonl`` in one write and fsynced. The
  manifest decides what is done: a shape whose records are missing is done again, and its stray files (placed before
  a kill) are replaced by the same bytes.
- **The same work everywhere.** :func:`amplify_shape` is the unit of work of the in-process run, of the local
  process pool and of Ray tasks; the driver alone appends records, as results come back.

The manifest holds, per variant: ``source`` (relative to the collection), ``variant``, ``file`` (relative to the output
folder), ``seed``, ``attempt`` and ``shrink`` (:func:`kpd.variants.draw_plausible` redraws it from them: attempt 0
is ``numpy.random.default_rng(seed)``), ``coefficients`` (the variant's keypoints in the prior's components),
``keypoints`` (K x 3, in the variant's own frame and units) and two plausibility measures:
``sigma`` (the largest ``|coefficient| / standard deviation``) and ``folded`` (the fraction of triangles whose normal
turned over against the source's); per shape that failed: ``source`` and ``error``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from kpd.errors import InputError, KpdError, WriteError
from kpd.variants import FOLDED_LIMIT, Folds, draw_plausible, typical

__all__ = ["CONFIG", "MANIFEST", "SHEET", "Drawn", "Job", "Manifest", "Settings", "ShapeResult", "Summary",
           "amplify", "amplify_shape", "draw_variant", "find_meshes", "folded_fraction", "output_names",
           "prepare_output", "ray_cluster", "ray_missing_message", "run_jobs", "sheet_rows", "variant_seed",
           "worker_model"]

log = logging.getLogger("kpd.amplify")

MANIFEST = "manifest.jsonl"
CONFIG = "amplify.json"
SHEET = "contact_sheet.png"
CONFIG_FORMAT = "kpd-amplify/1"


def ray_missing_message() -> str:
    return '--engine ray needs Ray, which is not installed: pip install "kpd[cluster]"'


@dataclasses.dataclass(frozen=True)
class Settings:
    """What a run's outputs depend on (written to ``amplify.json``; another run into the same folder must match).

    model : the bundle as named (a path or a shipped name); ``model_sha256`` identifies its contents.
    folder : the collection, absolute.
    variants, scale, seed : the draws (``scale``: standard deviations of the prior's components).
    scan, up : treat the sources as scans (``--scan``), with a known up axis.
    format : the variants' suffix (``.ply``), or None for each source's own.
    """

    model: str
    model_sha256: str
    folder: str
    variants: int
    scale: float
    seed: int
    scan: bool = False
    up: str | None = None
    format: str | None = None

    def to_dict(self) -> dict:
        return {"format_version": CONFIG_FORMAT, **dataclasses.asdict(self)}


class Job(NamedTuple):
    """One source shape to amplify: its path relative to ``Settings.folder``, the output folder (absolute) and its
    variants' file names relative to it."""

    source: str
    out: str
    names: tuple[str, ...]


class ShapeResult(NamedTuple):
    """What :func:`amplify_shape` returns: the shape's manifest records (its variants', or one with ``error``)."""

    source: str
    records: list[dict]

    @property
    def error(self) -> str | None:
        return self.records[0].get("error") if len(self.records) == 1 and "error" in self.records[0] else None


# --- the collection and its names ------------------------------------------------------------------------------


def find_meshes(folder: str | os.PathLike) -> list[str]:
    """The mesh files under ``folder`` (every sub-folder, every format :func:`kpd.io.read_mesh` reads; hidden names
    skipped), as sorted POSIX paths relative to it."""
    from kpd.io import MESH_FORMATS

    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{folder} is not a folder")
    found = []
    for where, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in files:
            if not name.startswith(".") and Path(name).suffix.lower() in MESH_FORMATS:
                found.append((Path(where) / name).relative_to(root).as_posix())
    return sorted(found)


def output_names(sources: Sequence[str], variants: int, suffix: str | None) -> dict[str, tuple[str, ...]]:
    """``{source: (file, ...)}``: variant ``i`` of ``a/b/chair.obj`` is ``a/b/chair_<i:03d>.obj`` (``suffix``: the
    variants' format, or None for the source's own). Sources whose names would collide (``chair.obj`` and
    ``chair.ply`` in one folder) keep their own suffix in the name (``chair_obj_000.obj``)."""
    def stem(source: str, full: bool) -> str:
        p = Path(source)
        name = f"{p.stem}_{p.suffix.lower().lstrip('.')}" if full else p.stem
        return (p.parent / name).as_posix() if p.parent != Path(".") else name

    counts: dict[str, int] = {}
    for source in sources:
        counts[stem(source, False)] = counts.get(stem(source, False), 0) + 1
    names = {}
    for source in sources:
        base = stem(source, counts[stem(source, False)] > 1)
        ext = suffix or Path(source).suffix.lower()
        names[source] = tuple(f"{base}_{i:03d}{ext}" for i in range(variants))
    return names


def variant_seed(seed: int, source: str, index: int) -> int:
    """The seed of variant ``index`` of ``source`` (a POSIX path relative to the collection): a 64-bit integer from
    :class:`numpy.random.SeedSequence` over ``seed``, the path's sha256 and ``index``, so that it is the same on any
    machine, in any order and in any process."""
    words = np.frombuffer(hashlib.sha256(source.encode("utf-8")).digest()[:16], dtype="<u4")
    state = np.random.SeedSequence([int(seed), *map(int, words), int(index)]).generate_state(2, np.uint32)
    return int(state[0]) | int(state[1]) << 32


# --- plausibility --------------------------------------------------------------------------------------------------


def folded_fraction(source: np.ndarray, variant: np.ndarray, triangles: np.ndarray) -> float:
    """The fraction of the source's non-degenerate triangles whose normal points against its own normal before the
    edit (a fold of the surface; :class:`kpd.variants.Folds`).

    Parameters
    ----------
    source, variant : (V, 3) float64 vertices before and after.
    triangles : (T, 3) int.
    """
    return Folds(source, triangles).fraction(variant)


# --- the unit of work ----------------------------------------------------------------------------------------------

_MODELS: dict[tuple[str, str], Any] = {}


def worker_model(settings: Settings):
    """The settings' model, loaded once per process with one onnxruntime thread (its results then do not depend on
    the thread count, so neither do the variants' bytes)."""
    key = (settings.model, settings.model_sha256)
    model = _MODELS.get(key)
    if model is None:
        from kpd.bundle import manifest_checksum
        from kpd.runtime import Model

        model = Model.load(settings.model, threads=1)
        if manifest_checksum(model.bundle.manifest) != settings.model_sha256:
            raise InputError(f"{settings.model}: this worker's bundle differs from the driver's (another version of "
                             "the model on this node)")
        _MODELS.clear()
        _MODELS[key] = model
    return model


def amplify_shape(settings: Settings, job: Job, *, check: Callable[[], None] | None = None) -> ShapeResult:
    """Bind one source and write its variants; returns its manifest records.

    A source that cannot be read or bound gives one record with ``error``; a failure to write (a full disk) raises
    :class:`~kpd.errors.WriteError`. The files are placed together, replacing any left by an unfinished run;
    ``check()``, called just before they are placed, may raise to place nothing (a worker whose driver is gone).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):  # BLAS sums in one order whatever the process count: the same bytes everywhere
        return _amplify_shape(settings, job, check)


def _amplify_shape(settings: Settings, job: Job, check: Callable[[], None] | None) -> ShapeResult:
    from kpd.frame import bind_shape
    from kpd.io import atomic_files, read_mesh, write_mesh

    model = worker_model(settings)
    path = Path(settings.folder) / job.source
    try:
        mesh = read_mesh(path)
        rig = bind_shape(model, mesh, scan=settings.scan, up=settings.up, path=path, seed=settings.seed)
    except (KpdError, OSError, ValueError) as exc:  # this shape only: the run goes on
        return ShapeResult(job.source, [{"source": job.source, "error": _one_line(exc)}])
    except MemoryError:
        return ShapeResult(job.source, [{"source": job.source, "error": "out of memory while binding"}])
    base = rig.normalizer.apply(rig.keypoints)  # (K, 3) in the model frame
    folds = Folds(mesh.vertices, mesh.triangles)
    out = Path(job.out)
    first = out / job.names[0]
    first.parent.mkdir(parents=True, exist_ok=True)
    records = []
    with atomic_files(first, force=True) as staged:
        for index, name in enumerate(job.names):
            variant = draw_variant(model.prior, rig, mesh, base, variant_seed(settings.seed, job.source, index),
                                   settings.scale, folds)
            write_mesh(staged.parent / Path(name).name, mesh.with_vertices(variant.vertices))
            records.append({"source": job.source, "variant": index, "file": name, **variant.record()})
        if check is not None:
            check()
    return ShapeResult(job.source, records)


class Drawn(NamedTuple):
    """One variant of a bound source (:func:`draw_variant`).

    vertices : (V, 3) float64, the deformed mesh; keypoints : (K, 3) float64, its keypoints (source frame and units);
    seed : the variant's seed; draw : the :class:`kpd.variants.Plausible` draw (model frame, its measures).
    """

    vertices: np.ndarray
    keypoints: np.ndarray
    seed: int
    draw: Any

    def record(self) -> dict:
        """The manifest's fields of the variant: ``seed``, ``attempt`` and ``shrink`` redraw it
        (:func:`kpd.variants.draw_plausible`); ``keypoints`` are its labels."""
        d = self.draw
        return {"seed": self.seed, "attempt": d.attempt, "shrink": d.shrink, "coefficients": d.coefficients.tolist(),
                "keypoints": self.keypoints.tolist(), "sigma": d.sigma, "folded": d.folded}


def draw_variant(prior, rig, mesh, base: np.ndarray, seed: int, scale: float, folds=None) -> Drawn:
    """A plausible variant of a bound source (:func:`kpd.variants.draw_plausible`), deformed by its rig.

    Parameters
    ----------
    rig : the source's :class:`kpd.rig.Rig` (or a rig seen in the source's frame); mesh : the source mesh.
    base : (K, 3) the rig's keypoints in the model frame (``rig.normalizer.apply(rig.keypoints)``).
    folds : the source's :class:`kpd.variants.Folds` (made when None; pass one to draw several variants).
    """
    folds = Folds(mesh.vertices, mesh.triangles) if folds is None else folds

    def deform(keypoints: np.ndarray) -> tuple[np.ndarray, float]:
        vertices = rig.deform(rig.normalizer.invert(keypoints))
        return vertices, folds.fraction(vertices)

    draw = draw_plausible(prior, base, scale, seed, deform)
    return Drawn(draw.deformed, rig.normalizer.invert(draw.keypoints), seed, draw)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


# --- the output folder ---------------------------------------------------------------------------------------------


def prepare_output(out: str | os.PathLike, settings: Settings, *, force: bool = False, check_only: bool = False
                   ) -> Path:
    """Check the output folder and make it ready: a new folder, or the folder of an earlier run of the same settings
    (continued); another run's folder or any other folder only with ``force`` (then emptied). It may neither hold the
    collection nor lie inside it. Temporaries of killed runs are removed. ``check_only``: refuse what would be refused,
    change nothing.

    Returns
    -------
    out : the folder, absolute.
    """
    from kpd.io import atomic_output
    from kpd.io.atomic import check_folder_writable, remove_stale_temporaries

    out = Path(out).absolute()
    folder = Path(settings.folder).resolve()
    resolved = out.resolve()
    if resolved == folder or folder in resolved.parents:
        raise InputError(f"--out {out} lies inside the collection {settings.folder}; choose a folder outside it")
    if resolved in folder.parents:
        raise InputError(f"--out {out} holds the collection {settings.folder}; choose another folder")
    model = Path(settings.model)
    if model.exists() and (model.resolve() == resolved or resolved in model.resolve().parents):
        raise InputError(f"--out {out} holds the model {settings.model}; choose another folder")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file; kpd amplify writes a folder")
    check_folder_writable(out.parent, f"--out {out}")
    config = out / CONFIG
    wanted = settings.to_dict()
    if out.exists():
        found = _read_config(config)
        if found is None and any(not e.name.startswith(".") for e in os.scandir(out)) and not force:
            raise InputError(f"--out {out} exists and is not the folder of a kpd amplify run; pass --force to replace "
                             "it")
        if found is not None and found != wanted and not force:
            differ = sorted(k for k in wanted if found.get(k) != wanted[k])
            raise InputError(f"--out {out} holds a run with other settings ({', '.join(differ)}); run the same "
                             "command to continue it, or pass --force to replace it")
        if force and not check_only:
            _empty(out)
    if check_only:
        return out
    out.mkdir(exist_ok=True)
    check_folder_writable(out, f"--out {out}")
    for where, dirs, _ in os.walk(out):
        remove_stale_temporaries(where)
        dirs[:] = [d for d in dirs if (Path(where) / d).exists()]
    if _read_config(config) != wanted:
        with atomic_output(config) as tmp:
            tmp.write_text(json.dumps(wanted, indent=1) + "\n")
    return out


def _read_config(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format_version") == CONFIG_FORMAT else None


def _empty(folder: Path) -> None:
    for entry in os.scandir(folder):
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path)
        else:
            os.unlink(entry.path)


class _Entry(NamedTuple):
    """What the driver keeps of one finished shape (a thousandth of its records' size, so that a manifest of
    hundreds of thousands of variants is not held in memory). ``lines``: (n, 3) int64 rows of ``(variant, offset,
    length)`` of its lines in the file; ``measures``: (n, 2) float64 rows of ``(sigma, folded)``, empty for a shape
    that failed; ``error``: its error, or None."""

    lines: np.ndarray
    measures: np.ndarray
    error: str | None


class Manifest:
    """``manifest.jsonl`` of an output folder: the records of finished shapes, appended one shape at a time.

    Reading drops what a killed run left unfinished (a last line cut short, a shape with only some of its records):
    such a shape counts as not done. Only an index of each shape's lines and its two plausibility measures stay in
    memory; records are read back from the file when asked for (:meth:`read`).
    """

    def __init__(self, out: str | os.PathLike, variants: int) -> None:
        self.path = Path(out) / MANIFEST
        self.variants = variants
        self._entries: dict[str, _Entry] = {}
        self._load()

    def _load(self) -> None:
        try:
            file = open(self.path, "rb")
        except FileNotFoundError:
            return
        grouped: dict[str, list[tuple[int, int, int, float, float, str | None]]] = {}
        clean, offset, order = True, 0, []
        with file:
            for line in file:
                start, offset = offset, offset + len(line)
                if not line.endswith(b"\n"):
                    clean = False  # the last line, cut short by a kill
                    continue
                if not line.strip():
                    continue
                fields = _fields(line)
                if fields is None:
                    clean = False
                    continue
                source, variant, sigma, folded, error = fields
                if source not in grouped:
                    order.append(source)
                grouped.setdefault(source, []).append((variant, start, len(line), sigma, folded, error))
        for source, rows in grouped.items():
            entry = self._entry(rows)
            if entry is None:
                clean = False
            else:
                self._entries[source] = entry
        if not clean:  # rewritten with the finished shapes only, so that appends start on a line of their own
            self._rewrite(order)

    def _entry(self, rows: list) -> _Entry | None:
        """The shape's entry from its lines' ``(variant, offset, length, sigma, folded, error)``, or None when its
        records are incomplete."""
        if len(rows) == 1 and rows[0][5] is not None:
            return _Entry(np.array([[-1, rows[0][1], rows[0][2]]], dtype=np.int64), np.empty((0, 2)), rows[0][5])
        rows = sorted(rows)
        if [r[0] for r in rows] != list(range(self.variants)) or any(r[5] is not None for r in rows):
            return None
        return _Entry(np.array([r[:3] for r in rows], dtype=np.int64), np.array([r[3:5] for r in rows],
                                                                                 dtype=np.float64), None)

    def _rewrite(self, order: Sequence[str]) -> None:
        """Write the file again with the finished shapes' lines, in ``order`` (the sources to keep first, as listed;
        the rest after, sorted), copied from the old file a shape at a time."""
        from kpd.io import atomic_output

        listed = [s for s in order if s in self._entries]
        sources = listed + sorted(set(self._entries) - set(listed))
        entries = {}
        with atomic_output(self.path) as tmp, open(self.path, "rb") as old, open(tmp, "wb") as new:
            offset = 0
            for source in sources:
                lines = self._entries[source].lines
                moved = lines.copy()
                for i, (_, start, length) in enumerate(lines):
                    old.seek(start)
                    data = old.read(length)
                    new.write(data)
                    moved[i, 1] = offset
                    offset += length
                entries[source] = self._entries[source]._replace(lines=moved)
        self._entries = entries

    def done(self) -> set[str]:
        return set(self._entries)

    def append(self, result: ShapeResult) -> None:
        """Append one shape's records in one write and fsync them: after this the shape is done."""
        records = sorted(result.records, key=lambda r: r.get("variant", -1))
        lines = [(json.dumps(r) + "\n").encode() for r in records]
        data = b"".join(lines)
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            start = os.fstat(fd).st_size  # the driver alone appends: its lines begin here
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        except OSError as exc:
            from kpd.io.atomic import describe_os_error

            raise WriteError(describe_os_error(exc, self.path)) from exc
        finally:
            os.close(fd)
        rows, offset = [], start
        for record, line in zip(records, lines):
            rows.append((record.get("variant", -1), offset, len(line), record.get("sigma", 0.0),
                         record.get("folded", 0.0), record.get("error")))
            offset += len(line)
        self._entries[result.source] = self._entry(rows)

    def read(self, source: str) -> list[dict]:
        """The records of a finished shape, read back from the file (sorted by variant)."""
        with open(self.path, "rb") as file:
            records = []
            for _, start, length in self._entries[source].lines:
                file.seek(start)
                records.append(json.loads(file.read(length)))
        return records

    def measures(self, sources: Sequence[str]) -> tuple[np.ndarray, list[tuple[str, str]]]:
        """Over the finished ones of ``sources``: their variants' ``(sigma, folded)`` (n, 2), and the failures
        ``(source, error)``, sorted."""
        entries = [(s, self._entries[s]) for s in sources if s in self._entries]
        failures = sorted((s, e.error) for s, e in entries if e.error is not None)
        found = [e.measures for _, e in entries if e.error is None]
        return (np.concatenate(found) if found else np.empty((0, 2))), failures

    def error(self, source: str) -> str | None:
        return self._entries[source].error

    def finish(self) -> None:
        """Rewrite the manifest sorted by source and variant, so that a finished run's manifest is the same file
        whatever the order of work (left as it is when it already is)."""
        sources = sorted(self._entries)
        offsets = [self._entries[s].lines[:, 1] for s in sources]  # each shape's lines by variant
        if not sources or np.all(np.diff(np.concatenate(offsets)) > 0):  # the file is in that order already
            return
        self._rewrite(sources)


def _fields(line: bytes) -> tuple[str, int, float, float, str | None] | None:
    """``(source, variant, sigma, folded, error)`` of one manifest line, or None when it is not a record."""
    try:
        record = json.loads(line)
    except ValueError:
        return None
    if not isinstance(record, dict) or not isinstance(record.get("source"), str):
        return None
    error = record.get("error")
    if error is not None:
        return record["source"], -1, 0.0, 0.0, str(error)
    variant, sigma, folded = record.get("variant"), record.get("sigma"), record.get("folded")
    if isinstance(variant, bool) or not isinstance(variant, int) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in (sigma, folded)):
        return None
    return record["source"], variant, float(sigma), float(folded), None


# --- engines -------------------------------------------------------------------------------------------------------


def run_jobs(settings: Settings, jobs: Sequence[Job], on_result: Callable[[ShapeResult], None], *,
             engine: str = "local", processes: int = 1, ray_address: str | None = None) -> None:
    """Run :func:`amplify_shape` on every job and hand each result to ``on_result`` (on this thread, as they come).

    Parameters
    ----------
    engine : ``"local"`` (this process when ``processes`` is 1, else a pool of that many processes) or ``"ray"``
        (tasks on the cluster at ``ray_address``, or on a local one of ``processes`` workers).
    """
    if not jobs:
        return
    if engine == "ray":
        _run_ray(settings, jobs, on_result, processes, ray_address)
    elif processes <= 1:
        for job in jobs:
            on_result(amplify_shape(settings, job))
    else:
        _run_pool(settings, jobs, on_result, processes)


def _orphan_check(parent: int) -> Callable[[], None]:
    def check() -> None:
        if os.getppid() != parent:  # the driver was killed: its successor will do this shape
            raise SystemExit(1)

    return check


def _pool_shape(settings: Settings, job: Job, parent: int) -> ShapeResult:
    return amplify_shape(settings, job, check=_orphan_check(parent))


def _run_pool(settings: Settings, jobs: Sequence[Job], on_result, processes: int) -> None:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    # spawned, not forked: a fork would copy this process's onnxruntime and numba threads' state mid-flight
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(processes, mp_context=context) as pool:
        queue = iter(jobs)
        pending = set()
        try:
            for job in queue:  # a bounded window, so that a stop does not wait for thousands of queued shapes
                pending.add(pool.submit(_pool_shape, settings, job, os.getpid()))
                if len(pending) >= 2 * processes:
                    break
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    on_result(future.result())
                    job = next(queue, None)
                    if job is not None:
                        pending.add(pool.submit(_pool_shape, settings, job, os.getpid()))
        except BaseException:
            for future in pending:
                future.cancel()
            raise


def _ray_shape(settings: Settings, job: Job) -> ShapeResult:
    return amplify_shape(settings, job)


@contextlib.contextmanager
def ray_cluster(processes: int = 1, address: str | None = None) -> Iterator[Any]:
    """Ray ready for tasks (yields the ``ray`` module): connected to the cluster at ``address`` or, without one, a
    local cluster of ``processes`` workers, shut down after; a Ray this process already started is used as it is.
    A missing Ray or an unreachable cluster is one :class:`~kpd.errors.InputError`."""
    try:
        import ray
    except ImportError:
        raise InputError(ray_missing_message()) from None
    if ray.is_initialized():
        yield ray
        return
    try:
        if address:
            _check_reachable(address)
            ray.init(address=address, logging_level=logging.ERROR, log_to_driver=False)
        else:
            ray.init(num_cpus=processes, include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise InputError(f"cannot start Ray on {address or 'a local cluster'}: {_one_line(exc)}") from exc
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_reachable(address: str) -> None:
    """Fail at once when a ``HOST:PORT`` (or ``ray://HOST:PORT``) cluster does not answer: ``ray.init`` would retry
    for minutes."""
    import socket

    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        return  # "auto", or an address Ray resolves itself
    try:
        socket.create_connection((host, int(port)), timeout=10).close()
    except OSError as exc:
        raise InputError(f"cannot reach the Ray cluster at {address}: {exc.strerror or exc}") from exc


def _run_ray(settings: Settings, jobs: Sequence[Job], on_result, processes: int, address: str | None) -> None:
    with ray_cluster(processes, address) as ray:
        # a task whose worker dies (a node lost, a process killed) is run again; its shape's files are placed by
        # the task and its records appended here, so that a retry replaces nothing finished
        task = ray.remote(num_cpus=1, max_retries=3)(_ray_shape)
        window = 2 * max(1, int(ray.cluster_resources().get("CPU", processes)))
        queue = iter(jobs)
        pending: dict[Any, Job] = {}

        def submit() -> None:
            job = next(queue, None)
            if job is not None:
                pending[task.remote(settings, job)] = job

        for _ in range(window):
            submit()
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                job = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as exc:  # retries spent: this shape failed, the others go on
                    result = ShapeResult(job.source, [{"source": job.source, "error": _ray_error(exc)}])
                on_result(result)
                submit()


def _ray_error(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, KpdError):
        raise cause  # a write failed on the node: the run stops as a local one would
    first = str(exc).strip().splitlines()
    return f"Ray task failed: {first[0] if first else type(exc).__name__}"


# --- a run ---------------------------------------------------------------------------------------------------------


class Summary(NamedTuple):
    """A run's outcome. ``shapes``: in the collection; ``done``: amplified (this run or an earlier one);
    ``failed``: sources with an error; ``new``: shapes worked on by this run; ``variants``: written in all;
    ``typical``: the fraction of variants within the prior's typical range (:mod:`kpd.variants`); ``folded_max``:
    the largest folded fraction; ``folded_ok``: the fraction of variants with at most ``FOLDED_LIMIT`` folded;
    ``seconds``: this run's time."""

    shapes: int
    done: int
    failed: int
    new: int
    variants: int
    typical: float
    folded_max: float
    folded_ok: float
    seconds: float
    failures: list[tuple[str, str]]


def amplify(settings: Settings, out: str | os.PathLike, *, engine: str = "local", processes: int = 1,
            ray_address: str | None = None, force: bool = False, model: Any = None,
            on_start: Callable[[int, int], None] | None = None,
            on_result: Callable[[ShapeResult], None] | None = None) -> Summary:
    """Amplify the collection of ``settings`` into ``out`` (see the module notes), continuing an earlier run there.

    Parameters
    ----------
    model : the settings' model already loaded with ``threads=1``, for the work done in this process (else it is
        loaded where the work runs).
    on_start : called with (shapes to do, shapes already done) before the work.
    on_result : called with each shape's result once its records are in the manifest.
    """
    start = time.perf_counter()
    sources = find_meshes(settings.folder)
    if not sources:
        from kpd.io import MESH_FORMATS

        raise InputError(f"no mesh files ({' '.join(MESH_FORMATS)}) under {settings.folder}")
    prepare_output(out, settings, force=force, check_only=True)
    # Ray before the output folder is made: a cluster that cannot be reached leaves none behind
    with ray_cluster(processes, ray_address) if engine == "ray" else contextlib.nullcontext():
        return _amplify(settings, out, sources, engine, processes, ray_address, force, model, on_start, on_result,
                        start)


def _amplify(settings, out, sources, engine, processes, ray_address, force, model, on_start, on_result, start):
    from kpd.io.atomic import remove_stale_temporaries

    out = prepare_output(out, settings, force=force)
    if model is not None:
        _MODELS.clear()
        _MODELS[(settings.model, settings.model_sha256)] = model
    names = output_names(sources, settings.variants, settings.format)
    manifest = Manifest(out, settings.variants)
    done = manifest.done()
    jobs = [Job(s, str(out), names[s]) for s in sources if s not in done]
    if on_start is not None:
        on_start(len(jobs), len(sources) - len(jobs))

    def commit(result: ShapeResult) -> None:
        manifest.append(result)
        if on_result is not None:
            on_result(result)

    run_jobs(settings, jobs, commit, engine=engine, processes=processes, ray_address=ray_address)
    manifest.finish()
    for where, _, _ in os.walk(out):
        remove_stale_temporaries(where)
    return _summary(manifest, sources, len(jobs), time.perf_counter() - start)


def _summary(manifest: Manifest, sources: Sequence[str], new: int, seconds: float) -> Summary:
    measures, failures = manifest.measures(sources)
    sigma, folded = measures[:, 0], measures[:, 1]
    return Summary(shapes=len(sources), done=len(set(sources) & manifest.done()), failed=len(failures), new=new,
                   variants=len(measures), typical=float(typical(sigma).mean()) if len(sigma) else 1.0,
                   folded_max=float(folded.max(initial=0.0)),
                   folded_ok=float((folded <= FOLDED_LIMIT).mean()) if len(folded) else 1.0,
                   seconds=seconds, failures=failures)


def sheet_rows(manifest: Manifest, *, rows: int = 4, columns: int = 5) -> list[tuple[str, list[str], list[Any]]]:
    """The contact sheet's rows: for the first ``rows`` amplified sources (sorted), ``(source, files, keypoints)``:
    its first ``columns - 1`` variants' files (relative to the output folder) and keypoints (K, 3)."""
    picked = []
    for source in sorted(manifest.done()):
        if manifest.error(source) is not None:
            continue
        records = manifest.read(source)[:max(columns - 1, 0)]
        picked.append((source, [r["file"] for r in records], [np.asarray(r["keypoints"]) for r in records]))
        if len(picked) >= rows:
            break
    return picked

