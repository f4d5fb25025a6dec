"""The bundle's rounds (stage 3's solve): :func:`bundle_stage`.

After :func:`~obliq_colmap.adjustment.facade_stage` and the datum
corrections, a first solve of the bundle problem, then rounds that drop the
outliers (:func:`without_outliers`), re-triangulate every track as a 3D
horizontal line near its wall (:func:`with_track_lines`) and weight each
residual kind by its robust spread (:func:`with_variance_components`),
solving again each time. The last solve's per-image diagnostics (RMS, share
of constraints kept, precision, edge-end offsets) go into the
:class:`~obliq_colmap.adjustment.Stage3` the verdicts read.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import NamedTuple

import numpy as np

from obliq_colmap.adjustment.options import AdjustmentOptions
from obliq_colmap.adjustment.problem import Stage3, build_bundle_problem, facade_stage
from obliq_colmap.adjustment.ties import (
    TiePoints,
    consistent_pairs,
    reprojection_errors,
    triangulate_tie_tracks,
)
from obliq_colmap.adjustment.tracks import triangulate_tracks
from obliq_colmap.adjustment.verdicts import edge_end_offsets
from obliq_colmap.bundle import (
    BundleOptions,
    BundleProblem,
    BundleResult,
    solve_bundle,
    vertical_row_pairs,
)
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = [
    "AdjustedBlock",
    "bundle_stage",
    "with_solved_lines",
    "with_track_lines",
    "with_variance_components",
    "without_outliers",
]

logger = logging.getLogger(__name__)


class AdjustedBlock(NamedTuple):
    """What :func:`bundle_stage` returns."""

    #: The block after stage 3 (the per-image state when there are no facade
    #: constraints or the solve fails).
    state: BlockState
    #: The last solve's result, or None (skipped or failed).
    bundle: BundleResult | None
    #: The facade edges and tracks, and the bundle's per-image diagnostics.
    stage3: Stage3


def bundle_stage(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    options: AdjustmentOptions,
    timings: dict[str, float],
    ties: TiePoints | None = None,
) -> AdjustedBlock:
    """Stage 3: facade edges, matching, datum corrections and the bundle.

    ``ties``: tie points matched across the block (their tracks), observed
    in the bundle (``None``: none).

    Returns the block as it stands after it (the per-image state when there
    are no facade constraints or the solve fails), the bundle's result or
    None, and the facade edges and tracks.
    """
    t0 = time.perf_counter()
    stage3 = facade_stage(inputs, state, outcomes, options)
    timings["facades"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = None
    if stage3.tracks.num_observations == 0:
        # Corner-to-vertical-line constraints alone cannot observe a camera's
        # height nor its focal/distance trade-off (measured: the solve drifts
        # by tens of metres): without facade constraints the per-image
        # registration is the better result.
        logger.warning(
            "no facade-edge constraints: the bundle is skipped and the "
            "per-image registration is written"
        )
    else:
        state = state.with_datum_correction(
            dict(zip(stage3.ids, stage3.tracks.datum_correction, strict=True))
        )
        problem = build_bundle_problem(
            inputs,
            outcomes,
            state,
            stage3,
            ties,
            options.tie_point_options,
            options.measured_vertical_directions,
            options.map_vertex_sigma_m,
            options.level_height_m,
        )
        # The tie points enter from the second solve, triangulated from the
        # first and without the image pairs it shows on a wrong geometry
        # (with_tie_points); the first is the map's alone.
        tie_obs = (problem.tie_image, problem.tie_point, problem.tie_xy, problem.tie_sd)
        problem = problem.without_ties()
        bundle_options = dataclasses.replace(
            options.bundle,
            corner_heights="fixed",
            # The corners stay where the map has them; their error moves
            # every row of a corner in every image together, which the
            # precision carries (the solve is unchanged).
            map_corner_sigma_m=options.map_vertex_sigma_m,
            horizontal_offset_sigma_m=options.track_offset_sigma_m,
            # On each segment's own line the two ends' rows also say its
            # direction, with less noise than the map's: weighted apart.
            vertical_direction_sigma_px=(
                options.bundle.vertical_sigma_px
                if options.measured_vertical_directions
                else None
            ),
        )
        try:
            # A wide loss first: after stage 2 and the datum corrections some
            # images still sit metres too high or low (tens of pixels), where
            # a tight robust loss has no gradient left to pull them in.
            first = bundle_options
            if options.initial_loss_scale_px > 0:
                first = dataclasses.replace(
                    bundle_options,
                    loss="huber",
                    loss_scale_px=max(
                        options.initial_loss_scale_px, bundle_options.loss_scale_px
                    ),
                )
            # The precision (one more linearisation and a dense inverse) is
            # wanted of the last solve only, which is known before it runs.
            # The VPs are evaluated against the map-only first solve and
            # enter from the second, with the factor that solve shows: at
            # stage 1's stated sd they would pull the first solve before
            # anything says how good they are, and the outlier rounds would
            # then drop the map's constraints that disagree with them.
            rounds = options.outlier_rounds
            if rounds > 0:
                # The facade lines enter from the second solve too: the
                # first's rows, each a point on its map wall, are what shows
                # a track of an edge off the wall (a taller building behind)
                # as an outlier; a free 3D line would take it in.
                first = dataclasses.replace(first, vp_in_fit=False, facade_lines=False)
            result = solve_bundle(problem, _precision_if(first, rounds == 0))
            initial = problem
            # Per horizontal row: the track observation it is (facade rows)
            # or -1 (ground rows); filtered with the rows.
            obs = stage3.row_obs
            scale_obs = _observation_pixel_scale(stage3)
            for k in range(rounds):
                problem, kv, kh = without_outliers(
                    problem,
                    result,
                    options.outlier_factor,
                    options.outlier_floor_px,
                    horizontal_pixel_scale=scale_obs[obs],
                )
                obs = obs[kh]
                if k == 0 and len(tie_obs[0]):
                    problem = with_tie_points(problem, result, *tie_obs, options)
                lines = bundle_options.facade_lines
                if lines and len(result.facade_offsets):
                    problem = with_solved_lines(problem, result)
                elif options.track_lines or lines:
                    problem = with_track_lines(
                        problem, result, inputs, stage3, obs, options, lines
                    )
                if options.variance_components:
                    # Each kind weighted by its own noise (map corners ~1 px,
                    # facade edges ~0.15 px). A facade line fits 3 of its
                    # 2n rows and 2 prior rows: 1/2 unknown per observation.
                    unknowns = 0.5 if lines else 2 if options.track_lines else 1
                    # The VPs are tested from the second round on: the first
                    # solve's map rows still held their own outliers.
                    with_vp = set(problem.vertical_vps or {})
                    problem, bundle_options = with_variance_components(
                        problem, result, bundle_options, kh, unknowns, k > 0
                    )
                    for i in with_vp - set(problem.vertical_vps or {}):
                        stage3.vp_rejected[i] = result.vp_angle_deg.get(i, math.nan)
                last = (kv.all() and kh.all()) or k == rounds - 1
                result = solve_bundle(problem, _precision_if(bundle_options, last))
                if last:
                    break
        except ValueError as exc:
            logger.warning("bundle failed (%s): the per-image result is kept", exc)
            result = None
        else:
            stage3.bundle_problem = problem
            stage3.kept_observations = np.unique(obs[obs >= 0])
            state = state.with_bundle(result, problem.image_camera)
            stage3.bundle_rms = _rms_per_image(problem, result)
            stage3.constraints_kept = _kept_share(initial, problem)
            stage3.bundle_precision = dict(result.image_precision_px)
            stage3.tie_fit = _tie_fit(problem, result)
            stage3.end_offset_px = edge_end_offsets(
                inputs,
                outcomes,
                state,
                stage3.ids,
                measured_directions=options.measured_vertical_directions,
            )
    timings["bundle"] = time.perf_counter() - t0
    return AdjustedBlock(state, result, stage3)


def with_tie_points(
    problem: BundleProblem,
    result: BundleResult,
    image: np.ndarray,
    point: np.ndarray,
    xy: np.ndarray,
    sd: np.ndarray | None,
    options: AdjustmentOptions,
) -> BundleProblem:
    """``problem`` with the tie observations (image index, track, raw
    pixel, relative sd or None; (O,) each) as rows, triangulated from the solved block
    ``result``, without the tracks of image pairs the block shows on a
    wrong geometry (:func:`~obliq_colmap.adjustment.ties.consistent_pairs`)."""
    ids = problem.image_ids
    cams = [result.cameras[problem.image_camera[i]].to_pycolmap() for i in ids]
    poses = [result.poses[i].to_rigid3d() for i in ids]
    xyz = triangulate_tie_tracks(cams, poses, point, image, xy)
    err = reprojection_errors(cams, poses, xyz, point, image, xy)
    good = consistent_pairs(
        err, image, point, options.tie_pair_factor, options.tie_pair_floor_px
    )
    keep = good[point] & np.isfinite(err)
    keep &= np.bincount(point[keep], minlength=len(good))[point] >= 2
    used, track = np.unique(point[keep], return_inverse=True)
    logger.info(
        "bundle: %d tie points, %d observations (%d tracks on image pairs the"
        " block shows on a wrong geometry left out)",
        len(used),
        int(keep.sum()),
        int((~good).sum()),
    )
    return dataclasses.replace(
        problem,
        tie_xyz=xyz[used],
        tie_image=image[keep],
        tie_point=track,
        tie_xy=xy[keep],
        tie_sd=None if sd is None else sd[keep],
    )


def _precision_if(options: BundleOptions, wanted: bool) -> BundleOptions:
    """``options`` with the precision computed only where ``wanted``."""
    wanted = wanted and options.compute_precision
    return dataclasses.replace(options, compute_precision=wanted)


def _observation_pixel_scale(stage3: Stage3) -> np.ndarray:
    """(H,) per track observation its segment's ``pixel_scale``."""
    t = stage3.tracks
    scale = np.concatenate([f.pixel_scale for f in stage3.facades] + [np.zeros(0)])
    offset = np.cumsum([0] + [len(f) for f in stage3.facades])
    return scale[offset[t.image] + t.row] if t.num_observations else np.zeros(0)


