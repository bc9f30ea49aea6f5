"""kpd.data: layouts, split files, validation carving, the sample cache, unreadable meshes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import box_mesh

from kpd.data import (SampleSettings, ShapeFile, discover, file_digest, ingest, load_samples, prepare,
                      read_split_file)
from kpd.errors import DataError
from kpd.io import write_mesh

TINY = SampleSettings(points=64, samples=2, weights=True)


def write_boxes(folder, names, suffix=".ply"):
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        write_mesh(folder / f"{name}{suffix}", box_mesh((1.0 + 0.1 * i, 2.0, 0.5 + 0.05 * i), (i, -i, 0.5 * i)))


# ----------------------------------------------------------------------------------------------- layouts

def test_modelnet_real_layout(data_dir):
    cat = discover(data_dir / "modelnet10", "chair", seed=0)
    assert cat.layout == "modelnet"
    counts = cat.to_dict()["counts"]
    assert counts["test"] == 99 and counts["train"] + counts["val"] == 875
    assert counts["val"] == round(0.1 * 875)
    train = {f.name for f in cat.splits["train"]}
    assert not train & {f.name for f in cat.splits["val"]}
    again = discover(data_dir / "modelnet10", "chair", seed=0)
    assert [f.name for f in again.splits["val"]] == [f.name for f in cat.splits["val"]]
    other = discover(data_dir / "modelnet10", "chair", seed=1)
    assert [f.name for f in other.splits["val"]] != [f.name for f in cat.splits["val"]]


def test_shapenet_v1_and_v2_layouts(tmp_path):
    ids = [f"m{i:03d}" for i in range(6)]
    split = ["train", "train", "train", "val", "test", "test"]
    for root, inner in ((tmp_path / "v1", "model.obj"), (tmp_path / "v2", "models/model_normalized.obj")):
        for i, model in enumerate(ids):
            path = root / "03001627" / model / inner
            path.parent.mkdir(parents=True)
            write_mesh(path, box_mesh((1 + 0.1 * i, 1, 1)))
        rows = ["id,synsetId,subSynsetId,modelId,split"] + [f"{i},03001627,1,{m},{s}" for i, (m, s) in
                                                           enumerate(zip(ids, split))]
        (root / "all.csv").write_text("\n".join(rows) + "\n")
    v1 = discover(tmp_path / "v1", "chair")
    v2 = discover(tmp_path / "v2", "03001627")
    assert (v1.layout, v2.layout) == ("shapenet-v1", "shapenet-v2")
    for cat in (v1, v2):
        assert [len(cat.splits[s]) for s in ("train", "val", "test")] == [3, 1, 2]
        assert cat.splits["test"][0].name == "m004"


@pytest.mark.parametrize("form", ["json", "txt", "dir", "csv"])
def test_flat_folder_with_split_files(tmp_path, form):
    names = [f"s{i}" for i in range(8)]
    write_boxes(tmp_path / "shapes", names, ".obj")
    assign = {n: ("test" if i < 2 else "val" if i == 2 else "train") for i, n in enumerate(names)}
    if form == "json":
        split = tmp_path / "split.json"
        split.write_text(json.dumps({s: [n for n in names if assign[n] == s] for s in ("train", "val", "test")}))
    elif form == "txt":
        split = tmp_path / "split.txt"
        split.write_text("".join(f"{n} {assign[n]}\n" for n in names))
    elif form == "csv":
        split = tmp_path / "split.csv"
        split.write_text("modelId,split\n" + "".join(f"{n},{assign[n]}\n" for n in names))
    else:
        split = tmp_path / "splits"
        split.mkdir()
        for s in ("train", "val", "test"):
            (split / f"{s}.txt").write_text("".join(f"03001627-{n}\n" for n in names if assign[n] == s))
    cat = discover(tmp_path, "shapes", split_file=split)
    assert cat.layout == "flat"
    assert {s: sorted(f.name for f in cat.splits[s]) for s in ("train", "val", "test")} == {
        s: sorted(n for n in names if assign[n] == s) for s in ("train", "val", "test")}


def test_flat_folder_without_split_carves_test_and_val(tmp_path):
    write_boxes(tmp_path, [f"s{i:02d}" for i in range(20)])
    cat = discover(tmp_path, None, seed=3)
    counts = cat.to_dict()["counts"]
    assert counts == {"train": 16, "val": 2, "test": 2}
    names = [f.name for s in ("train", "val", "test") for f in cat.splits[s]]
    assert sorted(names) == [f"s{i:02d}" for i in range(20)]


def test_split_file_errors(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("a train\nb holdout\n")
    with pytest.raises(DataError, match="holdout"):
        read_split_file(bad)
    with pytest.raises(DataError, match="does not exist"):
        read_split_file(tmp_path / "missing.json")
    with pytest.raises(DataError, match="not found"):
        discover(tmp_path, "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no mesh files"):
        discover(tmp_path, "empty")


# ----------------------------------------------------------------------------------------------- cache

def test_cache_content_reuse_and_keys(tmp_path):
    write_boxes(tmp_path / "shapes", ["a", "b"])
    files = [ShapeFile(p.stem, p) for p in sorted((tmp_path / "shapes").iterdir())]
    cache = tmp_path / "cache"
    first = ingest(files, TINY, cache, processes=1, progress=False)
    assert not first.skipped and len(first.entries) == 2
    paths = sorted((cache / "samples").glob("*.npz"))
    # one file per shape, named by the shape file's content digest and the settings' key
    assert len(paths) == 2
    assert sorted(p.name for p in paths) == sorted(f"{file_digest(f.path)}_{TINY.key()}.npz" for f in files)
    stamps = {p: p.stat().st_mtime_ns for p in paths}
    again = ingest(files, TINY, cache, processes=1, progress=False)
    assert [e[1] for e in again.entries] == [e[1] for e in first.entries]
    assert {p: p.stat().st_mtime_ns for p in paths} == stamps  # reused, not rewritten
    ingest(files, SampleSettings(points=64, samples=3), cache, processes=1, progress=False)
    assert len(list((cache / "samples").glob("*.npz"))) == 4  # other settings, other key
    with np.load(first.entries[0][1], allow_pickle=False) as z:
        assert z["points"].shape == (2, 64, 3) and z["points"].dtype == np.float32
        assert z["weights"].shape == (2, 64, 42) and z["weights"].dtype == np.float32
        assert z["cage_vertices"].shape == (2, 42, 3) and z["cage_faces"].shape == (80, 3)
        assert np.abs(z["points"]).max() <= 1.0 + 1e-6 and np.abs(z["points"]).max() > 0.99
        np.testing.assert_allclose(np.linalg.norm(z["normals"], axis=2), 1.0, atol=1e-5)
        assert not np.array_equal(z["points"][0], z["points"][1])  # independent samples
        json.loads(str(z["settings"]))
        recon = np.einsum("rnc,rcd->rnd", z["weights"].astype(np.float64), z["cage_vertices"])
        np.testing.assert_allclose(recon, z["points"], atol=1e-4)  # a box lies inside its cage


def test_cache_is_deterministic_and_follows_content(tmp_path):
    write_boxes(tmp_path / "a", ["x"])
    write_boxes(tmp_path / "b", ["x"])  # same bytes, other folder
    fa = [ShapeFile("x", tmp_path / "a" / "x.ply")]
    fb = [ShapeFile("x", tmp_path / "b" / "x.ply")]
    ea = ingest(fa, TINY, tmp_path / "c1", processes=1, progress=False).entries
    eb = ingest(fb, TINY, tmp_path / "c2", processes=1, progress=False).entries
    sa, sb = load_samples(ea, TINY), load_samples(eb, TINY)
    assert np.array_equal(sa.points, sb.points) and np.array_equal(sa.weights, sb.weights)
    assert ea[0][1].name == eb[0][1].name


def test_unreadable_meshes_are_listed_and_skipped(tmp_path, caplog):
    write_boxes(tmp_path / "shapes", ["good1", "good2", "good3"])
    (tmp_path / "shapes" / "empty.ply").write_bytes(b"")
    (tmp_path / "shapes" / "corrupt.obj").write_text("this is not a mesh\nv 1 2\nf 1 2 9\n")
    (tmp_path / "shapes" / "nofaces.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n")
    data = prepare(tmp_path, "shapes", settings=TINY, cache_dir=tmp_path / "cache", split_file=None,
                   val_fraction=0.0, splits=("train",), processes=1, progress=False)
    cat = data.category
    everything = {f.name for s in cat.splits.values() for f in s}
    assert everything == {"good1", "good2", "good3", "empty", "corrupt", "nofaces"}
    skipped = {s.path.rsplit("/", 1)[1]: s.reason for s in data.skipped}
    usable = set(data.samples["train"].names)
    assert usable | {n.split(".")[0] for n in skipped} == {f.name for f in cat.splits["train"]}
    assert not usable & {"empty", "corrupt", "nofaces"}
    assert all(reason for reason in skipped.values())
    if "empty.ply" in skipped:
        assert "empty" in skipped["empty.ply"]
    summary = data.to_dict()
    assert summary["skipped"] == [s._asdict() for s in data.skipped]


def test_too_few_usable_shapes_is_a_data_error(tmp_path):
    write_boxes(tmp_path / "shapes", ["only"])
    (tmp_path / "shapes" / "broken.ply").write_bytes(b"ply\ngarbage")
    with pytest.raises(DataError, match="usable"):
        prepare(tmp_path, "shapes", settings=TINY, cache_dir=tmp_path / "cache", val_fraction=0.0,
                splits=("train",), processes=1, progress=False, min_shapes=2)


def test_parallel_ingest_matches_serial(data_dir, tmp_path):
    src = sorted((data_dir / "modelnet10" / "table" / "test").glob("*.ply"))[:3]
    files = [ShapeFile(p.stem, p) for p in src]
    serial = load_samples(ingest(files, TINY, tmp_path / "c1", processes=1, progress=False).entries, TINY)
    parallel = load_samples(ingest(files, TINY, tmp_path / "c2", processes=2, progress=False).entries, TINY)
    assert serial.names == parallel.names
    assert np.array_equal(serial.points, parallel.points)
    np.testing.assert_allclose(serial.weights, parallel.weights, atol=1e-6)
    # the same cache files, byte for byte in their arrays, whichever way they were made
    for one, two in zip(sorted((tmp_path / "c1" / "samples").glob("*.npz")),
                        sorted((tmp_path / "c2" / "samples").glob("*.npz"))):
        assert one.name == two.name
        with np.load(one, allow_pickle=False) as a, np.load(two, allow_pickle=False) as b:
            assert np.array_equal(a["points"], b["points"]) and np.array_equal(a["normals"], b["normals"])
