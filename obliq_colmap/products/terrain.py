"""The terrain height grid from a registration's constraints (paper, sec. 4).

Two kinds of constraint carry the terrain. The map corners at their ground
heights: where stage 2 matched a corner's vertical edge, the median over
those images of where the edge's bottom meets the corner's vertical through
the final pose, else a local plane through the measured corners
(``pipeline.output._corner_ground``); dense (every mapped corner) and good
to ~0.3 m each, but a segment ends where the ground's contrast lets it, so
their datum can sit a few tenths off the bundle's. And the facade tracks
that run along a wall's foot (a horizontal edge where the wall meets the
ground, height ``h_j`` from the bundle, in the same datum as the eaves),
sparse and hidden behind cars and trees. With the images, the open ground
the views agree on joins the corners (:mod:`.ground`), each kind weighted
by its own scatter. The grid's shape comes from these (a robust quadratic
refined by the Gaussian-weighted mean of their residuals); its datum from
the feet among the tracks near it (a mixture
that tells the feet from the lines just above them, :func:`foot_offset`),
so that eave heights above it are measured in one datum.

Heights are in the result model's vertical datum (the priors', see
``georef.json``): ``z_abs = z_local + origin[2]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

__all__ = [
    "TerrainGrid",
    "TerrainOptions",
    "estimate_terrain",
    "robust_surface",
    "feet_datum",
    "foot_offset",
]

logger = logging.getLogger(__name__)

#: samples the quadratic surface needs (:func:`robust_surface`)
_QUADRATIC = 12


@dataclass
class TerrainOptions:
    """Options of :func:`estimate_terrain`."""

    #: grid cell size (m).
    cell_size_m: float = 5.0
    #: cells farther than this from every ground sample are NODATA (m).
    max_distance_m: float = 20.0
    #: the facade tracks within this of the corners' surface (m) are the
    #: walls' feet and the lines just above them (:func:`foot_offset`): the
    #: corners' datum is a few tenths off, floors are >= 2.5 m up.
    foot_window_m: float = 1.5
    #: the feet's sd about the corners' surface is searched among these (m):
    #: the tracks' own noise (~0.05 m) up to the surface's local error.
    foot_sd_m: tuple[float, ...] = (0.05, 0.08, 0.12, 0.17, 0.25, 0.35)
    #: tracks within ``foot_window_m`` needed to move the corners' surface
    #: into the tracks' datum.
    min_feet: int = 12
    #: Gaussian sigma of the corners' correction to their quadratic (m): the
    #: terrain of a town varies over hundreds of metres; 10 / 20 / 30 m gave
    #: 0.46 / 0.38 / 0.37 m on houses-102, 0.43 / 0.39 / 0.38 on urban-101.
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


def robust_surface(
    xy: np.ndarray,
    z: np.ndarray,
    sigmas: float = 2.5,
    rounds: int = 5,
    weights: np.ndarray | None = None,
):
    """A quadratic surface z(x, y) fitted with iterative outlier rejection.

    Parameters
    ----------
    xy : (N, 2); z : (N,); weights : (N,) inverse variances relative to a
        unit-weight sample (None: all 1).

    Returns
    -------
    A function (M, 2) -> (M,), and the robust sigma of the unit-weight
    residuals (m).
    """
    scale = max(float(np.ptp(xy)) if len(xy) else 1.0, 1.0)
    A = _design(xy, scale)
    # fewer points than monomials: a plane or a constant.
    ncol = 6 if len(z) >= _QUADRATIC else (3 if len(z) >= 3 else 1)
    A = A[:, :ncol]
    sw = np.ones(len(z)) if weights is None else np.sqrt(weights)
    keep = np.ones(len(z), bool)
    coef, sigma = np.zeros(ncol), 0.0
    for _ in range(rounds):
        coef = np.linalg.lstsq(
            A[keep] * sw[keep, None], z[keep] * sw[keep], rcond=None
        )[0]
        r = (z - A @ coef) * sw
        sigma = max(1.4826 * float(np.median(np.abs(r[keep]))), 0.05)
        keep = np.abs(r) <= sigmas * sigma

    def surface(q: np.ndarray) -> np.ndarray:
        return _design(q, scale)[:, :ncol] @ coef

    return surface, sigma


def _smoothed(
    samples: np.ndarray,
    values: np.ndarray,
    query: np.ndarray,
    sigma: float,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-weighted mean of ``values`` (N,) at samples (N, 2) for query
    points (M, 2), truncated at 3 sigma, each sample also weighted by
    ``weights`` (N,): (M,) mean (0 without samples) and (M,) weight sum."""
    if len(samples) == 0:
        return np.zeros(len(query)), np.zeros(len(query))
    D = cKDTree(query).sparse_distance_matrix(
        cKDTree(samples), 3.0 * sigma, output_type="coo_matrix"
    )
    w = np.exp(-0.5 * (D.data / sigma) ** 2)
    if weights is not None:
        w = w * weights[D.col]
    wsum = np.bincount(D.row, w, len(query))
    wv = np.bincount(D.row, w * values[D.col], len(query))
    return np.where(wsum > 0, wv / np.maximum(wsum, 1e-12), 0.0), wsum