def _rms_per_image(
    problem: BundleProblem, result: BundleResult
) -> dict[int, tuple[float, float]]:
    """Image id -> RMS (px) of its vertical and horizontal residuals."""
    out = {}
    for kind, img, r in (
        (0, problem.vertical_image, result.vertical_residuals_px),
        (1, problem.horizontal_image, result.horizontal_residuals_px),
    ):
        n = np.bincount(img, minlength=len(problem.image_ids))
        ss = np.bincount(img, r * r, minlength=len(problem.image_ids))
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(ss / n)
        for k, i in enumerate(problem.image_ids):
            out.setdefault(i, [math.nan, math.nan])[kind] = float(rms[k])
    return {i: (v[0], v[1]) for i, v in out.items()}


def _tie_fit(
    problem: BundleProblem, result: BundleResult
) -> dict[int, tuple[int, float]]:
    """Image id -> (its observations of tie points that another head's
    camera sees too, the median reprojection error of all its tie
    observations in px) in the solve ``result`` of ``problem``; images
    without tie observations absent. Only another head's views tie an image
    across the weak mode its own head shares (urban-101 seed 2: S_05 13.7 px
    off with 104 tie observations at a typical error, 24 of them across
    heads; 61-66 where it was right)."""
    if not len(problem.tie_image):
        return {}
    err = np.linalg.norm(result.tie_residuals_px, axis=1)
    cam = np.array([problem.image_camera[i] for i in problem.image_ids])
    obs_cam = cam[problem.tie_image]
    n_points = len(problem.tie_xyz)
    heads = np.zeros(n_points, np.int64)
    for c in np.unique(cam):
        heads += np.bincount(problem.tie_point[obs_cam == c], minlength=n_points) > 0
    across = heads[problem.tie_point] >= 2
    n_img = len(problem.image_ids)
    count = np.bincount(problem.tie_image, weights=across, minlength=n_img)
    order = np.argsort(problem.tie_image, kind="stable")
    per_image = np.split(err[order], np.cumsum(np.bincount(problem.tie_image))[:-1])
    return {
        problem.image_ids[k]: (int(count[k]), float(np.median(e)))
        for k, e in enumerate(per_image)
        if len(e)
    }


