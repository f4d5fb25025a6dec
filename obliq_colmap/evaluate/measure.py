"""The measurement of one image: corner deviations between the estimated and
the true camera (full or across the projected vertical), an image's own
vertical offset, and the search of the ONE block offset that minimises the
median of the images' mean deviations (``vertical_offset="search"``)."""

from __future__ import annotations

import logging
import math

import numpy as np

from obliq_colmap.geometry import Camera, Pose

logger = logging.getLogger(__name__)

#: Gauss-Newton steps of an image's own vertical offset (the projections are
#: nearly linear in it over the metres in question: 3 steps reach ~1e-9 m).
_OFFSET_STEPS = 3

#: The block offset search (``vertical_offset="search"``): coarse grid step
#: (m), local minima refined, zooms of x20 each. An image's mean deviation
#: changes by ~5 px per metre of height at 45 deg and 650 m (4,450 px focal),
#: so 0.1 m keeps a dip from hiding between grid points and three zooms reach
#: ~1e-5 m (~5e-5 px).
_SEARCH_STEP_M = 0.1
_SEARCH_CANDIDATES = 5
_SEARCH_ZOOMS = 3

#: Step (m) along the world vertical for the image direction of the vertical,
#: central difference. The projected vertical is a straight line for pinhole
#: cameras and nearly one under distortion, so any small step works; points
#: are shifted to a frame near the block first, so 5 cm keeps ~1e-9 px.
_VERTICAL_STEP_M = 0.05


