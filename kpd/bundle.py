"""Model bundles: write, read and validate (format in :mod:`kpd.onnx_contract`).

A bundle is a directory ``name.kpd/`` or a ``.zip`` of the same files. Reading checks everything before anything is
used -- format name and version, the manifest's own checksum, the sha256 of every file, and the shapes of every array
-- and a :class:`~kpd.errors.BundleError` names what is wrong. Nothing is unpickled: the manifest is JSON and the
template cloud is read with ``np.load(allow_pickle=False)``.

Bundles trained by the project ship inside the package (``kpd/models/<name>.kpd``) and are found by name.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import logging
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from kpd import onnx_contract as contract
from kpd.cage import Cage
from kpd.errors import BundleError, InputError
from kpd.io.common import memory_free
from kpd.prior import KeypointPrior

__all__ = ["Bundle", "read_bundle", "write_bundle", "resolve_bundle", "shipped_bundles", "manifest_checksum",
           "MODELS_DIR", "MANIFEST_BYTES", "FILE_BYTES", "RATIO"]

log = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"
_CHECKSUM_KEY = "manifest_sha256"


@dataclass(frozen=True)
class Bundle:
    """A validated bundle held in memory.

    Attributes
    ----------
    path : where it was read from.
    manifest : the parsed manifest.json.
    files : {file name: bytes} of every file the manifest lists (the ONNX graphs, the template cloud).
    """

    path: Path
    manifest: dict
    files: dict

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def category(self) -> str:
        return self.manifest["category"]

    @property
    def num_keypoints(self) -> int:
        """K."""
        return self.manifest["model"]["keypoints"]

    @property
    def num_cage_vertices(self) -> int:
        """C."""
        return self.manifest["model"]["cage_vertices"]

    @property
    def m(self) -> int:
        """M: cage vertices each keypoint moves (the locality mask)."""
        return self.manifest["model"]["m"]

    @property
    def point_count(self) -> int:
        """N the model was trained with; the runtime samples this many points per shape."""
        return self.manifest["input"]["points"]

    @property
    def cage(self) -> Cage:
        """The cage template in the model frame: vertices (C, 3) float64, faces (F, 3) int64."""
        cage = self.manifest["cage"]
        return Cage(np.asarray(cage["vertices"], dtype=np.float64), np.asarray(cage["faces"], dtype=np.int64))

    @property
    def shared_influence(self) -> np.ndarray:
        """(K, C) float64: W_C, the category-shared influence matrix (unmasked)."""
        return np.asarray(self.manifest["shared_influence"], dtype=np.float64)

    @property
    def prior(self) -> KeypointPrior | None:
        """The category's keypoint prior, or None when the bundle has none (e.g. imported without data)."""
        data = self.manifest.get("prior")
        return None if data is None else KeypointPrior.from_dict(data)

    @property
    def template_points(self) -> np.ndarray | None:
        """(P, 3) float64 surface points of a representative training shape in the model frame, or None."""
        entry = self.manifest.get("template")
        if entry is None:
            return None
        return _load_npy(self.files[entry["file"]], entry["file"]).astype(np.float64)

    @property
    def training(self) -> dict:
        """The training record (data, command, seed, iterations, metrics) as exported."""
        return self.manifest.get("training") or {}

    def graph(self, spec: contract.GraphSpec) -> bytes:
        """The serialised ONNX model of one graph (``contract.KEYPOINTS_GRAPH`` or ``contract.INFLUENCE_GRAPH``)."""
        return self.files[self.manifest["graphs"][spec.key]["file"]]

    def __repr__(self) -> str:
        prior = "prior" if self.manifest.get("prior") is not None else "no prior"
        return (f"Bundle({str(self.path)!r}, category={self.category!r}, K={self.num_keypoints}, "
                f"C={self.num_cage_vertices}, {prior})")


# --- reading ------------------------------------------------------------------------------------------------------

