"""kpd.benchmark: the JSON writer goes through the atomic writer; the timers time what they are given."""

import json
import time

import pytest

from kpd.benchmark import best_seconds, median_ms, write_json
from kpd.errors import KpdError


def test_write_json_makes_the_folder_and_replaces(tmp_path):
    path = tmp_path / "results" / "x.json"
    write_json(path, {"a": 1})
    write_json(path, {"a": 2, "b": [1.5]})
    assert json.loads(path.read_text()) == {"a": 2, "b": [1.5]}
    assert [p.name for p in path.parent.iterdir()] == ["x.json"]


def test_write_json_refuses_a_folder_in_one_error_and_leaves_it_as_it_was(tmp_path):
    folder = tmp_path / "x.json"
    folder.mkdir()
    (folder / "inside").write_text("kept")
    with pytest.raises(KpdError, match="x.json"):
        write_json(folder, {"a": 1})
    assert [p.name for p in folder.iterdir()] == ["inside"] and sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]


class _Clock:
    """A clock that a call advances by a known amount: the timers' arithmetic is checked without real time."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_timers_measure_the_call(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(time, "perf_counter", clock)
    durations = iter([0.5, 0.5, 0.003, 0.001, 0.002, 0.004, 0.005])  # two warm-up calls, then five timed
    calls = []

    def call():
        calls.append(1)
        clock.now += next(durations)

    assert median_ms(call, repeats=5, warmup=2) == pytest.approx(3.0)  # the median of 1-5 ms; the warm-up not timed
    assert len(calls) == 7
    steps = iter([0.9, 0.004, 0.002, 0.003])  # one untimed call, then three timed
    assert best_seconds(lambda: setattr(clock, "now", clock.now + next(steps)), repeats=3,
                        clock=clock) == pytest.approx(0.002)


def test_machine_speed_times_a_sort_and_fresh_pages():
    from kpd.benchmark import machine_speed

    speed = machine_speed(repeats=1)
    assert set(speed) == {"sort_s", "fresh_memory_gb_per_s"}
    assert 0 < speed["sort_s"] < 60 and 0 < speed["fresh_memory_gb_per_s"] < 1e4


def test_machine_cpu_reads_the_first_processor(tmp_path):
    from kpd.benchmark import machine_cpu

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
                    "model name\t: AMD EPYC 9B14\nflags\t\t: fpu sse2 avx avx2 avx512f avx512bw\n\n"
                    "processor\t: 1\nmodel name\t: Other\nflags\t\t: sse2\n")
    assert machine_cpu(info) == {"model": "AMD EPYC 9B14", "family": "25", "model_number": "17",
                                 "vectors": "avx512f"}
    info.write_text("model name\t: Zen 3\nflags\t\t: fpu sse2 avx avx2 fma\n")
    assert machine_cpu(info)["vectors"] == "avx2"
    assert machine_cpu(tmp_path / "missing") == {"model": "", "family": "", "model_number": "", "vectors": "unknown"}
