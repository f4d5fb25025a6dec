"""Hypotheses of the vertical VP: the prior's region, candidate segments,
RANSAC over segment pairs and the a contrario significance test."""

from __future__ import annotations

import numpy as np
from scipy.special import pdtrc

from obliq_colmap.geometry import cross, tangent_basis
from obliq_colmap.lines import Segments
from obliq_colmap.vanishing.collinear import distinct_lines
from obliq_colmap.vanishing.options import VanishingOptions, VPPrior
from obliq_colmap.vanishing.pencil import (
    canonical_sign,
    endpoint_scatter,
    midpoint_distance,
    pencil_costs_each,
)


class PriorTest:
    """Vectorised test of hypotheses (normalised homogeneous) against a prior."""

    def __init__(
        self,
        prior: VPPrior,
        width: int,
        height: int,
        T: np.ndarray,
        K: np.ndarray | None,
    ) -> None:
        self.prior, self.W, self.H = prior, width, height
        self.Tinv = np.linalg.inv(T)
        self.K = K
        if prior.kind == "ins":
            if K is None:
                raise ValueError("the 'ins' prior needs intrinsics (a camera)")
            self.Kinv = np.linalg.inv(K)
            self.cos_cone = np.cos(np.radians(prior.cone_deg))
        if prior.kind == "aerial":
            self.Kinv = None if K is None else np.linalg.inv(K)
            self.cos_tilt = np.cos(np.radians(prior.max_tilt_deg))
            tan_tilt = np.tan(np.radians(prior.max_tilt_deg))
            self.max_distance = prior.max_focal_w * width * tan_tilt

    def __call__(self, v_n: np.ndarray) -> np.ndarray:
        v = v_n @ self.Tinv.T  # (H, 3) pixel homogeneous
        p = self.prior
        if p.kind == "ins":
            d = v @ self.Kinv.T
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            return np.abs(d @ p.down_cam) >= self.cos_cone
        v = canonical_sign(v)
        x, y, w = v[:, 0], v[:, 1], v[:, 2]
        dx, dy = x - 0.5 * self.W * w, y - 0.5 * self.H * w
        in_cone = np.abs(dx) <= np.tan(np.radians(p.max_angle_deg)) * np.abs(dy)
        if p.kind == "aerial":
            below = y >= p.min_y_h * self.H * w
            return in_cone & below & (dy > 0) & self._finite(v, dx, dy, w)
        return in_cone & (np.abs(dy) >= p.min_distance_h * self.H * w)

    def _finite(self, v, dx, dy, w) -> np.ndarray:
        """Aerial: the VP no farther than the steepest allowed tilt puts it."""
        if self.Kinv is not None:
            d = v @ self.Kinv.T  # w >= 0 and below the image: d points down
            return d[:, 2] >= self.cos_tilt * np.linalg.norm(d, axis=1)
        return np.hypot(dx, dy) <= self.max_distance * w


