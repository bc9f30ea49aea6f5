"""Run a model bundle without torch: onnxruntime for Φ and Γ, numpy for the cage, MVC and the rig.

>>> from kpd.runtime import Model                           # doctest: +SKIP
>>> model = Model.load("chair")                             # a shipped bundle, or a path to a .kpd folder / .zip
>>> keypoints = model.keypoints(read_mesh("chair.ply"))     # (K, 3) in the mesh's own frame
>>> rig = model.rig(mesh)                                   # kpd.rig.Rig, ready for rig.deform(new_keypoints)
>>> aligned = model.align(source_mesh, target_mesh)         # source deformed to the target's keypoints

Shapes come in any position and scale: each is mapped into the model's [-1, 1] frame by its own
:class:`~kpd.geometry.Normalizer` (fitted on the mesh vertices the triangles use, as in training), the model runs
there, and results are mapped back. A mesh is sampled with a fixed seed (area-weighted, ``point_count`` points), so
the same mesh gives the same keypoints on every call; a point set with more than ``point_count`` points uses a seeded
subset, and a smaller one all of its points.
"""

from __future__ import annotations

import logging
import os
from typing import Any, Iterable, Mapping, NamedTuple, Sequence

import numpy as np

from kpd import onnx_contract as contract
from kpd.bundle import Bundle, read_bundle
from kpd.cage import Cage, fit_cage
from kpd.errors import BundleError, InputError
from kpd.geometry import Normalizer, as_points, as_rng, sample_surface
from kpd.io import Mesh, PointSet
from kpd.prior import KeypointPrior
from kpd.memory import check_bind_memory
from kpd.rig import TRANSFER_RIDGE, TRANSFER_SIGMA, TRANSFER_SUPPORT, Rig, transfer_influence

__all__ = ["Model", "Prediction", "Shape"]

log = logging.getLogger(__name__)

Shape = Any  # Mesh | PointSet | (N, 3) array-like | path of a mesh or point file


class Prediction(NamedTuple):
    """The model's view of one shape, in the model frame.

    keypoints : (K, 3) float64, model frame.
    influence : (K, C) float64, unmasked W = W_C + W_I.
    normalizer : maps the shape's own frame to the model frame.
    points : (N, 3) float64, the sampled points the networks saw (model frame).
    """

    keypoints: np.ndarray
    influence: np.ndarray
    normalizer: Normalizer
    points: np.ndarray