def _kept_share(initial: BundleProblem, final: BundleProblem) -> dict[int, float]:
    """Image id -> share of its constraints (vertical and horizontal rows)
    of ``initial`` still in ``final`` (NaN for an image without any)."""
    m = len(initial.image_ids)

    def rows(p: BundleProblem) -> np.ndarray:
        return np.bincount(p.vertical_image, minlength=m) + np.bincount(
            p.horizontal_image, minlength=m
        )

    with np.errstate(invalid="ignore", divide="ignore"):
        share = rows(final) / rows(initial)
    return {i: float(share[k]) for k, i in enumerate(initial.image_ids)}


def _robust_sigma(r: np.ndarray, default: float) -> float:
    """1.4826 MAD of residuals (px), at least 0.05; ``default`` when empty."""
    return float(max(1.4826 * np.median(np.abs(r)), 0.05)) if len(r) else default


#: Median of a chi-square variable with 2 degrees of freedom (2 ln 2).
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)

#: Significance level of the test of each VP against the rest of the block
#: (Baarda's alpha_0 of data snooping).
VP_TEST_ALPHA = 0.001
#: Its critical value: chi-square with 2 degrees of freedom, whose survival
#: function is exp(-x / 2).
_VP_TEST_CRITICAL = -2.0 * math.log(VP_TEST_ALPHA)