def shipped_bundles() -> list[str]:
    """Names of the bundles shipped inside the package (``kpd/models/<name>.kpd``)."""
    if not MODELS_DIR.is_dir():
        return []
    return sorted(p.name[: -len(".kpd")] for p in MODELS_DIR.glob("*.kpd") if (p / contract.MANIFEST_FILE).is_file())


def resolve_bundle(name_or_path: str | os.PathLike) -> Path:
    """A bundle path from a path or the name of a shipped bundle (``"chair"``, ``"table"``)."""
    path = Path(name_or_path)
    if path.exists():
        return path
    text = str(name_or_path)
    if os.sep not in text and "/" not in text:
        shipped = MODELS_DIR / (text if text.endswith(".kpd") else text + ".kpd")
        if shipped.is_dir():
            return shipped
    names = ", ".join(shipped_bundles()) or "none"
    raise BundleError(f"{text}: no such bundle (a .kpd folder, a .zip, or a shipped name: {names})")


def read_bundle(name_or_path: str | os.PathLike) -> Bundle:
    """Read and validate a bundle (folder, zip, or shipped name).

    Only the manifest and the files it lists are read, each after its size (and, in a zip, its compression ratio)
    passed the bounds below; every file is a plain name inside the bundle; the ONNX graphs are checked to be
    self-contained (:func:`kpd.onnx_contract.graph_refusal`) before anything runs them.

    Raises
    ------
    BundleError naming the problem: missing file, changed bytes, other format version, a mis-shaped array, a file
    too large, a graph that reaches outside the bundle.
    """
    path = resolve_bundle(name_or_path)
    where = str(path)
    with _Members(path) as members:
        manifest_bytes = members.read(contract.MANIFEST_FILE, MANIFEST_BYTES)
        if manifest_bytes is None:
            raise BundleError(f"{where}: not a kpd bundle: {contract.MANIFEST_FILE} is missing")
        try:
            manifest = json.loads(manifest_bytes.decode("utf-8"), parse_float=_finite_float,
                                  parse_constant=_no_constant)
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, ValueError) as exc:
            raise BundleError(f"{where}: {contract.MANIFEST_FILE} is not valid JSON ({exc})") from exc
        if not isinstance(manifest, dict):
            raise BundleError(f"{where}: {contract.MANIFEST_FILE} must hold a JSON object")
        _check_format(manifest, where)
        recorded = manifest.get(_CHECKSUM_KEY)
        actual = manifest_checksum(manifest)
        if recorded != actual:
            raise BundleError(f"{where}: {contract.MANIFEST_FILE} was modified: checksum {recorded} recorded, "
                              f"{actual} computed")
        files = _check_files(manifest, members, where)
    try:
        _check_manifest(manifest, files)
    except (KeyError, TypeError, ValueError, InputError) as exc:
        detail = f"lacks {exc.args[0]!r}" if isinstance(exc, KeyError) else str(exc)
        raise BundleError(f"{where}: invalid manifest: {detail}") from exc
    for spec in contract.GRAPHS:
        name = manifest["graphs"][spec.key]["file"]
        refusal = contract.graph_refusal(files[name])
        if refusal is not None:
            raise BundleError(f"{where}: {name} is refused: {refusal}")
    return Bundle(path=path, manifest=manifest, files=files)


MANIFEST_BYTES = 64 << 20  # the manifest is JSON of a few hundred kilobytes (W_C, the prior, the cage)
FILE_BYTES = 1 << 30  # one file of a bundle: the largest graph kpd exports is tens of megabytes
RATIO = 100  # the most a zip member may inflate (ONNX weights and point clouds barely deflate; JSON about 4x)
_RATIO_FROM = 1 << 20  # bytes below which a member's ratio is not judged (a small file of zeros is no threat)
_MAX_FILES = 64


