"""The terrain height grid from a registration's constraints (paper, sec. 4).

Two kinds of constraint carry the terrain: the map corners at their ground
heights (each the mean of the ground planes of the images that used the
corner: smooth, but only as detailed as one plane per image), and the facade
tracks that run along a wall's foot (a horizontal edge where the wall meets
the ground, height ``h_j`` from the bundle, in the same datum as the eaves).
The grid is a robust low-order surface through the corners, refined by the
foot-of-wall tracks near it (Gaussian-weighted mean of their residuals).

Heights are in the result model's vertical datum (the priors', see
``georef.json``): ``z_abs = z_local + origin[2]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "TerrainGrid",
    "TerrainOptions",
    "estimate_terrain",
    "robust_surface",
    "foot_tracks",
]

logger = logging.getLogger(__name__)


@dataclass
class TerrainOptions:
    """Options of :func:`estimate_terrain`."""

    #: grid cell size (m).
    cell_size_m: float = 5.0
    #: cells farther than this from every ground sample are NODATA (m).
    max_distance_m: float = 20.0
    #: a facade track within this of the corners' surface is a wall's foot
    #: (m): the corners' surface is ~0.2-0.5 m off, floors are >= 2.5 m up.
    foot_window_m: float = 1.5
    #: Gaussian sigma of the foot tracks' correction (m); the terrain of a
    #: town varies over hundreds of metres, a wall's foot is noisy.
    smoothing_m: float = 30.0
    #: residuals beyond this many robust sigmas are dropped.
    outlier_sigmas: float = 2.5

    def __post_init__(self) -> None:
        for name in ("cell_size_m", "max_distance_m", "foot_window_m", "smoothing_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")


@dataclass
class TerrainGrid:
    """A height grid, LOCAL frame. Cell (row r, column c) has its centre at
    ``(x0 + (c + 0.5) * cell, y0 + (ny - r - 0.5) * cell)``: row 0 is north,
    as in an ESRI ASCII grid. ``Z``: (ny, nx), NaN where not constrained."""

    x0: float
    y0: float
    cell: float
    Z: np.ndarray

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(ny, nx) x and y of the cell centres."""
        ny, nx = self.Z.shape
        xs = self.x0 + (np.arange(nx) + 0.5) * self.cell
        ys = self.y0 + (ny - np.arange(ny) - 0.5) * self.cell
        return np.meshgrid(xs, ys)


def _design(xy: np.ndarray, scale: float) -> np.ndarray:
    """(N, 6) quadratic monomials of (N, 2) points scaled by ``scale``."""
    x, y = xy[:, 0] / scale, xy[:, 1] / scale
    return np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])


def robust_surface(xy: np.ndarray, z: np.ndarray, sigmas: float = 2.5, rounds: int = 5):
    """A quadratic surface z(x, y) fitted with iterative outlier rejection.

    Parameters
    ----------
    xy : (N, 2); z : (N,).

    Returns
    -------
    A function (M, 2) -> (M,), and the robust sigma of the residuals (m).
    """
    scale = max(float(np.ptp(xy)) if len(xy) else 1.0, 1.0)
    A = _design(xy, scale)
    # fewer points than monomials: a plane or a constant.
    ncol = 6 if len(z) >= 12 else (3 if len(z) >= 3 else 1)
    A = A[:, :ncol]
    keep = np.ones(len(z), bool)
    coef, sigma = np.zeros(ncol), 0.0
    for _ in range(rounds):
        coef = np.linalg.lstsq(A[keep], z[keep], rcond=None)[0]
        r = z - A @ coef
        sigma = max(1.4826 * float(np.median(np.abs(r[keep]))), 0.05)
        keep = np.abs(r) <= sigmas * sigma

    def surface(q: np.ndarray) -> np.ndarray:
        return _design(q, scale)[:, :ncol] @ coef

    return surface, sigma


def foot_tracks(facade_xyz: np.ndarray, surface, window_m: float) -> np.ndarray:
    """(F,) bool: facade points (F, 3) within ``window_m`` of ``surface``."""
    if len(facade_xyz) == 0:
        return np.zeros(0, bool)
    return np.abs(facade_xyz[:, 2] - surface(facade_xyz[:, :2])) <= window_m