def _mixture_fit(
    r: np.ndarray, mu: np.ndarray, window_m: float, sigmas_m, iterations: int
) -> tuple[float, float]:
    """(log-likelihood, offset) of :func:`foot_offset`'s mixture, best over
    the offsets ``mu`` (M,) and the sds ``sigmas_m``."""
    d = r[None, :] - mu[:, None]  # (M, N)
    best = (-np.inf, 0.0)
    for s in sigmas_m:
        dens = np.stack(
            [
                norm.pdf(d, scale=s),
                (norm.cdf(d / s) - norm.cdf((d - window_m) / s)) / window_m,
                np.full_like(d, 0.5 / window_m),
            ]
        )  # (3, M, N)
        # the weights' start (feet, lines above, wrong): EM moves them
        w = np.repeat(np.array([[0.5], [0.4], [0.1]]), len(mu), axis=1)  # (3, M)
        for _ in range(iterations):
            like = np.einsum("km,kmn->mn", w, dens) + 1e-300
            w = (w[:, :, None] * dens / like).mean(axis=2)
        ll = np.log(np.einsum("km,kmn->mn", w, dens) + 1e-300).sum(axis=1)
        k = int(np.argmax(ll))
        if ll[k] > best[0]:
            best = (float(ll[k]), float(mu[k]))
    return best


def foot_offset(
    r: np.ndarray,
    window_m: float,
    sigmas_m: tuple[float, ...],
    iterations: int = 30,
    max_samples: int = 4000,
) -> float:
    """Where the wall feet lie among residuals ``r`` (N,) about a ground
    surface, all within ``window_m`` of it: the maximum-likelihood offset of
    a mixture of the feet (normal, sd one of ``sigmas_m``), the lines just
    above a wall's foot (plinths, sills, fences, parked cars: uniform from
    the feet up to ``window_m`` above them, blurred alike) and wrong tracks
    (uniform over the window). The lines above make the window's median a
    few tenths too high where the feet are few; nothing lies below a foot.

    The offset is searched on a 5 cm grid, then on 1 cm about the best; at
    each (offset, sd) the three weights by EM. More than ``max_samples``
    residuals are thinned to as many of their quantiles (time and memory
    grow with offsets x residuals).
    """
    if len(r) > max_samples:
        r = np.sort(r)[np.linspace(0, len(r) - 1, max_samples).astype(int)]
    coarse = np.arange(-window_m, window_m + 1e-9, 0.05)
    _, m0 = _mixture_fit(r, coarse, window_m, sigmas_m, iterations)
    fine = m0 + np.arange(-0.05, 0.05 + 1e-9, 0.01)
    return _mixture_fit(r, fine, window_m, sigmas_m, iterations)[1]


