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
from typing import Any, Callable

import numba  # before numba.core's modules, which cannot be imported first
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from kpd._compiled import njit
from kpd.cage import Cage, cage_faces_from_vertices, default_m, fit_cage, influence_mask
from kpd.errors import InputError
from kpd.geometry import Normalizer, as_points, sample_surface
from kpd.grouping import first_occurrence_groups, merge_coincident, same_corners
from kpd.io import Mesh, atomic_output
from kpd.io.integrity import HASH_KEY, check_hash, content_hash, load_numpy
from kpd.mvc import mvc_weights
from kpd.mvc_fast import mvc_project, mvc_weights_compiled

__all__ = ["Rig", "RIG_FORMAT", "transfer_influence", "TRANSFER_SIGMA", "TRANSFER_RIDGE", "TRANSFER_SUPPORT",
           "straighten_basis", "STRAIGHTEN_THINNESS", "STRAIGHTEN_REACH", "STRAIGHTEN_TOLERANCE",
           "coincident_mvc_weights", "distinct_points", "coincident_mvc_basis", "bind_memory", "check_bind_memory"]

log = logging.getLogger(__name__)

RIG_FORMAT = "kpd-rig/3"  # /3 stores the edit basis, not the (V, C) weights; /1 and /2 files are still read
_READ_FORMATS = ("kpd-rig/1", "kpd-rig/2", RIG_FORMAT)  # /2 added the optional basis_correction to /1
_CAGE_SAMPLE_POINTS = 2048
_FLOAT32_ROW_SUM = 16.0  # a basis whose rows' absolute sums stay below this is kept in float32 (see _compact_basis)
TRANSFER_SIGMA = 0.3  # width of the neighbourhood each keypoint's motion is kept in, [-1, 1] box units
TRANSFER_RIDGE = 1e-4  # ridge of the transfer's least squares, relative to the neighbourhood's weight
TRANSFER_SUPPORT = 2  # rig-cage vertices per keypoint in a transfer, in multiples of the model's M
STRAIGHTEN_THINNESS = 0.1  # a triangle is a sliver when its height is below this share of its longest edge
STRAIGHTEN_REACH = 0.1  # how far a sliver's straightening spreads over the surface, [-1, 1] box units
STRAIGHTEN_TOLERANCE = 1e-6  # the straightening is solved where it changes the basis by more than this (0: everywhere)
_STRAIGHTEN_ENDS = 20.0  # how much more firmly the ends of straight runs (never a sliver's third corner) are held
_STRAIGHTEN_CAP = 1e8  # largest weight of one sliver's straightness (a collinear triangle's weight is infinite)


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
    correction : (V, K) float64 or None, added to ``weights @ influence.T`` (:func:`straighten_basis`); only with
        ``weights``.
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

        A rig read from weights (the authors' demo files, rig files before kpd-rig/3) holds them; a bound rig does
        not (its edits need only :attr:`basis`) and computes them here on each call, which takes V × C × 8 bytes.
        """
        if self._weights is not None:
            return self._weights
        vertices = self.normalizer.apply(self.mesh.vertices)
        points, inverse = _merge_coincident(vertices)
        return mvc_weights_compiled(points, self.cage.vertices, self.cage.faces)[inverse]

    @property
    def correction(self) -> np.ndarray | None:
        """(V, K) float64 or None: what the straightening of slivers (:func:`straighten_basis`) added to the edit
        basis ``weights @ influence.T``; ``None`` when nothing was. A bound rig computes it on each call."""
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
        straighten : keep the mesh's sliver triangles from turning over in edits (:func:`straighten_basis`).
        model_vertices : (V, 3) float64 ``normalizer.apply(mesh.vertices)``, when the caller has it already (with
            ``normalizer`` given): not computed again.
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
        check_bind_memory(len(vertices), len(mesh.triangles), k)
        # the basis is computed once per distinct position, the positions in the mesh's order: its neighbours are
        # near each other in memory (the straightening's passes over the mesh took twice as long in sorted order).
        # Grouped in the mesh's own units, by the mesh (a command drawing it at once uses the same groups)
        first, inverse = mesh.position_groups()
        points = vertices if len(first) == len(vertices) else vertices[first]
        triangles = np.ascontiguousarray(mesh.triangles, dtype=np.int64)
        building = None
        # the straightening's system (the edge graph, the slivers' terms) does not depend on the basis: it is made on
        # a thread of its own while the MVC basis takes the others (whose two threads leave part of the two cores
        # idle: 2.9 s of CPU in 1.9 s at 1.37M points)
        with ThreadPoolExecutor(1, thread_name_prefix="kpd-straighten") as pool:
            if straighten and len(triangles) and _has_sliver(np.ascontiguousarray(vertices), triangles,
                                                             STRAIGHTEN_THINNESS):
                # the system looks the triangles' corners up on the distinct points itself: no renumbered copy of
                # the triangles made here first (a pass over them all, 0.3 s at 5.5M triangles, before the MVC)
                building = pool.submit(_merged_system, points, triangles, inverse if len(points) < len(vertices)
                                       else None)
            basis = mvc_project(points, cage.vertices, cage.faces, masked.T)  # (n, K) float64
        straightened = building is not None and _straighten_system(building.result(), basis, STRAIGHTEN_TOLERANCE)
        del building
        basis = _compact_basis(basis)
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
        edits within 1e-6 of the box diagonal, see :func:`_compact_basis`)."""
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
            _edit(self._basis_t, offsets, self._rest_vertices, out)
        else:
            rows = np.asarray(rows)
            if rows.ndim != 1 or rows.dtype.kind not in "iu" or (len(rows) and (
                    rows.min() < 0 or rows.max() >= len(out))):
                raise InputError(f"rows must be (P,) vertex indices in [0, {len(out)})")
            _edit_rows(self._basis_t, offsets, self._rest_vertices, rows.astype(np.int64, copy=False), out)
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
            # an .npz as numpy.savez_compressed writes it, at the fastest deflate level: a scan's rig is written in
            # a second or two instead of several, and is a few percent larger
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
        """Import a rig in the authors' project-page demo format (docs/method.md §17).

        Reads ``source_vertices.txt`` (V × 3), ``source_faces.txt`` (T × 3), ``source_keypoints.txt`` (K lines
        ``%03d x y z``), ``cage.txt`` (C × 3), ``influence.txt`` (K × C, masked) and, when present, ``weights.txt``
        (V × C); missing weights are computed. The cage's triangles are recovered from its vertex directions.
        Everything is already in the model frame, so the normaliser is the identity.
        """
        directory = Path(directory)
        if not directory.is_dir():
            raise InputError(f"{directory}: not a folder of demo files")
        vertices = _read_table(directory / "source_vertices.txt", 3)
        faces = _read_table(directory / "source_faces.txt", 3)
        if not np.allclose(faces, np.round(faces)):
            raise InputError(f"{directory / 'source_faces.txt'}: face indices must be integers")
        triangles = np.round(faces).astype(np.int64)
        keypoints = _read_table(directory / "source_keypoints.txt", None)
        if keypoints.shape[1] == 4:
            keypoints = keypoints[:, 1:]
        if keypoints.shape[1] != 3:
            raise InputError(f"{directory / 'source_keypoints.txt'}: rows must be 'x y z' or 'index x y z'")
        cage_vertices = _read_table(directory / "cage.txt", 3)
        influence = _read_table(directory / "influence.txt", len(cage_vertices))
        mesh = Mesh(vertices=vertices, triangles=triangles)
        _check_faces(triangles, len(vertices), directory / "source_faces.txt")
        cage = Cage(cage_vertices, cage_faces_from_vertices(cage_vertices))
        weights_file = directory / "weights.txt"
        if weights_file.exists():
            weights = _read_table(weights_file, len(cage_vertices))
        else:
            weights = mvc_weights(vertices, cage.vertices, cage.faces)
        identity = Normalizer.from_dict({"center": [0.0, 0.0, 0.0], "scale": 1.0})
        return cls(mesh, identity, keypoints, cage, influence, weights)

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


def straighten_basis(
    basis: Any,
    vertices: Any,
    triangles: Any,
    *,
    thinness: float = STRAIGHTEN_THINNESS,
    reach: float = STRAIGHTEN_REACH,
    tolerance: float = STRAIGHTEN_TOLERANCE,
) -> np.ndarray:
    """The smallest smooth correction of an edit basis that keeps the mesh's sliver triangles from turning over.

    CAD meshes are full of slivers: long triangles whose third corner lies within a fraction of a percent of the
    long edge (strips along a table's edges and legs, fans across lattice panels, collinear runs of vertices). A
    cage deformation is smooth, so it bends a long edge slightly; the mesh draws the edge straight between its two
    ends while the third corner follows the bend, and a bend larger than the sliver's height carries that corner
    across the edge: the triangle turns over and shows as a dark crease. This solves, once per rig, for a
    correction ``D`` of the (V, K) basis (each keypoint's column alike) that makes every sliver's third corner
    move as the linear interpolation of its long edge's ends, spread smoothly over the surface::

        min_D  sum_slivers min((L/h)^2, cap) |B_c + D_c - (1-s)(B_a + D_a) - s(B_b + D_b)|^2
             + sum_edges |D_i - D_j|^2 / l_ij^2  +  sum_v e_v (a_v / mean a) |D_v|^2 / reach^2

    with ``a, b`` the ends of a sliver's longest edge (length ``L``), ``c`` its third corner at height ``h`` and
    projected at ``s`` along it, ``l_ij`` the mesh's edge lengths and ``a_v`` the vertices' areas. The edge term
    keeps small details moving with their neighbours (a correction of the corners alone folds the small triangles
    around them); the last term keeps the correction within about ``reach`` of the slivers, so that a keypoint's
    move reaches no farther than before. ``e_v`` is 20 for the vertices that are never a sliver's third corner (the
    ends of straight runs: a leg's foot, a panel's corner) and 1 otherwise, so that a run is straightened by moving
    its middle rather than its ends: a chair's feet stay on the floor when its back is raised. Straight features
    (a table's top edge, a lattice's slats, a leg) stay straight.
    A translation is kept exactly; any other affine motion (which turns nothing over) changes by no more than a
    sliver's height times its gradient across the sliver: the straightness asks a sliver to keep its thickness.
    (Asking instead for the smooth field's own change across each sliver, through one more MVC evaluation per
    sliver, gave the same folds and leakage on the training shapes; CAD meshes have about as many slivers as
    vertices, so it would double the MVC cost of binding.)

    The system is solved on the mesh with coincident vertices merged (CAD meshes store one vertex per corner), so
    the corrected mesh has no cracks. ``thinness`` (0.1), ``reach`` (0.1) and the ends' 20 were chosen on 12
    ModelNet10 training chairs and tables each (``benchmarks/bench_edits.py`` measures them on the test shapes):
    their worst semantic edit folds 0.09% (chairs) and 0.56% (tables: 13 of one table's 2,310) of the triangles,
    against 1.29% and 2.38% uncorrected, and the far-side leakage of single moves grows by 3% and 15%. Holding
    the ends as firmly as the rest folds a little less (0.35% of that table) but lowers feet: on ModelNet10
    chair_0890 with its back raised they move by 1.5% of the raise, by 0.8% at 20 (the rig test's limit is 1%).

    The system is solved where it matters, not over every vertex: around the slivers whose own term alone would
    move one of their corners by more than ``tolerance`` (a vertex offset per unit keypoint offset; one Jacobi
    step: the straightness times the sliver's weight over the corner's diagonal entry), or move the third corner
    across the sliver's height in a move of half the model box of every keypoint, grown until the correction just
    outside is below ``tolerance`` (:class:`_StraightenSystem`). On a native mesh a thin sliver's weight is most of
    its corners' diagonal, and that step is its straightness itself. On a real scan only a few percent of the
    triangles are slivers, and this solves 8% of the points (a 324k-vertex shoe scan: 0.22 s on a quiet machine,
    against 3.0 s for every piece); the result differs from the solve over every piece with a sliver
    (``tolerance=0``, as kpd did before) by at most 1.4e-5 there and 4e-7 on the test chairs (the many slivers
    left out, each moving the correction by less than ``tolerance``, and the region's growth solved as patches
    with the rest held, add up to that). A CAD mesh subdivided to a scan's size keeps a sliver in every triangle
    of a sliver, but the edges around each one grow stiffer with each subdivision, and their many small terms add
    up to a smooth correction over the whole mesh that turns no triangle over: on a ShapeNet chair subdivided to
    86k and 342k points this solves 45% and 26% of the points, differs from the solve over every piece by 2.0e-4
    and 9.0e-4, and turns over as many triangles in 72 single moves (each keypoint by 10% of the box along each
    axis, both ways) at worst.

    Parameters
    ----------
    basis : (V, K) float64, vertex offset per unit keypoint offset (:attr:`Rig.basis`).
    vertices : (V, 3) float64, rest vertices in the model frame.
    triangles : (T, 3) int, the mesh's triangles.
    thinness : a triangle is a sliver when its height is below ``thinness`` times its longest edge (0 < t <= 1).
    reach : (> 0) spread of the correction, in the units of ``vertices``.
    tolerance : (>= 0) the correction is solved for where it exceeds this; 0 solves every connected piece that has
        a sliver, exactly.

    Returns
    -------
    (V, K) float64, the corrected basis (``basis`` itself, not a copy, when the mesh has no sliver).
    """
    basis, vertices, triangles = _check_straighten(basis, vertices, triangles, thinness, reach)
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise InputError(f"the straightening's tolerance must be a number >= 0; got {tolerance!r}")
    if not len(triangles) or not _has_sliver(np.ascontiguousarray(vertices), triangles, float(thinness)):
        return basis  # no sliver (the cheap test first: merging below does not make new ones)
    points, inverse = _distinct_in_order(vertices)  # in the mesh's order, as Rig.bind
    first = np.zeros(len(points), dtype=np.int64)
    first[inverse[::-1]] = np.arange(len(vertices))[::-1]  # one vertex per merged point
    merged = np.ascontiguousarray(basis[first])  # coincident vertices have the same basis rows
    changed = _straighten_merged(merged, points, inverse[triangles], thinness, reach, tolerance)
    return merged[inverse] if changed else basis


def _straighten_merged(basis: np.ndarray, points: np.ndarray, triangles: np.ndarray, thinness: float, reach: float,
                       tolerance: float) -> bool:
    """:func:`straighten_basis` of the (n, K) basis of distinct ``points`` (n, 3), ``triangles`` indexing them, in
    place: only the rows of the points solved change. Returns whether there was a sliver to straighten."""
    return _straighten_system(_StraightenSystem(points, triangles, thinness, reach), basis, tolerance)


def _merged_system(points: np.ndarray, triangles: np.ndarray, inverse: np.ndarray | None) -> "_StraightenSystem":
    """The straightening's system of a mesh's ``triangles`` on its distinct ``points``: ``inverse`` (V,) maps each
    vertex to its point (None when no two vertices coincide)."""
    return _StraightenSystem(points, triangles, STRAIGHTEN_THINNESS, STRAIGHTEN_REACH, point_of=inverse)


def _straighten_system(system: "_StraightenSystem", basis: np.ndarray, tolerance: float) -> bool:
    """:func:`_straighten_merged` with its system made already."""
    if system.slivers == 0:
        return False
    correction = system.solve(basis, float(tolerance))
    basis[correction.rows] += correction.values
    return True


class _Correction:
    """The straightening's correction of the points solved so far, zero elsewhere: ``values`` (m, K), the rows of
    the points ``rows`` (m,), and each point's row in ``slot`` (n,) (-1: not solved). On a scan the region is a few
    percent of the points: an (n, K) array, faulted in page by page where the region's points fall and then added
    whole, took longer than the region's solve (0.57 s of 1.3 s at 1.26M points)."""

    def __init__(self, n: int, k: int) -> None:
        self.slot = np.full(n, -1, dtype=np.int64)
        self.rows = np.zeros(0, dtype=np.int64)
        self.values = np.zeros((0, k))

    def reserve(self, points: np.ndarray) -> None:
        """Rows for those of ``points`` (p,) int64 that have none, zero until set (before threads set them)."""
        new = points[self.slot[points] < 0]
        if len(new):
            self.slot[new] = np.arange(len(self.rows), len(self.rows) + len(new))
            self.rows = np.concatenate([self.rows, new])
            self.values = np.concatenate([self.values, np.zeros((len(new), self.values.shape[1]))])

    def set(self, points: np.ndarray, values: np.ndarray) -> None:
        """The correction of ``points`` (p,) int64 is ``values`` (p, K) (rows reserved for them already, or now)."""
        self.reserve(points)
        self.values[self.slot[points]] = values


def _factorised(system: Any) -> Callable[[np.ndarray], np.ndarray]:
    """``solve(rhs)`` for ``system``, a symmetric positive definite sparse matrix (CSC, both triangles): ``rhs`` (n, K)
    to (n, K), by QDLDL's LDLᵀ factorisation in an approximate minimum-degree order (which lets go of the GIL).
    Half the time of SuperLU's LU in its symmetric mode on the straightening's systems (45 ms against 90 ms for
    30k points of a subdivided CAD chair), to the same solution within rounding."""
    import qdldl

    factor = qdldl.Solver(system)

    def solve(rhs: np.ndarray) -> np.ndarray:
        out = np.empty(rhs.shape)
        for k in range(rhs.shape[1]):
            out[:, k] = factor.solve(np.ascontiguousarray(rhs[:, k]))
        return out

    return solve


def _check_straighten(basis: Any, vertices: Any, triangles: Any, thinness: float, reach: float) -> tuple:
    basis = np.asarray(basis, dtype=np.float64)
    vertices = as_points(vertices, "vertices")
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    if basis.ndim != 2 or len(basis) != len(vertices):
        raise InputError(f"basis must be (V, K) for {len(vertices)} vertices; got {basis.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or (len(triangles) and (triangles.min() < 0 or
                                                                                triangles.max() >= len(vertices))):
        raise InputError(f"triangles must be (T, 3) indices into {len(vertices)} vertices")
    if not (np.isfinite(thinness) and 0 < thinness <= 1 and np.isfinite(reach) and reach > 0):
        raise InputError(f"straightening needs 0 < thinness <= 1 and reach > 0; got {thinness!r}, {reach!r}")
    return basis, vertices, triangles


