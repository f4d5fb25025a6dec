"""The registration's search (:func:`search`, steps 1-5 of
:func:`~obliq_colmap.registration.register_image` without the chance test):
segments, ground height and coarse pose, the tries of the strongest coarse
peaks, refinement, the result."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from obliq_colmap.geometry import Camera, Pose, vertical_vp_in_frame
from obliq_colmap.registration.hough import HoughGrid, HoughPeak, hough
from obliq_colmap.registration.options import (
    RegistrationOptions,
    RegistrationResult,
    at_image_scale,
)
from obliq_colmap.registration.refine import Fit, lens_of, radial_index, refine_rounds
from obliq_colmap.registration.segments import Segments, pairs_near, prepare_segments
from obliq_colmap.registration.tries import Try, finish_try, try_start
from obliq_colmap.registration.view import EZ, View, make_view

logger = logging.getLogger(__name__)


def _check_inputs(
    segments_px, vertical_direction_cam
) -> tuple[np.ndarray, np.ndarray | None]:
    seg = np.asarray(segments_px, float)
    if seg.size == 0:
        seg = seg.reshape(0, 2, 2)
    if seg.ndim != 3 or seg.shape[1:] != (2, 2):
        raise ValueError(f"segments_px must be (N, 2, 2), got shape {seg.shape}")
    n = None
    if vertical_direction_cam is not None:
        n = np.asarray(vertical_direction_cam, float).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
            raise ValueError(
                "vertical_direction_cam must be a finite nonzero (3,) vector, "
                f"got {n!r}"
            )
        n = n / np.linalg.norm(n)
    return seg, n


def _oriented_vertical(n: np.ndarray | None, prior: Pose) -> tuple[np.ndarray, str]:
    """The vertical direction (camera frame) oriented down the world, the
    prior's when ``n`` is None, and its source ("detected" or "prior")."""
    vertical_source = "detected"
    down_prior = prior.rotation @ -EZ
    if n is None:
        n = down_prior
        vertical_source = "prior"
    elif n @ down_prior < 0:
        n = -n  # orient down the world
    return n, vertical_source


