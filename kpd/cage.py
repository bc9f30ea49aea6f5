"""Cages: the icosphere template, the authors' cage fit (docs/method.md §4), inside/outside tests, the influence mask.

A cage is a closed triangle mesh with outward-oriented faces around a shape in the [-1, 1] box. The authors start from
a radius-1.4 icosphere and shrink each vertex along its ray toward the origin until it is within 0.4 of the shape, so
the cage stays star-shaped about the origin: every ray from the origin crosses it exactly once. That property is what
:func:`fit_cage` (``enclose=True``) and :func:`cage_faces_from_vertices` rely on.
"""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np

from kpd._compiled import compiled_on_first_call
from kpd.errors import InputError, KpdError
from kpd.geometry import as_points

__all__ = [
    "Cage",
    "icosphere",
    "fit_cage",
    "winding_number",
    "points_outside",
    "cage_faces_from_vertices",
    "influence_mask",
    "default_m",
]

log = logging.getLogger(__name__)

# The level-0 icosahedron of pytorch3d.utils.ico_sphere, rounded to 4 decimals as there, with its face order, so that
# our subdivided template numbers its vertices as the authors' (and their W_C columns) do.
_ICO_VERTS0 = np.array(
    [
        [-0.5257, 0.8507, 0.0], [0.5257, 0.8507, 0.0], [-0.5257, -0.8507, 0.0], [0.5257, -0.8507, 0.0],
        [0.0, -0.5257, 0.8507], [0.0, 0.5257, 0.8507], [0.0, -0.5257, -0.8507], [0.0, 0.5257, -0.8507],
        [0.8507, 0.0, -0.5257], [0.8507, 0.0, 0.5257], [-0.8507, 0.0, -0.5257], [-0.8507, 0.0, 0.5257],
    ]
)
_ICO_FACES0 = np.array(
    [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6],
        [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
        [8, 6, 7], [9, 8, 1],
    ],
    dtype=np.int64,
)
_MAX_LEVEL = 7  # 163,842 vertices; more is never a cage

# enclose=True leaves every point at most this fraction of the cage's radial distance (in its direction) inside:
# a point at radius r ends with r <= (1 - margin) * R(direction).
_ENCLOSE_MARGIN = 0.02
_ENCLOSE_ROUNDS = 10
_CHUNK_PAIRS = 1 << 15  # point-face pairs per chunk in the vectorised loops


class Cage(NamedTuple):
    """A closed triangle mesh with outward-oriented faces.

    vertices : (C, 3) float64
    faces : (F, 3) int64
    """

    vertices: np.ndarray
    faces: np.ndarray


# --- template ----------------------------------------------------------------------------------------------------

