"""Options and result of the initial registration (stage 2), and the inlier
threshold at an image's scale."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from obliq_colmap.geometry import Camera, Pose


@dataclass(kw_only=True)
class RegistrationOptions:
    """Options of :func:`~obliq_colmap.registration.register_image` (units in the
    names or comments).

    Attributes
    ----------
    prior_position_sigma_m : float
        1-sigma error of the prior camera centre per horizontal axis (m).
    prior_rotation_sigma_deg : float
        1-sigma error of the prior heading (deg); the tilt comes from the VP.
    prior_focal_sigma : float
        Relative 1-sigma error of the rough focal length. A focal error is
        absorbed by moving the camera along its view, by this fraction of the
        viewing distance, so it widens the search for the centre.
    search_sigmas : float
        The coarse search covers this many sigmas of the prior errors.
    search_radius_px : float or None
        Radius (px) across the projected vertical within which a segment
        is a candidate for a corner in the coarse steps; None derives it
        from the prior sigmas (``search_sigmas``), the focal length and the
        viewing distance.
    ground_height : float or None
        Ground height under the image (m, local frame, the priors' vertical
        datum); None estimates it (step 2).
    altitude_range_m : (float, float)
        Camera heights above the ground (m) considered by the ground-height
        search.
    height_range_m : (float, float)
        Heights above the ground (m) spanned by the vertical building edges,
        for the visibility of corners (:func:`cadastre.visible_corners`).
    min_segment_length_px : float
        Shorter segments are ignored (px).
    vp_tolerance_deg : float
        A segment is used when its direction is within this angle of the line
        from its midpoint to the VP (matters when the VP comes from the prior
        rotation; the vanishing stage's segments pass through the VP).
    coarse_cells_mrad : (float, float, float)
        Cells of the coarse pose vote (step 2) along alpha, the lateral and
        the forward axis of the centre, in milliradians of image motion at the
        median viewing distance (pixels / focal length). Angles, not pixels:
        the vote only has to land within the reach of the fine vote, whose
        error budget is angular, and its cost grows with the cube of the
        number of cells. Alpha and forward are coarse on purpose (see
        :func:`~obliq_colmap.registration.hough.hough`).
    coarse_max_segments : int
        The coarse vote uses at most this many segments, the longest.
    coarse_height_step_m : float
        Height cell of the coarse vote (m).
    hough_cell_px : float
        Cell size of the fine pose vote (step 3), pixels.
    hough_max_cells : int
        Upper bound on the number of accumulator cells; the cells grow when
        the search range would need more.
    candidate_height_tolerance_m : float
        RANSAC candidates: a segment's bottom within this height (m) of the
        ground estimate on the corner's vertical.
    ransac_radius_px : float
        RANSAC candidates: segments within this distance (px) across the
        projected vertical of the coarse pose.
    inlier_threshold_px : float
        Mahalanobis inlier threshold, in pixels across the segment: the
        least threshold (the segments' localisation, px) ...
    inlier_threshold_m : float
        ... and the threshold on the ground (m) for the map's vertex noise,
        which lives in metres: converted with the image's scale (focal length
        over the median depth of the corners in view, px per m), the larger
        of the two is used: a fixed pixel threshold is fewer sigmas of the
        map's noise on a finer image. 0.3 m is 2 sigma of a map with 0.15 m
        vertex noise; 0 keeps the threshold in pixels.
    along_segment_stretch : float
        The inlier ellipse is this many times longer along the segment than
        across it (the segment's bottom vs the corner on the height function).
    confidence : float
        RANSAC stops when one all-inlier sample was drawn with this
        probability (adaptive trial count).
    min_trials, max_trials : int
        Bounds on the number of RANSAC samples.
    num_candidates_verified : int
        Strongest peaks of the coarse vote that are each tried with a fine
        vote and a short RANSAC (``verify_trials`` samples); the one with the
        most inlier corners is kept.
    fill_starts_with_poses : bool
        With fewer candidate heights than ``num_candidates_verified`` (a
        given ``ground_height``: the rescue, the re-registration against the
        block), try the next strongest coarse poses too, up to that number of
        starts: a weak image's true pose need not be the strongest coarse
        cell of its height. Off by default: on urban-101 it brings back
        images at stage 2, but the larger block then lets two wrong rescued
        images through the bundle's verdicts (docs/journal/independent-scenes.md).
    verify_trials : int
        RANSAC samples per candidate ground height.
    batch_size : int
        Hypotheses evaluated at once.
    min_inliers : int
        Fewer inlier corners is a failure ("no consensus").
    min_segments : int
        Fewer usable segments is a failure.
    height_sigma_m : float
        Expected error of one bottom height (m), for the height plane.
    slope_sigma : float
        Prior on the terrain slope (rise / run) of the height plane; with
        ``height_sigma_m`` it damps the plane through nearly collinear samples.
    refine_max_iterations : int
        Levenberg-Marquardt iterations per refinement.
    refine_rounds : int
        Refine / re-score rounds.
    building_outlier_factor : float
        After refinement, a building whose median residual exceeds this times
        ``inlier_threshold_px`` loses all its pairs.
    refine_vertical : str
        "always" (refine the vertical direction with the pose, from
        ``min_inliers_intrinsics`` inliers on), "auto" (only when it comes
        from the prior rotation) or "never". A detected VP a few degrees off
        tilts every projected vertical; the positions of many corners at
        different distances observe the tilt.
    vertical_sigma_deg : float
        Prior 1-sigma of the given vertical direction when it is refined
        (deg): a weak prior against drift with few inliers.
    refine_focal : bool
        Refine the focal length with the pose (the priors' rough focal length
        is a few percent off, which leaves pixels of error across the
        verticals). The result carries the refined ``camera``.
    focal_sigma_min : float
        Lower bound of the relative 1-sigma focal prior in the refinement
        (``prior_focal_sigma`` also sets the search window; a tight focal
        prior would hold the focal where the data can move it).
    min_inliers_intrinsics : int
        The focal length, the vertical and the distortion move only with at
        least this many inlier corners.
    refine_distortion : bool
        Refine the radial distortion ``k1`` (``k`` of SIMPLE_RADIAL) with the
        pose when the camera model has it; the other distortion terms are
        held. A lens the priors do not describe bends the projected verticals
        by more than the inlier threshold, which no pose and focal length
        absorb. The segments are undistorted with the current ``k1`` inside
        the refinement (consistent residuals), and again after it.
    distortion_sigma_px : float
        Prior 1-sigma of the change of the radial distortion, as the
        displacement it makes at the image corners (px): weak, so that a few
        inliers cannot drag ``k1`` far.
    allow_vp_in_frame : bool
        Register images whose vertical vanishing point lies inside the frame
        (near-nadir views). Off by default, where such an image fails with a
        message: lines through a VP inside the frame run in every direction,
        so ground and roof edges radiating from the nadir pass as verticals,
        and every corner's vertical passes the nadir point, which leaves the
        scale about it (camera height over ground) to the ground-height
        search.
    chance_trials : int
        Searches run with the segments mirrored about lines through the
        vertical VP (:func:`~obliq_colmap.registration.chance_counts`): the
        same segments and the same map corners in view, no relation between
        them, so whatever inliers they find are chance. 0 switches the test
        off. One search draws from a wide space of poses and ground heights,
        so its best chance consensus is far above what a local count
        predicts: it is measured, not modelled.
    chance_factor : float
        A result needs more than this times the most inliers found by the
        mirrored searches (a chance result rarely beats the largest of three
        by half).
    chance_test_below : int
        Only results with fewer inlier corners are tested (each test costs
        ``chance_trials`` searches); at least ``chance_factor`` x the largest
        chance count seen, with a margin.
    seed : int
        Seed of the random generator; the result is a deterministic function
        of the inputs and the seed.
    """

    prior_position_sigma_m: float = 8.0
    prior_rotation_sigma_deg: float = 1.5
    prior_focal_sigma: float = 0.015
    search_sigmas: float = 3.5
    search_radius_px: float | None = None
    ground_height: float | None = None
    altitude_range_m: tuple[float, float] = (20.0, 2000.0)
    height_range_m: tuple[float, float] = (0.0, 60.0)
    min_segment_length_px: float = 8.0
    vp_tolerance_deg: float = 3.0
    coarse_cells_mrad: tuple[float, float, float] = (13.0, 6.5, 6.5)
    coarse_max_segments: int = 150
    coarse_height_step_m: float = 4.0
    hough_cell_px: float = 4.0
    hough_max_cells: int = 4_000_000
    candidate_height_tolerance_m: float = 12.0
    ransac_radius_px: float = 16.0
    inlier_threshold_px: float = 2.0
    inlier_threshold_m: float = 0.3
    along_segment_stretch: float = 5.0
    confidence: float = 0.99
    min_trials: int = 200
    max_trials: int = 20_000
    verify_trials: int = 768
    num_candidates_verified: int = 12
    fill_starts_with_poses: bool = False
    batch_size: int = 256
    min_inliers: int = 6
    min_segments: int = 6
    height_sigma_m: float = 0.5
    slope_sigma: float = 0.05
    refine_max_iterations: int = 50
    refine_rounds: int = 2
    building_outlier_factor: float = 1.5
    refine_vertical: str = "always"
    vertical_sigma_deg: float = 3.0
    refine_focal: bool = True
    focal_sigma_min: float = 0.05
    min_inliers_intrinsics: int = 15
    refine_distortion: bool = True
    distortion_sigma_px: float = 20.0
    allow_vp_in_frame: bool = False
    chance_trials: int = 3
    chance_factor: float = 1.5
    chance_test_below: int = 40
    seed: int = 0

    def __post_init__(self) -> None:
        positive = (
            "prior_position_sigma_m",
            "prior_rotation_sigma_deg",
            "search_sigmas",
            "min_segment_length_px",
            "vp_tolerance_deg",
            "hough_cell_px",
            "coarse_height_step_m",
            "candidate_height_tolerance_m",
            "ransac_radius_px",
            "inlier_threshold_px",
            "along_segment_stretch",
            "height_sigma_m",
            "slope_sigma",
            "building_outlier_factor",
            "vertical_sigma_deg",
            "distortion_sigma_px",
        )
        for name in positive:
            value = getattr(self, name)
            if not (
                isinstance(value, (int, float)) and math.isfinite(value) and value > 0
            ):
                raise ValueError(
                    f"RegistrationOptions.{name} must be > 0, got {value!r}"
                )
        if not self.inlier_threshold_m >= 0:
            raise ValueError("RegistrationOptions.inlier_threshold_m must be >= 0")
        if not self.prior_focal_sigma >= 0:
            raise ValueError("RegistrationOptions.prior_focal_sigma must be >= 0")
        if self.search_radius_px is not None and not self.search_radius_px > 0:
            raise ValueError("RegistrationOptions.search_radius_px must be > 0 or None")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence!r}")
        if not 1 <= self.min_trials <= self.max_trials:
            raise ValueError("need 1 <= min_trials <= max_trials")
        lo, hi = self.altitude_range_m
        if not 0 < lo < hi:
            raise ValueError(
                f"altitude_range_m must be (min, max), 0 < min < max, "
                f"got {self.altitude_range_m!r}"
            )
        if self.refine_vertical not in ("auto", "always", "never"):
            raise ValueError(
                f"refine_vertical={self.refine_vertical!r}; allowed: "
                "auto, always, never"
            )
        if self.min_inliers < 3:
            raise ValueError("min_inliers must be >= 3")
        if self.chance_trials < 0 or self.chance_test_below < 0:
            raise ValueError("chance_trials and chance_test_below must be >= 0")
        if not self.chance_factor >= 1.0:
            raise ValueError("chance_factor must be >= 1")


@dataclass
class RegistrationResult:
    """The initial registration of one image (failure is a value).

    Attributes
    ----------
    success : bool
    cam_from_world : Pose
        LOCAL frame; on failure the prior. The camera height is the prior's
        (vertical-line constraints cannot observe it).
    vertical_direction : (3,) array
        Unit vertical in the camera frame pointing down the world, as used
        (detected, from the prior, or refined).
    vertical_source : str
        "detected", "prior" (the VP detection failed) or "refined".
    inlier_pairs : (K, 2) int array
        (corner index into the cadastre, segment index into the input).
    inlier_segments_px : (K, 2, 2) float array
        The inlier segments, undistorted with the INPUT camera (the frame of
        ``segments_undistorted``), for drawing and the bundle.
    height_plane : (3,) array
        ``z = a x + b y + c`` (local metres, the priors' datum) fitted to the
        heights of the inlier segments' bottoms; NaN on failure.
    ground_height : float
        The ground height found (m, local frame, the priors' datum): on
        success the height plane at the inlier corners' centroid, else the
        coarse estimate; NaN if unknown.
    num_segments : int, usable segments.
    num_candidates : int, RANSAC candidate pairs.
    num_inliers : int, final inlier pairs (one per corner).
    num_trials : int, RANSAC samples drawn.
    inlier_ratio : float, best RANSAC inliers / candidates.
    residual_rms_px : float, RMS of the final geometric residuals (px).
    message : str, what happened, in words.
    timings : dict, wall time per step (s).
    camera : Camera or None
        The intrinsics the pose belongs to: the input camera with the refined
        focal length (``options.refine_focal``) and radial distortion
        (``options.refine_distortion``); None on failure.
    distortion_refined : bool
        ``camera``'s radial distortion was refined (enough inliers, a model
        with a radial term).
    chance_inliers : int
        The most inlier corners the searches with the segments mirrored
        found (:func:`~obliq_colmap.registration.chance_counts`); -1 when not tested.
    """

    success: bool
    cam_from_world: Pose
    vertical_direction: np.ndarray
    vertical_source: str = "detected"
    inlier_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    inlier_segments_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    height_plane: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    ground_height: float = math.nan
    num_segments: int = 0
    num_candidates: int = 0
    num_inliers: int = 0
    num_trials: int = 0
    inlier_ratio: float = 0.0
    residual_rms_px: float = math.nan
    message: str = ""
    timings: dict = field(default_factory=dict)
    camera: Camera | None = None
    distortion_refined: bool = False
    chance_inliers: int = -1

    def __bool__(self) -> bool:
        return self.success


def inlier_threshold_px(options: RegistrationOptions, px_per_m: float) -> float:
    """The inlier threshold (px) of an image of ``px_per_m`` pixels per metre
    across its verticals (focal length / depth): the larger of the pixel
    threshold (edge localisation) and the ground threshold (map noise)."""
    return max(options.inlier_threshold_px, options.inlier_threshold_m * px_per_m)


def at_image_scale(
    options: RegistrationOptions, focal_px: float, depth_m: float
) -> RegistrationOptions:
    """``options`` with ``inlier_threshold_px`` at the image's scale (the
    threshold and everything derived from it: RANSAC, inlier assignment,
    the robust scale of the refinement, the building test, re-scoring)."""
    thr = inlier_threshold_px(options, focal_px / depth_m)
    return replace(options, inlier_threshold_px=thr, inlier_threshold_m=0.0)
