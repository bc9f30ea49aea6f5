"""The pictures kpd makes outside the editor -- contact sheets of meshes (``kpd sample``, ``kpd demo``), the alignment
gallery (``kpd eval alignment --gallery``) and the scan check (``kpd scan --picture``) -- drawn by the one OpenGL path
of :mod:`kpd.viewer.gl`, so shading, framing and the numbered keypoint palette are those of ``kpd render`` and the
editor. Cells are drawn at twice their size and averaged down (smooth edges without multisampling); captions are set
with Pillow.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from kpd.errors import InputError

__all__ = ["picture_display", "render_sheet", "point_panels", "alignment_sheet", "compose", "arrow_mesh"]

_SUPERSAMPLE = 2


@contextlib.contextmanager
def picture_display(width: int = 1024, height: int = 1024) -> Iterator[None]:
    """Where the hidden drawing window goes: a headless EGL context (no X server needed)."""
    from kpd.viewer.render import gl_display

    with gl_display("egl", width, height):
        yield


def _font(size: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: a fixed bitmap font
        return ImageFont.load_default()


def compose(images: Sequence[np.ndarray], *, titles: Sequence[str] | None = None, columns: int | None = None,
            title: str | None = None, caption_colors: Sequence[Any] | None = None) -> np.ndarray:
    """(H, W, 3) uint8: equal-sized cells in a grid, each with its caption above, and an optional title on top."""
    from PIL import Image, ImageDraw

    count = len(images)
    columns = columns or int(math.ceil(math.sqrt(count)))
    rows = int(math.ceil(count / columns))
    h, w = images[0].shape[:2]
    font_size = max(12, min(22, w // 22))
    caption = 0
    if titles is not None:
        lines = max(str(t).count("\n") + 1 for t in titles)
        caption = lines * (font_size + 4) + 6
    top = (font_size + 14) if title else 0
    sheet = Image.new("RGB", (columns * w, top + rows * (caption + h)), "white")
    draw = ImageDraw.Draw(sheet)
    font = _font(font_size)
    if title:
        draw.text((8, 6), title, fill=(20, 20, 20), font=_font(font_size + 2))
    for i, image in enumerate(images):
        r, c = divmod(i, columns)
        x, y = c * w, top + r * (caption + h)
        sheet.paste(Image.fromarray(np.ascontiguousarray(image)), (x, y + caption))
        if titles is not None:
            color = tuple(caption_colors[i]) if caption_colors is not None else (20, 20, 20)
            text = "\n".join(_fit(draw, line, font, w - 10) for line in str(titles[i]).split("\n"))
            draw.multiline_text((x + 6, y + 4), text, fill=color, font=font, spacing=4)
    return np.asarray(sheet)


def _fit(draw: Any, text: str, font: Any, width: float) -> str:
    """``text`` shortened in the middle (with an ellipsis) until it is at most ``width`` pixels long."""
    if draw.textlength(text, font=font) <= width:
        return text
    keep = len(text)
    while keep > 2:
        keep -= 1
        short = text[: (keep + 1) // 2] + "…" + text[len(text) - keep // 2:]
        if draw.textlength(short, font=font) <= width:
            return short
    return text[:1] + "…"


def arrow_mesh(start: Any, end: Any, radius: float) -> Any:
    """A kpd Mesh of an arrow from ``start`` to ``end`` (3,), shaft ``radius`` thick."""
    import open3d as o3d

    from kpd.io import Mesh

    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    d = end - start
    length = float(np.linalg.norm(d))
    if length <= 0:
        raise InputError("an arrow needs distinct ends")
    head = min(0.35 * length, 6 * radius)
    arrow = o3d.geometry.TriangleMesh.create_arrow(cylinder_radius=radius, cone_radius=2.2 * radius,
                                                   cylinder_height=length - head, cone_height=head, resolution=16)
    z = d / length
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    rotation = np.stack([x, np.cross(z, x), z], axis=1)  # columns: the arrow's x, y, z in the world
    vertices = np.asarray(arrow.vertices) @ rotation.T + start
    return Mesh(vertices=vertices, triangles=np.asarray(arrow.triangles).astype(np.int64))


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    h, w = image.shape[0] // factor, image.shape[1] // factor
    blocks = image[:h * factor, :w * factor].reshape(h, factor, w, factor, 3).astype(np.float32)
    return np.clip(np.rint(blocks.mean(axis=(1, 3))), 0, 255).astype(np.uint8)


def _draw_cells(shots: Iterable[Any], settings: Any, radius: float | None) -> list[np.ndarray]:
    """The shots at ``settings``' size (drawn supersampled), with the keypoint numbers set at the final size. The
    shots are taken once, in order (they may be made as they are asked for)."""
    from kpd.viewer.gl import render_shots
    from kpd.viewer.render import label_image_at

    big = settings.replace(width=settings.width * _SUPERSAMPLE, height=settings.height * _SUPERSAMPLE,
                           show_labels=False)
    labels = []  # each shot's keypoints and camera, for its numbers: not the shot, which may hold a large mesh

    def noted(shots: Iterable[Any]) -> Iterator[Any]:
        for shot in shots:
            labels.append((shot.keypoints, shot.camera))
            yield shot

    with picture_display(big.width + 64, big.height + 64):
        images = render_shots(noted(shots), big, keypoint_radius=radius)
    out = []
    for (keypoints, camera), image in zip(labels, images):
        image = _downsample(image, _SUPERSAMPLE)
        if keypoints is not None and settings.show_labels and settings.show_keypoints and radius is not None:
            image = label_image_at(image, keypoints, radius, camera)
        out.append(image)
    return out


def render_sheet(meshes: Sequence[Any], path: Any, *, titles: Sequence[str] | None = None,
                 keypoints: Sequence[Any] | None = None, columns: int | None = None, up: str = "z",
                 cell: float = 3.0, arrows: Sequence[Any] | None = None, max_triangles: int | None = None,
                 title: str | None = None, front: str | None = None, azimuth: float = 30.0) -> None:
    """Draw meshes side by side from one camera and on one scale (a contact sheet) into a PNG.

    Parameters
    ----------
    meshes : kpd.io.Mesh objects in one frame (a shape and its variants, say): a sequence whose items may be made
        as they are asked for (each is asked for three times, one at a time).
    path : the PNG to write (atomically).
    titles : one caption per mesh.
    keypoints : per mesh, (K, 3) keypoints or None: numbered markers in the keypoint palette.
    columns : grid width; about square when None.
    up : the frames' up axis ("z" for ModelNet, "y" for ShapeNet); the view looks at the front three-quarters.
    cell : cell size in hundreds of pixels.
    arrows : per mesh, None or (starts (E, 3), ends (E, 3)) drawn as dark arrows (keypoint moves).
    max_triangles : unused (kept for callers of the former matplotlib sheet; the OpenGL path draws every triangle).
    title : a line across the top.
    front, azimuth : where the camera looks from (:class:`kpd.viewer.settings.ViewSettings`'s ``front`` and
        ``azimuth``).
    """
    from kpd.viewer.camera import box, camera_pose_over
    from kpd.viewer.gl import Layer, Shot
    from kpd.viewer.render import ViewSettings, write_png

    if not len(meshes):
        raise InputError("a contact sheet needs at least one mesh")
    pixels = int(round(cell * 100))
    axis = str(up or "z").strip().lower()
    settings = ViewSettings(width=pixels, height=pixels, up=axis if axis[0] in "+-" else f"+{axis}", front=front,
                            azimuth=float(azimuth), elevation=18.0)
    # framed on everything, each mesh taken as it comes: ``meshes`` may make them as they are asked for (a shape's
    # variants, never all held at once: the variants of a dense mesh are gigabytes)
    def everything() -> Iterator[np.ndarray]:
        for mesh in meshes:  # one mesh at a time
            yield np.ascontiguousarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
        for k in keypoints if keypoints is not None else []:
            if k is not None:
                yield np.ascontiguousarray(k, dtype=np.float64).reshape(-1, 3)

    lo, hi = box(everything())
    camera = camera_pose_over(everything, settings, bounds=(lo, hi))
    diagonal = float(np.linalg.norm(hi - lo)) or 1.0
    radius = settings.keypoint_size * diagonal * 1.1

    def shots() -> Iterator[Any]:
        for i, mesh in enumerate(meshes):
            layers = [Layer(mesh)]
            if arrows is not None and arrows[i] is not None:
                for s, e in zip(*(np.asarray(a, dtype=np.float64) for a in arrows[i])):
                    if np.linalg.norm(e - s) > 1e-9 * diagonal:
                        layers.append(Layer(arrow_mesh(s, e, 0.006 * diagonal), color=(0.12, 0.12, 0.12)))
            kp = None if keypoints is None or keypoints[i] is None else np.asarray(keypoints[i], dtype=np.float64)
            yield Shot(layers=layers, keypoints=kp, camera=camera)

    images = _draw_cells(shots(), settings, radius)
    write_png(path, compose(images, titles=titles, columns=columns, title=title))


def point_panels(panels: Sequence[dict], path: Any, *, up: str = "z", cell: float = 3.0, columns: int | None = None,
                 title: str | None = None, shared_camera: bool = False) -> None:
    """Draw point sets (clouds as lit splats) with optional keypoints into a PNG grid.

    Parameters
    ----------
    panels : dicts with ``points`` (N, 3), optional ``behind`` (M, 3) drawn in light grey (a reference),
        ``keypoints`` (K, 3), ``mesh`` (a kpd Mesh drawn shaded instead of ``points``), ``title`` and ``color``
        (RGB 0-255 of the caption).
    path : the PNG to write (atomically).
    shared_camera : one camera framing every panel (shapes compare on one scale), else each panel framed alone.
    """
    from kpd.viewer.gl import Layer, Shot, frame_points
    from kpd.viewer.render import ViewSettings, camera_pose, write_png

    pixels = int(round(cell * 100))
    axis = str(up).strip().lower()
    settings = ViewSettings(width=pixels, height=pixels, up=axis if axis[0] in "+-" else f"+{axis}", azimuth=30.0,
                            elevation=20.0)
    shots, radii = [], []
    for panel in panels:
        layers = []
        if panel.get("behind") is not None:
            layers.append(Layer(np.asarray(panel["behind"], dtype=np.float64), color=(0.72, 0.72, 0.74),
                                style="points"))
        if panel.get("mesh") is not None:
            layers.append(Layer(panel["mesh"], color=panel.get("tint")))
        elif panel.get("points") is not None:
            layers.append(Layer(np.asarray(panel["points"], dtype=np.float64), color=panel.get("tint"),
                                style="splats"))
        kp = panel.get("keypoints")
        shot = Shot(layers=layers, keypoints=None if kp is None else np.asarray(kp, dtype=np.float64))
        everything = frame_points(shot)
        shot.camera = camera_pose(everything, settings)
        radii.append(settings.keypoint_size * 1.1 * float(np.linalg.norm(np.ptp(everything, axis=0)) or 1.0))
        shots.append(shot)
    if shared_camera:
        camera = camera_pose(np.vstack([frame_points(shot) for shot in shots]), settings)
        for shot in shots:
            shot.camera = camera
    radius = float(np.median(radii))
    images = _draw_cells(shots, settings, radius)
    titles = [p.get("title", "") for p in panels]
    colors = [p.get("color", (20, 20, 20)) for p in panels]
    write_png(path, compose(images, titles=titles, columns=columns, title=title, caption_colors=colors))


def alignment_sheet(model: Any, pairs: Sequence[tuple[Any, Any]], path: Any, *, titles: Sequence[str] | None = None,
                    scores: Sequence[float] | None = None, up: str | None = None, seed: int = 0,
                    cell: float = 2.8) -> None:
    """One row per (source, target) mesh pair: the source with its keypoints, the source deformed by ``model`` to the
    target's keypoints (:meth:`kpd.runtime.Model.align`), the target with its keypoints; each drawn in its own
    [-1, 1] model frame, all from one camera, into a PNG.

    Parameters
    ----------
    model : kpd.runtime.Model.
    pairs : (source, target) kpd Mesh objects.
    titles : one line per pair (its names); scores : its chamfer x1e3 (shown over the deformed source).
    up : the frame's up axis (default: the model's).
    """
    from kpd.viewer.gl import Layer, Shot
    from kpd.viewer.render import ViewSettings, camera_pose, write_png

    if not len(pairs):
        raise InputError("an alignment sheet needs at least one pair")
    axis = str(up or getattr(model, "up", None) or "z").strip().lower()
    pixels = int(round(cell * 100))
    settings = ViewSettings(width=pixels, height=pixels, up=axis if axis[0] in "+-" else f"+{axis}", azimuth=30.0,
                            elevation=18.0)
    shots, captions = [], []
    for i, (source, target) in enumerate(pairs):
        rig = model.rig(source, seed=seed)
        seen = model.predict(target, seed=seed)
        deformed = rig.deformed_mesh(rig.normalizer.invert(seen.keypoints))
        frame = rig.normalizer.apply
        shots.append(Shot(layers=[Layer(source.with_vertices(frame(source.vertices)), color=(0.55, 0.66, 0.9))],
                          keypoints=frame(rig.keypoints)))
        shots.append(Shot(layers=[Layer(deformed.with_vertices(frame(deformed.vertices)), color=(0.55, 0.82, 0.6))],
                          keypoints=seen.keypoints))
        shots.append(Shot(layers=[Layer(target.with_vertices(seen.normalizer.apply(target.vertices)),
                                        color=(0.92, 0.6, 0.55))], keypoints=seen.keypoints))
        name = titles[i] if titles is not None else f"pair {i}"
        score = f": chamfer {scores[i]:.2f}" if scores is not None else ""
        captions += [f"source {name}", f"deformed{score}", "target"]
    from kpd.viewer.gl import frame_points

    camera = camera_pose(np.vstack([frame_points(shot) for shot in shots]), settings)
    for shot in shots:
        shot.camera = camera
    radius = settings.keypoint_size * 2.0  # the [-1, 1] frame: diagonal about 2 to 3.5
    images = _draw_cells(shots, settings, radius * 1.6)
    write_png(path, compose(images, titles=captions, columns=3,
                            title="kpd eval chamfer: source (blue) deformed to the target's keypoints (green), target "
                                  "(red)"))
