"""How plausible ``kpd amplify``'s variants are on whole collections; prints ONE JSON object.

    .venv/bin/python benchmarks/bench_plausibility.py --out benchmarks/results/plausibility.json

Each collection is amplified with its shipped model (``--variants`` per shape, scale 0.5, seed 0, two processes):
every ModelNet10 chair (train and test) with ``chair``, every ModelNet10 table with ``table``, and the 205 Google
Scanned Objects shoes with ``shoe`` and ``--scan`` (their long axis along z, not the model's frame). Per collection:
the fraction of variants in the prior's typical range and with at most 0.5% of their triangles folded, the worst
fold, how many variants were drawn again (``attempt`` > 0) or moved less (``shrink`` < 1), and how many sources' own
keypoints lie beyond the typical range (their variants start from its edge).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data"))


def _linked(root: Path, name: str, paths: list[Path], names: list[str]) -> Path:
    """The collection as a folder of links (the data stays read-only where it is)."""
    folder = root / name
    folder.mkdir()
    for path, link in zip(paths, names):
        (folder / link).parent.mkdir(parents=True, exist_ok=True)
        (folder / link).symlink_to(path)
    return folder


def collections(root: Path) -> dict[str, tuple[str, Path, bool]]:
    """{name: (model, folder, scan)}."""
    found = {}
    for category in ("chair", "table"):
        paths = sorted((DATA / "modelnet10" / category).glob("*/*.ply"))
        found[f"modelnet10_{category}"] = (category, _linked(root, category, paths,
                                                             [p.relative_to(p.parents[1]).as_posix() for p in paths]),
                                           False)
    shoes = sorted((DATA / "gso_shoes").glob("*/model.obj"))
    found["gso_shoes"] = ("shoe", _linked(root, "shoes", shoes, [f"{p.parent.name}.obj" for p in shoes]), True)
    return found


def measure(root: Path, name: str, model_name: str, folder: Path, scan: bool, variants: int, processes: int) -> dict:
    from kpd.amplify import MANIFEST, Settings, amplify
    from kpd.bundle import manifest_checksum
    from kpd.runtime import Model
    from kpd.variants import TYPICAL_SIGMA, typical

    model = Model.load(model_name, threads=1)
    settings = Settings(model=model_name, model_sha256=manifest_checksum(model.bundle.manifest), folder=str(folder),
                        variants=variants, scale=0.5, seed=0, scan=scan)
    start = time.perf_counter()
    summary = amplify(settings, root / f"{name}_out", processes=processes, model=model)
    seconds = time.perf_counter() - start
    records = [json.loads(line) for line in (root / f"{name}_out" / MANIFEST).read_text().splitlines()]
    variants_ = [r for r in records if "error" not in r]
    # a source's own range: its variants' attempt-0 draws are centred on it, so a source beyond the range is one whose
    # variants all start from the range's edge; measured directly from the source's keypoints
    beyond = sum(1 for source in {r["source"] for r in variants_}
                 if _source_sigma(model, folder / source, scan) > TYPICAL_SIGMA)
    sigma = np.array([r["sigma"] for r in variants_])
    return {"model": model_name, "scan": scan, "shapes": summary.shapes, "failed": summary.failed,
            "failures": summary.failures[:5], "variants": summary.variants,
            "typical": summary.typical, "folded_at_most_half_percent": summary.folded_ok,
            "folded_worst": round(summary.folded_max, 5), "sigma_worst": round(float(sigma.max()), 4),
            "all_typical": bool(typical(sigma).all()),
            "drawn_again": sum(r["attempt"] > 0 for r in variants_),
            "moved_less": sum(r["shrink"] < 1 for r in variants_),
            "sources_beyond_range": beyond, "seconds": round(seconds, 1), "processes": processes}


def _source_sigma(model, path: Path, scan: bool) -> float:
    from kpd.frame import bind_shape
    from kpd.io import read_mesh

    rig = bind_shape(model, read_mesh(path), scan=scan, path=path)
    coefficients = model.prior.coefficients(rig.normalizer.apply(rig.keypoints))
    return float(np.abs(coefficients / np.sqrt(model.prior.explained_variance_)).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", type=int, default=10)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--only", nargs="*", default=None, help="collections to measure (default: all)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    from kpd.benchmark import machine_cpu, write_json

    result = {"benchmark": "plausibility", "complete": False, "machine_cpu": machine_cpu(), "variants": args.variants,
              "scale": 0.5, "seed": 0, "collections": {}}
    with tempfile.TemporaryDirectory(prefix="kpd-bench-plausibility-") as tmp:
        root = Path(tmp)
        for name, (model, folder, scan) in collections(root).items():
            if args.only and name not in args.only:
                continue
            result["collections"][name] = measure(root, name, model, folder, scan, args.variants, args.processes)
            if args.out:
                write_json(args.out, result)
    result["complete"] = True
    print(json.dumps(result, indent=2))
    if args.out:
        write_json(args.out, result)


if __name__ == "__main__":
    main()
