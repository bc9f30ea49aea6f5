"""Edit-session state of the keypoint editor: where the keypoints are, and the history to undo and redo.

Pure numpy, no window: the editor (:mod:`kpd.viewer.app`) turns gestures into calls here, and the tests drive the
same calls without a display.

* :class:`EditSession` holds the rest keypoints of a rig and a linear history of keypoint states (user units).
  :meth:`EditSession.apply` pushes a state; a ``merge`` key folds a run of states from one gesture (a drag, one slider
  sweep) into a single undo step. The session writes itself to JSON (``kpd-edit/1``) and reads that back.
* :func:`propose` is the edit rule: the edited keypoints go where asked and, with a category prior, the others follow
  (:meth:`kpd.prior.KeypointPrior.sync`, in the prior's model frame, reached through the rig's normaliser).
* :func:`component_offsets` maps slider positions (in standard deviations per PCA component, the paper's Fig. 8) to
  keypoint offsets in user units.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any, Hashable, Mapping

import numpy as np

from kpd.errors import InputError

__all__ = ["EditSession", "SESSION_FORMAT", "propose", "component_offsets"]

log = logging.getLogger(__name__)

SESSION_FORMAT = "kpd-edit/1"


class EditSession:
    """Keypoint positions being edited, with undo and redo.

    Parameters
    ----------
    rest_keypoints : (K, 3) float64, the rig's rest keypoints in the user's units.
    history_limit : oldest states are dropped beyond this many undo steps.

    The history is a list of (K, 3) states; ``index`` points at the current one. Applying a state after undoing
    discards the redo branch, as editors do.
    """

    def __init__(self, rest_keypoints: Any, *, history_limit: int = 500) -> None:
        rest = np.array(rest_keypoints, dtype=np.float64)
        if rest.ndim != 2 or rest.shape[1] != 3 or len(rest) == 0:
            raise InputError(f"rest keypoints must have shape (K, 3) with K >= 1; got {rest.shape}")
        if not np.isfinite(rest).all():
            raise InputError("rest keypoints must be finite")
        if isinstance(history_limit, bool) or not isinstance(history_limit, int) or history_limit < 1:
            raise InputError(f"history_limit must be a positive integer; got {history_limit!r}")
        rest.flags.writeable = False
        self._rest = rest
        self._states: list[np.ndarray] = [rest]
        self._labels: list[str] = ["open"]
        self._merge: Hashable | None = None
        self._index = 0
        self.history_limit = history_limit

    # --- state -------------------------------------------------------------------------------------------------

    @property
    def num_keypoints(self) -> int:
        return len(self._rest)

    @property
    def rest(self) -> np.ndarray:
        """(K, 3) float64, read-only: the keypoints the rig was bound with."""
        return self._rest

    @property
    def keypoints(self) -> np.ndarray:
        """(K, 3) float64: a copy of the current keypoints."""
        return self._states[self._index].copy()

    @property
    def offsets(self) -> np.ndarray:
        """(K, 3) float64: current minus rest keypoints."""
        return self._states[self._index] - self._rest

    @property
    def moved(self) -> dict[int, np.ndarray]:
        """{index: (3,) offset} of the keypoints away from rest."""
        offsets = self.offsets
        return {int(i): offsets[i] for i in np.flatnonzero(np.any(offsets != 0.0, axis=1))}

    @property
    def can_undo(self) -> bool:
        return self._index > 0

    @property
    def can_redo(self) -> bool:
        return self._index < len(self._states) - 1

    @property
    def depth(self) -> int:
        """Undo steps available."""
        return self._index

    @property
    def last_label(self) -> str:
        """What the current state came from (``"open"``, ``"drag"``, ``"undo"`` is never a label)."""
        return self._labels[self._index]

    # --- editing -----------------------------------------------------------------------------------------------

    def check(self, keypoints: Any, name: str = "keypoints") -> np.ndarray:
        """(K, 3) float64 copy of ``keypoints``, or :class:`InputError` for a wrong shape or a non-finite value."""
        array = np.array(keypoints, dtype=np.float64)
        if array.shape != self._rest.shape:
            raise InputError(f"{name} must have shape ({self.num_keypoints}, 3); got {array.shape}")
        if not np.isfinite(array).all():
            raise InputError(f"{name} must be finite")
        return array

    def apply(self, keypoints: Any, *, label: str = "edit", merge: Hashable | None = None) -> bool:
        """Make ``keypoints`` the current state.

        Parameters
        ----------
        keypoints : (K, 3) float64, user units.
        label : a word for the step (shown by the editor).
        merge : a key; consecutive applies with the same non-None key replace each other, so a whole gesture is one
            undo step. Undo, redo, or an apply with another key ends the run.

        Returns
        -------
        changed : False when ``keypoints`` equal the current state (nothing is recorded, the merge run ends).
        """
        state = self.check(keypoints)
        current = self._states[self._index]
        if np.array_equal(state, current):
            if merge is None or merge != self._merge:
                self._merge = None
            return False
        state.flags.writeable = False
        if merge is not None and merge == self._merge and self._index > 0 and not self.can_redo:
            self._states[self._index] = state
            self._labels[self._index] = label
            if np.array_equal(state, self._states[self._index - 1]):  # the gesture came back to where it started
                del self._states[self._index], self._labels[self._index]
                self._index -= 1
                self._merge = None
            return True
        del self._states[self._index + 1:], self._labels[self._index + 1:]
        self._states.append(state)
        self._labels.append(label)
        self._index += 1
        self._merge = merge
        if len(self._states) > self.history_limit + 1:
            drop = len(self._states) - self.history_limit - 1
            del self._states[:drop], self._labels[:drop]
            self._index -= drop
        return True

    def end_gesture(self) -> None:
        """End a merge run: the next apply is a new undo step even with the same key."""
        self._merge = None

    def move(self, indices: Any, delta: Any, *, label: str = "move", merge: Hashable | None = None) -> bool:
        """Add ``delta`` (3,) to the keypoints ``indices`` (no prior); see :meth:`apply`."""
        keypoints = self.keypoints
        index = self._indices(indices)
        delta = np.asarray(delta, dtype=np.float64)
        if delta.shape != (3,) or not np.isfinite(delta).all():
            raise InputError(f"a move needs 3 finite numbers; got {np.asarray(delta).tolist()}")
        keypoints[index] += delta
        return self.apply(keypoints, label=label, merge=merge)

    def reset(self) -> bool:
        """Back to the rest keypoints, as a new (undoable) step."""
        return self.apply(self._rest, label="reset")

    def undo(self) -> bool:
        """Step back; False when there is nothing to undo."""
        self._merge = None
        if not self.can_undo:
            return False
        self._index -= 1
        return True

    def redo(self) -> bool:
        """Step forward again; False when there is nothing to redo."""
        self._merge = None
        if not self.can_redo:
            return False
        self._index += 1
        return True

    def _indices(self, indices: Any) -> np.ndarray:
        index = np.atleast_1d(np.asarray(indices))
        if index.size == 0:
            return index.astype(np.int64)
        if index.dtype.kind not in "iu" or index.ndim != 1:
            raise InputError(f"keypoint indices must be integers; got {np.asarray(indices).tolist()!r}")
        k = self.num_keypoints
        if index.min() < 0 or index.max() >= k:
            raise InputError(f"keypoint indices must lie in [0, {k}); got {index.tolist()}")
        return index.astype(np.int64)

    # --- files -------------------------------------------------------------------------------------------------

    def to_dict(self, **meta: Any) -> dict:
        """A JSON-safe dict: rest and current keypoints, the moves, and ``meta`` (source files, prior use...)."""
        moved = self.moved
        return {
            "format": SESSION_FORMAT,
            "num_keypoints": self.num_keypoints,
            "units": "input",
            "rest_keypoints": self._rest.tolist(),
            "keypoints": self._states[self._index].tolist(),
            "moves": {str(i): d.tolist() for i, d in moved.items()},
            **meta,
        }

    def save(self, path: str | os.PathLike, **meta: Any) -> Path:
        """Write the session as JSON, atomically (see :meth:`to_dict`)."""
        from kpd.io import atomic_output
        from kpd.io.integrity import HASH_KEY, json_hash

        path = Path(path)
        try:
            data = self.to_dict(**meta)
            text = json.dumps({**data, HASH_KEY: json_hash(data)}, indent=2, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{path}: session metadata is not JSON-serialisable ({exc})") from exc
        with atomic_output(path) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        return path

    def load_dict(self, data: Mapping, *, where: str = "session", tolerance: float | None = None) -> np.ndarray:
        """Apply a saved session to this one (one undoable step); returns the new keypoints.

        The saved *offsets* from rest are applied to this session's rest keypoints, so a session saved on one run of
        a model opens on another run of the same shape even if the rest keypoints differ by rounding. A rest that
        differs by more than ``tolerance`` (default: 1e-6 of the keypoints' extent) is reported in the log.
        """
        keypoints = read_session_keypoints(data, self.num_keypoints, where=where)
        rest = keypoints.rest
        extent = float(np.ptp(self._rest, axis=0).max()) or 1.0
        tolerance = 1e-6 * extent if tolerance is None else tolerance
        gap = float(np.abs(rest - self._rest).max())
        if gap > tolerance:
            log.warning("%s: its rest keypoints differ from this rig's by up to %.3g; applying its moves to this rig's "
                        "rest keypoints", where, gap)
        target = self._rest + (keypoints.current - rest)
        self.apply(target, label="load")
        self.end_gesture()
        return self.keypoints

    def load(self, path: str | os.PathLike, **kwargs: Any) -> np.ndarray:
        """:meth:`load_dict` of a JSON file written by :meth:`save`."""
        return self.load_dict(read_session_file(path), where=str(path), **kwargs)

    def __repr__(self) -> str:
        return (f"EditSession(K={self.num_keypoints}, moved={len(self.moved)}, undo={self.depth}, "
                f"redo={len(self._states) - 1 - self._index})")


class _SavedKeypoints:
    def __init__(self, rest: np.ndarray, current: np.ndarray) -> None:
        self.rest, self.current = rest, current


def read_session_file(path: str | os.PathLike) -> dict:
    """The JSON object of a session file; :class:`InputError` when missing or not JSON."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such session file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a JSON edit session ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(f"{path}: an edit session must be a JSON object; got {type(data).__name__}")
    from kpd.io.integrity import HASH_KEY, check_hash

    if HASH_KEY in data:  # kpd writes one; a session written by hand or by a script may have none
        check_hash(data, data[HASH_KEY], str(path), "edit session")
    return data


def read_session_keypoints(data: Mapping, k: int, *, where: str = "session") -> _SavedKeypoints:
    """Rest and current keypoints of a saved session, checked against K."""
    fmt = data.get("format")
    if fmt != SESSION_FORMAT:
        raise InputError(f"{where}: session format must be {SESSION_FORMAT!r}; got {fmt!r}")
    arrays = []
    for key in ("rest_keypoints", "keypoints"):
        if key not in data:
            raise InputError(f"{where}: session lacks {key!r}")
        try:
            array = np.asarray(data[key], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{where}: {key} must be a list of [x, y, z] rows ({exc})") from exc
        if array.ndim != 2 or array.shape[1] != 3:
            raise InputError(f"{where}: {key} must have shape (K, 3); got {array.shape}")
        if len(array) != k:
            raise InputError(f"{where}: the session has {len(array)} keypoints; this rig has {k}")
        if not np.isfinite(array).all():
            raise InputError(f"{where}: {key} must be finite")
        arrays.append(array)
    return _SavedKeypoints(*arrays)


# --- the edit rule -------------------------------------------------------------------------------------------------


def propose(base: Any, edits: Mapping[int, Any], *, prior: Any = None, normalizer: Any = None) -> np.ndarray:
    """Keypoints after moving ``edits`` from ``base``, the others following the prior when one is given.

    Parameters
    ----------
    base : (K, 3) float64, keypoints before the gesture, user units.
    edits : {index: (3,) new position} in user units.
    prior : :class:`kpd.prior.KeypointPrior` or None; with it, the other keypoints move as the category says.
    normalizer : :class:`kpd.geometry.Normalizer` of the rig (user units -> the prior's model frame); required with
        ``prior``.

    Returns
    -------
    keypoints : (K, 3) float64, user units; ``keypoints[i] == edits[i]`` exactly for every edited ``i``.
    """
    base = np.array(base, dtype=np.float64)
    k = len(base)
    targets = {}
    for index, position in edits.items():
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < k:
            raise InputError(f"edited keypoint index must be an integer in [0, {k}); got {index!r}")
        position = np.asarray(position, dtype=np.float64)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise InputError(f"edit of keypoint {index} must be 3 finite numbers; got {np.asarray(position).tolist()}")
        targets[int(index)] = position
    if prior is None or not targets:
        for index, position in targets.items():
            base[index] = position
        return base
    if normalizer is None:
        raise InputError("propose with a prior needs the rig's normalizer (user units -> model frame)")
    if prior.num_keypoints != k:
        raise InputError(f"the prior has {prior.num_keypoints} keypoints; the rig has {k}")
    model_edits = {i: normalizer.apply(p[None])[0] for i, p in targets.items()}
    result = normalizer.invert(prior.sync(normalizer.apply(base), model_edits))
    for index, position in targets.items():  # exact in user units (the frame round trip may round)
        result[index] = position
    return result


def component_offsets(prior: Any, normalizer: Any, sigmas: Any) -> np.ndarray:
    """(K, 3) float64 keypoint offsets in user units for slider positions ``sigmas`` (M,), in standard deviations
    of each principal component: ``Σ_m sigmas[m] · sqrt(λ_m) · components_[m]`` mapped out of the model frame."""
    m = len(prior.components_)
    z = np.asarray(sigmas, dtype=np.float64)
    if z.shape != (m,) or not np.isfinite(z).all():
        raise InputError(f"slider values must be {m} finite numbers; got shape {z.shape}")
    model = np.tensordot(z * np.sqrt(prior.explained_variance_), prior.components_, axes=1)  # (K, 3)
    return normalizer.invert_vectors(model)