def feet_datum(
    facade_xyz: np.ndarray,
    terrain,
    window_m: float,
    min_feet: int,
    sigmas_m: tuple[float, ...] = TerrainOptions.foot_sd_m,
) -> tuple[float, int]:
    """The offset (m) that moves ``terrain`` onto the wall-foot tracks among
    ``facade_xyz`` (F, 3): :func:`foot_offset` of the tracks within
    ``window_m`` of it; 0 with fewer than ``min_feet`` such tracks. Returns
    (offset, tracks in the window)."""
    if len(facade_xyz) == 0:
        return 0.0, 0
    r = facade_xyz[:, 2] - terrain(facade_xyz[:, :2])
    near = np.abs(r) <= window_m
    if near.sum() < min_feet:
        return 0.0, 0
    return foot_offset(r[near], window_m, sigmas_m), int(near.sum())


def _mad(r: np.ndarray) -> float:
    """Robust sd (m) of residuals ``r`` (N,), at least 1 cm."""
    return max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 0.01)


def _shape(pts: np.ndarray, w: np.ndarray, options: TerrainOptions):
    """(shape (M, 2) -> (M,), sigma, (N,) bool samples kept): the robust
    quadratic through ``pts`` (N, 3) weighted by ``w`` (N,), refined by the
    Gaussian-weighted mean of the kept samples' residuals."""
    surface, sigma = robust_surface(
        pts[:, :2], pts[:, 2], options.outlier_sigmas, weights=w
    )
    r = pts[:, 2] - surface(pts[:, :2])
    used = np.abs(r) * np.sqrt(w) <= options.outlier_sigmas * sigma
    xy, r, wk = pts[used, :2], r[used], w[used]
    # With few samples nearby the correction shrinks towards the surface (one
    # pseudo-sample of unit weight at residual 0).
    prior_weight = 1.0

    def shape(q: np.ndarray) -> np.ndarray:
        mean, wsum = _smoothed(xy, r, q, options.smoothing_m, wk)
        return surface(q) + mean * wsum / (wsum + prior_weight)

    return shape, sigma, used


def estimate_terrain(
    ground_xyz: np.ndarray,
    facade_xyz: np.ndarray,
    options: TerrainOptions,
    image_ground: np.ndarray | None = None,
):
    """The terrain as a function of (x, y), and the ground samples it used.

    Parameters
    ----------
    ground_xyz : (G, 3) map corners at their ground heights, local frame.
    facade_xyz : (F, 3) facade track points.
    image_ground : (S, 3) ground points the views agree on
        (:func:`.ground.ground_samples`); with enough of them for the
        surface, they join the corners, each kind weighted by its scatter
        about their common shape.

    Returns
    -------
    terrain : function (M, 2) -> (M,) heights.
    samples : (S, 2) the positions of the corners it used, for the NODATA
        mask.
    """
    if len(ground_xyz) == 0:
        raise ValueError("no ground corner to estimate the terrain from")
    from_images = image_ground is not None and len(image_ground) >= _QUADRATIC
    pts = np.vstack([ground_xyz, image_ground]) if from_images else ground_xyz
    kind = np.repeat([0, 1], [len(ground_xyz), len(pts) - len(ground_xyz)])
    shape, sigma, used = _shape(pts, np.ones(len(pts)), options)
    if from_images:
        # each kind weighted by its own scatter about the common shape (the
        # views' ground is the sharper on textured ground, not on all)
        r = pts[:, 2] - shape(pts[:, :2])
        sd = np.array([_mad(r[kind == k]) for k in (0, 1)])
        shape, sigma, used = _shape(pts, (sd[0] / sd[kind]) ** 2, options)
        logger.info(
            "terrain: corners %.2f m, ground the views agree on %.2f m about it",
            *sd,
        )
    xy = pts[used & (kind == 0), :2]
    mask_xy = ground_xyz[:, :2] if from_images else xy

    # The eaves are measured against this ground: it must be in the tracks'
    # datum, which the feet give (the corners' datum sits a few tenths off
    # it, either way).
    offset, n_feet = feet_datum(
        facade_xyz, shape, options.foot_window_m, options.min_feet, options.foot_sd_m
    )
    logger.info(
        "terrain: %d samples (sd %.2f m about their quadratic), moved %+.2f m "
        "onto the wall feet among %d tracks near it",
        int(used.sum()),
        sigma,
        offset,
        n_feet,
    )

    def terrain(q: np.ndarray) -> np.ndarray:
        return shape(q) + offset

    return terrain, mask_xy


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