def _vp_median_scale(result: BundleResult, default: float) -> float:
    """The factor that makes the median whitened squared VP residual that of
    a chi-square with 2 dof, never below 1; the fallback where the solve has
    no redundancy numbers (no cofactor matrix)."""
    chi2 = np.array(list(result.vp_chi2.values()), float)
    chi2 = chi2[np.isfinite(chi2)]
    if len(chi2) == 0:
        return default
    return float(max(1.0, math.sqrt(np.median(chi2) / _CHI2_2_MEDIAN)))


def _loo_tests(z0: np.ndarray, A: np.ndarray, scale: float) -> np.ndarray:
    """(n,) ``z0^T (scale^2 I + A)^-1 z0`` per VP (stated units)."""
    C = A + scale * scale * np.eye(2)
    return np.einsum("ki,ki->k", z0, np.linalg.solve(C, z0[..., None])[..., 0])


def _scale_where(stat, target: float, z0: np.ndarray, A: np.ndarray) -> float:
    """The factor ``s >= 1`` at which ``stat`` of the leave-one-out tests
    equals ``target``; 1 where it is below already. ``stat`` of the tests
    decreases with ``s``: bisection on log s."""
    if stat(_loo_tests(z0, A, 1.0)) <= target:
        return 1.0
    lo, hi = 0.0, math.log(1e4)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if stat(_loo_tests(z0, A, math.exp(mid))) > target:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def _moment_scale(z0: np.ndarray, A: np.ndarray) -> float:
    """The factor at which the tests average 2, their expectation."""
    return _scale_where(np.mean, 2.0, z0, A)


def _median_scale(z0: np.ndarray, A: np.ndarray) -> float:
    """The factor at which the tests' median is that of a chi-square with 2
    dof (2 ln 2): robust to up to half the VPs off."""
    return _scale_where(np.median, _CHI2_2_MEDIAN, z0, A)


