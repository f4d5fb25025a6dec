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
from obliq_colmap.adjustment.tracks import triangulate_tracks
from obliq_colmap.adjustment.verdicts import edge_end_offsets
from obliq_colmap.bundle import BundleOptions, BundleProblem, BundleResult, solve_bundle
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = [
    "AdjustedBlock",
    "bundle_stage",
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
) -> AdjustedBlock:
    """Stage 3: facade edges, matching, datum corrections and the bundle.

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
        problem = build_bundle_problem(inputs, outcomes, state, stage3)
        bundle_options = dataclasses.replace(
            options.bundle,
            corner_heights="fixed",
            horizontal_offset_sigma_m=options.track_offset_sigma_m,
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
            rounds = options.outlier_rounds
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
                if options.track_lines:
                    problem = with_track_lines(
                        problem, result, inputs, stage3, obs, options
                    )
                if options.variance_components:
                    # Each kind weighted by its own noise (map corners ~1 px,
                    # facade edges ~0.15 px).
                    unknowns = 2 if options.track_lines else 1
                    problem, bundle_options = with_variance_components(
                        problem, result, bundle_options, kh, unknowns
                    )
                last = (kv.all() and kh.all()) or k == rounds - 1
                result = solve_bundle(problem, _precision_if(bundle_options, last))
                if last:
                    break
        except ValueError as exc:
            logger.warning("bundle failed (%s): the per-image result is kept", exc)
            result = None
        else:
            state = state.with_bundle(result, problem.image_camera)
            stage3.bundle_rms = _rms_per_image(problem, result)
            stage3.constraints_kept = _kept_share(initial, problem)
            stage3.bundle_precision = dict(result.image_precision_px)
            stage3.end_offset_px = edge_end_offsets(inputs, outcomes, state, stage3.ids)
    timings["bundle"] = time.perf_counter() - t0
    return AdjustedBlock(state, result, stage3)


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


def _vp_sigma_scale(result: BundleResult, default: float) -> float:
    """The factor on stage 1's stated VP standard deviations that makes the
    median whitened squared VP residual of ``result`` that of a chi-square
    with 2 degrees of freedom (robust: wrong pencils do not count), never
    below 1 (no more weight than stage 1 states; residuals shrink where the
    VPs hold the fit). ``default`` without VP observations."""
    chi2 = np.array(list(result.vp_chi2.values()), float)
    chi2 = chi2[np.isfinite(chi2)]
    if len(chi2) == 0:
        return default
    return float(max(1.0, math.sqrt(np.median(chi2) / _CHI2_2_MEDIAN)))


def with_variance_components(
    problem: BundleProblem,
    result: BundleResult,
    options: BundleOptions,
    kept: np.ndarray,
    unknowns_per_track: int,
) -> tuple[BundleProblem, BundleOptions]:
    """Both residual kinds weighted by their robust standard deviation in
    the last solve: vertical (map corners) and horizontal (facade tracks);
    with VP observations, stage 1's stated VP covariance scaled by the
    factor the last solve's VP residuals show (:func:`_vp_sigma_scale`).
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
    scaled = rh * np.sqrt(n / np.maximum(n - u, 1))
    options = dataclasses.replace(
        options,
        vertical_sigma_px=_robust_sigma(
            result.vertical_residuals_px, options.vertical_sigma_px
        ),
        horizontal_sigma_px=_robust_sigma(scaled[n > u], options.horizontal_sigma_px),
        vp_sigma_scale=_vp_sigma_scale(result, options.vp_sigma_scale),
    )
    logger.info(
        "bundle: sigma px: map corners %.3f, facade lines %.3f; VP sd x %.2f",
        options.vertical_sigma_px,
        options.horizontal_sigma_px,
        options.vp_sigma_scale,
    )
    return problem, options


def with_track_lines(
    problem: BundleProblem,
    result: BundleResult,
    inputs: Inputs,
    stage3: Stage3,
    obs: np.ndarray,
    options: AdjustmentOptions,
) -> BundleProblem:
    """The problem with each track re-triangulated as a 3D horizontal line.

    The facade constraint's point ``x_j + h_j z`` sits on the map edge; a
    roof rim overhangs it and a parapet stands back, so the point is moved
    to the track's line (:func:`~obliq_colmap.adjustment.triangulate_tracks`,
    with the solved cameras) and its height restarted there. ``obs``:
    indices into the tracks' observations of the problem's horizontal
    constraints.
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
        return np.abs(r) <= np.maximum(factor * _robust_sigma(r, 0.0), floor)

    rh = result.horizontal_residuals_px
    scale = 1.0 if horizontal_pixel_scale is None else horizontal_pixel_scale
    kv = keep(result.vertical_residuals_px, floor_px)
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
        prior_rotations=p.prior_rotations,
        prior_centers=p.prior_centers,
        prior_principal_points=p.prior_principal_points,
        vertical_vps=p.vertical_vps,
        vertical_vp_covariances=p.vertical_vp_covariances,
    )
    logger.info(
        "bundle: %d of %d vertical and %d of %d horizontal constraints rejected",
        (~kv).sum(),
        len(kv),
        (~kh).sum(),
        len(kh),
    )
    return reduced, kv, kh
