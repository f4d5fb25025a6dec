"""Stage 3 as run by ``register``: facade edges, matching, the bundle's rounds.

From the per-image registrations (stage 2) to one adjusted block:

1. :func:`facade_stage`: horizontal facade edges of every registered image
   (:mod:`obliq_colmap.facades`) matched across images into tracks and
   per-image height datum corrections (:mod:`obliq_colmap.matching`).
2. :func:`build_bundle_problem`: the constraints of eq. 3 as a
   :class:`~obliq_colmap.bundle.BundleProblem`: two fixed points of each
   inlier corner's vertical per segment, one dist_z row per track
   observation.
3. :func:`bundle_stage`: a first solve, then rounds that drop outliers,
   re-triangulate every track as a 3D horizontal line near its wall and
   weight each residual kind by its robust spread, solving again each time.

:class:`BlockState` is the block as it stands (poses, intrinsics, ground
planes) before and after.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from obliq_colmap.bundle import BundleOptions, BundleProblem, BundleResult, solve_bundle
from obliq_colmap.bundle import residuals as res
from obliq_colmap.facades import FacadeEdges, FacadeOptions, facade_edges
from obliq_colmap.geometry import Camera, Pose, lines_through
from obliq_colmap.matching import (
    FacadeTracks,
    MatchingOptions,
    match_facade_edges,
    triangulate_tracks,
)
from obliq_colmap.state import BlockState, ImageOutcome, Inputs, json_float

__all__ = [
    "AdjustmentOptions",
    "BlockState",
    "Stage3",
    "build_bundle_problem",
    "bundle_stage",
    "edge_end_offsets",
    "end_offset_ratios",
    "facade_stage",
    "imprecise_images",
    "misplaced_images",
    "rejected_images",
    "vertical_constraints",
    "with_track_lines",
    "with_variance_components",
    "without_outliers",
]

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class AdjustmentOptions:
    """Options of stage 3 (:func:`bundle_stage`)."""

    facades: FacadeOptions = field(default_factory=FacadeOptions)
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    #: The bundle (its corner points are always fixed: vertical_constraints).
    #: Cauchy at 1 px: the facade tracks fit to ~0.15 px, so a wrong match is
    #: many scales out and must lose its pull.
    bundle: BundleOptions = field(
        default_factory=lambda: BundleOptions(loss="cauchy", loss_scale_px=1.0)
    )
    #: Bundle rounds after the first that drop the constraints whose residual
    #: exceeds ``outlier_factor`` robust standard deviations (of their kind)
    #: and at least ``outlier_floor_px``, then solve again from the result.
    #: The floor is in pixels of the image its segments were detected in (the
    #: facade lines: ``Segments.pixel_scale``), where their noise lives.
    outlier_rounds: int = 5
    outlier_factor: float = 3.0
    outlier_floor_px: float = 1.0
    #: Huber scale (px) of the first bundle round (then the bundle's own
    #: loss); 0 uses the bundle's own loss throughout.
    initial_loss_scale_px: float = 0.0
    #: Between rounds: re-triangulate each facade track as a 3D horizontal
    #: line near its wall (roof rims overhang), and weight the residual kinds
    #: by their robust standard deviations.
    track_lines: bool = True
    variance_components: bool = True
    #: Prior 1-sigma (m) of a track's offset from its wall (weak: at the true
    #: cameras, tracks as free 3D lines fit to 0.000 px median, pinned to the
    #: wall to 0.23 px; scripts/bench_bundle_diagnostics.py).
    track_offset_sigma_m: float = 10.0

    def __post_init__(self) -> None:
        if self.outlier_rounds < 0 or self.outlier_factor <= 0:
            raise ValueError("outlier_rounds must be >= 0 and outlier_factor > 0")
        if self.track_offset_sigma_m <= 0:
            raise ValueError("track_offset_sigma_m must be > 0")


# --------------------------------------------------------------------------
# Stage 3: facade edges, matching, the bundle problem
# --------------------------------------------------------------------------


@dataclass
class Stage3:
    """Facade edges of every registered image and their tracks.

    Attributes
    ----------
    ids : tuple of image ids, the order of ``facades`` and of the tracks'
        image indices.
    facades : list of FacadeEdges, per image.
    tracks : FacadeTracks.
    ends_raw : (H, 2, 2) array, each track observation's segment in raw
        pixels (set by :func:`build_bundle_problem`).
    row_obs : (R,) int array, per horizontal row of the bundle problem the
        track observation it holds (set by :func:`build_bundle_problem`).
    """

    ids: tuple[int, ...]
    facades: list[FacadeEdges]
    tracks: FacadeTracks
    ends_raw: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    row_obs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    #: Per image id: RMS (px) of its final vertical and horizontal residuals.
    bundle_rms: dict[int, tuple[float, float]] = field(default_factory=dict)
    #: Per image id: the share of its constraints (map corners and facade
    #: observations) that the bundle's outlier rounds kept.
    constraints_kept: dict[int, float] = field(default_factory=dict)
    #: Per image id: the bundle's a-posteriori precision (px) of its
    #: constrained points (:attr:`BundleResult.image_precision_px`).
    bundle_precision: dict[int, float] = field(default_factory=dict)
    #: Per image id: how far along its verticals (px, signed, + up) the feet
    #: and the tops of its corners' vertical edges sit from where the other
    #: images put them, (2,) (:func:`edge_end_offsets`).
    end_offset_px: dict[int, np.ndarray] = field(default_factory=dict)

    def report(self, outcomes: dict[int, ImageOutcome]) -> dict[str, Any]:
        t = self.tracks
        obs = np.bincount(t.image, minlength=len(self.ids))
        return {
            "num_tracks": t.num_tracks,
            "num_observations": t.num_observations,
            "num_image_pairs": len(t.pairs),
            "num_pair_matches": int(sum(p.num_matches for p in t.pairs)),
            "images": {
                outcomes[i].name: {
                    "facade_segments": len(f),
                    "walls": f.num_walls,
                    "observations": int(obs[k]),
                    "datum_correction_m": json_float(t.datum_correction[k]),
                    "bundle_rms_px": [
                        json_float(x) for x in self.bundle_rms.get(i, (math.nan,) * 2)
                    ],
                    "constraints_kept": json_float(
                        self.constraints_kept.get(i, math.nan)
                    ),
                    "bundle_precision_px": json_float(
                        self.bundle_precision.get(i, math.nan)
                    ),
                    "edge_end_offset_px": [
                        json_float(x)
                        for x in self.end_offset_px.get(i, (math.nan,) * 2)
                    ],
                }
                for k, (i, f) in enumerate(zip(self.ids, self.facades, strict=True))
            },
        }


def facade_stage(
    inputs: Inputs,
    state: BlockState,
    outcomes: dict[int, ImageOutcome],
    options: AdjustmentOptions,
) -> Stage3:
    """Horizontal facade edges per image, matched across images into tracks."""
    ids = tuple(sorted(state.poses))
    facades = []
    for i in ids:
        seg = outcomes[i].line_segments
        prior = inputs.priors.cameras[inputs.priors.images[i].camera_id]
        facades.append(
            facade_edges(
                _in_camera(prior, state.cameras[i], seg.endpoints),
                seg.normal,
                state.cameras[i],
                state.poses[i],
                state.ground(i),
                inputs.cadastre,
                options.facades,
                seg.pixel_scale,
            )
        )
    grounds = np.array([state.planes[i] for i in ids]).reshape(-1, 3)
    tracks = match_facade_edges(facades, grounds, inputs.cadastre, options.matching)
    logger.info(
        "facade edges: %d segments on walls, %d tracks with %d observations",
        sum(len(f) for f in facades),
        tracks.num_tracks,
        tracks.num_observations,
    )
    return Stage3(ids, facades, tracks)


def _in_camera(prior: Camera, camera: Camera, segments: np.ndarray) -> np.ndarray:
    """(N, 2, 2) segments undistorted with the priors' camera (the frame of the
    per-image stages' segments) as undistorted pixels of ``camera``, whose
    distortion stage 2 may have refined (through the raw pixels)."""
    if not (prior.has_distortion or camera.has_distortion):
        return segments  # both frames are the raw pixels
    raw = prior.distort_pixels(segments.reshape(-1, 2))
    return camera.undistort_pixels(raw).reshape(segments.shape)


def _raw_lines(camera: Camera, segments_undistorted: np.ndarray) -> np.ndarray:
    """(N, 3) unit lines through segments' endpoints in RAW (distorted) pixels."""
    ends = camera.distort_pixels(segments_undistorted.reshape(-1, 2)).reshape(-1, 2, 2)
    return lines_through(ends[:, 0], ends[:, 1])


