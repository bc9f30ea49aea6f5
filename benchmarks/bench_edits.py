"""Edit quality on held-out shapes: locality, detail preservation, semantic edits, the prior's response, samples.

Prints one JSON object (``--out`` writes it too). For each category (ModelNet10 *test* chairs and tables, never seen
in training) and each deformer, side by side in one run:

* each ``--variant NAME:CATEGORY=BUNDLE,...`` (default ``shipped``: the bundles in ``kpd/models``), e.g. the
  bundles shipped before (level-1 cage), the level-2 cage retrained, and the same with the rig's cage fitted
  tighter (``kpd export --rig-cage-distance``), each with its prior as written;
* ``biharmonic``: libigl's biharmonic deformation (``igl.harmonic(..., k=2)``, the classical handle deformer) with
  the first variant's keypoints as handles (each handle the mesh vertex nearest its keypoint), the anchor for
  locality and detail.

Every measure is defined in :mod:`kpd.metrics` and runs in the model's [-1, 1] frame on the test mesh with its
duplicate vertices merged (``igl.remove_duplicate_vertices``; CAD meshes store one vertex per triangle corner, and
the biharmonic solve needs a connected surface), the same mesh for all deformers:

* locality (``far_side_leakage``): every keypoint moved alone along each axis by ``--move`` (0.2 = 10% of the box
  side); the area-weighted mean displacement of the farther half of the surface, relative to the move;
* detail (``edit_distortion``): share of folded triangles, mean relative edge-length change, mean dihedral change,
  for those single moves and for the semantic edits (``semantic_edits`` from ``keypoint_roles`` of the model's
  training keypoints, each keypoint by ``--move``);
* prior response (``prior_response``): each keypoint that has a mirror partner moved alone along each axis with the
  prior, for the bundle's prior and for the prior refitted by this kpd (mirror-symmetric) on the same network's
  training keypoints; the permutation is the mirror-consistency one (``fit_mirror_permutation`` on training shapes);
* samples (``folded_share``, ``new_self_intersections``, ``keypoint_set_distance``): ``--samples`` prior draws per
  shape at the default scale (0.5) and at 1.0, with the refitted prior.

    python benchmarks/bench_edits.py --variant before:chair=old/chair.kpd,table=old/table.kpd \\
        --variant level2:chair=runs/chair-l2.kpd,table=runs/table-l2.kpd --variant shipped:chair=chair,table=table \\
        --out benchmarks/results/edits.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from kpd.data import discover
from kpd.io import Mesh, read_mesh
from kpd.metrics import (edit_distortion, far_side_leakage, fit_mirror_permutation, folded_area_share, folded_share,
                         keypoint_roles,
                         keypoint_set_distance, new_self_intersections, prior_response, semantic_edits, vertex_areas)
from kpd.prior import KeypointPrior
from kpd.runtime import Model
from kpd.benchmark import write_json
from kpd.triangles import areas as triangle_areas

DATA = Path(os.environ.get("KPD_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
SAMPLE_SCALES = (0.5, 1.0)  # kpd sample's default scale, and one standard deviation


def weld(mesh: Mesh) -> Mesh:
    """The mesh with coincident vertices merged and degenerate triangles dropped (igl.remove_duplicate_vertices)."""
    import igl

    v, f = mesh.vertices, mesh.triangles
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    sv, _, _, sf = igl.remove_duplicate_vertices(v, f, 1e-7 * diag)
    sf = np.asarray(sf, dtype=np.int64)
    area = triangle_areas(sv, sf)
    sf = sf[(area > 1e-12 * diag**2) & (sf[:, 0] != sf[:, 1]) & (sf[:, 1] != sf[:, 2]) & (sf[:, 0] != sf[:, 2])]
    used = np.unique(sf)
    remap = np.full(len(sv), -1)
    remap[used] = np.arange(len(used))
    return Mesh(np.ascontiguousarray(sv[used], dtype=np.float64), remap[sf])


class BiharmonicFailed(RuntimeError):
    """libigl could not solve the biharmonic system of a mesh (counted in the JSON, the shape is left out)."""


def biharmonic_basis(vertices: np.ndarray, triangles: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """(V, K) biharmonic coordinates of the handles (libigl): displacement = basis @ keypoint offsets.

    Handle k is the mesh vertex nearest keypoint k (a distinct one per keypoint). Each connected piece of the mesh
    with handles is solved on its own; a piece without handles does not move (a surface deformer cannot reach it).
    """
    import igl
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse import coo_matrix

    k = len(keypoints)
    d = np.linalg.norm(vertices[None] - keypoints[:, None], axis=2)  # (K, V)
    handles = np.empty(k, dtype=np.int64)
    taken: set[int] = set()
    for i in np.argsort(d.min(axis=1)):
        for j in np.argsort(d[i]):
            if int(j) not in taken:
                handles[i] = j
                taken.add(int(j))
                break
    n = len(vertices)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    basis = np.zeros((n, k))
    for piece in np.unique(label[handles]):
        members = np.flatnonzero(label == piece)
        local = np.full(n, -1)
        local[members] = np.arange(len(members))
        faces = local[triangles[np.isin(triangles[:, 0], members)]]
        mine = np.flatnonzero(label[handles] == piece)
        bc = np.zeros((len(mine), k))
        bc[np.arange(len(mine)), mine] = 1.0
        try:
            w = igl.harmonic(np.ascontiguousarray(vertices[members]), np.ascontiguousarray(faces),
                             local[handles[mine]].astype(np.int64), bc, 2)
        except RuntimeError as exc:  # libigl's solve fails on some CAD pieces (degenerate cotangent weights)
            raise BiharmonicFailed(str(exc)) from exc
        basis[members] = np.nan_to_num(np.asarray(w), nan=0.0, posinf=0.0, neginf=0.0)
    return basis


def training_keypoints(model: Model, files: list, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, K, 3) keypoints of training shapes and of their mirror images (about x) mirrored back, model frame."""
    flip = np.array([-1.0, 1.0, 1.0])
    kp, mk = [], []
    for f in tqdm(files[:limit], desc="training keypoints", leave=False):
        mesh = read_mesh(f.path)
        mirror = Mesh(mesh.vertices * flip, mesh.triangles[:, ::-1].copy())
        a, b = model.predict_batch([mesh, mirror])
        kp.append(a.keypoints)
        mk.append(b.keypoints * flip)
    return np.stack(kp), np.stack(mk)