def _smoothed(
    samples: np.ndarray, values: np.ndarray, query: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-weighted mean of ``values`` (N,) at samples (N, 2) for query
    points (M, 2), truncated at 3 sigma: (M,) mean (0 without samples) and
    (M,) weight sum."""
    if len(samples) == 0:
        return np.zeros(len(query)), np.zeros(len(query))
    D = cKDTree(query).sparse_distance_matrix(
        cKDTree(samples), 3.0 * sigma, output_type="coo_matrix"
    )
    w = np.exp(-0.5 * (D.data / sigma) ** 2)
    wsum = np.bincount(D.row, w, len(query))
    wv = np.bincount(D.row, w * values[D.col], len(query))
    return np.where(wsum > 0, wv / np.maximum(wsum, 1e-12), 0.0), wsum


def estimate_terrain(
    ground_xyz: np.ndarray, facade_xyz: np.ndarray, options: TerrainOptions
):
    """The terrain as a function of (x, y), and the ground samples it used.

    Parameters
    ----------
    ground_xyz : (G, 3) map corners at their ground heights, local frame.
    facade_xyz : (F, 3) facade track points.

    Returns
    -------
    terrain : function (M, 2) -> (M,) heights.
    samples : (S, 2) the positions of the wall-foot tracks it used (of the
        ground corners where fewer than 12 feet), for the NODATA mask.
    """
    if len(ground_xyz) == 0:
        raise ValueError("no ground corner to estimate the terrain from")
    # The corners' heights come from per-image ground planes, which the
    # bundle does not move: their datum can sit ~1 m off the tracks'. They
    # only find the feet; the feet (in the eaves' datum) make the terrain.
    surface, sigma = robust_surface(ground_xyz[:, :2], ground_xyz[:, 2])
    window = options.foot_window_m
    feet = np.zeros((0, 3))
    for _ in range(3):
        feet = facade_xyz[foot_tracks(facade_xyz, surface, window)]
        if len(feet) < 12:
            break
        surface, sigma = robust_surface(feet[:, :2], feet[:, 2], options.outlier_sigmas)
        window = max(options.outlier_sigmas * sigma, 0.5)
    r = feet[:, 2] - surface(feet[:, :2])
    ok = np.abs(r) <= options.outlier_sigmas * sigma
    feet, r = feet[ok], r[ok]
    logger.info(
        "terrain: %d wall-foot tracks (sd %.2f m about their surface), %d corners",
        len(feet),
        sigma,
        len(ground_xyz),
    )
    # With few feet nearby the correction shrinks towards the surface (one
    # pseudo-sample of weight 1 at residual 0).
    prior_weight = 1.0

    def terrain(q: np.ndarray) -> np.ndarray:
        mean, wsum = _smoothed(feet[:, :2], r, q, options.smoothing_m)
        return surface(q) + mean * wsum / (wsum + prior_weight)

    # Only the feet hold the grid in the eaves' datum: cells far from every
    # foot are left NODATA (the corners alone are ~1 m off, see above).
    samples = feet[:, :2] if len(feet) >= 12 else ground_xyz[:, :2]
    return terrain, samples


def terrain_grid(terrain, samples: np.ndarray, options: TerrainOptions) -> TerrainGrid:
    """Sample ``terrain`` on a grid covering ``samples`` (S, 2) plus
    ``max_distance_m``; cells farther than that from every sample are NaN."""
    c, pad = options.cell_size_m, options.max_distance_m
    lo = np.floor((samples.min(axis=0) - pad) / c) * c
    hi = np.ceil((samples.max(axis=0) + pad) / c) * c
    nx, ny = int(round((hi[0] - lo[0]) / c)), int(round((hi[1] - lo[1]) / c))
    grid = TerrainGrid(float(lo[0]), float(lo[1]), c, np.zeros((ny, nx)))
    X, Y = grid.centres()
    q = np.column_stack([X.ravel(), Y.ravel()])
    d, _ = cKDTree(samples).query(q, distance_upper_bound=pad)
    z = np.full(len(q), np.nan)
    near = np.isfinite(d)
    z[near] = terrain(q[near])
    grid.Z = z.reshape(ny, nx)
    return grid