def _heights_on_vertical(
    camera: Camera, pose: Pose, xy: np.ndarray, raw: np.ndarray
) -> np.ndarray:
    """(N,) heights where the rays through RAW pixels (N, 2) of ``camera``
    (the intrinsics ``pose`` belongs to) pass closest to the verticals over
    map points xy (N, 2)."""
    rays = camera.cam_from_img(raw)
    d = np.column_stack([rays, np.ones(len(rays))]) @ pose.rotation  # world
    c = pose.center
    lam = np.sum(d[:, :2] * (xy - c[:2]), axis=1) / np.sum(d[:, :2] ** 2, axis=1)
    return c[2] + lam * d[:, 2]


def vertical_constraints(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    image_ids: Sequence[int],
) -> dict[str, np.ndarray]:
    """Corner-to-vertical-line constraints from the registrations' inliers.

    Each inlier pair (map corner, vertical segment) gives TWO point-to-line
    residuals: the corner's vertical at the heights of the segment's two
    endpoints (fixed, from the start pose), projected, to the segment's line.
    Together they say that the segment lies on the image of the corner's
    vertical: its position AND its direction, i.e. the vanishing point,
    which is what holds the block's tilt (with one point per segment, or a
    free corner height, a tilted block fits the lines nearly as well:
    measured on the sample, 3 deg drift from the truth). The heights only
    place the points near the segment; sliding along the vertical does not
    change a distance to a line through the vanishing point.

    Returns
    -------
    dict with ``xy`` (M, 2) corner positions, ``height`` (M,), ``image`` (M,)
    index into ``image_ids``, ``line`` (M, 3) raw pixels, ``corner`` (M,)
    cadastre corner ids.
    """
    cad = inputs.cadastre
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("xy", "height", "image", "line", "corner")
    }
    for k, image_id in enumerate(image_ids):
        r = outcomes[image_id].registration
        if r is None or not r.success or len(r.inlier_pairs) == 0:
            continue
        prior_cam = inputs.priors.cameras[inputs.priors.images[image_id].camera_id]
        c = r.inlier_pairs[:, 0]
        ends = r.inlier_segments_px  # (K, 2, 2) undistorted
        xy = np.repeat(cad.corner_xy[c], 2, axis=0)
        # Through the camera the pose belongs to (stage 2 refines focal and
        # lens): with the priors' camera the points land metres off along
        # the vertical, and under a lens that vertical's image is curved,
        # so they would leave the segment's chord (hard seed 1: the real
        # vertical lines alone left 1.8 px, scripts/bench_bundle_limit.py).
        camera = state.cameras.get(image_id) or prior_cam
        h = _heights_on_vertical(
            camera,
            state.poses[image_id],
            xy,
            prior_cam.distort_pixels(ends.reshape(-1, 2)),
        )
        parts["xy"].append(xy)
        parts["height"].append(h)
        parts["image"].append(np.full(len(xy), k))
        parts["line"].append(np.repeat(_raw_lines(prior_cam, ends), 2, axis=0))
        parts["corner"].append(np.repeat(c, 2))
    if not parts["xy"]:
        return dict(
            xy=np.zeros((0, 2)),
            height=np.zeros(0),
            image=np.zeros(0, np.int64),
            line=np.zeros((0, 3)),
            corner=np.zeros(0, np.int64),
        )
    return {k: np.concatenate(v) for k, v in parts.items()}


