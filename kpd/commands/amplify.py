"""kpd amplify: variants of every mesh of a collection, drawn from the model's category prior (dataset
amplification)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from kpd.commands import folder, integer, number

HELP = ("write N prior-sampled variants of every mesh under a folder (sub-folders mirrored, formats and materials "
        "kept), with manifest.jsonl of their keypoints and a contact sheet; resumable; local processes or Ray")
EXAMPLE = ("kpd amplify chair modelnet10/chair --variants 10 --out chairs_x10 --processes 2    "
           "(the same command again continues a stopped run; on a Ray cluster: --engine ray --ray-address HOST:6379)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from kpd.commands._shared import add_model_arguments, add_scan_arguments

    add_model_arguments(parser)
    for action in parser._actions:  # the shared model options, as this command uses them
        if action.dest == "seed":
            action.help = "seed of the binding's surface sample and of the draws (default 0)"
        elif action.dest == "threads":  # one onnxruntime thread per worker: the same bytes on any machine
            action.help = argparse.SUPPRESS
    parser.add_argument("folder", metavar="FOLDER", type=folder, help="the collection: every mesh under it, in "
                                                                     "every sub-folder")
    parser.add_argument("--variants", type=integer(1, 10000), default=10, help="variants per shape (default 10)")
    parser.add_argument("--scale", type=number(0), default=0.5,
                        help="standard deviations of the prior's components (default 0.5, as kpd sample)")
    parser.add_argument("--format", default=None, metavar="EXT",
                        help="file type of the variants (.obj .ply ...); default: each source's own")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="folder of the variants, manifest.jsonl and contact_sheet.png (created, or continued "
                             "when it holds a stopped run of the same command)")
    parser.add_argument("--processes", type=integer(1, 1024), default=1,
                        help="worker processes (default 1); with --engine ray and no --ray-address: the local "
                             "cluster's workers")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help='where the work runs: local processes (default) or Ray tasks (pip install "kpd[cluster]")')
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="with --engine ray: a running cluster (HOST:PORT or ray://...); default: start a local "
                             "one. FOLDER and --out must be on a path every node sees")
    parser.add_argument("--sheet", type=integer(0, 64), default=4, metavar="ROWS",
                        help="sources in the contact sheet, each with 4 variants (default 4; 0: no sheet)")
    add_scan_arguments(parser)
    parser.add_argument("--force", action="store_true",
                        help="replace --out when it holds another run (or anything else); inputs are never replaced")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from kpd.amplify import Manifest, Settings, amplify, ray_missing_message
    from kpd.bundle import manifest_checksum
    from kpd.commands._shared import load_model
    from kpd.errors import InputError
    from kpd.io import MESH_FORMATS

    if args.ray_address is not None and args.engine != "ray":
        raise InputError("--ray-address goes with --engine ray")
    if args.engine == "ray":
        try:
            import ray  # noqa: F401  (checked before any work)
        except ImportError:
            raise InputError(ray_missing_message()) from None
    suffix = args.format
    if suffix is not None:
        suffix = (suffix if suffix.startswith(".") else "." + suffix).lower()
        if suffix not in MESH_FORMATS:
            raise InputError(f"--format must be one of {' '.join(MESH_FORMATS)}; got {args.format!r}")
    if args.threads is not None:
        raise InputError("kpd amplify runs onnxruntime on one thread per worker, so that the variants are the same "
                         "bytes on any machine; drop --threads and give --processes")
    args.threads = 1
    model = load_model(args)
    if model.prior is None:
        raise InputError(f"{args.model}: this bundle has no category prior to sample from")
    settings = Settings(model=str(args.model), model_sha256=manifest_checksum(model.bundle.manifest),
                        folder=str(Path(args.folder).resolve()), variants=args.variants, scale=args.scale,
                        seed=args.seed, scan=bool(args.scan), up=args.up, format=suffix)
    bar = None

    def start(todo: int, done: int) -> None:
        nonlocal bar
        if done:
            print(f"continuing: {done} shape(s) already done", file=sys.stderr)
        bar = tqdm(total=todo, desc="shapes", unit="shape", leave=False, dynamic_ncols=True)
        bar.set_postfix(done=0, failed=0)

    counts = {"done": 0, "failed": 0}

    def result(shape) -> None:
        if shape.error is not None:
            counts["failed"] += 1
            line = shape.error if shape.source in shape.error else f"{shape.source}: {shape.error}"
            tqdm.write(f"warning: {line}", file=sys.stderr)
        else:
            counts["done"] += 1
        bar.set_postfix(counts, refresh=False)
        bar.update()

    try:
        summary = amplify(settings, args.out, engine=args.engine, processes=args.processes,
                          ray_address=args.ray_address, force=args.force, model=model, on_start=start,
                          on_result=result)
    finally:
        if bar is not None:
            bar.close()
    out = Path(args.out)
    sheet = ""
    if args.sheet and summary.variants:
        render_collection_sheet(out, Manifest(out, args.variants), settings, args.sheet, model.up)
        sheet = ", contact_sheet.png"
    minutes, seconds = divmod(round(summary.seconds), 60)
    failed = f"; {summary.failed} failed (their errors are in manifest.jsonl)" if summary.failed else ""
    print(f"amplified {summary.done - summary.failed} of {summary.shapes} shapes into {out} ({summary.variants} "
          f"variants, manifest.jsonl{sheet}) in {minutes}m{seconds:02d}s{failed}; "
          f"{summary.typical:.1%} of variants within 3 sigma of the prior, {summary.folded_ok:.1%} with at most 0.5% "
          f"of triangles folded (worst {summary.folded_max:.2%})")
    return 2 if summary.failed else 0


def render_collection_sheet(out: Path, manifest, settings, rows: int, up: str | None) -> None:
    """``contact_sheet.png`` in ``out``: a row per source (the first ``rows`` amplified), the source then four of its
    variants, read back from their files (:func:`kpd.viewer.pictures.render_sheet`). Each row is shown in its
    source's box scaled to one size: a collection's shapes come in any units (ModelNet's chairs differ twentyfold)."""
    import numpy as np

    from kpd.amplify import SHEET, sheet_rows
    from kpd.io import file_up, read_mesh
    from kpd.viewer.pictures import render_sheet

    picked = sheet_rows(manifest, rows=rows, columns=5)
    paths, titles, keypoints, frames = [], [], [], []
    for source, files, kps in picked:
        vertices = read_mesh(Path(settings.folder) / source).vertices
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        frame = ((lo + hi) / 2, float(np.max(hi - lo)) or 1.0)  # the row's centre and size
        paths += [Path(settings.folder) / source, *(out / f for f in files)]
        titles += [source, *(f"{Path(f).stem[-3:]}" for f in files)]
        keypoints += [None, *((k - frame[0]) / frame[1] for k in kps)]
        frames += [frame] * (1 + len(files))
    meshes = _Lazy(paths, frames, read_mesh)
    render_sheet(meshes, out / SHEET, titles=titles, keypoints=keypoints, columns=1 + max(len(f) for _, f, _ in picked),
                 up=file_up(paths[0]) or up or "z", cell=2.0,
                 title=f"{len(picked)} of the sources, each with {len(picked[0][1])} of its {settings.variants} "
                       f"variants (scale {settings.scale:g})")


class _Lazy:
    """Meshes read when asked for (the sheet asks for each one at a time), each moved and scaled by its frame
    ``(centre (3,), size)`` for the picture only."""

    def __init__(self, paths, frames, read) -> None:
        self.paths, self.frames, self.read = paths, frames, read

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int):
        mesh = self.read(self.paths[i])
        centre, size = self.frames[i]
        return mesh.with_vertices((mesh.vertices - centre) / size)

    def __iter__(self):
        return (self[i] for i in range(len(self)))
