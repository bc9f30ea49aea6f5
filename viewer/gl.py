"""The OpenGL drawing path, used by the editor's 3D view and by every picture kpd draws: Open3D's legacy
``Visualizer`` (GLFW + OpenGL 3.3), fast with Mesa's software rasteriser. Its parts, one module each, all importable
from here:

* :mod:`kpd.viewer.glview` -- :class:`GLView`, one window (visible for the editor, hidden for pictures) with named
  geometries updated in place, a look-at camera and ``capture`` to an (H, W, 3) uint8 image;
* :mod:`kpd.viewer.shaded` -- :class:`ShadedMesh`, a mesh ready to draw (one legacy ``TriangleMesh`` per texture);
* :mod:`kpd.viewer.normals` -- the shading normals (two-sided lighting, welded by position) and the camera's lights;
* :mod:`kpd.viewer.culling` -- the triangles that show in a pixel (:func:`visible_triangles`), all a frame of a large
  mesh uploads;
* :mod:`kpd.viewer.standins` -- the lighter meshes the editor draws in place of a large one during a gesture;
* :mod:`kpd.viewer.markers` -- keypoint markers, line sets and camera-facing digits;
* :mod:`kpd.viewer.rigdrawing` -- :class:`RigDrawing`, the geometries of one rig in a view;
* :mod:`kpd.viewer.shots` -- :func:`render_shots`, pictures of several :class:`Shot` with one hidden window;
* :mod:`kpd.viewer.threads` -- the worker threads the compiled passes share.
"""

from __future__ import annotations

from kpd.viewer.culling import DEPTH_SLACK, PIXEL_CENTRE, CullingLayout, Viewport, edge_neighbours, visible_triangles
from kpd.viewer.glview import GLView, NoWindowError
from kpd.viewer.markers import Digits, Markers, line_set, mesh_edges
from kpd.viewer.normals import ShadingNormals, Welding, camera_lights, shade, shading_normals
from kpd.viewer.rigdrawing import RigDrawing
from kpd.viewer.shaded import CULL_TRIANGLES, ShadedMesh, distinct_triangles, material_sides
from kpd.viewer.shots import Layer, Shot, frame_points, render_shots
from kpd.viewer.standins import (COARSE_STAND_IN_TRIANGLES, FINE_STAND_IN_CELLS, STAND_IN_TRIANGLES, coarse_stand_in,
                                 fine_stand_in, image_maps, stand_in, stand_in_colors)

# private names that code outside the modules reads from here
from kpd.viewer.culling import _BLOCK as _BLOCK, _block_hidden as _block_hidden, _margin as _margin  # isort: skip
from kpd.viewer.culling import _project as _project, _showing as _showing  # isort: skip
from kpd.viewer.glview import _raster_threads as _raster_threads, _runtime_dir as _runtime_dir  # isort: skip
from kpd.viewer.glview import _sample_points as _sample_points  # isort: skip
from kpd.viewer.shaded import _distinct_triangles_reference as _distinct_triangles_reference  # isort: skip
from kpd.viewer.shaded import _texture_coordinates as _texture_coordinates  # isort: skip
from kpd.viewer.shots import _shaded_layer as _shaded_layer  # isort: skip

__all__ = [
    "GLView", "NoWindowError", "ShadedMesh", "RigDrawing", "Shot", "Layer", "render_shots", "frame_points",
    "shading_normals", "ShadingNormals", "Welding", "camera_lights", "shade",
    "PIXEL_CENTRE", "DEPTH_SLACK", "Viewport", "visible_triangles", "edge_neighbours", "CullingLayout",
    "CULL_TRIANGLES", "distinct_triangles", "material_sides",
    "COARSE_STAND_IN_TRIANGLES", "STAND_IN_TRIANGLES", "FINE_STAND_IN_CELLS", "coarse_stand_in", "fine_stand_in",
    "stand_in", "stand_in_colors", "image_maps",
    "Markers", "Digits", "line_set", "mesh_edges",
    "PROXY_TRIANGLES", "proxy_triangles",
]

# other names of the coarse stand-in and of the normals' classes, for the code that imports them by those
PROXY_TRIANGLES, proxy_triangles = COARSE_STAND_IN_TRIANGLES, coarse_stand_in
_Welding, _Normals = Welding, ShadingNormals
