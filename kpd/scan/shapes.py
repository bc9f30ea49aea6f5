"""The shapes scan preprocessing accepts: (N, 3) arrays, :class:`kpd.mesh.PointSet` and :class:`kpd.mesh.Mesh`,
duck-typed so this package depends only on their fields."""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from kpd.geometry import as_points


__all__ = []

log = logging.getLogger("kpd.scan")


def _is_mesh(shape: Any) -> bool:
    return hasattr(shape, "triangles") and hasattr(shape, "vertices")


def _is_pointset(shape: Any) -> bool:
    return hasattr(shape, "points") and not _is_mesh(shape)


def _shape_points(shape: Any, name: str = "scan") -> np.ndarray:
    if _is_mesh(shape):
        return as_points(shape.vertices, f"{name} vertices")
    if _is_pointset(shape):
        return as_points(shape.points, f"{name} points")
    return as_points(shape, name)


def _take_points(shape: Any, keep: np.ndarray) -> Any:
    """A point shape (array or PointSet) restricted to the boolean mask ``keep`` (N,)."""
    if isinstance(shape, np.ndarray):
        return shape[keep]
    changes = {"points": np.asarray(shape.points)[keep]}
    for field in ("normals", "colors"):
        value = getattr(shape, field, None)
        if value is not None:
            changes[field] = np.asarray(value)[keep]
    return dataclasses.replace(shape, **changes)


def _take_triangles(mesh: Any, keep: np.ndarray) -> Any:
    """A mesh restricted to the triangles in the boolean mask ``keep`` (T,), without unreferenced vertices."""
    triangles = np.asarray(mesh.triangles, dtype=np.int64)[keep]  # (T', 3)
    used = np.zeros(len(mesh.vertices), dtype=bool)
    used[triangles.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    changes: dict[str, Any] = {"vertices": np.asarray(mesh.vertices)[used], "triangles": remap[triangles]}
    for field in ("vertex_normals", "vertex_colors"):
        value = getattr(mesh, field, None)
        if value is not None:
            changes[field] = np.asarray(value)[used]
    uvs = getattr(mesh, "triangle_uvs", None)
    if uvs is not None and len(uvs) == 3 * len(keep):
        changes["triangle_uvs"] = np.asarray(uvs).reshape(-1, 3, 2)[keep].reshape(-1, 2)
    for field in ("triangle_material_ids", "triangle_uv_mask"):
        value = getattr(mesh, field, None)
        if value is not None and len(value) == len(keep):
            changes[field] = np.asarray(value)[keep]
    return dataclasses.replace(mesh, **changes)


def _with_points(shape: Any, points: np.ndarray, linear: np.ndarray) -> Any:
    """``shape`` with its points replaced (topology, colours, UVs kept); normals turned by ``linear`` (3, 3)."""
    if isinstance(shape, np.ndarray):
        return points
    if hasattr(shape, "with_vertices"):
        return shape.with_vertices(points)  # kpd.io.Mesh: same topology, UVs, colours; normals recomputed
    if _is_mesh(shape):
        changes: dict[str, Any] = {"vertices": points}
        field = "vertex_normals"
    else:
        changes = {"points": points}
        field = "normals"
    normals = getattr(shape, field, None)
    if normals is not None and len(normals):
        # normals transform by the inverse transpose: n' = L^-T n, as rows n @ L^-1
        turned = np.asarray(normals, dtype=np.float64) @ np.linalg.inv(linear)
        length = np.linalg.norm(turned, axis=1, keepdims=True)
        changes[field] = np.divide(turned, length, out=np.zeros_like(turned), where=length > 0)
    return dataclasses.replace(shape, **changes)


def _shape_points_raw(shape: Any) -> np.ndarray:
    if _is_mesh(shape):
        return np.asarray(shape.vertices)
    if _is_pointset(shape):
        return np.asarray(shape.points)
    return np.asarray(shape)
