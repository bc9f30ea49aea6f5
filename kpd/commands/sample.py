"""kpd sample: variants of a shape drawn from the model's category prior (dataset amplification)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kpd.commands import integer, number

HELP = "write variants of a mesh deformed to keypoints sampled from the category prior, and a contact sheet"
EXAMPLE = "kpd sample chair my_chair.obj --n 16 --out chair_variants"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands.keypoints import add_model_arguments

    add_model_arguments(parser)
    parser.add_argument("mesh", metavar="MESH", help="the mesh to vary")
    parser.add_argument("--n", type=integer(1, 1000), default=16, help="number of variants (default 16)")
    parser.add_argument("--scale", type=number(0), default=0.5,
                        help="standard deviations of the prior's components (default 0.5; 1 is as varied as the "
                             "whole category, which bends diverse categories such as tables strongly)")
    parser.add_argument("--sample-seed", type=integer(0), default=0, help="seed of the prior draws (default 0)")
    parser.add_argument("--format", default=None, metavar="EXT",
                        help="file type of the variants (.obj .ply ...); default: the input's, else .ply")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder to create with the variants, "
                                                                    "keypoints.json and contact_sheet.png")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")


def run(args: argparse.Namespace) -> int:
    import json

    from kpd.commands.keypoints import load_model
    from kpd.errors import InputError
    from kpd.io import MESH_FORMATS, Outputs, file_up, read_mesh, write_mesh

    suffix = args.format or Path(args.mesh).suffix.lower()
    suffix = suffix if suffix.startswith(".") else "." + suffix
    if suffix not in MESH_FORMATS:
        if args.format is not None:
            raise InputError(f"--format must be one of {' '.join(MESH_FORMATS)}; got {args.format!r}")
        suffix = ".ply"
    with Outputs(force=args.force, inputs=(args.mesh, args.model)) as outputs:
        out = outputs.folder(args.out, "--out")
        model = load_model(args)
        if model.prior is None:
            raise InputError(f"{args.model}: this bundle has no category prior to sample from")
        mesh = read_mesh(args.mesh)
        rig = model.rig(mesh, seed=args.seed)
        keypoint_sets = model.sample_keypoints(rig, args.n, seed=args.sample_seed, scale=args.scale)
        meshes = [rig.deformed_mesh(keypoints) for keypoints in keypoint_sets]
        staging = outputs.stage(out)
        staging.mkdir()
        names = []
        for i, variant in enumerate(meshes):
            name = f"variant_{i:03d}{suffix}"
            write_mesh(staging / name, variant)
            names.append(name)
        record = {"model": str(args.model), "mesh": str(args.mesh), "seed": args.seed, "sample_seed": args.sample_seed,
                  "scale": args.scale, "frame": "input", "source_keypoints": rig.keypoints.tolist(),
                  "variants": [{"file": name, "keypoints": kp.tolist()} for name, kp in zip(names, keypoint_sets)]}
        (staging / "keypoints.json").write_text(json.dumps(record, indent=1) + "\n")
        render_sheet([mesh, *meshes], staging / "contact_sheet.png",
                     titles=["input", *[f"{i:03d}" for i in range(len(meshes))]],
                     keypoints=[rig.keypoints, *keypoint_sets], up=file_up(args.mesh) or model.up or "z")
    print(f"wrote {len(meshes)} variants, keypoints.json and contact_sheet.png to {out}")
    return 0


def render_sheet(meshes: Sequence[Any], path: str | Path, **options: Any) -> None:
    """A contact sheet of meshes (see :func:`kpd.viewer.pictures.render_sheet`: the editor's OpenGL drawing path)."""
    from kpd.viewer.pictures import render_sheet as draw

    draw(meshes, path, **options)