def _group_cameras(
    inputs: Inputs, state: BlockState, outcomes: dict[int, ImageOutcome]
) -> dict[int, Camera]:
    """Start intrinsics per camera_id: the result model's camera with the
    median of its images' per-image focal lengths (stage 2 refines the focal
    per image; the images of one head share one), and the median of the
    distortion of those images whose stage 2 refined it (one lens per head:
    a much better start than the priors' for the bundle). After a bundle
    (``state.shared``) the heads' solved cameras, as they stand."""
    if state.shared:
        return {
            inputs.priors.images[i].camera_id: dataclasses.replace(
                cam, camera_id=inputs.priors.images[i].camera_id
            )
            for i, cam in state.cameras.items()
        }
    ratios: dict[int, list[float]] = {}
    lenses: dict[int, list[np.ndarray]] = {}
    for i, cam in state.cameras.items():
        cid = inputs.priors.images[i].camera_id
        prior = inputs.priors.cameras[cid]
        ratios.setdefault(cid, []).append(cam.params[0] / prior.params[0])
        r = outcomes[i].registration
        if r is not None and r.distortion_refined:
            extra = res.focal_principal_extra_indices(cam.model)[2]
            lenses.setdefault(cid, []).append(cam.params[extra])
    out = {}
    for cid, r in ratios.items():
        cam = inputs.cameras[cid]
        focal, _, extra = res.focal_principal_extra_indices(cam.model)
        params = cam.params.copy()
        params[focal] *= float(np.median(r))
        if cid in lenses and len(lenses[cid][0]) == len(extra):
            params[extra] = np.median(np.array(lenses[cid]), axis=0)
        out[cid] = Camera(cam.model, cam.width, cam.height, params, cid)
    return out