class Model:
    """A validated bundle with two onnxruntime sessions.

    Parameters
    ----------
    bundle : from :func:`kpd.bundle.read_bundle`.
    threads : onnxruntime intra-op threads (``SessionOptions.intra_op_num_threads``); None lets onnxruntime choose.
    inter_op_threads : onnxruntime inter-op threads; None lets onnxruntime choose.
    providers : onnxruntime execution providers; CPU when None.
    spinning : let idle onnxruntime threads spin (lowest latency on an otherwise idle machine); off by default.
    parallel_graphs : run Φ and Γ at the same time (Γ on a worker thread) unless ``threads == 1``; about 15 %
        faster on two cores.
    """

    def __init__(self, bundle: Bundle, *, threads: int | None = None, inter_op_threads: int | None = None,
                 providers: Sequence[str] | None = None, spinning: bool = False,
                 parallel_graphs: bool = True) -> None:
        import onnxruntime as ort

        if hasattr(ort, "disable_telemetry_events"):  # onnxruntime started before kpd (ORT_DISABLE_TELEMETRY unseen)
            ort.disable_telemetry_events()
        self.bundle = bundle
        options = ort.SessionOptions()
        # fatal only: an error of onnxruntime reaches the user as the exception kpd reports in one line, not
        # also as a coloured log line of its own before it (a session that cannot allocate, for one)
        options.log_severity_level = 4
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        # idle worker threads sleep instead of spinning: on a busy machine (or beside a GUI) spinning threads
        # steal the cores they wait for (5x slower on 2 shared cores); the cost on an idle machine is ~0.3 ms
        options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
        options.add_session_config_entry("session.inter_op.allow_spinning", "1" if spinning else "0")
        for name, value in (("threads", threads), ("inter_op_threads", inter_op_threads)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
                raise InputError(f"{name} must be a non-negative integer (0 = onnxruntime's choice); got {value!r}")
        if threads is not None:
            options.intra_op_num_threads = threads
        if inter_op_threads is not None:
            options.inter_op_num_threads = inter_op_threads
        providers = list(providers) if providers is not None else ["CPUExecutionProvider"]
        self._sessions = {}
        self._io = {}
        for spec in contract.GRAPHS:
            session = _session(ort, bundle, spec, options, providers)
            self._io[spec.key] = _check_session(session, bundle, spec)
            self._sessions[spec.key] = session
        self._pool = None
        if parallel_graphs and threads != 1:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kpd-influence")
        self._shared = bundle.shared_influence  # (K, C)
        self._cage = bundle.cage
        self._prior = bundle.prior
        fit = bundle.manifest["cage"].get("fit") or {}
        self._cage_fit = {key: fit[key] for key in ("distance", "iterations", "step") if key in fit}
        # a bundle may fit its rigs' cages tighter than training did (kpd export --rig-cage-distance); the learned
        # influence is then transferred to that cage (kpd.rig.transfer_influence)
        rig = bundle.manifest["cage"].get("rig") or {}
        self._rig_fit = {key: rig[key] for key in ("distance", "iterations", "step") if key in rig}
        self._transfer = {key: float(rig[key]) for key in ("sigma", "ridge", "support") if key in rig}

    @classmethod
    def load(cls, path: str | os.PathLike, *, threads: int | None = None, inter_op_threads: int | None = None,
             providers: Sequence[str] | None = None, spinning: bool = False,
             parallel_graphs: bool = True) -> "Model":
        """Read, validate and open a bundle: a ``.kpd`` folder, a ``.zip`` of one, or a shipped name (``"chair"``)."""
        return cls(read_bundle(path), threads=threads, inter_op_threads=inter_op_threads, providers=providers,
                   spinning=spinning, parallel_graphs=parallel_graphs)

    # --- what the model is --------------------------------------------------------------------------------------

    @property
    def category(self) -> str:
        return self.bundle.category

    @property
    def num_keypoints(self) -> int:
        """K."""
        return self.bundle.num_keypoints

    @property
    def num_cage_vertices(self) -> int:
        """C."""
        return self.bundle.num_cage_vertices

    @property
    def m(self) -> int:
        """Cage vertices each keypoint moves (the locality mask)."""
        return self.bundle.m

    @property
    def point_count(self) -> int:
        """Points sampled per shape (the training N)."""
        return self.bundle.point_count

    @property
    def cage_template(self) -> Cage:
        """The cage template in the model frame."""
        return self._cage

    @property
    def shared_influence(self) -> np.ndarray:
        """(K, C) float64: W_C."""
        return self._shared.copy()

    @property
    def prior(self) -> KeypointPrior | None:
        """The category prior, or None when the bundle has none."""
        return self._prior

    @property
    def template_points(self) -> np.ndarray | None:
        """(P, 3) float64: a representative training shape in the model frame (for orienting scans), or None."""
        return self.bundle.template_points

    @property
    def outer_surface(self) -> bool:
        """Whether the model was trained on outer-surface samples (``kpd train --outer-surface``); meshes are then
        sampled the same way (:func:`kpd.geometry.sample_surface` with ``outer=True``)."""
        checkpoint = (self.bundle.manifest.get("training") or {}).get("checkpoint") or {}
        return bool((checkpoint.get("sample_settings") or {}).get("outer", False))

    @property
    def up(self) -> str | None:
        """The up axis of the training data's frame (``"+z"`` for ModelNet), if the bundle records it."""
        return self.bundle.manifest["input"].get("up")

    def __repr__(self) -> str:
        return (f"Model({self.category!r}, K={self.num_keypoints}, C={self.num_cage_vertices}, M={self.m}, "
                f"N={self.point_count}, prior={'yes' if self._prior is not None else 'no'})")

    # --- running the networks ----------------------------------------------------------------------------------

    def run(self, points: Any) -> tuple[np.ndarray, np.ndarray]:
        """Φ and Γ on model-frame points.

        Parameters
        ----------
        points : (B, N, 3) or (N, 3) float, already in the model frame.

        Returns
        -------
        keypoints : (B, K, 3) float32 (clamped), influence : (B, K, C) float32, the instance offset W_I
            (without the batch axis when ``points`` had none).
        """
        array = np.asarray(points, dtype=np.float32)
        single = array.ndim == 2
        if single:
            array = array[None]
        if array.ndim != 3 or array.shape[2] != 3 or array.shape[1] < 1 or array.shape[0] < 1:
            raise InputError(f"points must have shape (B, N, 3) or (N, 3) with N >= 1; got {np.shape(points)}")
        if not np.isfinite(array).all():
            raise InputError("points must be finite")
        array = np.ascontiguousarray(array)

        def call(spec: contract.GraphSpec) -> np.ndarray:
            input_name, output_name = self._io[spec.key]
            try:
                return self._sessions[spec.key].run([output_name], {input_name: array})[0]
            except _ort_failures() as exc:  # the graph's own failure (an allocation it cannot make, for one)
                raise BundleError(f"{self.bundle.path}: {spec.file} failed in onnxruntime "
                                  f"({_one_line(exc)})") from exc

        if self._pool is not None:  # Γ on a worker thread while Φ runs here (onnxruntime releases the GIL)
            pending = self._pool.submit(call, contract.INFLUENCE_GRAPH)
            keypoints = call(contract.KEYPOINTS_GRAPH)
            influence = pending.result()
        else:
            keypoints, influence = call(contract.KEYPOINTS_GRAPH), call(contract.INFLUENCE_GRAPH)
        return (keypoints[0], influence[0]) if single else (keypoints, influence)

    def sample(self, shape: Shape, *, seed: int = 0) -> tuple[Normalizer, np.ndarray]:
        """The normaliser of a shape and the model-frame points the networks see.

        Returns
        -------
        normalizer : Normalizer, the shape's frame -> model frame.
        points : (n, 3) float64, n = ``point_count`` for a mesh, at most that for a point set.
        """
        shape = _as_shape(shape)
        n = self.point_count
        if isinstance(shape, Mesh) and len(shape.triangles):
            used = np.zeros(len(shape.vertices), dtype=bool)
            used[shape.triangles] = True  # the vertices of some triangle (as np.unique, without sorting 3T indices)
            normalizer = Normalizer().fit(shape.vertices if used.all() else shape.vertices[used])
            points = sample_surface(normalizer.apply(shape.vertices), shape.triangles, n, seed=seed,
                                    outer=self.outer_surface).points
            return normalizer, points
        raw = shape.vertices if isinstance(shape, Mesh) else shape.points
        normalizer = Normalizer().fit(raw)
        if len(raw) > n:
            raw = raw[np.sort(as_rng(seed).choice(len(raw), n, replace=False))]
        return normalizer, normalizer.apply(raw)

    def predict(self, shape: Shape, *, seed: int = 0) -> Prediction:
        """Keypoints and influence of one shape in the model frame (see :class:`Prediction`)."""
        return self.predict_batch([shape], seed=seed)[0]

    def predict_batch(self, shapes: Iterable[Shape], *, seed: int = 0, batch_size: int = 16) -> list[Prediction]:
        """:meth:`predict` for many shapes, ``batch_size`` at a time through the networks.

        Shapes with fewer points are padded by repeating their first point, which leaves the networks' max-pooled
        features, and so their outputs, unchanged.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise InputError(f"batch_size must be a positive integer; got {batch_size!r}")
        sampled = [self.sample(shape, seed=seed) for shape in shapes]
        results: list[Prediction] = []
        for start in range(0, len(sampled), batch_size):
            chunk = sampled[start:start + batch_size]
            longest = max(len(points) for _, points in chunk)
            stack = np.empty((len(chunk), longest, 3), dtype=np.float32)
            for i, (_, points) in enumerate(chunk):
                stack[i, : len(points)] = points
                stack[i, len(points):] = points[0]
            keypoints, offsets = self.run(stack)
            for (normalizer, points), kp, w in zip(chunk, keypoints, offsets):
                results.append(Prediction(kp.astype(np.float64), self._shared + w, normalizer, points))
        return results

    def keypoints(self, shape: Shape, *, seed: int = 0) -> np.ndarray:
        """(K, 3) float64: the shape's keypoints in its own frame, in the model's keypoint order."""
        prediction = self.predict(shape, seed=seed)
        return prediction.normalizer.invert(prediction.keypoints)

    def keypoints_batch(self, shapes: Iterable[Shape], *, seed: int = 0, batch_size: int = 16) -> np.ndarray:
        """(S, K, 3) float64: :meth:`keypoints` of each shape, each in its own frame."""
        predictions = self.predict_batch(shapes, seed=seed, batch_size=batch_size)
        return np.stack([p.normalizer.invert(p.keypoints) for p in predictions]) if predictions else \
            np.empty((0, self.num_keypoints, 3))

    def influence(self, shape: Shape, *, seed: int = 0) -> np.ndarray:
        """(K, C) float64: the unmasked influence W = W_C + W_I of a shape."""
        return self.predict(shape, seed=seed).influence

    def influence_batch(self, shapes: Iterable[Shape], *, seed: int = 0, batch_size: int = 16) -> np.ndarray:
        """(S, K, C) float64: :meth:`influence` of each shape."""
        predictions = self.predict_batch(shapes, seed=seed, batch_size=batch_size)
        return np.stack([p.influence for p in predictions]) if predictions else \
            np.empty((0, self.num_keypoints, self.num_cage_vertices))

    # --- rigs, alignment and the prior -------------------------------------------------------------------------

    def rig(self, mesh: Mesh | str | os.PathLike, *, seed: int = 0, enclose: bool = True,
            prediction: Prediction | None = None, straighten: bool = True, check_memory: bool = True) -> Rig:
        """Bind a mesh for editing: predicted keypoints, the cage fitted to the sampled points, the influence W.

        Parameters
        ----------
        mesh : Mesh (or a mesh file), in its own units.
        seed : surface-sampling seed.
        enclose : grow the cage until every mesh vertex is inside (MVC misplaces vertices outside the cage).
        prediction : reuse a :meth:`predict` result of this mesh.
        straighten : keep the mesh's sliver triangles from turning over in edits (:func:`kpd.rig.straighten_basis`).
        check_memory : refuse a mesh too large for the memory available (:func:`kpd.memory.check_bind_memory`)
            before any work; ``False`` when the caller has checked it already.
        """
        mesh = _as_shape(mesh)
        if not isinstance(mesh, Mesh) or not len(mesh.triangles):
            raise InputError(f"a rig needs a triangle mesh; got {_describe(mesh)}")
        if check_memory:  # before any work; the binding below trusts it
            check_bind_memory(len(mesh.vertices), len(mesh.triangles), self.num_keypoints)
        prediction = prediction if prediction is not None else self.predict(mesh, seed=seed)
        # the authors' rule on the sampled points, as in training; then, beyond it, push faces out until every mesh
        # vertex is inside (only the vertices are deformed through MVC; a position stored several times is enclosed
        # alike, so they are not merged first)
        vertices = prediction.normalizer.apply(mesh.vertices) if enclose else None  # (V, 3)
        cage = self._fitted_cage(prediction.points, vertices, self._cage_fit)
        influence = prediction.influence
        if self._rig_fit:  # a tighter cage for editing, with the learned motion transferred onto it
            rig_cage = self._fitted_cage(prediction.points, vertices, {**self._cage_fit, **self._rig_fit})
            support = min(self.num_cage_vertices, int(round(self._transfer.get("support", TRANSFER_SUPPORT) * self.m)))
            influence = transfer_influence(influence, prediction.keypoints, prediction.points, cage, rig_cage,
                                           self.m, sigma=self._transfer.get("sigma", TRANSFER_SIGMA),
                                           ridge=self._transfer.get("ridge", TRANSFER_RIDGE), support=support)
            return Rig.bind(mesh, prediction.keypoints, influence, normalizer=prediction.normalizer,
                            cage=rig_cage, m=support, straighten=straighten, model_vertices=vertices,
                            check_memory=False)
        return Rig.bind(mesh, prediction.keypoints, influence, normalizer=prediction.normalizer,
                        cage=cage, m=self.m, straighten=straighten, model_vertices=vertices, check_memory=False)

    def _fitted_cage(self, points: np.ndarray, vertices: np.ndarray | None, fit: dict) -> Cage:
        """The template shrunk onto the sampled points (N, 3), then grown to enclose the vertices (V, 3) if given."""
        cage = fit_cage(points, template=self._cage, **fit)
        return cage if vertices is None else fit_cage(vertices, template=cage, iterations=0, enclose=True)

    @property
    def rig_settings(self) -> dict:
        """How :meth:`rig` fits the cage: the training fit, and the tighter rig fit with its transfer, if any."""
        return {"fit": dict(self._cage_fit), "rig": dict(self._rig_fit),
                "transfer": {"sigma": TRANSFER_SIGMA, "ridge": TRANSFER_RIDGE, "support": TRANSFER_SUPPORT,
                             **self._transfer}
                if self._rig_fit else None}

    def align(self, source: Mesh | str | os.PathLike, target: Shape, *, seed: int = 0) -> Mesh:
        """Deform ``source`` so that its keypoints move to ``target``'s (paper §4.2); returns a copy of ``source``
        (same topology, UVs, colours) in the source's own units.

        The target's keypoints are predicted in the model frame of the target and placed into the source's frame by
        the *source's* normaliser, so sources and targets of any size and position align by shape, not by pose.
        """
        return self.align_batch(source, [target], seed=seed)[0]

    def align_batch(self, source: Mesh | str | os.PathLike, targets: Iterable[Shape], *, seed: int = 0,
                    batch_size: int = 16) -> list[Mesh]:
        """:meth:`align` of one source to many targets (the source is rigged once)."""
        rig = self.rig(source, seed=seed)
        predictions = self.predict_batch(targets, seed=seed, batch_size=batch_size)
        return [rig.deformed_mesh(rig.normalizer.invert(p.keypoints)) for p in predictions]

    def sync(self, rig: Rig, edits: Mapping[int, Any]) -> np.ndarray:
        """Synchronised edit through the category prior, in the rig's own units.

        Parameters
        ----------
        rig : a rig of this model (K keypoints).
        edits : {index: (3,) new position} in the rig's units.

        Returns
        -------
        keypoints : (K, 3) float64 in the rig's units; the edited ones exactly where asked, the others moved as the
            prior says (pass them to ``rig.deform``).
        """
        prior = self._require_prior()
        if rig.num_keypoints != prior.num_keypoints:
            raise InputError(f"the rig has {rig.num_keypoints} keypoints; this model's prior has "
                             f"{prior.num_keypoints}")
        normalizer = rig.normalizer
        model_edits = {}
        for index, position in edits.items():
            position = np.asarray(position, dtype=np.float64)
            if position.shape != (3,):
                raise InputError(f"edit of keypoint {index} must be 3 numbers; got shape {position.shape}")
            model_edits[index] = normalizer.apply(position[None])[0]
        synced = prior.sync(normalizer.apply(rig.keypoints), model_edits)
        result = normalizer.invert(synced)
        for index in model_edits:  # exact in the user's units too (the frame round trip may round)
            result[index] = np.asarray(edits[index], dtype=np.float64)
        return result

    def sample_keypoints(self, rig: Rig, n: int, *, seed: int = 0, scale: float = 1.0,
                         limit: float | None = None) -> np.ndarray:
        """(n, K, 3) float64: prior-sampled variants of a rig's keypoints, in the rig's units (around its own
        keypoints, with the category's component variances times ``scale``; ``limit``: kept within that many
        standard deviations of each component, as :meth:`kpd.prior.KeypointPrior.sample` keeps them)."""
        prior = self._require_prior()
        normalizer = rig.normalizer
        sets = prior.sample(n, seed=seed, scale=scale, base=normalizer.apply(rig.keypoints), limit=limit)
        return np.stack([normalizer.invert(s) for s in sets]) if len(sets) else np.empty((0, rig.num_keypoints, 3))

    def _require_prior(self) -> KeypointPrior:
        if self._prior is None:
            raise BundleError(f"{self.bundle.path}: this bundle has no keypoint prior (exported without training "
                              "data); re-export it with --data to use the prior")
        return self._prior


def _ort_failures() -> tuple:
    """The exceptions onnxruntime raises for a graph it cannot open or run."""
    from onnxruntime.capi import onnxruntime_pybind11_state as state

    return (state.Fail, state.InvalidGraph, state.InvalidProtobuf, state.InvalidArgument, state.NotImplemented,
            state.NoSuchFile, state.RuntimeException, state.EPFail, RuntimeError, ValueError, MemoryError)


def _one_line(exc: BaseException) -> str:
    """onnxruntime's message on one line (it may span several, with a stack of its own)."""
    return " ".join(str(exc).split())[:500] or type(exc).__name__


def _session(ort, bundle: Bundle, spec: contract.GraphSpec, options, providers):
    try:
        return ort.InferenceSession(bundle.graph(spec), options, providers=providers)
    except _ort_failures() as exc:
        raise BundleError(f"{bundle.path}: {spec.file} cannot be opened by onnxruntime ({_one_line(exc)})") from exc


def _check_session(session, bundle: Bundle, spec: contract.GraphSpec) -> tuple[str, str]:
    """Read the input and output names and shapes from the session and check them against the manifest."""
    where = f"{bundle.path}: {spec.file}"
    meta = session.get_modelmeta().custom_metadata_map
    if meta.get(contract.META_GRAPH) != spec.key:
        raise BundleError(f"{where}: graph is {meta.get(contract.META_GRAPH)!r}; expected {spec.key!r}")
    if meta.get(contract.META_FORMAT_VERSION) != str(contract.FORMAT_VERSION):
        raise BundleError(f"{where}: graph format version {meta.get(contract.META_FORMAT_VERSION)!r}; this kpd reads "
                          f"{contract.FORMAT_VERSION}")
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1 or len(outputs) != 1:
        raise BundleError(f"{where}: expected one input and one output; got {len(inputs)} and {len(outputs)}")
    entry, result = inputs[0], outputs[0]
    if entry.type != "tensor(float)" or len(entry.shape) != 3 or entry.shape[2] != 3:
        raise BundleError(f"{where}: input {entry.name!r} must be float (B, N, 3); got {entry.type} {entry.shape}")
    if isinstance(entry.shape[0], int) or isinstance(entry.shape[1], int):
        raise BundleError(f"{where}: input {entry.name!r} must have dynamic batch and point axes; got {entry.shape}")
    k, c = bundle.num_keypoints, bundle.num_cage_vertices
    want = {"K": k, "C": c, "3": 3}
    expected = [want[a] for a in spec.output_axes[1:]]
    if len(result.shape) != 3 or list(result.shape[1:]) != expected:
        raise BundleError(f"{where}: output {result.name!r} has shape {result.shape}; expected "
                          f"[{contract.BATCH_AXIS}, {', '.join(map(str, expected))}] for K={k}, C={c}")
    if entry.name != contract.INPUT_NAME or result.name != spec.output:
        log.info("%s: input/output named %r/%r (contract: %r/%r); using the graph's names", where, entry.name,
                 result.name, contract.INPUT_NAME, spec.output)
    return entry.name, result.name


def _as_shape(shape: Shape) -> Mesh | PointSet:
    if isinstance(shape, (Mesh, PointSet)):
        return shape
    if isinstance(shape, (str, os.PathLike)):
        from kpd.io import read_shape

        return read_shape(shape)
    return PointSet(as_points(shape, "shape points"))


def _describe(shape: Any) -> str:
    if isinstance(shape, Mesh):
        return f"a mesh with {len(shape.triangles)} triangles"
    if isinstance(shape, PointSet):
        return f"a point set ({len(shape.points)} points)"
    return type(shape).__name__
