"""kpd sample: variants of a shape drawn from the model's category prior (dataset amplification)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd.commands import integer, number
from kpd.commands._shared import render_sheet  # noqa: F401  (importable from here as before)

HELP = "write variants of a mesh deformed to keypoints sampled from the category prior, and a contact sheet"
EXAMPLE = "kpd sample chair my_chair.obj --n 16 --out chair_variants"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_model_arguments, add_scan_arguments

    add_model_arguments(parser)
    parser.add_argument("mesh", metavar="MESH", help="the mesh to vary")
    add_scan_arguments(parser)
    parser.add_argument("--n", type=integer(1, 1000), default=16, help="number of variants (default 16)")
    parser.add_argument("--scale", type=number(0), default=0.5,
                        help="standard deviations of the prior's components (default 0.5; 1 is as varied as the "
                             "whole category, which bends diverse categories such as tables strongly); draws stay "
                             "within 3 of them")
    parser.add_argument("--sample-seed", type=integer(0), default=0, help="seed of the prior draws (default 0)")
    parser.add_argument("--format", default=None, metavar="EXT",
                        help="file type of the variants (.obj .ply ...); default: the input's, else .ply")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder to create with the variants, "
                                                                    "keypoints.json and contact_sheet.png")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    import json
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from kpd.commands._shared import (category_azimuth, load_model, model_beside_read, rig_checked, scan_frame,
                                      shape_view)
    from kpd.errors import InputError
    from kpd.frame import ScanRig
    from kpd.io import MESH_FORMATS, Outputs, write_mesh
    from kpd.variants import TYPICAL_SIGMA

    suffix = args.format or Path(args.mesh).suffix.lower()
    suffix = suffix if suffix.startswith(".") else "." + suffix
    if suffix not in MESH_FORMATS:
        if args.format is not None:
            raise InputError(f"--format must be one of {' '.join(MESH_FORMATS)}; got {args.format!r}")
        suffix = ".ply"
    with Outputs(force=args.force, inputs=(args.mesh, args.model)) as outputs:
        out = outputs.folder(args.out, "--out")

        def load():
            model = load_model(args)
            if model.prior is None:
                raise InputError(f"{args.model}: this bundle has no category prior to sample from")
            return model

        model, mesh = model_beside_read(load, args.mesh)
        scan = None
        if args.scan:
            # the prior's variants are drawn in the model's frame and written in the scan's own (ScanRig)
            scan = scan_frame(args, model, mesh, path=args.mesh)
            rig = ScanRig(model.rig(mesh.with_vertices(scan.to_aligned(mesh.vertices)), seed=args.seed), mesh, scan)
        else:
            rig = rig_checked(model, mesh, args.seed, args.mesh)
        up, front = shape_view(model, args.mesh, scan)
        # in the prior's typical range, as kpd amplify draws (an unusual source's variants start from its edge)
        keypoint_sets = model.sample_keypoints(rig, args.n, seed=args.sample_seed, scale=args.scale,
                                               limit=TYPICAL_SIGMA)
        # each variant is deformed when it is written or drawn and let go after (an edit: milliseconds), so that the
        # command's memory does not grow with --n
        meshes = _Variants(mesh, rig, keypoint_sets)
        staging = outputs.stage(out)
        staging.mkdir()
        names = [f"variant_{i:03d}{suffix}" for i in range(len(keypoint_sets))]

        # seconds each at scale; on a terminal only (disable=None): a pipe or a log keeps a bar's redraws
        bar = tqdm(total=len(names), desc="variants written", unit="variant", leave=False, disable=None)

        def write_variants() -> None:
            for i, name in enumerate(names):
                write_mesh(staging / name, meshes[i + 1])
                bar.update()

        # the variants are written on a thread of their own while the contact sheet is drawn: a file's write waits
        # mostly on the disk (the variants of a dense mesh are gigabytes of PLY)
        with ThreadPoolExecutor(1, thread_name_prefix="kpd-write") as pool:
            writing = pool.submit(write_variants)
            try:
                render_sheet(meshes, staging / "contact_sheet.png",
                             titles=["input", *[f"{i:03d}" for i in range(len(keypoint_sets))]],
                             keypoints=[rig.keypoints, *keypoint_sets], up=up or "z", front=front,
                             azimuth=category_azimuth(model))
            finally:
                try:
                    writing.result()  # its error first (a full disk), else the sheet's
                finally:
                    bar.close()
        record = {"model": str(args.model), "mesh": str(args.mesh), "seed": args.seed, "sample_seed": args.sample_seed,
                  "scale": args.scale, "frame": "input", **({"scan": scan.report()} if scan is not None else {}),
                  "source_keypoints": rig.keypoints.tolist(),
                  "variants": [{"file": name, "keypoints": kp.tolist()} for name, kp in zip(names, keypoint_sets)]}
        (staging / "keypoints.json").write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {len(keypoint_sets)} variants, keypoints.json and contact_sheet.png to {out}")
    return 0


class _Variants(Sequence):
    """The input mesh, then its variants: item ``i`` > 0 is the rig deformed to keypoint set ``i - 1``, made each
    time it is asked for (the same vertices each time)."""

    def __init__(self, mesh: Any, rig: Any, keypoint_sets: Sequence[np.ndarray]) -> None:
        self.mesh, self.rig, self.keypoint_sets = mesh, rig, keypoint_sets

    def __len__(self) -> int:
        return 1 + len(self.keypoint_sets)

    def __getitem__(self, i: int) -> Any:
        if not isinstance(i, int):
            raise TypeError("variants are indexed by an int")
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        i %= len(self)
        return self.mesh if i == 0 else self.rig.deformed_mesh(self.keypoint_sets[i - 1])