def corner_deviations_px(
    est_camera: Camera,
    est_pose: Pose,
    true_camera: Camera,
    true_pose: Pose,
    corners_world: np.ndarray,
    across_vertical: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Deviations of the estimated from the true projections of 3D corners.

    Parameters
    ----------
    est_camera, est_pose : the estimated camera (own intrinsics and
        distortion), ``cam_from_world`` in the frame of ``corners_world``.
    true_camera, true_pose : the true camera, same frame.
    corners_world : (K, 3) array, metres; corners visible in the true image.
    across_vertical : bool
        Measure only the distance of the estimated projection from the line
        through the true projection along the TRUE image direction of the world
        vertical at that corner (central difference over +-2.5 cm of height).
        Where the vertical projects to a point (a corner on the nadir or zenith
        ray of the camera) the full distance is used.

    Returns
    -------
    deviation_px : (K,) array, pixels; NaN where the corner is behind the
        estimated camera.
    behind : (K,) bool array, corner at depth <= 0 in the estimated camera.
    """
    X = np.asarray(corners_world, float).reshape(-1, 3)
    X_est_cam = est_pose.transform(X)  # (K, 3)
    behind = ~(X_est_cam[:, 2] > 0)
    xy_est = est_camera.img_from_cam(X_est_cam)  # (K, 2), NaN behind
    xy_true = true_camera.img_from_cam(true_pose.transform(X))  # (K, 2)
    diff = xy_est - xy_true  # (K, 2)
    if not across_vertical:
        return np.linalg.norm(diff, axis=1), behind
    direction, degenerate = _vertical_direction(true_camera, true_pose, X)
    return _across(diff, direction, degenerate), behind


def _vertical_direction(
    camera: Camera, pose: Pose, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The unit image direction (K, 2) of the world vertical through each of
    the points ``X`` (K, 3) in ``camera``, and where it is a point (K,) bool."""
    dz = np.array([0.0, 0.0, 0.5 * _VERTICAL_STEP_M])
    up = camera.img_from_cam(pose.transform(X + dz))  # (K, 2)
    down = camera.img_from_cam(pose.transform(X - dz))  # (K, 2)
    direction = up - down  # (K, 2), image direction of the vertical
    length = np.linalg.norm(direction, axis=1)
    degenerate = ~(length > 1e-9)
    return direction / np.where(degenerate, 1.0, length)[:, None], degenerate


def _across(diff: np.ndarray, direction: np.ndarray, degenerate: np.ndarray):
    """Length of ``diff`` (..., K, 2) across ``direction`` (K, 2); its full
    length where the direction is ``degenerate`` (K,)."""
    # |2D cross product| = distance from the line through xy_true along direction.
    across = np.abs(direction[:, 0] * diff[..., 1] - direction[:, 1] * diff[..., 0])
    return np.where(degenerate, np.linalg.norm(diff, axis=-1), across)


def mean_deviation_by_offset(
    est_camera: Camera,
    est_pose: Pose,
    true_camera: Camera,
    true_pose: Pose,
    corners_world: np.ndarray,
    across_vertical: bool = False,
):
    """A function of the height offsets ``d`` (D,) giving an image's mean
    corner deviation (D,) px with its estimated camera lowered by each ``d``
    (as :func:`corner_deviations_px`, vectorised over the offsets); infinite
    where a corner is behind the lowered camera. Corners that do not project
    into the true camera are left out (bad ground truth, warned about there).
    """
    X = np.asarray(corners_world, float).reshape(-1, 3)
    xy_true = true_camera.img_from_cam(true_pose.transform(X))  # (K, 2)
    ok = np.isfinite(xy_true).all(axis=1)
    X, xy_true = X[ok], xy_true[ok]
    X_cam = est_pose.transform(X)  # (K, 3)
    # Lowering the camera by d is raising the corners by d: + d * R e_z.
    up = est_pose.rotation[:, 2]  # (3,)
    if across_vertical:
        direction, degenerate = _vertical_direction(true_camera, true_pose, X)

    def mean_deviation(offsets: np.ndarray) -> np.ndarray:
        d = np.asarray(offsets, float).reshape(-1)
        if len(X) == 0:
            return np.full(len(d), math.inf)
        pts = X_cam[None] + d[:, None, None] * up  # (D, K, 3)
        xy = est_camera.img_from_cam(pts.reshape(-1, 3)).reshape(len(d), len(X), 2)
        diff = xy - xy_true  # (D, K, 2)
        if across_vertical:
            dev = _across(diff, direction, degenerate)
        else:
            dev = np.linalg.norm(diff, axis=-1)
        behind = ~(pts[..., 2] > 0).all(axis=1)  # (D,)
        return np.where(behind, math.inf, dev.mean(axis=1))

    return mean_deviation


def search_block_offset(
    profiles: list,
    num_missing: int,
    center: float,
    half_range: float,
) -> tuple[float, float]:
    """The ONE vertical offset (m) of a block minimising the median over its
    images of their mean corner deviation, in ``center +- half_range``.

    Parameters
    ----------
    profiles : functions of the offsets (D,) -> (D,) mean deviation px, one
        per measured image present in the result
        (:func:`mean_deviation_by_offset`).
    num_missing : images missing from the result, infinite at every offset.
    center, half_range : float, m; the camera-height offset and the span.

    Returns
    -------
    offset : float, m; ``center`` when every offset gives an infinite median
        even over the present images alone (too few images in front).
    median : float, px, the minimised median (missing images infinite).

    The median of per-image V-shaped curves is not convex: a grid of
    ``_SEARCH_STEP_M`` over the whole range, then its lowest
    ``_SEARCH_CANDIDATES`` local minima zoomed into (grids of 41 points over
    +-1 step, ``_SEARCH_ZOOMS`` times). ``center`` is a grid point and is kept
    on ties, so a model equal to the truth gets exactly its offset.
    """
    if not profiles:
        return center, math.inf
    n = int(round(half_range / _SEARCH_STEP_M))
    grid = center + _SEARCH_STEP_M * np.arange(-n, n + 1)
    lo, hi = center - half_range, center + half_range

    def cost(d, missing):
        m = np.column_stack(
            [f(d) for f in profiles] + [np.full(len(d), math.inf)] * missing
        )
        return np.median(m, axis=1) if m.shape[1] else np.full(len(d), math.inf)

    missing = num_missing
    values = cost(grid, missing)
    if not np.isfinite(values).any() and missing:
        # More than half of the images missing: the median over the images
        # present picks the offset; the judged median stays infinite.
        logger.warning(
            "vertical offset search: %d of %d images missing; the offset "
            "minimises the median over the %d present",
            missing,
            missing + len(profiles),
            len(profiles),
        )
        missing = 0
        values = cost(grid, missing)
    if not np.isfinite(values).any():
        logger.warning(
            "vertical offset search: no offset puts half of the images' corners "
            "in front of their cameras; the camera-height offset %.3f m is used",
            center,
        )
        return center, math.inf
    i_best = int(np.argmin(values))
    best, best_value = float(grid[i_best]), float(values[i_best])
    padded = np.concatenate([[math.inf], values, [math.inf]])
    local = (values <= padded[:-2]) & (values <= padded[2:]) & np.isfinite(values)
    order = np.argsort(np.where(local, values, math.inf), kind="stable")
    candidates = grid[order[: min(_SEARCH_CANDIDATES, int(local.sum()))]]
    step = _SEARCH_STEP_M
    offsets = np.linspace(-1.0, 1.0, 41)
    for _ in range(_SEARCH_ZOOMS):
        d = np.clip((candidates[:, None] + step * offsets).reshape(-1), lo, hi)
        v = cost(d, missing).reshape(len(candidates), -1)
        candidates = d.reshape(len(candidates), -1)[
            np.arange(len(candidates)), np.argmin(v, axis=1)
        ]
        step /= 20.0
        if v.min() < best_value:
            best_value = float(v.min())
            best = float(d[int(np.argmin(v))])
    if missing != num_missing:
        best_value = float(cost(np.array([best]), num_missing)[0])
    return best, best_value


def scene_height_offset(
    est_camera: Camera,
    est_pose: Pose,
    true_camera: Camera,
    true_pose: Pose,
    corners_world: np.ndarray,
    start: float,
) -> float:
    """The height (m) by which the estimated camera must be lowered for its
    projections of ``corners_world`` (K, 3) to fit the true camera's best
    (least squares over the corners in front of it; Gauss-Newton from
    ``start``, e.g. the centre-height difference). Lowering the camera by d
    is raising the corners by d. NaN when no corner is in front.
    """
    X = np.asarray(corners_world, float).reshape(-1, 3)
    X = X[est_pose.transform(X)[:, 2] > 0]
    if len(X) == 0:
        return math.nan
    target = true_camera.img_from_cam(true_pose.transform(X))  # (K, 2)

    def project(d: float) -> np.ndarray:
        return est_camera.img_from_cam(est_pose.transform(X + [0.0, 0.0, d]))

    d, h = float(start), 0.5 * _VERTICAL_STEP_M
    for _ in range(_OFFSET_STEPS):
        r = project(d) - target
        J = (project(d + h) - project(d - h)) / (2 * h)
        ok = np.isfinite(r).all(axis=1) & np.isfinite(J).all(axis=1)
        jj = float(np.sum(J[ok] ** 2))
        if not ok.any() or jj <= 0:
            return math.nan
        d -= float(np.sum(J[ok] * r[ok])) / jj
    return d
