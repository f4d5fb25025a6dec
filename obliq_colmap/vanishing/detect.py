"""The stage's entry points: the first pass on segments
(:func:`estimate_vertical_vp`) and the whole detection on an image with its
starts and second passes (:func:`detect_vertical_vp`)."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence

import numpy as np

from obliq_colmap.geometry import Camera, tangent_basis
from obliq_colmap.lines import (
    Segments,
    as_gray_u8,
    detect_segments,
    equalize_local_contrast,
    gradients,
)
from obliq_colmap.vanishing.collinear import line_length
from obliq_colmap.vanishing.options import VanishingOptions, VanishingResult, VPPrior
from obliq_colmap.vanishing.pencil import (
    canonical_sign,
    direction_std_deg,
    grouped_jackknife_covariance,
    nominal_K,
    normaliser,
    pencil_fit,
    vertical_direction,
)
from obliq_colmap.vanishing.ransac import (
    PriorTest,
    candidate_segments,
    ransac_vp,
    significance_test,
)
from obliq_colmap.vanishing.refine import refine_on_chains, refine_with_competitors
from obliq_colmap.vanishing.second_pass import SecondPass, run_second_pass

logger = logging.getLogger(__name__)


def estimate_vertical_vp(
    segments: Segments,
    image_size: tuple[int, int],
    options: VanishingOptions | None = None,
    camera: Camera | None = None,
    prior: VPPrior | None = None,
    rng: np.random.Generator | int | None = None,
) -> VanishingResult:
    """Vertical VP from segments (steps 2 and 3 of the package docstring).

    Parameters
    ----------
    segments : Segments, undistorted COLMAP pixels of the full image.
    image_size : (width, height) in pixels.
    options, camera, prior : as :func:`detect_vertical_vp`.
    rng : Generator, seed or None (then ``options.seed``).

    Returns
    -------
    VanishingResult (without second-pass segments).
    """
    options = options or VanishingOptions()
    prior = prior or VPPrior.none()
    if prior.kind == "ins" and camera is None:
        raise ValueError("the 'ins' prior needs intrinsics (a camera)")
    rng = np.random.default_rng(options.seed if rng is None else rng)
    W, H = image_size
    T, s = normaliser(W, H)
    K = camera.K if camera is not None else None
    Knom = K if K is not None else nominal_K(W, H)
    limit = options.lines.max_image_size_px
    factor = max(1.0, max(W, H) / limit) if limit else 1.0
    thr_px = options.inlier_threshold_px * factor
    thr_n = thr_px / s
    t0 = time.perf_counter()

    use = segments.lengths >= options.min_length_px * factor
    cand, half_range = candidate_segments(segments, prior, K, options)
    use &= cand
    idx = np.flatnonzero(use)
    result = VanishingResult(
        status="no_vp", segments=segments, inliers=np.zeros(len(segments), bool)
    )
    if len(idx) < options.min_inliers:
        result.message = (
            f"no vertical structure: {len(idx)} candidate segments "
            f"(need {options.min_inliers})"
        )
        return result
    ends_n = segments.endpoints[idx] @ T[:2, :2].T + T[:2, 2]  # (S, 2, 2)
    mid_n = ends_n.mean(axis=1)
    half_n = 0.5 * (ends_n[:, 1] - ends_n[:, 0])
    lines_n = np.cross(
        np.concatenate([ends_n[:, 0], np.ones((len(idx), 1))], 1),
        np.concatenate([ends_n[:, 1], np.ones((len(idx), 1))], 1),
    )
    lines_n /= np.linalg.norm(lines_n, axis=1, keepdims=True)
    length = segments.lengths[idx]
    prior_ok = PriorTest(prior, W, H, T, K)
    weight = length**options.score_length_power
    if options.line_weights:
        # Pieces of one image line share the weight the whole line would
        # have as one segment (:mod:`.collinear`): length**power for the
        # line, split among its pieces by their lengths.
        line = line_length(ends_n, thr_n) * s
        weight = length * line ** (options.score_length_power - 1.0)
    v, inl, n_hyp = ransac_vp(
        lines_n, mid_n, half_n, weight, thr_n, prior_ok, options, rng
    )
    result.n_hypotheses = n_hyp
    result.time_s["ransac"] = time.perf_counter() - t0
    if v is None:
        result.message = "no pair of segments meets where the prior allows a VP"
        return result

    t0 = time.perf_counter()
    significance_of = significance_test(
        segments, len(idx), T, factor, thr_px, thr_n, options
    )

    v, cov, inl, comps = refine_with_competitors(
        ends_n,
        lines_n,
        mid_n,
        half_n,
        weight,
        v,
        inl,
        thr_n,
        T @ Knom,
        prior_ok,
        significance_of,
        options,
        rng,
        intrinsics_known=K is not None,
    )
    if comps:
        c = np.array(comps) @ np.linalg.inv(T).T
        result.competing_vps = canonical_sign(
            c / np.linalg.norm(c, axis=1, keepdims=True)
        )
    result.time_s["refine"] = time.perf_counter() - t0
    if not prior_ok(v[None])[0]:
        # The structure converges where the prior says the VP cannot be (e.g.
        # nearly parallel verticals whose refinement crosses infinity to the
        # other side): by the prior's definition there is no vertical VP.
        vpx = canonical_sign(np.linalg.inv(T) @ v)
        result.message = (
            "the vertical structure converges outside the prior's region "
            f"(homogeneous VP {np.round(vpx / np.linalg.norm(vpx), 5).tolist()})"
        )
        return result
    sig = float(significance_of(v)[0])
    result.inliers[idx[inl]] = True
    _set_vp(result, v, cov, T, K, Knom, prior)
    result.significance = sig
    _set_status(result, options)
    return result


def _set_vp(result, v_n, cov_n, T, K, Knom, prior) -> None:
    """Store the VP (pixels, canonical sign), its covariance and direction.

    ``Knom`` (intrinsics or a nominal camera) gives the direction's angular
    uncertainty; None keeps the result's current one.
    """
    Tinv = np.linalg.inv(T)
    v = Tinv @ v_n
    nv = np.linalg.norm(v)
    J = (np.eye(3) - np.outer(v, v) / nv**2) / nv @ Tinv
    v = v / nv
    # Fewer than three inliers leave the VP unconstrained (cov_n infinite).
    cov = J @ cov_n @ J.T if np.isfinite(cov_n).all() else np.full((3, 3), np.inf)
    flip = canonical_sign(v)
    result.vp = flip
    result.covariance = cov
    if Knom is not None:
        result.direction_std_deg = direction_std_deg(flip, cov, Knom)
    if K is not None:
        result.vertical_direction = vertical_direction(
            flip, K, prior.down_cam if prior.kind == "ins" else None
        )


def _set_status(result: VanishingResult, options: VanishingOptions) -> None:
    k, sig, std = result.n_inliers, result.significance, result.direction_std_deg
    if k < options.min_inliers or sig <= 0:
        result.status = "no_vp"
        result.message = (
            f"no vertical structure: best VP has {k} consistent segments, "
            f"not more than chance (significance {sig:.1f})"
        )
        result.vp = result.covariance = result.vertical_direction = None
        return
    reasons = []
    if k < options.ok_min_inliers:
        reasons.append(f"{k} inlier segments < {options.ok_min_inliers}")
    if sig < options.ok_min_significance:
        reasons.append(f"significance {sig:.1f} < {options.ok_min_significance}")
    if not std <= options.ok_max_std_deg:
        reasons.append(f"direction std {std:.2f} deg > {options.ok_max_std_deg}")
    result.status = "low_confidence" if reasons else "ok"
    result.message = (
        "; ".join(reasons)
        if reasons
        else (f"{k} inlier segments, direction std {std:.3f} deg")
    )


def _start_priors(prior: VPPrior, factors: Sequence[float]) -> list[VPPrior]:
    """One prior per first-pass start: the INS cone times each factor (at
    most 80 deg); the other kinds have no cone: the prior itself as often
    (each start draws its own RANSAC samples)."""
    if prior.kind != "ins":
        return [prior] * len(factors)
    return [
        dataclasses.replace(prior, cone_deg=min(80.0, prior.cone_deg * f))
        for f in factors
    ]


def _same_vp(a: np.ndarray, b: np.ndarray, K: np.ndarray, same_deg: float) -> bool:
    """Whether homogeneous VPs a, b (3,) are one: their directions through K
    within ``same_deg`` (sign-free)."""
    da, db = np.linalg.solve(K, a), np.linalg.solve(K, b)
    cos = abs(float(da @ db)) / (np.linalg.norm(da) * np.linalg.norm(db))
    return cos >= math.cos(math.radians(same_deg))


def _distinct(
    results: list[VanishingResult], K: np.ndarray, same_deg: float
) -> list[VanishingResult]:
    """The results with a VP that is not :func:`_same_vp` as any earlier
    one, in order; the first result alone when none has a VP."""
    kept: list[VanishingResult] = []
    for r in results:
        if r.vp is not None and not any(
            _same_vp(r.vp, k.vp, K, same_deg) for k in kept
        ):
            kept.append(r)
    return kept or results[:1]


def _with_second_pass(
    result: VanishingResult,
    img: np.ndarray,
    grads: tuple[np.ndarray, np.ndarray],
    options: VanishingOptions,
    camera: Camera | None,
    prior: VPPrior,
) -> float:
    """Run the second pass for ``result`` in place (its vertical segments,
    and the VP refined on them); returns their total length, px (0 without
    a VP)."""
    if result.vp is None:
        return 0.0
    H, W = img.shape
    Knom = nominal_K(W, H)
    t0 = time.perf_counter()
    T, s_px = normaliser(W, H)
    sp = run_second_pass(img, result.vp, options.second_pass, camera, T, grads)
    result.time_s["second_pass"] = time.perf_counter() - t0
    if options.refine_with_second_pass and len(sp.scatter) >= 3:
        t0 = time.perf_counter()
        v_n = T @ result.vp
        v_n = v_n / np.linalg.norm(v_n)
        comps = result.competing_vps @ T.T
        comps /= np.linalg.norm(comps, axis=1, keepdims=True)
        v_n, keep, use = refine_on_chains(sp, v_n, comps, options, s_px)
        method = options.second_pass_covariance
        cov_n = None
        if method != "first_pass":
            cov_n = _chain_covariance(sp.scatter[use], v_n, method, options)
        sp = SecondPass(sp.segments.subset(keep), sp.scatter[keep])
        cov_px, sd_first = result.covariance, result.direction_std_deg
        K = camera.K if camera is not None else None
        if cov_n is None:
            # The first pass's covariance (on LSD segments) for the refined VP.
            _set_vp(result, v_n, np.zeros((3, 3)), T, K, None, prior)
            result.covariance = cov_px
        else:
            _set_vp(result, v_n, cov_n, T, K, K if K is not None else Knom, prior)
            if method == "max_blocks" and not (result.direction_std_deg >= sd_first):
                # The larger of the two statements: the chains' spread misses
                # errors they share (measured: docs/journal/stage1-vanishing.md,
                # 2026-12-04 "a covariance from the chains").
                result.covariance, result.direction_std_deg = cov_px, sd_first
            if options.status_from_second_pass_covariance:
                _set_status(result, options)
        result.time_s["refine_second"] = time.perf_counter() - t0
    result.vertical_segments = sp.through(result.vp, T)
    result.vertical_segments_free = sp.free(T)
    e = result.vertical_segments.endpoints
    return float(np.linalg.norm(e[:, 1] - e[:, 0], axis=1).sum()) if len(e) else 0.0


def _choose(
    results: list[VanishingResult],
    lengths: list[float],
    prior: VPPrior,
    K: np.ndarray,
    same_deg: float,
) -> VanishingResult:
    """The starts' result to return: the longest second pass picks the pencil.

    With an INS prior, among the VPs the second pass brought together (within
    ``same_deg``) the first start's (the prior's own cone): the length picks
    the pencil, not the most accurate VP within it; and a VP outside the cone
    must beat the prior's odds (:func:`_within_prior_odds`). Without a cone
    the starts are exchangeable draws and the first has no standing: the
    longest stands (urban-101 N_08, aerial prior, with the sector weights
    tried on 2026-12-05: two starts 1.75 and 0.23 deg off, 1.5 deg apart
    after the second pass, and the first was taken).
    """
    best = results[int(np.argmax(lengths))]
    if prior.kind != "ins":
        return best
    best = _within_prior_odds(best, results, lengths, prior)
    return next(r for r in results if _same_vp(best.vp, r.vp, K, same_deg))


def _prior_log10_odds(result: VanishingResult, prior: VPPrior) -> float:
    """log10 of the INS prior's density at ``result``'s vertical, up to a
    constant: a Gaussian on the angle from ``prior.down_cam`` whose 3 sigma
    is the prior's cone (how the cone is set: 3 sigma of the attitude)."""
    d = result.vertical_direction
    if d is None:
        return -math.inf
    angle = math.degrees(math.acos(min(1.0, abs(float(d @ prior.down_cam)))))
    sigma = prior.cone_deg / 3.0
    return -0.5 * (angle / sigma) ** 2 / math.log(10.0)