def candidate_segments(
    segs: Segments, prior: VPPrior, K: np.ndarray | None, options: VanishingOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Which segments can point to a VP the prior allows, and their tolerance.

    Returns
    -------
    mask : (N,) bool.
    half_range : (N,) float, half the range of orientations (rad) a candidate
        may have; used for the chance probability of the significance test.
    """
    d = segs.directions
    if prior.kind != "ins":
        # Angle from the image's vertical axis, 0..pi/2.
        ang = np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1]))
        lim = np.radians(options.candidate_max_angle_deg)
        return ang <= lim, np.full(len(d), lim)
    # INS: the predicted VP and 8 directions on its cone, projected.
    Kinv = np.linalg.inv(K)
    c = prior.down_cam
    B = tangent_basis(c)
    t = np.tan(np.radians(prior.cone_deg))
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    dirs = c[None] + t * (
        np.cos(phi)[:, None] * B[:, 0] + np.sin(phi)[:, None] * B[:, 1]
    )
    vps = np.vstack([c, dirs]) @ K.T  # (9, 3) pixel homogeneous
    m = segs.midpoints
    # Directions from the midpoints to the 9 points (homogeneous-safe).
    u = vps[None, :, :2] - m[:, None, :] * vps[None, :, 2:3]  # (N, 9, 2)
    ang_u = np.arctan2(u[..., 1], u[..., 0])
    dev = np.abs((ang_u[:, 1:] - ang_u[:, :1] + np.pi / 2) % np.pi - np.pi / 2)
    half_range = dev.max(axis=1) + np.radians(2.0)
    # Midpoints inside the cone's image: any orientation.
    rays = np.hstack([m, np.ones((len(m), 1))]) @ Kinv.T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    inside = np.abs(rays @ c) >= np.cos(np.radians(prior.cone_deg))
    half_range = np.where(inside, np.pi / 2, np.minimum(half_range, np.pi / 2))
    a = np.arctan2(d[:, 1], d[:, 0])
    seg_dev = np.abs((a - ang_u[:, 0] + np.pi / 2) % np.pi - np.pi / 2)
    return seg_dev <= half_range, half_range


def ransac_vp(
    lines_n: np.ndarray,
    mid_n: np.ndarray,
    half_n: np.ndarray,
    length: np.ndarray,
    thr_n: float,
    prior_ok,
    options: VanishingOptions,
    rng: np.random.Generator,
    cap: np.ndarray | None = None,
    sample: np.ndarray | None = None,
    max_trials: int | None = None,
    batch_size: int | None = None,
) -> tuple[np.ndarray | None, np.ndarray, int]:
    """Best VP hypothesis from pairs of segments (length-weighted MSAC).

    Pairs are drawn with probabilities proportional to the segment weights,
    in batches; every hypothesis of a batch is scored against every segment
    at once. The number of batches adapts to the best inlier fraction by
    weight (a pair is all-inlier with probability ~ w^2).

    ``cap`` (S,), optional: a segment counts only where its distance is below
    its cap (the distance to another VP: exclusive scoring). ``sample`` (S,)
    bool, optional: the segments pairs are drawn from.

    Returns
    -------
    vp_n : (3,) unit homogeneous VP (normalised coordinates) or None.
    inliers : (S,) bool.
    n_hypotheses : int, hypotheses that passed the prior and were scored.
    """
    S = len(lines_n)
    pool = np.arange(S) if sample is None else np.flatnonzero(sample)
    if len(pool) < 2:
        return None, np.zeros(S, bool), 0
    max_trials = options.max_trials if max_trials is None else max_trials
    batch = options.batch_size if batch_size is None else batch_size
    p = length[pool] / length[pool].sum()
    best_score, best_v, n_hyp, trials = -1.0, None, 0, 0
    needed = max_trials
    chunk = max(1, 2_000_000 // S)

    def inliers_of(v):
        d = midpoint_distance(v[None], mid_n, half_n)[0]
        return (d <= thr_n) & (d < cap) if cap is not None else d <= thr_n

    min_trials = min(options.min_trials, max_trials)
    while trials < min(needed, max_trials) or trials < min_trials:
        if trials >= max_trials:
            break
        i = pool[rng.choice(len(pool), batch, p=p)]
        j = pool[rng.choice(len(pool), batch, p=p)]
        trials += batch
        keep = i != j
        v = cross(lines_n[i[keep]], lines_n[j[keep]])
        nv = np.linalg.norm(v, axis=1)
        v = v[nv > 1e-12] / nv[nv > 1e-12, None]
        v = v[prior_ok(v)]
        n_hyp += len(v)
        for k in range(0, len(v), chunk):
            d = midpoint_distance(v[k : k + chunk], mid_n, half_n)
            m = np.maximum(0.0, 1.0 - (d / thr_n) ** 2)
            if cap is not None:
                m *= d < cap
            score = m @ length
            h = int(np.argmax(score))
            if score[h] > best_score:
                best_score, best_v = float(score[h]), v[k + h]
        if best_v is not None:
            inl = inliers_of(best_v)
            w = float(length[inl].sum() / length[pool].sum())
            pw = min(max(w * w, 1e-12), 1 - 1e-12)
            needed = int(np.ceil(np.log(1 - options.confidence) / np.log1p(-pw)))
    if best_v is None:
        return None, np.zeros(S, bool), n_hyp
    return best_v, inliers_of(best_v), n_hyp


def significance(k: np.ndarray, p_chance: np.ndarray, n_tests: float) -> np.ndarray:
    """-log10 NFA of k consistent segments among candidates (Poisson tail).

    ``k`` : int or (P,) ints, consistent segments per hypothesis;
    ``p_chance`` are the probabilities that each candidate is consistent by
    chance; the two segments defining a hypothesis are discounted.
    """
    mu = float(np.sum(p_chance)) * max(len(p_chance) - 2, 0) / max(len(p_chance), 1)
    kk = np.asarray(k) - 2
    log_tests = np.log10(max(n_tests, 1.0))
    # P(X >= kk) for X ~ Poisson(mu); a tail below the smallest double is
    # -inf (as scipy.stats.poisson.logsf gives).
    with np.errstate(divide="ignore"):
        log_tail = np.log10(pdtrc(np.maximum(kk, 1) - 1, max(mu, 1e-12)))
    return np.where(kk <= 0, -log_tests, -(log_tests + log_tail))


def significance_test(
    segments: Segments,
    n_candidates: int,
    T: np.ndarray,
    factor: float,
    thr_px: float,
    thr_n: float,
    options: VanishingOptions,
):
    """The significance of VPs among ``segments`` (:func:`significance`).

    ``n_candidates`` segments took part in RANSAC; ``factor`` is the
    detection image's downscaling, ``thr_px`` / ``thr_n`` the inlier
    threshold in pixels / normalised units. Returns ``significance_of(V)``:
    (P,) significance of each of (P, 3) VPs (normalised).
    """
    # Background model: every segment has a uniform orientation (deviation from the line
    # to the VP uniform in [0, pi/2]); k counts the distinct lines through the VP that
    # the segments consistent with it lie on, whichever VP they were assigned to (random
    # segments rarely share one). The prior only limits where hypotheses may lie (fewer
    # tests); using the candidates' narrow orientation band as the chance range would
    # make a strong pencil of 400 verticals look like chance under a tight INS cone. The
    # test is made in three length classes (at least 1, 2 and 4 times min_length_px),
    # the best one counting, with the number of tests multiplied by 3: a pencil of many
    # short segments and one of a few long ones in a textured image (where hundreds of
    # short segments make any VP look like chance) are both recognised. Number of tests:
    # the hypotheses RANSAC may examine (fixed a priori by max_trials), not all pairs of
    # segments.
    # Precisions: a pencil of short clean edges among many short clutter segments (low
    # industrial halls among trees and cars) is chance at the RANSAC threshold (a 12 px
    # segment meets it with probability 0.1 at any VP) and plain at a quarter of it; the
    # test is made at each precision too, the best counting, the tests multiplied by
    # their number (the a contrario multi-precision test of LSD).
    precisions = tuple(options.significance_precisions) or (1.0,)
    n_tests = (
        3
        * len(precisions)
        * min(n_candidates * (n_candidates - 1) / 2, options.max_trials)
    )
    # The classes are nested: one scatter for the first, masks for the others.
    sel = segments.lengths >= options.min_length_px * factor
    L1 = segments.lengths[sel]
    E1 = segments.endpoints[sel] @ T[:2, :2].T + T[:2, 2]
    S_sig = endpoint_scatter(E1)
    classes = [
        m
        for m in (mult * options.min_length_px * factor <= L1 for mult in (1, 2, 4))
        if m.any()
    ]
    p_chance = [
        np.minimum(
            1.0, np.arcsin(np.minimum(1.0, f * thr_px / (0.5 * L1))) / (np.pi / 2)
        )
        for f in precisions
    ]

    def significance_of(V):
        """(P,) significance of each of (P, 3) VPs (normalised)."""
        V = np.asarray(V, float).reshape(-1, 3)
        best = np.full(len(V), -np.inf)
        if not classes:
            return best
        rms = np.sqrt(pencil_costs_each(S_sig, V) / 2.0)  # (P, G)
        for f, p in zip(precisions, p_chance, strict=True):
            consistent = rms <= f * thr_n
            for m in classes:
                # Distinct lines, not pieces (:mod:`.collinear`).
                k = np.array(
                    [
                        distinct_lines(E1[c & m], v, f * thr_n)
                        for c, v in zip(consistent, V, strict=True)
                    ]
                )
                best = np.maximum(best, significance(k, p[m], n_tests))
        return best

    return significance_of
