"""kpd.augment: variants drawn from cached, memory-mapped rigs: reproducible per (seed, index), equal to Rig.deform."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from kpd.augment import Augmenter
from kpd.errors import InputError
from kpd.io import read_mesh, write_mesh
from kpd.io.atomic import TEMP_MARK
from kpd.runtime import Model


@pytest.fixture(scope="module")
def model() -> Model:
    return Model.load("chair", threads=1)


@pytest.fixture(scope="module")
def shapes(tmp_path_factory) -> list[Path]:
    from kpd.procedural import procedural_chair

    root = tmp_path_factory.mktemp("shapes")
    paths = []
    for i, stretch in enumerate([(1.0, 1.0, 1.0), (1.3, 0.9, 1.1)]):
        mesh = procedural_chair()
        path = root / f"chair{i}.ply"
        write_mesh(path, mesh.with_vertices(mesh.vertices * np.asarray(stretch)))
        paths.append(path)
    broken = root / "broken.off"
    broken.write_text("OFF\n3 1 0\n0 0 0\n")
    return [paths[0], broken, paths[1]]


@pytest.fixture(scope="module")
def augmenter(model, shapes, tmp_path_factory) -> Augmenter:
    return Augmenter.build(model, shapes, tmp_path_factory.mktemp("cache") / "chairs", points=512)


def test_bound_once_unreadable_left_out_and_arrays_memory_mapped(augmenter, shapes, model):
    assert augmenter.sources == [str(shapes[0]), str(shapes[2])]
    assert [f["source"] for f in augmenter.failed] == [str(shapes[1])]
    arrays = augmenter.arrays(1)
    assert all(isinstance(a, np.memmap) and not a.flags.writeable for a in arrays.values())
    assert arrays["points"].shape == (512, 3) and arrays["basis"].shape[1] == model.num_keypoints
    index = augmenter.cache / "index.json"
    stamp = index.stat().st_mtime_ns
    again = Augmenter.build(model, shapes, augmenter.cache, points=512)  # the same collection: the cache as it is
    assert index.stat().st_mtime_ns == stamp and len(again) == 2


def test_draws_are_reproducible_per_seed_and_index(augmenter):
    a = augmenter.points(0, seed=7)
    b = augmenter.points(0, seed=7)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.keypoints, b.keypoints)
    assert not np.allclose(a.points, augmenter.points(0, seed=8).points)
    assert not np.allclose(augmenter.points(1, seed=(3, 1)).keypoints, augmenter.points(1, seed=(3, 2)).keypoints)
    reopened = Augmenter(augmenter.cache)  # another process opening the cache, say
    assert np.array_equal(reopened.mesh(1, seed=(5, 9)).points, augmenter.mesh(1, seed=(5, 9)).points)
    copy = pickle.loads(pickle.dumps(augmenter))  # as a data-loader worker receives it
    assert np.array_equal(copy.points(1, seed=4).points, augmenter.points(1, seed=4).points)


def test_draws_equal_rig_deform_of_the_sampled_keypoints(augmenter, model):
    for index in range(len(augmenter)):
        mesh = read_mesh(augmenter.sources[index])
        rig = model.rig(mesh, seed=0)
        seed = (11, index)
        variant = augmenter.mesh(index, seed=seed)
        # the keypoints are the prior's draw around the shape's own in its typical range, with the generator of
        # (seed, index) (these shapes are typical, and their first draws fold nothing)
        rng = np.random.default_rng([*seed, index])
        base = rig.normalizer.apply(rig.keypoints)
        expected = rig.normalizer.invert(model.prior.sample(1, seed=rng, scale=0.5, base=base, limit=3.0)[0])
        np.testing.assert_allclose(variant.keypoints, expected, atol=1e-9 * np.ptp(mesh.vertices))
        np.testing.assert_allclose(variant.points, rig.deform(variant.keypoints), atol=1e-9 * np.ptp(mesh.vertices))
        np.testing.assert_array_equal(augmenter.triangles(index), mesh.triangles)
        assert np.abs(variant.points - mesh.vertices).max() > 1e-3 * np.ptp(mesh.vertices)
        np.testing.assert_allclose(variant.coefficients, model.prior.coefficients(rig.normalizer.apply(
            variant.keypoints)), atol=1e-9)
        # a drawn point set lies on the drawn mesh: each point at its fixed place on its triangle
        points = augmenter.points(index, seed=seed)
        np.testing.assert_array_equal(points.keypoints, variant.keypoints)
        arrays = augmenter.arrays(index)
        corners = variant.points[np.asarray(mesh.triangles)[arrays["faces"]]]  # (N, 3, 3)
        np.testing.assert_allclose(points.points, np.einsum("nj,njd->nd", arrays["barycentric"], corners),
                                   atol=1e-9 * np.ptp(mesh.vertices))


def test_bad_calls_name_the_problem(augmenter, tmp_path):
    with pytest.raises(InputError, match=r"shape index must be an integer in \[0, 2\); got 2"):
        augmenter.points(2, seed=0)
    with pytest.raises(InputError, match="seed must be a non-negative integer"):
        augmenter.points(0, seed=-1)
    with pytest.raises(InputError, match="not an augmenter cache"):
        Augmenter(tmp_path)


def test_the_documented_data_loader_is_reproducible_across_workers(augmenter):
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader, Dataset

    class Variants(Dataset):  # the example of docs/amplify.md
        def __init__(self, augmenter: Augmenter) -> None:
            self.augmenter, self.epoch = augmenter, 0

        def __len__(self) -> int:
            return len(self.augmenter)

        def __getitem__(self, i: int):
            variant = self.augmenter.points(i, seed=self.epoch)
            return torch.from_numpy(variant.points).float(), torch.from_numpy(variant.keypoints).float()

    data = Variants(augmenter)

    def epoch(number: int, workers: int) -> list:
        data.epoch = number
        loader = DataLoader(data, batch_size=1, shuffle=False, num_workers=workers)
        return [points.numpy() for points, _ in loader]

    two = epoch(1, 2)
    assert all(np.array_equal(a, b) for a, b in zip(two, epoch(1, 0)))  # workers draw what this process draws
    assert not np.allclose(two[0], epoch(2, 2)[0])  # another epoch, other variants


def test_a_stopped_build_is_no_cache_and_the_same_build_continues_it(model, shapes, tmp_path, monkeypatch):
    calls = []

    def full_disk(path, *args, **kwargs):
        calls.append(path)
        if len(calls) > 12:  # the second shape's third array
            raise OSError(28, "No space left on device", str(path))
        return real(path, *args, **kwargs)

    real = np.save
    monkeypatch.setattr(np, "save", full_disk)
    cache = tmp_path / "cache"
    with pytest.raises(Exception, match="no space left on device"):
        Augmenter.build(model, shapes, cache, points=64)
    monkeypatch.setattr(np, "save", real)
    with pytest.raises(InputError, match="not an augmenter cache"):
        Augmenter(cache)  # no index: not a cache yet
    assert not [p for p in cache.rglob("*") if TEMP_MARK in p.name]  # nothing half-written
    bound = []
    real_rig = model.rig
    monkeypatch.setattr(model, "rig", lambda mesh, **kw: bound.append(len(mesh.vertices)) or real_rig(mesh, **kw))
    again = Augmenter.build(model, shapes, cache, points=64)
    assert len(bound) == 1  # the first shape was kept; only the second was bound
    fresh = Augmenter.build(model, shapes, tmp_path / "fresh", points=64)
    assert again.sources == fresh.sources and len(again) == 2
    for index in range(len(again)):
        for name, array in fresh.arrays(index).items():
            np.testing.assert_array_equal(again.arrays(index)[name], array)
    assert not (cache / "build.json").exists()
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="is not an augmenter cache"):
        Augmenter.build(model, shapes, tmp_path / "foreign", points=64)
    assert (tmp_path / "foreign" / "notes.txt").read_text() == "mine"


def test_two_processes_build_the_same_cache(model, shapes, augmenter, tmp_path):
    two = Augmenter.build(model, shapes, tmp_path / "two", points=augmenter.arrays(0)["points"].shape[0],
                          processes=2)
    assert two.sources == augmenter.sources and two.failed == augmenter.failed
    for index in range(len(two)):
        for name, array in augmenter.arrays(index).items():
            np.testing.assert_allclose(two.arrays(index)[name], array, atol=1e-9)


def test_scans_are_bound_in_the_model_s_frame_and_drawn_in_their_own(data_dir, tmp_path):
    """GSO shoes (long axis along z, y up): bound as scans, each draw is the scan rig's deformation in the shoe's own
    frame and units."""
    from kpd.frame import bind_shape

    shoe_model = Model.load("shoe", threads=1)
    shoes = [data_dir / "gso_shoes" / name / "model.obj" for name in ("11pro_SL_TRX_FG", "AMBERLIGHT_UP_W")]
    with pytest.raises(InputError, match="scan=True"):
        Augmenter.build(shoe_model, shoes, tmp_path / "refused", up="y")
    aug = Augmenter.build(shoe_model, shoes, tmp_path / "shoes", points=256, scan=True, up="y")
    for index, path in enumerate(shoes):
        mesh = read_mesh(path)
        rig = bind_shape(shoe_model, mesh, scan=True, up="y", seed=0)
        variant = aug.mesh(index, seed=3)
        size = np.ptp(mesh.vertices)
        np.testing.assert_allclose(variant.points, rig.deform(variant.keypoints), atol=1e-9 * size)
        assert 1e-3 * size < np.abs(variant.points - mesh.vertices).max() < 0.3 * size
        # the keypoints are the shoe's in its own frame: near its surface, not in the model's [-1, 1] box
        drawn, _ = aug.draw_keypoints(index, seed=3)
        np.testing.assert_array_equal(drawn, variant.keypoints)
        assert np.linalg.norm(drawn - rig.keypoints, axis=1).max() < 0.3 * size
        points = aug.points(index, seed=3)
        corners = variant.points[np.asarray(mesh.triangles)[aug.arrays(index)["faces"]]]
        np.testing.assert_allclose(points.points, np.einsum("nj,njd->nd", aug.arrays(index)["barycentric"], corners),
                                   atol=1e-9 * size)


@pytest.mark.parametrize("damage", [{"key": "../../outside"}, {"key": "/etc"}, {"to_shape": [[1, 0, 0]]},
                                    {"to_shape": [[float("nan")] * 4] * 3}, {"source": 3}])
def test_a_damaged_index_entry_is_refused_and_nothing_outside_the_cache_is_read(augmenter, tmp_path, damage):
    copy = tmp_path / "cache"
    shutil.copytree(augmenter.cache, copy)
    index = json.loads((copy / "index.json").read_text())
    index["shapes"][0].update(damage)
    (copy / "index.json").write_text(json.dumps(index))
    with pytest.raises(InputError, match="damaged augmenter cache"):
        Augmenter(copy)


@pytest.mark.parametrize("name, value", [("fold_triangles", lambda a: a + 10**6), ("basis", lambda a: a[:, :2]),
                                         ("faces", lambda a: -a - 1), ("vertices", lambda a: a.astype(np.int64))])
def test_damaged_arrays_are_refused_before_a_draw_reads_them(augmenter, tmp_path, name, value):
    copy = tmp_path / "cache"
    shutil.copytree(augmenter.cache, copy)
    key = json.loads((copy / "index.json").read_text())["shapes"][0]["key"]
    path = copy / key / f"{name}.npy"
    np.save(path, value(np.load(path)), allow_pickle=False)
    damaged = Augmenter(copy)
    with pytest.raises(InputError, match=rf"damaged augmenter cache entry \({name}\.npy"):
        damaged.points(0, seed=0)
    assert damaged.points(1, seed=0).points.shape[1] == 3  # the other shapes still draw