def build_bundle_problem(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    stage3: Stage3,
) -> BundleProblem:
    """The global bundle over the registered images (paper eq. 3).

    Vertical constraints: the registrations' inlier corner-to-segment pairs;
    horizontal ones: every observation of every facade track, anchored at
    the track's point on its map edge. Lines in RAW pixels (the bundle
    projects through the full camera model). The corner points are fixed
    (``BundleOptions.corner_heights = "fixed"``, see
    :func:`vertical_constraints`). Sets ``stage3.ends_raw`` and
    ``stage3.row_obs``.
    """
    ids = stage3.ids
    v = vertical_constraints(inputs, outcomes, state, ids)
    t = stage3.tracks
    ends = np.zeros((t.num_observations, 2, 2))
    for k, i in enumerate(ids):
        sel = np.flatnonzero(t.image == k)
        if len(sel) == 0:
            continue
        # The facade edges are in the frame of the image's own camera
        # (facade_stage).
        und = stage3.facades[k].endpoints[t.row[sel]]
        ends[sel] = (
            state.cameras[i].distort_pixels(und.reshape(-1, 2)).reshape(-1, 2, 2)
        )
    stage3.ends_raw = ends
    lines = lines_through(ends[:, 0], ends[:, 1])
    stage3.row_obs = np.arange(t.num_observations)
    cameras = _group_cameras(inputs, state, outcomes)
    return BundleProblem(
        cameras=cameras,
        poses={i: state.poses[i] for i in ids},
        image_camera={i: inputs.priors.images[i].camera_id for i in ids},
        image_ids=ids,
        corner_xy=v["xy"],
        corner_heights=v["height"],
        vertical_image=v["image"],
        vertical_corner=np.arange(len(v["xy"])),
        vertical_line=v["line"],
        facade_heights=t.height,
        horizontal_image=t.image,
        horizontal_height=t.track,
        horizontal_anchor_xy=t.anchor_xy[t.track],
        horizontal_line=lines,
        # The INS attitude and the GNSS centres, observations where the
        # bundle is given their sigmas (BundleOptions.rotation_prior_sigma_deg,
        # position_prior_sigma_m).
        prior_rotations={
            i: inputs.priors.images[i].cam_from_world.rotation for i in ids
        },
        prior_centers={i: inputs.priors.images[i].cam_from_world.center for i in ids},
    )


