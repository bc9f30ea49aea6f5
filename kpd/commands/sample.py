"""kpd sample: variants of a shape drawn from the model's category prior (dataset amplification)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kpd.commands import integer, number

HELP = "write variants of a mesh deformed to keypoints sampled from the category prior, and a contact sheet"
EXAMPLE = "kpd sample chair my_chair.obj --n 16 --out chair_variants"

# Keypoint marker colours (tab20, cycled).
_TAB20 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
          "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#c7c7c7",
          "#dbdb8d", "#9edae5"]


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
    from kpd.io import MESH_FORMATS, Outputs, read_mesh, write_mesh

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
                     keypoints=[rig.keypoints, *keypoint_sets])
    print(f"wrote {len(meshes)} variants, keypoints.json and contact_sheet.png to {out}")
    return 0


# --- rendering (matplotlib, no window) ------------------------------------------------------------------------------

def render_sheet(meshes: Sequence[Any], path: str | Path, *, titles: Sequence[str] | None = None,
                 keypoints: Sequence[np.ndarray | None] | None = None, columns: int | None = None,
                 up: str = "z", cell: float = 2.6, max_triangles: int = 6000, arrows: Sequence | None = None) -> None:
    """Draw meshes side by side, shaded, from one viewpoint and on one scale, into a PNG (matplotlib Agg).

    Parameters
    ----------
    meshes : kpd.io.Mesh objects, in one frame (for instance a shape and its variants).
    path : PNG to write (directly; callers write into a staging folder or use atomic_output).
    titles : one caption per mesh.
    keypoints : (K, 3) markers per mesh (or None), drawn in fixed colours per keypoint index.
    columns : grid width; about square when None.
    up : the frames' up axis ("z" for ModelNet, "y" for ShapeNet); the view looks at the front three-quarters.
    max_triangles : meshes with more triangles are drawn with an evenly spaced subset (drawing only).
    arrows : per mesh, None or (starts (E, 3), ends (E, 3)) drawn as arrows (keypoint moves).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    count = len(meshes)
    columns = columns or int(np.ceil(np.sqrt(count)))
    rows = int(np.ceil(count / columns))
    perm = {"z": [0, 1, 2], "y": [2, 0, 1], "x": [1, 2, 0]}[up]
    all_vertices = np.concatenate([np.asarray(m.vertices)[:, perm] for m in meshes])
    lo, hi = all_vertices.min(axis=0), all_vertices.max(axis=0)
    centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1e-3 * (hi - lo).max()) * 1.02
    light = np.array([-0.35, -0.6, 0.75])
    light /= np.linalg.norm(light)
    fig = plt.figure(figsize=(cell * columns, cell * rows), dpi=100)
    for i, mesh in enumerate(meshes):
        ax = fig.add_subplot(rows, columns, i + 1, projection="3d")
        ax.computed_zorder = False  # draw in the order added: the mesh, then markers and arrows on top
        vertices = np.asarray(mesh.vertices)[:, perm]
        triangles = np.asarray(mesh.triangles)
        if len(triangles) > max_triangles:
            triangles = triangles[np.linspace(0, len(triangles) - 1, max_triangles).astype(int)]
        corners = vertices[triangles]  # (T, 3, 3)
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        shade = 0.35 + 0.65 * np.abs(normals @ light)  # two-sided lighting
        if getattr(mesh, "vertex_colors", None) is not None:
            base = np.asarray(mesh.vertex_colors)[triangles].mean(axis=1)
        else:
            base = np.tile([0.62, 0.70, 0.82], (len(triangles), 1))
        colours = np.clip(base * shade[:, None], 0, 1)
        ax.add_collection3d(Poly3DCollection(corners, facecolors=colours, edgecolors="none", linewidths=0))
        if keypoints is not None and keypoints[i] is not None:
            kp = np.asarray(keypoints[i])[:, perm]
            ax.scatter(kp[:, 0], kp[:, 1], kp[:, 2], c=[_TAB20[j % 20] for j in range(len(kp))], s=14,
                       depthshade=False, edgecolors="black", linewidths=0.4, zorder=10)
        if arrows is not None and arrows[i] is not None:
            starts, ends = (np.asarray(a)[:, perm] for a in arrows[i])
            d = ends - starts
            ax.quiver(starts[:, 0], starts[:, 1], starts[:, 2], d[:, 0], d[:, 1], d[:, 2], color="black",
                      linewidths=1.2, arrow_length_ratio=0.25)
        ax.set_xlim(centre[0] - half[0], centre[0] + half[0])
        ax.set_ylim(centre[1] - half[1], centre[1] + half[1])
        ax.set_zlim(centre[2] - half[2], centre[2] + half[2])
        ax.set_box_aspect(tuple(half / half.max()), zoom=1.0)
        ax.view_init(elev=18, azim=-60)
        ax.set_axis_off()
        if titles is not None:
            ax.set_title(titles[i], fontsize=9, pad=0)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.95, wspace=0, hspace=0.05)
    from kpd.io import verify_png

    try:
        fig.savefig(path, format="png", facecolor="white")
    finally:
        plt.close(fig)
    verify_png(path)
