"""The open ground the views see: a height sweep of small patches between
the buildings.

The map corners' ground heights carry the terrain without the images, each
good to ~0.3 m: a corner's vertical edge ends where the ground's contrast
lets it, and cars, hedges and shadows sit at the feet of walls. The open
ground between the buildings (streets, yards, lawns, parking lots) is seen
by several views at once, from different heads: the views agree on a
patch's texture only at the ground's height (:func:`patch_profiles`),
and the parallax across heads (a metre of height moves a point by metres
between opposite heads) puts that height within about a tenth of a metre.
Patches on a car, a tree crown or a building the map lacks agree higher, or
nowhere; the terrain's robust fit leaves them out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy.spatial import cKDTree

from obliq_colmap.geometry import parabola_peak
from obliq_colmap.products.roof import (
    RoofView,
    patch_pixels,
    stacked_agreement,
    view_samples,
    views_seeing,
)

__all__ = ["GroundOptions", "ground_samples", "patch_profiles"]


@dataclass
class GroundOptions:
    """Options of :func:`ground_samples`."""

    #: measure the open ground with the images (``export_products
    #: --image_path``); else the terrain comes from the map corners only.
    enabled: bool = True
    #: patch centres on a grid of this step (m): where the open ground is
    #: narrow (courtyards and streets between tall blocks) a coarser grid
    #: leaves it unsampled; ~10,000 patches for a block of 36 images.
    step_m: float = 5.0
    #: a patch keeps this far from every footprint (m): walls, eaves and
    #: the feet's clutter are not ground.
    clearance_m: float = 2.0
    #: the patch: a square of this side (m) sampled every ``grid_m``, about
    #: 1.5 pixels at 0.15 m/px.
    size_m: float = 3.0
    grid_m: float = 0.25
    #: heights swept about the corners' terrain (m), in ``step_z_m``: the
    #: corners' surface is good to a few tenths.
    search_m: float = 2.0
    step_z_m: float = 0.1
    #: a patch is ground where at least ``min_views`` views agree best
    #: inside the sweep with a mean NCC of at least ``min_ncc`` (smooth
    #: asphalt and shade agree weakly at any height).
    min_ncc: float = 0.5
    min_views: int = 3

    def __post_init__(self) -> None:
        if min(self.step_m, self.size_m, self.grid_m, self.step_z_m) <= 0:
            raise ValueError("step_m, size_m, grid_m, step_z_m > 0")
        if self.search_m < 2 * self.step_z_m or self.min_views < 2:
            raise ValueError("search_m >= 2 step_z_m, min_views >= 2")


def patch_centres(
    polygons: list,
    corners_xy: np.ndarray,
    max_distance_m: float,
    options: GroundOptions,
) -> np.ndarray:
    """(N, 2) grid points within ``max_distance_m`` of a map corner
    (``corners_xy`` (C, 2)) and ``clearance_m`` clear of every footprint."""
    lo, hi = corners_xy.min(axis=0), corners_xy.max(axis=0)
    gx, gy = np.meshgrid(
        np.arange(lo[0], hi[0] + 1e-9, options.step_m),
        np.arange(lo[1], hi[1] + 1e-9, options.step_m),
    )
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    d, _ = cKDTree(corners_xy).query(xy, distance_upper_bound=max_distance_m)
    xy = xy[np.isfinite(d)]
    if len(polygons):
        blocked = shapely.unary_union(polygons).buffer(options.clearance_m)
        xy = xy[~shapely.contains_xy(blocked, xy[:, 0], xy[:, 1])]
    return xy


def patch_profiles(
    views: list[RoofView],
    sees: np.ndarray,
    centres: np.ndarray,
    offsets: np.ndarray,
    z: np.ndarray,
    min_inside: float = 0.9,
    chunk: int = 128,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`.roof.height_profile` of many small horizontal patches at
    once: patch n is the points ``centres[n]`` + ``offsets`` (P, 2) at the
    heights ``z[n]`` (N, H), read in the views where ``sees`` (V, N).

    Each view reads the patches of a chunk it sees in one ``remap``, at
    pixels projected affinely (:func:`.roof.patch_pixels`).

    Returns
    -------
    ncc : (N, H) mean NCC over pairs of views (NaN where < 2 count);
    views : (N, H) int, how many views count.
    """
    N, H, P = len(centres), z.shape[1], len(offsets)
    ncc, nviews = np.full((N, H), np.nan), np.zeros((N, H), int)
    # the chunk's values (patches x views x heights x points, float32) held
    # to ~64 MB where many views see a patch (a long block, a dense flight)
    most = int(sees.sum(axis=0).max()) if sees.size else 0
    chunk = int(np.clip(64e6 / (4 * max(most, 1) * H * P), 1, chunk))
    for start in range(0, N, chunk):
        idx = np.arange(start, min(N, start + chunk))
        S = sees[:, idx]  # (V, B)
        n_slots = int(S.sum(axis=0).max()) if S.size else 0
        if n_slots < 2:
            continue
        slot = np.cumsum(S, axis=0) - 1  # the view's place among the patch's
        A = np.full((len(idx), n_slots, H, P), np.nan, np.float32)
        used = np.zeros((len(idx), n_slots, H), bool)
        for v in np.flatnonzero(S.any(axis=1)):
            b = np.flatnonzero(S[v])
            q, front = patch_pixels(views[v], centres[idx[b]], offsets, z[idx[b]])
            front = np.broadcast_to(front[..., None], q.shape[:-1])
            read = view_samples(views[v], q, front, min_inside)
            if read is not None:
                A[b, slot[v, b]], used[b, slot[v, b]] = read
        ncc[idx], nviews[idx] = stacked_agreement(A, used)
    return ncc, nviews


def ground_samples(
    polygons: list,
    corners_xy: np.ndarray,
    terrain,
    views: list[RoofView],
    max_distance_m: float,
    options: GroundOptions,
) -> np.ndarray:
    """(S, 3) ground points (local frame): per patch the height at which
    the views agree best, refined between the sweep's steps.

    Parameters
    ----------
    polygons : the footprints; corners_xy : (C, 2) the map corners the
        terrain was measured at; terrain : function (M, 2) -> (M,), the
        corners' terrain the sweep is centred on.
    """
    cen = patch_centres(polygons, corners_xy, max_distance_m, options)
    if len(cen) == 0:
        return np.zeros((0, 3))
    z0 = terrain(cen)
    sees = views_seeing(views, np.column_stack([cen, z0]))
    half = options.size_m / 2
    u = np.arange(-half, half + 1e-9, options.grid_m)
    patch = np.stack(np.meshgrid(u, u), axis=-1).reshape(-1, 2)
    dz = np.arange(-options.search_m, options.search_m + 1e-9, options.step_z_m)
    swept = np.flatnonzero(sees.sum(axis=0) >= options.min_views)
    ncc, n = patch_profiles(
        views, sees[:, swept], cen[swept], patch, z0[swept, None] + dz
    )
    out = []
    for i, profile, views_at in zip(swept, ncc, n, strict=True):
        if not np.isfinite(profile).any():
            continue
        k = int(np.nanargmax(profile))
        # a peak at the sweep's end is no peak: the ground lies outside
        inside = 0 < k < len(dz) - 1
        if (
            not inside
            or profile[k] < options.min_ncc
            or views_at[k] < options.min_views
        ):
            continue
        near = slice(k - 1, k + 2)
        out.append((*cen[i], z0[i] + parabola_peak(dz[near], profile[near])))
    return np.array(out).reshape(-1, 3)
