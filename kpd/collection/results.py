"""What a collection's alignment returns: one result per shape and the collection's (rotations, templates, rounds, the
floor)."""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple

import numpy as np

__all__ = ["CollectionShape", "CollectionAlignment"]

log = logging.getLogger("kpd.collection")


class CollectionShape(NamedTuple):
    """One shape's result in :class:`CollectionAlignment`.

    - name : the shape's name ; rotation : (3, 3) float64, turns the shape into the shared frame (``x @ rotation.T``)
    - score : trimmed RMS distance to the template after refinement (template's [-1, 1] units)
    - runner_up_score / runner_up_angle : the best rotation more than ``distinct_angle`` degrees away, and its angle
    - margin : ``runner_up_score / score - 1`` ; ambiguous : margin under the threshold (not decided)
    - template : True for the shape that served as the final template (its rotation is the reference's)
    - decided_by : ``"template"`` (its fit to the template), ``"neighbours"`` (flagged there, settled by its decided
      look-alikes) or ``"undecided"``
    """

    name: str
    rotation: np.ndarray
    score: float
    runner_up_score: float
    runner_up_angle: float
    margin: float
    ambiguous: bool
    template: bool = False
    decided_by: str = "template"
    tilt: float = math.nan

    def to_dict(self) -> dict:
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        transform = np.eye(4)
        transform[:3, :3] = self.rotation
        return {"name": self.name, "transform": transform.tolist(), "score": num(self.score),
                "runner_up_score": num(self.runner_up_score), "runner_up_angle": num(self.runner_up_angle),
                "margin": num(self.margin), "ambiguous": bool(self.ambiguous), "template": bool(self.template),
                "decided_by": self.decided_by, "tilt": None if not np.isfinite(self.tilt) else float(self.tilt)}

    @classmethod
    def from_dict(cls, data: dict) -> "CollectionShape":
        def num(x: Any) -> float:
            return math.inf if x is None else float(x)

        return cls(str(data["name"]), np.asarray(data["transform"], dtype=np.float64)[:3, :3], num(data["score"]),
                   num(data["runner_up_score"]), math.nan if data["runner_up_angle"] is None
                   else float(data["runner_up_angle"]), num(data["margin"]), bool(data["ambiguous"]),
                   bool(data.get("template", False)),
                   "undecided" if data["ambiguous"] else str(data.get("decided_by", "template")),
                   math.nan if data.get("tilt") is None else float(data["tilt"]))


class CollectionAlignment(NamedTuple):
    """Result of :func:`align_collection`.

    - shapes : one :class:`CollectionShape` per input, in input order (the last round's results)
    - rotations : (S, 3, 3) float64, the same rotations stacked
    - templates : the template's name in each round (the first is the descriptor medoid)
    - changed : per round after the first, how many shapes turned by more than 10 degrees against the round before
    - converged : the re-estimated template was the one just used, or no shape turned by more than 10 degrees in the
      last round (another round would change nothing that matters)
    - seconds : (S,) float64, each shape's orientation time summed over the rounds (as measured when it was done,
      also in an earlier, resumed run)
    - floor : what :func:`floor_up` found (the up axis in the shared frame, the flat-contact share of every candidate
      direction, how many shapes were stood and by how much), or None when the up axis was given or standing off
    """

    shapes: list
    rotations: np.ndarray
    templates: list
    changed: list
    converged: bool
    seconds: np.ndarray
    floor: dict | None = None

    @property
    def ambiguous(self) -> np.ndarray:
        """(S,) bool: the flagged shapes."""
        return np.array([s.ambiguous for s in self.shapes], dtype=bool)

    def to_dict(self) -> dict:
        return {"templates": list(self.templates), "changed": list(self.changed), "converged": self.converged,
                "rounds": len(self.templates), "count": len(self.shapes),
                "seconds_per_shape": float(self.seconds.mean()),
                "ambiguous": int(self.ambiguous.sum()), "floor": self.floor,
                "shapes": [s.to_dict() for s in self.shapes]}