def vp_components(
    result: BundleResult, scale: float, test: bool = True
) -> tuple[float, list[int]]:
    """The factor on stage 1's stated VP standard deviations, and the images
    whose VP the block rejects, from the last solve (VP sd factor ``scale``).

    Each VP is compared with the solution WITHOUT it (``BundleResult.vp_loo``:
    its residual there ``z0`` and the others' cofactor ``A`` of that
    direction, in stage 1's stated units), where ``E[z0 z0^T] = s^2 I + A``
    if stage 1's covariance is right up to the factor ``s``. The factor is
    the variance component of the VP group estimated from these predicted
    residuals: the ``s`` at which ``z0^T (s^2 I + A)^-1 z0`` averages 2 over
    the VPs (its expectation, chi-square with 2 dof). Unlike the VPs' own
    residuals in the fit, the predicted ones do not shrink where a VP holds
    its image's tilt alone (redundancy near 0), so such a VP cannot read as
    consistent however wrong it is; unlike the one-step Förstner estimate
    (weighted squared residuals over redundancy numbers, with the Cauchy
    weights), it does not need many re-solves to converge when the stated
    sd is several times too small. Never below 1: the segments the map rows
    use were fitted through stage 1's VP, so the VPs agree with the bundle
    better than independent observations would, and stage 1's covariance is
    the most it claims.

    With ``test``, data snooping: a VP whose test at the factor exceeds the
    chi-square (2 dof) critical value at ``VP_TEST_ALPHA`` is rejected. The
    first factor is the robust one (the tests' median at that of a
    chi-square with 2 dof); then the factor is the mean's over the VPs not
    rejected and the test is repeated with it, until the set of rejected
    VPs no longer changes: rejected VPs do not enter the factor (estimated
    from all, it grows with the wrong VPs until none of them is rejected).
    Without ``test``: the robust factor alone.

    Without the leave-one-out quantities (no cofactor matrix): the median
    rule (:func:`_vp_median_scale`), nothing rejected.
    """
    ids = [
        i
        for i, (z0, A) in result.vp_loo.items()
        if np.all(np.isfinite(z0)) and np.all(np.isfinite(A))
    ]
    if not ids:
        return _vp_median_scale(result, scale), []
    z0 = np.array([result.vp_loo[i][0] for i in ids], float)
    A = np.array([result.vp_loo[i][1] for i in ids], float)
    # A robust start (the median of the tests, which up to half the VPs off
    # cannot move), then the VPs it rejects left out of the mean: estimated
    # from all, the factor grows with the wrong VPs and hides them (masking).
    # Without the test (the map's own outliers still in), the robust factor
    # alone.
    new = _median_scale(z0, A)
    if not test:
        return float(new), []
    bad = _loo_tests(z0, A, new) > _VP_TEST_CRITICAL
    for _ in range(len(ids) + 1):
        if bad.all():
            break
        new = _moment_scale(z0[~bad], A[~bad])
        now = _loo_tests(z0, A, new) > _VP_TEST_CRITICAL
        if np.array_equal(now, bad):
            break
        bad = now
    return float(new), [ids[k] for k in np.flatnonzero(bad)]


