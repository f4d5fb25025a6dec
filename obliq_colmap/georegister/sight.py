"""Which map corners a street-level camera can see: the frustum and facing
test of :func:`~obliq_colmap.cadastre.visible_corners`, plus a line of sight
in plan.

``visible_corners`` does not model occlusion (an aerial camera looks over
the roofs); a camera 1.6 m above a street sees nothing behind the first
facade, and the corners of the courtyards and back streets that pass the
frustum and facing tests are most of the candidates. Seen from eye level
a building hides what lies behind its footprint whatever its height, so the
test is 2D: the sight line from the camera to the corner must cross no
footprint edge before it reaches the corner.
"""

from __future__ import annotations

import numpy as np

from obliq_colmap.cadastre import Cadastre


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def corners_in_sight(
    cad: Cadastre,
    center_xy: np.ndarray,
    corners: np.ndarray,
    clearance_m: float = 0.05,
) -> np.ndarray:
    """(K,) bool: the sight line from ``center_xy`` (2,) to each of the
    ``corners`` (K,) (indices into ``cad``'s corners) crosses no footprint
    edge more than ``clearance_m`` before the corner (the corner's own walls
    end at it, and a neighbour's wall that ends at the same point as well).
    """
    corners = np.asarray(corners, np.int64)
    if len(corners) == 0:
        return np.zeros(0, bool)
    xy = cad.corner_xy[corners]  # (K, 2)
    reach = np.linalg.norm(xy - center_xy, axis=1).max() + 1.0
    lo, hi = center_xy - reach, center_xy + reach
    near = np.isin(cad.edge_building, cad.buildings_in_box(*lo, *hi))
    p = cad.edge_xy[near, 0]  # (E, 2)
    s = cad.edge_xy[near, 1] - p  # (E, 2)
    r = xy - center_xy  # (K, 2)
    length = np.linalg.norm(r, axis=1)  # (K,)
    denom = _cross(r[:, None], s[None])  # (K, E)
    op = p[None] - center_xy  # (1, E, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _cross(op, s[None]) / denom  # along the sight line, (K, E)
        u = _cross(op, r[:, None]) / denom  # along the edge
    before = t * length[:, None] < length[:, None] - clearance_m
    blocked = (denom != 0) & (t > 0) & before & (u >= 0) & (u <= 1)
    return ~blocked.any(axis=1)
