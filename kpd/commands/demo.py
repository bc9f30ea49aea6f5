"""kpd demo: deform a chair with the shipped chair model, offline, and write the result and a picture."""

from __future__ import annotations

import argparse

import numpy as np

from kpd.commands import number
from kpd.procedural import box_mesh as _box, procedural_chair  # noqa: F401  (importable from here as before)

HELP = "deform a chair with the shipped chair model (offline) and write the meshes, keypoints and a picture"
EXAMPLE = "kpd demo --out demo-output    (or: kpd demo --mesh my_chair.obj --out demo-output)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_scan_arguments

    parser.add_argument("--out", default="kpd-demo", metavar="DIR", help="folder to create (default kpd-demo)")
    parser.add_argument("--mesh", default=None, help="your own chair mesh instead of the built-in procedural chair "
                                                     "(z up, back toward +y, like ModelNet)")
    parser.add_argument("--model", default="chair", help="bundle to use (default: the shipped chair model)")
    add_scan_arguments(parser)
    parser.add_argument("--amount", type=number(0, 1), default=0.12, metavar="FRACTION",
                        help="how far to pull one leg outward, as a fraction of the shape's height (default 0.12)")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    import json

    from kpd.commands._shared import category_azimuth, render_sheet, rig_checked, scan_frame, shape_view
    from kpd.errors import InputError
    from kpd.frame import ScanRig
    from kpd.io import Outputs, read_mesh, write_mesh
    from kpd.runtime import Model

    if args.scan and args.mesh is None:
        raise InputError("--scan goes with --mesh (the built-in chair is in the model's frame already)")
    outputs = Outputs(force=args.force, inputs=(args.mesh, args.model))
    out = outputs.folder(args.out, "--out")
    model = Model.load(args.model)
    scan = None
    if args.mesh is None:
        mesh = procedural_chair()
        rig = model.rig(mesh)
    else:
        mesh = read_mesh(args.mesh)
        if args.scan:
            # rigged in the model's frame, edited and written in the mesh's own (its rig.npz would lose that frame)
            scan = scan_frame(args, model, mesh, path=args.mesh)
            rig = ScanRig(model.rig(mesh.with_vertices(scan.to_aligned(mesh.vertices))), mesh, scan)
        else:
            rig = rig_checked(model, mesh, 0, args.mesh)
    rest = rig.keypoints  # (K, 3) in the mesh's units
    view_up, front = shape_view(model, args.mesh, scan)
    up = _axis(view_up)
    height = float(np.ptp(mesh.vertices @ up))
    leg, target = pick_edit(rest, up, height, args.amount)
    alone = rig.moved({leg: target - rest[leg]})
    synced = model.sync(rig, {leg: target}) if model.prior is not None else None

    with outputs:
        staging = outputs.stage(out)
        staging.mkdir()
        write_mesh(staging / "input.ply", mesh)
        write_mesh(staging / "deformed_alone.ply", rig.deformed_mesh(alone))
        meshes, keypoints = [mesh, rig.deformed_mesh(alone)], [rest, alone]
        titles = ["input", f"keypoint {leg} pulled outward"]
        if synced is not None:
            write_mesh(staging / "deformed.ply", rig.deformed_mesh(synced))
            meshes.append(rig.deformed_mesh(synced))
            keypoints.append(synced)
            titles.append("the same, with the category prior")
        if scan is None:
            rig.save(staging / "rig.npz")
        record = {
            "model": str(args.model), "category": model.category, "input": args.mesh or "procedural chair",
            "frame": "input", **({"scan": scan.report()} if scan is not None else {}), "moved": leg,
            "target": target.tolist(), "rest_keypoints": rest.tolist(),
            "moved_alone": alone.tolist(), "moved_with_prior": None if synced is None else synced.tolist(),
        }
        (staging / "keypoints.json").write_text(json.dumps(record, indent=1) + "\n")
        arrows = [(rest[[leg]], target[None]), None] + ([None] if synced is not None else [])
        render_sheet(meshes, staging / "demo.png", titles=titles, keypoints=keypoints, columns=len(meshes),
                     up=view_up or "+z", front=front, azimuth=category_azimuth(model), cell=3.6, arrows=arrows)
    files = "input.ply, deformed_alone.ply" + (", deformed.ply" if synced is not None else "")
    files += ", rig.npz" if scan is None else ""
    print(f"wrote {out}/: {files}, keypoints.json, demo.png (keypoint {leg}, a leg, pulled outward by "
          f"{args.amount:g} of the height" + (", and again with the category prior moving the others)" if synced
                                               is not None else ")"))
    tops = np.argsort(rest @ up, kind="stable")[-2:]  # the two highest keypoints (a chair's backrest corners)
    lift = ",".join(f"{v:g}" for v in np.round(up * 0.15 * height, 2) + 0.0)
    moves = " ".join(f"--move {int(i)}:{lift}" for i in sorted(tops))
    print(f"next: kpd deform {args.model} {out}/input.ply {moves}{' --scan' if scan is not None else ''} "
          "--out taller_back.ply")
    return 0


def pick_edit(keypoints: np.ndarray, up: np.ndarray, height: float, amount: float) -> tuple[int, np.ndarray]:
    """The demo's edit: of the four lowest keypoints (the legs of a chair), the one farthest from the keypoints'
    vertical axis, pulled horizontally outward by ``amount * height``.

    Returns
    -------
    index : int, target : (3,) float64.
    """
    heights = keypoints @ up
    low = np.argsort(heights, kind="stable")[: min(4, len(keypoints))]
    centre = keypoints.mean(axis=0)
    flat = keypoints[low] - centre
    flat -= np.outer(flat @ up, up)  # horizontal parts (n, 3)
    i = int(np.argmax(np.linalg.norm(flat, axis=1)))
    direction = flat[i] / max(np.linalg.norm(flat[i]), 1e-12)
    index = int(low[i])
    return index, keypoints[index] + amount * height * direction


def _axis(up: str | None) -> np.ndarray:
    letter = _up_letter(up)
    axis = np.zeros(3)
    axis["xyz".index(letter)] = -1.0 if (up or "").startswith("-") else 1.0
    return axis


def _up_letter(up: str | None) -> str:
    return (up or "+z").lstrip("+-")[:1] or "z"