def with_variance_components(
    problem: BundleProblem,
    result: BundleResult,
    options: BundleOptions,
    kept: np.ndarray,
    unknowns_per_track: float,
    test_vps: bool = True,
) -> tuple[BundleProblem, BundleOptions]:
    """Both residual kinds weighted by their robust standard deviation in
    the last solve: vertical (map corners) and horizontal (facade tracks);
    with VP observations, stage 1's stated VP covariance scaled by the
    group's variance component, and the VPs the block rejects dropped
    (:func:`vp_components`; ``test_vps`` False: no test, e.g. while the map
    rows still hold their own outliers).
    ``kept``: the horizontal rows of the last solve still in ``problem``.

    A track of n observations fits ``unknowns_per_track`` of them exactly
    (a 3D line: offset and height), so its residuals are shrunk by
    sqrt((n - u) / n): they are scaled back, and tracks with n <= u (no
    redundancy, zero residuals) do not count. Without that the spread of the
    two-image tracks, half of all, reads as ~0 and the facade lines get
    hundreds of times the weight their noise deserves.
    """
    rh = result.horizontal_residuals_px[kept]
    track = problem.horizontal_height
    n = np.bincount(track, minlength=len(problem.facade_heights))[track]
    u = unknowns_per_track
    with np.errstate(divide="ignore", invalid="ignore"):
        scaled = rh * np.sqrt(np.where(n > u, n / (n - u), 1.0))
    direction_sigma = options.vertical_direction_sigma_px
    pairs = result.vertical_pair_residuals_px
    if direction_sigma is not None and len(pairs):
        # each segment's ends: the sum carries the map's noise, the
        # difference only the segment's direction
        vertical_sigma = _robust_sigma(pairs[:, 0], options.vertical_sigma_px)
        direction_sigma = _robust_sigma(pairs[:, 1], direction_sigma)
    else:
        vertical_sigma = _robust_sigma(
            result.vertical_residuals_px, options.vertical_sigma_px
        )
    vp_scale, rejected = options.vp_sigma_scale, []
    if result.vp_chi2:
        vp_scale, rejected = vp_components(result, options.vp_sigma_scale, test_vps)
    options = dataclasses.replace(
        options,
        vertical_sigma_px=vertical_sigma,
        vertical_direction_sigma_px=direction_sigma,
        horizontal_sigma_px=_robust_sigma(scaled[n > u], options.horizontal_sigma_px),
        vp_sigma_scale=vp_scale,
        tie_sigma_px=_tie_sigma(result, options.tie_sigma_px),
    )
    logger.info(
        "bundle: sigma px: map corners %.3f%s, facade lines %.3f, tie points %.3f;"
        " VP sd x %.2f",
        options.vertical_sigma_px,
        ""
        if direction_sigma is None
        else f" (segment directions {direction_sigma:.3f})",
        options.horizontal_sigma_px,
        options.tie_sigma_px,
        options.vp_sigma_scale,
    )
    if rejected:
        logger.info(
            "bundle: VPs rejected against the block (test > %.1f): %s",
            _VP_TEST_CRITICAL,
            ", ".join(
                f"{i} ({result.vp_angle_deg.get(i, math.nan):.2f} deg)"
                for i in rejected
            ),
        )
        drop = set(rejected)
        problem = dataclasses.replace(
            problem,
            vertical_vps={
                i: v for i, v in problem.vertical_vps.items() if i not in drop
            },
            vertical_vp_covariances={
                i: c
                for i, c in problem.vertical_vp_covariances.items()
                if i not in drop
            },
        )
    return problem, options


def _tie_sigma(result: BundleResult, default: float) -> float:
    """Robust sd (px, per axis) of the last solve's tie observations, each
    scaled back for its point's 3 unknowns
    (:attr:`BundleResult.tie_residuals_scaled_px`)."""
    r = result.tie_residuals_scaled_px
    return _robust_sigma(r.ravel(), default) if len(r) else default