def _within_prior_odds(
    best: VanishingResult,
    results: list[VanishingResult],
    lengths: list[float],
    prior: VPPrior,
) -> VanishingResult:
    """The longest second pass ``best``, unless it lies outside the INS
    prior's own cone and a VP inside the cone is more probable.

    A wider start's VP outside the cone says the prior is more than 3 sigma
    off; a pencil of tree flanks (cones: each flank is the vertical turned by
    the same angle, ~12 deg on our generator's industrial class) or of a
    street's curbs is as long as the buildings' few short verticals, so length
    alone takes it. Its evidence (the a contrario significance, log10) must
    then beat the inside VP's by the prior's log10 odds of the two
    directions; a prior that is really 7 deg off loses to a true pencil much
    more significant than the one inside its cone."""
    cos_cone = math.cos(math.radians(prior.cone_deg))

    def inside(r: VanishingResult) -> bool:
        d = r.vertical_direction
        return d is not None and abs(float(d @ prior.down_cam)) >= cos_cone

    if best.vp is None or inside(best):
        return best
    candidates = [
        (length, r)
        for length, r in zip(lengths, results, strict=True)
        if inside(r) and r.status != "no_vp"
    ]
    if not candidates:
        return best
    _, inner = max(candidates, key=lambda c: c[0])

    def score(r: VanishingResult) -> float:
        return r.significance + _prior_log10_odds(r, prior)

    return inner if score(inner) >= score(best) else best


