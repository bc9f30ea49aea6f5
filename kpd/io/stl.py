"""STL: vertices welded back by position (STL stores no shared vertices)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from kpd.grouping import first_occurrence_groups
from kpd.io.capture import open3d_module

if TYPE_CHECKING:  # pragma: no cover
    import open3d

__all__ = ["weld"]


def weld(m: "open3d.geometry.TriangleMesh") -> "open3d.geometry.TriangleMesh":
    """STL has no shared vertices (Assimp keeps one per distinct facet normal): merge equal positions, drop the
    facet normals."""
    o3d = open3d_module()
    vertices = np.asarray(m.vertices)
    first, group = first_occurrence_groups(vertices)
    out = o3d.geometry.TriangleMesh()
    out.vertices = o3d.utility.Vector3dVector(vertices[first])
    out.triangles = o3d.utility.Vector3iVector(group[np.asarray(m.triangles)].astype(np.int32))
    return out