def edge_table(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The undirected edges of a triangle mesh, numbered as pytorch3d's ``Meshes.edges_packed``.

    Parameters
    ----------
    faces : (F, 3) int64
    n_vertices : C, the number of vertices.

    Returns
    -------
    edges : (E, 2) int64, ``edges[e] = (a, b)`` with ``a < b``, sorted.
    face_edges : (F, 3) int64, the edge opposite each corner: ``face_edges[f, k]`` joins ``faces[f, k+1]`` and
        ``faces[f, k+2]`` (indices mod 3).
    """
    corners = np.concatenate([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]])  # (3F, 2)
    corners = np.sort(corners, axis=1)
    keys, inverse = np.unique(corners[:, 0] * n_vertices + corners[:, 1], return_inverse=True)
    edges = np.stack([keys // n_vertices, keys % n_vertices], axis=1).astype(np.int64)
    face_edges = inverse.reshape(3, len(faces)).T.astype(np.int64)
    return edges, np.ascontiguousarray(face_edges)


def icosphere(level: int = 1, radius: float = 1.4) -> Cage:
    """The authors' cage template: a subdivided icosahedron on a sphere (docs/method.md §4).

    Level 0 is the icosahedron (12 vertices, 20 faces); each level splits every face in four (level 1: 42 / 80,
    level 2: 162 / 320). Vertices and faces are numbered as ``pytorch3d.utils.ico_sphere(level)``, faces point
    outward, and every vertex lies at distance ``radius`` from the origin (for level >= 1 this is the authors'
    ``cage_size * normalize_to_box(ico_sphere(level))``).

    Parameters
    ----------
    level : number of subdivisions, 0 to 7.
    radius : sphere radius; the authors' ``cage_size`` 1.4.
    """
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 0 <= level <= _MAX_LEVEL:
        raise InputError(f"icosphere level must be an integer in [0, {_MAX_LEVEL}]; got {level!r}")
    radius = float(radius)
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"icosphere radius must be positive and finite; got {radius}")
    vertices, faces = _ICO_VERTS0.copy(), _ICO_FACES0.copy()
    for _ in range(int(level)):
        # pytorch3d SubdivideMeshes: one new vertex per edge (in edge order) and four faces per face, in four blocks.
        edges, face_edges = edge_table(faces, len(vertices))
        mid = face_edges + len(vertices)  # (F, 3) index of the midpoint opposite each corner
        vertices = np.concatenate([vertices, vertices[edges].mean(axis=1)])
        faces = np.concatenate(
            [
                np.stack([faces[:, 0], mid[:, 2], mid[:, 1]], axis=1),
                np.stack([faces[:, 1], mid[:, 0], mid[:, 2]], axis=1),
                np.stack([faces[:, 2], mid[:, 1], mid[:, 0]], axis=1),
                mid,
            ]
        )
        vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    vertices = vertices / np.linalg.norm(vertices, axis=1, keepdims=True) * radius
    return Cage(np.ascontiguousarray(vertices), np.ascontiguousarray(faces, dtype=np.int64))


# --- checks ------------------------------------------------------------------------------------------------------

def _check_faces(faces: Any, n_vertices: int, name: str = "cage faces") -> np.ndarray:
    arr = np.asarray(faces)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
        raise InputError(f"{name} must have shape (F, 3) with F >= 1; got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        if not (np.issubdtype(arr.dtype, np.floating) and np.isfinite(arr).all() and (arr == np.round(arr)).all()):
            raise InputError(f"{name} must be integer vertex indices; got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.int64)
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi >= n_vertices:
        raise InputError(f"{name} must lie in [0, {n_vertices - 1}] for {n_vertices} vertices; got [{lo}, {hi}]")
    return arr


def check_cage(vertices: Any, faces: Any) -> Cage:
    """Convert and check cage arrays: ``(C, 3)`` finite vertices, C >= 4, ``(F, 3)`` integer faces in range."""
    vertices = as_points(vertices, "cage vertices", min_count=4)
    return Cage(vertices, _check_faces(faces, len(vertices)))


# --- fitting -----------------------------------------------------------------------------------------------------

def fit_cage(
    points: Any,
    *,
    template: Cage | None = None,
    distance: float = 0.4,
    iterations: int = 100,
    step: float = 0.01,
    enclose: bool = False,
) -> Cage:
    """Shrink a template cage onto a shape, as the authors do (docs/method.md §4); optionally make it enclose the
    shape.

    At each of ``iterations`` rounds every cage vertex farther than ``distance`` from its nearest input point moves
    toward the origin by ``step`` of its position (``c <- c - step * c``); the others stay. The points are expected in
    the [-1, 1] box (:class:`kpd.geometry.Normalizer`), centred on the origin.

    The authors' rule can leave parts of the shape outside the cage (a few percent of a chair's points, and the box
    corners are outside even the template), where the cage's mean value coordinates extrapolate instead of
    interpolate. ``enclose=True`` goes beyond the authors: afterwards, each point that is outside the cage, or closer
    to it than 2 % of the cage's radial distance in its direction, raises the vertices of the face its ray from the
    origin crosses, along their rays, the lowest first to a common radius, just enough to bring the point to that
    margin. Vertices only move outward, so points already inside stay inside; one pass suffices (a second checks),
    and the result is deterministic. It needs a template star-shaped about the origin (any fitted icosphere is).

    Parameters
    ----------
    points : (N, 3) float64, the shape's points (the authors use 1024 surface samples).
    template : the starting cage, star-shaped about the origin; ``icosphere(1, 1.4)`` when ``None``.
    distance : stop distance of a vertex from the nearest point.
    iterations : maximum number of shrinking rounds.
    step : fraction of its position a vertex moves toward the origin per round.
    enclose : push vertices out until every point is inside, with the margin.

    Returns
    -------
    Cage with the template's faces and the moved vertices.
    """
    points = as_points(points)
    if template is None:
        template = icosphere(1, 1.4)
    if not isinstance(template, tuple) or len(template) != 2:
        raise InputError(f"template must be a Cage (vertices, faces); got {type(template).__name__}")
    vertices, faces = check_cage(*template)
    distance, step = float(distance), float(step)
    if not (np.isfinite(distance) and distance >= 0):
        raise InputError(f"distance must be finite and >= 0; got {distance}")
    if not 0 < step < 1:
        raise InputError(f"step must lie in (0, 1); got {step}")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 0:
        raise InputError(f"iterations must be an integer >= 0; got {iterations!r}")

    from scipy.spatial import cKDTree  # here: importing scipy.spatial takes 0.3 s, and the CLI's help needs none

    vertices = vertices.copy()
    tree = cKDTree(points) if iterations else None
    moving = np.arange(len(vertices))  # a vertex that stops stays where it is, so it is not looked at again
    for _ in range(int(iterations)):
        nearest, _ = tree.query(vertices[moving], k=1)
        moving = moving[nearest > distance]
        if not len(moving):
            break
        vertices[moving] += step * -vertices[moving]
    if enclose:
        vertices = _enclose(points, vertices, faces)
    return Cage(vertices, faces.copy())


def _star_cones(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Inverse direction matrices of a cage star-shaped about the origin: ``(F, 3, 3)``, ``inv[f] @ p`` = the
    coordinates of ``p`` in the basis of face ``f``'s unit vertex directions. Raises InputError if the cage is not
    star-shaped about the origin."""
    radii = np.linalg.norm(vertices, axis=1)
    if not (radii > 0).all():
        raise InputError(f"a cage vertex lies at the origin (vertex {int(np.argmin(radii))}); cannot enclose")
    units = vertices / radii[:, None]
    dirs = units[faces].transpose(0, 2, 1)  # (F, 3, 3) columns: the three unit directions
    det = np.einsum("fi,fi->f", dirs[:, :, 0], np.cross(dirs[:, :, 1], dirs[:, :, 2]))
    total = float(winding_number(np.zeros((1, 3)), vertices, faces)[0])
    if not ((det > 1e-12).all() and abs(total - 1.0) < 1e-6):
        raise InputError(
            "enclose needs a cage that is star-shaped about the origin with outward faces "
            f"(winding number of the origin 1, every face seen from inside); got winding number {total:.6g} and "
            f"{int((det <= 1e-12).sum())} face(s) not facing away from the origin"
        )
    return np.linalg.inv(dirs)