def summarise(values: list[float]) -> dict:
    a = np.asarray(values, dtype=np.float64)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p90": float(np.quantile(a, 0.9)),
            "max": float(a.max()), "n": int(a.size)}


def measure_deformer(rest: np.ndarray, triangles: np.ndarray, areas: np.ndarray, basis: np.ndarray,
                     keypoints: np.ndarray, edits: dict, move: float, acc: dict) -> None:
    """Single moves and semantic edits of one shape with one linear deformer (displacement = basis @ offsets)."""
    for k in range(len(keypoints)):
        for axis in range(3):
            offset = np.zeros(3)
            offset[axis] = move
            deformed = rest + basis[:, k:k + 1] * offset  # (V, 3)
            acc["leakage"].append(far_side_leakage(rest, deformed, keypoints[k], move, areas))
            dist = edit_distortion(rest, deformed, triangles)
            acc["single_folded"].append(dist.folded)
            acc.setdefault("single_folded_area", []).append(folded_area_share(rest, deformed, triangles))
            acc["single_edge"].append(dist.edge)
            acc["single_dihedral"].append(dist.dihedral)
    for name, edit in edits.items():
        offsets = np.zeros_like(keypoints)
        for index, offset in edit.items():
            offsets[index] = offset
        deformed = rest + basis @ offsets
        dist = edit_distortion(rest, deformed, triangles)
        for field in ("folded", "edge", "dihedral"):
            acc.setdefault(f"{name}_{field}", []).append(getattr(dist, field))
        acc.setdefault(f"{name}_folded_area", []).append(folded_area_share(rest, deformed, triangles))


