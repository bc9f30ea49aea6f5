"""The editor's event log: one JSON object a line for each thing the editor does (``shown``, ``ready``, ``input``,
``frame``, ``select``, ``drag``, ``save``...), so that scripts, tests and the benchmark can follow a window without
reading its pixels; and the two calls they follow it with (:func:`read_events`, :func:`wait_for`)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from kpd.errors import KpdError

__all__ = ["EventLog", "read_events", "wait_for"]


class EventLog:
    """Appends events to a JSON-lines file, opened at the first event and flushed after each (a reader sees every
    whole line at once).

    Parameters
    ----------
    path : the file to append to.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._file: Any = None

    def write(self, record: dict) -> None:
        """Append ``record`` (a JSON object) as one line."""
        if self._file is None:
            self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def read_events(path: str | os.PathLike) -> list[dict]:
    """The events an editor started with ``events=path`` has written so far (whole lines only; [] before it opens)."""
    path = Path(path)
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.endswith("}")]


def wait_for(condition: Any, timeout: float, what: str, *, poll: float = 0.02) -> Any:
    """Call ``condition()`` until it returns something true and return that; :class:`KpdError` after ``timeout`` s
    (scripts driving an editor wait for its events with it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(poll)
    raise KpdError(f"timed out after {timeout:g} s waiting for {what}")
