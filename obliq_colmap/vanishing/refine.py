"""Refinement of the vertical VP: ML on its segments against competing VPs
(streets, facades), with alternating assignment, and once more on the second
pass's chains."""

from __future__ import annotations

import numpy as np

from obliq_colmap.vanishing.options import VanishingOptions
from obliq_colmap.vanishing.pencil import (
    endpoint_scatter,
    midpoint_distance,
    pencil_cost,
    pencil_costs_each,
    refine_vp,
)
from obliq_colmap.vanishing.ransac import ransac_vp
from obliq_colmap.vanishing.second_pass import SecondPass


def _refine_segments(
    ends_n: np.ndarray, v: np.ndarray, inl: np.ndarray, thr_n: float, rounds: int
):
    """ML refinement on the inlier segments, re-selecting the inliers."""
    S_all = endpoint_scatter(ends_n)
    cov = np.full((3, 3), np.inf)
    for _ in range(max(rounds, 1)):
        if inl.sum() < 3:
            break
        v, cov, _, _ = refine_vp(S_all[inl], v)
        new = np.sqrt(pencil_cost(S_all, v) / 2.0) <= thr_n
        if np.array_equal(new, inl):
            break
        inl = new
    return v, cov, inl


def _segment_residuals(S_all: np.ndarray, vps: list[np.ndarray]) -> np.ndarray:
    """(M, G) RMS endpoint distance of each segment to its best line through each VP."""
    return np.sqrt(pencil_costs_each(S_all, np.array(vps)) / 2.0)


def refine_with_competitors(
    ends_n,
    lines_n,
    mid_n,
    half_n,
    weight,
    v,
    inl,
    thr_n,
    Kn,
    prior_ok,
    significance_of,
    options,
    rng,
    intrinsics_known=False,
):
    """Vertical VP refined against competing VPs (exclusive assignment).

    1. ML refinement of the vertical VP on its inliers (:func:`_refine_segments`).
    2. Up to ``options.competing_vps`` times: RANSAC for another VP among the
       segments, scored only on segments that fit it better than every VP
       found so far, its hypotheses at least ``competing_min_angle_deg`` from
       the vertical direction; kept with ``competing_min_segments`` such
       segments.
    3. Alternation (:func:`_alternate`): every segment goes to the VP it
       fits best (RMS endpoint distance to the best line through the VP), the
       vertical VP is refined by ML on its segments, until stable.
    4. If a competitor that the prior allows as the vertical is more
       significant (``significance_of``; with intrinsics plus the
       significance of its best nearly orthogonal partner), they swap, and
       3. again.

    Returns the vertical VP, its covariance, its inliers (S,) bool, and the
    competing VPs (normalised homogeneous).
    """
    v, cov, inl = _refine_segments(ends_n, v, inl, thr_n, options.refine_rounds)
    if options.competing_vps <= 0 or inl.sum() < 3:
        return v, cov, inl, []
    S_all = endpoint_scatter(ends_n)
    Kinv = np.linalg.inv(Kn)
    cos_sep = np.cos(np.radians(options.competing_min_angle_deg))

    def direction(h):
        d = h @ Kinv.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    comps: list[np.ndarray] = []
    for _ in range(options.competing_vps):
        dv = direction(v)

        def far_from_vertical(h, dv=dv):
            return np.abs(direction(h) @ dv) <= cos_sep

        cap = midpoint_distance(np.vstack([v] + comps), mid_n, half_n).min(axis=0)
        free = cap > 0.5 * thr_n
        h, hinl, _ = ransac_vp(
            lines_n,
            mid_n,
            half_n,
            weight,
            thr_n,
            far_from_vertical,
            options,
            rng,
            cap=cap,
            sample=free,
            # Streets and facades are strong pencils: one small batch.
            max_trials=options.competing_batch_size,
            batch_size=options.competing_batch_size,
        )
        if h is None or hinl.sum() < options.competing_min_segments:
            break
        comps.append(h)
    if not comps:
        return v, cov, inl, []
    vps = [v] + comps
    vps, cov, assign = _alternate(S_all, vps, cov, thr_n, direction, cos_sep, options)
    # The vertical is the most significant pencil the prior allows: a street
    # seen along its length (dashes, curbs, cars: many short segments) can
    # outscore the buildings in pair-RANSAC; if a competitor the prior allows
    # is more significant, the two swap roles.
    allowed = prior_ok(np.array(vps))
    use_ortho = intrinsics_known and options.orthogonal_support_tol_deg > 0
    need = allowed.copy()
    if use_ortho:
        d = direction(np.array(vps))
        ortho = np.abs(d @ d.T) <= np.sin(
            np.radians(options.orthogonal_support_tol_deg)
        )
        need |= (ortho & allowed[:, None]).any(axis=0)
    # Significance only where it is used (each costs three pencil fits).
    sig = np.full(len(vps), -np.inf)
    sig[need] = significance_of(np.array(vps)[need])
    score = np.where(allowed, sig, -np.inf)
    if use_ortho:
        # With intrinsics, the vertical is orthogonal to the horizontal
        # directions (streets, facades) whose pencils compete with it; a
        # pencil of street lines and facade rows that merely looks vertical
        # inside a strip (paper seed 2, S_11: 42 deg off with significance
        # 100) has no orthogonal partner. Each allowed candidate is scored
        # with the significance of its best orthogonal partner added, and a
        # candidate with a significant orthogonal partner goes before any
        # without one.
        partner = np.where(ortho, np.maximum(sig, 0.0)[None, :], 0.0).max(axis=1)
        score = np.full(len(vps), -np.inf)
        score[allowed] = sig[allowed] + partner[allowed]
        paired = allowed & (partner >= options.ok_min_significance)
        if paired.any():
            score = np.where(paired, score, -np.inf)
    best = int(np.argmax(score))
    if best != 0 and score[best] > score[0]:
        vps[0], vps[best] = vps[best], vps[0]
        v2, cov2, _, _ = refine_vp(S_all[assign == best], vps[0])
        if np.all(np.isfinite(v2)):
            vps[0], cov = v2, cov2
        vps, cov, assign = _alternate(
            S_all, vps, cov, thr_n, direction, cos_sep, options
        )
    inl = assign == 0
    return vps[0], cov, inl, vps[1:]


