"""kpd.variants and the prior's bounded draw: variants in the prior's typical range, redrawn when they fold, the same
numbers from the same seed; on ModelNet10 chairs the shipped model's unusual sources and a folding draw."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from helpers import kpd
from scipy import stats

from kpd.amplify import Settings, amplify
from kpd.augment import Augmenter
from kpd.bundle import manifest_checksum
from kpd.runtime import Model
from kpd.variants import ATTEMPTS, FOLDED_LIMIT, TYPICAL_SIGMA, Folds, attempt_sequence, draw_plausible, typical


@pytest.fixture(scope="module")
def model() -> Model:
    return Model.load("chair", threads=1)


def _sd(prior) -> np.ndarray:
    return np.sqrt(prior.explained_variance_)


def _far_base(prior, sigmas) -> np.ndarray:
    """A keypoint set whose coefficients are ``sigmas`` standard deviations, plus a part outside the components."""
    outside = np.random.default_rng(1).normal(size=prior.mean_.shape) * 1e-2
    outside -= np.tensordot(prior.coefficients(prior.mean_ + outside), prior.components_, axes=1)
    return prior.synthesize(np.asarray(sigmas) * _sd(prior)) + outside


def test_a_bounded_draw_stays_in_range_and_is_the_unbounded_one_when_inside(model):
    prior = model.prior
    m = len(_sd(prior))
    far = _far_base(prior, [4.8, -6.0] + [0.5] * (m - 2))
    sets = prior.sample(400, seed=3, scale=1.0, base=far, limit=TYPICAL_SIGMA)
    sigma = np.abs(np.stack([prior.coefficients(s) for s in sets]) / _sd(prior))  # (400, M)
    assert sigma.max() <= TYPICAL_SIGMA + 1e-9 and sigma[:, 0].max() > 2.9
    # the part of the keypoints outside the components is the source's own, untouched
    edge = prior.typical_base(far, TYPICAL_SIGMA)
    np.testing.assert_allclose(prior.coefficients(edge) / _sd(prior), [3.0, -3.0] + [0.5] * (m - 2), atol=1e-12)
    residual = far - prior.synthesize(prior.coefficients(far))
    np.testing.assert_allclose(edge - prior.synthesize(prior.coefficients(edge)), residual, atol=1e-12)
    # inside the range, a draw that stays inside is the unbounded draw, number for number
    base = prior.synthesize(np.full(m, 0.2) * _sd(prior))
    bounded = prior.sample(50, seed=9, scale=0.5, base=base, limit=TYPICAL_SIGMA)
    unbounded = prior.sample(50, seed=9, scale=0.5, base=base)
    assert np.array_equal(bounded, unbounded)
    np.testing.assert_array_equal(prior.typical_base(base, TYPICAL_SIGMA), base)


def test_a_bounded_component_is_the_truncated_normal(model):
    """From the range's edge, a component's draws follow N(0, sd²) cut at the edge (Kolmogorov-Smirnov)."""
    prior = model.prior
    sd = _sd(prior)
    base = prior.synthesize(np.r_[3.0, np.zeros(len(sd) - 1)] * sd)
    sets = prior.sample(4000, seed=5, scale=1.0, base=base, limit=TYPICAL_SIGMA)
    z = (np.stack([prior.coefficients(s) for s in sets])[:, 0] - 3.0 * sd[0]) / sd[0]  # standard units, <= 0
    truncated = stats.truncnorm(-6.0, 0.0)
    assert stats.kstest(z, truncated.cdf).pvalue > 0.01
    assert stats.kstest(z, stats.norm.cdf).pvalue < 1e-6  # and not the uncut normal


def test_a_folding_draw_is_drawn_again_then_moved_less(model):
    prior = model.prior
    base = prior.mean_
    seen = []

    def folds_first(n):
        def deform(keypoints):
            seen.append(keypoints.copy())
            return None, 0.02 if len(seen) <= n else 0.0
        return deform

    draw = draw_plausible(prior, base, 0.5, 77, folds_first(3))
    assert draw.attempt == 3 and draw.shrink == 1.0 and draw.folded == 0.0
    expected = prior.sample(1, seed=np.random.default_rng(attempt_sequence(77, 3)), scale=0.5, base=base,
                            limit=TYPICAL_SIGMA)[0]
    np.testing.assert_array_equal(draw.keypoints, expected)
    assert len({k.tobytes() for k in seen}) == 4  # four different draws
    # attempt 0 is default_rng(seed) itself: the seed in a manifest redraws an accepted first draw
    first = prior.sample(1, seed=np.random.default_rng(77), scale=0.5, base=base, limit=TYPICAL_SIGMA)[0]
    np.testing.assert_array_equal(seen[0], first)

    # every draw folds, the more the farther it moves: the least folded one, moved less until flat
    draws = [prior.sample(1, seed=np.random.default_rng(attempt_sequence(5, a)), scale=0.5, base=base,
                          limit=TYPICAL_SIGMA)[0] for a in range(ATTEMPTS)]
    small = 0.3 * min(np.abs(k - base).max() for k in draws)

    def folds_unless_small(keypoints):
        offset = np.abs(keypoints - base).max()
        return None, 0.0 if offset < small else 0.01 + offset

    draw = draw_plausible(prior, base, 0.5, 5, folds_unless_small)
    least = min(range(ATTEMPTS), key=lambda a: np.abs(draws[a] - base).max())
    assert draw.attempt == least and draw.shrink == 0.25 and draw.folded == 0.0
    np.testing.assert_allclose(draw.keypoints, base + 0.25 * (draws[least] - base), atol=1e-15)
    again = draw_plausible(prior, base, 0.5, 5, folds_unless_small)
    np.testing.assert_array_equal(again.keypoints, draw.keypoints)

    # nothing but the source is flat: the source itself, brought into the range
    far = _far_base(prior, [5.0] + [0.0] * (len(_sd(prior)) - 1))
    edge = prior.typical_base(far, TYPICAL_SIGMA)
    draw = draw_plausible(prior, far, 0.5, 5, lambda k: (None, 0.0 if np.array_equal(k, edge) else 0.5))
    assert draw.shrink == 0.0 and draw.folded == 0.0 and typical(draw.sigma)
    np.testing.assert_array_equal(draw.keypoints, edge)


def test_folds_count_triangles_turned_over():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 2, 0]], dtype=np.float64)
    triangles = np.array([[0, 1, 2], [1, 3, 2], [0, 0, 4]])  # the last has no area: no side to turn
    folds = Folds(vertices, triangles)
    assert len(folds.triangles) == 2 and folds.fraction(vertices) == 0.0
    moved = vertices.copy()
    moved[3] = [-1.0, -1.0, 0.0]  # the second triangle turned over, the first kept
    assert folds.fraction(moved) == 0.5
    kept = Folds.kept(folds.triangles, folds.normals)
    assert kept.fraction(moved) == 0.5


# the shipped chair model's unusual ModelNet10 training chairs (coefficients beyond 3 sd: 4.73 in the fifth component
# for chair_0030, -4.5 in the seventh for chair_0018) and one whose first draw of variant 6 folds 2% of its triangles
# (chair_0062)
UNUSUAL = ("chair_0018.ply", "chair_0030.ply", "chair_0061.ply", "chair_0062.ply")


@pytest.fixture(scope="module")
def unusual(data_dir, tmp_path_factory):
    folder = tmp_path_factory.mktemp("unusual")
    for name in UNUSUAL:
        os.symlink(data_dir / "modelnet10" / "chair" / "train" / name, folder / name)
    return folder


def test_amplified_variants_of_unusual_chairs_are_all_plausible(model, unusual, tmp_path):
    settings = Settings(model="chair", model_sha256=manifest_checksum(model.bundle.manifest), folder=str(unusual),
                        variants=10, scale=0.5, seed=0)
    summary = amplify(settings, tmp_path / "out", model=model)
    assert summary.done == 4 and summary.failed == 0
    assert summary.typical == 1.0 and summary.folded_ok == 1.0 and summary.folded_max <= FOLDED_LIMIT
    records = [json.loads(line) for line in (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()]
    sources = {}
    for r in records:
        sources.setdefault(r["source"], []).append(r)
    # the sources beyond the range: their variants are at its edge at most, not beyond
    sd = _sd(model.prior)
    for name in ("chair_0018.ply", "chair_0030.ply"):
        rig = model.rig(read(unusual / name), seed=0)
        own = np.abs(model.prior.coefficients(rig.normalizer.apply(rig.keypoints)) / sd).max()
        assert own > 4.0 and max(r["sigma"] for r in sources[name]) <= TYPICAL_SIGMA + 1e-9
    redrawn = [r for r in records if r["attempt"] > 0]
    assert [(r["source"], r["variant"]) for r in redrawn] == [("chair_0062.ply", 6)]


def read(path):
    from kpd.io import read_mesh

    return read_mesh(path)


def test_augmenter_draws_of_unusual_chairs_are_plausible(model, unusual, tmp_path):
    aug = Augmenter.build(model, sorted(unusual.iterdir()), tmp_path / "cache", points=512)
    for index in range(len(aug)):
        mesh = read(aug.sources[index])
        folds = Folds(mesh.vertices, mesh.triangles)
        for seed in range(12):
            variant = aug.mesh(index, seed=seed)
            assert typical(np.abs(variant.coefficients / _sd(model.prior)).max())
            assert folds.fraction(variant.points) <= FOLDED_LIMIT
            points = aug.points(index, seed=seed)  # checked on the same mesh: the same draw
            np.testing.assert_array_equal(points.keypoints, variant.keypoints)


@pytest.mark.parametrize("index_type", [np.int32, np.int64])
def test_the_compiled_count_is_numpy_s(index_type, tmp_path):
    """kpd.triangles.turned_over against its slow twin, on read-only memory-mapped arrays as the augmenter has them."""
    from kpd.triangles import cross, turned_over

    rng = np.random.default_rng(4)
    vertices = rng.normal(size=(3000, 3))
    triangles = rng.integers(0, len(vertices), size=(6000, 3)).astype(index_type)
    np.save(tmp_path / "t.npy", triangles)
    np.save(tmp_path / "n.npy", cross(vertices, triangles))
    mapped_triangles, normals = np.load(tmp_path / "t.npy", mmap_mode="r"), np.load(tmp_path / "n.npy", mmap_mode="r")
    for step in (0.0, 0.05, 0.3, 3.0):
        moved = vertices + step * rng.normal(size=vertices.shape)
        expected = int((np.einsum("ij,ij->i", normals, cross(moved, triangles)) < 0).sum())
        assert turned_over(moved, mapped_triangles, normals) == expected
    assert turned_over(vertices, triangles[:0], normals[:0]) == 0


def test_kpd_sample_draws_in_the_typical_range_too(model, unusual, tmp_path):
    source = unusual / "chair_0030.ply"  # 4.73 standard deviations out in its fifth component
    assert kpd("sample", "chair", source, "--n", "6", "--scale", "1", "--out", tmp_path / "out") == 0
    record = json.loads((tmp_path / "out" / "keypoints.json").read_text())
    rig = model.rig(read(source), seed=0)
    np.testing.assert_allclose(record["source_keypoints"], rig.keypoints, atol=1e-9)
    for variant in record["variants"]:
        coefficients = model.prior.coefficients(rig.normalizer.apply(np.asarray(variant["keypoints"])))
        assert typical(np.abs(coefficients / _sd(model.prior)).max())
