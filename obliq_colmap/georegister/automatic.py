"""The automatic mode's geometry: the whole upright block onto the map.

With the model upright (its vertical from the VPs), a vertical image segment
through the VP back-projects to a VERTICAL plane through the camera centre;
seen from above it is a ray from the camera's xy along a bearing, and the
map corner the segment images lies on it. So the block's placement is a 2D
problem with four unknowns, the similarity ``p = s R(theta) q + t`` from
the model's xy to the map's (MetropoGIS 3.3-3.4; the oblique paper's stage 2
for a whole block at once), fixed by the corner-to-ray pairs of all images
together: :func:`fit_block` (Gauss-Newton on the pairs' angles, Cauchy
loss). The pairs are stage 2's inliers of each image
(:mod:`.run_automatic`). The vertical offset is not seen by vertical lines.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)


@dataclass
class Rays:
    """(R,) rays in the upright MODEL frame: camera xy (R, 2), unit bearing
    (R, 2), image index (R,); optionally (R,) the segments' lengths (px)."""

    origin: np.ndarray
    bearing: np.ndarray
    image: np.ndarray
    length: np.ndarray | None = None


@dataclass
class BlockPlacement:
    """``map_xy = scale R(theta) model_xy + t``; the pairs of the last round."""

    scale: float
    theta: float
    translation: np.ndarray  # (2,)
    num_pairs: int
    rms_deg: float
    pairs_per_image: np.ndarray

    def rotation(self) -> np.ndarray:
        c, s = np.cos(self.theta), np.sin(self.theta)
        return np.array([[c, -s], [s, c]])


def segment_rays(
    segments: np.ndarray, K: np.ndarray, R: np.ndarray, center: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays of one image's (N, 2, 2) undistorted vertical segments: camera xy
    (2,) and (N, 2) unit bearings of their midpoints' rays (model frame,
    ``R`` cam_from_world of the upright model)."""
    mid = segments.mean(axis=1)
    rays = np.c_[mid, np.ones(len(mid))] @ np.linalg.inv(K).T @ R  # R^T K^-1 m
    b = rays[:, :2]
    return center[:2], b / np.linalg.norm(b, axis=1, keepdims=True)


def rays_in_map(
    rays: Rays, scale: float, theta: float, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(R, 2) ray origins and (R, 2) bearings in the map frame under
    ``map_xy = scale R(theta) model_xy + t``."""
    c, sn = np.cos(theta), np.sin(theta)
    Rm = np.array([[c, -sn], [sn, c]])
    return scale * rays.origin @ Rm.T + t, rays.bearing @ Rm.T


def _transform(params: np.ndarray, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and bearings in the map frame under (log s, theta, tx, ty)."""
    return rays_in_map(rays, np.exp(params[0]), params[1], params[2:])


def _refine(rays: Rays, params, corners, pairs, scale_rad, iterations=5):
    """Gauss-Newton (Cauchy-weighted) on the pairs' angular residuals;
    ``scale_rad`` one loss scale or (P,) each pair's sd (then also its
    weight: a level camera's corners carry the map's metric noise, a far
    one's angle is finer than a near one's)."""
    per_pair = np.ndim(scale_rad) > 0
    for _ in range(iterations):
        r = _residuals(rays, params, corners, pairs)
        J = np.empty((len(pairs), 4))
        for k in range(4):
            e = np.zeros(4)
            e[k] = 1e-6
            J[:, k] = (_residuals(rays, params + e, corners, pairs) - r) / 1e-6
        w = 1.0 / (1.0 + (r / scale_rad) ** 2)
        if per_pair:
            w = w / scale_rad**2
        step = np.linalg.lstsq(J * np.sqrt(w)[:, None], -r * np.sqrt(w), rcond=None)[0]
        params = params + step
        if np.abs(step).max() < 1e-10:
            break
    return params


def _residuals(rays, params, corners, pairs) -> np.ndarray:
    origins, bearings = _transform(params, rays)
    o, b = origins[pairs[:, 0]], bearings[pairs[:, 0]]
    d = corners[pairs[:, 1]] - o
    return np.arctan2(b[:, 0] * d[:, 1] - b[:, 1] * d[:, 0], np.sum(b * d, axis=1))


def fit_block(
    rays: Rays,
    corners: np.ndarray,
    pairs: np.ndarray,
    start: tuple[float, float, np.ndarray],
    scale_deg: float | np.ndarray = 0.05,
) -> BlockPlacement:
    """The 2D similarity from given (P, 2) (ray, corner) pairs (stage 2's
    inliers of every image), Gauss-Newton with a Cauchy loss of
    ``scale_deg`` (one, or (P,) per pair: each pair's sd, also its weight),
    from ``start`` = (scale, theta, (2,) t)."""
    s0, th0, t0 = start
    params = _refine(
        rays, np.r_[np.log(s0), th0, t0], corners, pairs, np.radians(scale_deg), 20
    )
    r = _residuals(rays, params, corners, pairs)
    per_image = np.bincount(rays.image[pairs[:, 0]], minlength=rays.image.max() + 1)
    return BlockPlacement(
        scale=float(np.exp(params[0])),
        theta=float(params[1]),
        translation=params[2:].copy(),
        num_pairs=len(pairs),
        rms_deg=float(np.degrees(np.sqrt(np.mean(r**2)))),
        pairs_per_image=per_image,
    )