def _alternate(S_all, vps, cov, thr_n, direction, cos_sep, options):
    """Assign segments to their best VP and refine, until stable.

    The competitors (``vps[1:]``) are refined once, a few Newton steps (they
    only claim their segments); the vertical VP ``vps[0]`` in every round.
    """
    vps = list(vps)
    assign, first_round = None, True
    for _ in range(max(options.refine_rounds, 1)):
        D = _segment_residuals(S_all, vps)
        new = np.where(D.min(axis=0) <= thr_n, np.argmin(D, axis=0), -1)
        if assign is not None and np.array_equal(new, assign):
            break
        assign = new
        if first_round:
            for m in range(1, len(vps)):
                sel = assign == m
                if sel.sum() >= 3:
                    vm = refine_vp(S_all[sel], vps[m], max_iterations=3)[0]
                    # A competitor must not drift onto the vertical.
                    if np.abs(direction(vm) @ direction(vps[0])) <= cos_sep:
                        vps[m] = vm
            first_round = False
        sel = assign == 0
        if sel.sum() >= 3:
            vm, cm, _, _ = refine_vp(S_all[sel], vps[0])
            if np.all(np.isfinite(vm)):
                vps[0], cov = vm, cm
    return vps, cov, assign


def refine_on_chains(
    sp: SecondPass,
    v_n: np.ndarray,
    comps: np.ndarray,
    options: VanishingOptions,
    s_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The VP refined on the second pass's chains, and the chains to return.

    Parameters
    ----------
    sp : the second pass (scatter in normalised coordinates).
    v_n : (3,) unit VP, normalised coordinates.
    comps : (K, 3) unit competing VPs, normalised coordinates.
    s_px : pixels per normalised unit.

    Returns
    -------
    v_n : (3,) the refined VP; keep : (G,) bool, the chains through it within
    ``second_pass.max_rms_px`` that fit it better than any competing VP;
    use : (G,) bool, the chains the VP was refined on.
    """
    S = sp.scatter
    n_pts = np.maximum(S[:, 2, 2], 1)
    max_cost = (options.second_pass.max_rms_px / s_px) ** 2
    # Chains that fit a competing VP (a street's direction) better than the
    # vertical one are not vertical edges.
    other = np.full(len(S), np.inf)
    if len(comps):
        other = pencil_costs_each(S, comps).min(axis=0) / n_pts
    cost = pencil_cost(S, v_n) / n_pts
    # Re-select the segments with each refined VP: a few long non-vertical
    # edges that passed near the first-pass VP (streets receding towards the
    # horizon) drop out as the VP improves.
    use = (cost <= max_cost) & (cost <= np.maximum(other, 0.25 * max_cost))
    if use.sum() < 3:
        use[:] = True
    for _ in range(max(options.refine_rounds, 1) + 2):
        v_n, _, _, _ = refine_vp(S[use], v_n)
        cost = pencil_cost(S, v_n) / n_pts
        # Robust scale of the chains' RMS distances: straight edges through
        # the VP share one noise level. The VP is refined on the chains within
        # ``second_pass_rms_factor`` of it; a chain goes to a competing VP only
        # when that fits it better by more than this noise (near the line
        # joining the two VPs both fit equally well).
        scale2 = (1.4826 * np.median(np.sqrt(cost[use]))) ** 2
        thr = min(max_cost, options.second_pass_rms_factor**2 * scale2)
        new = (cost <= thr) & (cost - other <= scale2)
        if np.array_equal(new, use) or new.sum() < 3:
            break
        use = new
    return v_n, (cost <= max_cost) & (cost < other), use
