"""Per-camera visibility: the corners and facade walls a rough pose can see.

A purely geometric test, vectorised over the whole map: back-face culling
(the wall's outward normal points towards the camera centre, party walls
excluded) and the viewing frustum (image grown by a margin, near plane).
It does NOT model occlusion by other buildings; later stages handle that
through their robust matching.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from obliq_colmap.geometry import Camera, Pose

from .model import SHARED_WALL_FRACTION, Cadastre

#: A ground height: a constant in metres (local frame, the priors' vertical
#: datum), or a function of (N, 2) local xy (m) returning (N,) heights (m).
GroundHeight = float | Callable[[np.ndarray], np.ndarray]

# Edges are clipped against the frustum in chunks of this many to bound memory
# ((chunk, 36, 9) arrays in the wall clipping).
_EDGE_CHUNK = 4096


def _ground_at(ground_height: GroundHeight, xy: np.ndarray) -> np.ndarray:
    """(N,) ground heights (m) at (N, 2) local xy."""
    if callable(ground_height):
        z = np.asarray(ground_height(xy), dtype=float)
        if z.shape != (len(xy),):
            raise ValueError(
                f"ground_height({len(xy)} x 2 points) must return shape "
                f"({len(xy)},), got {z.shape}"
            )
        return z
    return np.full(len(xy), float(ground_height))


def _frustum_bounds(camera: Camera, margin_px: float) -> np.ndarray:
    """(xmin, xmax, ymin, ymax) of the image in normalised camera coordinates.

    The image spans pixels [0, width] x [0, height] (COLMAP convention), grown
    by ``margin_px``. Without distortion the bounds are exact; with distortion
    they are the bounding box of the undistorted image border (sampled), so
    the frustum test is conservative near the image corners.
    """
    m = float(margin_px)
    w, h = float(camera.width), float(camera.height)
    if not camera.has_distortion:
        K = camera.K
        return np.array(
            [
                (-m - K[0, 2]) / K[0, 0],
                (w + m - K[0, 2]) / K[0, 0],
                (-m - K[1, 2]) / K[1, 1],
                (h + m - K[1, 2]) / K[1, 1],
            ]
        )
    u = np.linspace(-m, w + m, 65)
    v = np.linspace(-m, h + m, 65)
    border = np.concatenate(
        [
            np.stack([u, np.full_like(u, -m)], 1),
            np.stack([u, np.full_like(u, h + m)], 1),
            np.stack([np.full_like(v, -m), v], 1),
            np.stack([np.full_like(v, w + m), v], 1),
        ]
    )
    uv = camera.cam_from_img(border)
    return np.array([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])


def _frustum_planes(
    camera: Camera, margin_px: float, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Half-spaces ``n . X_cam + d >= 0`` of the viewing frustum.

    Returns
    -------
    normals : (5, 3) array, camera frame.
    offsets : (5,) array, metres.
    """
    xmin, xmax, ymin, ymax = _frustum_bounds(camera, margin_px)
    normals = np.array(
        [
            [1.0, 0.0, -xmin],  # x >= xmin z
            [-1.0, 0.0, xmax],  # x <= xmax z
            [0.0, 1.0, -ymin],  # y >= ymin z
            [0.0, -1.0, ymax],  # y <= ymax z
            [0.0, 0.0, 1.0],  # z >= min_depth
        ]
    )
    offsets = np.array([0.0, 0.0, 0.0, 0.0, -float(min_depth_m)])
    return normals, offsets


