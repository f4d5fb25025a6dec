"""The usable vertical segments of one image in the VP-aligned frame
(:class:`Segments`), the (corner, segment) pairs near a pose, and the
elliptical Mahalanobis distance of projected corners to segment bottoms."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from obliq_colmap.registration.options import RegistrationOptions
from obliq_colmap.registration.view import View


@dataclass
class Segments:
    """Usable segments in the VP-aligned frame (J of them).

    index : (J,) into the input; bottom, top : (J, 2) undistorted px;
    direction : (J, 2) unit, bottom to top; normal : (J, 2) unit;
    length : (J,); line : (J, 3) through the VP and the midpoint, unit (a, b);
    m_xy : (J, 2) ``(R0^T K^T line)_xy``; side : (J, 3) midpoint ray minus its
    component along n (camera frame); ends : (J, 2, 2) the original endpoints.
    """

    index: np.ndarray
    bottom: np.ndarray
    top: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    length: np.ndarray
    line: np.ndarray
    m_xy: np.ndarray
    side: np.ndarray
    ends: np.ndarray

    def __len__(self) -> int:
        return len(self.index)


def prepare_segments(
    segments_px: np.ndarray,
    view: View,
    options: RegistrationOptions,
    index: np.ndarray | None = None,
) -> Segments:
    """The usable segments of (N, 2, 2) undistorted ``segments_px``.

    ``index`` given: exactly these segments, in this order, without the
    length and VP tests (the same set again after the camera changed).
    """
    seg = np.asarray(segments_px, float).reshape(-1, 2, 2)
    finite = np.all(np.isfinite(seg), axis=(1, 2))
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    mid = seg.mean(axis=1)
    vp = view.K @ view.n  # homogeneous, the image of the nadir
    line = np.cross(vp, np.column_stack([mid, np.ones(len(mid))]))
    nrm = np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    line = line / np.where(nrm > 0, nrm, 1.0)
    # Angle between the segment and its line through the VP.
    dist = np.abs(np.sum(seg[:, 0] * line[:, :2], axis=1) + line[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        angle = np.degrees(np.arcsin(np.minimum(1.0, 2.0 * dist / length)))
    keep = finite & (length >= options.min_segment_length_px) & (nrm[:, 0] > 0)
    keep &= angle <= options.vp_tolerance_deg
    idx = np.flatnonzero(keep) if index is None else np.asarray(index, int)
    seg, line, length, mid = seg[idx], line[idx], length[idx], mid[idx]
    # Bottom: the endpoint whose viewing ray points further down the world.
    rays = np.concatenate([seg, np.ones((len(seg), 2, 1))], axis=2) @ view.Kinv.T
    down = (rays @ view.n) / np.linalg.norm(rays, axis=2)  # (J, 2)
    first_low = down[:, 0] >= down[:, 1]
    bottom = np.where(first_low[:, None], seg[:, 0], seg[:, 1])
    top = np.where(first_low[:, None], seg[:, 1], seg[:, 0])
    # Bottom and top projected onto the line through the VP.
    bottom = (
        bottom - (np.sum(bottom * line[:, :2], 1) + line[:, 2])[:, None] * line[:, :2]
    )
    top = top - (np.sum(top * line[:, :2], 1) + line[:, 2])[:, None] * line[:, :2]
    direction = top - bottom
    dl = np.linalg.norm(direction, axis=1, keepdims=True)
    direction = direction / np.where(dl > 0, dl, 1.0)
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    m = line @ view.K @ view.R0  # (R0^T K^T l)^T
    ray_mid = np.column_stack([mid, np.ones(len(mid))]) @ view.Kinv.T
    side = ray_mid - (ray_mid @ view.n)[:, None] * view.n
    return Segments(
        idx, bottom, top, direction, normal, length, line, m[:, :2], side, seg
    )


def pairs_near(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    radius_px: float,
    h_range: tuple[float, float] | None = None,
    ground=None,
    height_tol_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs whose segment bottom lies within ``radius_px`` across the corner's
    projected vertical, with the bottom's height in ``h_range`` or within
    ``height_tol_m`` of ``ground`` ((I,) array or float) on that vertical.

    Returns (corner indices, segment indices), sorted by corner then segment.
    """
    a, c = np.array([alpha]), np.asarray(c_xy, float)[None]
    lines = view.corner_lines(a, c, corner_rel)[0]  # (I, 3)
    across = lines[:, :2] @ segs.bottom.T + lines[:, 2:3]  # (I, J)
    ii, jj = np.nonzero(np.abs(across) <= radius_px)  # sorted by (i, j)
    h = view.bottom_heights(a, c, corner_rel[ii], segs.bottom[jj])[0]
    with np.errstate(invalid="ignore"):
        if h_range is not None:
            ok = (h >= h_range[0]) & (h <= h_range[1])
        else:
            g = ground[ii] if np.ndim(ground) else ground
            ok = np.abs(h - g) <= height_tol_m
    return ii[ok], jj[ok]


