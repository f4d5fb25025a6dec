"""Step 4 of the registration: the candidate pairs near a pose, the scoring
of a batch of hypotheses (distinct inlier corners, MSAC cost) and the RANSAC
loop (:func:`run_ransac`), resumable from its state."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from obliq_colmap.registration import ransac_core
from obliq_colmap.registration.options import RegistrationOptions
from obliq_colmap.registration.segments import Segments, pair_d2, pairs_near
from obliq_colmap.registration.view import View, fit_planes, plane_at

#: Elements of the (hypotheses, pairs) float64 temporaries of the RANSAC's
#: scoring that stay in the cache (128 KiB each).
_CACHE_ELEMENTS = 1 << 14


@dataclass
class Candidates:
    corner: np.ndarray  # (P,) index into corner_rel
    segment: np.ndarray  # (P,) index into Segments
    starts: np.ndarray  # group starts of equal corners (pairs sorted by corner)


def candidates(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    ground: np.ndarray | float,
    radius_px: float,
    height_tol_m: float,
) -> Candidates:
    ii, jj = pairs_near(
        view,
        segs,
        corner_rel,
        alpha,
        c_xy,
        radius_px,
        ground=ground,
        height_tol_m=height_tol_m,
    )
    starts = (
        np.flatnonzero(np.r_[True, ii[1:] != ii[:-1]]) if len(ii) else np.zeros(0, int)
    )
    return Candidates(ii, jj, starts)


def _score(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    cand: Candidates,
    alpha: np.ndarray,
    c_xy: np.ndarray,
    plane: np.ndarray,
    thr2: float,
    stretch: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Distinct inlier corners and MSAC cost of a batch of hypotheses.

    Returns
    -------
    count : (H,) int; cost : (H,) float (sum of truncated d^2 over pairs).
    """
    xy = corner_rel[cand.corner]  # (P, 2)
    count = np.zeros(len(alpha), int)
    cost = np.zeros(len(alpha))
    if len(xy) == 0:
        return count, cost
    # Hypotheses in chunks whose (h, P) temporaries stay in the cache (3x
    # faster than all at once); the row-wise reductions are unchanged.
    step = max(1, _CACHE_ELEMENTS // len(xy))
    for h0 in range(0, len(alpha), step):
        h = slice(h0, h0 + step)
        z = plane_at(plane[h], xy)  # (h, P)
        d2 = pair_d2(view, segs, cand.segment, alpha[h], c_xy[h], xy, z, stretch)
        inl = d2 <= thr2
        count[h] = np.maximum.reduceat(inl, cand.starts, axis=1).sum(axis=1)
        cost[h] = np.minimum(d2, thr2).sum(axis=1)
    return count, cost


@dataclass
class RansacState:
    """Where a RANSAC run stopped: resuming it with a larger ``max_trials``
    draws and scores exactly the samples a single longer run would have."""

    rng: np.random.Generator
    trials: int = 0
    needed: float = 0.0
    best: tuple[int, float] = (-1, math.inf)
    model: tuple[float, np.ndarray, np.ndarray] = field(
        default_factory=lambda: (math.nan, np.full(2, np.nan), np.full(3, np.nan))
    )


def run_ransac(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    cand: Candidates,
    alpha_center: float,
    c_center: np.ndarray,
    alpha_half: float,
    c_half: float,
    options: RegistrationOptions,
    state: RansacState,
    max_trials: int | None = None,
) -> tuple[float, np.ndarray, np.ndarray, int, float, int]:
    """Step 4: RANSAC over the candidate pairs, from ``state`` (updated).

    Hypotheses farther than ``alpha_half`` / ``c_half`` from the centre of the
    search are rejected before scoring.

    Returns
    -------
    alpha, c_xy (2,), plane (3,) relative coordinates, best count of distinct
    inlier corners, its MSAC cost, trials drawn (in all, since the start).
    """
    max_trials = options.max_trials if max_trials is None else max_trials
    thr2 = options.inlier_threshold_px**2
    ridge = (options.height_sigma_m / options.slope_sigma) ** 2
    P = len(cand.corner)
    st = state
    if st.trials == 0:
        st.needed = float(options.min_trials)
    while st.trials < min(st.needed, max_trials):
        B = options.batch_size
        idx = ransac_core.sample_pairs(st.rng, B, cand.corner, cand.segment)
        st.trials += B
        if len(idx) == 0:
            continue
        ci, sj = cand.corner[idx], cand.segment[idx]  # (S, 3)
        alpha, c_xy, valid = ransac_core.solve_minimal(
            segs.m_xy[sj], corner_rel[ci], view.R0, segs.side[sj]
        )
        with np.errstate(invalid="ignore"):
            valid &= (np.abs(alpha - alpha_center) <= alpha_half) & (
                np.linalg.norm(c_xy - c_center, axis=1) <= c_half
            )
        if not valid.any():
            continue
        alpha, c_xy, ci, sj = alpha[valid], c_xy[valid], ci[valid], sj[valid]
        h = view.bottom_heights(alpha, c_xy, corner_rel[ci], segs.bottom[sj])  # (S, 3)
        plane = fit_planes(corner_rel[ci], h, None, ridge)
        ok = np.all(np.isfinite(plane), axis=1)
        if not ok.any():
            continue
        alpha, c_xy, plane = alpha[ok], c_xy[ok], plane[ok]
        count, cost = _score(
            view,
            segs,
            corner_rel,
            cand,
            alpha,
            c_xy,
            plane,
            thr2,
            options.along_segment_stretch,
        )
        # Most distinct inlier corners; ties broken by the lower MSAC cost.
        k = int(np.lexsort((cost, -count))[0])
        if (count[k], -cost[k]) > (st.best[0], -st.best[1]):
            st.best = (int(count[k]), float(cost[k]))
            st.model = (float(alpha[k]), c_xy[k].copy(), plane[k].copy())
            ratio = st.best[0] / max(P, 1)
            st.needed = max(
                options.min_trials,
                ransac_core.required_trials(ratio, 3, options.confidence),
            )
    return (*st.model, max(st.best[0], 0), st.best[1], st.trials)
