"""A rig as glTF 2.0 morph targets: kpd's edits in Blender, game engines and web pages, without kpd.

A rig's edit is linear in the keypoint offsets (:mod:`kpd.rig`): ``vertices = V₀ + B · Δp`` with ``B`` the (V, K)
basis. A synchronised edit through the category prior and each principal component of the prior are linear too, so
every edit kpd offers is a weighted sum of fixed vertex displacements, which is what a glTF morph target is (Blender
shape keys, three.js ``morphTargetInfluences``, Unity and Unreal blend shapes). A :class:`MorphRig` holds, per
target ``t``, the keypoint offsets ``Δ_t`` (K, 3) of one unit of its weight; its vertex displacement is ``B · Δ_t``,
and weights ``w`` give

    vertices(w) = V₀ + B · Σ_t w_t Δ_t,        keypoints(w) = P₀ + Σ_t w_t Δ_t          # (V, 3), (K, 3)

The targets, in this order, named in ``meshes[0].extras.targetNames`` (the names Blender's importer and three.js
read):

* ``keypoint_<i>_x``, ``keypoint_<i>_y``, ``keypoint_<i>_z``: weight ``w`` moves keypoint ``i`` by ``w`` user units
  along that axis and the vertices as :meth:`kpd.rig.Rig.deform` moves them;
* ``prior_<i>_x|y|z`` (with a prior): the same move of keypoint ``i`` with the other keypoints following the
  category prior (:meth:`kpd.runtime.Model.sync` of that single move; the synchronised edit is linear in the move);
* ``pca_<c>`` (with a prior): principal component ``c`` of the prior, weight 1 = one standard deviation.

Several ``prior_`` targets of different keypoints add their synchronised edits, which is not the synchronised edit
of the keypoints moved together (:meth:`kpd.prior.KeypointPrior.sync` conditions on every edited keypoint at once).

The file (:func:`write_gltf`: ``.glb``, or ``.gltf`` with a ``.bin`` beside it) holds the mesh with its UVs, vertex
colours and textures (one primitive per material, vertices split where UVs differ), stored relative to its
bounding-box centre (the centre is the mesh node's translation, so float32 keeps the shape exact far from the
origin), under a root node that turns the shape's up axis to glTF's +Y; the keypoints as nodes ``keypoint_<i>``
(children of the mesh node, at their rest positions); and the model, category, kpd version and the targets' keypoint
offsets in ``asset.extras.kpd``. Vertex normals are not written: a stored normal would not follow the morphs, and
glTF consumers compute normals of the deformed surface themselves when none are given. Positions and displacements
are float32: weights equal to an edit's offsets reproduce ``Rig.deform`` within 3e-8 of the box diagonal as
measured (``docs/rigs.md`` has the error and the sizes).
"""

from __future__ import annotations

import io
import json
import logging
import os
import struct
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from kpd.errors import InputError
from kpd._compiled import compiled_on_first_call
from kpd.io import Mesh, atomic_files, atomic_output
from kpd.io.gltf import GlbBuffer, primitive_groups, read_accessor, read_buffers, read_gltf_json, write_glb
from kpd.io.images import encode_png

__all__ = ["MorphRig", "GltfRig", "write_gltf", "gltf_bytes", "write_glb_to", "read_gltf", "GLTF_FORMATS",
           "up_rotation"]

log = logging.getLogger(__name__)

GLTF_FORMATS = (".glb", ".gltf")
_FLOAT, _UINT, _ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 5126, 5125, 34962, 34963
_AXES = {"x": 0, "y": 1, "z": 2}
_BLOCK = 4096  # mesh vertices per product: small enough that BLAS runs each on the calling thread (as Rig.deform)


