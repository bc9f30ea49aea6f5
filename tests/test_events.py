"""kpd.viewer.events: the editor's event log and the calls scripts follow it with."""

import json

import pytest

from kpd.errors import KpdError
from kpd.viewer.events import EventLog, read_events, wait_for


def test_the_log_appends_whole_lines_a_reader_sees_at_once(tmp_path):
    path = tmp_path / "events.jsonl"
    assert read_events(path) == []  # before the editor opens it
    log = EventLog(path)
    assert not path.exists()  # opened at the first event
    log.write({"event": "shown", "time": 1.0})
    assert read_events(path) == [{"event": "shown", "time": 1.0}]  # flushed: seen while the log is open
    log.write({"event": "frame", "keypoints": [[0.0, 1.0, 2.0]]})
    log.close()
    EventLog(path).write({"event": "ready"})  # another session appends
    assert [e["event"] for e in read_events(path)] == ["shown", "frame", "ready"]
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps({"event": "close"})[:-3])  # a line still being written
    assert [e["event"] for e in read_events(path)] == ["shown", "frame", "ready"]


def test_wait_for_returns_the_first_true_value_or_says_what_it_waited_for():
    calls = iter([None, [], {"event": "ready"}])
    assert wait_for(lambda: next(calls), 5, "the window", poll=0.001) == {"event": "ready"}
    with pytest.raises(KpdError, match="timed out after 0.05 s waiting for the rig"):
        wait_for(lambda: None, 0.05, "the rig", poll=0.01)
