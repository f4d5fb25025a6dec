"""Is something standing on a footprint? A height sweep of its interior.

A building's roof is the part of it that every oblique view sees (walls face
half the heads, corners need a contrast, and a neighbour that the map lacks
can hide them or merge with them). Points on a horizontal plane through the
footprint's interior project to the same surface texture in every view only
at the height of what is really there: the roof for a standing building, the
ground for an empty site. :func:`height_profile` measures that agreement
(the mean normalised cross-correlation over pairs of views of the interior's
intensities) at each height of a sweep; :func:`stands` reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import shapely

from obliq_colmap.geometry import PIXEL_CENTER_OFFSET, Camera, Pose
from obliq_colmap.products.discrepancy_options import DiscrepancyOptions

__all__ = [
    "RoofView",
    "agreement",
    "empty_site",
    "footprint_samples",
    "height_profile",
    "patch_pixels",
    "roof_height",
    "roof_heights",
    "sample_image",
    "stacked_agreement",
    "stands",
    "view_samples",
    "views_seeing",
]


@dataclass
class RoofView:
    """One image for the sweep: blurred grey (float32), camera, pose, and
    the image file (for the full-resolution edges of :mod:`.missing`)."""

    gray: np.ndarray
    camera: Camera
    pose: Pose
    path: Path | None = None


def views_seeing(views: list[RoofView], xyz: np.ndarray) -> np.ndarray:
    """(V, N) bool: view v has point n of ``xyz`` (N, 3) in front and inside."""
    out = np.zeros((len(views), len(xyz)), bool)
    for i, v in enumerate(views):
        Xc = v.pose.transform(xyz)
        q = v.camera.img_from_cam(Xc)
        h, w = v.gray.shape
        inside = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
        out[i] = (Xc[:, 2] > 0) & inside
    return out


def blurred(gray: np.ndarray, sigma_px: float) -> np.ndarray:
    """The image smoothed so that a sweep step's residual misalignment
    (about a pixel) does not decorrelate pixel-scale texture."""
    return cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma_px)


def footprint_samples(
    polygon, step_m: float, inset_m: float, max_points: int
) -> np.ndarray:
    """(P, 2) grid points inside ``polygon`` at least ``inset_m`` from its
    outline (the roof's rim, parapets and overhangs are left out: they are
    not at one height), at most ``max_points`` (a regular thinning)."""
    inner = polygon.buffer(-inset_m)
    if inner.is_empty:
        return np.zeros((0, 2))
    x0, y0, x1, y1 = inner.bounds
    gx, gy = np.meshgrid(np.arange(x0, x1, step_m), np.arange(y0, y1, step_m))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xy = xy[shapely.contains_xy(inner, xy[:, 0], xy[:, 1])]
    if len(xy) > max_points:
        xy = xy[np.linspace(0, len(xy) - 1, max_points).astype(int)]
    return xy


def height_profile(
    views: list[RoofView],
    xy: np.ndarray,
    z: np.ndarray,
    min_inside: float = 0.9,
) -> tuple[np.ndarray, np.ndarray]:
    """Agreement of the views at each height.

    Parameters
    ----------
    xy : (P, 2) points on the footprint; z : (H,) heights swept (model frame).
    min_inside : a view counts at a height when this share of the points
        projects into it there (a tall sweep leaves the image at its top).

    Returns
    -------
    ncc : (H,) mean NCC over pairs of views of the points' intensities
        (NaN where fewer than 2 views count); views : (H,) int, how many.
    """
    H, P = len(z), len(xy)
    X = np.empty((H, P, 3))
    X[..., :2] = xy[None]
    X[..., 2] = z[:, None]
    samples = []
    for v in views:
        Xc = v.pose.transform(X.reshape(-1, 3))
        q = v.camera.img_from_cam(Xc).reshape(H, P, 2)
        samples.append(view_samples(v, q, Xc[:, 2].reshape(H, P) > 0, min_inside))
    return agreement(samples, H)


def sample_image(gray: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Bilinear values (..., P) of ``gray`` at pixels ``q`` (..., P, 2),
    COLMAP's convention (pixel centres at +0.5; OpenCV's at the integers),
    borders replicated. ``cv2.remap`` takes maps below 32,767 rows and
    columns: the rows go in chunks (P, a patch's or a roof cell's samples,
    is far below it)."""
    P = q.shape[-2]
    mx = (q[..., 0] - PIXEL_CENTER_OFFSET).astype(np.float32).reshape(-1, P)
    my = (q[..., 1] - PIXEL_CENTER_OFFSET).astype(np.float32).reshape(-1, P)
    rows = 32000
    out = [
        cv2.remap(
            gray,
            mx[i : i + rows],
            my[i : i + rows],
            cv2.INTER_LINEAR,
            cv2.BORDER_REPLICATE,
        )
        for i in range(0, len(mx), rows)
    ]
    return np.concatenate(out).reshape(q.shape[:-1])


