"""Variants of a collection's shapes drawn inside a training loop, without torch: :class:`Augmenter`.

A collection is bound once (:meth:`Augmenter.build`: each mesh's rig, and a fixed sample of points on its surface) into
a cache folder of plain ``.npy`` arrays, which :class:`Augmenter` maps into memory (``np.load(mmap_mode="r")``): a
thousand cached rigs cost the pages a loop touches, shared by every data-loader worker on the machine. Each draw takes
keypoints from the model's category prior around the shape's own and moves the points or the mesh vertices with the
rig's linear edit basis, ``rest + basis @ (keypoints - rest keypoints)``: microseconds of arithmetic. Draws are
plausible as ``kpd amplify``'s are (:mod:`kpd.variants`: in the prior's typical range, the mesh folding at most 0.5% of
its triangles, drawn again when it folds more), and a point draw is checked on the mesh it lies on, so the points and
the mesh of one draw agree. A draw is seeded per call by ``(seed, index)``, so that the same call in any worker, in
any order, gives the same variant.

The cache folder holds ``index.json`` (the format, the model's checksum, the prior, the settings and one entry per
bound shape) and a folder per shape with ``vertices.npy`` (V, 3), ``triangles.npy`` (T, 3), ``basis.npy`` (V, K),
``keypoints.npy`` (K, 3, the model frame), ``faces.npy`` (N,), ``barycentric.npy`` (N, 3), ``points.npy`` (N, 3) and
``points_basis.npy`` (N, K), and the source's triangles with an area and their normals for the fold count
(``fold_triangles.npy`` (T', 3), ``fold_normals.npy`` (T', 3)). A point on a triangle moves with the triangle's
corners: its basis row is the barycentric mix of theirs, so a drawn point set lies exactly on the drawn mesh.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from kpd.errors import InputError, KpdError
from kpd.prior import KeypointPrior

__all__ = ["CACHE_FORMAT", "Augmenter", "Variant"]

log = logging.getLogger("kpd.augment")

CACHE_FORMAT = "kpd-augment/2"
INDEX = "index.json"
BUILDING = "build.json"  # the settings of a build not finished yet
ENTRY = "entry.json"  # a shape's entry of the index, beside its arrays
_ARRAYS = ("vertices", "triangles", "basis", "keypoints", "faces", "barycentric", "points", "points_basis",
           "fold_triangles", "fold_normals")


class Variant(NamedTuple):
    """One draw.

    points : (N, 3) float64 surface points, or (V, 3) mesh vertices (:meth:`Augmenter.mesh`), in the shape's units.
    keypoints : (K, 3) float64, the variant's keypoints in the shape's units (its labels).
    coefficients : (M,) float64, the variant's keypoints in the prior's components.
    """

    points: np.ndarray
    keypoints: np.ndarray
    coefficients: np.ndarray


class Augmenter:
    """Random plausible variants of the shapes of a bound collection (see the module notes).

    Parameters
    ----------
    cache : a folder written by :meth:`build`.
    scale : standard deviations of the prior's components in a draw (0.5: as ``kpd sample`` and ``kpd amplify``).

    Example
    -------
    >>> aug = Augmenter.build("chair", sorted(Path("chairs").glob("*.off")), "chairs.cache")   # doctest: +SKIP
    >>> variant = aug.points(3, seed=(epoch, 3))     # (2048, 3) points, (K, 3) keypoints   # doctest: +SKIP
    """

    def __init__(self, cache: str | os.PathLike, *, scale: float = 0.5) -> None:
        if not (np.isfinite(scale) and scale >= 0):
            raise InputError(f"scale must be a non-negative number; got {scale!r}")
        self.cache = Path(cache)
        self.scale = float(scale)
        index = _read_index(self.cache)
        if index is None:
            raise InputError(f"{self.cache}: not an augmenter cache (no {INDEX} of {CACHE_FORMAT}; make one with "
                             "Augmenter.build)")
        self._index = index
        self.prior = KeypointPrior.from_dict(index["prior"])
        self._entries = [_checked_entry(self.cache, e) for e in index["shapes"]]
        self._open: dict[int, dict[str, np.ndarray]] = {}

    # --- building -------------------------------------------------------------------------------------------------

    @classmethod
    def build(cls, model: Any, shapes: Iterable[str | os.PathLike], cache: str | os.PathLike, *, points: int = 2048,
              seed: int = 0, scale: float = 0.5, scan: bool = False, up: str | None = None, processes: int = 1,
              progress: Any = None) -> Augmenter:
        """Bind every shape once and cache what draws need; a cache of the same model, shapes and settings is
        reused as it is, and a build of them that was stopped (killed, a full disk) continues where it stopped.

        Parameters
        ----------
        model : a :class:`kpd.runtime.Model` with a prior, or a bundle path or shipped name.
        shapes : mesh files; one that cannot be read or bound is left out with a logged warning.
        cache : the folder to write (created; an existing cache of other shapes or settings is replaced).
        points : surface points per shape for :meth:`points`.
        seed : the binding's and the surface sample's seed.
        scan, up : the shapes are scans in frames of their own (``--scan``, ``--up`` of the commands): each is
            oriented into the model's frame to be bound (``up``: its up axis when known; a glTF's is y), and its draws
            are in its own frame and units.
        processes : shapes bound at once, each in a worker process of its own (one onnxruntime thread each; spawned,
            so a script that builds with more than one needs Python's ``if __name__ == "__main__":`` guard).
        progress : optional callable ``progress(path, error_or_None)`` after each shape.

        Each shape's arrays and its entry are placed in its folder together, so a stopped build keeps the shapes it
        finished; ``index.json`` is written last, and only its presence makes the folder a cache.
        """
        from kpd.bundle import manifest_checksum
        from kpd.io import atomic_output
        from kpd.runtime import Model

        if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 1:
            raise InputError(f"points must be a positive integer; got {points!r}")
        if isinstance(processes, bool) or not isinstance(processes, (int, np.integer)) or processes < 1:
            raise InputError(f"processes must be a positive integer; got {processes!r}")
        if up is not None and not scan:
            raise InputError("up is the up axis of scans: pass scan=True with it")
        model = model if isinstance(model, Model) else Model.load(model)
        if model.prior is None:
            raise InputError("this model has no category prior to draw variants from")
        cache = Path(cache)
        sources = [str(p) for p in shapes]
        settings = {"format": CACHE_FORMAT, "model": manifest_checksum(model.bundle.manifest), "points": int(points),
                    "seed": int(seed), "scan": bool(scan), "up": up, "sources": sources}
        index = _read_index(cache)
        if index is not None and {k: index.get(k) for k in settings} == settings:
            return cls(cache, scale=scale)
        if cache.exists() and _read_json(cache / BUILDING) != settings:
            if index is None and _read_json(cache / BUILDING) is None and any(cache.iterdir()):
                raise InputError(f"{cache} exists and is not an augmenter cache; choose another folder")
            shutil.rmtree(cache)  # another cache, or another build's start: replaced
        if not cache.exists():
            cache.mkdir(parents=True)
            with atomic_output(cache / BUILDING) as tmp:  # what a stopped build was, so that the same one continues
                tmp.write_text(json.dumps(settings) + "\n")
        work = _Work(model if processes == 1 else str(model.bundle.path), int(points), int(seed), bool(scan), up)
        entries, failed = _bind_all(work, sources, cache, int(processes), progress)
        if not entries:
            raise InputError("no shape could be bound for the augmenter (see the warnings)")
        index = {**settings, "prior": model.prior.to_dict(), "shapes": entries, "failed": failed}
        with atomic_output(cache / INDEX) as tmp:  # last: its presence says the cache is whole
            tmp.write_text(json.dumps(index) + "\n")
        (cache / BUILDING).unlink()
        return cls(cache, scale=scale)

    # --- drawing --------------------------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def sources(self) -> list[str]:
        """The bound shapes' paths, in index order."""
        return [e["source"] for e in self._entries]

    @property
    def failed(self) -> list[dict]:
        """The shapes left out (``source``, ``error``)."""
        return list(self._index.get("failed", []))

    def arrays(self, index: int) -> dict[str, np.ndarray]:
        """Shape ``index``'s cached arrays (read-only, memory-mapped): see the module notes."""
        index = self._check_index(index)
        arrays = self._open.get(index)
        if arrays is None:
            folder = self.cache / self._entries[index]["key"]
            try:
                arrays = {name: np.load(folder / f"{name}.npy", mmap_mode="r", allow_pickle=False) for name in _ARRAYS}
            except (OSError, ValueError) as exc:
                raise InputError(f"{folder}: a damaged augmenter cache entry ({exc}); build the cache again") from exc
            problem = _array_problem(arrays, self.prior.num_keypoints)
            if problem:
                raise InputError(f"{folder}: a damaged augmenter cache entry ({problem}); build the cache again")
            self._open[index] = arrays
        return arrays

    def triangles(self, index: int) -> np.ndarray:
        """(T, 3) int: shape ``index``'s triangles (those of :meth:`mesh`'s vertices)."""
        return self.arrays(index)["triangles"]

    def draw_keypoints(self, index: int, seed: int | Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """``(keypoints (K, 3), coefficients (M,))`` of the draw ``(seed, index)``, in shape ``index``'s units: the
        keypoints :meth:`points` and :meth:`mesh` move to."""
        keypoints, _, draw = self._plausible(index, seed)
        return keypoints, draw.coefficients

    def points(self, index: int, seed: int | Sequence[int]) -> Variant:
        """A variant of shape ``index``'s cached surface points (N, 3), drawn with ``(seed, index)``."""
        keypoints, offsets, draw = self._plausible(index, seed)
        arrays = self.arrays(index)
        moved = arrays["points_basis"] @ offsets  # (N, 3)
        moved += arrays["points"]
        return Variant(moved, keypoints, draw.coefficients)

    def mesh(self, index: int, seed: int | Sequence[int]) -> Variant:
        """A variant of shape ``index``'s mesh vertices (V, 3) (triangles: :meth:`triangles`), drawn with
        ``(seed, index)``: the vertices ``Rig.deform`` gives for its keypoints."""
        keypoints, _, draw = self._plausible(index, seed)
        return Variant(draw.deformed, keypoints, draw.coefficients)

    def _plausible(self, index: int, seed: int | Sequence[int]) -> tuple[np.ndarray, np.ndarray, Any]:
        """The draw ``(seed, index)``: ``(keypoints (K, 3) in the shape's units, their offsets from its own (K, 3),
        the :class:`kpd.variants.Plausible` draw whose ``deformed`` are the mesh's vertices)``."""
        from kpd.variants import Folds, draw_plausible

        index = self._check_index(index)
        words = _seed_words(seed)
        arrays = self.arrays(index)
        entry = self._entries[index]
        to_shape = np.asarray(entry["to_shape"])  # (3, 4): the model frame -> the shape's frame and units
        linear, origin = to_shape[:, :3], to_shape[:, 3]
        base = np.asarray(arrays["keypoints"])  # (K, 3) model frame
        folds = Folds.kept(arrays["fold_triangles"], arrays["fold_normals"])

        def deform(drawn: np.ndarray) -> tuple[np.ndarray, float]:
            moved = arrays["basis"] @ ((drawn - base) @ linear.T)  # (V, 3) float64 (a float32 basis is widened)
            moved += arrays["vertices"]
            return moved, folds.fraction(moved)

        draw = draw_plausible(self.prior, base, self.scale, [*words, index], deform)
        keypoints = draw.keypoints @ linear.T + origin
        return keypoints, (draw.keypoints - base) @ linear.T, draw

    def _check_index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not -len(self) <= index < len(self):
            raise InputError(f"shape index must be an integer in [0, {len(self)}); got {index!r}")
        return int(index) % len(self)

    # --- pickling (data-loader workers) ---------------------------------------------------------------------------

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_open"] = {}  # each worker maps the files itself
        return state

    def __repr__(self) -> str:
        return f"Augmenter({len(self)} shapes, K={self.prior.num_keypoints}, scale={self.scale:g}, cache={self.cache})"


class _Work(NamedTuple):
    """What binding one shape for a cache needs: the model (loaded, or a bundle path a worker loads once), the point
    count, the seed and the frame (``scan``, ``up``)."""

    model: Any
    points: int
    seed: int
    scan: bool
    up: str | None


def _bind_all(work: _Work, sources: list[str], cache: Path, processes: int, progress: Any
              ) -> tuple[list[dict], list[dict]]:
    """Bind and cache every source not cached yet, ``processes`` at a time (see :meth:`Augmenter.build`); returns
    the entries of the index (in the sources' order) and the failures."""
    from kpd.io.atomic import remove_stale_temporaries

    results: dict[int, dict] = {}
    todo = []
    remove_stale_temporaries(cache)
    for i, source in enumerate(sources):
        done = _read_json(cache / _key(i) / ENTRY)
        if isinstance(done, dict) and done.get("source") == source:
            results[i] = done
        else:
            remove_stale_temporaries(cache / _key(i))  # what a killed build was writing there
            todo.append(i)

    def finish(i: int, result: dict) -> None:
        results[i] = result
        if progress is not None:
            progress(sources[i], result.get("error"))

    if processes == 1 or len(todo) < 2:
        for i in todo:
            finish(i, _bind_one(work, sources[i], cache / _key(i)))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawned, not forked: a fork would copy this process's onnxruntime and numba threads' state mid-flight
        with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")) as pool:
            from concurrent.futures.process import BrokenProcessPool

            try:
                futures = {pool.submit(_bind_one, work, sources[i], cache / _key(i)): i for i in todo}
                for future in as_completed(futures):
                    finish(futures[future], future.result())
            except BrokenProcessPool:
                raise InputError("a binding process ended abruptly (killed, out of memory, or started from a script "
                                 "without the if __name__ == '__main__': guard that spawned processes need); the "
                                 "shapes finished are kept: build again to continue") from None
    entries = [results[i] for i in range(len(sources)) if "error" not in results[i]]
    failed = [results[i] for i in range(len(sources)) if "error" in results[i]]
    return entries, failed


def _key(i: int) -> str:
    return f"{i:06d}"


_MODELS: dict[str, Any] = {}


def _bind_one(work: _Work, source: str, folder: Path) -> dict:
    """Bind one source and place its arrays and entry in ``folder`` together; returns its entry, or
    ``{"source", "error"}`` when it cannot be read or bound (a failure to write raises)."""
    from kpd.frame import bind_shape
    from kpd.geometry import sample_surface
    from kpd.io import atomic_files, read_mesh
    from kpd.variants import Folds

    model = work.model
    if isinstance(model, str):  # a worker process: the bundle loaded once, with one thread (the cores are its pool's)
        if model not in _MODELS:
            from kpd.runtime import Model

            _MODELS[model] = Model.load(model, threads=1)
        model = _MODELS[model]
    try:
        mesh = read_mesh(source)
        rig = bind_shape(model, mesh, scan=work.scan, up=work.up, path=source, seed=work.seed)
        sample = sample_surface(mesh.vertices, mesh.triangles, work.points, seed=work.seed)
    except (KpdError, OSError, ValueError) as exc:
        error = " ".join(str(exc).split())
        log.warning("%s: left out of the augmenter: %s", source, error)
        return {"source": source, "error": error}
    triangles = np.asarray(mesh.triangles)
    corners = triangles[sample.faces]  # (N, 3) vertex indices
    weights = _barycentric(sample.points, mesh.vertices[corners])  # (N, 3)
    # a scan's rig is bound in the model's orientation; its basis is the same in the scan's frame (the frames differ
    # by a linear map, which commutes with the basis' mixing of keypoint offsets)
    basis = np.ascontiguousarray(getattr(rig, "aligned", rig).basis)  # (V, K)
    arrays = {
        "vertices": np.ascontiguousarray(mesh.vertices, dtype=np.float64),
        "triangles": triangles.astype(np.int32 if len(mesh.vertices) < 2**31 else np.int64),
        "basis": basis,
        "keypoints": rig.normalizer.apply(rig.keypoints),
        "faces": sample.faces.astype(np.int64),
        "barycentric": weights,
        "points": np.einsum("nj,njd->nd", weights, mesh.vertices[corners]),
        "points_basis": np.einsum("nj,njk->nk", weights, basis[corners].astype(np.float64)),
    }
    folds = Folds(arrays["vertices"], arrays["triangles"])
    arrays["fold_triangles"], arrays["fold_normals"] = folds.triangles, folds.normals
    origin = rig.normalizer.invert(np.zeros((1, 3)))[0]  # the model frame -> the shape's: an affine map
    linear = rig.normalizer.invert(np.eye(3)) - origin  # (3, 3), row j: the image of axis j
    entry = {"source": source, "key": folder.name, "to_shape": np.c_[linear.T, origin].tolist(),
             "vertices": len(mesh.vertices), "triangles": len(triangles)}
    folder.mkdir(exist_ok=True)
    with atomic_files(folder / ENTRY, force=True) as staged:  # a shape's arrays and entry appear together
        for name, value in arrays.items():
            np.save(staged.parent / f"{name}.npy", value, allow_pickle=False)
        (staged.parent / ENTRY).write_text(json.dumps(entry) + "\n")
    return entry


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _read_index(cache: Path) -> dict | None:
    try:
        index = json.loads((cache / INDEX).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(index, dict) or index.get("format") != CACHE_FORMAT or not isinstance(index.get("shapes"), list):
        return None
    return index


def _array_problem(arrays: dict[str, np.ndarray], k: int) -> str | None:
    """What is wrong with a shape's cached arrays, or None: every shape agreeing with the others (V vertices, T
    triangles, N points, K keypoints) and every index inside what it indexes (the compiled fold count reads
    ``vertices[fold_triangles]`` unchecked), read once when the shape is first drawn."""
    v, t, n = (len(arrays[name]) for name in ("vertices", "triangles", "points"))
    folds = len(arrays["fold_triangles"])
    shapes = {"vertices": (v, 3), "triangles": (t, 3), "basis": (v, k), "keypoints": (k, 3), "faces": (n,),
              "barycentric": (n, 3), "points": (n, 3), "points_basis": (n, k), "fold_triangles": (folds, 3),
              "fold_normals": (folds, 3)}
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            return f"{name}.npy has shape {arrays[name].shape}, not {shape}"
        integer = name in ("triangles", "faces", "fold_triangles")
        if arrays[name].dtype.kind not in ("iu" if integer else "f"):
            return f"{name}.npy holds {arrays[name].dtype}"
    for name, bound in (("triangles", v), ("faces", t), ("fold_triangles", v)):
        if arrays[name].size and (int(arrays[name].min()) < 0 or int(arrays[name].max()) >= bound):
            return f"{name}.npy indexes outside its {bound} rows"
    return None


def _checked_entry(cache: Path, entry: Any) -> dict:
    """An index entry as :meth:`Augmenter.build` writes it: its ``key`` names a folder of the cache itself (six to
    nine digits: never a path out of it) and ``to_shape`` is a finite (3, 4) map; anything else is a damaged or foreign
    cache, refused in one line."""
    key = entry.get("key") if isinstance(entry, dict) else None
    to_shape = entry.get("to_shape") if isinstance(entry, dict) else None
    try:
        matrix = np.asarray(to_shape, dtype=np.float64)
    except (TypeError, ValueError):
        matrix = np.empty(0)
    if not (isinstance(key, str) and 6 <= len(key) <= 9 and key.isascii() and key.isdigit()) or matrix.shape != (3, 4) \
            or not np.isfinite(matrix).all() or not isinstance(entry.get("source"), str):
        raise InputError(f"{cache}: a damaged augmenter cache (an entry of {INDEX} is not one Augmenter.build "
                         "writes); build the cache again")
    return entry


def _seed_words(seed: int | Sequence[int]) -> list[int]:
    words = [seed] if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) else list(seed)
    if not words or any(isinstance(w, bool) or not isinstance(w, (int, np.integer)) or w < 0 for w in words):
        raise InputError(f"seed must be a non-negative integer or a sequence of them; got {seed!r}")
    return [int(w) for w in words]


def _barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric weights of points (N, 3) on their triangles' corners (N, 3, 3)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(den > 0, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=1)