def mahalanobis2(
    px: np.ndarray, segs: Segments, seg_idx: np.ndarray, stretch: float
) -> np.ndarray:
    """Squared Mahalanobis distances (px^2) of projected corners to segments.

    The ellipse is centred on the segment's bottom: ``across^2 +
    (along / stretch)^2``; NaN projections give inf.

    Parameters
    ----------
    px : (H, P, 2) projected corners; seg_idx : (P,) segment of each pair.
    """
    d = px - segs.bottom[seg_idx]
    across = np.sum(d * segs.normal[seg_idx], axis=-1)
    along = np.sum(d * segs.direction[seg_idx], axis=-1)
    d2 = across * across + (along / stretch) ** 2
    return np.where(np.isfinite(d2), d2, np.inf)


def pair_d2(
    view: View,
    segs: Segments,
    seg_idx: np.ndarray,
    alpha: np.ndarray,
    c_xy: np.ndarray,
    xy: np.ndarray,
    z: np.ndarray,
    stretch: float,
) -> np.ndarray:
    """:func:`mahalanobis2` of the corners projected by :meth:`View.project`,
    fused (the RANSAC's scoring loop).

    The same floating-point operations per element, on (H, P) arrays per
    coordinate instead of (H, P, 3) temporaries and a matmul by ``K``: the
    result is bit-identical when ``K`` has no skew (the products with its zero
    entries add exact zeros); otherwise the two functions are called.

    Parameters
    ----------
    seg_idx : (P,) segment of each pair; alpha : (H,); c_xy : (H, 2);
    xy : (P, 2) corners (relative); z : (H, P) heights (m); stretch : float.

    Returns
    -------
    (H, P) squared distances (px^2), inf where not finite.
    """
    K, R0 = view.K, view.R0
    if K[0, 1] != 0 or K[1, 0] != 0:
        px, _ = view.project(alpha, c_xy, xy, z)
        return mahalanobis2(px, segs, seg_idx, stretch)
    ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
    dx = xy[:, 0] - c_xy[:, 0, None]
    dy = xy[:, 1] - c_xy[:, 1, None]
    rx = ca * dx - sa * dy  # as ransac_core.horizontal_in_camera
    ry = sa * dx + ca * dy
    zz = z - view.c0[2]
    depth = rx * R0[2, 0] + ry * R0[2, 1] + zz * R0[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        den = np.where(depth > 0, depth, np.nan)
        u = (rx * R0[0, 0] + ry * R0[0, 1] + zz * R0[0, 2]) / den
        v = (rx * R0[1, 0] + ry * R0[1, 1] + zz * R0[1, 2]) / den
    bottom = segs.bottom[seg_idx]
    ex = u * K[0, 0] + K[0, 2] - bottom[:, 0]
    ey = v * K[1, 1] + K[1, 2] - bottom[:, 1]
    nrm, dirn = segs.normal[seg_idx], segs.direction[seg_idx]
    across = ex * nrm[:, 0] + ey * nrm[:, 1]
    along = (ex * dirn[:, 0] + ey * dirn[:, 1]) / stretch
    d2 = across * across + along * along
    return np.where(np.isfinite(d2), d2, np.inf)