def bundle_stage(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    options: AdjustmentOptions,
    timings: dict[str, float],
) -> tuple[BlockState, BundleResult | None, Stage3]:
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
    return state, result, stage3


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


def rejected_images(stage3: Stage3, min_kept: float) -> list[int]:
    """The images whose constraints the bundle rejected in large part.

    The outlier rounds reject some of every image's constraints (map
    corners and facade observations together: at most 26 % in 18 `paper`
    and `hard` runs for every image that ends < 2 px off). An image the
    bundle leaves metres off along its verticals, where its own corners and
    facade edges no longer fit the block, loses more (in those runs 6 of the
    7 images that end > 5 px off, and one at 4.6 px: 31-49 %; the seventh
    kept 81 %), and its RMS does not show it (the rows kept fit). A share
    below ``min_kept`` flags it.
    """
    return sorted(
        i
        for i, k in stage3.constraints_kept.items()
        if math.isfinite(k) and k < min_kept
    )


def imprecise_images(
    stage3: Stage3, max_ratio: float, min_images: int = 4
) -> list[int]:
    """The images whose pose the bundle determines far worse than the block's.

    Each image's a-posteriori precision (:attr:`Stage3.bundle_precision`,
    px) against the median over the block: an image held along its
    verticals by little more than two-view facade tracks (whose offset and
    height absorb a shift of either camera) has a predicted sd several times
    the block's, and there the bundle can leave it metres off with every
    constraint kept and its RMS unremarkable. A ratio above ``max_ratio``
    flags it (0: none); the median needs ``min_images`` finite values. The
    precision is internal: it does not see wrong matches
    (:func:`rejected_images` does).
    """
    sd = {i: v for i, v in stage3.bundle_precision.items() if math.isfinite(v)}
    if max_ratio <= 0 or len(sd) < min_images:
        return []
    limit = max_ratio * float(np.median(list(sd.values())))
    return sorted(i for i, v in sd.items() if v > limit)


def edge_end_offsets(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    image_ids: Sequence[int],
    min_corners: int = 5,
) -> dict[int, np.ndarray]:
    """Per image: how far its corners' vertical edges end, along its
    verticals, from where the other images' edges end: (2,) px, + up, the
    feet and the tops.

    Each inlier segment of stage 2 ends near the foot and the top of its
    corner's edge. Cast through the image's solved camera onto the corner's
    vertical, both ends get heights; per corner and end, the other images'
    median height is the block's. Per end, the image's offset is the median
    over its corners of (own height - block's height) in pixels along its
    vertical. Either end alone can be off for reasons of its own (feet cut
    by cars and trees, tops by roof rims seen from another side), but an
    image whose camera the bundle left off along its verticals (its facade
    edges matched a floor off, say) moves both together, which its
    corner-to-line and facade rows cannot show. Absent for an image sharing
    fewer than ``min_corners`` corners with the others.
    """
    v = vertical_constraints(inputs, outcomes, state, image_ids)
    if not len(v["xy"]):
        return {}
    # Two rows per segment (its ends); order each pair foot, top.
    h = np.sort(v["height"].reshape(-1, 2), axis=1)
    img, corner, xy = v["image"][::2], v["corner"][::2], v["xy"][::2]
    corners, col = np.unique(corner, return_inverse=True)
    table = np.full((2, len(image_ids), len(corners)), np.nan)  # end x image x corner
    table[:, img, col] = h.T
    out = {}
    for k, i in enumerate(image_ids):
        sel = img == k
        if sel.sum() < min_corners:
            continue
        others = np.delete(table[:, :, col[sel]], k, axis=1)  # (2, I-1, n)
        # Both ends of a segment are always there together: a corner another
        # image saw has both.
        seen = np.isfinite(others[0]).any(axis=0)
        if seen.sum() < min_corners:
            continue
        block = np.nanmedian(others[:, :, seen], axis=1)  # (2, s)
        # Pixels per metre along the vertical at each corner, solved camera.
        cam, pose = state.cameras[i], state.poses[i]
        X = np.column_stack([xy[sel][seen], h[sel][seen].mean(axis=1)])
        up = cam.img_from_cam(pose.transform(X + [0.0, 0.0, 0.5]))
        down = cam.img_from_cam(pose.transform(X - [0.0, 0.0, 0.5]))
        d = (h[sel][seen].T - block) * np.linalg.norm(up - down, axis=1)  # (2, s)
        out[i] = np.median(d, axis=1)
    return out