def _enclose(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Scale cage vertices outward along their rays until every point is inside with the margin.

    A compiled pass finds each point's cone by walking across the cage's faces and keeps only the points that are
    over the margin for the cage as it is; radii only grow, so no other point can ever need raising, and the
    rounds run on those alone (:func:`_enclose_reference` is the whole computation in numpy)."""
    inv = _star_cones(vertices, faces)
    radii = np.linalg.norm(vertices, axis=1)
    units = vertices / radii[:, None]
    limit = 1.0 - _ENCLOSE_MARGIN
    # a little below the limit, so that the rounds below decide, as numpy rounds the fractions, every point near it
    face_of = np.empty(len(points), dtype=np.int64)  # pages the kernel does not write are never touched
    coords = np.empty((len(points), 3))
    count = _near_points(points, inv, _face_neighbours(faces), faces, radii, limit * (1.0 - 1e-9), face_of, coords)
    face_of, coords = face_of[:count].copy(), coords[:count].copy()
    corner = faces[face_of]  # (n, 3)
    active = np.arange(count)  # the points still over the margin, first ones first
    count = len(active)
    for _ in range(_ENCLOSE_ROUNDS):
        lifted = np.zeros(len(radii))
        count = _lift_round(coords, corner, radii, limit, active, count, lifted)
        if not count:
            break
        log.debug("enclose: %d point(s) outside or too close; raising %d vertices", count, (lifted > radii).sum())
        radii = np.maximum(radii, lifted)
    else:
        raise KpdError(f"enclose did not converge in {_ENCLOSE_ROUNDS} rounds")
    out = vertices.copy()
    moved = radii > np.linalg.norm(vertices, axis=1)
    out[moved] = units[moved] * radii[moved, None]
    return out


def _enclose_reference(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """:func:`_enclose` in numpy over every point and face (the slow twin tests compare with)."""
    inv = _star_cones(vertices, faces)
    radii = np.linalg.norm(vertices, axis=1)
    units = vertices / radii[:, None]
    # The cone (face) of each point and its coordinates in that face's unit directions; both fixed by the directions.
    face_of = np.empty(len(points), dtype=np.int64)
    coords = np.empty((len(points), 3))
    inv_rows = np.ascontiguousarray(inv.reshape(-1, 3).T)  # (3, 3F)
    chunk = max(1, _CHUNK_PAIRS // len(faces))
    for start in range(0, len(points), chunk):
        p = points[start : start + chunk]
        lam = (p @ inv_rows).reshape(len(p), len(faces), 3)  # (n, F, 3)
        least = np.minimum(np.minimum(lam[:, :, 0], lam[:, :, 1]), lam[:, :, 2])  # (n, F)
        best = least.argmax(axis=1)  # (n,) the face whose cone holds the point most surely
        face_of[start : start + chunk] = best
        coords[start : start + chunk] = lam[np.arange(len(p)), best]
    # Rounding at cone borders: drop coordinates that are noise next to the others (the margin dwarfs them).
    coords[coords < 1e-12 * np.abs(coords).sum(axis=1, keepdims=True)] = 0.0
    radii = _raise_radii(coords, faces[face_of], radii, 1.0 - _ENCLOSE_MARGIN)
    out = vertices.copy()
    moved = radii > np.linalg.norm(vertices, axis=1)
    out[moved] = units[moved] * radii[moved, None]
    return out


def _raise_radii(coords: np.ndarray, corner: np.ndarray, radii: np.ndarray, limit: float) -> np.ndarray:
    """The cage's vertex radii after raising, round by round, the faces of the points over the margin.

    Parameters
    ----------
    coords : (N, 3) the points' coordinates in their faces' unit vertex directions (>= 0).
    corner : (N, 3) int64, the vertices of each point's face.
    radii : (C,) the vertex radii before.
    limit : the largest radial fraction allowed.

    Returns
    -------
    radii : (C,) float64, each at least as before.
    """
    for _ in range(_ENCLOSE_ROUNDS):
        # A point at coordinates lam (in unit directions) lies at the fraction s = sum(lam_i / r_i) of the cage's
        # radial distance in its direction: inside iff s < 1.
        frac = np.sum(coords / radii[corner], axis=1)  # (N,)
        over = np.flatnonzero(frac > limit)
        if not len(over):
            return radii
        level = _raise_level(coords[over], radii[corner[over]], limit)  # (n,)
        # Raise the vertices that carry each such point (coordinate > 0) to its level, if they are below it.
        carry = coords[over] > 0  # (n, 3)
        lifted = np.zeros(len(radii))
        np.maximum.at(lifted, corner[over][carry], np.broadcast_to(level[:, None], carry.shape)[carry])
        log.debug("enclose: %d point(s) outside or too close; raising %d vertices", len(over), (lifted > radii).sum())
        radii = np.maximum(radii, lifted)
    raise KpdError(f"enclose did not converge in {_ENCLOSE_ROUNDS} rounds")


def _face_neighbours(faces: np.ndarray) -> np.ndarray:
    """(F, 3) int64: the face across the edge opposite each corner (-1 where the edge has no other face)."""
    f = len(faces)
    start = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])  # (3F,) edge opposite corner k: k+1 -> k+2
    end = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    n = int(faces.max()) + 1
    key = start * n + end
    order = np.argsort(key)
    # the same edge walked the other way round by its other face
    at = np.searchsorted(key[order], end * n + start)
    found = order[np.minimum(at, 3 * f - 1)]
    neighbour = np.where(key[found] == end * n + start, found % f, -1)
    return np.ascontiguousarray(neighbour.reshape(3, f).T)


@compiled_on_first_call
def _near_points(points, inv, neighbours, faces, radii, threshold, face_of, coords):  # pragma: no cover - compiled
    """The points whose radial fraction for the cage as it is exceeds ``threshold``: their cones written to
    ``face_of`` and their coordinates in that cone's unit directions to ``coords``, in order; returns how many.

    From the cone of the point before, walk to the face across the edge opposite the most negative coordinate until
    all three are clearly positive (above 1e-9 of their sum: a cone's interior, where no other face can hold the
    point); a point within that of a border, or whose walk goes round, takes the face whose smallest coordinate is
    largest over all faces, as the numpy twin does for every point. Coordinates below 1e-12 of their absolute sum
    are then set to zero, as there.
    """
    n_faces = len(inv)
    f = 0
    count = 0
    for p in range(len(points)):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        g, walking, steps = f, True, 0
        best, best_least, b0, b1, b2 = -1, -np.inf, 0.0, 0.0, 0.0
        while True:
            # the coordinates of the point in face g's unit directions: inv[g] @ p
            l0 = inv[g, 0, 0] * x + inv[g, 0, 1] * y + inv[g, 0, 2] * z
            l1 = inv[g, 1, 0] * x + inv[g, 1, 1] * y + inv[g, 1, 2] * z
            l2 = inv[g, 2, 0] * x + inv[g, 2, 1] * y + inv[g, 2, 2] * z
            least = min(l0, l1, l2)
            if walking:
                size = 1e-9 * (abs(l0) + abs(l1) + abs(l2))
                if least > size:
                    best, b0, b1, b2 = g, l0, l1, l2
                    break
                step = neighbours[g, 0 if l0 == least else (1 if l1 == least else 2)]
                steps += 1
                if least >= -size or step < 0 or steps > n_faces:  # a border, the origin, or going round
                    g, walking = 0, False
                else:
                    g = step
            else:
                if least > best_least:
                    best, best_least, b0, b1, b2 = g, least, l0, l1, l2
                g += 1
                if g == n_faces:
                    break
        f = best
        small = 1e-12 * (abs(b0) + abs(b1) + abs(b2))
        b0, b1, b2 = (b0 if b0 >= small else 0.0), (b1 if b1 >= small else 0.0), (b2 if b2 >= small else 0.0)
        if b0 / radii[faces[f, 0]] + b1 / radii[faces[f, 1]] + b2 / radii[faces[f, 2]] > threshold:
            face_of[count] = f
            coords[count, 0], coords[count, 1], coords[count, 2] = b0, b1, b2
            count += 1
    return count


@compiled_on_first_call
def _lift_round(coords, corner, radii, limit, active, count, lifted):  # pragma: no cover - compiled
    """One round of :func:`_raise_radii` over ``active[:count]``: the points over the margin are moved to the front
    of ``active`` (a point under it now stays under, the radii only grow) and each raises ``lifted`` at the
    vertices that carry it to its level (:func:`_raise_level`, here a point at a time). Returns how many are over.
    """
    over = 0
    r = np.empty(3)
    lam = np.empty(3)
    for a in range(count):
        p = active[a]
        c0, c1, c2 = coords[p, 0], coords[p, 1], coords[p, 2]
        k0, k1, k2 = corner[p, 0], corner[p, 1], corner[p, 2]
        if (c0 / radii[k0] + c1 / radii[k1]) + c2 / radii[k2] <= limit:
            continue
        active[over] = p
        over += 1
        # the carrying vertices' radii in ascending order (a vertex that does not carry the point last), stably
        for i in range(3):
            lam[i] = coords[p, i]
            r[i] = radii[corner[p, i]] if lam[i] > 0 else np.inf
        for i in range(1, 3):
            j = i
            while j > 0 and r[j - 1] > r[j]:
                r[j - 1], r[j] = r[j], r[j - 1]
                lam[j - 1], lam[j] = lam[j], lam[j - 1]
                j -= 1
        level = np.nan
        for j in range(1, 4):
            rest = 0.0
            if j == 1:
                rest = (lam[1] / r[1] if lam[1] > 0 else 0.0) + (lam[2] / r[2] if lam[2] > 0 else 0.0)
            elif j == 2:
                rest = lam[2] / r[2] if lam[2] > 0 else 0.0
            rest = limit - rest
            held = lam[0] if j == 1 else (lam[0] + lam[1] if j == 2 else (lam[0] + lam[1]) + lam[2])
            upper = r[j] if j < 3 else np.inf
            if rest > 0:
                cand = held / rest
                if cand <= upper and cand >= r[j - 1]:
                    level = cand
                    break
        if level != level:  # a rounding miss at a breakpoint: the uniform level, which always works
            level = ((lam[0] + lam[1]) + lam[2]) / limit
        level *= 1.0 + 1e-12
        for i in range(3):
            if coords[p, i] > 0 and level > lifted[corner[p, i]]:
                lifted[corner[p, i]] = level
    return over


def _raise_level(coords: np.ndarray, radii: np.ndarray, limit: float) -> np.ndarray:
    """The lowest level R such that raising a face's vertex radii to at least R brings a point inside.

    Parameters
    ----------
    coords : (n, 3) the points' coordinates in their faces' unit vertex directions (>= 0).
    radii : (n, 3) the current radii of those vertices.
    limit : the largest radial fraction allowed.

    Returns
    -------
    level : (n,) R with ``sum(coords / maximum(radii, R)) == limit`` (vertices with a zero coordinate ignored).
    """
    radii = np.where(coords > 0, radii, np.inf)  # a vertex that does not carry the point is never raised
    order = np.argsort(radii, axis=1)
    r = np.take_along_axis(radii, order, axis=1)  # (n, 3) ascending
    lam = np.take_along_axis(coords, order, axis=1)
    level = np.full(len(r), np.nan)
    upper = np.concatenate([r[:, 1:], np.full((len(r), 1), np.inf)], axis=1)
    for j in range(1, 4):
        # The j lowest vertices raised to R, the others kept: sum(lam[:j]) / R + sum(lam[j:] / r[j:]) = limit.
        with np.errstate(divide="ignore", invalid="ignore"):
            rest = limit - np.sum(np.where(lam[:, j:] > 0, lam[:, j:] / r[:, j:], 0.0), axis=1)
            cand = np.sum(lam[:, :j], axis=1) / rest
        ok = np.isnan(level) & (rest > 0) & (cand <= upper[:, j - 1]) & (cand >= r[:, j - 1])
        level[ok] = cand[ok]
    # A rounding miss at a breakpoint: fall back to the uniform level, which always works.
    miss = np.isnan(level)
    level[miss] = np.sum(lam[miss], axis=1) / limit
    return level * (1.0 + 1e-12)


# --- inside / outside --------------------------------------------------------------------------------------------

def winding_number(points: Any, vertices: Any, faces: Any) -> np.ndarray:
    """Generalised winding number of points with respect to a triangle mesh (solid angles summed, over 4π).

    About 1 inside a closed outward-oriented mesh and 0 outside; on the surface itself it is not defined (a face
    through the point adds +-2π or 0 depending on rounding).

    Parameters
    ----------
    points : (N, 3) float64
    vertices : (C, 3) float64
    faces : (F, 3) int

    Returns
    -------
    winding : (N,) float64
    """
    points = as_points(points, min_count=0)
    vertices = as_points(vertices, "vertices")
    faces = _check_faces(faces, len(vertices), "faces")
    corners = [vertices[faces[:, k]].T.copy() for k in range(3)]  # 3 x (3, F)
    out = np.empty(len(points))
    chunk = max(1, _CHUNK_PAIRS // len(faces))
    for start in range(0, len(points), chunk):
        x = points[start : start + chunk].T[:, :, None]  # (3, n, 1)
        a, b, c = (corner[:, None, :] - x for corner in corners)  # (3, n, F) each, per component
        la, lb, lc = (np.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2) for v in (a, b, c))  # (n, F)
        num = (
            a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2]) + a[2] * (b[0] * c[1] - b[1] * c[0])
        )
        den = la * lb * lc + _dot3(a, b) * lc + _dot3(a, c) * lb + _dot3(b, c) * la
        out[start : start + chunk] = 2.0 * np.arctan2(num, den).sum(axis=1)  # Van Oosterom & Strackee
    return out / (4.0 * np.pi)


def _dot3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def points_outside(points: Any, vertices: Any, faces: Any) -> np.ndarray:
    """``(N,)`` bool: points whose winding number with respect to the cage is below 1/2."""
    return winding_number(points, vertices, faces) < 0.5


# --- demo import -------------------------------------------------------------------------------------------------

def cage_faces_from_vertices(vertices: Any) -> np.ndarray:
    """The triangles of a cage star-shaped about the origin, recovered from its vertices alone (docs/method.md §17).

    The authors' demo files store a cage's vertices but not its faces. Such a cage is an icosphere whose vertices
    were moved along their rays, so its triangles are those of the convex hull of the directions ``v / |v|``.

    Parameters
    ----------
    vertices : (C, 3) float64, no vertex at the origin, no two in the same direction.

    Returns
    -------
    faces : (F, 3) int64, outward-oriented, each starting at its smallest index, rows sorted.
    """
    vertices = as_points(vertices, "cage vertices", min_count=4)
    radii = np.linalg.norm(vertices, axis=1)
    if not (radii > 0).all():
        raise InputError(f"cage vertex {int(np.argmin(radii))} lies at the origin; its direction is undefined")
    dirs = vertices / radii[:, None]
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(dirs)
    except QhullError as exc:
        raise InputError(f"the {len(dirs)} vertex directions span no volume (all on one great circle?)") from exc
    missing = np.setdiff1d(np.arange(len(dirs)), hull.vertices)
    if len(missing):
        raise InputError(
            f"every cage vertex must have its own direction from the origin; {len(missing)} do not "
            f"(vertices {missing[:10].tolist()}): repeated directions or a cage that is not star-shaped"
        )
    if not (hull.equations[:, 3] < -1e-9).all():
        raise InputError("the origin is not inside the cage: its vertex directions lie in one half-space")
    faces = hull.simplices.astype(np.int64)
    a, b, c = dirs[faces[:, 0]], dirs[faces[:, 1]], dirs[faces[:, 2]]
    inward = np.einsum("fi,fi->f", a, np.cross(b, c)) < 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    first = np.argmin(faces, axis=1)
    faces = np.take_along_axis(faces, (first[:, None] + np.arange(3)) % 3, axis=1)
    return np.ascontiguousarray(faces[np.lexsort(faces.T[::-1])])


# --- influence mask ----------------------------------------------------------------------------------------------

def influence_mask(keypoints: Any, cage_vertices: Any, m: int) -> np.ndarray:
    """Which cage vertices each keypoint may move: its ``m`` nearest, ties kept (docs/method.md §3).

    Parameters
    ----------
    keypoints : (K, 3) float64
    cage_vertices : (C, 3) float64
    m : 1 <= m <= C.

    Returns
    -------
    mask : (K, C) bool, True where the squared distance is <= the m-th smallest of the row.
    """
    keypoints = as_points(keypoints, "keypoints")
    cage_vertices = as_points(cage_vertices, "cage vertices")
    c = len(cage_vertices)
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= c:
        raise InputError(f"m must be an integer in [1, {c}] for {c} cage vertices; got {m!r}")
    d2 = np.sum((keypoints[:, None, :] - cage_vertices[None, :, :]) ** 2, axis=2)  # (K, C)
    kth = np.partition(d2, int(m) - 1, axis=1)[:, int(m) - 1 : int(m)]  # (K, 1)
    return d2 <= kth


def default_m(C: int, K: int, paper: bool = False) -> int:
    """Cage vertices per keypoint in the mask: ``max(5, C // K)`` as the authors' code, ``C // K`` as the paper.

    The code's value is capped at C (it only matters for cages with fewer than 5 vertices).
    """
    for name, value in (("C", C), ("K", K)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"{name} must be a positive integer; got {value!r}")
    if paper:
        if C // K < 1:
            raise InputError(f"the paper's rule C // K gives 0 for C = {C} cage vertices and K = {K} keypoints")
        return int(C // K)
    return int(min(C, max(5, C // K)))