def _vertical_extent(
    cadastre: Cadastre,
    buildings: np.ndarray,
    height_range_m: tuple[float, float],
    use_building_heights: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bottom and top heights above the ground (m) for each building index."""
    h_min, h_max = (float(v) for v in height_range_m)
    if not h_max >= h_min:
        raise ValueError(
            f"height_range_m must be (min, max) with min <= max, got {height_range_m!r}"
        )
    bottom = np.full(len(buildings), h_min)
    top = np.full(len(buildings), h_max)
    if use_building_heights:
        h = cadastre.heights[buildings]
        known = np.isfinite(h)
        top[known] = np.clip(h[known], h_min, h_max)
    return bottom, top


def _facing(
    cadastre: Cadastre,
    center_xy: np.ndarray,
    exclude_shared_walls: bool,
    edges: np.ndarray | slice = slice(None),
) -> np.ndarray:
    """(E,) bool for ``edges`` (default all): the wall's outward normal
    points towards the camera centre."""
    to_camera = center_xy[None, :] - cadastre.edge_xy[edges, 0]  # (E, 2)
    facing = np.sum(cadastre.edge_normal[edges] * to_camera, axis=1) > 0
    if exclude_shared_walls:
        facing &= cadastre.edge_shared_fraction[edges] < SHARED_WALL_FRACTION
    return facing


def _view_box(
    camera: Camera,
    cam_from_world: Pose,
    z_range: tuple[float, float],
    margin_px: float,
) -> tuple[float, float, float, float] | None:
    """Horizontal bounding box (xmin, ymin, xmax, ymax) of the viewing
    frustum between the heights ``z_range``; None when it is unbounded (an
    edge of the image looks level or up, or the camera is not above the
    slab).

    With every edge ray pointing down from above the slab, the frustum's part
    in the slab is the convex hull of the 8 points where the 4 edge rays
    cross its two planes, so their box bounds every point it contains.
    """
    z_lo, z_hi = z_range
    center = cam_from_world.center
    if not center[2] > z_hi:
        return None
    xmin, xmax, ymin, ymax = _frustum_bounds(camera, margin_px)
    rays = np.array(
        [[xmin, ymin, 1], [xmax, ymin, 1], [xmax, ymax, 1], [xmin, ymax, 1]]
    )
    d = rays @ cam_from_world.rotation  # (4, 3) world directions (R^T ray)
    if not np.all(d[:, 2] < 0):
        return None
    t = (np.array([z_lo, z_hi])[:, None] - center[2]) / d[None, :, 2]  # (2, 4)
    xy = center[:2] + t[..., None] * d[None, :, :2]  # (2, 4, 2)
    lo, hi = xy.reshape(-1, 2).min(axis=0), xy.reshape(-1, 2).max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _corners_of(cadastre: Cadastre, buildings: np.ndarray) -> np.ndarray:
    """(K,) ascending indices of the corners of ``buildings`` (ascending);
    the corners of one building are contiguous (``corner_building`` is
    sorted)."""
    start = np.searchsorted(cadastre.corner_building, buildings, side="left")
    stop = np.searchsorted(cadastre.corner_building, buildings, side="right")
    count = stop - start
    if not count.sum():
        return np.zeros(0, dtype=np.int64)
    offsets = np.repeat(start - np.cumsum(count) + count, count)
    return (np.arange(count.sum()) + offsets).astype(np.int64)


def visible_corners(
    cadastre: Cadastre,
    camera: Camera,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float] = (0.0, 50.0),
    margin_px: float = 0.0,
    *,
    use_building_heights: bool = True,
    exclude_shared_walls: bool = True,
    min_depth_m: float = 0.1,
) -> np.ndarray:
    """Corners whose vertical building edge a camera can potentially see.

    A corner is kept when

    1. the vertical segment from ``ground + h_min`` to ``ground + h_max`` at the
       corner lies at least partly inside the viewing frustum (in front of the
       camera by ``min_depth_m`` and inside the image grown by ``margin_px``),
       and
    2. at least one of its two walls faces the camera: the wall's outward
       normal has a positive dot product with the horizontal direction from
       the wall to the camera centre. A convex corner with both walls facing
       away is hidden by its own building; so is a reflex corner, which is
       seen only when its walls face the camera.

    There is no occlusion test against other buildings (later stages handle
    occlusion through robust matching).

    Parameters
    ----------
    cadastre : Cadastre
    camera : Camera
        Intrinsics; the image is [0, width] x [0, height] px.
    cam_from_world : Pose
        Pose in the cadastre's LOCAL frame.
    ground_height : float or callable
        Ground height (m, local frame, the priors' vertical datum), or a
        function of (N, 2) local xy returning (N,) heights, e.g. a plane.
    height_range_m : (2,) tuple of float
        (h_min, h_max), metres above the ground spanned by the corner's
        vertical segment.
    margin_px : float
        Grow the image by this many pixels on every side (uncertain poses).
    use_building_heights : bool
        Where the map gives a building's height, end its segment there
        (clipped to ``height_range_m``).
    exclude_shared_walls : bool
        Party walls (``edge_shared_fraction >= SHARED_WALL_FRACTION``) do not
        count as walls facing the camera.
    min_depth_m : float
        Near plane (m in front of the camera).

    Returns
    -------
    (K,) int array
        Indices into the cadastre's corners, ascending.

    Notes
    -----
    With lens distortion the frustum is the bounding box of the undistorted
    image border, which keeps a few corners just outside the image corners.
    """
    if cadastre.num_corners == 0:
        return np.zeros(0, dtype=np.int64)
    center = cam_from_world.center
    # A constant ground bounds the frustum's footprint: only the buildings the
    # spatial index finds there are tested (a city-wide map costs per image
    # what its part in view costs).
    idx = np.arange(cadastre.num_corners)
    if not callable(ground_height):
        lo, hi = sorted(float(v) for v in height_range_m)
        box = _view_box(
            camera,
            cam_from_world,
            (float(ground_height) + lo, float(ground_height) + hi),
            margin_px,
        )
        if box is not None:
            idx = _corners_of(cadastre, cadastre.buildings_in_box(*box))
    edges = cadastre.corner_edges[idx]  # (K, 2)
    facing = _facing(cadastre, center[:2], exclude_shared_walls, edges.ravel())
    idx = idx[facing.reshape(-1, 2).any(axis=1)]
    if len(idx) == 0:
        return idx.astype(np.int64)

    xy = cadastre.corner_xy[idx]
    ground = _ground_at(ground_height, xy)
    bottom, top = _vertical_extent(
        cadastre, cadastre.corner_building[idx], height_range_m, use_building_heights
    )
    R, t = cam_from_world.rotation, cam_from_world.translation
    start_world = np.column_stack([xy, ground + bottom])  # (K, 3)
    start_cam = start_world @ R.T + t  # (K, 3)
    up_cam = np.outer(top - bottom, R[:, 2])  # (K, 3), R @ (0, 0, dz)
    normals, offsets = _frustum_planes(camera, margin_px, min_depth_m)
    # X(t) = start + t up, t in [0, 1]; each plane: a t + c >= 0.
    a = up_cam @ normals.T  # (K, 5)
    c = start_cam @ normals.T + offsets  # (K, 5)
    inside = _interval_nonempty(a, c)
    return idx[inside].astype(np.int64)


def _interval_nonempty(a: np.ndarray, c: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(K,) bool: some t in [0, 1] has ``a t + c >= 0`` for all (K, P) rows."""
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -c / a
    lower = np.max(np.where(a > 0, root, 0.0), axis=1, initial=0.0)
    upper = np.min(np.where(a < 0, root, 1.0), axis=1, initial=1.0)
    flat_ok = np.all((a != 0) | (c >= -tol), axis=1)
    return flat_ok & (lower <= upper + tol)


def visible_edge_parts(
    cadastre: Cadastre,
    camera: Camera,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float] = (0.0, 50.0),
    margin_px: float = 0.0,
    *,
    use_building_heights: bool = True,
    exclude_shared_walls: bool = True,
    min_depth_m: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Facade walls a camera can potentially see, with their visible parts.

    A wall is the vertical quadrilateral over an edge from ``ground + h_min``
    to ``ground + h_max`` (the ground is interpolated linearly along the edge,
    exact for a planar ground). It is kept when it faces the camera (outward
    normal towards the camera centre, horizontally) and intersects the viewing
    frustum. The intersection is exact for a pinhole camera: in wall
    coordinates (s along the edge, t up the wall, both in [0, 1]) the part
    inside the frustum is a convex polygon cut out by 9 half-planes, found for
    all walls at once from the pairwise intersections of their boundary lines.
    No occlusion by other buildings is modelled.

    Parameters
    ----------
    Same as :func:`visible_corners`.

    Returns
    -------
    indices : (K,) int array
        Edge indices, ascending.
    clipped_xy : (K, 2, 2) float array
        Start and end (local frame, m) of the part of each edge over which
        some of the wall is inside the frustum, in the edge's direction.
    """
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 2, 2)))
    if cadastre.num_edges == 0:
        return empty
    center = cam_from_world.center
    idx = np.flatnonzero(_facing(cadastre, center[:2], exclude_shared_walls))
    if len(idx) == 0:
        return empty
    normals, offsets = _frustum_planes(camera, margin_px, min_depth_m)
    keep: list[np.ndarray] = []
    ranges: list[np.ndarray] = []
    for lo in range(0, len(idx), _EDGE_CHUNK):
        chunk = idx[lo : lo + _EDGE_CHUNK]
        ok, s_range = _clip_walls(
            cadastre,
            chunk,
            cam_from_world,
            ground_height,
            height_range_m,
            use_building_heights,
            normals,
            offsets,
        )
        keep.append(chunk[ok])
        ranges.append(s_range[ok])
    indices = np.concatenate(keep).astype(np.int64)
    s_range = np.concatenate(ranges, axis=0)  # (K, 2)
    p0, p1 = cadastre.edge_xy[indices, 0], cadastre.edge_xy[indices, 1]
    d = p1 - p0
    clipped = np.stack([p0 + s_range[:, :1] * d, p0 + s_range[:, 1:] * d], axis=1)
    return indices, clipped


def visible_edges(
    cadastre: Cadastre,
    camera: Camera,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float] = (0.0, 50.0),
    margin_px: float = 0.0,
    *,
    use_building_heights: bool = True,
    exclude_shared_walls: bool = True,
    min_depth_m: float = 0.1,
) -> np.ndarray:
    """Indices of the facade walls a camera can potentially see.

    See :func:`visible_edge_parts` (which also returns the visible part of
    each edge) for the test and the parameters.

    Returns
    -------
    (K,) int array
        Edge indices, ascending.
    """
    indices, _ = visible_edge_parts(
        cadastre,
        camera,
        cam_from_world,
        ground_height,
        height_range_m,
        margin_px,
        use_building_heights=use_building_heights,
        exclude_shared_walls=exclude_shared_walls,
        min_depth_m=min_depth_m,
    )
    return indices


def _clip_walls(
    cadastre: Cadastre,
    edges: np.ndarray,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float],
    use_building_heights: bool,
    normals: np.ndarray,
    offsets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Clip N walls against the frustum.

    Returns
    -------
    ok : (N,) bool, the wall intersects the frustum.
    s_range : (N, 2) array, [s_min, s_max] along the edge of the visible part
        (meaningless where not ok).
    """
    xy = cadastre.edge_xy[edges]  # (N, 2, 2)
    n = len(edges)
    ground = _ground_at(ground_height, xy.reshape(-1, 2)).reshape(n, 2)
    bottom, top = _vertical_extent(
        cadastre, cadastre.edge_building[edges], height_range_m, use_building_heights
    )
    R, t = cam_from_world.rotation, cam_from_world.translation
    b0 = np.column_stack([xy[:, 0], ground[:, 0] + bottom])  # (N, 3)
    b1 = np.column_stack([xy[:, 1], ground[:, 1] + bottom])  # (N, 3)
    # X(s, t) = b0 + s (b1 - b0) + t (0, 0, top - bottom), camera frame:
    base = b0 @ R.T + t
    along = (b1 - b0) @ R.T
    up = np.outer(top - bottom, R[:, 2])
    # Half-planes a s + b t + c >= 0: 5 frustum planes, then the unit square.
    a = np.concatenate([along @ normals.T, np.tile([1.0, -1.0, 0.0, 0.0], (n, 1))], 1)
    b = np.concatenate([up @ normals.T, np.tile([0.0, 0.0, 1.0, -1.0], (n, 1))], 1)
    c = np.concatenate(
        [base @ normals.T + offsets, np.tile([0.0, 1.0, 0.0, 1.0], (n, 1))], 1
    )  # (N, 9)
    scale = np.hypot(a, b)
    degenerate = scale < 1e-12  # a constant constraint: c >= 0 or never
    scale = np.where(degenerate, 1.0, scale)
    a, b, c = a / scale, b / scale, c / scale
    tol = 1e-9
    always_violated = np.any(degenerate & (c < -tol), axis=1)

    # Candidate vertices: intersections of every pair of boundary lines.
    i, j = np.triu_indices(a.shape[1], k=1)  # 36 pairs
    det = a[:, i] * b[:, j] - a[:, j] * b[:, i]  # (N, 36)
    good = np.abs(det) > 1e-12
    det = np.where(good, det, 1.0)
    s = (-c[:, i] * b[:, j] + b[:, i] * c[:, j]) / det
    tt = (-a[:, i] * c[:, j] + a[:, j] * c[:, i]) / det
    # Feasible: every half-plane holds, (N, 36, 9).
    slack = a[:, None, :] * s[..., None] + b[:, None, :] * tt[..., None] + c[:, None, :]
    feasible = good & np.all(slack >= -tol, axis=2)
    ok = feasible.any(axis=1) & ~always_violated
    s_min = np.min(np.where(feasible, s, np.inf), axis=1)
    s_max = np.max(np.where(feasible, s, -np.inf), axis=1)
    s_range = np.clip(np.stack([s_min, s_max], axis=1), 0.0, 1.0)
    return ok, s_range