def end_offset_ratios(
    stage3: Stage3, min_images: int = 4, floor_px: float = 0.2
) -> dict[int, float]:
    """Per image id: how many of the block's spreads both ends of its
    vertical edges sit off, in the same direction (0 where they disagree).

    Per end (feet, tops), each image's :attr:`Stage3.end_offset_px` from the
    block's median over the images, in the block's robust spread (1.4826
    MAD, at least ``floor_px``: the ends are found to about a pixel, and
    below that a ratio would count sub-pixel offsets); the smaller of the
    two. Empty with fewer than ``min_images`` images with offsets.
    """
    ids = [i for i, v in stage3.end_offset_px.items() if np.all(np.isfinite(v))]
    if len(ids) < min_images:
        return {}
    off = np.array([stage3.end_offset_px[i] for i in ids])  # (I, 2)
    centre = np.median(off, axis=0)
    spread = np.maximum(1.4826 * np.median(np.abs(off - centre), axis=0), floor_px)
    z = (off - centre) / spread
    both = np.where(z[:, 0] * z[:, 1] > 0, np.abs(z).min(axis=1), 0.0)
    return dict(zip(ids, both.tolist(), strict=True))


def misplaced_images(stage3: Stage3, max_ratio: float) -> list[int]:
    """The images whose vertical edges end, feet and tops alike, far from
    where the block's do: :func:`end_offset_ratios` above ``max_ratio`` (0:
    none)."""
    if max_ratio <= 0:
        return []
    return sorted(i for i, r in end_offset_ratios(stage3).items() if r > max_ratio)


def _robust_sigma(r: np.ndarray, default: float) -> float:
    """1.4826 MAD of residuals (px), at least 0.05; ``default`` when empty."""
    return float(max(1.4826 * np.median(np.abs(r)), 0.05)) if len(r) else default


def with_variance_components(
    problem: BundleProblem,
    result: BundleResult,
    options: BundleOptions,
    kept: np.ndarray,
    unknowns_per_track: int,
) -> tuple[BundleProblem, BundleOptions]:
    """Both residual kinds weighted by their robust standard deviation in
    the last solve: vertical (map corners) and horizontal (facade tracks).
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
    )
    logger.info(
        "bundle: sigma px: map corners %.3f, facade lines %.3f",
        options.vertical_sigma_px,
        options.horizontal_sigma_px,
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
    to the track's line (:func:`matching.triangulate_tracks`, with the
    solved cameras) and its height restarted there. ``obs``: indices into
    the tracks' observations of the problem's horizontal constraints.
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
    )
    logger.info(
        "bundle: %d of %d vertical and %d of %d horizontal constraints rejected",
        (~kv).sum(),
        len(kv),
        (~kh).sum(),
        len(kh),
    )
    return reduced, kv, kh