class _Members:
    """The files of a bundle folder or zip, read one by one on request, each only after its size is checked."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.archive = None
        self.prefix = ""
        if path.is_dir():
            return
        if not path.is_file():
            raise BundleError(f"{path}: no such bundle")
        if not zipfile.is_zipfile(path):
            raise BundleError(f"{path}: a bundle must be a .kpd folder or a .zip of one")
        try:
            self.archive = zipfile.ZipFile(path)
            names = [n for n in self.archive.namelist() if not n.endswith("/")]
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
            raise BundleError(f"{path}: damaged zip ({exc or type(exc).__name__})") from exc
        roots = {n.split("/")[0] for n in names if "/" in n}
        # files at the archive's root, or inside one top-level folder
        self.prefix = roots.pop() + "/" if len(roots) == 1 and all("/" in n for n in names) else ""

    def __enter__(self) -> "_Members":
        return self

    def __exit__(self, *exc) -> None:
        if self.archive is not None:
            self.archive.close()

    def read(self, name: str, limit: int) -> bytes | None:
        """The bytes of the bundle's file ``name`` (a plain file name), or None when it has none; BundleError when
        it is larger than ``limit`` or (in a zip) inflates more than :data:`RATIO` times."""
        if not isinstance(name, str) or name in ("", ".", "..") or "/" in name or "\\" in name or \
                any(ord(c) < 32 for c in name):
            raise BundleError(f"{self.path}: the manifest names {name!r}, not a plain file name of the bundle")
        if self.archive is None:
            return self._read_file(name, limit)
        try:
            info = self.archive.getinfo(self.prefix + name)
        except KeyError:
            return None
        if info.file_size > limit:
            raise BundleError(f"{self.path}: {name} inflates to {info.file_size} bytes, over the {limit} kpd reads "
                              "for one file of a bundle")
        if info.file_size > _RATIO_FROM and info.file_size > RATIO * max(info.compress_size, 1):
            raise BundleError(f"{self.path}: {name} inflates {info.file_size // max(info.compress_size, 1)} times "
                              f"({info.compress_size} to {info.file_size} bytes), more than the {RATIO} of a bundle")
        try:
            with self.archive.open(info) as fh:
                data = fh.read(info.file_size + 1)
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError) as exc:
            raise BundleError(f"{self.path}: damaged zip ({exc or type(exc).__name__})") from exc
        if len(data) != info.file_size:
            raise BundleError(f"{self.path}: damaged zip ({name} holds {len(data)} of its {info.file_size} bytes)")
        return data

    def _read_file(self, name: str, limit: int) -> bytes | None:
        from kpd.io.references import locate, read_named

        found = locate(self.path, self.path, name, dataset_layouts=False)
        if found.refused is not None:
            raise BundleError(f"{self.path}: {name} is not read ({found.refused}); a bundle holds its own files")
        if found.path is None:
            return None
        data = read_named(found.path, limit)
        if isinstance(data, str):
            raise BundleError(f"{self.path}: {name} is not read ({data})")
        return data


def _check_format(manifest: dict, where: str) -> None:
    name = manifest.get("format")
    if name != contract.FORMAT_NAME:
        raise BundleError(f"{where}: format must be {contract.FORMAT_NAME!r}; got {name!r}")
    version = manifest.get("format_version")
    if version != contract.FORMAT_VERSION:
        raise BundleError(f"{where}: bundle format version {version!r}; this kpd reads version "
                          f"{contract.FORMAT_VERSION} (re-export the model with this kpd)")


def _check_files(manifest: dict, members: _Members, where: str) -> dict[str, bytes]:
    listed = manifest.get("files")
    if not isinstance(listed, dict) or not listed:
        raise BundleError(f"{where}: manifest lists no files")
    if len(listed) > _MAX_FILES:
        raise BundleError(f"{where}: manifest lists {len(listed)} files; a bundle holds at most {_MAX_FILES}")
    graphs = manifest.get("graphs") if isinstance(manifest.get("graphs"), dict) else {}
    needed = [(graphs.get(g.key) if isinstance(graphs.get(g.key), dict) else {}).get("file", g.file)
              for g in contract.GRAPHS]
    if isinstance(manifest.get("template"), dict):
        needed.append(manifest["template"].get("file", contract.TEMPLATE_FILE))
    if not all(isinstance(name, str) for name in needed):
        raise BundleError(f"{where}: invalid manifest: a file name that is not a string")
    needed = set(needed)
    for name in sorted(needed - set(listed), key=str):
        raise BundleError(f"{where}: manifest has no sha256 for {name}")
    files = {}
    for name, digest in sorted(listed.items()):
        data = members.read(name, min(FILE_BYTES, memory_free()))
        if data is None:
            raise BundleError(f"{where}: {name} is missing")
        actual = hashlib.sha256(data).hexdigest()
        if actual != digest:
            raise BundleError(f"{where}: {name} was modified: sha256 {digest} expected, {actual} found")
        files[name] = data
    return files


def _check_manifest(manifest: dict, files: dict[str, bytes]) -> None:
    model = manifest["model"]
    k, c, f, m = (_positive_int(model, key) for key in ("keypoints", "cage_vertices", "cage_faces", "m"))
    if m > c:
        raise ValueError(f"m must be at most C = {c}; got {m}")
    inputs = manifest["input"]
    _positive_int(inputs, "points")
    if inputs["normalization"] != contract.NORMALIZATION:
        raise ValueError(f"normalization must be {contract.NORMALIZATION!r}; got {inputs['normalization']!r}")
    for spec in contract.GRAPHS:
        graph = manifest["graphs"][spec.key]
        if graph["file"] not in files:
            raise ValueError(f"graph {spec.key} is in {graph['file']!r}, which the manifest does not list")
        if graph["input"] != contract.INPUT_NAME or graph["output"] != spec.output:
            raise ValueError(f"graph {spec.key} must map {contract.INPUT_NAME!r} -> {spec.output!r}; "
                             f"got {graph['input']!r} -> {graph['output']!r}")
    vertices = np.asarray(manifest["cage"]["vertices"], dtype=np.float64)
    faces = np.asarray(manifest["cage"]["faces"])
    if vertices.shape != (c, 3) or not np.isfinite(vertices).all():
        raise ValueError(f"cage vertices must be finite with shape (C, 3) = ({c}, 3); got {vertices.shape}")
    if faces.shape != (f, 3) or faces.dtype.kind not in "iu" or faces.min() < 0 or faces.max() >= c:
        raise ValueError(f"cage faces must be integers in [0, {c}) with shape (F, 3) = ({f}, 3); got {faces.shape}")
    for entry, keys in (("fit", ("distance", "iterations", "step")),
                        ("rig", ("distance", "iterations", "step", "sigma", "ridge", "support"))):
        fit = manifest["cage"].get(entry) or {}
        for key, value in fit.items():
            if key not in keys or isinstance(value, bool) or \
                    not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
                raise ValueError(f"cage {entry} setting {key}={value!r} is not one of {'/'.join(keys)} >= 0")
        if entry == "rig" and (fit.get("sigma") == 0 or fit.get("support") == 0):
            raise ValueError("cage rig settings sigma and support must be > 0")
    shared = np.asarray(manifest["shared_influence"], dtype=np.float64)
    if shared.shape != (k, c) or not np.isfinite(shared).all():
        raise ValueError(f"shared_influence (W_C) must be finite with shape (K, C) = ({k}, {c}); got {shared.shape}")
    if manifest.get("prior") is not None:
        prior = KeypointPrior.from_dict(manifest["prior"])
        if prior.num_keypoints != k:
            raise ValueError(f"prior is for K = {prior.num_keypoints} keypoints; the model has K = {k}")
    if manifest.get("template") is not None:
        name = manifest["template"]["file"]
        points = _load_npy(files[name], name)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 1 or not np.isfinite(points).all():
            raise ValueError(f"{name} must hold finite (P, 3) points; got shape {points.shape}")


def _positive_int(mapping: Mapping, key: str) -> int:
    value = mapping[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{key} must be a positive integer; got {value!r}")
    return value


def _finite_float(text: str) -> float:
    """A JSON number of the manifest: finite, as a manifest written by kpd holds only finite numbers (``1e309`` would
    be infinity, which its checksum's canonical JSON cannot hold)."""
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"a number out of float64's range: {text[:40]}")
    return value