def _chain_covariance(
    S: np.ndarray, v_n: np.ndarray, method: str, options: VanishingOptions
) -> np.ndarray:
    """(3, 3) covariance of the VP ``v_n`` (normalised) refined on the chains
    of scatter ``S``: a jackknife over the chains ("chains") or over
    ``options.covariance_blocks`` blocks of neighbouring chains in the order
    of their angle in the pencil ("blocks", "max_blocks"; neighbours in the
    pencil are neighbours in the image: one facade, one row of windows)."""
    if method == "chains":
        return grouped_jackknife_covariance(S, v_n)
    _, lines = pencil_fit(S, v_n)
    x = lines @ tangent_basis(v_n)
    order = np.argsort(np.arctan2(x[:, 1], x[:, 0]) % np.pi)
    nb = min(options.covariance_blocks, len(S))
    groups = np.empty(len(S), int)
    groups[order] = np.arange(len(S)) * nb // max(len(S), 1)
    return grouped_jackknife_covariance(S, v_n, groups)


def detect_vertical_vp(
    image_gray: np.ndarray,
    options: VanishingOptions | None = None,
    camera: Camera | None = None,
    prior: VPPrior | None = None,
    rng: np.random.Generator | int | None = None,
) -> VanishingResult:
    """The vertical vanishing point of one image, and the vertical segments.

    A pure function of its arguments (safe to run in a process pool).

    Parameters
    ----------
    image_gray : (H, W) uint8 array (or (H, W, 3) BGR).
    options : VanishingOptions or None for the defaults.
    camera : Camera or None
        Intrinsics: with them the vertical direction is returned, the INS prior
        is possible, and lens distortion is removed from the segments first.
    prior : VPPrior or None (``VPPrior.none()``).
    rng : numpy Generator, seed, or None (``options.seed``).

    Returns
    -------
    VanishingResult
        ``status`` "no_vp" (with a message) instead of an exception when the
        image has no usable vertical structure.
    """
    options = options or VanishingOptions()
    prior = prior or VPPrior.none()
    img = as_gray_u8(image_gray)
    H, W = img.shape
    if camera is not None and (camera.width, camera.height) != (W, H):
        raise ValueError(
            f"camera is {camera.width}x{camera.height} but the image is {W}x{H}"
        )
    t_start = time.perf_counter()
    t0 = time.perf_counter()
    segs = detect_segments(img, options.lines).undistorted(camera)
    t_lines = time.perf_counter() - t0
    rng = np.random.default_rng(options.seed if rng is None else rng)
    K = camera.K if camera is not None else nominal_K(W, H)
    same_deg = (
        options.starts_same_deg if prior.kind == "ins" else options.restarts_same_deg
    )
    # Every start is a whole first pass: stopping a restart whose RANSAC
    # lands near a known VP lost `paper` seed 5 N_21 (11.8 deg off), whose
    # refinement swaps to the vertical pencil from a competitor's winner.
    results = _distinct(
        [
            estimate_vertical_vp(segs, (W, H), options, camera, p, rng)
            for p in _start_priors(prior, options.start_cones)
        ],
        K,
        same_deg,
    )
    if options.second_pass is None or results[0].vp is None:
        result = results[0]
    else:
        t0 = time.perf_counter()
        img2 = img
        if options.contrast_clip_limit > 0:
            img2 = equalize_local_contrast(
                img, options.contrast_clip_limit, options.contrast_tiles
            )
        grads = gradients(img2, options.second_pass.sigma_px)
        # One VP: its second pass as always; several: the one whose second
        # pass finds the most vertical edge length (``start_cones``).
        lengths = [
            _with_second_pass(r, img2, grads, options, camera, prior) for r in results
        ]
        result = _choose(results, lengths, prior, K, same_deg)
        result.time_s["second_pass_all"] = time.perf_counter() - t0
        if len(results) > 1:
            logger.debug(
                "%d distinct VPs from %d starts; second-pass lengths %s px",
                len(results),
                len(options.start_cones),
                np.round(lengths).tolist(),
            )
    result.time_s["lines"] = t_lines
    result.time_s["total"] = time.perf_counter() - t_start
    logger.debug("%s: %s", result.status, result.message)
    return result