def _undistorted_and_raw(
    seg: np.ndarray, camera: Camera, segments_undistorted: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The (N, 2, 2) segments in undistorted pixels and as detected (RAW)."""
    # RAW (as detected) endpoints are kept for a refinement of the distortion.
    raw = seg
    if len(seg) and camera.has_distortion:
        if segments_undistorted:
            raw = camera.distort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
        else:
            seg = camera.undistort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
    return seg, raw


def _median_depth(view: View, corner_rel: np.ndarray) -> float:
    """A viewing-distance scale before the ground height is known (m).

    The lower quartile of the horizontal distances to the corners that may be
    in view at some ground height: the far corners of that set belong to
    heights far below the true ground, so the median would overestimate.
    """
    d = np.linalg.norm(corner_rel, axis=1)
    return float(np.percentile(d, 25)) if len(d) else 100.0


def _search_windows(view: View, options: RegistrationOptions, depth_m: float):
    """(alpha half-range rad, centre half-range m, search radius px)."""
    k = options.search_sigmas
    alpha_half = k * math.radians(options.prior_rotation_sigma_deg)
    c_sigma = math.hypot(
        options.prior_position_sigma_m, options.prior_focal_sigma * depth_m
    )
    c_half = k * c_sigma
    if options.search_radius_px is not None:
        radius = float(options.search_radius_px)
    else:
        f = view.focal
        radius = math.hypot(f * alpha_half, f * c_half / depth_m)
    return alpha_half, c_half, radius


def search(
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions,
    segments_undistorted: bool,
) -> RegistrationResult:
    """:func:`~obliq_colmap.registration.register_image` without the chance test."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    seg, n = _check_inputs(segments_px, vertical_direction_cam)
    n, vertical_source = _oriented_vertical(n, prior)
    refine_vertical = options.refine_vertical == "always" or (
        options.refine_vertical == "auto" and vertical_source == "prior"
    )
    refine_focal = bool(options.refine_focal)
    view = make_view(camera, prior, n)

    def fail(message: str, **kw) -> RegistrationResult:
        timings["total"] = time.perf_counter() - t_start
        logger.debug("registration failed: %s", message)
        return RegistrationResult(
            success=False,
            cam_from_world=prior,
            vertical_direction=n,
            vertical_source=vertical_source,
            message=message,
            timings=timings,
            **kw,
        )

    if (
        not options.allow_vp_in_frame
        and (vp := vertical_vp_in_frame(camera, n)) is not None
    ):
        return fail(
            f"near-nadir view: the vertical vanishing point ({vp[0]:.0f}, "
            f"{vp[1]:.0f}) px lies inside the {camera.width} x {camera.height} "
            "frame; registration to the map's corners needs an oblique view"
        )

    # 1. Segments.
    t0 = time.perf_counter()
    seg, raw = _undistorted_and_raw(seg, camera, segments_undistorted)
    segs = prepare_segments(seg, view, options)
    timings["segments"] = time.perf_counter() - t0
    if len(segs) < options.min_segments:
        return fail(
            f"too few vertical segments: {len(segs)} usable of {len(seg)} "
            f"(need {options.min_segments})",
            num_segments=len(segs),
        )

    # 2. Ground height and coarse pose: 4-D Hough vote over (alpha, c, h).
    t0 = time.perf_counter()
    coarse = _coarse_vote(view, segs, camera, cadastre, options)
    if isinstance(coarse, str):
        return fail(coarse, num_segments=len(segs))
    timings["ground"] = time.perf_counter() - t0

    # 3.-4. The strongest peaks: fine pose vote, then a short RANSAC; the one
    # with the most inlier corners wins and gets the full RANSAC.
    t0 = time.perf_counter()
    tries = _try_starts(view, segs, cadastre, camera, coarse, options)
    timings["coarse"] = time.perf_counter() - t0
    for st, tr in zip(coarse.starts, tries, strict=True):
        logger.debug(
            "start h %.1f votes %.0f -> %s",
            st.height,
            st.votes,
            None if tr is None else (tr.count, round(tr.cost, 1), len(tr.cand.corner)),
        )
    tries = [t for t in tries if t is not None]
    if not tries:
        return fail(
            "no consensus: no candidate ground height has matching pairs",
            num_segments=len(segs),
        )
    best_try = max(tries, key=lambda t: (t.count, -t.cost))
    t0 = time.perf_counter()
    # Every try's RANSAC starts from the same seed: the winner's full run
    # continues its short one.
    best_try = finish_try(view, segs, best_try, options)
    timings["ransac"] = time.perf_counter() - t0
    h0, vis, corner_rel, depth_m, cand = (
        best_try.h0,
        best_try.vis,
        best_try.corner_rel,
        best_try.depth_m,
        best_try.cand,
    )
    options = at_image_scale(options, view.focal, depth_m)
    alpha_r, c_r, plane_r, n_best, trials = (
        best_try.alpha,
        best_try.c_xy,
        best_try.plane,
        best_try.count,
        best_try.trials,
    )
    num_candidates = len(cand.corner)
    common = dict(
        num_segments=len(segs),
        num_candidates=num_candidates,
        num_trials=trials + sum(t.trials for t in tries),
        inlier_ratio=n_best / max(num_candidates, 1),
        ground_height=h0,
    )
    if n_best < options.min_inliers:
        return fail(
            f"no consensus: best hypothesis has {n_best} inlier corners "
            f"(need {options.min_inliers}) among {num_candidates} candidates",
            **common,
        )

    # 5. Refinement and re-scoring.
    t0 = time.perf_counter()
    f0 = view.focal
    k_index = radial_index(camera.model) if options.refine_distortion else None
    fit = refine_rounds(
        view,
        segs,
        raw,
        corner_rel,
        vis,
        cand,
        alpha_r,
        c_r,
        plane_r,
        lens_of(camera, k_index, options),
        (refine_focal, refine_vertical, k_index is not None),
        depth_m,
        cadastre,
        options,
    )
    ci = fit.ci
    timings["refine"] = time.perf_counter() - t0
    common["num_inliers"] = len(ci)
    if len(ci) < options.min_inliers:
        return fail(
            f"no consensus after refinement: {len(ci)} inlier corners", **common
        )
    # Degenerate geometry: the inliers must not lie on one vertical line.
    spread = np.linalg.svd(corner_rel[ci] - corner_rel[ci].mean(0), compute_uv=False)
    if spread[0] < 1.0:
        return fail("degenerate geometry: the inlier corners coincide", **common)

    return _registered(
        fit,
        seg,
        corner_rel,
        vis,
        camera,
        f0,
        k_index,
        "refined" if refine_vertical else vertical_source,
        common,
        trials,
        timings,
        t_start,
    )


@dataclass
class _Coarse:
    """Step 2's outcome: the coarse vote, its strongest peaks (one per
    candidate ground height, strongest first) and the search windows (alpha
    half-range rad, centre half-range m, search radius px)."""

    grid: HoughGrid
    starts: list[HoughPeak]
    alpha_half: float
    c_half: float
    radius: float


def _coarse_vote(
    view: View,
    segs: Segments,
    camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> _Coarse | str:
    """Step 2: ground height and coarse pose, a 4-D Hough vote over (alpha, c,
    h) of the pairs near the prior; the failure message when it cannot run."""
    from obliq_colmap.cadastre import visible_corners

    alt_lo, alt_hi = options.altitude_range_m
    c0z = view.c0[2]
    if options.ground_height is not None:
        h_bounds = (
            options.ground_height - options.candidate_height_tolerance_m,
            options.ground_height + options.candidate_height_tolerance_m,
        )
    else:
        h_bounds = (c0z - alt_hi, c0z - alt_lo)
    prior0 = view.pose(0.0, np.zeros(2))
    wide = visible_corners(
        cadastre,
        camera,
        prior0,
        ground_height=h_bounds[0],
        height_range_m=(0.0, h_bounds[1] - h_bounds[0] + options.height_range_m[1]),
        margin_px=0.25 * max(camera.width, camera.height),
        use_building_heights=False,
    )
    if len(wide) < options.min_inliers:
        return f"too few map corners in view of the prior: {len(wide)}"
    corner_rel = cadastre.corner_xy[wide] - view.c0[:2]
    # Viewing distance for the search windows (the horizontal distance to the
    # map corners; refined from the ground height below).
    depth_m = _median_depth(view, corner_rel)
    alpha_half, c_half, radius = _search_windows(view, options, depth_m)
    ii, jj = pairs_near(
        view,
        segs,
        corner_rel,
        0.0,
        np.zeros(2),
        radius,
        h_range=(h_bounds[0] - c_half, h_bounds[1] + c_half),
    )
    if len(segs) > options.coarse_max_segments:
        # The coarse vote needs the strong structure only: its cost is
        # linear in the pairs, and the long segments (building edges from
        # the ground up) carry most of the true pairs.
        rank = np.empty(len(segs), int)
        rank[np.argsort(-segs.length, kind="stable")] = np.arange(len(segs))
        keep = rank[jj] < options.coarse_max_segments
        ii, jj = ii[keep], jj[keep]
    if len(ii) < 3:
        return f"no consensus: {len(ii)} candidate pairs near the prior"
    coarse = hough(
        view,
        segs,
        corner_rel,
        ii,
        jj,
        0.0,
        alpha_half,
        np.zeros(2),
        c_half,
        tuple(1e-3 * c * view.focal for c in options.coarse_cells_mrad),
        depth_m,
        options.hough_max_cells,
        heights=(h_bounds[0], h_bounds[1], options.coarse_height_step_m),
    )
    separation = (
        1,
        1,
        1,
        int(
            math.ceil(
                options.candidate_height_tolerance_m / options.coarse_height_step_m
            )
        ),
    )
    num = options.num_candidates_verified
    starts = coarse.peaks_by_height(num, separation[3])
    if options.fill_starts_with_poses and len(starts) < num:
        # Few candidate heights (a given ground height: its band of a few
        # cells): the remaining starts are the next strongest poses, so that
        # a weak image's true pose need not be the strongest coarse cell of
        # its height, where chance alignments of clutter compete with it.
        starts += _more_poses(coarse.peaks(num, separation), starts, num)
    return _Coarse(coarse, starts, alpha_half, c_half, radius)


def _more_poses(
    peaks: list[HoughPeak], starts: list[HoughPeak], num: int
) -> list[HoughPeak]:
    """The ``peaks`` that are not already ``starts`` (same pose and height),
    in their order, up to ``num`` starts in all."""

    def key(p: HoughPeak) -> tuple:
        return (p.alpha, *np.round(p.c_xy, 9), p.height)

    seen = {key(p) for p in starts}
    more = [p for p in peaks if key(p) not in seen]
    return more[: max(0, num - len(starts))]


def _try_starts(
    view: View,
    segs: Segments,
    cadastre,
    camera: Camera,
    coarse: _Coarse,
    options: RegistrationOptions,
) -> list[Try | None]:
    """Steps 3-4 from each of the coarse peaks (:func:`try_start`), in their
    order; None where nothing matches."""
    tries = []
    for start in coarse.starts:
        h_k = (
            start.height
            if options.ground_height is None
            else float(options.ground_height)
        )
        tries.append(
            try_start(
                view,
                segs,
                cadastre,
                camera,
                start,
                h_k,
                coarse.grid,
                coarse.radius,
                coarse.alpha_half,
                coarse.c_half,
                options,
                np.random.default_rng(options.seed),
            )
        )
    return tries


def _registered(
    fit: Fit,
    seg: np.ndarray,
    corner_rel: np.ndarray,
    vis: np.ndarray,
    camera: Camera,
    f0: float,
    k_index: int | None,
    vertical_source: str,
    common: dict,
    trials: int,
    timings: dict[str, float],
    t_start: float,
) -> RegistrationResult:
    """The result of a successful search from its refined ``fit`` (step 5):
    ``seg`` the input segments (undistorted pixels), ``corner_rel`` and ``vis``
    the best try's corners, ``f0`` the focal length before the refinement,
    ``common`` the counts so far, ``trials`` the best try's RANSAC samples."""
    view, segs, lens, alpha, c_xy, plane = (
        fit.view,
        fit.segs,
        fit.lens,
        fit.alpha,
        fit.c_xy,
        fit.plane,
    )
    ci, sj, resid = fit.ci, fit.sj, fit.resid
    distortion_refined = fit.distortion_refined
    num_candidates = common["num_candidates"]
    pose = view.pose(alpha, c_xy)
    centroid = corner_rel[ci].mean(axis=0)
    common["ground_height"] = float(
        plane[0] * centroid[0] + plane[1] * centroid[1] + plane[2]
    )
    plane_abs = np.array(
        [plane[0], plane[1], plane[2] - plane[0] * view.c0[0] - plane[1] * view.c0[1]]
    )
    rms = float(np.sqrt(np.mean(resid**2))) if resid.size else math.nan
    timings["total"] = time.perf_counter() - t_start
    result_camera = camera.with_focal_scaled(view.focal / f0)
    if lens is not None and k_index is not None:
        result_camera.params[k_index] = lens.camera.params[k_index]
    return RegistrationResult(
        camera=result_camera,
        distortion_refined=distortion_refined,
        success=True,
        cam_from_world=pose,
        vertical_direction=view.n.copy(),
        vertical_source=vertical_source,
        inlier_pairs=np.column_stack([vis[ci], segs.index[sj]]).astype(int),
        inlier_segments_px=seg[segs.index[sj]].copy(),
        height_plane=plane_abs,
        residual_rms_px=rms,
        message=f"{len(ci)} inlier corners of {num_candidates} candidates, "
        f"RMS {rms:.2f} px, {trials} trials",
        timings=timings,
        **common,
    )
