"""A seeded sample of the reader fuzz (tests/fuzzing.py): every reader given mutated real files ends in a kpd error or
a result, within the time limit, under 1 GiB more memory, reading nothing outside the input's folder.

The long run is ``benchmarks/bench_fuzz.py``; a failing case ``i`` is rebuilt alone by ``fuzzing.make_case(root, SEED,
i)``.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import fuzzing

SEED = 51
PER_FORMAT = 20
# the readers of references and bundles (OBJ maps, glTF URIs, images, bundle members): their containment and
# declared sizes are being fixed beside this test; their findings are expected until that is merged
TRUST_FILES = ("kpd/io/obj.py", "kpd/io/gltf.py", "kpd/io/images.py", "kpd/bundle.py")
TRUST_REASON = ("reference containment and declared sizes in kpd/io/obj.py, gltf.py, images.py and kpd/bundle.py "
                "(issue 51, fixed beside this test): remove this mark once merged")


def _data_root() -> Path | None:
    root = Path(os.environ.get("KPD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    return root if (root / "modelnet10").is_dir() else None


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    return fuzzing.make_seeds(tmp_path_factory.mktemp("fuzz"), _data_root())


@pytest.fixture(scope="module")
def campaign(root) -> list:
    with fuzzing.Runner(root, SEED) as runner:
        return [runner.run(i) for i in range(PER_FORMAT * len(fuzzing.FORMATS))]


def _described(failures: list) -> str:
    return "\n".join(f"case {r.index} {r.format} {r.reader} {r.mutations}: {r.outcome} at {r.where or '?'}: "
                     f"{fuzzing.headline(r)}" for r in failures)


@pytest.mark.parametrize("fmt", fuzzing.FORMATS)
def test_mutated_files_end_in_a_kpd_error_or_a_result(fmt, campaign):
    results = [r for r in campaign if r.format == fmt]
    assert len(results) == PER_FORMAT
    failures = [r for r in results if r.outcome in fuzzing.FAILURES and not r.where.startswith(TRUST_FILES)]
    assert not failures, _described(failures)
    # the mutations reach the readers' checks: most cases are refused, with a kpd error
    assert sum(r.outcome == "error" for r in results) >= PER_FORMAT // 4


@pytest.mark.xfail(strict=False, reason=TRUST_REASON)
@pytest.mark.parametrize("fmt", ("obj", "gltf", "glb", "bundle_dir", "bundle_zip"))
def test_reference_and_bundle_readers_under_fuzz(fmt, campaign):
    failures = [r for r in campaign if r.format == fmt and r.outcome in fuzzing.FAILURES
                and r.where.startswith(TRUST_FILES)]
    assert not failures, _described(failures)


def test_cases_are_rebuilt_from_their_seed_and_number(root):
    a, b = fuzzing.make_case(root, SEED, 7), fuzzing.make_case(root, SEED, 7)
    assert a.mutations == b.mutations and a.files == b.files
    assert fuzzing.make_case(root, SEED + 1, 7).files != a.files or \
        fuzzing.make_case(root, SEED + 1, 7).mutations != a.mutations


def test_the_worker_reports_each_failure(root):
    with fuzzing.Runner(root, SEED, timeout=5) as runner:
        results = {kind: runner.probe(kind) for kind in ("outside", "traceback", "memory", "hang", "crash")}
    assert {kind: r.outcome for kind, r in results.items()} == {kind: kind for kind in results}
    assert results["outside"].detail == str((root / "cases" / "probe-outside" / "secret.txt").resolve())
    assert "ValueError: a probe's plain exception" in results["traceback"].detail
