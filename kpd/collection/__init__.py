"""Bring a collection of scans of one category into one shared frame, without a hand-picked reference.

Groupwise alignment (:func:`align_collection`), reusing the orientation search of :class:`kpd.scan.ScanAligner`:

1. the first template is the collection's **medoid** by a rotation-invariant descriptor (:func:`shape_descriptor`:
   the distribution of point-pair distances and the principal extents of each shape at unit RMS radius), so no
   rotation search is needed to choose it, and the collection frame is that shape's own frame;
2. every shape is oriented to the template (the full rotation search, or the turns about ``up`` when it is known),
   with its score, runner-up and ambiguity flag;
3. a flagged shape is settled by its decided look-alikes when they clearly prefer one of its candidate rotations
   (:func:`_neighbour_vote`: a ballet flat is judged by other flats, not by the template sneaker);
4. the template is **re-estimated** as the medoid, by chamfer distance in the shared frame, of the shapes just
   aligned and not flagged, and step 2 is repeated, until the template no longer changes or no shape turns by
   more than 10 degrees between rounds (or ``rounds``);
5. without a known up axis, the collection is **stood on its floor** (:func:`floor_up`, :func:`stand_collection`):
   objects are scanned standing, so the shared frame's up axis is the direction in which the decided shapes rest on
   a flat contact (a sole, the tips of four legs) and each decided shape is turned by the small tilt that stands it
   on its own support plane (:func:`kpd.scan.support_plane`). A template fit tilts shapes of other proportions (a
   ballet flat fitted to a sneaker); the floor under each shape does not. Nothing is stood when no direction is a
   clear floor for the collection.

A shape flagged ambiguous (two rotations more than ``distinct_angle`` apart fit within the ambiguity margin) is
reported as such, never silently counted as aligned. Every result is kept in a JSON state file after each shape,
so a killed run continues where it stopped (``state``). Everything is numpy, scipy and Open3D; no torch.

The package's modules, one topic each: kpd.collection.results, files, templates, floor and align; every name is
importable from kpd.collection itself.
"""

from __future__ import annotations

from kpd.collection.results import CollectionShape, CollectionAlignment  # noqa: F401
from kpd.collection.files import find_shapes, collection_points  # noqa: F401
from kpd.collection.templates import rms_unit, shape_descriptor, descriptor_medoid, chamfer_medoid  # noqa: F401
from kpd.collection.floor import (FLOOR_APART, FLOOR_CLEAR, FLOOR_DIRECTIONS, FLOOR_NEAR, floor_up,  # noqa: F401
                                  stand_collection)
from kpd.collection.align import STATE_VERSION, align_collection, pairwise_rotation_errors  # noqa: F401

__all__ = [
    "CollectionShape", "CollectionAlignment", "find_shapes", "collection_points", "shape_descriptor",
    "descriptor_medoid", "chamfer_medoid", "floor_up", "stand_collection", "align_collection",
    "pairwise_rotation_errors", "rms_unit",
]


def __getattr__(attr: str):
    if attr == "contact_sheet":  # drawing is the viewer's: the core never imports it
        raise AttributeError(f"{__name__}.contact_sheet moved to kpd.viewer.figures.contact_sheet")
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
