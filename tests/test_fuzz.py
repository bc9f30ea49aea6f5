"""A seeded sample of the reader fuzz (tests/fuzzing.py): every reader given mutated real files ends in a kpd error or
a result, within the time limit, under 1 GiB more memory, reading nothing outside the input's folder.

The long run is ``benchmarks/bench_fuzz.py``; a failing case ``i`` is rebuilt alone by ``fuzzing.make_case(root, SEED,
i)``. The sample is one test, so that ``pytest -n 2`` runs its campaign once.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import fuzzing

SEED = 51
PER_FORMAT = 20


def _data_root() -> Path | None:
    root = Path(os.environ.get("KPD_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    return root if (root / "modelnet10").is_dir() else None


def _described(failures: list) -> str:
    return "\n".join(f"case {r.index} {r.format} {r.reader} {r.mutations}: {r.outcome} at {r.where or '?'}: "
                     f"{fuzzing.headline(r)}" for r in failures)


def test_mutated_files_end_in_a_kpd_error_or_a_result(tmp_path):
    root = fuzzing.make_seeds(tmp_path, _data_root())
    a, b = fuzzing.make_case(root, SEED, 7), fuzzing.make_case(root, SEED, 7)  # a case is rebuilt from its number
    assert a.mutations == b.mutations and a.files == b.files
    with fuzzing.Runner(root, SEED) as runner:
        results = [runner.run(i) for i in range(PER_FORMAT * len(fuzzing.FORMATS))]
    for fmt in fuzzing.FORMATS:
        of_format = [r for r in results if r.format == fmt]
        assert len(of_format) == PER_FORMAT
        # the mutations reach the readers' checks: many cases are refused, with a kpd error
        assert sum(r.outcome == "error" for r in of_format) >= PER_FORMAT // 4, fmt
    failures = [r for r in results if r.outcome in fuzzing.FAILURES]
    assert not failures, _described(failures)


def test_the_worker_reports_each_failure(tmp_path):
    from kpd.io import Mesh, write_mesh

    (tmp_path / "seeds" / "ply_binary").mkdir(parents=True)  # the other formats' seeds are not needed here
    write_mesh(tmp_path / "seeds" / "ply_binary" / "mesh.ply", Mesh(vertices=np.eye(3), triangles=[[0, 1, 2]]))
    (tmp_path / "secret.txt").write_text("SECRET=fuzz\n")
    (tmp_path / "secret.png").write_bytes(b"")
    with fuzzing.Runner(tmp_path, SEED, timeout=5) as runner:
        results = {kind: runner.probe(kind) for kind in ("outside", "traceback", "memory", "hang", "crash")}
    assert {kind: r.outcome for kind, r in results.items()} == {kind: kind for kind in results}
    assert results["outside"].detail == str((tmp_path / "cases" / "probe-outside" / "secret.txt").resolve())
    assert "ValueError: a probe's plain exception" in results["traceback"].detail