class MorphRig:
    """A rig's edits as morph targets: per target, the keypoint offsets of one unit of its weight.

    Built from a :class:`kpd.rig.Rig` and a prior by :meth:`from_rig`.

    Parameters
    ----------
    mesh : Mesh, the rest shape in the user's frame and units.
    keypoints : (K, 3) float64, the rest keypoints in the user's frame.
    basis : (V, K) float64, vertex offset per unit keypoint offset (:attr:`kpd.rig.Rig.basis`).
    names : (T,) target names.
    offsets : (T, K, 3) float64, keypoint offsets per unit weight of each target, user units.
    meta : JSON-safe dict written to ``asset.extras.kpd`` (model, category, version...).
    """

    def __init__(self, mesh: Mesh, keypoints: Any, basis: Any, names: Sequence[str], offsets: Any,
                 meta: Mapping | None = None) -> None:
        if not isinstance(mesh, Mesh):
            raise InputError(f"mesh must be a kpd.io.Mesh; got {type(mesh).__name__}")
        keypoints = np.asarray(keypoints, dtype=np.float64)
        basis = np.asarray(basis, dtype=np.float64)
        offsets = np.asarray(offsets, dtype=np.float64)
        v, k = len(mesh.vertices), len(keypoints)
        if keypoints.shape != (k, 3) or not np.isfinite(keypoints).all():
            raise InputError(f"keypoints must be (K, 3) finite numbers; got {keypoints.shape}")
        if basis.shape != (v, k):
            raise InputError(f"basis must have shape (V, K) = ({v}, {k}); got {basis.shape}")
        names = [str(n) for n in names]
        if offsets.shape != (len(names), k, 3) or not np.isfinite(offsets).all():
            raise InputError(f"offsets must be (T, K, 3) = ({len(names)}, {k}, 3) finite numbers; got {offsets.shape}")
        if len(set(names)) != len(names):
            raise InputError("target names must be distinct")
        self.mesh = mesh
        self.keypoints = keypoints
        self.basis = basis
        self.names = names
        self.offsets = offsets
        self.meta = dict(meta or {})

    @classmethod
    def from_rig(cls, rig: Any, prior: Any = None, *, mesh: Mesh | None = None, frame: Any = None,
                 meta: Mapping | None = None) -> "MorphRig":
        """The targets of a rig: its keypoints, and with a prior the synchronised moves and the components.

        Parameters
        ----------
        rig : kpd.rig.Rig.
        prior : kpd.prior.KeypointPrior of the rig's model (``Model.prior``), or None (keypoint targets only).
        mesh : the user's mesh when ``frame`` is given (same topology as ``rig.mesh``); default ``rig.mesh``.
        frame : (4, 4) float64 or None, the affine map from the user's frame to the rig's (a scan's alignment,
            ``ScanResult.transform``); the targets are then in the user's frame, as every other output of a scan.
        meta : extra entries for ``asset.extras.kpd``.

        Returns
        -------
        MorphRig with targets ``keypoint_<i>_<axis>``, then ``prior_<i>_<axis>`` and ``pca_<c>`` with a prior.
        """
        k = rig.num_keypoints
        linear = np.eye(3)  # user -> rig frame, for offsets
        if frame is None:
            mesh = rig.mesh if mesh is None else mesh
            keypoints = rig.keypoints
        else:
            frame = np.asarray(frame, dtype=np.float64)
            if frame.shape != (4, 4) or not np.isfinite(frame).all():
                raise InputError(f"frame must be a finite (4, 4) matrix; got shape {frame.shape}")
            if mesh is None:
                raise InputError("a MorphRig in another frame needs the user's mesh (mesh=...)")
            linear = frame[:3, :3]
            keypoints = np.linalg.solve(linear, (rig.keypoints - frame[:3, 3]).T).T  # (K, 3)
        if not isinstance(mesh, Mesh) or len(mesh.vertices) != len(rig.mesh.vertices):
            raise InputError(f"mesh must be a kpd.io.Mesh of the rig's {len(rig.mesh.vertices)} vertices")
        inverse = np.linalg.inv(linear)
        names, offsets = [], []
        for i in range(k):
            for a, axis in enumerate("xyz"):
                delta = np.zeros((k, 3))
                delta[i, a] = 1.0
                names.append(f"keypoint_{i}_{axis}")
                offsets.append(delta)
        if prior is not None:
            if prior.num_keypoints != k:
                raise InputError(f"the prior has {prior.num_keypoints} keypoints; the rig has {k}")
            normalizer = rig.normalizer
            rest = normalizer.apply(rig.keypoints)  # (K, 3) model frame

            def to_user(model_offsets: np.ndarray) -> np.ndarray:  # (K, 3) model-frame offsets -> user units
                return normalizer.invert_vectors(model_offsets) @ inverse.T

            for i in range(k):
                for a, axis in enumerate("xyz"):
                    move = normalizer.apply_vectors((linear[:, a])[None])[0]  # unit user move, in the model frame
                    # the synchronised edit is linear in the move: a move of one model unit keeps its digits
                    length = float(np.linalg.norm(move))
                    synced = prior.sync(rest, {i: rest[i] + move / length})
                    delta = to_user((synced - rest) * length)
                    delta[i] = 0.0
                    delta[i, a] = 1.0  # the edited keypoint moves exactly as asked (as Model.sync)
                    names.append(f"prior_{i}_{axis}")
                    offsets.append(delta)
            for c, (component, variance) in enumerate(zip(prior.components_, prior.explained_variance_)):
                names.append(f"pca_{c}")
                offsets.append(to_user(np.sqrt(variance) * component))
        return cls(mesh, keypoints, rig.basis, names, np.stack(offsets), meta)

    # --- what the targets do ------------------------------------------------------------------------------------

    def weight_vector(self, weights: Mapping[str, float] | Any) -> np.ndarray:
        """(T,) float64 from ``{name: weight}`` (missing names weigh 0) or a (T,) sequence."""
        t = len(self.names)
        if isinstance(weights, Mapping):
            vector = np.zeros(t)
            index = {n: j for j, n in enumerate(self.names)}
            for name, value in weights.items():
                if name not in index:
                    raise InputError(f"unknown morph target {name!r}; targets are keypoint_<i>_<axis>, "
                                     f"prior_<i>_<axis>, pca_<c> (this rig has {t})")
                vector[index[name]] = float(value)
        else:
            vector = np.asarray(weights, dtype=np.float64).reshape(-1)
        if vector.shape != (t,) or not np.isfinite(vector).all():
            raise InputError(f"weights must be {t} finite numbers; got shape {vector.shape}")
        return vector

    def keypoint_offsets(self, weights: Mapping[str, float] | Any) -> np.ndarray:
        """(K, 3) float64: ``Σ_t w_t Δ_t``, the keypoint offsets of the weights (user units)."""
        return np.tensordot(self.weight_vector(weights), self.offsets, axes=1)

    def keypoints_at(self, weights: Mapping[str, float] | Any) -> np.ndarray:
        """(K, 3) float64: the keypoints the weights move to."""
        return self.keypoints + self.keypoint_offsets(weights)

    def vertices_at(self, weights: Mapping[str, float] | Any) -> np.ndarray:
        """(V, 3) float64: the mesh vertices of the weights, ``V₀ + B Σ_t w_t Δ_t`` (the rig's own edit)."""
        delta = self.keypoint_offsets(weights)
        out = np.empty_like(self.mesh.vertices)
        for start in range(0, len(out), _BLOCK):
            block = slice(start, start + _BLOCK)
            np.matmul(self.basis[block], delta, out=out[block])
        return np.add(out, self.mesh.vertices, out=out)

    def displacement(self, target: int | str) -> np.ndarray:
        """(V, 3) float64: the vertex displacement of one unit of a target's weight."""
        index = self.names.index(target) if isinstance(target, str) else int(target)
        return self.basis @ self.offsets[index]

    def __repr__(self) -> str:
        return (f"MorphRig({len(self.mesh.vertices)} vertices, K={len(self.keypoints)}, {len(self.names)} targets: "
                f"{sum(n.startswith('keypoint_') for n in self.names)} keypoint, "
                f"{sum(n.startswith('prior_') for n in self.names)} prior, "
                f"{sum(n.startswith('pca_') for n in self.names)} pca)")