def _no_constant(text: str) -> float:
    raise ValueError(f"{text} is not a JSON number")


def _load_npy(data: bytes, name: str) -> np.ndarray:
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise BundleError(f"{name}: not a plain .npy array ({exc})") from exc


# --- writing ------------------------------------------------------------------------------------------------------

def manifest_checksum(manifest: Mapping) -> str:
    """sha256 of the manifest's canonical JSON without its own checksum entry."""
    body = {key: value for key, value in manifest.items() if key != _CHECKSUM_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def build_manifest(
    *,
    category: str,
    keypoints_onnx: bytes,
    influence_onnx: bytes,
    cage: Cage,
    shared_influence: Any,
    m: int,
    point_count: int,
    cage_fit: Mapping | None = None,
    prior: KeypointPrior | None = None,
    template_points: Any = None,
    template_source: str | None = None,
    up: str | None = None,
    training: Mapping | None = None,
    clamp: bool = True,
    frame_check: Mapping | None = None,
    rig_fit: Mapping | None = None,
) -> tuple[dict, dict[str, bytes]]:
    """The manifest and the files of a bundle (not yet written).

    Parameters
    ----------
    category : the shape category ("chair").
    keypoints_onnx, influence_onnx : serialised ONNX graphs following :mod:`kpd.onnx_contract`.
    cage : the cage template, vertices (C, 3), faces (F, 3), model frame.
    shared_influence : (K, C) W_C.
    m : locality (cage vertices per keypoint).
    point_count : N the model was trained with.
    cage_fit : the :func:`kpd.cage.fit_cage` settings of training (``distance``, ``iterations``, ``step``).
    prior : the fitted keypoint prior, or None.
    template_points : (P, 3) model-frame points of a representative training shape, or None.
    template_source : name of that shape.
    up : the up axis of the training data's frame ("+z" for ModelNet), if known.
    training : the training record (data, command, seed, iterations, metrics), JSON-safe.
    frame_check : the limits of :func:`kpd.frame.calibrate` (the frame and category check), or None.
    rig_fit : cage-fitting settings for rigs that differ from ``cage_fit`` (a tighter ``distance``), or None.

    Returns
    -------
    manifest : dict (with its checksum), files : {name: bytes} including manifest.json.
    """
    shared = np.asarray(shared_influence, dtype=np.float64)
    vertices = np.asarray(cage.vertices, dtype=np.float64)
    faces = np.asarray(cage.faces, dtype=np.int64)
    k, c = shared.shape
    files: dict[str, bytes] = {
        contract.KEYPOINTS_GRAPH.file: bytes(keypoints_onnx),
        contract.INFLUENCE_GRAPH.file: bytes(influence_onnx),
    }
    template = None
    if template_points is not None:
        points = np.ascontiguousarray(template_points, dtype=np.float32)
        buffer = io.BytesIO()
        np.save(buffer, points, allow_pickle=False)
        files[contract.TEMPLATE_FILE] = buffer.getvalue()
        template = {"file": contract.TEMPLATE_FILE, "points": int(len(points)), "source": template_source}
    manifest = {
        "format": contract.FORMAT_NAME,
        "format_version": contract.FORMAT_VERSION,
        "category": str(category),
        "model": {"keypoints": int(k), "cage_vertices": int(c), "cage_faces": int(len(faces)), "m": int(m),
                  "clamp": bool(clamp)},
        "input": {"points": int(point_count), "normalization": contract.NORMALIZATION,
                  "normalization_note": "per shape: bounding-box centre to the origin, largest absolute coordinate "
                                        "to 1 (docs/method.md §7); mesh vertices and points share one normaliser",
                  "up": up},
        "graphs": {
            spec.key: {"file": spec.file, "input": contract.INPUT_NAME, "output": spec.output,
                       "dynamic_axes": [contract.BATCH_AXIS, contract.POINTS_AXIS], "opset": contract.OPSET}
            for spec in contract.GRAPHS
        },
        "cage": {"vertices": vertices.tolist(), "faces": faces.tolist(), "fit": dict(cage_fit or {})},
        "shared_influence": shared.tolist(),
        "prior": None if prior is None else prior.to_dict(),
        "template": template,
        "training": dict(training or {}),
        "files": {name: hashlib.sha256(data).hexdigest() for name, data in sorted(files.items())},
        "created_by": f"kpd {_version()}",
    }
    if frame_check is not None:
        manifest["frame_check"] = dict(frame_check)
    if rig_fit:
        manifest["cage"]["rig"] = dict(rig_fit)
    _seal(manifest, files)
    return manifest, files


def _seal(manifest: dict, files: dict[str, bytes]) -> None:
    """Put the manifest's checksum in it and its JSON into ``files``."""
    manifest[_CHECKSUM_KEY] = manifest_checksum(manifest)
    files[contract.MANIFEST_FILE] = (json.dumps(manifest, indent=1, allow_nan=False) + "\n").encode("utf-8")


def with_rig_fit(bundle: Bundle, rig_fit: Mapping | None, note: str | None = None) -> tuple[dict, dict[str, bytes]]:
    """The files of ``bundle`` with its rig settings (``manifest.cage.rig``) replaced; everything else as it was.

    ``rig_fit`` : e.g. ``{"distance": 0.2}`` (the cage fitted for each rig; the learned influence is transferred to
    it, :func:`kpd.rig.transfer_influence`), or None to rig with the training cage. ``note`` is recorded beside it.
    """
    manifest = copy.deepcopy(bundle.manifest)
    manifest["cage"].pop("rig", None)
    manifest["cage"].pop("rig_note", None)
    if rig_fit:
        manifest["cage"]["rig"] = dict(rig_fit)
        if note:
            manifest["cage"]["rig_note"] = str(note)
    files = {name: data for name, data in bundle.files.items() if name != contract.MANIFEST_FILE}
    _seal(manifest, files)
    _check_manifest(manifest, files)
    return manifest, files


def write_bundle(path: str | os.PathLike, files: Mapping[str, bytes], *, force: bool = False) -> Path:
    """Write bundle files to a folder, or to a zip when ``path`` ends in ``.zip``, atomically.

    Everything is written through :class:`kpd.io.Outputs`: into a staging area beside ``path``, fsynced, then put
    in place; an existing ``path`` is replaced only with ``force``.
    """
    from kpd.io import Outputs

    path = Path(path)
    with Outputs(force=force) as outputs:
        is_zip = path.suffix == ".zip"
        target = outputs.file(path, None) if is_zip else outputs.folder(path, None)
        staged = outputs.stage(target)
        if is_zip:
            with zipfile.ZipFile(staged, "w", compression=zipfile.ZIP_DEFLATED) as archive:
                for name, data in sorted(files.items()):
                    info = zipfile.ZipInfo(name, date_time=(2021, 6, 1, 0, 0, 0))
                    info.compress_type = zipfile.ZIP_DEFLATED
                    info.external_attr = 0o644 << 16
                    archive.writestr(info, data)
        else:
            staged.mkdir()
            for name, data in files.items():
                (staged / name).write_bytes(data)
                os.chmod(staged / name, 0o644)
            os.chmod(staged, 0o755)
    return path


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("kpd")
    except PackageNotFoundError:
        return "unknown"