def with_track_lines(
    problem: BundleProblem,
    result: BundleResult,
    inputs: Inputs,
    stage3: Stage3,
    obs: np.ndarray,
    options: AdjustmentOptions,
    as_lines: bool = False,
) -> BundleProblem:
    """The problem with each track re-triangulated as a 3D horizontal line.

    The facade constraint's point ``x_j + h_j z`` sits on the map edge; a
    roof rim overhangs it and a parapet stands back, so the point is moved
    to the track's line (:func:`~obliq_colmap.adjustment.triangulate_tracks`,
    with the solved cameras) and its height restarted there. ``obs``:
    indices into the tracks' observations of the problem's horizontal
    constraints. ``as_lines``: the start of the facade lines
    (``BundleOptions.facade_lines``): the offsets as their start, the
    anchors left on the map edges.
    """
    t = stage3.tracks
    ids = problem.image_ids
    cams = [result.cameras[problem.image_camera[i]] for i in ids]
    poses = [result.poses[i] for i in ids]
    o = obs
    px_per_m = np.concatenate([f.px_per_m for f in stage3.facades])
    offset = np.cumsum([0] + [len(f) for f in stage3.facades])
    ppm = px_per_m[offset[t.image[o]] + t.row[o]]
    normal = inputs.cadastre.edge_normal[t.edge]
    d, h = triangulate_tracks(
        t.image[o],
        t.track[o],
        stage3.ends_raw[o],
        cams,
        poses,
        t.anchor_xy,
        normal,
        ppm,
        offset_sigma_m=options.track_offset_sigma_m,
    )
    J = t.num_tracks
    heights = result.facade_heights.copy()
    heights[:J] = np.where(np.isfinite(h), h, heights[:J])
    if as_lines:
        return dataclasses.replace(
            problem,
            facade_heights=heights,
            facade_offsets=np.pad(d, (0, len(heights) - J)),
            facade_angles=np.zeros(len(heights)),
        )
    anchor = (t.anchor_xy + d[:, None] * normal)[problem.horizontal_height]
    return dataclasses.replace(
        problem,
        cameras=result.cameras,
        poses=result.poses,
        facade_heights=heights,
        horizontal_anchor_xy=anchor,
        # The offsets were fitted to these observations: the bundle's
        # precision counts them as unknowns.
        horizontal_offset_normal=normal[problem.horizontal_height],
    )


def with_solved_lines(problem: BundleProblem, result: BundleResult) -> BundleProblem:
    """The problem started at the facade lines (height, offset, angle) that
    the solve ``result`` gave (``BundleOptions.facade_lines``)."""
    return dataclasses.replace(
        problem,
        facade_heights=result.facade_heights,
        facade_offsets=result.facade_offsets,
        facade_angles=result.facade_angles,
    )


def without_outliers(
    problem: BundleProblem,
    result: BundleResult,
    factor: float,
    floor_px: float,
    horizontal_pixel_scale: np.ndarray | None = None,
) -> tuple[BundleProblem, np.ndarray, np.ndarray]:
    """The problem without the constraints the solved block rejects.

    A residual is an outlier when it exceeds ``factor`` robust standard
    deviations (1.4826 MAD) of the residuals of its kind, and ``floor_px``
    (for a horizontal row times its ``horizontal_pixel_scale`` (H,): pixels
    of the image its segment was detected in; default 1).
    Facade heights no longer observed keep their slot (unobserved heights
    are eliminated per residual anyway). Returns the reduced problem, started
    at the result, and the masks of the kept vertical and horizontal
    constraints.
    """

    def keep(r: np.ndarray, floor: np.ndarray | float) -> np.ndarray:
        return within_robust_bound(r, factor, floor)

    rh = result.horizontal_residuals_px
    scale = 1.0 if horizontal_pixel_scale is None else horizontal_pixel_scale
    kv = keep(result.vertical_residuals_px, floor_px)
    pairs = result.vertical_pair_residuals_px
    if len(pairs):
        # A segment weighted as its sum and difference goes as a whole, when
        # its position (the sum) is off: a wrong match. A direction off (a
        # bent or cluttered edge) is left to the difference row's robust
        # loss, which scales with its sd.
        a, b = vertical_row_pairs(problem)
        kv[a] = kv[b] = keep(pairs[:, 0], floor_px)
    kh = keep(rh, floor_px * np.broadcast_to(scale, rh.shape))
    p = problem
    reduced = BundleProblem(
        cameras=result.cameras,
        poses=result.poses,
        image_camera=p.image_camera,
        image_ids=p.image_ids,
        corner_xy=p.corner_xy,
        corner_heights=p.corner_heights,
        vertical_image=p.vertical_image[kv],
        vertical_corner=p.vertical_corner[kv],
        vertical_line=p.vertical_line[kv],
        facade_heights=result.facade_heights,
        horizontal_image=p.horizontal_image[kh],
        horizontal_height=p.horizontal_height[kh],
        horizontal_anchor_xy=p.horizontal_anchor_xy[kh],
        horizontal_line=p.horizontal_line[kh],
        horizontal_offset_normal=(
            None
            if p.horizontal_offset_normal is None
            else p.horizontal_offset_normal[kh]
        ),
        horizontal_ends=None if p.horizontal_ends is None else p.horizontal_ends[kh],
        facade_direction=p.facade_direction,
        facade_angle_sigma=p.facade_angle_sigma,
        facade_level=p.facade_level,
        **_solved_lines(result),
        prior_rotations=p.prior_rotations,
        prior_centers=p.prior_centers,
        prior_principal_points=p.prior_principal_points,
        vertical_vps=p.vertical_vps,
        vertical_vp_covariances=p.vertical_vp_covariances,
        **_ties_kept(p, result, factor, floor_px),
    )
    logger.info(
        "bundle: %d of %d vertical and %d of %d horizontal constraints rejected;"
        " %d of %d tie observations",
        (~kv).sum(),
        len(kv),
        (~kh).sum(),
        len(kh),
        len(p.tie_image) - len(reduced.tie_image),
        len(p.tie_image),
    )
    return reduced, kv, kh