_SOLVE_BATCH = 1 << 17  # merged points per sparse factorisation: small connected pieces are solved together
_MAX_SOLVE_THREADS = 2
_SEEDS_ON_TWO_THREADS = 200_000  # slivers: fewer are judged on one thread
_FOLD_MOVE = 1.0  # a sliver that a move this large (half the model box) of every keypoint would turn over: straightened
_WHOLE_PIECE = 0.5  # a connected piece whose points the region covers more than this share of is solved whole
_FIRST_RINGS = 2  # the region first reaches this many edges from the slivers to straighten
_GROW_RINGS = 2  # then grows by this many edges where the correction just outside it is above the tolerance
_MAX_GROW_RINGS = 8  # and twice as many each further step, up to this many
_PATCH_RINGS = 4  # a growth is solved with the region's points this many edges around it, the rest held


class _StraightenSystem:
    """The straightening's sparse system (:func:`straighten_basis`) on the merged points, solved where it matters.

    The system's pattern is the mesh's edge graph with its diagonal (a sliver's three corners are a triangle, so its
    straightness couples only neighbours); compiled kernels find the edges, add the slivers' part ``SᵀWS`` into that
    pattern and each point's anchor in one pass over the triangles, and make the rest of a row (the edges'
    stiffness) only when the row is solved.

    :meth:`solve` solves on a region (:func:`straighten_basis`): the points within two edges of the slivers whose
    own term moves a corner by more than ``tolerance`` (one Jacobi step from no correction) or that a large edit
    would turn over, with no correction beyond it; where the points just outside would still move by more than
    ``tolerance`` (one Jacobi step from the region's correction), the region grows from them by two edges (twice
    as far each further step, up to eight), and a patch of the region four edges around the growth is solved with
    the correction elsewhere held (a block Gauss-Seidel step: the growth moves the points farther inside by less
    than the tolerance), until nothing beyond the rim is above it. The first region's connected parts are
    factorised on their own, packed into batches (at least one per thread, the largest parts first), two batches at
    a time (:func:`_factorised`: an LDLᵀ factorisation in an approximate minimum-degree order, which does not
    depend on how the points are numbered); a connected piece of the mesh that the first region covers more than
    half of is taken whole.
    """

    def __init__(self, points: np.ndarray, tri: np.ndarray, thinness: float, reach: float,
                 point_of: np.ndarray | None = None) -> None:
        """``points`` (n, 3) distinct, ``tri`` (T, 3) int64 indexing them (repeated corners allowed: skipped); or
        indexing a mesh's vertices, each vertex ``v`` at point ``point_of[v]`` (the triangles are not renumbered
        into a copy: the kernels look the points up)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        self.reach = float(reach)
        n = self.n = len(points)
        tri = np.ascontiguousarray(tri, dtype=np.int64)
        point_of = np.zeros(0, np.int64) if point_of is None else np.ascontiguousarray(point_of, dtype=np.int64)
        # a triangle stored again over the same corners (ShapeNet's meshes store every face twice, once each way
        # round) is counted with its first copy: the same system in half the passes
        same = np.empty(len(tri), dtype=np.int64)
        same_corners(tri, point_of if len(point_of) else np.arange(n, dtype=np.int64), n, True, same)
        # (n + 1,), (n + 2E,): each row's neighbours and itself, sorted
        indptr, indices = _graph_pattern(tri, point_of, same, n)
        self.indptr, self.indices, self.points = indptr, indices, points
        self.sliver_values, self.anchor = np.zeros(len(indices)), np.empty(n)  # the rest of a row: _row
        ends, along, height = np.empty((len(tri), 3), dtype=np.int32), np.empty(len(tri)), np.empty(len(tri))
        self.label = np.empty(n, dtype=np.int64)  # connected pieces
        self.slivers, longest = _sliver_terms(points, tri, point_of, same, indptr, indices, float(thinness),
                                              1.0 / reach**2, _STRAIGHTEN_ENDS, _STRAIGHTEN_CAP, self.sliver_values,
                                              self.anchor, ends, along, height, self.label)
        self.floor = 1e-6 * max(longest, 1e-300)  # edge lengths floored at 1e-6 of the longest
        del tri, same
        if self.slivers == 0:
            return
        s = self.slivers
        self.ends, self.along, self.height = ends[:s].copy(), along[:s].copy(), height[:s].copy()  # per sliver
        del ends, along, height
        self.pieces = int(self.label.max()) + 1
        # what the region's seeds need of the system, made here beside the MVC basis, not after it (0.1 s at 1.77M
        # slivers)
        self.step = _sliver_steps(points, indptr, indices, self.sliver_values, self.anchor, self.floor, self.ends,
                                  self.along, self.height, _STRAIGHTEN_CAP)

    def solve(self, basis: np.ndarray, tolerance: float) -> _Correction:
        """The correction of the merged points (0 where it is below ``tolerance``; ``tolerance`` 0: every connected
        piece with a sliver, exactly)."""
        merged = np.ascontiguousarray(basis)
        correction = _Correction(self.n, merged.shape[1])
        if tolerance <= 0:
            inside = np.zeros(self.pieces, dtype=bool)
            inside[self.label[self.ends[:, 0]]] = True
            self._solve_region(inside[self.label], inside[self.label], merged, correction)
            return correction
        seeds = np.flatnonzero(self._seeds(merged, float(tolerance)))
        inside = np.zeros(self.n, dtype=bool)
        piece_size = np.bincount(self.label, minlength=self.pieces)
        frontier, rings, first = seeds, _FIRST_RINGS, True
        while len(frontier):
            reached = _rings(self.indptr, self.indices, frontier, rings)
            if first:
                # a piece the region covers mostly is taken whole: solving it whole costs little more than solving
                # that part, and a rim there could make the part grow
                covered = np.bincount(self.label, weights=reached, minlength=self.pieces)
                reached |= (covered > _WHOLE_PIECE * piece_size)[self.label]
                inside |= reached
                del reached
                rim = self._solve_region(inside, inside, merged, correction)
            else:
                # the region grows by a few points: solve a patch around them, holding the correction elsewhere (a
                # block Gauss-Seidel step; the growth's effect on points farther inside is below the tolerance)
                added = reached & ~inside
                inside |= reached
                patch = _rings(self.indptr, self.indices, np.flatnonzero(added), _PATCH_RINGS) & inside
                del reached, added
                rim = self._solve_patch(patch, inside, merged, correction)
            # cut off too soon where the points just outside would move by more than the tolerance (one Jacobi step
            # from the region's correction): grow from there
            frontier = _beyond_rim(self.indptr, self.indices, self.points, self.sliver_values, self.anchor, self.floor,
                                   rim, inside, correction.slot, correction.values, float(tolerance))
            log.debug("straightening: %d seed points, %d rings: %d of %d points solved, %d beyond the rim above %.3g",
                      len(seeds), rings, inside.sum(), self.n, len(frontier), tolerance)
            # a region that keeps growing (along a strip, a few points a step) grows twice as far each step
            rings, first = (_GROW_RINGS if first else min(2 * rings, _MAX_GROW_RINGS)), False
        return correction

    def _seeds(self, merged: np.ndarray, tolerance: float) -> np.ndarray:
        """(n,) bool: :func:`_sliver_seeds` of every sliver, in two halves on two threads when there are many."""
        seed = np.zeros(self.n, dtype=np.bool_)
        args = (merged, self.ends, self.along, self.height, self.step, tolerance, _FOLD_MOVE, seed)
        s = self.slivers
        if s < _SEEDS_ON_TWO_THREADS or (os.cpu_count() or 1) < 2:
            _sliver_seeds(0, s, *args)
            return seed
        with ThreadPoolExecutor(1, thread_name_prefix="kpd-seeds") as pool:
            other = pool.submit(_sliver_seeds, s // 2, s, *args)
            _sliver_seeds(0, s // 2, *args)
            other.result()
        return seed

    def _solve_patch(self, patch: np.ndarray, inside: np.ndarray, basis: np.ndarray,
                     correction: _Correction) -> np.ndarray:
        """Solve, into ``correction``, the points ``patch`` (n,) bool of the region ``inside`` with the
        correction of every other point held as it is. Returns the region's rim within the patch."""
        import scipy.sparse as sparse

        members = np.flatnonzero(patch)
        local = np.full(self.n, -1, dtype=np.int64)
        local[members] = np.arange(len(members))
        ptr, idx, val = _submatrix(self.indptr, self.indices, members, local, self.points, self.sliver_values,
                                   self.anchor, self.floor)
        system = sparse.csc_matrix((val, idx, ptr), shape=(len(members),) * 2)
        solve = _factorised(system)
        rhs = _held_rhs(self.indptr, self.indices, self.points, self.sliver_values, self.anchor, self.floor, members,
                        patch, basis, correction.slot, correction.values)
        correction.set(members, solve(rhs))
        return members[_has_outside(self.indptr, self.indices, members, inside)]

    def _solve_region(self, inside: np.ndarray, added: np.ndarray, basis: np.ndarray,
                      correction: _Correction) -> np.ndarray:
        """Solve, into ``correction``, the connected parts of the region ``inside`` (n,) bool that hold an
        ``added`` (n,) point, with no correction outside the region; the other parts keep theirs. Returns the
        region's rim: its points next to points outside it."""
        import scipy.sparse as sparse

        part, rim = _region_parts(self.indptr, self.indices, inside)  # (n,) -1 outside; (n,) bool
        parts = int(part.max()) + 1 if len(part) else 0
        changed = np.zeros(parts + 1, dtype=bool)
        changed[part[added]] = True
        part = np.where(changed[part], part, -1)  # only the parts with an added point are solved (again)
        sizes = np.bincount(part[part >= 0], minlength=parts)
        # the parts packed into batches of about _SOLVE_BATCH points, and at least one per thread: the largest first,
        # each into the batch with the fewest points so far (a part is never split: fill-in does not cross parts)
        threads = min(_MAX_SOLVE_THREADS, os.cpu_count() or 1)
        total, nonempty = int(sizes.sum()), int(np.count_nonzero(sizes))
        batches = min(max(-(-total // _SOLVE_BATCH), threads), nonempty)
        batch_of_part = np.zeros(parts, dtype=np.int64)
        filled = [0] * batches
        for p in np.argsort(-sizes, kind="stable")[:nonempty].tolist():
            b = min(range(batches), key=filled.__getitem__)
            batch_of_part[p] = b
            filled[b] += int(sizes[p])
        point_batch = np.where(part >= 0, batch_of_part[np.maximum(part, 0)], -1)
        order = np.argsort(point_batch, kind="stable")  # each batch's points in ascending order
        bounds = np.searchsorted(point_batch[order], np.arange(batches + 1))
        local = np.full(self.n, -1, dtype=np.int64)

        def solve_batch(b: int) -> None:
            # each batch numbers its own points (a point's neighbours in the region are in its part, so its batch)
            members = order[bounds[b]:bounds[b + 1]]
            local[members] = np.arange(len(members))
            ptr, idx, val = _submatrix(self.indptr, self.indices, members, local, self.points, self.sliver_values,
                                       self.anchor, self.floor)
            system = sparse.csc_matrix((val, idx, ptr), shape=(len(members),) * 2)  # symmetric: CSR rows = columns
            solve = _factorised(system)
            rhs = _rows_times(self.indptr, self.indices, self.sliver_values, members, basis)  # -Sᵀ W S B
            correction.values[correction.slot[members]] = solve(rhs)  # rows of their own: no lock

        correction.reserve(order[bounds[0]:bounds[batches]] if batches else order[:0])
        # QDLDL lets go of the GIL: two batches at a time on two cores, the largest first
        largest_first = sorted(range(batches), key=lambda b: bounds[b] - bounds[b + 1])
        threads = min(threads, batches)
        if threads <= 1:
            for b in largest_first:
                solve_batch(b)
        else:
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(solve_batch, largest_first))
        return np.flatnonzero(rim)


@njit(nogil=True)
def _graph_pattern(tri, point_of, same, n):  # pragma: no cover - compiled
    """CSR (indptr (n + 1,), indices) of the symmetric pattern of the triangles' edges plus the diagonal, each
    entry once, columns sorted; degenerate triangles (a repeated corner) add no edge. The triangles' corners are
    ``point_of[tri]`` (``tri`` itself when ``point_of`` is empty); only the triangles ``t`` with ``same[t] == t``
    (the first over their corners) are read."""
    count = np.ones(n + 1, dtype=np.int64)  # the diagonal
    count[0] = 0
    for t in range(tri.shape[0]):
        if same[t] != t:
            continue
        a, b, c = _corners(tri, point_of, t)
        if a == b or b == c or c == a:
            continue
        count[a + 1] += 2
        count[b + 1] += 2
        count[c + 1] += 2
    for i in range(n):
        count[i + 1] += count[i]
    fill = count[:-1].copy()
    other = np.empty(count[n], dtype=np.int32)  # n < 2**31: a mesh that large is refused before binding
    for i in range(n):
        other[fill[i]] = i
        fill[i] += 1
    for t in range(tri.shape[0]):
        if same[t] != t:
            continue
        a, b, c = _corners(tri, point_of, t)
        if a == b or b == c or c == a:
            continue
        other[fill[a]] = b
        other[fill[a] + 1] = c
        fill[a] += 2
        other[fill[b]] = c
        other[fill[b] + 1] = a
        fill[b] += 2
        other[fill[c]] = a
        other[fill[c] + 1] = b
        fill[c] += 2
    indptr = np.zeros(n + 1, dtype=np.int64)
    size = 0
    for i in range(n):
        lo, hi = count[i], count[i + 1]
        if hi - lo > 64:  # a fan's centre: a real sort
            other[lo:hi].sort()  # in place (assigning a sorted copy cost 1.8 s of a first run's compiling)
        for j in range(lo + 1, hi):  # insertion sort: rows are short (a no-op after the sort)
            value = other[j]
            k = j - 1
            while k >= lo and other[k] > value:
                other[k + 1] = other[k]
                k -= 1
            other[k + 1] = value
        for j in range(lo, hi):
            if j == lo or other[j] != other[j - 1]:
                other[size] = other[j]  # size <= j: compacting in place
                size += 1
        indptr[i + 1] = size
    return indptr, other[:size].copy()


@njit(nogil=True, inline="always")
def _corners(tri, point_of, t):  # pragma: no cover - compiled
    """The three corners of triangle ``t``: ``tri[t]``, through ``point_of`` when it is not empty."""
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    if point_of.shape[0]:
        return point_of[a], point_of[b], point_of[c]
    return a, b, c


@njit(nogil=True, inline="always")
def _entry(indptr, indices, row, col):  # pragma: no cover - compiled
    """Position of (row, col) in a CSR pattern with sorted columns (it is there)."""
    lo, hi = indptr[row], indptr[row + 1] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if indices[mid] < col:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(nogil=True, error_model="numpy", inline="always")
def _sliver_weight(longest, height, cap):  # pragma: no cover - compiled
    """The weight of a sliver's straightness: its long edge over its height, squared, at most ``cap``."""
    return (longest / max(height, longest / np.sqrt(cap))) ** 2


@njit(nogil=True, error_model="numpy")
def _sliver_terms(points, tri, point_of, same, indptr, indices, thinness, inverse_reach2, ends_weight, cap,
                  sliver_values, anchor, sliver_ends, sliver_along, sliver_height,
                  piece):  # pragma: no cover - compiled
    """One pass over the triangles: the slivers' ``SᵀWS`` into the pattern (``sliver_values``); per sliver, in the
    order found, its third corner and long edge's ends (``sliver_ends``), the corner's place along that edge and its
    height; each point's anchor weight (``anchor``) and connected piece (``piece``, numbered from 0 in order of
    the points). Returns the number of slivers and the longest edge.

    A triangle whose corners an earlier one has (``same[t] != t``; -1: two equal corners) adds what it would add
    through that first one, which counts its copies: the same long edge, so the same terms. Not where two edges are
    equally longest: which one is taken depends on the order of the corners, so each copy adds its own, as it is."""
    n = points.shape[0]
    copies = np.zeros(tri.shape[0], dtype=np.int32)
    for t in range(tri.shape[0]):
        if same[t] >= 0:
            copies[same[t]] += 1
    for i in range(n):
        piece[i] = i  # union-find: each point's parent
    area = np.zeros(n)
    corner_of = np.zeros(n, dtype=np.bool_)
    slivers = 0
    longest_edge = 0.0
    for t in range(tri.shape[0]):
        first = same[t]
        if first < 0 or (first != t and copies[first] == 0):  # two equal corners; a copy counted already
            continue
        v = _corners(tri, point_of, t)
        a, b, c = v
        l0 = np.sqrt((points[c, 0] - points[b, 0]) ** 2 + (points[c, 1] - points[b, 1]) ** 2
                     + (points[c, 2] - points[b, 2]) ** 2)
        l1 = np.sqrt((points[a, 0] - points[c, 0]) ** 2 + (points[a, 1] - points[c, 1]) ** 2
                     + (points[a, 2] - points[c, 2]) ** 2)
        l2 = np.sqrt((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
                     + (points[b, 2] - points[a, 2]) ** 2)
        k, longest = 0, l0
        if l1 > longest:
            k, longest = 1, l1
        if l2 > longest:
            k, longest = 2, l2
        tied = (l0 == longest) + (l1 == longest) + (l2 == longest) > 1
        if first != t and not tied:
            continue  # added by its first copy
        times = 1.0
        if first == t and not tied:
            times = float(copies[t])
            copies[t] = 0  # its copies are counted (a tied one keeps its count: its copies add their own)
        if first == t:
            for x, y in ((a, b), (a, c)):
                while piece[x] != x:
                    piece[x] = piece[piece[x]]
                    x = piece[x]
                while piece[y] != y:
                    piece[y] = piece[piece[y]]
                    y = piece[y]
                if x != y:
                    piece[max(x, y)] = min(x, y)
        longest_edge = max(longest_edge, longest)
        ux, uy, uz = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        vx, vy, vz = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        twice_area = np.sqrt(nx * nx + ny * ny + nz * nz)
        area[a] += times * twice_area / 6.0
        area[b] += times * twice_area / 6.0
        area[c] += times * twice_area / 6.0
        height = twice_area / max(longest, 1e-300)
        if not height < thinness * longest:
            continue
        corner, start, end = v[k], v[(k + 1) % 3], v[(k + 2) % 3]
        ex, ey = points[end, 0] - points[start, 0], points[end, 1] - points[start, 1]
        ez = points[end, 2] - points[start, 2]
        dot = ((points[corner, 0] - points[start, 0]) * ex + (points[corner, 1] - points[start, 1]) * ey
               + (points[corner, 2] - points[start, 2]) * ez)
        s = min(max(dot / (ex * ex + ey * ey + ez * ez), 0.0), 1.0)
        weight = times * _sliver_weight(longest, height, cap)
        ends = (corner, start, end)
        coef = (1.0, s - 1.0, -s)
        corner_of[corner] = True
        sliver_ends[slivers, 0], sliver_ends[slivers, 1], sliver_ends[slivers, 2] = corner, start, end
        sliver_along[slivers] = s
        sliver_height[slivers] = height
        slivers += 1
        for i in range(3):
            for j in range(3):
                sliver_values[_entry(indptr, indices, ends[i], ends[j])] += weight * coef[i] * coef[j]
    mean_area = 0.0
    for i in range(n):
        mean_area += area[i]
    mean_area = max(mean_area / max(n, 1), 1e-300)
    for i in range(n):
        anchor[i] = (area[i] / mean_area + 1e-6) * (1.0 if corner_of[i] else ends_weight) * inverse_reach2
    pieces = 0
    for i in range(n):  # roots are the smallest point of their piece: number them in order, then the rest
        if piece[i] == i:
            piece[i] = -1 - pieces  # numbered roots are negative until the end
            pieces += 1
        else:
            root = piece[piece[i]]
            piece[i] = root if root < 0 else piece[root]  # a root below i is numbered already
    for i in range(n):
        piece[i] = -1 - piece[i]
    return slivers, longest_edge


@njit(nogil=True, error_model="numpy", inline="always")
def _row(i, indptr, indices, points, sliver_values, anchor, floor, out):  # pragma: no cover - compiled
    """Row ``i`` of the system into ``out`` (its pattern entries in order): the edges' stiffness ``-1 / l²`` (lengths
    floored at ``floor``) and on the diagonal their sum and the anchor, plus the slivers' terms. Returns the
    diagonal entry."""
    diagonal = anchor[i]
    at_diagonal = 0
    for e in range(indptr[i], indptr[i + 1]):
        j = indices[e]
        out[e - indptr[i]] = sliver_values[e]
        if j == i:
            at_diagonal = e - indptr[i]
        else:
            length = max(np.sqrt((points[i, 0] - points[j, 0]) ** 2 + (points[i, 1] - points[j, 1]) ** 2
                                 + (points[i, 2] - points[j, 2]) ** 2), floor)
            stiffness = 1.0 / (length * length)
            out[e - indptr[i]] -= stiffness
            diagonal += stiffness
    out[at_diagonal] += diagonal
    return out[at_diagonal]


@njit(nogil=True, error_model="numpy")
def _submatrix(indptr, indices, members, local, points, sliver_values, anchor, floor):  # pragma: no cover - compiled
    """CSR (indptr, indices, data) of the system's rows and columns ``members`` (sorted), renumbered by ``local``;
    entries whose column has no local number (-1: outside the region) are left out."""
    m = len(members)
    ptr = np.zeros(m + 1, dtype=np.int64)
    widest = 0
    for r in range(m):
        kept = 0
        for e in range(indptr[members[r]], indptr[members[r] + 1]):
            if local[indices[e]] >= 0:
                kept += 1
        ptr[r + 1] = ptr[r] + kept
        widest = max(widest, indptr[members[r] + 1] - indptr[members[r]])
    idx = np.empty(ptr[m], dtype=np.int32)
    val = np.empty(ptr[m])
    row = np.empty(widest)
    for r in range(m):
        i = members[r]
        _row(i, indptr, indices, points, sliver_values, anchor, floor, row)
        at = ptr[r]
        for e in range(indptr[i], indptr[i + 1]):
            if local[indices[e]] >= 0:
                idx[at] = local[indices[e]]
                val[at] = row[e - indptr[i]]
                at += 1
    return ptr, idx, val


@njit(nogil=True)
def _region_parts(indptr, indices, inside):  # pragma: no cover - compiled
    """The connected parts of the graph restricted to ``inside`` (n,) bool: (n,) part numbers (-1 outside), in
    order of their smallest point, and (n,) whether an inside point has a neighbour outside."""
    n = len(inside)
    part = np.full(n, -1, dtype=np.int64)
    rim = np.zeros(n, dtype=np.bool_)
    stack = np.empty(n, dtype=np.int64)
    parts = 0
    for start in np.flatnonzero(inside):
        if part[start] >= 0:
            continue
        part[start] = parts
        top = 1
        stack[0] = start
        while top:
            top -= 1
            i = stack[top]
            for e in range(indptr[i], indptr[i + 1]):
                j = indices[e]
                if not inside[j]:
                    rim[i] = True
                elif part[j] < 0:
                    part[j] = parts
                    stack[top] = j
                    top += 1
        parts += 1
    return part, rim


@njit(nogil=True)
def _rings(indptr, indices, sources, rings):  # pragma: no cover - compiled
    """(n,) bool: the points within ``rings`` edges of ``sources`` (breadth first from all of them at once)."""
    n = len(indptr) - 1
    depth = np.full(n, -1, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    tail = 0
    for s in sources:
        if depth[s] < 0:
            depth[s] = 0
            queue[tail] = s
            tail += 1
    head = 0
    while head < tail:
        i = queue[head]
        head += 1
        if depth[i] >= rings:
            continue
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if depth[j] < 0:
                depth[j] = depth[i] + 1
                queue[tail] = j
                tail += 1
    return depth >= 0


@njit(nogil=True, error_model="numpy")
def _beyond_rim(indptr, indices, points, sliver_values, anchor, floor, rim, inside, slot, values,
                tolerance):  # pragma: no cover - compiled
    """The points outside the region next to its ``rim`` whose correction, one Jacobi step from the region's
    (``-Σ_i A_ji D_i / A_jj``), exceeds ``tolerance`` in some column (the region's correction in ``values`` at
    each point's ``slot``, :class:`_Correction`)."""
    k = values.shape[1]
    seen = np.zeros(len(inside), dtype=np.bool_)
    estimate = np.empty(k)
    row = np.empty(1)
    out = []
    for i in rim:
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if inside[j] or seen[j]:
                continue
            seen[j] = True
            if len(row) < indptr[j + 1] - indptr[j]:
                row = np.empty(indptr[j + 1] - indptr[j])
            _row(j, indptr, indices, points, sliver_values, anchor, floor, row)
            estimate[:] = 0.0
            diagonal = 1.0
            for f in range(indptr[j], indptr[j + 1]):
                col = indices[f]
                if col == j:
                    diagonal = row[f - indptr[j]]
                elif inside[col] and slot[col] >= 0:
                    for c in range(k):
                        estimate[c] -= row[f - indptr[j]] * values[slot[col], c]
            for c in range(k):
                if abs(estimate[c]) > tolerance * diagonal:
                    out.append(j)
                    break
    return np.array(out, dtype=np.int64)


@njit(nogil=True, error_model="numpy")
def _held_rhs(indptr, indices, points, sliver_values, anchor, floor, rows, patch, basis, slot,
              values):  # pragma: no cover - compiled
    """(len(rows), K): the right-hand side of the system's ``rows`` with the points outside ``patch`` (n,) bool
    held at their correction D (``values`` at each point's ``slot``, :class:`_Correction`):
    ``-(Sᵀ W S basis)[rows] - A[rows, outside] D[outside]``."""
    k = basis.shape[1]
    out = np.zeros((len(rows), k))
    row = np.empty(1)
    for r in range(len(rows)):
        i = rows[r]
        if len(row) < indptr[i + 1] - indptr[i]:
            row = np.empty(indptr[i + 1] - indptr[i])
        _row(i, indptr, indices, points, sliver_values, anchor, floor, row)
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            value = sliver_values[e]
            if value != 0.0:
                for c in range(k):
                    out[r, c] -= value * basis[j, c]
            if not patch[j] and slot[j] >= 0:
                value = row[e - indptr[i]]
                for c in range(k):
                    out[r, c] -= value * values[slot[j], c]
    return out


@njit(nogil=True)
def _has_outside(indptr, indices, rows, inside):  # pragma: no cover - compiled
    """(len(rows),) bool: whether each of ``rows`` has a neighbour outside ``inside``."""
    out = np.zeros(len(rows), dtype=np.bool_)
    for r in range(len(rows)):
        for e in range(indptr[rows[r]], indptr[rows[r] + 1]):
            if not inside[indices[e]]:
                out[r] = True
                break
    return out


@njit(nogil=True)
def _rows_times(indptr, indices, data, rows, basis):  # pragma: no cover - compiled
    """(len(rows), K): ``-(M @ basis)[rows]`` for the CSR matrix M (indptr, indices, data)."""
    out = np.zeros((len(rows), basis.shape[1]))
    for r in range(len(rows)):
        for e in range(indptr[rows[r]], indptr[rows[r] + 1]):
            value = data[e]
            if value != 0.0:
                j = indices[e]
                for c in range(basis.shape[1]):
                    out[r, c] -= value * basis[j, c]
    return out


@njit(nogil=True, error_model="numpy")
def _sliver_steps(points, indptr, indices, sliver_values, anchor, floor, ends, along, height, cap
                  ):  # pragma: no cover - compiled
    """(S,) each sliver's Jacobi step from no correction per unit of straightness, at the corner it moves most: its
    weight (:func:`_sliver_weight`) times that corner's coefficient over the corner's diagonal entry of the system
    (:func:`_row`; on a thin sliver of a native mesh its weight is most of the diagonal, and the step is 1). It does
    not depend on the basis: made with the system. The diagonal is made for the slivers' corners only."""
    n = points.shape[0]
    step = np.empty(ends.shape[0])
    diagonal = np.full(n, -1.0)  # made on first use
    row = np.empty(1)
    for s in range(ends.shape[0]):
        c, a, b = ends[s, 0], ends[s, 1], ends[s, 2]
        t = along[s]
        for i in (c, a, b):
            if diagonal[i] < 0.0:
                if len(row) < indptr[i + 1] - indptr[i]:
                    row = np.empty(indptr[i + 1] - indptr[i])
                diagonal[i] = _row(i, indptr, indices, points, sliver_values, anchor, floor, row)
        longest = np.sqrt((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
                          + (points[b, 2] - points[a, 2]) ** 2)
        w = _sliver_weight(longest, height[s], cap)
        step[s] = max(w / diagonal[c], w * (1.0 - t) / diagonal[a], w * t / diagonal[b])
    return step


@njit(nogil=True, error_model="numpy")
def _sliver_seeds(lo, hi, merged, ends, along, height, step, tolerance, move, seed):  # pragma: no cover - compiled
    """``seed`` (n,) bool set at the corners of the slivers ``lo:hi`` whose own term alone would move one of their
    corners by more than ``tolerance`` in a keypoint's column, or move its third corner across its height for a
    ``move`` of every keypoint: one Jacobi step from no correction, the straightness ``r`` (off in ``merged``
    (n, K)) times the sliver's ``step`` (:func:`_sliver_steps`). Only ever sets True: two threads may share
    ``seed``."""
    k = merged.shape[1]
    for s in range(lo, hi):
        c, a, b = ends[s, 0], ends[s, 1], ends[s, 2]
        t = along[s]
        largest, total = 0.0, 0.0
        for j in range(k):
            off = abs(merged[c, j] - (1.0 - t) * merged[a, j] - t * merged[b, j])
            largest = max(largest, off)
            total += off
        if largest * step[s] > tolerance or total * step[s] * move > height[s]:
            seed[c] = True
            seed[a] = True
            seed[b] = True


def _straighten_basis_reference(basis: Any, vertices: Any, triangles: Any, *, thinness: float = STRAIGHTEN_THINNESS,
                                reach: float = STRAIGHTEN_REACH) -> np.ndarray:
    """:func:`straighten_basis` as one sparse LU over every merged point (the slow twin tests compare with)."""
    import scipy.sparse as sparse
    from scipy.sparse.linalg import splu

    basis, vertices, triangles = _check_straighten(basis, vertices, triangles, thinness, reach)
    if not len(triangles) or not _thin_triangles(vertices, triangles, thinness)[0].any():
        return basis  # no sliver (the cheap test first: merging below does not make new ones)
    points, inverse = _merge_coincident(vertices)
    tri = inverse[triangles]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])]
    if not len(tri):
        return basis
    n = len(points)
    thin, apex, longest, height, twice_area = _thin_triangles(points, tri, thinness)
    sliver = np.flatnonzero(thin)
    if not len(sliver):
        return basis
    corner = tri[sliver, apex[sliver]]
    start, end = tri[sliver, (apex[sliver] + 1) % 3], tri[sliver, (apex[sliver] + 2) % 3]
    edge = points[end] - points[start]
    s = np.clip(np.einsum("ij,ij->i", points[corner] - points[start], edge) / np.einsum("ij,ij->i", edge, edge), 0, 1)
    weight = (longest[sliver] / np.maximum(height[sliver], longest[sliver] / np.sqrt(_STRAIGHTEN_CAP))) ** 2
    count = len(sliver)
    straight = sparse.csr_matrix(
        (np.stack([np.ones(count), s - 1.0, -s], axis=1).ravel(),
         (np.repeat(np.arange(count), 3), np.stack([corner, start, end], axis=1).ravel())), shape=(count, n))
    first = np.zeros(n, dtype=np.int64)
    first[inverse[::-1]] = np.arange(len(vertices))[::-1]  # one original vertex per merged point
    merged = basis[first]  # (n, K): coincident vertices have the same basis rows
    residual = straight @ merged  # (count, K)
    pairs = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)  # (3T, 2)
    keys = np.unique(pairs[:, 0] * n + pairs[:, 1])
    edges = np.stack([keys // n, keys % n], axis=1)  # (E, 2) each edge once
    length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    length = np.maximum(length, 1e-6 * max(float(length.max()), 1e-300))
    difference = sparse.csr_matrix(
        (np.tile([1.0, -1.0], len(edges)), (np.repeat(np.arange(len(edges)), 2), edges.ravel())),
        shape=(len(edges), n))
    area = np.zeros(n)
    for i in range(3):
        np.add.at(area, tri[:, i], twice_area / 6.0)
    ends = np.ones(n, dtype=bool)
    ends[corner] = False  # never a sliver's third corner: a leg's foot, a panel's corner, a run's end
    anchor = (area / max(float(area.mean()), 1e-300) + 1e-6) * np.where(ends, _STRAIGHTEN_ENDS, 1.0) / reach**2
    system = (sparse.diags(anchor) + difference.T @ sparse.diags(1.0 / length**2) @ difference
              + straight.T @ sparse.diags(weight) @ straight).tocsc()
    correction = splu(system).solve(-(straight.T @ (weight[:, None] * residual)))  # (n, K)
    return basis + correction[inverse]


def coincident_mvc_weights(vertices: Any, cage: Cage) -> np.ndarray:
    """(V, C) mean value coordinates of ``vertices`` in ``cage``, computed once per distinct position.

    CAD meshes store one vertex per triangle corner (ModelNet10's chairs have about four vertices per position), and
    the coordinates of a position do not depend on how often it is stored: this is :func:`kpd.mvc.mvc_weights` at a
    quarter of the cost on such meshes, with the same result.
    """
    vertices = as_points(vertices, "vertices")
    points, inverse = _merge_coincident(vertices)
    if len(points) == len(vertices):
        return mvc_weights(vertices, cage.vertices, cage.faces)
    return mvc_weights(points, cage.vertices, cage.faces)[inverse]


def coincident_mvc_basis(vertices: Any, cage: Cage, rows: Any) -> np.ndarray:
    """(V, R) float64: ``coincident_mvc_weights(vertices, cage) @ rows`` without the (V, C) weights.

    Computed once per distinct position by the compiled kernel (:func:`kpd.mvc_fast.mvc_project`); with
    ``rows = influence.T`` (C, K) this is a rig's edit basis before straightening.
    """
    vertices = as_points(vertices, "vertices")
    points, inverse = _merge_coincident(vertices)
    if len(points) == len(vertices):
        return mvc_project(vertices, cage.vertices, cage.faces, rows)
    return mvc_project(points, cage.vertices, cage.faces, rows)[inverse]


def _compact_basis(basis: np.ndarray) -> np.ndarray:
    """``basis`` (V, K) in float32 when that moves no vertex by more than 1e-6 of the box diagonal for keypoint
    moves of up to a box diagonal each, else as it is.

    Rounding to float32 changes each entry by at most 2^-24 of it, so a vertex moves by at most
    ``2^-24 · Σ_k |B_vk| · max_k |Δp_k|``: within 1e-6 of a diagonal ``max_k |Δp_k|`` when every row's absolute
    sum is below 16 (a mesh inside its cage has rows that sum to about 1 per keypoint that moves it).
    """
    if basis.dtype == np.float32 or not len(basis):
        return basis
    if _largest_row_sum(np.ascontiguousarray(basis, dtype=np.float64)) > _FLOAT32_ROW_SUM:
        return basis
    return basis.astype(np.float32)


@njit(nogil=True)
def _largest_row_sum(basis):  # pragma: no cover - compiled
    """``np.abs(basis).sum(axis=1).max()`` without the (V, K) temporary (NaN if any entry is NaN)."""
    largest = 0.0
    for v in range(basis.shape[0]):
        total = 0.0
        for k in range(basis.shape[1]):
            total += abs(basis[v, k])
        if total != total:
            return total
        largest = max(largest, total)
    return largest


_EDIT_LANES = 256  # vertices per block of an edit


@intrinsic
def _store_streaming(typingctx, array, index, value):  # pragma: no cover - compiled
    """``array[index] = value`` for a 1-d float64 array, as a non-temporal store: the line is written to memory
    without being read into the cache first, as a plain store does (half the memory traffic of writing an output
    that nothing reads soon). Other threads see it after :func:`_streaming_done`."""

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        store = builder.store(args[2], builder.gep(data, [args[1]]))
        store.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
        return context.get_dummy_value()

    return types.void(array, types.intp, types.float64), codegen


@intrinsic
def _streaming_done(typingctx):  # pragma: no cover - compiled
    """A full memory fence (``mfence`` on x86, ``dmb`` on ARM): the non-temporal stores before it are in memory
    for every thread after it."""

    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return types.void(), codegen


@njit(nogil=True, error_model="numpy")
def _edit(basis_t, offsets, rest, out):  # pragma: no cover - compiled
    """``out = rest + basis_t.T @ offsets`` with float64 sums: (K, V) basis of float32 or float64, (K, 3) offsets.

    Blocks of vertices, each keypoint's row of the block in order: the loops over the block are SIMD code (one pass
    at 1.37M vertices takes about 10 ms; a vertex at a time, 12 dependent sums, took 27 ms). The rows of keypoints
    that did not move are not read: a drag of one keypoint reads one row of the basis, not K. The pass is bound by
    memory, so ``out`` is written with non-temporal stores (:func:`_store_streaming`): 13-19% less time at 1.37M
    vertices, one keypoint moved or all twelve."""
    moved = np.zeros(offsets.shape[0], dtype=np.int64)
    k = 0
    for j in range(offsets.shape[0]):
        if offsets[j, 0] != 0.0 or offsets[j, 1] != 0.0 or offsets[j, 2] != 0.0:
            moved[k] = j
            k += 1
    n_all = rest.shape[0]
    x = np.empty(_EDIT_LANES)
    y = np.empty(_EDIT_LANES)
    z = np.empty(_EDIT_LANES)
    flat = out.reshape(-1)  # C-contiguous (V, 3): vertex v's coordinates at 3v, 3v + 1, 3v + 2
    for start in range(0, n_all, _EDIT_LANES):
        n = min(_EDIT_LANES, n_all - start)
        for i in range(n):
            x[i] = rest[start + i, 0]
            y[i] = rest[start + i, 1]
            z[i] = rest[start + i, 2]
        for m in range(k):
            j = moved[m]
            o0 = offsets[j, 0]
            o1 = offsets[j, 1]
            o2 = offsets[j, 2]
            row = basis_t[j, start:start + n]
            for i in range(n):
                b = np.float64(row[i])
                x[i] += b * o0
                y[i] += b * o1
                z[i] += b * o2
        for i in range(n):
            v = 3 * (start + i)
            _store_streaming(flat, v, x[i])
            _store_streaming(flat, v + 1, y[i])
            _store_streaming(flat, v + 2, z[i])
    _streaming_done()


@njit(nogil=True, error_model="numpy")
def _edit_rows(basis_t, offsets, rest, rows, out):  # pragma: no cover - compiled
    """:func:`_edit` for the vertices ``rows`` only."""
    k = offsets.shape[0]
    for v in rows:
        x = rest[v, 0]
        y = rest[v, 1]
        z = rest[v, 2]
        for j in range(k):
            b = np.float64(basis_t[j, v])
            x += b * offsets[j, 0]
            y += b * offsets[j, 1]
            z += b * offsets[j, 2]
        out[v, 0] = x
        out[v, 1] = y
        out[v, 2] = z


# What binding adds at its peak to a process that has read the mesh and loaded the model (the surface sample, the
# mesh's copies, the basis and the straightening's system and factorisations; CAD meshes, full of slivers, are the
# worst case), with what the commands that bind add to draw it: measured 2026-12-06 (12 keypoints) for the
# 1.37M-vertex, 5.5M-triangle CAD chair of docs/scale.md, Model.rig and one edit 572 MiB (198 MiB at 344k; the
# 1.28M-vertex scan 427 MiB), kpd render 825 MiB, the editor about 1.16 GiB once bound; this gives 1.28 GiB.
_BIND_BYTES = 150 * 2**20
_BIND_BYTES_PER_VERTEX = 200
_BIND_BYTES_PER_TRIANGLE = 100
_BIND_BYTES_PER_KEYPOINT_VERTEX = 24  # the (V, K) basis in float64 and its corrected copy


def bind_memory(vertices: int, triangles: int, keypoints: int) -> int:
    """Bytes that binding a mesh of ``vertices`` and ``triangles`` to ``keypoints`` holds at its peak (an estimate
    from measurements, docs/scale.md)."""
    return int(_BIND_BYTES + vertices * (_BIND_BYTES_PER_VERTEX + keypoints * _BIND_BYTES_PER_KEYPOINT_VERTEX)
               + triangles * _BIND_BYTES_PER_TRIANGLE)


def available_memory() -> int | None:
    """Bytes of memory this process can still use (Linux: MemAvailable, capped by a cgroup limit and by a limit on
    the process's address space, ``ulimit -v``, less what it maps already), or None when the system does not say."""
    available = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_file).read_text().strip()
            usage = int(Path(usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 1 << 60:
            available = min(available, int(limit) - usage)
        break
    mapped = _address_space_left()
    return available if mapped is None else min(available, mapped)


def _address_space_left() -> int | None:
    """Bytes the process may still map under its address-space limit (``RLIMIT_AS``, as ``ulimit -v`` and some
    batch schedulers set it), or None without a limit."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    return limit - int(line.split()[1]) * 1024
    except (ImportError, OSError, ValueError):
        pass
    return None


def check_bind_memory(vertices: int, triangles: int, keypoints: int) -> None:
    """Raise :class:`~kpd.errors.InputError` naming the mesh's size and the memory it needs when binding it would
    not fit in the memory that is available (rather than being killed by the system midway)."""
    need = bind_memory(vertices, triangles, keypoints)
    have = available_memory()
    if have is not None and need > have:
        left = _address_space_left()
        limited = left is not None and left < need  # the process's own limit refuses it, whatever the machine has
        where = ("of address space is left under this process's limit (simplify the mesh, or raise the limit: "
                 "ulimit -v)" if limited else "of memory is available (simplify the mesh, or free memory)")
        raise InputError(f"a mesh of {vertices:,} vertices and {triangles:,} triangles needs about "
                         f"{_size(need)} to bind; {_size(max(have, 0))} {where}")


def _size(count: int) -> str:
    return f"{count / 2**30:.1f} GiB" if count >= 2**30 else f"{count / 2**20:.0f} MiB"


@njit(nogil=True, error_model="numpy")
def _has_sliver(points, tri, thinness):  # pragma: no cover - compiled
    """Whether any triangle's height is below ``thinness`` times its longest edge (:func:`_thin_triangles`)."""
    for t in range(tri.shape[0]):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        l0 = ((points[c, 0] - points[b, 0]) ** 2 + (points[c, 1] - points[b, 1]) ** 2
              + (points[c, 2] - points[b, 2]) ** 2)
        l1 = ((points[a, 0] - points[c, 0]) ** 2 + (points[a, 1] - points[c, 1]) ** 2
              + (points[a, 2] - points[c, 2]) ** 2)
        l2 = ((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
              + (points[b, 2] - points[a, 2]) ** 2)
        longest = np.sqrt(max(l0, l1, l2))
        ux, uy, uz = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        vx, vy, vz = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        if np.sqrt(nx * nx + ny * ny + nz * nz) / max(longest, 1e-300) < thinness * longest:
            return True
    return False


def _thin_triangles(points: np.ndarray, tri: np.ndarray, thinness: float) -> tuple[np.ndarray, ...]:
    """Per triangle: sliver or not, the corner opposite the longest edge, that edge's length, the height over it
    and twice the area, all (T,)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    tri = np.ascontiguousarray(tri, dtype=np.int64)
    apex = np.empty(len(tri), dtype=np.int64)
    longest, twice_area = np.empty(len(tri)), np.empty(len(tri))
    _triangle_shapes(points, tri, apex, longest, twice_area)
    height = twice_area / np.maximum(longest, 1e-300)
    return height < thinness * longest, apex, longest, height, twice_area


@njit(nogil=True, error_model="numpy")
def _triangle_shapes(points, tri, apex, longest, twice_area):  # pragma: no cover - compiled
    """Per triangle: the corner opposite the longest edge (the first on ties), that edge's length and twice the
    area (|(b - a) x (c - a)|)."""
    for t in range(tri.shape[0]):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        ax, ay, az = points[a, 0], points[a, 1], points[a, 2]
        bx, by, bz = points[b, 0], points[b, 1], points[b, 2]
        cx, cy, cz = points[c, 0], points[c, 1], points[c, 2]
        l0 = np.sqrt((cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2)
        l1 = np.sqrt((ax - cx) ** 2 + (ay - cy) ** 2 + (az - cz) ** 2)
        l2 = np.sqrt((bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2)
        k, best = 0, l0
        if l1 > best:
            k, best = 1, l1
        if l2 > best:
            k, best = 2, l2
        apex[t] = k
        longest[t] = best
        ux, uy, uz = bx - ax, by - ay, bz - az
        vx, vy, vz = cx - ax, cy - ay, cz - az
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        twice_area[t] = np.sqrt(nx * nx + ny * ny + nz * nz)


def distinct_points(vertices: Any) -> np.ndarray:
    """(n, 3) the distinct positions among ``vertices`` (V, 3), in lexicographic order."""
    return _merge_coincident(as_points(vertices, "vertices"))[0]


def _merge_coincident(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct positions (n, 3) and, per vertex, the index of its position (V,): coincident corners merged
    (:func:`kpd.grouping.merge_coincident`, the one grouping by position kpd has)."""
    return merge_coincident(vertices)


def _distinct_in_order(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct positions (n, 3) in order of first occurrence and, per vertex, the index of its position (V,);
    ``vertices`` itself and ``arange(V)`` when no two coincide."""
    first, index = first_occurrence_groups(vertices)
    return (vertices if len(first) == len(vertices) else vertices[first]), index


def _read_table(path: Path, columns: int | None) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: missing demo file")
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise InputError(f"{path}: not a table of numbers: {exc}") from exc
    if table.size == 0:
        raise InputError(f"{path}: empty")
    if columns is not None and table.shape[1] != columns:
        raise InputError(f"{path}: rows must have {columns} numbers; got {table.shape[1]}")
    if not np.isfinite(table).all():
        raise InputError(f"{path}: contains NaN or inf")
    return table


def _check_faces(triangles: np.ndarray, count: int, where: Path) -> None:
    if triangles.min() < 0 or triangles.max() >= count:
        raise InputError(f"{where}: face indices must lie in [0, {count}); got [{triangles.min()}, {triangles.max()}]")


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