# --- writing -----------------------------------------------------------------------------------------------------


def up_rotation(up: str) -> list[float] | None:
    """The glTF rotation (x, y, z, w) that turns a named axis (``+z``, ``-y``...) to glTF's +Y; None for +y."""
    text = str(up).strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    key = text.lstrip("+-")
    if key not in _AXES or len(text) - len(key) > 1:
        raise InputError(f"up axis must be one of x, y, z, -x, -y, -z; got {up!r}")
    u = np.zeros(3)
    u[_AXES[key]] = sign
    y = np.array([0.0, 1.0, 0.0])
    if u[1] == 1.0:
        return None
    if u[1] == -1.0:
        return [1.0, 0.0, 0.0, 0.0]  # half a turn about x
    axis = np.cross(u, y)  # unit: u is perpendicular to y here
    return [*(axis * np.sqrt(0.5)).tolist(), float(np.sqrt(0.5))]  # a quarter turn


def _document(morph: MorphRig, *, name: str, up: str, bin_uri: str | None,
              targets: Sequence[str] | None = None, basis: bool = False,
              progress: Callable[[int, int], Any] | None = None,
              stand_in: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None) -> tuple[dict, GlbBuffer]:
    mesh = morph.mesh
    chosen = list(range(len(morph.names))) if targets is None else [morph.names.index(t) for t in targets]
    slots = -(-morph.basis.shape[1] // 4) if basis else 0  # the basis columns, four to an attribute
    rotation = up_rotation(up)
    vertices = mesh.vertices
    used = np.zeros(len(vertices), dtype=bool)  # the vertices of some triangle (np.unique's, without its sort)
    used[mesh.triangles] = True
    if not len(mesh.triangles):
        used[:] = True
    if not used.any():
        raise InputError("a glTF rig needs a mesh with vertices")
    center = (vertices[used].min(axis=0) + vertices[used].max(axis=0)) / 2.0  # (3,)
    builder = GlbBuffer()
    stacked = np.ascontiguousarray(morph.offsets[chosen].transpose(1, 0, 2).reshape(len(morph.keypoints), -1))
    primitives = []
    groups = primitive_groups(mesh)
    advance = None
    if progress is not None and chosen:  # bytes of targets written so far, of all of them
        written, total = [0], 12 * len(chosen) * sum(len(group[1]) for group in groups)

        def advance(nbytes: int) -> None:
            written[0] += nbytes
            progress(written[0], total)

    for material, source, triangles, uv in groups:
        attributes = {"POSITION": builder.accessor((vertices[source] - center).astype(np.float32), "VEC3", _FLOAT,
                                                   _ARRAY_BUFFER, bounds=True)}
        if mesh.vertex_colors is not None:
            attributes["COLOR_0"] = builder.accessor(mesh.vertex_colors[source].astype(np.float32), "VEC3", _FLOAT,
                                                     _ARRAY_BUFFER)
        if uv is not None:
            st = uv * [1.0, -1.0] + [0.0, 1.0]  # glTF puts the UV origin at the top left
            attributes["TEXCOORD_0"] = builder.accessor(st.astype(np.float32), "VEC2", _FLOAT, _ARRAY_BUFFER)
        for j in range(slots):
            columns = np.zeros((len(source), 4), dtype=np.float32)
            part = morph.basis[:, 4 * j:4 * j + 4]
            columns[:, :part.shape[1]] = part[source]
            attributes[f"_KPD_BASIS_{j}"] = builder.accessor(columns, "VEC4", _FLOAT, _ARRAY_BUFFER)
        indices = builder.accessor(triangles.reshape(-1).astype(np.uint32), "SCALAR", _UINT, _ELEMENT_ARRAY_BUFFER)
        primitive = {"attributes": attributes, "indices": indices, "mode": 4}
        coarse = None if stand_in is None else stand_in(vertices[source], triangles)
        if coarse is not None:  # a coarse stand-in over the same vertices: its triangles alone (extras.kpdStandIn)
            primitive["extras"] = {"kpdStandIn": builder.accessor(np.asarray(coarse).reshape(-1).astype(np.uint32),
                                                                  "SCALAR", _UINT, _ELEMENT_ARRAY_BUFFER)}
        if chosen:
            # the targets' displacements are made as the file is written, a block of vertices at a time (at 1.37M
            # vertices, 80 targets are 1.3 GB); their bounds, which the JSON before them holds, by a pass of their
            # own
            displacements = _Displacements(morph.basis, source, stacked, advance)
            low, high = displacements.bounds()  # (T, 3) float32 each
            start = builder.region(displacements.nbytes, displacements.write)
            size = 12 * len(source)  # bytes of one target: (n, 3) float32
            primitive["targets"] = [{"POSITION": builder.accessor_at(start + j * size, size, len(source), "VEC3",
                                                                     _FLOAT, _ARRAY_BUFFER, bounds=(lo, hi))}
                                    for j, (lo, hi) in enumerate(zip(low, high))]
        if material is not None:
            primitive["material"] = material
        primitives.append(primitive)
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": f"kpd {_version()}",
                  "extras": {"kpd": {**morph.meta, "version": _version(), "frame": "input",
                                     "keypoints": morph.keypoints.tolist(),
                                     "targets": list(morph.names),
                                     "keypointOffsets": morph.offsets.tolist()}}},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0]}],
    }
    root: dict[str, Any] = {"name": name, "children": [1]}
    if rotation is not None:
        root["rotation"] = rotation
    node = {"name": f"{name}_mesh", "mesh": 0, "children": list(range(2, 2 + len(morph.keypoints)))}
    if np.any(center != 0):
        node["translation"] = center.tolist()
    doc["nodes"] = [root, node] + [{"name": f"keypoint_{i}", "translation": (p - center).tolist()}
                                   for i, p in enumerate(morph.keypoints)]
    doc["meshes"] = [{"name": name, "primitives": primitives}]
    if chosen:
        doc["meshes"][0].update(weights=[0.0] * len(chosen), extras={"targetNames": [morph.names[t] for t in chosen]})
    if bool(mesh.textures) and mesh.triangle_uvs is not None:
        doc["images"] = [{"bufferView": builder.view(encode_png(t)), "mimeType": "image/png"} for t in mesh.textures]
        doc["samplers"] = [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}]
        doc["textures"] = [{"source": i, "sampler": 0} for i in range(len(mesh.textures))]
        doc["materials"] = [{"name": f"{name}_{i}", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": i}, "metallicFactor": 0.0, "roughnessFactor": 1.0}}
            for i in range(len(mesh.textures))]
    doc["bufferViews"] = builder.views
    doc["accessors"] = builder.accessors
    buffer: dict[str, Any] = {"byteLength": builder.length}
    if bin_uri is not None:
        buffer["uri"] = bin_uri
    doc["buffers"] = [buffer]
    return doc, builder


class _Displacements:
    """Every target's displacement of a primitive's vertices, ``basis[source] @ stacked``, in the file's layout: target
    after target, each (n, 3) float32 (the sums in keypoint order in float64, by a compiled loop over the vertices on
    two threads, :func:`_displace`). Made a block of vertices at a time, each block's rows of every target written to
    their places in the file (:meth:`write`), so that the (T, n, 3) array is never held: 1.3 GB for the 80 targets of
    a 1.37M-vertex chair (docs/rigs.md)."""

    def __init__(self, basis: np.ndarray, source: np.ndarray, stacked: np.ndarray,
                 progress: Callable[[int], Any] | None = None) -> None:
        self.basis = basis
        self.progress = progress  # called with the bytes of each block written
        self.source = np.ascontiguousarray(source, dtype=np.int64)
        self.stacked = np.ascontiguousarray(stacked, dtype=np.float64)
        self.n, self.t = len(self.source), self.stacked.shape[1] // 3
        self.nbytes = 12 * self.n * self.t

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(T, 3) float32 each: the accessors' min and max (float32 rounding keeps the order, so the float64 values'
        bounds, rounded, are the float32 data's)."""
        low, high = self._run(np.empty((self.t, 0, 3), dtype=np.float32), 0, self.n)
        return low.reshape(self.t, 3).astype(np.float32), high.reshape(self.t, 3).astype(np.float32)

    def block(self, lo: int, hi: int, out: np.ndarray | None = None) -> np.ndarray:
        """(T, hi - lo, 3) float32: the displacements of vertices ``source[lo:hi]`` (into ``out``'s first rows)."""
        out = np.empty((self.t, hi - lo, 3), dtype=np.float32) if out is None else out[:, :hi - lo]
        self._run(out, lo, hi)
        return out

    def write(self, fh) -> None:
        """Write every target's displacements to ``fh`` (seekable, at the targets' start), leaving it at their end."""
        start = fh.tell()
        rows = max(1, min(self.n, _WRITE_BYTES // max(12 * self.t, 1)))
        buffer = np.empty((self.t, rows, 3), dtype=np.float32)
        for lo in range(0, self.n, rows):
            hi = min(lo + rows, self.n)
            block = self.block(lo, hi, buffer)
            for j in range(self.t):
                fh.seek(start + 12 * (j * self.n + lo))
                fh.write(memoryview(block[j]).cast("B"))
            if self.progress is not None:
                self.progress(12 * self.t * (hi - lo))
        fh.seek(start + self.nbytes)

    def _run(self, out: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """:func:`_displace` of rows [lo, hi) into ``out`` (none stored when it has no rows), on two threads when
        there are many; returns the (3T,) bounds of the values."""
        n, c = hi - lo, 3 * self.t
        threads = 2 if n >= 2 * _BLOCK and (os.cpu_count() or 1) > 1 else 1
        cuts = np.linspace(lo, hi, threads + 1).astype(np.int64).tolist()
        low, high = np.full((threads, c), np.inf), np.full((threads, c), -np.inf)
        args = (self.basis, self.source, self.stacked, out)
        if threads == 1:
            _displace(*args, low[0], high[0], lo, hi, lo)
        else:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(threads - 1, thread_name_prefix="kpd-morph") as pool:
                others = [pool.submit(_displace, *args, low[k], high[k], cuts[k], cuts[k + 1], lo)
                          for k in range(1, threads)]
                _displace(*args, low[0], high[0], cuts[0], cuts[1], lo)
                for other in others:
                    other.result()
        return low.min(axis=0), high.max(axis=0)


_WRITE_BYTES = 32 * 2**20  # displacements made and written at a time


@compiled_on_first_call
def _displace(basis, source, stacked, out, low, high, lo, hi, base):  # pragma: no cover - compiled
    """``out[:, i - base] = (basis[source[i]] @ stacked).reshape(T, 3)`` for i in [lo, hi), the sums in keypoint
    order in float64 and stored as float32 (nothing stored when ``out`` has no rows); ``low`` and ``high`` (3T,) take
    the float64 values' bounds. Four rows at a time, each of ``stacked``'s values read once for the four, the loops
    over the 3T columns SIMD code (the bounds by selects, which vectorise where ``min`` does not): half the time of a
    row at a time. A short last group repeats its last row, which changes no bound and is not stored."""
    K, C = stacked.shape
    store = out.shape[1] > 0
    r0, r1, r2, r3 = np.empty(C), np.empty(C), np.empty(C), np.empty(C)
    for i in range(lo, hi, 4):
        m = min(4, hi - i)
        s0 = source[i]
        s1 = source[i + min(1, m - 1)]
        s2 = source[i + min(2, m - 1)]
        s3 = source[i + min(3, m - 1)]
        for c in range(C):
            r0[c] = 0.0
            r1[c] = 0.0
            r2[c] = 0.0
            r3[c] = 0.0
        for k in range(K):
            b0, b1, b2, b3 = basis[s0, k], basis[s1, k], basis[s2, k], basis[s3, k]
            for c in range(C):
                x = stacked[k, c]
                r0[c] += b0 * x
                r1[c] += b1 * x
                r2[c] += b2 * x
                r3[c] += b3 * x
        for c in range(C):
            least, most = low[c], high[c]
            v = r0[c]
            least, most = v if v < least else least, v if v > most else most
            v = r1[c]
            least, most = v if v < least else least, v if v > most else most
            v = r2[c]
            least, most = v if v < least else least, v if v > most else most
            v = r3[c]
            least, most = v if v < least else least, v if v > most else most
            low[c], high[c] = least, most
        if store:
            j = i - base
            for c in range(C):
                t, a = c // 3, c % 3
                out[t, j, a] = r0[c]
                if m > 1:
                    out[t, j + 1, a] = r1[c]
                if m > 2:
                    out[t, j + 2, a] = r2[c]
                if m > 3:
                    out[t, j + 3, a] = r3[c]


def _version() -> str:
    from kpd import __version__

    return __version__


def gltf_bytes(morph: MorphRig, *, name: str = "kpd_rig", up: str = "+z", targets: Sequence[str] | None = None,
               basis: bool = False) -> bytes:
    """The GLB file of a rig (what :func:`write_gltf` writes to a ``.glb``), in memory.

    ``targets`` keeps only the named morph targets in the mesh (``asset.extras.kpd`` still lists every target's
    keypoint offsets): every edit is a sum of the keypoint targets. ``basis``: see :func:`write_glb_to` (what the
    browser editor's page loads, with ``targets=[]``).
    """
    out = io.BytesIO()
    write_glb_to(out, morph, name=name, up=up, targets=targets, basis=basis)
    return out.getvalue()


def write_glb_to(fh, morph: MorphRig, *, name: str = "kpd_rig", up: str = "+z",
                 targets: Sequence[str] | None = None, basis: bool = False,
                 stand_in: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None) -> int:
    """Write the GLB of :func:`gltf_bytes` to ``fh`` (a seekable binary file at its start: the targets are written
    32 MB of vertices at a time, each block's rows to their places), leaving it at the end; returns its length.

    ``basis``: the rig's (V, K) basis as the primitives' own vertex attributes ``_KPD_BASIS_<j>`` (VEC4 float32,
    columns ``4j`` to ``4j + 3``, zeros past K; an application-specific attribute, which glTF viewers ignore), for
    a page that adds ``sum_i B_i o_i`` itself: K numbers a vertex where the K x 3 keypoint targets are 9 K. Give
    ``targets=[]`` with it for a file without morph targets.

    ``stand_in(vertices, triangles)``: for each primitive, (Q, 3) triangles over its own vertices drawn instead of
    its triangles while a keypoint is dragged (a coarse stand-in of a large mesh), or None; kept in the primitive's
    ``extras.kpdStandIn`` as the index of an accessor of them.
    """
    doc, builder = _document(morph, name=name, up=up, bin_uri=None, targets=targets, basis=basis, stand_in=stand_in)
    write_glb(fh, doc, builder)
    return fh.tell()


def write_gltf(path: str | os.PathLike, morph: MorphRig, *, name: str | None = None, up: str = "+z",
               targets: Sequence[str] | None = None, progress: Callable[[int, int], Any] | None = None) -> Path:
    """Write a rig as glTF 2.0 with morph targets, atomically.

    Parameters
    ----------
    path : ``.glb`` (one file), or ``.gltf`` (JSON) with ``<stem>.bin`` beside it.
    morph : MorphRig.
    name : the scene's, root node's and mesh's name; the file's stem by default.
    up : the shape's up axis (``+z`` for ModelNet); a root node turns it to glTF's +Y, so that viewers show the
        shape upright. The mesh node's coordinates stay the user's.
    targets : the morph targets to write (names of ``morph.names``, in its order); all when None.
        ``asset.extras.kpd`` lists every target's keypoint offsets either way.
    progress : ``progress(written, total)`` after each block of targets written (bytes), or None.

    Returns
    -------
    The path written.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in GLTF_FORMATS:
        raise InputError(f"{p}: a glTF rig file must end in .glb or .gltf; got {ext or 'no extension'!r}")
    name = p.stem if name is None else name
    if ext == ".glb":
        doc, builder = _document(morph, name=name, up=up, bin_uri=None, targets=targets, progress=progress)
        with atomic_output(p) as tmp:
            with open(tmp, "wb") as fh:
                write_glb(fh, doc, builder)
        return p
    bin_name = p.stem + ".bin"
    doc, builder = _document(morph, name=name, up=up, bin_uri=_uri(bin_name), targets=targets, progress=progress)
    with atomic_files(p) as target:
        with open(target.parent / bin_name, "wb") as fh:
            builder.write(fh)
        target.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    return p


def _uri(name: str) -> str:
    import urllib.parse

    return urllib.parse.quote(name)


# --- reading -----------------------------------------------------------------------------------------------------


class GltfRig(NamedTuple):
    """A glTF rig file as its consumers see it (:func:`read_gltf`).

    - document : dict, the glTF JSON.
    - names : (T,) target names from ``meshes[0].extras.targetNames``.
    - positions : per primitive, (n, 3) float64 positions in the mesh node's frame (the user's coordinates: the mesh
      node's translation added).
    - targets : per primitive, (T, n, 3) float64 displacements.
    - indices : per primitive, (t, 3) int64 triangles.
    - keypoints : (K, 3) float64, the ``keypoint_<i>`` nodes' positions in the mesh node's frame (user coordinates).
    """

    document: dict
    names: list
    positions: list
    targets: list
    indices: list
    keypoints: np.ndarray

    def morphed(self, weights: Mapping[str, float]) -> list[np.ndarray]:
        """Per primitive, (n, 3) positions for ``{name: weight}``, as a glTF consumer computes them (float64)."""
        w = np.zeros(len(self.names))
        for name, value in weights.items():
            w[self.names.index(name)] = value
        return [p + np.tensordot(w, t, axes=1) for p, t in zip(self.positions, self.targets)]


def read_gltf(path: str | os.PathLike) -> GltfRig:
    """Read a glTF rig written by :func:`write_gltf` (a ``.glb``, or a ``.gltf`` with its buffers)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such glTF file")
    try:
        doc, chunk = read_gltf_json(p)
        buffers = read_buffers(p, doc, chunk)

        def accessor(index: int) -> np.ndarray:
            a = read_accessor(p, doc, buffers, index)  # (count, width) float64 or int64
            return a[:, 0] if a.shape[1] == 1 else a

        gltf_mesh = doc["meshes"][0]
        names = list(gltf_mesh.get("extras", {}).get("targetNames", []))
        nodes = doc["nodes"]
        mesh_node = next(n for n in nodes if n.get("mesh") == 0)
        translation = np.asarray(mesh_node.get("translation", [0.0, 0.0, 0.0]), dtype=np.float64)
        positions, targets, indices = [], [], []
        for primitive in gltf_mesh["primitives"]:
            positions.append(accessor(primitive["attributes"]["POSITION"]) + translation)
            targets.append(np.stack([accessor(t["POSITION"]) for t in primitive.get("targets", [])])
                           if primitive.get("targets") else np.zeros((0, len(positions[-1]), 3)))
            indices.append(accessor(primitive["indices"]).reshape(-1, 3))
        points = {n["name"]: n.get("translation", [0.0, 0.0, 0.0]) for n in nodes if n.get("name", "").startswith(
            "keypoint_")}
        keypoints = np.array([points[f"keypoint_{i}"] for i in range(len(points))], dtype=np.float64).reshape(-1, 3)
    except (KeyError, IndexError, ValueError, StopIteration, struct.error, UnicodeDecodeError, OSError) as exc:
        raise InputError(f"{p}: not a glTF rig written by kpd ({type(exc).__name__}: {exc})") from exc
    return GltfRig(doc, names, positions, targets, indices, keypoints + translation)
