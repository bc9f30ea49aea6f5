"""Procedural shapes: the chair of ``kpd demo`` and the boxes it is built from (no files needed)."""

from __future__ import annotations

import numpy as np

from kpd.mesh import Mesh

__all__ = ["procedural_chair", "box_mesh"]


def procedural_chair(edge: float = 1.0):
    """A four-legged chair with a backrest, built from finely subdivided boxes, in ModelNet's frame and units.

    z is up, the back is toward +y, the bounding box is x, y in [-10, 10] and z in [-18, 18] (like ModelNet10 chairs);
    ``edge`` is the grid spacing of the box faces (1.0: 3,060 vertices; 0.52: 10,400);
    vertex colours: wooden legs and back, a red seat.

    Returns
    -------
    kpd.mesh.Mesh
    """
    wood, cushion = (0.55, 0.36, 0.20), (0.72, 0.14, 0.12)
    boxes = [((-10, -10, -2), (10, 10, 0), cushion)]  # seat
    for x in (-10, 8):
        for y in (-10, 8):
            boxes.append(((x, y, -18), (x + 2, y + 2, -2), wood))  # legs
    boxes.append(((-10, 8, 0), (10, 10, 18), wood))  # back
    vertices, triangles, colours = [], [], []
    for lo, hi, colour in boxes:
        v, t = box_mesh(np.asarray(lo, float), np.asarray(hi, float), edge=edge)
        triangles.append(t + sum(len(a) for a in vertices))
        vertices.append(v)
        colours.append(np.tile(colour, (len(v), 1)))
    return Mesh(vertices=np.concatenate(vertices), triangles=np.concatenate(triangles),
                vertex_colors=np.concatenate(colours))


def box_mesh(lo: np.ndarray, hi: np.ndarray, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box whose six faces are grids of about ``edge``-sized squares, outward triangles.

    Parameters
    ----------
    lo, hi : (3,) float64, opposite corners
    edge : grid spacing

    Returns
    -------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, outward by the right-hand rule (each face's grid has its own vertices)
    """
    vertices, triangles = [], []
    offset = 0
    for axis in range(3):
        u, w = [(a) for a in range(3) if a != axis]
        nu = max(1, int(np.ceil((hi[u] - lo[u]) / edge)))
        nw = max(1, int(np.ceil((hi[w] - lo[w]) / edge)))
        gu, gw = np.meshgrid(np.linspace(lo[u], hi[u], nu + 1), np.linspace(lo[w], hi[w], nw + 1), indexing="ij")
        for side, value in ((-1, lo[axis]), (1, hi[axis])):
            grid = np.empty((nu + 1, nw + 1, 3))
            grid[..., axis], grid[..., u], grid[..., w] = value, gu, gw
            index = np.arange((nu + 1) * (nw + 1)).reshape(nu + 1, nw + 1) + offset
            a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
            quads = np.stack([a, b, c, d], axis=-1).reshape(-1, 4)
            # (u, w, axis) is right-handed for axis 0 and 2 with u < w, and for axis 1 reversed
            outward = side * (1 if axis != 1 else -1) > 0
            if outward:
                tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
            else:
                tris = np.concatenate([quads[:, [0, 2, 1]], quads[:, [0, 3, 2]]])
            vertices.append(grid.reshape(-1, 3))
            triangles.append(tris)
            offset += (nu + 1) * (nw + 1)
    return np.concatenate(vertices), np.concatenate(triangles)
