"""Rig: one shape bound to its keypoints and cage, ready to edit.

Moving keypoints by ``Δp`` moves the cage by ``Wᵀ Δp`` and every mesh vertex by its mean value coordinates times the
cage offset, so the whole edit is linear:

    vertices' = V₀ + B · Δp,    B = MVC · Wᵀ    # (V, 3) = (V, 3) + (V, K) · (K, 3)

``B`` is computed once at bind time, so an edit costs one (V × K) by (K × 3) product. The map is scale-free: ``B``
applies to offsets in the mesh's own units, so keypoints go in and vertices come out in the user's frame.

A bound rig holds ``B`` and not the (V, C) mean value coordinates: :func:`kpd.mvc_fast.mvc_project` computes
``MVC · Wᵀ`` block by block, so binding a scan of a million vertices needs memory for ``B`` only (docs/scale.md).
``B`` is kept in float32 when that moves no vertex by more than 1e-6 of the box diagonal for keypoint moves of up
to a diagonal, in float64 otherwise.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from kpd.basis import coincident_mvc_basis, coincident_mvc_weights, compact_basis, distinct_points, edit, edit_rows
from kpd.cage import Cage, default_m, fit_cage, influence_mask
from kpd.demo_format import read_demo
from kpd.errors import InputError
from kpd.geometry import Normalizer, as_points, sample_surface
from kpd.grouping import merge_coincident
from kpd.io import Mesh, atomic_output
from kpd.io.integrity import HASH_KEY, check_hash, content_hash, load_numpy
from kpd.memory import bind_memory, check_bind_memory
from kpd.mvc_fast import mvc_project, mvc_weights_compiled
from kpd.straighten import (STRAIGHTEN_REACH, STRAIGHTEN_THINNESS, STRAIGHTEN_TOLERANCE, has_sliver, merged_system,
                            straighten_basis, straighten_system)

# names kept importable from kpd.rig, where code and docs written against it look for them
from kpd.basis import compact_basis as _compact_basis  # noqa: F401
from kpd.basis import edit as _edit  # noqa: F401
from kpd.basis import edit_rows as _edit_rows  # noqa: F401
from kpd.grouping import first_occurrence_groups  # noqa: F401
from kpd.grouping import merge_coincident as _merge_coincident  # noqa: F401
from kpd.memory import available_memory  # noqa: F401
from kpd.straighten import _SEEDS_ON_TWO_THREADS, _STRAIGHTEN_CAP, _Correction, _factorised, _row  # noqa: F401
from kpd.straighten import _sliver_weight  # noqa: F401
from kpd.straighten import StraightenSystem as _StraightenSystem  # noqa: F401
from kpd.straighten import straighten_basis_reference as _straighten_basis_reference  # noqa: F401

__all__ = ["Rig", "RIG_FORMAT", "transfer_influence", "TRANSFER_SIGMA", "TRANSFER_RIDGE", "TRANSFER_SUPPORT",
           "straighten_basis", "STRAIGHTEN_THINNESS", "STRAIGHTEN_REACH", "STRAIGHTEN_TOLERANCE",
           "coincident_mvc_weights", "distinct_points", "coincident_mvc_basis", "bind_memory", "check_bind_memory"]

log = logging.getLogger(__name__)

RIG_FORMAT = "kpd-rig/3"  # /3 stores the edit basis, not the (V, C) weights; /1 and /2 files are still read
_READ_FORMATS = ("kpd-rig/1", "kpd-rig/2", RIG_FORMAT)  # /2 added the optional basis_correction to /1
_CAGE_SAMPLE_POINTS = 2048
TRANSFER_SIGMA = 0.3  # width of the neighbourhood each keypoint's motion is kept in, [-1, 1] box units
TRANSFER_RIDGE = 1e-4  # ridge of the transfer's least squares, relative to the neighbourhood's weight
TRANSFER_SUPPORT = 2  # rig-cage vertices per keypoint in a transfer, in multiples of the model's M


class Rig:
    """A mesh with keypoints, a cage, a masked influence matrix and the edit basis of its vertices.

    Parameters
    ----------
    mesh : Mesh, in the user's own units.
    normalizer : Normalizer from the user's frame to the model's [-1, 1] frame.
    keypoints : (K, 3) float64, rest keypoints in the model frame.
    cage : Cage, vertices (C, 3) in the model frame.
    influence : (K, C) float64, masked influence W (row k: how much each cage vertex follows keypoint k).
    weights : (V, C) float64 or None, MVC weights of the mesh vertices w.r.t. the cage; the edit basis is then
        ``weights @ influence.T`` (+ ``correction``), in float64. ``None`` when ``basis`` is given.
    correction : (V, K) float64 or None, added to ``weights @ influence.T``
        (:func:`~kpd.straighten.straighten_basis`); only with ``weights``.
    basis : (V, K) float32 or float64, the edit basis itself (what :meth:`bind` computes and :meth:`save` stores),
        instead of ``weights``.
    """

    def __init__(
        self,
        mesh: Mesh,
        normalizer: Normalizer,
        keypoints: Any,
        cage: Cage,
        influence: Any,
        weights: Any = None,
        correction: Any = None,
        *,
        basis: Any = None,
    ) -> None:
        keypoints = as_points(keypoints, "keypoints")
        cage = Cage(as_points(cage.vertices, "cage vertices", min_count=4), np.asarray(cage.faces, dtype=np.int64))
        influence = np.asarray(influence, dtype=np.float64)
        k, c, v = len(keypoints), len(cage.vertices), len(mesh.vertices)
        if influence.shape != (k, c):
            raise InputError(f"influence must have shape (K, C) = ({k}, {c}); got {influence.shape}")
        if cage.faces.ndim != 2 or cage.faces.shape[1] != 3 or cage.faces.min() < 0 or cage.faces.max() >= c:
            raise InputError(f"cage faces must be (F, 3) indices into {c} cage vertices")
        if not np.isfinite(influence).all():
            raise InputError("influence and MVC weights must be finite")
        if (weights is None) == (basis is None):
            raise InputError("a rig needs either the MVC weights (V, C) or the edit basis (V, K), not both")
        if weights is not None:
            weights = np.asarray(weights, dtype=np.float64)
            if weights.shape != (v, c):
                raise InputError(f"MVC weights must have shape (V, C) = ({v}, {c}); got {weights.shape}")
            if not np.isfinite(weights).all():
                raise InputError("influence and MVC weights must be finite")
            if correction is not None:
                correction = np.asarray(correction, dtype=np.float64)
                if correction.shape != (v, k) or not np.isfinite(correction).all():
                    raise InputError(f"basis correction must be (V, K) = ({v}, {k}) finite numbers; got "
                                     f"{correction.shape}")
            basis = weights @ influence.T  # (V, K)
            basis = basis if correction is None else basis + correction
        else:
            if correction is not None:
                raise InputError("a basis correction goes with MVC weights; an edit basis already holds it")
            basis = np.asarray(basis)
            if basis.dtype not in (np.float32, np.float64):
                basis = basis.astype(np.float64)
            if basis.shape != (v, k) or not np.isfinite(basis).all():
                raise InputError(f"edit basis must be (V, K) = ({v}, {k}) finite numbers; got {basis.shape}")
        self.mesh = mesh
        self.normalizer = normalizer
        self.cage = cage
        self.influence = influence
        self._weights = weights
        self._correction = correction
        self._straightened = correction is not None
        self._keypoints_model = keypoints
        self._rest_keypoints = normalizer.invert(keypoints)  # (K, 3) user units
        self._rest_vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)  # (V, 3)
        self._basis_t = np.ascontiguousarray(basis.T)  # (K, V): an edit reads each keypoint's column in order

    @property
    def weights(self) -> np.ndarray:
        """(V, C) float64: the MVC weights of the mesh vertices w.r.t. the cage.

        A rig read from weights (the authors' demo files, kpd-rig/1 and /2 files) holds them; a bound rig does
        not (its edits need only :attr:`basis`) and computes them here on each call, which takes V × C × 8 bytes.
        """
        if self._weights is not None:
            return self._weights
        vertices = self.normalizer.apply(self.mesh.vertices)
        points, inverse = merge_coincident(vertices)
        return mvc_weights_compiled(points, self.cage.vertices, self.cage.faces)[inverse]

    @property
    def correction(self) -> np.ndarray | None:
        """(V, K) float64 or None: what the straightening of slivers (:func:`~kpd.straighten.straighten_basis`) added
        to the edit basis ``weights @ influence.T``; ``None`` when nothing was. A bound rig computes it on each call."""
        if not self._straightened:
            return None
        if self._correction is not None:
            return self._correction
        vertices = self.normalizer.apply(self.mesh.vertices)
        return self.basis - coincident_mvc_basis(vertices, self.cage, self.influence.T)

    # --- construction -----------------------------------------------------------------------------------------

    @classmethod
    def bind(
        cls,
        mesh: Mesh,
        keypoints: Any,
        influence: Any = None,
        *,
        normalizer: Normalizer | None = None,
        cage: Cage | None = None,
        points: Any = None,
        m: int | None = None,
        enclose: bool = True,
        seed: int = 0,
        straighten: bool = True,
        model_vertices: Any = None,
        check_memory: bool = True,
    ) -> "Rig":
        """Bind a mesh to keypoints predicted (or picked) in the model's [-1, 1] frame.

        Parameters
        ----------
        mesh : Mesh in the user's units.
        keypoints : (K, 3) float64, in the model frame of ``normalizer``.
        influence : (K, C) float64, the unmasked influence W = W_C + W_I; ``None`` gives ones, so each keypoint
            drags its ``m`` nearest cage vertices rigidly (a rig from hand-picked keypoints).
        normalizer : user frame -> model frame; fitted on the mesh vertices when ``None``.
        cage : cage in the model frame; fitted when ``None`` (docs/method.md §4 on ``points``).
        points : (N, 3) float64, model-frame surface points to fit the cage on; a seeded sample when ``None``.
        m : cage vertices per keypoint in the locality mask; ``default_m(C, K)`` when ``None``.
        enclose : grow the fitted cage until every mesh vertex is inside it (beyond the authors' rule, which leaves
            some points outside, where MVC misplaces them).
        seed : seed of the surface sample.
        straighten : keep the mesh's sliver triangles from turning over in edits
            (:func:`~kpd.straighten.straighten_basis`).
        model_vertices : (V, 3) float64 ``normalizer.apply(mesh.vertices)``, when the caller has it already (with
            ``normalizer`` given): not computed again.
        check_memory : refuse a mesh too large for the memory available (:func:`kpd.memory.check_bind_memory`)
            before the basis is computed; ``False`` when the caller has checked it already.
        """
        if not isinstance(mesh, Mesh):
            raise InputError(f"mesh must be a kpd.io.Mesh; got {type(mesh).__name__}")
        normalizer = normalizer if normalizer is not None else Normalizer().fit(mesh.vertices)
        keypoints = as_points(keypoints, "keypoints")
        if model_vertices is None:
            vertices = normalizer.apply(mesh.vertices)  # (V, 3)
        else:
            vertices = as_points(model_vertices, "model_vertices", min_count=0)
            if vertices.shape != mesh.vertices.shape:
                raise InputError(f"model_vertices must have the mesh's shape {mesh.vertices.shape}; got "
                                 f"{vertices.shape}")
        if cage is None:
            if points is None:
                points = sample_surface(vertices, mesh.triangles, _CAGE_SAMPLE_POINTS, seed=seed).points
            fit_points = as_points(points, "points")
            if enclose:
                fit_points = np.concatenate([fit_points, vertices])
            cage = fit_cage(fit_points, enclose=enclose)
        k, c = len(keypoints), len(cage.vertices)
        influence = np.ones((k, c)) if influence is None else np.asarray(influence, dtype=np.float64)
        if influence.shape != (k, c):
            raise InputError(f"influence must have shape (K, C) = ({k}, {c}); got {influence.shape}")
        m = default_m(c, k) if m is None else int(m)
        masked = influence * influence_mask(keypoints, cage.vertices, m)
        if check_memory:
            check_bind_memory(len(vertices), len(mesh.triangles), k)
        # the basis is computed once per distinct position, the positions in the mesh's order: its neighbours are
        # near each other in memory (sorted order halves the speed of the straightening's passes over the mesh).
        # Grouped in the mesh's own units, by the mesh (a command drawing it at once uses the same groups)
        first, inverse = mesh.position_groups()
        points = vertices if len(first) == len(vertices) else vertices[first]
        triangles = np.ascontiguousarray(mesh.triangles, dtype=np.int64)
        building = None
        # the straightening's system (the edge graph, the slivers' terms) does not depend on the basis: it is made on
        # a thread of its own while the MVC basis takes the others (whose threads leave part of the cores idle)
        with ThreadPoolExecutor(1, thread_name_prefix="kpd-straighten") as pool:
            if straighten and len(triangles) and has_sliver(np.ascontiguousarray(vertices), triangles,
                                                            STRAIGHTEN_THINNESS):
                # the system looks the triangles' corners up on the distinct points itself: no renumbered copy of
                # the triangles made here first (a pass over them all, before the MVC)
                building = pool.submit(merged_system, points, triangles, inverse if len(points) < len(vertices)
                                       else None)
            basis = mvc_project(points, cage.vertices, cage.faces, masked.T)  # (n, K) float64
        straightened = building is not None and straighten_system(building.result(), basis, STRAIGHTEN_TOLERANCE)
        del building
        basis = compact_basis(basis)
        if len(points) < len(vertices):
            basis = basis[inverse]  # (V, K)
        del points
        rig = cls(mesh, normalizer, keypoints, cage, masked, basis=basis)
        rig._straightened = straightened
        return rig

    # --- editing ----------------------------------------------------------------------------------------------

    @property
    def num_keypoints(self) -> int:
        return len(self._rest_keypoints)

    @property
    def keypoints(self) -> np.ndarray:
        """(K, 3) float64: the rest keypoints in the user's units."""
        return self._rest_keypoints.copy()

    @property
    def basis(self) -> np.ndarray:
        """(V, K) float32 or float64: vertex offset per unit keypoint offset (read-only view; float32 when that keeps
        edits within 1e-6 of the box diagonal, see :func:`kpd.basis.compact_basis`)."""
        view = self._basis_t.T  # (V, K), Fortran-ordered
        view.flags.writeable = False
        return view

    def _offsets(self, keypoints: Any) -> np.ndarray:
        keypoints = np.asarray(keypoints, dtype=np.float64)
        if keypoints.shape != self._rest_keypoints.shape:
            raise InputError(f"keypoints must have shape ({self.num_keypoints}, 3); got {keypoints.shape}")
        if not np.isfinite(keypoints).all():
            raise InputError("keypoints must be finite")
        return keypoints - self._rest_keypoints  # (K, 3)

    def deform(self, keypoints: Any, *, out: np.ndarray | None = None, rows: Any = None) -> np.ndarray:
        """Mesh vertices for moved keypoints.

        Parameters
        ----------
        keypoints : (K, 3) float64, in the user's units.
        out : optional (V, 3) float64 buffer to write into (avoids an allocation per edit).
        rows : optional (P,) int, vertex indices: only these rows of ``out`` are computed and written, the others are
            left as they were (a coarse stand-in of a large mesh needs only its own vertices).

        Returns
        -------
        vertices : (V, 3) float64, in the user's units; the rest vertices exactly when no keypoint moved.
        """
        offsets = self._offsets(keypoints)
        if out is None:
            out = np.empty_like(self._rest_vertices)
        elif out.shape != self._rest_vertices.shape or out.dtype != np.float64 or not out.flags.c_contiguous:
            raise InputError(f"out must be a C-contiguous ({len(self._rest_vertices)}, 3) float64 array; got "
                             f"{out.shape} {out.dtype}")
        # One pass over the basis on the calling thread, in float64: the product is memory-bound, and a
        # multi-threaded BLAS call stalls for tens of milliseconds when another process holds the other cores.
        if rows is None:
            edit(self._basis_t, offsets, self._rest_vertices, out)
        else:
            rows = np.asarray(rows)
            if rows.ndim != 1 or rows.dtype.kind not in "iu" or (len(rows) and (
                    rows.min() < 0 or rows.max() >= len(out))):
                raise InputError(f"rows must be (P,) vertex indices in [0, {len(out)})")
            edit_rows(self._basis_t, offsets, self._rest_vertices, rows.astype(np.int64, copy=False), out)
        return out

    def deform_cage(self, keypoints: Any) -> np.ndarray:
        """(C, 3) float64: the moved cage in the user's units."""
        offsets = self.normalizer.apply_vectors(self._offsets(keypoints))
        return self.normalizer.invert(self.cage.vertices + self.influence.T @ offsets)

    def deformed_mesh(self, keypoints: Any) -> Mesh:
        """A copy of the mesh (topology, UVs, colours, textures kept) with the deformed vertices."""
        return self.mesh.with_vertices(self.deform(keypoints))

    def moved(self, moves: dict[int, Any]) -> np.ndarray:
        """(K, 3) keypoints with ``{index: (dx, dy, dz)}`` offsets (user units) added to the rest keypoints."""
        keypoints = self.keypoints
        for index, delta in moves.items():
            if not 0 <= index < self.num_keypoints:
                raise InputError(f"keypoint index must lie in [0, {self.num_keypoints}); got {index}")
            delta = np.asarray(delta, dtype=np.float64)
            if delta.shape != (3,) or not np.isfinite(delta).all():
                raise InputError(f"a keypoint move needs 3 finite numbers; got {delta.tolist()}")
            keypoints[index] += delta
        return keypoints

    # --- files ------------------------------------------------------------------------------------------------

    def save(self, path: str | os.PathLike) -> None:
        """Write the rig to a ``.npz`` file (no pickle), atomically: the mesh, keypoints, cage, influence and the
        (V, K) edit basis (format kpd-rig/3; the (V, C) weights are not stored)."""
        arrays = {
            "format": np.array(RIG_FORMAT),
            "keypoints": self._keypoints_model,
            "cage_vertices": self.cage.vertices,
            "cage_faces": self.cage.faces,
            "influence": self.influence,
            "basis": self.basis,
            "straightened": np.array(self._straightened),
            "normalizer_center": self.normalizer.center_,
            "normalizer_scale": np.array(self.normalizer.scale_),
        }
        for name, value in _mesh_arrays(self.mesh).items():
            arrays["mesh_" + name] = value
        if len(self.mesh.vertices) < 2**31:  # read back as int64 by the mesh type; half the bytes to inflate
            arrays["mesh_triangles"] = arrays["mesh_triangles"].astype(np.int32)
        arrays[HASH_KEY] = np.array(content_hash(arrays))
        with atomic_output(path) as tmp:
            # an .npz as numpy.savez_compressed writes it, at the fastest deflate level: several times faster to
            # write than the default level, a few percent larger
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
                for name, value in arrays.items():
                    value = np.asanyarray(value)
                    member: str | zipfile.ZipInfo = name + ".npy"
                    if value.dtype.kind == "f" and value.size > 1 << 16:  # floats barely deflate: stored as they are
                        member = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                        member.compress_type = zipfile.ZIP_STORED
                    with archive.open(member, "w", force_zip64=True) as fh:
                        np.lib.format.write_array(fh, value, allow_pickle=False)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Rig":
        """Read a rig written by :meth:`save` (kpd-rig/3, or the older kpd-rig/1 and /2 that stored the (V, C)
        weights); a damaged file (bad zip, bad CRC, content not matching the stored sha256) raises
        :class:`~kpd.errors.InputError`."""
        path = Path(path)
        if path.is_dir():
            raise InputError(f"{path}: is a folder; a rig is a .npz file (a folder of the authors' demo files is "
                             "read by Rig.from_demo)")
        if not path.is_file():
            raise InputError(f"{path}: no such rig file")
        arrays = load_numpy(path, "kpd rig (.npz)")
        if not isinstance(arrays, dict):
            raise InputError(f"{path}: a single array, not a kpd rig (.npz)")
        fmt = str(arrays.get("format", ""))
        if fmt not in _READ_FORMATS:
            raise InputError(f"{path}: rig format must be {RIG_FORMAT!r}; got {fmt or 'none'!r}")
        check_hash(arrays, arrays.get(HASH_KEY), str(path), "rig")
        try:
            mesh = _mesh_from_arrays({k[5:]: v for k, v in arrays.items() if k.startswith("mesh_")})
            normalizer = Normalizer.from_dict(
                {"center": arrays["normalizer_center"].tolist(), "scale": float(arrays["normalizer_scale"])}
            )
            cage = Cage(arrays["cage_vertices"], arrays["cage_faces"])
            if "weights" in arrays:  # kpd-rig/1 and /2: the (V, C) weights, and in /2 the straightening's correction
                rig = cls(mesh, normalizer, arrays["keypoints"], cage, arrays["influence"], arrays["weights"],
                          arrays.get("basis_correction"))
            else:
                rig = cls(mesh, normalizer, arrays["keypoints"], cage, arrays["influence"], basis=arrays["basis"])
                rig._straightened = bool(arrays.get("straightened", False))
        except KeyError as exc:
            raise InputError(f"{path}: rig file lacks {exc.args[0]!r}") from exc
        except (TypeError, ValueError, IndexError) as exc:  # InputError too: arrays of another type or shape
            raise InputError(f"{path}: not a valid kpd rig ({exc})") from exc
        return rig

    @classmethod
    def from_demo(cls, directory: str | os.PathLike) -> "Rig":
        """Import a rig in the authors' project-page demo format (:func:`kpd.demo_format.read_demo`, docs/method.md
        §17). Everything is already in the model frame, so the normaliser is the identity."""
        demo = read_demo(directory)
        identity = Normalizer.from_dict({"center": [0.0, 0.0, 0.0], "scale": 1.0})
        return cls(demo.mesh, identity, demo.keypoints, demo.cage, demo.influence, demo.weights)

    def __repr__(self) -> str:
        return (
            f"Rig(V={len(self._rest_vertices)}, K={self.num_keypoints}, C={len(self.cage.vertices)}, "
            f"F={len(self.cage.faces)})"
        )


def transfer_influence(
    influence: Any,
    keypoints: Any,
    points: Any,
    source: Cage,
    target: Cage,
    m: int,
    *,
    sigma: float = TRANSFER_SIGMA,
    ridge: float = TRANSFER_RIDGE,
    support: int | None = None,
) -> np.ndarray:
    """Re-express an influence matrix learned for one cage of a shape on another, tighter cage of the same shape.

    The network's influence W moves the cage it was trained with (fitted at the training stop distance, 0.4 of the
    [-1, 1] box). Mean value coordinates of a cage that far from the shape are smooth but wide: a keypoint's move
    reaches the far side of the shape. A cage fitted closer to the shape is more local, but the learned W applied to
    it as it is overshoots (its coefficients of up to 5-7 were learned to move a distant cage) and folds the
    surface. Instead, for each keypoint ``k`` this solves for the row on the target cage whose motion of the
    shape's surface reproduces, near the keypoint, the motion the learned row gives through the source cage::

        min_w  sum_p g_p (A_t[p, mask_k] w - A_s[p] W_k)^2 + ridge * sum_p g_p * |w|^2,
        g_p = exp(-|p - keypoint_k|^2 / (2 sigma^2)),

    with ``A_s``, ``A_t`` the mean value coordinates of the surface points in the two cages and ``mask_k`` the
    target cage's ``support`` vertices nearest the keypoint. What the keypoint moves (its part) moves as before;
    what is far from it follows the tighter cage's smaller reach. A tighter cage's vertices lie closer together, so
    the model's ``m`` nearest of them cover less of the shape than on the training cage; ``support = 2 m`` (the
    runtime's choice, :data:`TRANSFER_SUPPORT`) keeps the corners of a part that no keypoint sits on moving with it
    (chosen on training shapes: it folds less in single and semantic edits than ``m`` and still halves the
    far-side leakage of the training cage).

    Parameters
    ----------
    influence : (K, C) float64, the learned influence for ``source`` (masked or not: it is masked with ``m``).
    keypoints : (K, 3) float64, model frame.
    points : (N, 3) float64, surface points of the shape, model frame (the network's input sample).
    source, target : the cages (same template topology, C vertices each), model frame.
    m : the model's cage vertices per keypoint (the learned influence's mask on ``source``).
    sigma : neighbourhood width (> 0); ridge : regularisation (>= 0).
    support : target-cage vertices per keypoint (default ``m``).

    Returns
    -------
    (K, C) float64, masked to the target cage's ``support`` nearest vertices per keypoint.
    """
    keypoints = as_points(keypoints, "keypoints")
    points = as_points(points, "points")
    influence = np.asarray(influence, dtype=np.float64)
    k, c = len(keypoints), len(source.vertices)
    if influence.shape != (k, c) or len(target.vertices) != c:
        raise InputError(f"influence must be (K, C) = ({k}, {c}) for two cages of {c} vertices; got "
                         f"{influence.shape} and a target of {len(target.vertices)}")
    if not (np.isfinite(sigma) and sigma > 0 and np.isfinite(ridge) and ridge >= 0):
        raise InputError(f"transfer needs sigma > 0 and ridge >= 0; got {sigma!r}, {ridge!r}")
    source_rows = influence * influence_mask(keypoints, source.vertices, m)  # (K, C)
    moved = mvc_project(points, source.vertices, source.faces, source_rows.T)  # (N, K) motion per keypoint
    coords = mvc_weights_compiled(points, target.vertices, target.faces)  # (N, C)
    mask = influence_mask(keypoints, target.vertices, m if support is None else min(int(support), c))  # (K, C)
    result = np.zeros((k, c))
    for i in range(k):
        d2 = np.sum((points - keypoints[i]) ** 2, axis=1)  # (N,)
        g = np.exp(-(d2 - d2.min()) / (2.0 * sigma**2))  # the nearest point weighs 1, whatever the keypoint's offset
        x = coords[:, mask[i]]  # (N, M)
        gram = x.T @ (g[:, None] * x) + ridge * g.sum() * np.eye(x.shape[1])
        result[i, mask[i]] = np.linalg.solve(gram, x.T @ (g * moved[:, i]))
    return result


def _mesh_arrays(mesh: Mesh) -> dict[str, np.ndarray]:
    """The mesh's array fields (None fields left out; textures as texture_0, texture_1, ...)."""
    arrays = {}
    for field in dataclasses.fields(mesh):
        value = getattr(mesh, field.name)
        if value is None or field.name == "path":
            continue
        if field.name == "textures":
            for i, image in enumerate(value):
                arrays[f"texture_{i}"] = np.asarray(image)
            continue
        arrays[field.name] = np.asarray(value)
    return arrays


def _mesh_from_arrays(arrays: dict[str, np.ndarray]) -> Mesh:
    names = {f.name for f in dataclasses.fields(Mesh)}
    textures = [arrays[k] for k in sorted((k for k in arrays if k.startswith("texture_")), key=lambda s: int(s[8:]))]
    kwargs = {k: v for k, v in arrays.items() if k in names}
    if "textures" in names:
        kwargs["textures"] = textures
    return Mesh(**kwargs)
