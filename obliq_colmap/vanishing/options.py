"""The vanishing stage's prior, options and result.

:class:`VPPrior` says where the vertical VP may lie, :class:`VanishingOptions`
(with :class:`SecondPassOptions`) how it is searched, :class:`VanishingResult`
what was found (failure is a value: status "no_vp").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from obliq_colmap.lines import LineOptions, Segments

PRIOR_KINDS = ("none", "aerial", "ins")
STATUSES = ("ok", "low_confidence", "no_vp")


@dataclass(kw_only=True, frozen=True)
class VPPrior:
    """Where the vertical vanishing point may lie.

    Attributes
    ----------
    kind : str
        "none": anywhere within ``max_angle_deg`` of the image's vertical axis,
        above or below the image, at least ``min_distance_h`` image heights from
        the centre. "aerial": the paper's prior, y >= ``min_y_h`` image heights
        (at least one image height below the image for the default 2), within
        ``max_angle_deg`` of the vertical axis (which excludes horizontal
        directions at infinity that satisfy y >= 2h only in the limit). "ins":
        the vertical direction within ``cone_deg`` of ``down_cam`` (needs
        intrinsics); covers near-nadir images whose VP is inside the frame.
    down_cam : (3,) array or None
        ins: predicted direction of the world's down axis in the camera frame,
        ``R_prior @ (0, 0, -1)``.
    cone_deg : float
        ins: half-angle of the cone of allowed vertical directions, degrees.
    max_angle_deg : float
        none/aerial: largest angle between the image's y axis and the direction
        from the image centre to the VP, degrees.
    min_distance_h : float
        none: least |y| distance of the VP from the image centre, image heights
        (0.5: outside the image's vertical extent).
    min_y_h : float
        aerial: least y coordinate of the VP, image heights.
    max_tilt_deg : float
        aerial: largest angle between the optical axis and the world's down
        direction (the camera's tilt from nadir; 85: a high oblique with the
        horizon 5 deg above the principal point). An oblique aerial camera
        has a FINITE VP below the image, ``f tan(tilt)`` below the principal
        point; the pencil of a street or railway running away from the
        camera meets at infinity and must not pass for it. With intrinsics
        the tilt is tested exactly; without, the VP must lie within
        ``max_focal_w * W * tan(max_tilt_deg)`` of the image centre.
    max_focal_w : float
        aerial without intrinsics: the longest focal length allowed, in
        image widths (3: a horizontal field of view of at least 19 deg).
    """

    kind: str = "none"
    down_cam: np.ndarray | None = None
    cone_deg: float = 5.0
    max_angle_deg: float = 30.0
    min_distance_h: float = 0.5
    min_y_h: float = 2.0
    max_tilt_deg: float = 85.0
    max_focal_w: float = 3.0

    def __post_init__(self) -> None:
        if self.kind not in PRIOR_KINDS:
            raise ValueError(
                f"unknown prior kind {self.kind!r}; allowed: {', '.join(PRIOR_KINDS)}"
            )
        if self.kind == "ins":
            if self.down_cam is None:
                raise ValueError("an 'ins' prior needs down_cam")
            d = np.asarray(self.down_cam, float).reshape(3)
            object.__setattr__(self, "down_cam", d / np.linalg.norm(d))

    @classmethod
    def none(cls, max_angle_deg: float = 30.0) -> VPPrior:
        """No prior knowledge: within +-``max_angle_deg`` of the vertical axis."""
        return cls(kind="none", max_angle_deg=max_angle_deg)

    @classmethod
    def aerial(cls, min_y_h: float = 2.0, max_angle_deg: float = 45.0) -> VPPrior:
        """The paper's oblique-aerial prior: VP far below the image."""
        return cls(kind="aerial", min_y_h=min_y_h, max_angle_deg=max_angle_deg)

    @classmethod
    def from_rotation(cls, cam_from_world_rotation: np.ndarray, cone_deg: float = 5.0):
        """INS prior from a rough ``cam_from_world`` rotation (3, 3)."""
        R = np.asarray(cam_from_world_rotation, float).reshape(3, 3)
        return cls(
            kind="ins", down_cam=R @ np.array([0.0, 0.0, -1.0]), cone_deg=cone_deg
        )


@dataclass(kw_only=True)
class SecondPassOptions:
    """Options of :func:`vertical_segments` (pixels of the full image)."""

    #: Gaussian smoothing before the derivative, pixels.
    sigma_px: float = 1.0
    #: hysteresis thresholds on the directional derivative, grey levels/px.
    low: float = 2.0
    high: float = 6.0
    #: largest angle between the gradient and the direction perpendicular to
    #: the line towards the VP, degrees.
    max_gradient_angle_deg: float = 20.0
    #: edge points farther than this from their chain's line are dropped, px.
    max_point_distance_px: float = 1.5
    #: largest RMS distance of a segment's edge points to its line, px.
    max_rms_px: float = 0.6
    #: chains are cut where consecutive points are farther apart, px.
    max_gap_px: float = 4.0
    #: shortest segment kept, px.
    min_length_px: float = 15.0
    #: least number of edge points per pixel of segment length.
    min_density: float = 0.6
    #: merge pieces of one line (same side brighter) across gaps up to
    #: ``merge_max_gap_px`` when both lie within ``merge_max_distance_px``.
    merge: bool = True
    merge_max_distance_px: float = 1.0
    merge_max_gap_px: float = 12.0
    #: segment ends are moved outwards along their line to where the
    #: contrast across it halves, by at most this much, px (0: off).
    extend_max_px: float = 6.0
    #: edge points within this distance of either end of their chain are
    #: left out of the line fit (still part of the extent), px.
    end_trim_px: float = 3.0


@dataclass(kw_only=True)
class VanishingOptions:
    """Options of :func:`detect_vertical_vp`."""

    #: local contrast equalisation (CLAHE, :func:`lines.equalize_local_contrast`)
    #: of the image the second pass reads: its clip limit (0: off) and the
    #: regions per side. Facades in shadow (a head against the sun) give few
    #: edges above the second pass's thresholds otherwise. Not for the first
    #: pass: its segments are stage 3's facade edges, whose positions the
    #: nonlinear mapping moves (measured: docs/journal/independent-scenes.md,
    #: 2026-12-04 "facades in shadow").
    contrast_clip_limit: float = 3.0
    contrast_tiles: int = 8
    #: segment detection (first pass).
    lines: LineOptions = field(default_factory=LineOptions)
    #: second pass (:func:`vertical_segments`); skipped when None.
    second_pass: SecondPassOptions | None = field(default_factory=SecondPassOptions)
    #: refine the VP once more on the second pass's edge points ...
    refine_with_second_pass: bool = True
    #: ... on the chains whose RMS distance to their line through the VP is
    #: at most this many robust standard deviations of those RMS values (and
    #: at most ``second_pass.max_rms_px``).
    second_pass_rms_factor: float = 3.0
    #: covariance of the VP refined on the second pass (the bundle uses it
    #: with VP observations): "first_pass" (the first pass's, on LSD segments, as before
    #: 2026-12-04), "chains" (a jackknife over the chains), "blocks" (a
    #: jackknife over ``covariance_blocks`` blocks of neighbouring chains),
    #: "max_blocks" (the larger of "first_pass" and "blocks", by the
    #: direction's sd). Measured in docs/journal/stage1-vanishing.md
    #: (2026-12-04, "a covariance from the chains").
    second_pass_covariance: str = "max_blocks"
    covariance_blocks: int = 20
    #: set the status again with that covariance's sd (``ok_max_std_deg``);
    #: False: the status stays the first pass's. Off: on houses-102 it sends
    #: 13 more images (VPs ~1-15 deg off) to stage 2's fallback (all first-pass
    #: segments), which then registers 8 instead of 18 of 36 below 2 px
    #: across the verticals (`--stop_after initial`); urban-101 unchanged.
    status_from_second_pass_covariance: bool = False
    #: RANSAC: largest distance of a segment endpoint to the line through the
    #: segment's midpoint and the hypothesis, pixels of the detection image.
    inlier_threshold_px: float = 1.0
    #: RANSAC: shortest segment used, pixels of the detection image.
    min_length_px: float = 12.0
    #: none/aerial priors: segments further than this from the image's
    #: vertical direction are not considered, degrees.
    candidate_max_angle_deg: float = 60.0
    #: RANSAC: a segment's weight in sampling and scoring is length**power;
    #: 0.5 balances long edges (precise) against many short ones (a few long
    #: street edges that pass near the VP must not outvote the buildings).
    score_length_power: float = 0.5
    #: RANSAC: pieces of one image line share the weight the whole line has
    #: as one segment (:func:`~obliq_colmap.vanishing.collinear.line_length`).
    #: Off: it takes a street seen along the heading out of the vertical
    #: pencil on the external renderer's houses, but loses images on our
    #: generator's houses and dense classes for a cause not yet found
    #: (docs/journal/independent-scenes.md, "pieces of one image line").
    line_weights: bool = False
    #: RANSAC: hypotheses per batch, least and most hypotheses, confidence.
    batch_size: int = 512
    min_trials: int = 256
    max_trials: int = 4096
    confidence: float = 0.999
    #: random seed (or pass a numpy Generator to the function).
    seed: int = 0
    #: The first pass (steps 2-4) runs once per factor: with an INS prior in
    #: the prior's cone times the factor, otherwise with its own RANSAC draws.
    #: Two pencils of near-equal first-pass score (verticals of part of the
    #: image with long street edges) make one start land degrees off; when the
    #: starts disagree, the VP whose second-pass segments are longest in total
    #: wins (without a second pass, the first start's).
    start_cones: tuple[float, ...] = (1.0, 0.5, 2.0)
    #: Two starts' VPs closer than this (deg, directions through the
    #: intrinsics or the nominal camera) are one VP ...
    starts_same_deg: float = 0.5
    #: ... and this without a cone, where the starts differ only in their
    #: draws: a restart is there to find another pencil, not to re-decide
    #: within one (real aerial images scatter by about a degree).
    restarts_same_deg: float = 2.0
    #: ML refinement: re-selection rounds of the inliers.
    refine_rounds: int = 3
    #: competing vanishing points: up to this many other VPs (street and
    #: facade directions) are found by RANSAC among the candidate segments;
    #: each segment then belongs to the VP it fits best (alternating
    #: assignment and ML refinement). Lines of a horizontal direction whose
    #: pencil passes near the vertical VP inside some image strip (a street
    #: seen along the camera's azimuth, with its curbs, markings and cars) are
    #: otherwise taken for verticals and pull the VP along that strip.
    competing_vps: int = 3
    #: a competing VP needs at least this many segments that fit it better
    #: than the vertical VP ...
    competing_min_segments: int = 8
    #: ... and directions (nominal camera when the intrinsics are unknown) at
    #: least this far from the vertical, degrees.
    competing_min_angle_deg: float = 20.0
    #: RANSAC hypotheses per competing VP (one batch).
    competing_batch_size: int = 128
    #: with intrinsics, a candidate vertical VP (the RANSAC winner or a
    #: competitor the prior allows) scores its significance plus that of its
    #: most significant competitor within this many degrees of orthogonal
    #: (the horizontal directions of streets and facades), and candidates
    #: with such a partner of significance >= ``ok_min_significance`` go
    #: first; 0: significance alone. Without intrinsics orthogonality is
    #: unknown and not used.
    orthogonal_support_tol_deg: float = 4.0
    #: the significance test is made at the inlier threshold times each of
    #: these, the best counting (:func:`ransac.significance_test`): the few
    #: short verticals of low halls among trees and cars are chance at the
    #: RANSAC threshold and plain at a finer one. (1.0,): one precision.
    significance_precisions: tuple[float, ...] = (1.0, 0.5, 0.25)
    #: fewer inlier segments than this: no VP at all.
    min_inliers: int = 4
    #: status "ok" needs this many inliers ...
    ok_min_inliers: int = 10
    #: ... a significance of at least this (-log10 of the number of false
    #: alarms) ...
    ok_min_significance: float = 3.0
    #: ... and a 1-sigma angular uncertainty of the vertical direction of at
    #: most this (nominal focal max(W, H) when the intrinsics are unknown), deg.
    ok_max_std_deg: float = 1.0

    def __post_init__(self) -> None:
        if self.second_pass_covariance not in (
            "first_pass",
            "chains",
            "blocks",
            "max_blocks",
        ):
            raise ValueError(
                f"unknown second_pass_covariance {self.second_pass_covariance!r}"
            )
        if not self.contrast_clip_limit >= 0 or self.contrast_tiles < 1:
            raise ValueError(
                "contrast_clip_limit must be >= 0 and contrast_tiles >= 1, got"
                f" {self.contrast_clip_limit}, {self.contrast_tiles}"
            )
        if not self.start_cones or min(self.start_cones) <= 0:
            raise ValueError(
                f"start_cones needs positive factors, got {self.start_cones}"
            )


@dataclass
class VanishingResult:
    """The vertical vanishing point of one image (failure is a value).

    Attributes
    ----------
    status : str, "ok", "low_confidence" or "no_vp".
    message : str, why, in words.
    vp : (3,) float array or None
        Homogeneous unit vector (x, y, w), COLMAP pixels of the distortion-free
        image (K's image when a camera with distortion was given); w >= 0 and
        w = 0 for a VP at infinity.
    covariance : (3, 3) float array or None, of ``vp`` (rank 2).
    vertical_direction : (3,) float array or None
        Unit vertical direction in the camera frame, pointing down the world;
        only with intrinsics.
    direction_std_deg : float, 1-sigma angular uncertainty of the vertical
        direction (nominal focal max(W, H) when the intrinsics are unknown).
    significance : float, -log10 of the number of false alarms (> 0: the VP is
        unlikely to be chance).
    segments : Segments, first-pass segments (undistorted, full resolution).
    inliers : (N,) bool array, the first-pass inliers of ``vp``.
    vertical_segments : Segments or None, second-pass segments (fitted
        through ``vp``).
    vertical_segments_free : Segments or None, the same segments each fitted
        on its own edge points (its own direction).
    n_hypotheses : int, RANSAC hypotheses evaluated.
    time_s : dict, wall time per step, seconds.
    competing_vps : (K, 3) float array, the other vanishing points the
        segments were assigned against (homogeneous unit vectors, pixels of
        the distortion-free image; horizontal directions of streets and
        facades in oblique aerial images).
    """

    status: str
    message: str = ""
    vp: np.ndarray | None = None
    covariance: np.ndarray | None = None
    vertical_direction: np.ndarray | None = None
    direction_std_deg: float = float("inf")
    significance: float = 0.0
    segments: Segments = field(default_factory=Segments)
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    vertical_segments: Segments | None = None
    vertical_segments_free: Segments | None = None
    n_hypotheses: int = 0
    time_s: dict = field(default_factory=dict)
    competing_vps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __bool__(self) -> bool:
        return self.status != "no_vp"

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def vp_pixel(self) -> np.ndarray | None:
        """(2,) pixel position of the VP, or None (no VP, or at infinity)."""
        if self.vp is None or abs(self.vp[2]) < 1e-12:
            return None
        return self.vp[:2] / self.vp[2]