def response(prior: KeypointPrior, keypoint_sets: np.ndarray, permutation: np.ndarray, move: float) -> dict:
    """Partner and others' response to single moves with the prior, per keypoint (mean over shapes and axes)."""
    per_key = {}
    for i, p in enumerate(permutation.tolist()):
        if p == i:
            continue
        partner, others = [], []
        for keypoints in keypoint_sets:
            for axis in range(3):
                offset = np.zeros(3)
                offset[axis] = move
                after = prior.sync(keypoints, {i: keypoints[i] + offset})
                r = prior_response(keypoints, after, i, p, offset)
                partner.append(r.partner)
                others.append(r.others)
        per_key[str(i)] = {"partner": p, "partner_response": float(np.mean(partner)),
                           "partner_response_min_axis": float(np.min(np.reshape(partner, (-1, 3)).mean(axis=0))),
                           "others_response": float(np.mean(others))}
    values = list(per_key.values())
    return {
        "per_keypoint": per_key,
        "partner_min": min(v["partner_response"] for v in values) if values else None,
        "partner_mean": float(np.mean([v["partner_response"] for v in values])) if values else None,
        "others_max": max(v["others_response"] for v in values) if values else None,
        "others_mean": float(np.mean([v["others_response"] for v in values])) if values else None,
        "pairs": int(len(values) // 2),
    }


def run_category(category: str, bundles: dict[str, str], args: argparse.Namespace) -> dict:
    data = discover(DATA / "modelnet10", category)
    tests = sorted(data.splits["test"], key=lambda f: f.name)[: args.shapes]
    train = sorted(data.splits["train"], key=lambda f: f.name)
    step = max(1, len(train) // args.train_shapes)
    train = train[::step][: args.train_shapes]
    meshes = [weld(read_mesh(f.path)) for f in tests]
    first = next(iter(bundles))
    out: dict = {"test_shapes": [f.name for f in tests], "train_shapes_for_prior": len(train), "deformers": {}}
    for label, path in bundles.items():
        model = Model.load(path, threads=1)
        if label in args.distances:  # as if exported with --rig-cage-distance (0: the training cage)
            model._rig_fit = {"distance": args.distances[label]} if args.distances[label] else {}
        t0 = time.perf_counter()
        kp_train, mk_train = training_keypoints(model, train, len(train))
        permutation = fit_mirror_permutation(kp_train, mk_train)
        refit = KeypointPrior(n_components=model.prior.n_components).fit(kp_train, mk_train)
        roles = keypoint_roles(model.prior.mean_)
        edits = semantic_edits(roles, category, args.move)
        acc: dict = {key: [] for key in ("leakage", "single_folded", "single_edge", "single_dihedral")}
        anchor: dict = {key: [] for key in acc}
        anchor_failed = 0
        samples = {scale: {"folded": [], "folded_area": [], "intersecting": [], "distance": []}
                   for scale in SAMPLE_SCALES}
        test_sets = []
        for mesh in tqdm(meshes, desc=f"{category} {label}", leave=False):
            rig = model.rig(mesh, straighten=label not in args.no_straighten)
            rest = rig.normalizer.apply(mesh.vertices)  # (V, 3) model frame
            keypoints = rig.normalizer.apply(rig.keypoints)
            test_sets.append(keypoints)
            areas = vertex_areas(rest, mesh.triangles)
            measure_deformer(rest, mesh.triangles, areas, rig.basis, keypoints, edits, args.move, acc)
            if label == first:
                try:
                    basis = biharmonic_basis(rest, mesh.triangles, keypoints)
                    measure_deformer(rest, mesh.triangles, areas, basis, keypoints, edits, args.move, anchor)
                except BiharmonicFailed:
                    anchor_failed += 1
            for scale in SAMPLE_SCALES:
                sets = refit.sample(args.samples, seed=0, scale=scale, base=keypoints)  # (n, K, 3)
                for s in sets:
                    deformed = rest + rig.basis @ (s - keypoints)
                    samples[scale]["folded"].append(folded_share(rest, deformed, mesh.triangles))
                    samples[scale]["folded_area"].append(folded_area_share(rest, deformed, mesh.triangles))
                    samples[scale]["intersecting"].append(
                        float(new_self_intersections(rest, deformed, mesh.triangles) > 0))
                samples[scale]["distance"].extend(keypoint_set_distance(sets, kp_train).tolist())
        test_sets = np.stack(test_sets)
        result = {
            "bundle": str(model.bundle.path),
            "cage_vertices": model.num_cage_vertices, "m": model.m,
            "rig_cage_distance": model.rig_settings["rig"].get("distance", model.rig_settings["fit"].get("distance")),
            "rig_settings": model.rig_settings,
            "straightened": label not in args.no_straighten,
            "roles": {k: (v.tolist()) for k, v in roles.items()},
            "semantic_edits": {name: {str(i): o.tolist() for i, o in e.items()} for name, e in edits.items()},
            "mirror_permutation": permutation.tolist(),
            "measures": {key: summarise(v) for key, v in acc.items()},
            "prior_response": {
                "bundle_prior": response(model.prior, test_sets, permutation, args.move),
                "refitted_prior": response(refit, test_sets, permutation, args.move),
            },
            "samples": {str(scale): {
                "folded_share": summarise(v["folded"]),
                "folded_area_share": summarise(v["folded_area"]),
                "self_intersecting_share": float(np.mean(v["intersecting"])),
                "distance_to_training": summarise(v["distance"]),
            } for scale, v in samples.items()},
            "test_keypoints_distance_to_training": summarise(keypoint_set_distance(test_sets, kp_train).tolist()),
            "seconds": time.perf_counter() - t0,
        }
        out["deformers"][label] = result
        if label == first:
            out["deformers"]["biharmonic"] = {
                "handles": f"the keypoints of {first} (nearest mesh vertex each)",
                "measures": {key: summarise(v) for key, v in anchor.items()},
                "shapes_libigl_failed_on": anchor_failed,
            }
    return out


def parse_paths(text: str | None) -> dict[str, str]:
    if not text:
        return {}
    pairs = [item.split("=", 1) for item in text.split(",") if item]
    if any(len(p) != 2 for p in pairs):
        raise SystemExit(f"expected CATEGORY=PATH[,CATEGORY=PATH]; got {text!r}")
    return dict(pairs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--categories", default="chair,table")
    parser.add_argument("--shapes", type=int, default=20, help="held-out test shapes per category (default 20)")
    parser.add_argument("--train-shapes", type=int, default=200,
                        help="training shapes for the mirror permutation and the refitted prior (default 200)")
    parser.add_argument("--move", type=float, default=0.2, help="keypoint move, [-1, 1] box units (default 0.2)")
    parser.add_argument("--samples", type=int, default=8, help="prior samples per shape and scale (default 8)")
    parser.add_argument("--variant", action="append", default=[],
                        help="NAME:CATEGORY=BUNDLE,... (repeatable; default shipped:chair=chair,table=table)")
    parser.add_argument("--rig-cage-distance", action="append", default=[], metavar="NAME=D",
                        help="fit the rigs' cages of variant NAME with stop distance D and transfer the influence "
                             "to them, as kpd export --rig-cage-distance D records it; 0: the training cage "
                             "(repeatable)")
    parser.add_argument("--no-straighten", action="append", default=[], metavar="NAME",
                        help="bind the rigs of variant NAME without straightening their slivers "
                             "(kpd.rig.straighten_basis), as kpd did before it (repeatable)")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    args.distances = {name: float(d) for name, d in (item.split("=", 1) for item in args.rig_cage_distance)}
    variants = {}
    for item in args.variant or ["shipped:chair=chair,table=table"]:
        name, _, paths = item.partition(":")
        variants[name] = parse_paths(paths)
    t0 = time.perf_counter()
    result: dict = {
        "benchmark": "edits",
        "settings": {"variants": variants, "rig_cage_distance": args.distances,
                     "no_straighten": args.no_straighten, "shapes": args.shapes,
                     "train_shapes": args.train_shapes, "move": args.move, "samples": args.samples,
                     "sample_scales": list(SAMPLE_SCALES), "frame": "model [-1, 1] box"},
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "load": os.getloadavg()},
        "categories": {},
    }
    for category in args.categories.split(","):
        bundles = {name: paths[category] for name, paths in variants.items() if category in paths}
        result["categories"][category] = run_category(category, bundles, args)
    result["seconds"] = time.perf_counter() - t0
    print(json.dumps(result, indent=2))
    if args.out:
        write_json(args.out, result, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