def patch_pixels(
    view: RoofView, centres: np.ndarray, offsets: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of small horizontal patches in one view: patch n is the points
    ``centres[n]`` (N, 2) + ``offsets`` (P, 2) at the heights ``z[n]``
    (N, H). Returns (N, H, P, 2) float32 pixels (COLMAP's convention) and
    (N, H) bool, the patch's centre in front of the camera.

    A patch of a metre or a few seen from hundreds of metres projects as an
    affine image of itself (the perspective's and the lens's second-order
    terms move its corners by a few hundredths of a pixel): only each
    centre and its derivatives (central differences, 5 points) go through
    the camera model.
    """
    N, H = z.shape
    d = max(float(np.abs(offsets).max()), 1e-3)
    steps = np.array([[0, 0], [d, 0], [-d, 0], [0, d], [0, -d]], float)
    X = np.empty((N, H, 5, 3))
    X[..., :2] = centres[:, None, None] + steps
    X[..., 2] = z[:, :, None]
    Xc = view.pose.transform(X.reshape(-1, 3))
    q5 = view.camera.img_from_cam(Xc).reshape(N, H, 5, 2)
    J = np.stack([q5[..., 1, :] - q5[..., 2, :], q5[..., 3, :] - q5[..., 4, :]], -1)
    J /= 2 * d  # (N, H, 2 pixel axes, 2 ground axes)
    # float32: a few 1e-4 px at 2,000 px, half the memory traffic
    q = q5[..., None, 0, :].astype(np.float32) + offsets.astype(
        np.float32
    ) @ np.swapaxes(J, -1, -2).astype(np.float32)
    return q, Xc[:, 2].reshape(N, H, 5)[..., 0] > 0


def view_samples(
    view: RoofView, q: np.ndarray, front: np.ndarray, min_inside: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """One view's intensities at pixels ``q`` (..., H, P, 2) (COLMAP's
    convention) of points in front of it where ``front`` (..., H, P):
    ((..., H, P) values, NaN where the view does not count; (..., H) bool,
    the heights at which at least ``min_inside`` of the points fall inside
    the image); None where it counts at no height."""
    h, w = view.gray.shape
    ok = (
        front
        & (q[..., 0] >= 0)
        & (q[..., 0] <= w - 1)
        & (q[..., 1] >= 0)
        & (q[..., 1] <= h - 1)
    )
    counts = ok.mean(axis=-1) >= min_inside  # (..., H)
    if not counts.any():
        return None
    vals = sample_image(view.gray, q)
    return np.where(ok & counts[..., None], vals, np.nan), counts


def agreement(
    samples: list[tuple[np.ndarray, np.ndarray] | None], n_heights: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`height_profile`'s (ncc (H,), views (H,)) from each view's
    :func:`view_samples` at ``n_heights`` (H) heights."""
    kept = [s for s in samples if s is not None]
    if len(kept) < 2:
        return np.full(n_heights, np.nan), np.zeros(n_heights, int)
    return stacked_agreement(
        np.stack([s[0] for s in kept]), np.stack([s[1] for s in kept])
    )


def stacked_agreement(A: np.ndarray, used: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ncc (..., H), views (..., H)) of the views' values ``A`` (..., V,
    H, P) (NaN where a view does not count) that count where ``used``
    (..., V, H): the mean NCC over ordered pairs of views."""
    n = used.sum(axis=-2)  # (..., H)
    # each view's intensities normalised (exposure and shading differ)
    valid = ~np.isnan(A)
    A = np.where(valid, A, 0.0)
    count = np.maximum(valid.sum(axis=-1, keepdims=True), 1)
    A -= A.sum(axis=-1, keepdims=True) / count
    A *= valid
    norm = np.sqrt(np.einsum("...p,...p->...", A, A))[..., None]
    A /= norm + 1e-9
    s = A.sum(axis=-3)  # (..., H, P)
    # sum over ordered pairs of <a_u, a_v> = |sum a|^2 - sum |a|^2, each
    # |a|^2 being 1 (0 for a view without contrast there)
    self_dot = ((norm / (norm + 1e-9)) ** 2).sum(axis=(-3, -1))
    ncc = (np.einsum("...p,...p->...", s, s) - self_dot) / np.maximum(n * (n - 1), 1)
    return np.where(n >= 2, ncc, np.nan), n


def stands(
    profile: np.ndarray,
    views: np.ndarray,
    above_ground: np.ndarray,
    min_height_m: float,
    min_views: int,
) -> bool:
    """The views agree best on a surface at least ``min_height_m`` above
    the ground, and at least ``min_views`` of them see it there: something
    stands on the footprint. An empty site agrees best at the ground; with
    too few views the profile is noise."""
    if not np.isfinite(profile).any():
        return False
    k = int(np.nanargmax(profile))
    return bool(above_ground[k] >= min_height_m and views[k] >= min_views)


def empty_site(
    profile: np.ndarray,
    views: np.ndarray,
    above_ground: np.ndarray,
    min_height_m: float,
    min_views: int,
) -> bool:
    """The views agree best below ``min_height_m`` (at the ground), at
    least ``min_views`` of them: nothing stands on the footprint."""
    if not np.isfinite(profile).any():
        return False
    k = int(np.nanargmax(profile))
    return bool(above_ground[k] < min_height_m and views[k] >= min_views)


def roof_height(
    profile: np.ndarray,
    views: np.ndarray,
    above_ground: np.ndarray,
    min_height_m: float,
    min_views: int,
) -> float:
    """The height above the ground (m) at which the views agree best, where
    something stands there (:func:`stands`); NaN otherwise."""
    if not stands(profile, views, above_ground, min_height_m, min_views):
        return float("nan")
    return float(above_ground[int(np.nanargmax(profile))])


def roof_heights(
    polygons: list,
    ground_z: np.ndarray,
    ask: np.ndarray,
    views: list[RoofView],
    up: np.ndarray,
    options: DiscrepancyOptions,
) -> np.ndarray:
    """(B,) :func:`roof_height` of the footprints where ``ask`` (B,) bool,
    a sweep of ``up`` (H,) heights above each one's ``ground_z`` (B,) over
    at most ``top_sweep_points`` interior points (:func:`footprint_samples`
    with ``sweep_grid_m``, ``sweep_inset_m``); NaN elsewhere, where fewer
    than ``stand_views`` views see the footprint's centre, or where nothing
    stands on it (``stand_height_m``)."""
    out = np.full(len(polygons), np.nan)
    ask = np.asarray(ask) & np.isfinite(ground_z)
    if not ask.any():
        return out
    cen = np.array([p.centroid.coords[0] for p in polygons]).reshape(-1, 2)
    # only the views that see the footprint's centre at the bottom, the
    # middle or the top of the sweep take part (the sweep's cost is the
    # projection of every height's points into every view; a tower's roof
    # is seen from views whose image ends before its foot)
    sees = np.zeros((len(views), len(polygons)), bool)
    for dz in (up[0], up[len(up) // 2], up[-1]):
        z = np.where(ask, ground_z + dz, 0.0)
        sees |= views_seeing(views, np.column_stack([cen, z]))
    o = options
    for b in np.flatnonzero(ask & (sees.sum(axis=0) >= o.stand_views)):
        xy = footprint_samples(
            polygons[b], o.sweep_grid_m, o.sweep_inset_m, o.top_sweep_points
        )
        if len(xy) == 0:
            continue
        vb = [views[i] for i in np.flatnonzero(sees[:, b])]
        ncc, n = height_profile(vb, xy, ground_z[b] + up)
        out[b] = roof_height(ncc, n, up, o.stand_height_m, o.stand_views)
    return out
