"""What the editor and the pictures draw besides meshes: keypoint markers (coloured spheres), line sets (cages,
wireframes) and keypoint numbers as camera-facing digits (legacy OpenGL draws no text)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from kpd.viewer.labels import _GLYPHS
from kpd.viewer.normals import camera_lights

__all__ = ["Markers", "line_set", "mesh_edges", "Digits"]


def _sphere(resolution: int = 10) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    return np.asarray(sphere.vertices).copy(), np.asarray(sphere.triangles).copy()


class Markers:
    """Coloured spheres at points: one legacy TriangleMesh, updated in place."""

    def __init__(self, colors: np.ndarray, radius: float) -> None:
        import open3d as o3d

        self.colors = np.asarray(colors, dtype=np.float64)
        self.radius = float(radius)
        self._v, self._t = _sphere()
        n, k = len(self._v), len(self.colors)
        self.geometry = o3d.geometry.TriangleMesh()
        triangles = (self._t[None] + n * np.arange(k)[:, None, None]).reshape(-1, 3)
        self.geometry.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
        self.geometry.vertex_colors = o3d.utility.Vector3dVector(np.repeat(self.colors, n, axis=0))
        self.geometry.vertex_normals = o3d.utility.Vector3dVector(np.tile(self._v, (k, 1)))
        self._lit_for: np.ndarray | None = None

    def set(self, points: np.ndarray, scales: np.ndarray | None = None, camera: Any = None) -> None:
        import open3d as o3d

        if camera is not None and (self._lit_for is None or not np.allclose(self._lit_for, camera.eye)):
            # brighter than the mesh (ambient 0.55): markers must stand out, and keep their palette colour
            lambert = np.clip(self._v @ camera_lights(camera).T, 0.0, None)
            light = np.clip(0.6 + 0.45 * lambert[:, 0] + 0.1 * lambert[:, 1], 0.0, 1.15)  # (n,)
            colors = np.clip(self.colors[:, None, :] * light[None, :, None], 0.0, 1.0).reshape(-1, 3)
            self.geometry.vertex_colors = o3d.utility.Vector3dVector(colors)
            self._lit_for = np.asarray(camera.eye, dtype=np.float64).copy()

        points = np.asarray(points, dtype=np.float64)
        scales = np.ones(len(points)) if scales is None else np.asarray(scales, dtype=np.float64)
        vertices = points[:, None, :] + (self.radius * scales)[:, None, None] * self._v[None]  # (K, n, 3)
        self.geometry.vertices = o3d.utility.Vector3dVector(vertices.reshape(-1, 3))


def line_set(points: np.ndarray, edges: np.ndarray, color: Sequence[float]) -> Any:
    import open3d as o3d

    lines = o3d.geometry.LineSet()
    lines.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    lines.lines = o3d.utility.Vector2iVector(np.asarray(edges, dtype=np.int32).reshape(-1, 2))
    lines.colors = o3d.utility.Vector3dVector(np.tile(np.asarray(color, dtype=np.float64), (len(lines.lines), 1)))
    return lines


def mesh_edges(triangles: np.ndarray, limit: int = 60000) -> np.ndarray:
    """(E, 2) unique undirected edges of triangles (T, 3), thinned to at most ``limit`` (a ghost or x-ray wireframe)."""
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    if len(edges) > limit:
        edges = edges[np.linspace(0, len(edges) - 1, limit).astype(np.int64)]
    return edges


class Digits:
    """Keypoint numbers as flat, camera-facing digit glyphs on a white card (legacy OpenGL draws no text)."""

    def __init__(self, colors: np.ndarray, height: float) -> None:
        import open3d as o3d

        self.colors = np.asarray(colors, dtype=np.float64)
        self.height = float(height)  # world height of a digit
        self.geometry = o3d.geometry.TriangleMesh()
        cells, colors_, cards = [], [], []
        for i in range(len(self.colors)):
            text = str(i)
            columns = 6 * len(text) - 1
            cards.append((i, columns))
            for j, ch in enumerate(text):
                rows, cols = np.nonzero(_GLYPHS[ch])
                for r, c in zip(rows, cols):
                    cells.append((i, 6 * j + c, 6 - r))  # (label, column, row from the bottom)
                    colors_.append(0.75 * self.colors[i])
        self._cells = np.array(cells, dtype=np.float64).reshape(-1, 3)
        self._cards = np.array(cards, dtype=np.float64).reshape(-1, 2)
        n_cells, n_cards = len(self._cells), len(self._cards)
        quads = np.arange(4 * (n_cells + n_cards)).reshape(-1, 4)
        triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        self.geometry.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
        ink = np.repeat(np.array(colors_).reshape(-1, 3), 4, axis=0)
        white = np.ones((4 * n_cards, 3))
        self.geometry.vertex_colors = o3d.utility.Vector3dVector(np.vstack([ink, white]))

    def set(self, anchors: np.ndarray, camera: Any, sizes: Any = 1.0) -> None:
        """Place label i's lower-left corner at ``anchors[i]`` (K, 3), facing ``camera``, ``sizes[i]`` times its
        height (a label drawn nearer the camera is drawn smaller, so that it looks the same)."""
        import open3d as o3d

        forward = camera.center - camera.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, camera.up)
        right /= max(np.linalg.norm(right), 1e-12)
        up = np.cross(right, forward)
        anchors = np.asarray(anchors, dtype=np.float64)
        cell = self.height / 7 * np.broadcast_to(np.asarray(sizes, dtype=np.float64), (len(anchors),))  # (K,)
        corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)  # (4, 2)
        label, col, row = self._cells.T.astype(np.int64) if len(self._cells) else (np.zeros(0, int),) * 3
        grid = np.stack([col, row], axis=1)[:, None, :] + corners[None]  # (n, 4, 2)
        step = cell[label][:, None, None]  # (n, 1, 1)
        ink = anchors[label][:, None, :] + step * (grid[..., :1] * right + grid[..., 1:] * up - 0.14 * forward)
        k, columns = self._cards[:, 0].astype(np.int64), self._cards[:, 1]
        box = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        extent = np.stack([columns + 1, np.full_like(columns, 8.0)], axis=1)[:, None, :]  # (c, 1, 2)
        low = np.array([[-1.0, -1.0]])
        card_grid = np.where(box[None] < 0, low[None], extent)  # (c, 4, 2)
        cards = anchors[k][:, None, :] + cell[k][:, None, None] * (card_grid[..., :1] * right + card_grid[..., 1:] * up)
        vertices = np.vstack([ink.reshape(-1, 3), cards.reshape(-1, 3)])
        self.geometry.vertices = o3d.utility.Vector3dVector(vertices)
        self.geometry.vertex_normals = o3d.utility.Vector3dVector(np.tile(-forward, (len(vertices), 1)))