def within_robust_bound(
    r: np.ndarray, factor: float, floor_px: np.ndarray | float
) -> np.ndarray:
    """(N,) bool: the residuals ``r`` (px) within ``factor`` robust standard
    deviations (1.4826 MAD) of all of them and ``floor_px`` (a number or
    (N,)): the outlier rounds' test (:func:`without_outliers`)."""
    return np.abs(r) <= np.maximum(factor * _robust_sigma(r, 0.0), floor_px)


def _solved_lines(result: BundleResult) -> dict[str, np.ndarray]:
    """The facade lines' offsets and angles of a solve that had them."""
    if not len(result.facade_offsets):
        return {}
    return dict(
        facade_offsets=result.facade_offsets, facade_angles=result.facade_angles
    )


def _ties_kept(
    problem: BundleProblem, result: BundleResult, factor: float, floor_px: float
) -> dict[str, np.ndarray]:
    """The tie rows whose 2D error is within ``factor`` robust standard
    deviations (per axis, sqrt 2 for the 2D length) and ``floor_px``, of
    points still seen twice, started at the solved points.

    Their relative sds (``BundleProblem.tie_sd``, the keypoint scales) are
    not carried on: the first solve with tie points weights them by their
    scale, the later rounds weight all alike. Measured (journal, stage 3,
    2026-12-06): carried through every round, houses-102 / stage-2 seed 1
    34 / 36 at 0.77 px and our industrial class s2 / seed 0 32 / 36 at 0.87
    px, against 33 / 36 at 0.50 and 34 / 36 at 0.49 this way; with a floor
    fitted between the rounds as well, houses-102 seed 1 fell to 2 / 36."""
    e = np.linalg.norm(result.tie_residuals_px, axis=1)
    if len(e) == 0:
        return {}
    sigma = _robust_sigma(result.tie_residuals_px.ravel(), 0.0)
    keep = e <= max(factor * np.sqrt(2.0) * sigma, floor_px)
    point = problem.tie_point[keep]
    keep[keep] = np.bincount(point, minlength=len(problem.tie_xyz))[point] >= 2
    used, point = np.unique(problem.tie_point[keep], return_inverse=True)
    return dict(
        tie_xyz=result.tie_xyz[used],
        tie_image=problem.tie_image[keep],
        tie_point=point,
        tie_xy=problem.tie_xy[keep],
        tie_sd=None,  # the first solve's only (docstring)
    )
