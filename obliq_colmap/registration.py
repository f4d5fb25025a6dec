"""Initial registration of one oblique image to the cadastral map (stage 2).

Habbecke & Kobbelt, section 2.2: with the vertical vanishing point known, the
pose has four unknowns, ``T(alpha, c) = R_vanish R_z(alpha) (I | -c)`` (eq. 1),
found from correspondences between map corners and vertical image segments.
Here the camera height is held at the prior (DESIGN.md, "height gauge"): a
vertical-line constraint cannot see it, so three unknowns (alpha, c_x, c_y)
remain and a sample of three pairs determines them in closed form
(:mod:`obliq_colmap.ransac`).

Steps of :func:`register_image`:

1. Frame. ``R_vanish`` is the prior rotation, minimally rotated so that its
   vertical agrees with the detected one (or the prior's own vertical when the
   VP detection failed); ``alpha`` is the heading correction from the prior.
   Segment endpoints are undistorted; each segment's line is taken through
   the VP and its endpoint nearer the nadir is its bottom.
2. Ground height and coarse offset. The priors' heights are in an unknown
   datum, so the ground height is estimated first: for every (corner,
   segment) pair within the search radius across the corner's projected
   vertical, the height of the segment's bottom on the corner's vertical is
   computed with the prior pose; a 2-D vote over (offset across the vertical,
   height) peaks at the ground height and the mean image offset.
3. Coarse pose (Hough). The pairs consistent with that peak vote over a grid
   of (alpha, c_x, c_y): for each alpha every pair's constraint is a straight
   line in the (c_x, c_y) plane, rasterised into the accumulator. The peak
   leaves a few pixels of error, so RANSAC runs in a small radius.
4. RANSAC. Candidates: pairs within ``ransac_radius_px`` across and
   ``candidate_height_tolerance_m`` of the ground. Samples of three pairs
   (distinct corners and segments), hypotheses from the closed-form solver in
   batches; for each, the linear height function through the samples'
   bottom heights (paper, Fig. 3b) and the elliptical Mahalanobis test of
   every candidate: across the segment ``inlier_threshold_px``, along it
   ``along_segment_stretch`` times more, measured from the segment's bottom
   to the corner projected at the height function. Score: the number of
   distinct inlier corners. Adaptive number of trials for ``confidence``.
5. Refinement. Levenberg-Marquardt (scipy, robust Huber loss) over (alpha,
   c_x, c_y) of the height-free geometric residual: the distances of both
   endpoints of each inlier segment to the image of its corner's vertical
   (eq. 2 without the heights; this avoids the collapse towards the VP of the
   plain point-to-line distance). Whole buildings whose median residual stays
   above the threshold are dropped (a building shifted in the map must not
   pull the pose), then all pairs are re-scored with the refined pose and
   height plane, and refined once more.

A failure (too few segments or candidates, no consensus, degenerate geometry)
is returned as a result with ``success=False`` and a message, never raised.

References
----------
M. Habbecke, L. Kobbelt, "Automatic registration of oblique aerial images with
cadastral maps", ECCV workshops 2010, section 2.2.
R. O. Duda, P. E. Hart, "Use of the Hough transformation to detect lines and
curves in pictures", CACM 15(1), 1972.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from obliq_colmap import ransac
from obliq_colmap.geometry import Camera, Pose, rotation_aligning, rotation_z

logger = logging.getLogger(__name__)

_EZ = np.array([0.0, 0.0, 1.0])

#: Upper bound on the cells of the fine pose vote (step 3); the window is
#: about (2 * 1.5 * coarse / fine)^3 ~ 30 x 13 x 13 cells at the true height.
_FINE_MAX_CELLS = 20_000

#: Elements of the (hypotheses, pairs) float64 temporaries of the RANSAC's
#: scoring that stay in the cache (128 KiB each).
_CACHE_ELEMENTS = 1 << 14


# --------------------------------------------------------------------------
# Options and result
# --------------------------------------------------------------------------


@dataclass(kw_only=True)
class RegistrationOptions:
    """Options of :func:`register_image` (units in the names or comments).

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
        median viewing distance (pixels / focal length; 13 mrad is 16 px at
        1000 px image width). Angles, not pixels: the vote only has to land
        within the reach of the fine vote, whose error budget is angular, and
        its cost grows with the cube of the number of cells. Alpha and forward
        are coarse on purpose (see :func:`_hough`).
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
        of the two is used. 0.3 m is 2 sigma of a map with 0.15 m vertex noise
        (2 px at 0.15 m/px; 4 px at 0.075 m/px, where a fixed 2 px kept only
        the inliers within 1 sigma); 0 keeps the threshold in pixels.
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
        from the prior rotation) or "never". A detected VP 1-5 deg off (the
        vanishing stage's tail) tilts every projected vertical; the tilt is
        observable from the positions of many corners at different
        distances.
    vertical_sigma_deg : float
        Prior 1-sigma of the given vertical direction when it is refined
        (deg): a weak prior against drift with few inliers.
    refine_focal : bool
        Refine the focal length with the pose (the rough focal length of the
        priors is a few percent off; at 0.15 m/px a 3 % error leaves ~2 px
        across the verticals). The result carries the refined ``camera``.
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
        held. A lens the priors do not describe (``k1 = -0.05`` is ~13 px at
        the corners of a 45 deg image) bends the projected verticals by more
        than the inlier threshold, which no pose and focal length absorb. The
        segments are undistorted with the current ``k1`` inside the
        refinement (consistent residuals), and again after it.
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
        search (measured on the UAVD4L drone image 0.9 deg off nadir: 15
        inliers, 20 m wrong).
    chance_trials : int
        Searches run with the segments mirrored about lines through the
        vertical VP (:func:`chance_counts`): the same segments and the same
        map corners in view, no relation between them, so whatever inliers
        they find are chance. 0 switches the test off. One search draws from
        a wide space of poses and ground heights, so its best chance
        consensus is far above what a local count predicts
        (docs/BENCHMARKS.md).
    chance_factor : float
        A result needs more than this times the most inliers found by the
        turned searches (the turned counts of one image spread by ~22 %
        (1 sigma) about their mean, so a chance result rarely beats the
        largest of three by half).
    chance_test_below : int
        Only results with fewer inlier corners are tested (each test costs
        ``chance_trials`` searches); at least ``chance_factor`` x the
        largest chance count measured (22, above) with a margin.
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
    refine_distortion: bool = False
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
        found (:func:`chance_counts`); -1 when not tested.
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


# --------------------------------------------------------------------------
# The VP-aligned frame of one image
# --------------------------------------------------------------------------


@dataclass
class _View:
    """Camera geometry of one image with the vertical fixed.

    ``X_cam = R0 R_z(alpha) (X - c)``; hypotheses are (alpha, c_xy) with c_xy
    relative to ``c0[:2]`` and the camera height held at ``c0[2]``. Corner
    coordinates are handled relative to ``c0[:2]`` too (conditioning).
    """

    K: np.ndarray
    Kinv: np.ndarray
    R0: np.ndarray
    n: np.ndarray
    c0: np.ndarray

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def rotation(self, alpha: float) -> np.ndarray:
        return self.R0 @ rotation_z(alpha)

    def pose(self, alpha: float, c_xy: np.ndarray) -> Pose:
        c = np.array([self.c0[0] + c_xy[0], self.c0[1] + c_xy[1], self.c0[2]])
        return Pose.from_center(self.rotation(alpha), c)

    def corner_lines(
        self, alpha: np.ndarray, c_xy: np.ndarray, corner_rel: np.ndarray
    ) -> np.ndarray:
        """Images of the corners' verticals, ``K^-T (n x R (X - c))``.

        Parameters
        ----------
        alpha : (H,) radians; c_xy : (H, 2) m; corner_rel : (P, 2) or (H, P, 2) m.

        Returns
        -------
        (H, P, 3) lines with unit (a, b); oriented so that a rotation about the
        vertical moves every point by the same sign of distance.
        """
        d = (
            corner_rel - c_xy[:, None, :]
            if corner_rel.ndim == 2
            else corner_rel - c_xy[:, None, :]
        )
        h_cam = ransac.horizontal_in_camera(self.R0, alpha, d)  # (H, P, 3)
        lines = np.cross(self.n, h_cam) @ self.Kinv  # (K^-T v)^T = v^T K^-1
        norm = np.linalg.norm(lines[..., :2], axis=-1, keepdims=True)
        return lines / np.where(norm > 0, norm, 1.0)

    def project(
        self,
        alpha: np.ndarray,
        c_xy: np.ndarray,
        corner_rel: np.ndarray,
        z: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels and depths of corners at heights ``z``.

        Parameters
        ----------
        alpha : (H,); c_xy : (H, 2); corner_rel : (P, 2) or (H, P, 2);
        z : (H, P) or (P,) absolute heights (m).

        Returns
        -------
        px : (H, P, 2) undistorted pixels (NaN behind); depth : (H, P).
        """
        d = corner_rel - c_xy[:, None, :]
        X = ransac.horizontal_in_camera(self.R0, alpha, d)  # (H, P, 3)
        X = X + np.asarray(z - self.c0[2])[..., None] * self.R0[:, 2]
        depth = X[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = X[..., :2] / np.where(depth > 0, depth, np.nan)[..., None]
        px = uv @ self.K[:2, :2].T + self.K[:2, 2]
        return px, depth

    def bottom_heights(
        self,
        alpha: np.ndarray,
        c_xy: np.ndarray,
        corner_rel: np.ndarray,
        bottom_px: np.ndarray,
    ) -> np.ndarray:
        """Heights of the segments' bottoms on the corners' verticals.

        The bottom's viewing ray meets the corner's vertical (up to the small
        offset across it) where its horizontal run equals the corner's
        distance along the ray's horizontal direction.

        Parameters
        ----------
        alpha : (H,); c_xy : (H, 2); corner_rel : (H, P, 2) or (P, 2);
        bottom_px : (H, P, 2) or (P, 2) undistorted pixels.

        Returns
        -------
        (H, P) absolute heights (m); NaN where the corner is behind the ray.
        """
        ray_cam = (
            np.concatenate([bottom_px, np.ones(bottom_px.shape[:-1] + (1,))], axis=-1)
            @ self.Kinv.T
        )  # (..., 3)
        ray0 = ray_cam @ self.R0  # R0^T ray: VP-aligned frame, (..., 3)
        ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
        # R_z(alpha)^T ray0: world direction.
        rx = ca * ray0[..., 0] + sa * ray0[..., 1]
        ry = -sa * ray0[..., 0] + ca * ray0[..., 1]
        rz = np.broadcast_to(ray0[..., 2], rx.shape)
        d = corner_rel - c_xy[:, None, :]
        r2 = rx * rx + ry * ry
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d[..., 0] * rx + d[..., 1] * ry) / r2
            h = self.c0[2] + t * rz
        return np.where(t > 0, h, np.nan)


def _make_view(camera: Camera, prior: Pose, n: np.ndarray) -> _View:
    K = camera.K
    R_prior = prior.rotation
    # The smallest rotation bringing the prior's vertical onto the detected one.
    R0 = rotation_aligning(R_prior @ _EZ, -n) @ R_prior
    return _View(K=K, Kinv=np.linalg.inv(K), R0=R0, n=n, c0=prior.center.copy())


# --------------------------------------------------------------------------
# Segments
# --------------------------------------------------------------------------


@dataclass
class _Segments:
    """Usable segments in the VP-aligned frame (J of them).

    index : (J,) into the input; bottom, top : (J, 2) undistorted px;
    direction : (J, 2) unit, bottom to top; normal : (J, 2) unit;
    length : (J,); line : (J, 3) through the VP and the midpoint, unit (a, b);
    m_xy : (J, 2) ``(R0^T K^T line)_xy``; side : (J, 3) midpoint ray minus its
    component along n (camera frame); ends : (J, 2, 2) the original endpoints.
    """

    index: np.ndarray
    bottom: np.ndarray
    top: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    length: np.ndarray
    line: np.ndarray
    m_xy: np.ndarray
    side: np.ndarray
    ends: np.ndarray

    def __len__(self) -> int:
        return len(self.index)


def _prepare_segments(
    segments_px: np.ndarray,
    view: _View,
    options: RegistrationOptions,
    index: np.ndarray | None = None,
) -> _Segments:
    """The usable segments of (N, 2, 2) undistorted ``segments_px``.

    ``index`` given: exactly these segments, in this order, without the
    length and VP tests (the same set again after the camera changed).
    """
    seg = np.asarray(segments_px, float).reshape(-1, 2, 2)
    finite = np.all(np.isfinite(seg), axis=(1, 2))
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    mid = seg.mean(axis=1)
    vp = view.K @ view.n  # homogeneous, the image of the nadir
    line = np.cross(vp, np.column_stack([mid, np.ones(len(mid))]))
    nrm = np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    line = line / np.where(nrm > 0, nrm, 1.0)
    # Angle between the segment and its line through the VP.
    dist = np.abs(np.sum(seg[:, 0] * line[:, :2], axis=1) + line[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        angle = np.degrees(np.arcsin(np.minimum(1.0, 2.0 * dist / length)))
    keep = finite & (length >= options.min_segment_length_px) & (nrm[:, 0] > 0)
    keep &= angle <= options.vp_tolerance_deg
    idx = np.flatnonzero(keep) if index is None else np.asarray(index, int)
    seg, line, length, mid = seg[idx], line[idx], length[idx], mid[idx]
    # Bottom: the endpoint whose viewing ray points further down the world.
    rays = np.concatenate([seg, np.ones((len(seg), 2, 1))], axis=2) @ view.Kinv.T
    down = (rays @ view.n) / np.linalg.norm(rays, axis=2)  # (J, 2)
    first_low = down[:, 0] >= down[:, 1]
    bottom = np.where(first_low[:, None], seg[:, 0], seg[:, 1])
    top = np.where(first_low[:, None], seg[:, 1], seg[:, 0])
    # Bottom and top projected onto the line through the VP.
    bottom = (
        bottom - (np.sum(bottom * line[:, :2], 1) + line[:, 2])[:, None] * line[:, :2]
    )
    top = top - (np.sum(top * line[:, :2], 1) + line[:, 2])[:, None] * line[:, :2]
    direction = top - bottom
    dl = np.linalg.norm(direction, axis=1, keepdims=True)
    direction = direction / np.where(dl > 0, dl, 1.0)
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    m = line @ view.K @ view.R0  # (R0^T K^T l)^T
    ray_mid = np.column_stack([mid, np.ones(len(mid))]) @ view.Kinv.T
    side = ray_mid - (ray_mid @ view.n)[:, None] * view.n
    return _Segments(
        idx, bottom, top, direction, normal, length, line, m[:, :2], side, seg
    )


# --------------------------------------------------------------------------
# Height plane and Mahalanobis test
# --------------------------------------------------------------------------


def _fit_planes(
    xy: np.ndarray, h: np.ndarray, weights: np.ndarray | None, ridge: float
) -> np.ndarray:
    """Ridge least-squares planes ``h = a x + b y + c`` for a batch.

    Parameters
    ----------
    xy : (H, S, 2) m (relative coordinates); h : (H, S) m; weights : (H, S) or
    None; ridge : damping of (a, b), m^2 (``(height_sigma / slope_sigma)^2``).

    Returns
    -------
    (H, 3) array (a, b, c) in the same relative coordinates; NaN where the
    heights are NaN.
    """
    w = np.ones(h.shape) if weights is None else weights
    w = np.where(np.isfinite(h), w, 0.0)
    hz = np.where(np.isfinite(h), h, 0.0)
    sw = w.sum(axis=1)  # (H,)
    sw_safe = np.where(sw > 0, sw, 1.0)
    mx = (w[..., None] * xy).sum(axis=1) / sw_safe[:, None]  # (H, 2)
    mh = (w * hz).sum(axis=1) / sw_safe
    d = xy - mx[:, None, :]
    dh = hz - mh[:, None]
    A = np.einsum("hs,hsi,hsj->hij", w, d, d) + ridge * np.eye(2)
    b = np.einsum("hs,hsi,hs->hi", w, d, dh)
    ab = np.linalg.solve(A, b[..., None])[..., 0]  # (H, 2)
    c = mh - np.sum(ab * mx, axis=1)
    out = np.column_stack([ab, c])
    out[sw <= 0] = np.nan
    return out


def _plane_at(plane: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Heights of (H, 3) planes at (P, 2) or (H, P, 2) points -> (H, P)."""
    return (
        plane[:, None, 0] * xy[..., 0]
        + plane[:, None, 1] * xy[..., 1]
        + plane[:, None, 2]
    )


def _mahalanobis2(
    px: np.ndarray, segs: _Segments, seg_idx: np.ndarray, stretch: float
) -> np.ndarray:
    """Squared Mahalanobis distances (px^2) of projected corners to segments.

    The ellipse is centred on the segment's bottom: ``across^2 +
    (along / stretch)^2``; NaN projections give inf.

    Parameters
    ----------
    px : (H, P, 2) projected corners; seg_idx : (P,) segment of each pair.
    """
    d = px - segs.bottom[seg_idx]
    across = np.sum(d * segs.normal[seg_idx], axis=-1)
    along = np.sum(d * segs.direction[seg_idx], axis=-1)
    d2 = across * across + (along / stretch) ** 2
    return np.where(np.isfinite(d2), d2, np.inf)


def _pair_d2(
    view: _View,
    segs: _Segments,
    seg_idx: np.ndarray,
    alpha: np.ndarray,
    c_xy: np.ndarray,
    xy: np.ndarray,
    z: np.ndarray,
    stretch: float,
) -> np.ndarray:
    """:func:`_mahalanobis2` of the corners projected by :meth:`_View.project`,
    fused (the RANSAC's scoring loop).

    The same floating-point operations per element, on (H, P) arrays per
    coordinate instead of (H, P, 3) temporaries and a matmul by ``K``: the
    result is bit-identical when ``K`` has no skew (the products with its zero
    entries add exact zeros); otherwise the two functions are called.

    Parameters
    ----------
    seg_idx : (P,) segment of each pair; alpha : (H,); c_xy : (H, 2);
    xy : (P, 2) corners (relative); z : (H, P) heights (m); stretch : float.

    Returns
    -------
    (H, P) squared distances (px^2), inf where not finite.
    """
    K, R0 = view.K, view.R0
    if K[0, 1] != 0 or K[1, 0] != 0:
        px, _ = view.project(alpha, c_xy, xy, z)
        return _mahalanobis2(px, segs, seg_idx, stretch)
    ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
    dx = xy[:, 0] - c_xy[:, 0, None]
    dy = xy[:, 1] - c_xy[:, 1, None]
    rx = ca * dx - sa * dy  # as ransac.horizontal_in_camera
    ry = sa * dx + ca * dy
    zz = z - view.c0[2]
    depth = rx * R0[2, 0] + ry * R0[2, 1] + zz * R0[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        den = np.where(depth > 0, depth, np.nan)
        u = (rx * R0[0, 0] + ry * R0[0, 1] + zz * R0[0, 2]) / den
        v = (rx * R0[1, 0] + ry * R0[1, 1] + zz * R0[1, 2]) / den
    bottom = segs.bottom[seg_idx]
    ex = u * K[0, 0] + K[0, 2] - bottom[:, 0]
    ey = v * K[1, 1] + K[1, 2] - bottom[:, 1]
    nrm, dirn = segs.normal[seg_idx], segs.direction[seg_idx]
    across = ex * nrm[:, 0] + ey * nrm[:, 1]
    along = (ex * dirn[:, 0] + ey * dirn[:, 1]) / stretch
    d2 = across * across + along * along
    return np.where(np.isfinite(d2), d2, np.inf)


# --------------------------------------------------------------------------
# Steps 2-3: Hough votes over (alpha, c_x, c_y[, ground height])
# --------------------------------------------------------------------------


def inlier_threshold_px(options: RegistrationOptions, px_per_m: float) -> float:
    """The inlier threshold (px) of an image of ``px_per_m`` pixels per metre
    across its verticals (focal length / depth): the larger of the pixel
    threshold (edge localisation) and the ground threshold (map noise)."""
    return max(options.inlier_threshold_px, options.inlier_threshold_m * px_per_m)


def _at_image_scale(
    options: RegistrationOptions, focal_px: float, depth_m: float
) -> RegistrationOptions:
    """``options`` with ``inlier_threshold_px`` at the image's scale (the
    threshold and everything derived from it: RANSAC, inlier assignment,
    the robust scale of the refinement, the building test, re-scoring)."""
    thr = inlier_threshold_px(options, focal_px / depth_m)
    return replace(options, inlier_threshold_px=thr, inlier_threshold_m=0.0)


def _search_windows(view: _View, options: RegistrationOptions, depth_m: float):
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


@dataclass
class _HoughPeak:
    alpha: float
    c_xy: np.ndarray
    height: float  # NaN without a height axis
    votes: float


@dataclass
class _HoughGrid:
    """A smoothed Hough accumulator over (alpha, c_1, c_2[, height]).

    The centre is ``c_center + k1 d1 u1 + k2 d2 u2`` for cell indices k1, k2
    centred on zero; ``u1`` is the camera's lateral direction and ``u2`` its
    horizontal viewing direction.
    """

    acc: np.ndarray  # (na, n1, n2, nh)
    alphas: np.ndarray  # (na,) radians
    c_center: np.ndarray  # (2,)
    axes: np.ndarray  # (2, 2) rows u1, u2
    steps: np.ndarray  # (2,) d1, d2 metres
    h_lo: float
    d_alpha: float
    d_h: float  # inf without a height axis

    @property
    def d_c(self) -> float:
        return float(self.steps.max())

    def center_of(self, k1, k2) -> np.ndarray:
        n1, n2 = self.acc.shape[1:3]
        return (
            self.c_center
            + (k1 - n1 // 2) * self.steps[0] * self.axes[0]
            + (k2 - n2 // 2) * self.steps[1] * self.axes[1]
        )

    def _at(self, ka, k1, k2, kh) -> _HoughPeak:
        h = self.h_lo + (kh + 0.5) * self.d_h if math.isfinite(self.d_h) else math.nan
        return _HoughPeak(
            float(self.alphas[ka]),
            self.center_of(k1, k2),
            float(h),
            float(self.acc[ka, k1, k2, kh]),
        )

    def peak(self) -> _HoughPeak:
        return self._at(*np.unravel_index(int(np.argmax(self.acc)), self.acc.shape))

    def peaks_by_height(self, num: int, separation: int) -> list[_HoughPeak]:
        """The best pose at each of the ``num`` strongest heights, the heights
        local maxima of the height profile (the best vote over all poses) at
        least ``separation`` cells apart, strongest first.

        Spurious heights (chance alignments of the map with clutter, far
        above or below the ground) can form many strong pose peaks at one
        height; ranking heights rather than 4-D peaks keeps the true ground
        among the candidates that are verified.
        """
        nh = self.acc.shape[3]
        flat = self.acc.reshape(-1, nh)
        # The first pose cell of each height's maximum, as argmax along the
        # strided axis 0 (3x slower) gives it; the accumulator has no NaN.
        profile = flat.max(axis=0)  # (nh,)
        best = np.argmax(flat == profile, axis=0)  # (nh,) pose cell per height
        order = np.argsort(-profile, kind="stable")
        chosen: list[int] = []
        for kh in order:
            if len(chosen) == num or profile[kh] <= 0:
                break
            if all(abs(int(kh) - c) > separation for c in chosen):
                chosen.append(int(kh))
        out = []
        for kh in chosen:
            ka, k1, k2 = np.unravel_index(int(best[kh]), self.acc.shape[:3])
            out.append(self._at(ka, k1, k2, kh))
        return out

    def peaks(
        self, num: int, separation: tuple[int, int, int, int]
    ) -> list[_HoughPeak]:
        """The ``num`` strongest local maxima, at least ``separation`` cells apart
        on some axis (non-maximum suppression), strongest first."""
        from scipy.ndimage import maximum_filter

        size = tuple(
            min(2 * s + 1, n) for s, n in zip(separation, self.acc.shape, strict=True)
        )
        local = self.acc == maximum_filter(self.acc, size=size, mode="constant")
        idx = np.argwhere(local & (self.acc > 0))
        values = self.acc[tuple(idx.T)]
        order = np.argsort(-values, kind="stable")
        sep = np.asarray(separation)
        chosen: list[np.ndarray] = []
        for k in order:
            if len(chosen) == num:
                break
            if all(np.any(np.abs(idx[k] - c) > sep) for c in chosen):
                chosen.append(idx[k])
        return [self._at(*c) for c in chosen]


def _horizontal_axes(view: _View) -> np.ndarray:
    """(2, 2): the camera's lateral and viewing directions on the ground."""
    forward = view.R0[2, :2]  # optical axis in the world, horizontal part
    if np.linalg.norm(forward) < 0.2:  # near-nadir: the image's up direction
        forward = -view.R0[1, :2]
    forward = forward / np.linalg.norm(forward)
    lateral = np.array([forward[1], -forward[0]])
    return np.stack([lateral, forward])


def _hough(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    pair_i: np.ndarray,
    pair_j: np.ndarray,
    alpha_center: float,
    alpha_half: float,
    c_center: np.ndarray,
    c_half: float,
    cell_px: tuple[float, float, float],
    depth_m: float,
    max_cells: int,
    heights: tuple[float, float, float] | None = None,
) -> _HoughGrid:
    """Vote of candidate pairs over a grid of poses (Hough transform).

    For a fixed alpha, pair k's constraint ``r0 cos + r1 sin - g . c = 0``
    (``g = R_z(alpha)^T m_xy``, :func:`ransac.constraint_rows`) is a straight
    line in the plane of the centre; it is sampled at the cell centres of
    the axis along which it runs and the other coordinate is rounded to a
    cell. With ``heights`` the accumulator has a fourth axis, the height of
    the segment's bottom on the corner's vertical at that pose: a pair votes
    only at the ground height it implies, which separates the true pairs (all
    at the ground) from the many chance pairs along each vertical.

    The cells are anisotropic because of two near-degeneracies of an oblique
    view: a heading change moves the image almost like a lateral shift of
    the camera, and a forward shift almost like a change of the ground
    height. Coarse cells along alpha and the forward axis are compensated by
    the lateral axis and the height, which are sampled finely.

    Each (alpha, pair) line is rasterised over its exact interval of votes
    (:func:`_rasterise`), vectorised over lines and votes; the result is
    bit-identical to an enumeration vote by vote in (alpha, pair, t) order.

    Parameters
    ----------
    pair_i, pair_j : (P,) corner and segment of each pair.
    alpha_center, alpha_half : radians; c_center (2,), c_half : metres, the
        search window (relative to the prior).
    cell_px : (alpha, lateral, forward) cell sizes, pixels of image motion
        at ``depth_m``.
    max_cells : the cells grow until the accumulator has at most this many.
    heights : (lo, hi, step) metres, or None for a 3-D vote.

    Returns
    -------
    _HoughGrid, the accumulator smoothed over 3 cells per axis.
    """
    f = view.focal
    d_alpha = cell_px[0] / f
    steps = np.array([cell_px[1], cell_px[2]]) * depth_m / f
    if heights is not None:
        h_lo, h_hi, d_h = heights
        nh = max(1, int(math.ceil((h_hi - h_lo) / d_h)))
    else:
        h_lo, d_h, nh = 0.0, math.inf, 1
    while True:
        na = 2 * int(math.ceil(alpha_half / d_alpha)) + 1
        n1, n2 = (2 * np.ceil(c_half / steps).astype(int) + 1).tolist()
        if na * n1 * n2 * nh <= max_cells or (na == 1 and n1 == 1 and n2 == 1):
            break
        d_alpha *= 1.2
        steps *= 1.2
    axes = _horizontal_axes(view)
    alphas = alpha_center + (np.arange(na) - na // 2) * d_alpha
    xy = corner_rel[pair_i]  # (P, 2)
    m = segs.m_xy[pair_j]  # (P, 2)
    rows = ransac.constraint_rows(m, xy - c_center)  # c relative to c_center
    weight = np.minimum(segs.length[pair_j], 60.0)
    if heights is not None:
        ray0 = (
            np.column_stack([segs.bottom[pair_j], np.ones(len(pair_j))])
            @ view.Kinv.T
            @ view.R0
        )  # (P, 3) bottom rays, VP-aligned frame
    slab = n1 * n2 * nh
    acc = np.zeros(na * slab, dtype=np.float32)
    half = np.array([n1 // 2, n2 // 2])
    band_of = None
    if heights is not None:
        # Every pair's votes lie on a segment of cells whose heights are
        # computed in closed form (:func:`_vote_rows`).
        h_hi = h_lo + nh * d_h
        band_of = (ray0, xy - c_center, float(view.c0[2]), h_lo, h_hi, d_h, nh, n1 * n2)
    P = len(pair_i)
    # Rows (alpha, pair) in pieces of ~2^16 rows, several alphas at once or
    # one alpha's pairs in pieces of 2^14 (the coarse vote's ~10^5): the
    # rows' temporaries stay in the cache; an alpha's pieces are joined for
    # its sum.
    pc = min(P, _ROW_PIECE)
    chunk = 1 if pc < P else max(1, (1 << 16) // max(P, 1))
    work = _Workspace()
    for k0 in range(0, na, chunk):
        ka = np.arange(k0, min(na, k0 + chunk))
        ca = np.cos(alphas[ka])[:, None]
        sa = np.sin(alphas[ka])[:, None]
        pieces = [
            _vote_rows(
                ca,
                sa,
                m[p0 : p0 + pc],
                rows[p0 : p0 + pc],
                weight[p0 : p0 + pc],
                axes,
                steps,
                half,
                None if band_of is None else _pair_slice(band_of, p0, pc),
            )
            for p0 in range(0, P, pc)
        ]
        lines, band, ia = _join_pieces(pieces)
        group_ends = np.searchsorted(ia, np.arange(len(ka) + 1))
        off = k0 * slab
        acc[off : off + len(ka) * slab] += _rasterise(
            lines, band, slab, groups=len(ka), work=work, group_ends=group_ends
        )
    from scipy.ndimage import uniform_filter

    acc = np.ascontiguousarray(acc.reshape(na, nh, n1, n2).transpose(0, 2, 3, 1))
    acc = uniform_filter(acc, size=(3, 3, 3, min(nh, 3)), mode="constant")
    grid = _HoughGrid(
        acc,
        alphas,
        np.asarray(c_center, float),
        axes,
        steps,
        h_lo,
        float(d_alpha),
        float(d_h),
    )
    return grid


#: Pairs per piece of Hough rows (:func:`_hough`).
_ROW_PIECE = 1 << 14


def _vote_rows(
    ca: np.ndarray,
    sa: np.ndarray,
    m: np.ndarray,
    rows: np.ndarray,
    weight: np.ndarray,
    axes: np.ndarray,
    steps: np.ndarray,
    half: np.ndarray,
    band_of: tuple | None,
) -> tuple[_VoteRows, _HeightBand | None, np.ndarray]:
    """The Hough rows of some alphas and pairs that cross the window.

    For a fixed alpha, pair k's constraint is the line ``a1 k1 + a2 k2 =
    rhs`` in cell units of the centre; it is iterated along the axis along
    which it runs. Only the rows that cross the window are returned (a third
    to a half do not), the same elementwise expressions on fewer rows.

    Parameters
    ----------
    ca, sa : (A, 1) cos and sin of the alphas; m : (P, 2) ``m_xy`` of the
    pairs' segments; rows : (P, 4) their constraint rows; weight : (P,);
    axes, steps, half : of the grid (:class:`_HoughGrid`); band_of : None, or
    (ray0 (P, 3), d_rel (P, 2), c0_z, h_lo, h_hi, d_h, nh, stride) for a
    height axis.

    Returns
    -------
    The rows, (alpha, pair) order; their height band or None; (R,) the
    alpha (index into ``ca``) of each row.
    """
    mx, my = m[:, 0], m[:, 1]
    rhs = rows[:, 0] * ca + rows[:, 1] * sa  # = g . (c - c_center)
    gx, gy = ca * mx + sa * my, -sa * mx + ca * my
    # In cell units: a1 k1 + a2 k2 = rhs.
    a1 = (gx * axes[0, 0] + gy * axes[0, 1]) * steps[0]
    a2 = (gx * axes[1, 0] + gy * axes[1, 1]) * steps[1]
    iter_2 = np.abs(a1) >= np.abs(a2)  # iterate k2, solve k1 (else swap)
    den = np.where(iter_2, a1, a2)
    with np.errstate(divide="ignore", invalid="ignore"):
        A_o = rhs / den  # other = A_o + B_o t (cell units)
        B_o = -np.where(iter_2, a2, a1) / den
    half_it = np.where(iter_2, half[1], half[0])
    half_o = np.where(iter_2, half[0], half[1])
    t_lo, t_hi = _t_interval(A_o, B_o, -half_o - 0.5, half_o + 0.5)
    t_lo, t_hi = np.maximum(t_lo, -half_it), np.minimum(t_hi, half_it)
    sel = np.flatnonzero(t_lo <= t_hi)  # rows (alpha, pair)
    ia, ip = np.divmod(sel, len(m))
    A_o, B_o, iter_2 = A_o.ravel()[sel], B_o.ravel()[sel], iter_2.ravel()[sel]
    t_lo, t_hi = t_lo.ravel()[sel], t_hi.ravel()[sel]
    band = None
    if band_of is not None:
        ray0, d_rel, c0_z, h_lo, h_hi, d_h, nh, stride = band_of
        ca, sa = ca[ia, 0], sa[ia, 0]
        ray, d = ray0[ip], d_rel[ip]
        # Horizontal run of the corner from the search centre along each
        # bottom ray's heading is linear in the centre, hence in the cell
        # index along the iterated axis. Centre offsets e1 = E1a + E1b t,
        # e2 = E2a + E2b t (m).
        E1a = np.where(iter_2, A_o * steps[0], 0.0)
        E1b = np.where(iter_2, B_o * steps[0], steps[0])
        E2a = np.where(iter_2, 0.0, A_o * steps[1])
        E2b = np.where(iter_2, steps[1], B_o * steps[1])
        rx = ca * ray[:, 0] + sa * ray[:, 1]
        ry = -sa * ray[:, 0] + ca * ray[:, 1]
        r2 = rx * rx + ry * ry
        u1r = axes[0, 0] * rx + axes[0, 1] * ry
        u2r = axes[1, 0] * rx + axes[1, 1] * ry
        with np.errstate(divide="ignore", invalid="ignore"):
            # Run along the ray: tt = TA + TB t (> 0: in front).
            TA = (d[:, 0] * rx + d[:, 1] * ry - E1a * u1r - E2a * u2r) / r2
            TB = -(E1b * u1r + E2b * u2r) / r2
        hA = c0_z + TA * ray[:, 2]
        hB = TB * ray[:, 2]
        lo, hi = _t_interval(hA, hB, h_lo, h_hi)
        t_lo, t_hi = np.maximum(t_lo, lo), np.minimum(t_hi, hi)
        lo, hi = _t_interval(TA, TB, 0.0, np.inf)
        t_lo, t_hi = np.maximum(t_lo, lo), np.minimum(t_hi, hi)
        band = _HeightBand(hA, hB, TA, TB, h_lo, d_h, nh, float(stride))
    # Cell of vote t of a row: base + stride_t t + stride_o k_other
    # (+ n1 n2 ih), relative to its alpha's slab (each alpha is summed
    # alone). The votes are laid out (alpha, height, k1, k2): a line's
    # successive votes then touch nearby cells (the height changes slowly
    # along it), which keeps the accumulation in cache; transposed to
    # (alpha, k1, k2, height) at the end.
    s1, s2 = float(2 * half[1] + 1), 1.0
    lines = _VoteRows(
        A_o,
        B_o,
        np.where(iter_2, half[0], half[1]),
        t_lo,
        t_hi,
        np.full(len(sel), half[0] * s1 + half[1] * s2),
        np.where(iter_2, s2, s1),
        np.where(iter_2, s1, s2),
        weight[ip],
    )
    return lines, band, ia


def _pair_slice(band_of: tuple, p0: int, n: int) -> tuple:
    """``band_of`` of :func:`_vote_rows` for the pairs ``p0:p0 + n``."""
    ray0, d_rel, *rest = band_of
    return (ray0[p0 : p0 + n], d_rel[p0 : p0 + n], *rest)


def _join_pieces(pieces: list) -> tuple[_VoteRows, _HeightBand | None, np.ndarray]:
    """The results of :func:`_vote_rows` over consecutive pair ranges of one
    alpha (or one piece of several alphas), concatenated."""
    if len(pieces) == 1:
        return pieces[0]
    lines = _VoteRows(
        *(
            np.concatenate([getattr(p[0], f.name) for p in pieces])
            for f in dataclasses.fields(_VoteRows)
        )
    )
    band = pieces[0][1]
    if band is not None:
        band = replace(
            band,
            **{
                k: np.concatenate([getattr(p[1], k) for p in pieces])
                for k in ("hA", "hB", "TA", "TB")
            },
        )
    return lines, band, np.concatenate([p[2] for p in pieces])


def _t_interval(
    A: np.ndarray, B: np.ndarray, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Integer t with ``lo <= A + B t <= hi``, per row: (t_lo, t_hi) float
    arrays (t_lo > t_hi when empty; infinite bounds where B = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - A) / B, (hi - A) / B
    t_lo = np.ceil(np.minimum(t1, t2))
    t_hi = np.floor(np.maximum(t1, t2))
    # B = 0 (all t or none) and non-finite rows are rare: set sparsely. With
    # a finite lo they all have a non-finite t1, a cheaper first sieve.
    if np.all(np.isfinite(lo)):
        odd = np.flatnonzero(~np.isfinite(t1))
        a, b = np.ravel(A)[odd], np.ravel(B)[odd]
        odd = odd[(b == 0) | ~np.isfinite(a) | np.isnan(b)]
        odd = np.unravel_index(odd, t1.shape)
    else:
        odd = np.nonzero((B == 0) | ~np.isfinite(A) | np.isnan(B))
    if len(odd[0]):
        a, b = A[odd], B[odd]
        lo_o = lo[odd] if np.ndim(lo) else lo
        hi_o = hi[odd] if np.ndim(hi) else hi
        inside = (lo_o <= a) & (hi_o >= a)
        bad = ~np.isfinite(a) | np.isnan(b)
        t_lo[odd] = np.where(inside & ~bad, -np.inf, np.inf)
        t_hi[odd] = np.where(inside & ~bad, np.inf, -np.inf)
    return t_lo, t_hi


@dataclass
class _HeightBand:
    """The height axis of a vote (rows as in :class:`_VoteRows`): vote t of a
    row falls into height cell ``ih = floor((hA + hB t - h_lo) / d_h)``,
    which must lie in [0, nh), and only in front of the ray, ``TA + TB t >
    0``; ``stride`` is the cell offset of one height step."""

    hA: np.ndarray
    hB: np.ndarray
    TA: np.ndarray
    TB: np.ndarray
    h_lo: float
    d_h: float
    nh: int
    stride: float


@dataclass
class _VoteRows:
    """R straight lines to rasterise, one per (alpha, pair), in cell units.

    Vote t (integer, ``t_lo <= t <= t_hi``) of row r lands in the cell
    ``base + stride_t t + stride_o k``, ``k = rint(A + B t)`` the other
    coordinate, which must satisfy ``|k| <= half_o``; ``weight`` (R,) per row.
    All arrays (R,) float (``half_o`` int).
    """

    A: np.ndarray
    B: np.ndarray
    half_o: np.ndarray
    t_lo: np.ndarray
    t_hi: np.ndarray
    base: np.ndarray
    stride_t: np.ndarray
    stride_o: np.ndarray
    weight: np.ndarray


def _vote_ok(
    rows: _VoteRows, band: _HeightBand | None, r: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Whether vote ``t`` (K,) of rows ``r`` (K,) lands in the accumulator:
    the same float expressions as :func:`_rasterise` evaluates per vote."""
    ok = np.abs(np.rint(rows.A[r] + rows.B[r] * t)) <= rows.half_o[r]
    if band is not None:
        ih = np.floor((band.hA[r] + band.hB[r] * t - band.h_lo) / band.d_h)
        ok &= (ih >= 0) & (ih < band.nh) & (band.TA[r] + band.TB[r] * t > 0)
    return ok


def _trim(
    rows: _VoteRows, band: _HeightBand | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows' exact vote intervals: (row index (R',), t_lo (R',), t_hi (R',))
    of the rows with votes, such that every integer t in [t_lo, t_hi] passes
    :func:`_vote_ok` and no other t of [rows.t_lo, rows.t_hi] does.

    ``rows.t_lo``, ``rows.t_hi`` bound the conditions in exact arithmetic, so
    they may be off by rounding at their ends. Each condition is monotone in
    t also in floating point (``fl(A + fl(B t))`` is monotone, so are rint,
    floor and the comparisons), so the passing t of a row form one interval:
    moving each end inwards while it fails finds it, in a few vectorised
    rounds over the few rows whose end fails. The first round tests both
    ends of every row on the rows' coefficients gathered once.
    """
    count = np.maximum(rows.t_hi - rows.t_lo + 1, 0)
    r = np.flatnonzero(count > 0)
    lo, hi = rows.t_lo[r], rows.t_hi[r]
    sub = _VoteRows(rows.A[r], rows.B[r], rows.half_o[r], lo, hi, *(None,) * 4)
    sub_band = None
    if band is not None:
        sub_band = replace(
            band, hA=band.hA[r], hB=band.hB[r], TA=band.TA[r], TB=band.TB[r]
        )
    every = slice(None)
    fail_hi = ~_vote_ok(sub, sub_band, every, hi)  # hi is not moved before its turn
    for end, step in ((lo, 1.0), (hi, -1.0)):
        fail = ~_vote_ok(sub, sub_band, every, lo) if step > 0 else fail_hi
        k = np.flatnonzero(fail & (lo <= hi))
        end[k] += step
        while len(k):
            k = k[lo[k] <= hi[k]]
            k = k[~_vote_ok(sub, sub_band, k, end[k])]
            end[k] += step
    keep = lo <= hi
    return r[keep], lo[keep], hi[keep]


#: Votes (dense t x row entries) generated at once by :func:`_rasterise`:
#: its three float64 temporaries of this size stay in the L2 / L3 cache.
_RASTER_BLOCK = 1 << 16


class _Workspace:
    """Scratch arrays reused across the calls of one vote (fresh arrays of
    megabytes cost page faults on every first touch: measured 10-20 % of
    the coarse vote's CPU time as system time)."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def array(self, name: str, size: int, dtype) -> np.ndarray:
        """A (size,) array of ``dtype`` with arbitrary contents."""
        a = self._arrays.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            # With headroom: the next call's rows are a few more.
            a = np.empty(size + size // 4, dtype)
            self._arrays[name] = a
        return a[:size]


def _rasterise(
    rows: _VoteRows,
    band: _HeightBand | None,
    size: int,
    groups: int = 1,
    work: _Workspace | None = None,
    group_ends: np.ndarray | None = None,
) -> np.ndarray:
    """Sum of the rows' weights over the cells they cross.

    The rows form ``groups`` consecutive groups that vote into disjoint
    ranges of ``size`` cells (the alphas of the Hough vote; cell indices
    relative to the range), of equal length or group g the rows
    ``group_ends[g]:group_ends[g + 1]``: returns (groups * size,) float64.

    Every row's votes are an interval of t (:func:`_trim`); they are generated
    densely, (t - t_lo) x rows (the inner loops run over rows, not over a
    row's few votes), in blocks that fit the cache, the entries past a row's
    end sent to a spare cell. A group's votes reach one ``np.bincount`` in
    row order, t ascending, so that each cell sums the same terms in the same
    order as an enumeration vote by vote.
    """
    work = work or _Workspace()
    out = np.zeros(groups * size)
    r, lo, hi = _trim(rows, band)
    if len(r) == 0:
        return out
    count = hi - lo + 1
    width = int(count.max())
    steps = np.arange(width, dtype=float)[:, None]
    block = max(1, _RASTER_BLOCK // width)
    buf = work.array("buf", 3 * width * block, float).reshape(3, width * block)
    A, B, base = rows.A[r], rows.B[r], rows.base[r]
    stride_t, stride_o = rows.stride_t[r], rows.stride_o[r]
    if band is not None:
        hA, hB = band.hA[r], band.hB[r]
    if group_ends is None:
        group_ends = np.arange(groups + 1) * (len(rows.A) // groups)
    ends = np.searchsorted(r, group_ends)
    for g in range(groups):
        g0, g1 = ends[g], ends[g + 1]
        if g0 == g1:
            continue
        n = g1 - g0
        cells = work.array("cells", n * width, np.int64).reshape(n, width)
        for b0 in range(g0, g1, block):
            b = slice(b0, min(b0 + block, g1))
            nb = b.stop - b0
            # Contiguous (width, rows) arrays (putmask copies strided ones).
            t, k, cell = (x[: width * nb].reshape(width, nb) for x in buf)
            np.add(lo[b], steps, out=t)
            np.multiply(B[b], t, out=k)
            k += A[b]
            np.rint(k, out=k)
            np.multiply(stride_o[b], k, out=cell)
            cell += base[b]
            if band is not None:
                np.multiply(hB[b], t, out=k)
                k += hA[b]
                k -= band.h_lo
                k /= band.d_h
                np.floor(k, out=k)
                k *= band.stride
                cell += k
            np.multiply(stride_t[b], t, out=k)
            cell += k
            np.putmask(cell, steps >= count[b], size)  # spare
            # Integer-valued floats: the cast to the cell index is exact.
            np.copyto(cells[b0 - g0 : b.stop - g0], cell.T, casting="unsafe")
        weights = work.array("weights", n * width, float).reshape(n, width)
        weights[...] = rows.weight[r[g0:g1], None]
        out[g * size : (g + 1) * size] = np.bincount(
            cells.ravel(), weights=weights.ravel(), minlength=size + 1
        )[:size]
    return out


def _pairs_near(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    radius_px: float,
    h_range: tuple[float, float] | None = None,
    ground=None,
    height_tol_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs whose segment bottom lies within ``radius_px`` across the corner's
    projected vertical, with the bottom's height in ``h_range`` or within
    ``height_tol_m`` of ``ground`` ((I,) array or float) on that vertical.

    Returns (corner indices, segment indices), sorted by corner then segment.
    """
    a, c = np.array([alpha]), np.asarray(c_xy, float)[None]
    lines = view.corner_lines(a, c, corner_rel)[0]  # (I, 3)
    across = lines[:, :2] @ segs.bottom.T + lines[:, 2:3]  # (I, J)
    ii, jj = np.nonzero(np.abs(across) <= radius_px)  # sorted by (i, j)
    h = view.bottom_heights(a, c, corner_rel[ii], segs.bottom[jj])[0]
    with np.errstate(invalid="ignore"):
        if h_range is not None:
            ok = (h >= h_range[0]) & (h <= h_range[1])
        else:
            g = ground[ii] if np.ndim(ground) else ground
            ok = np.abs(h - g) <= height_tol_m
    return ii[ok], jj[ok]


# --------------------------------------------------------------------------
# Step 4: RANSAC
# --------------------------------------------------------------------------


@dataclass
class _Candidates:
    corner: np.ndarray  # (P,) index into corner_rel
    segment: np.ndarray  # (P,) index into _Segments
    starts: np.ndarray  # group starts of equal corners (pairs sorted by corner)


def _candidates(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    ground: np.ndarray | float,
    radius_px: float,
    height_tol_m: float,
) -> _Candidates:
    ii, jj = _pairs_near(
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
    return _Candidates(ii, jj, starts)


def _score(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    cand: _Candidates,
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
        z = _plane_at(plane[h], xy)  # (h, P)
        d2 = _pair_d2(view, segs, cand.segment, alpha[h], c_xy[h], xy, z, stretch)
        inl = d2 <= thr2
        count[h] = np.maximum.reduceat(inl, cand.starts, axis=1).sum(axis=1)
        cost[h] = np.minimum(d2, thr2).sum(axis=1)
    return count, cost


@dataclass
class _RansacState:
    """Where a RANSAC run stopped: resuming it with a larger ``max_trials``
    draws and scores exactly the samples a single longer run would have."""

    rng: np.random.Generator
    trials: int = 0
    needed: float = 0.0
    best: tuple[int, float] = (-1, math.inf)
    model: tuple[float, np.ndarray, np.ndarray] = field(
        default_factory=lambda: (math.nan, np.full(2, np.nan), np.full(3, np.nan))
    )


def _ransac(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    cand: _Candidates,
    alpha_center: float,
    c_center: np.ndarray,
    alpha_half: float,
    c_half: float,
    options: RegistrationOptions,
    state: _RansacState,
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
        idx = ransac.sample_pairs(st.rng, B, cand.corner, cand.segment)
        st.trials += B
        if len(idx) == 0:
            continue
        ci, sj = cand.corner[idx], cand.segment[idx]  # (S, 3)
        alpha, c_xy, valid = ransac.solve_minimal(
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
        plane = _fit_planes(corner_rel[ci], h, None, ridge)
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
                options.min_trials, ransac.required_trials(ratio, 3, options.confidence)
            )
    return (*st.model, max(st.best[0], 0), st.best[1], st.trials)


# --------------------------------------------------------------------------
# Step 5: refinement
# --------------------------------------------------------------------------


def _inlier_assignment(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    cand: _Candidates,
    alpha: float,
    c_xy: np.ndarray,
    plane: np.ndarray,
    options: RegistrationOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one inlier pairs (best Mahalanobis distance first).

    Returns (corner indices, segment indices), both (K,).
    """
    xy = corner_rel[cand.corner]
    z = _plane_at(plane[None], xy)
    px, _ = view.project(np.array([alpha]), c_xy[None], xy, z)
    d2 = _mahalanobis2(px, segs, cand.segment, options.along_segment_stretch)[0]
    inl = np.flatnonzero(d2 <= options.inlier_threshold_px**2)
    inl = inl[np.argsort(d2[inl], kind="stable")]
    used_c, used_s = set(), set()
    keep = []
    for k in inl:
        ci, sj = int(cand.corner[k]), int(cand.segment[k])
        if ci in used_c or sj in used_s:
            continue
        used_c.add(ci)
        used_s.add(sj)
        keep.append(k)
    keep = np.asarray(keep, int)
    return cand.corner[keep], cand.segment[keep]


def _tilt_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3) two unit vectors orthogonal to n (axes of small tilts)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def _perturbed_view(
    view: _View, log_focal: float, tilt: np.ndarray | None, tilt_axes: np.ndarray
) -> _View:
    """The view with its focal length scaled by ``exp(log_focal)`` and its
    vertical tilted by ``tilt`` (2,) radians about ``tilt_axes``.

    The focal change keeps the vanishing point's PIXEL fixed (the detected
    quantity): the vertical direction ``n = K^-1 v`` follows the new ``K``
    by the smallest rotation; the tilt then moves the vanishing point.
    """
    from obliq_colmap.geometry import rotation_from_axis_angle

    K = view.K.copy()
    K[0, 0] *= math.exp(log_focal)
    K[1, 1] *= math.exp(log_focal)
    Kinv = np.linalg.inv(K)
    n_f = Kinv @ (view.K @ view.n)
    dR = rotation_aligning(view.n, n_f)
    if tilt is not None:
        dR = (
            rotation_from_axis_angle(tilt[0] * tilt_axes[0] + tilt[1] * tilt_axes[1])
            @ dR
        )
    n = dR @ view.n
    return _View(K=K, Kinv=Kinv, R0=dR @ view.R0, n=n / np.linalg.norm(n), c0=view.c0)


@dataclass
class _Lens:
    """The current camera's distortion, for residuals from RAW segments.

    ``camera``: the current intrinsics (its pinhole part is the view's
    ``K``); ``k_index``: index of the radial ``k1`` in its params, or None
    when it is not refined; ``k_prior``, ``k_sigma``: centre and 1-sigma of
    its prior (unitless).
    """

    camera: Camera
    k_index: int | None
    k_prior: float = 0.0
    k_sigma: float = math.inf

    def camera_at(self, log_focal: float, dk: float) -> Camera:
        """The camera with its focal scaled by ``exp(log_focal)`` and ``k1 + dk``."""
        cam = self.camera.with_focal_scaled(math.exp(log_focal))
        if self.k_index is not None:
            cam.params[self.k_index] += dk
        return cam

    def undistorted(self, raw: np.ndarray, log_focal: float, dk: float) -> np.ndarray:
        """(K, 2, 2) raw endpoints to undistorted pixels of that camera."""
        cam = self.camera_at(log_focal, dk)
        return cam.undistort_pixels(raw.reshape(-1, 2)).reshape(raw.shape)


def _radial_index(model: str) -> int | None:
    """Index of the first radial distortion term in a model's params."""
    from obliq_colmap.geometry import SUPPORTED_MODELS

    names = SUPPORTED_MODELS[model]
    for name in ("k", "k1"):
        if name in names:
            return names.index(name)
    return None


def _residuals(
    params: np.ndarray,
    view: _View,
    corner_rel: np.ndarray,
    ends: np.ndarray,
    free: tuple[bool, bool, bool],
    tilt_axes: np.ndarray,
    prior_px: np.ndarray,
    lens: _Lens | None = None,
) -> np.ndarray:
    """Distances (px) of both endpoints of each segment to its corner's
    vertical, then the prior terms of the free focal / tilt / k1 (1 px per
    sigma).

    ``params`` = (alpha, c_x, c_y[, log focal][, tilt_1, tilt_2][, dk1]) as
    ``free`` (focal, vertical, distortion) says; ``prior_px`` (3,) = 1 / sigma
    of (log focal, tilt_1, tilt_2). With a ``lens``, ``ends`` are RAW pixels,
    undistorted here with the candidate focal length and k1 (the distortion
    depends on both); without, undistorted pixels of the view's ``K``.
    """
    alpha, cx, cy = params[:3]
    v = view
    extra = []
    k = 3
    log_f = 0.0
    if free[0]:
        log_f = params[k]
        extra.append(log_f * prior_px[0])
        k += 1
    tilt = None
    if free[1]:
        tilt = params[k : k + 2]
        extra += list(tilt * prior_px[1:])
        k += 2
    dk = 0.0
    if free[2]:
        dk = params[k]
        k0 = lens.camera.params[lens.k_index]
        extra.append((k0 + dk - lens.k_prior) / lens.k_sigma)
    if free[0] or free[1]:
        v = _perturbed_view(view, log_f, tilt, tilt_axes)
    if lens is not None:
        ends = lens.undistorted(ends, log_f, dk)
    lines = v.corner_lines(np.array([alpha]), np.array([[cx, cy]]), corner_rel)[0]
    r = np.sum(ends * lines[:, None, :2], axis=2) + lines[:, None, 2]  # (K, 2)
    return np.r_[r.ravel(), extra]


def _refine(
    view: _View,
    corner_rel: np.ndarray,
    ends: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    free: tuple[bool, bool, bool],
    options: RegistrationOptions,
    lens: _Lens | None = None,
) -> tuple[_View, Camera | None, float, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over (alpha, c_x, c_y[, focal][, two tilts][, k1])
    with a Huber loss.

    ``free`` = (focal, vertical, distortion): which of the extra parameters
    move. The focal length is observable from one image through the spread
    of the pencil of projected verticals (a 1-D homography from the azimuths
    of the corners around the camera); the vertical through the directions
    of the segments and the positions of corners at different distances; the
    radial distortion through the cubic growth of the lateral offsets towards
    the image borders (pose and focal move the verticals affinely). All get
    a weak prior (``prior_focal_sigma``, ``vertical_sigma_deg``,
    ``distortion_sigma_px``) so that a few inliers cannot drag them far.

    ``lens``: the current camera when it has (or refines) distortion; then
    ``ends`` are the segments' RAW endpoints (K, 2, 2), else undistorted
    pixels of ``view.K``.

    Returns the (possibly re-focused and re-tilted) view, the camera with the
    refined focal and k1 (None without a ``lens``), alpha, c_xy and the final
    residuals (K, 2) in px.
    """
    from scipy.optimize import least_squares

    free = (free[0], free[1], free[2] and lens is not None and lens.k_index is not None)
    tilt_axes = _tilt_basis(view.n)
    n_extra = int(free[0]) + 2 * int(free[1]) + int(free[2])
    x0 = np.r_[alpha, c_xy, np.zeros(n_extra)]

    depth = max(1.0, float(np.median(np.linalg.norm(corner_rel - c_xy, axis=1))))
    x_scale = np.r_[1.0 / view.focal, np.full(2, depth / view.focal)]
    x_scale = np.r_[x_scale, np.full(n_extra - int(free[2]), 1.0 / view.focal)]
    if free[2]:
        # k1 moving the image corners by one pixel.
        x_scale = np.r_[x_scale, 1.0 / _corner_px_per_k(lens.camera)]
    prior_px = np.array(
        [
            1.0 / max(options.prior_focal_sigma, options.focal_sigma_min),
            1.0 / math.radians(options.vertical_sigma_deg),
            1.0 / math.radians(options.vertical_sigma_deg),
        ]
    )
    sol = least_squares(
        _residuals,
        x0,
        args=(view, corner_rel, ends, free, tilt_axes, prior_px, lens),
        loss="huber",
        f_scale=options.inlier_threshold_px,
        x_scale=x_scale,
        max_nfev=options.refine_max_iterations * (len(x0) + 1),
        method="trf",
    )
    x = sol.x
    log_f = x[3] if free[0] else 0.0
    if free[0] or free[1]:
        tilt = x[3 + int(free[0]) : 5 + int(free[0])] if free[1] else None
        view = _perturbed_view(view, log_f, tilt, tilt_axes)
    camera = None
    if lens is not None:
        camera = lens.camera_at(log_f, x[-1] if free[2] else 0.0)
        lens = _Lens(camera, None)
    r = _residuals(
        x[:3], view, corner_rel, ends, (False,) * 3, tilt_axes, prior_px, lens
    )
    return view, camera, float(x[0]), x[1:3].copy(), r.reshape(-1, 2)


@dataclass
class _Fit:
    """Step 5's outcome: the refined view, segments (undistorted with the
    refined lens), lens, pose (alpha, c_xy), relative height plane (3,), the
    inlier pairs (ci into corner_rel, sj into segs, both (K,)), their
    residuals (K, 2) px, and whether the distortion moved."""

    view: _View
    segs: _Segments
    lens: _Lens | None
    alpha: float
    c_xy: np.ndarray
    plane: np.ndarray
    ci: np.ndarray
    sj: np.ndarray
    resid: np.ndarray
    distortion_refined: bool


def _lens_of(
    camera: Camera, k_index: int | None, options: RegistrationOptions
) -> _Lens | None:
    """The current camera when its distortion matters (has or refines one):
    the residuals then come from the raw segments, undistorted with it."""
    if not (camera.has_distortion or k_index is not None):
        return None
    k_prior = float(camera.params[k_index]) if k_index is not None else 0.0
    k_sigma = options.distortion_sigma_px / _corner_px_per_k(camera)
    return _Lens(camera, k_index, k_prior, k_sigma)


def _refine_rounds(
    view: _View,
    segs: _Segments,
    raw: np.ndarray,
    corner_rel: np.ndarray,
    vis: np.ndarray,
    cand: _Candidates,
    alpha: float,
    c_xy: np.ndarray,
    plane: np.ndarray,
    lens: _Lens | None,
    moving: tuple[bool, bool, bool],
    depth_m: float,
    cadastre,
    options: RegistrationOptions,
) -> _Fit:
    """Step 5: the inliers of a pose, refined and re-scored
    (``options.refine_rounds``), then the pose alone on the final inliers.

    ``raw``: the segments' raw pixels (N, 2, 2) (for a ``lens``); ``vis``:
    the cadastre's indices of ``corner_rel``; ``cand``: the candidate pairs
    of the starting pose; ``moving``: (focal, vertical, distortion) may move
    (each from ``options.min_inliers_intrinsics`` inliers on); ``options`` at
    the image's scale.
    """
    ci, sj = _inlier_assignment(
        view, segs, corner_rel, cand, alpha, c_xy, plane, options
    )
    resid = np.zeros((0, 2))
    k_index = lens.k_index if lens is not None else None
    distortion_refined = False

    def refine(free):
        if lens is None:
            v, _, a, c, r = _refine(
                view, corner_rel[ci], segs.ends[sj], alpha, c_xy, free, options
            )
            return v, None, a, c, r
        ends = raw[segs.index[sj]]
        return _refine(view, corner_rel[ci], ends, alpha, c_xy, free, options, lens)

    for _ in range(options.refine_rounds):
        if len(ci) < options.min_inliers:
            break
        # The focal, the vertical and the distortion move only with enough
        # inliers.
        enough = len(ci) >= options.min_inliers_intrinsics
        free = (
            moving[0] and enough,
            moving[1] and enough,
            moving[2] and k_index is not None and enough,
        )
        distortion_refined |= free[2]
        new_view, new_cam, alpha, c_xy, resid = refine(free)
        # Whole buildings that do not fit (a building shifted in the map).
        bld = cadastre.corner_building[vis[ci]]
        res_pair = np.sqrt(np.mean(resid**2, axis=1))
        bad = np.zeros(len(ci), bool)
        for b in np.unique(bld):
            sel = bld == b
            if (
                np.median(res_pair[sel])
                > options.building_outlier_factor * options.inlier_threshold_px
            ):
                bad |= sel
        if bad.any() and (~bad).sum() >= options.min_inliers:
            ci, sj = ci[~bad], sj[~bad]
            new_view, new_cam, alpha, c_xy, resid = refine(free)
        view = new_view
        if lens is not None:
            # The segments again, undistorted with the refined camera.
            lens = dataclasses.replace(lens, camera=new_cam)
            und = new_cam.undistort_pixels(raw.reshape(-1, 2)).reshape(raw.shape)
            segs = _prepare_segments(und, view, options, index=segs.index)
        plane = _final_plane(view, segs, corner_rel, ci, sj, alpha, c_xy, options)
        # Re-score every pair near the refined pose.
        ground = _plane_at(plane[None], corner_rel)[0]
        cand = _candidates(
            view,
            segs,
            corner_rel,
            alpha,
            c_xy,
            ground,
            4.0 * options.inlier_threshold_px,
            options.along_segment_stretch
            * options.inlier_threshold_px
            * depth_m
            / view.focal
            * 2.0
            + 2.0,
        )
        ci, sj = _inlier_assignment(
            view, segs, corner_rel, cand, alpha, c_xy, plane, options
        )
    if len(ci) >= options.min_inliers:
        _, _, alpha, c_xy, resid = refine((False, False, False))
        plane = _final_plane(view, segs, corner_rel, ci, sj, alpha, c_xy, options)
    return _Fit(view, segs, lens, alpha, c_xy, plane, ci, sj, resid, distortion_refined)


def _corner_px_per_k(camera: Camera) -> float:
    """Displacement (px) at the image corners per unit of radial ``k1``."""
    f = float(np.mean(np.diag(camera.K)[:2]))
    r = 0.5 * math.hypot(camera.width, camera.height) / f  # normalised radius
    return f * r**3


def _final_plane(
    view: _View,
    segs: _Segments,
    corner_rel: np.ndarray,
    ci: np.ndarray,
    sj: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    options: RegistrationOptions,
) -> np.ndarray:
    """Height plane through the inliers' bottom heights (relative coordinates)."""
    ridge = (options.height_sigma_m / options.slope_sigma) ** 2
    h = view.bottom_heights(
        np.array([alpha]), c_xy[None], corner_rel[ci], segs.bottom[sj]
    )  # (1, K)
    plane = _fit_planes(corner_rel[ci][None], h, None, ridge)
    for _ in range(2):  # Huber-like reweighting against occluded bottoms
        res = h - _plane_at(plane, corner_rel[ci][None])
        s = 2.0 * options.height_sigma_m
        w = np.where(np.abs(res) <= s, 1.0, s / np.maximum(np.abs(res), 1e-9))
        plane = _fit_planes(corner_rel[ci][None], h, w, ridge)
    return plane[0]


# --------------------------------------------------------------------------
# The stage
# --------------------------------------------------------------------------


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


def _vp_in_frame(camera: Camera, n: np.ndarray) -> np.ndarray | None:
    """The (2,) pixel of the vertical VP of direction ``n`` (camera frame,
    down the world) when it lies inside the image (pinhole part), else None."""
    v = camera.K @ n
    if v[2] <= 0:  # the nadir is behind the camera
        return None
    x, y = v[:2] / v[2]
    inside = 0.0 <= x <= camera.width and 0.0 <= y <= camera.height
    return np.array([x, y]) if inside else None


def register_image(
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions | None = None,
    *,
    segments_undistorted: bool = False,
) -> RegistrationResult:
    """Register one image to the map from its vertical segments (stage 2).

    A pure function of its inputs (safe in a process pool); deterministic for
    ``options.seed``.

    Parameters
    ----------
    segments_px : (N, 2, 2) float array
        Vertical segments (endpoint k = (x, y) of segment i), COLMAP pixels
        as detected, i.e. DISTORTED (undistorted here with the camera) unless
        ``segments_undistorted``.
    vertical_direction_cam : (3,) array or None
        Unit vertical direction in the camera frame, pointing down the world,
        from the vanishing stage; None when its detection failed: the prior
        rotation's vertical is used and refined with the pose.
    camera : Camera
        Rough intrinsics (COLMAP model).
    prior : Pose
        Rough ``cam_from_world`` in the cadastre's LOCAL frame; its height is in
        an unknown vertical datum.
    cadastre : obliq_colmap.cadastre.Cadastre
    options : RegistrationOptions or None for the defaults.
    segments_undistorted : bool
        The segments are already in pixels of the pinhole part ``K`` (the
        vanishing stage's second-pass segments are).

    Returns
    -------
    RegistrationResult
        ``success`` False with a message on failure (nothing is raised for a
        failed registration).

    Raises
    ------
    ValueError
        Malformed inputs (shapes, non-finite vertical direction).
    """
    options = options or RegistrationOptions()
    args = (segments_px, vertical_direction_cam, camera, prior, cadastre, options)
    result = _search(*args, segments_undistorted)
    return chance_test(result, *args, segments_undistorted=segments_undistorted)


def chance_test(
    result: RegistrationResult,
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions,
    *,
    segments_undistorted: bool = False,
) -> RegistrationResult:
    """``result`` (of :func:`register_image` on these arguments, with or
    without the test) refused as a failure when its inlier count is no more
    than ``options.chance_factor`` x what chance gives (:func:`chance_counts`);
    results with ``options.chance_test_below`` inliers or more pass untested.
    """
    if (
        options.chance_trials == 0
        or not result.success
        or result.num_inliers >= options.chance_test_below
        or result.chance_inliers >= 0
    ):
        return result
    t0 = time.perf_counter()
    args = (segments_px, vertical_direction_cam, camera, prior, cadastre, options)
    chance = max(chance_counts(*args, segments_undistorted))
    timings = dict(result.timings)
    timings["chance"] = time.perf_counter() - t0
    timings["total"] = timings.get("total", 0.0) + timings["chance"]
    result = dataclasses.replace(result, chance_inliers=chance, timings=timings)
    if result.num_inliers > options.chance_factor * chance:
        return result
    return dataclasses.replace(
        result,
        success=False,
        cam_from_world=prior,
        camera=None,
        message=(
            f"no consensus: {result.num_inliers} inlier corners is no more than "
            f"chance (the same search with the segments mirrored finds up to "
            f"{chance}; need more than {options.chance_factor:g} x that)"
        ),
    )


def _mirrored(segments: np.ndarray, vp: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(N, 2, 2) segments reflected about the image line through the vertical
    VP ``vp`` (3,) (homogeneous, may lie at infinity) and the pixel ``point``
    (2,): lines through the VP stay lines through it."""
    u = vp[:2] - point * vp[2]
    u = u / np.linalg.norm(u)
    reflect = 2.0 * np.outer(u, u) - np.eye(2)
    return (segments - point) @ reflect.T + point


def chance_counts(
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions,
    segments_undistorted: bool = False,
) -> list[int]:
    """Inlier corners the same search finds with the segments mirrored (one
    count per mirror, ``options.chance_trials`` of them): what chance alone
    gives this image's segments against this map.

    The mirror axes pass through the vertical VP and points on the image's
    middle row spread by an eighth of the width around the principal point.
    A mirror about the axis through the principal point is the image of the
    map mirrored about the camera's vertical plane: the same corners at the
    same distances in view, the same segments, but no relation between them.
    Arguments as :func:`register_image`. Each mirror is one more search.
    """
    seg = np.asarray(segments_px, float).reshape(-1, 2, 2)
    if camera.has_distortion and not segments_undistorted and len(seg):
        seg = camera.undistort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
    n = vertical_direction_cam
    down = n if n is not None else prior.rotation @ -_EZ
    vp = camera.K @ np.asarray(down, float)
    null = replace(options, min_inliers=3, chance_trials=0)
    m = options.chance_trials
    counts = []
    for k in range(m):
        shift = (k - (m - 1) / 2.0) * camera.width / 8.0
        point = np.array([camera.K[0, 2] + shift, camera.K[1, 2]])
        r = _search(_mirrored(seg, vp, point), n, camera, prior, cadastre, null, True)
        counts.append(r.num_inliers)
    return counts


def _search(
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions,
    segments_undistorted: bool,
) -> RegistrationResult:
    """:func:`register_image` without the chance test."""
    from obliq_colmap.cadastre import visible_corners

    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    seg, n = _check_inputs(segments_px, vertical_direction_cam)
    vertical_source = "detected"
    down_prior = prior.rotation @ -_EZ
    if n is None:
        n = down_prior
        vertical_source = "prior"
    elif n @ down_prior < 0:
        n = -n  # orient down the world
    refine_vertical = options.refine_vertical == "always" or (
        options.refine_vertical == "auto" and vertical_source == "prior"
    )
    refine_focal = bool(options.refine_focal)
    view = _make_view(camera, prior, n)

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

    if not options.allow_vp_in_frame and (vp := _vp_in_frame(camera, n)) is not None:
        return fail(
            f"near-nadir view: the vertical vanishing point ({vp[0]:.0f}, "
            f"{vp[1]:.0f}) px lies inside the {camera.width} x {camera.height} "
            "frame; registration to the map's corners needs an oblique view"
        )

    # 1. Segments.
    t0 = time.perf_counter()
    # RAW (as detected) endpoints are kept for a refinement of the distortion.
    raw = seg
    if len(seg) and camera.has_distortion:
        if segments_undistorted:
            raw = camera.distort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
        else:
            seg = camera.undistort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
    segs = _prepare_segments(seg, view, options)
    timings["segments"] = time.perf_counter() - t0
    if len(segs) < options.min_segments:
        return fail(
            f"too few vertical segments: {len(segs)} usable of {len(seg)} "
            f"(need {options.min_segments})",
            num_segments=len(segs),
        )

    # 2. Ground height and coarse pose: 4-D Hough vote over (alpha, c, h).
    t0 = time.perf_counter()
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
        return fail(
            f"too few map corners in view of the prior: {len(wide)}",
            num_segments=len(segs),
        )
    corner_rel = cadastre.corner_xy[wide] - view.c0[:2]
    # Viewing distance for the search windows (the horizontal distance to the
    # map corners; refined from the ground height below).
    depth_m = _median_depth(view, corner_rel)
    alpha_half, c_half, radius = _search_windows(view, options, depth_m)
    ii, jj = _pairs_near(
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
        return fail(
            f"no consensus: {len(ii)} candidate pairs near the prior",
            num_segments=len(segs),
        )
    coarse = _hough(
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
    starts = coarse.peaks_by_height(options.num_candidates_verified, separation[3])
    timings["ground"] = time.perf_counter() - t0

    # 3.-4. The strongest peaks: fine pose vote, then a short RANSAC; the one
    # with the most inlier corners wins and gets the full RANSAC.
    t0 = time.perf_counter()
    tries = []
    for start in starts:
        h_k = (
            start.height
            if options.ground_height is None
            else float(options.ground_height)
        )
        tries.append(
            _try_start(
                view,
                segs,
                cadastre,
                camera,
                start,
                h_k,
                coarse,
                radius,
                alpha_half,
                c_half,
                options,
                np.random.default_rng(options.seed),
            )
        )
    timings["coarse"] = time.perf_counter() - t0
    for st, tr in zip(starts, tries, strict=True):
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
    best_try = _finish_try(view, segs, best_try, options)
    timings["ransac"] = time.perf_counter() - t0
    h0, vis, corner_rel, depth_m, cand = (
        best_try.h0,
        best_try.vis,
        best_try.corner_rel,
        best_try.depth_m,
        best_try.cand,
    )
    options = _at_image_scale(options, view.focal, depth_m)
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
    k_index = _radial_index(camera.model) if options.refine_distortion else None
    fit = _refine_rounds(
        view,
        segs,
        raw,
        corner_rel,
        vis,
        cand,
        alpha_r,
        c_r,
        plane_r,
        _lens_of(camera, k_index, options),
        (refine_focal, refine_vertical, k_index is not None),
        depth_m,
        cadastre,
        options,
    )
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
        vertical_source="refined" if refine_vertical else vertical_source,
        inlier_pairs=np.column_stack([vis[ci], segs.index[sj]]).astype(int),
        inlier_segments_px=seg[segs.index[sj]].copy(),
        height_plane=plane_abs,
        residual_rms_px=rms,
        message=f"{len(ci)} inlier corners of {num_candidates} candidates, "
        f"RMS {rms:.2f} px, {trials} trials",
        timings=timings,
        **common,
    )


@dataclass
class _Try:
    """One candidate ground height carried through steps 3 and 4."""

    start: _HoughPeak
    grid: _HoughGrid
    h0: float
    vis: np.ndarray
    corner_rel: np.ndarray
    depth_m: float
    cand: _Candidates
    alpha: float
    c_xy: np.ndarray
    plane: np.ndarray
    count: int
    cost: float
    trials: int
    #: The RANSAC's search centre (alpha, c_xy) and half-widths, and where it
    #: stopped (to resume it).
    center: tuple[float, np.ndarray]
    windows: tuple[float, float]
    state: _RansacState


def _try_start(
    view: _View,
    segs: _Segments,
    cadastre,
    camera: Camera,
    start: _HoughPeak,
    h0: float,
    coarse: _HoughGrid,
    radius: float,
    alpha_half: float,
    c_half: float,
    options: RegistrationOptions,
    rng: np.random.Generator,
) -> _Try | None:
    """Steps 3 and 4 from one coarse peak, with the short RANSAC
    (``options.verify_trials``; :func:`_finish_try` resumes it); None when
    nothing matches."""
    from obliq_colmap.cadastre import visible_corners

    vis = visible_corners(
        cadastre,
        camera,
        view.pose(start.alpha, start.c_xy),
        ground_height=h0,
        height_range_m=options.height_range_m,
        margin_px=radius,
    )
    if len(vis) < 3:
        return None
    corner_rel = cadastre.corner_xy[vis] - view.c0[:2]
    _, depth0 = view.project(
        np.array([start.alpha]), start.c_xy[None], corner_rel, np.full(len(vis), h0)
    )
    front = depth0[0][depth0[0] > 0]
    if len(front) < 3:
        return None
    depth_m = float(np.median(front))
    options = _at_image_scale(options, view.focal, depth_m)
    # 3. Fine pose vote within two coarse cells, pairs near the ground height.
    band_px = (
        2.0 * coarse.d_c * view.focal / depth_m + 2.0 * coarse.d_alpha * view.focal
    )
    ii, jj = _pairs_near(
        view,
        segs,
        corner_rel,
        start.alpha,
        start.c_xy,
        band_px,
        ground=h0,
        height_tol_m=options.candidate_height_tolerance_m + 2.0 * coarse.d_c,
    )
    if len(ii) < 3:
        return None
    fine = _hough(
        view,
        segs,
        corner_rel,
        ii,
        jj,
        start.alpha,
        1.5 * coarse.d_alpha,
        start.c_xy,
        1.5 * coarse.d_c,
        (options.hough_cell_px,) * 3,
        depth_m,
        # The window is 3 coarse cells wide; at a spurious ground height
        # near the camera the viewing distance, hence the cell in metres,
        # is tiny and the window would need 10^5-10^6 cells: cap it (the
        # cells grow instead; a wrong height fails the RANSAC anyway).
        min(options.hough_max_cells, _FINE_MAX_CELLS),
    ).peak()
    # 4. RANSAC in a small radius around it.
    cand = _candidates(
        view,
        segs,
        corner_rel,
        fine.alpha,
        fine.c_xy,
        h0,
        options.ransac_radius_px,
        options.candidate_height_tolerance_m,
    )
    if len(cand.corner) < 3:
        return None
    windows = (
        alpha_half + 4.0 * options.ransac_radius_px / view.focal,
        c_half + 4.0 * options.ransac_radius_px * depth_m / view.focal,
    )
    state = _RansacState(rng)
    alpha, c_xy, plane, count, cost, trials = _ransac(
        view,
        segs,
        corner_rel,
        cand,
        fine.alpha,
        fine.c_xy,
        *windows,
        options,
        state,
        max_trials=options.verify_trials,
    )
    return _Try(
        start,
        coarse,
        h0,
        vis,
        corner_rel,
        depth_m,
        cand,
        alpha,
        c_xy,
        plane,
        count,
        cost,
        trials,
        (fine.alpha, fine.c_xy),
        windows,
        state,
    )


def _finish_try(
    view: _View, segs: _Segments, t: _Try, options: RegistrationOptions
) -> _Try:
    """The full RANSAC of a verified try: its short run resumed, which draws
    and scores the samples a fresh full run with the same seed would (the
    steps before it are deterministic, so they are not recomputed)."""
    options = _at_image_scale(options, view.focal, t.depth_m)
    alpha, c_xy, plane, count, cost, trials = _ransac(
        view, segs, t.corner_rel, t.cand, *t.center, *t.windows, options, t.state
    )
    return replace(
        t, alpha=alpha, c_xy=c_xy, plane=plane, count=count, cost=cost, trials=trials
    )


def block_ground_height(
    results: list[RegistrationResult], min_inliers: int = 20
) -> float | None:
    """The ground height of a block from its confident registrations.

    All priors of a block share one vertical datum, so the ground heights found
    per image agree up to the terrain and the prior height noise. A second
    pass of :func:`register_image` with ``options.ground_height`` set to this
    value rescues images whose own ground-height search failed (their
    results have few inliers).

    Parameters
    ----------
    results : registrations of the images of one block (local frame).
    min_inliers : only results with at least this many inlier corners count.

    Returns
    -------
    float, the median ground height (m), or None when no result qualifies.
    """
    heights = [
        r.ground_height
        for r in results
        if r.success and r.num_inliers >= min_inliers and math.isfinite(r.ground_height)
    ]
    return float(np.median(heights)) if heights else None


def _median_depth(view: _View, corner_rel: np.ndarray) -> float:
    """A viewing-distance scale before the ground height is known (m).

    The lower quartile of the horizontal distances to the corners that may be
    in view at some ground height: the far corners of that set belong to
    heights far below the true ground, so the median would overestimate.
    """
    d = np.linalg.norm(corner_rel, axis=1)
    return float(np.percentile(d, 25)) if len(d) else 100.0


# --------------------------------------------------------------------------
# One focal length for the images of one lens
# --------------------------------------------------------------------------


@dataclass
class _Inliers:
    """One registered image's inlier pairs as a refinement problem.

    ``view`` is at the result's pose (alpha 0, c_xy 0); ``corner_rel`` (K, 2)
    the inlier corners relative to its centre; ``ends`` (K, 2, 2) their
    segments, RAW pixels with a ``lens``, else undistorted pixels of
    ``view.K``; ``options`` at the image's scale (inlier threshold).
    """

    view: _View
    corner_rel: np.ndarray
    ends: np.ndarray
    lens: _Lens | None
    options: RegistrationOptions


def _inlier_problem(
    result: RegistrationResult,
    camera: Camera,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> _Inliers:
    """The inliers of a successful ``result`` seen through ``camera``.

    ``segments_camera``: the camera in whose undistorted pixels the result's
    ``inlier_segments_px`` are. Another focal length than the result's keeps
    the vanishing point's pixel (the detected quantity) and turns the pose
    about the camera centre by the smallest rotation that follows it.
    """
    pose = result.cam_from_world
    n_old = -pose.rotation[:, 2]  # the world's down in the camera frame
    vp = result.camera.K @ n_old
    n = np.linalg.solve(camera.K, vp)
    n = n / np.linalg.norm(n)
    R0 = rotation_aligning(n_old, n) @ pose.rotation
    view = _View(K=camera.K, Kinv=np.linalg.inv(camera.K), R0=R0, n=n, c0=pose.center)
    corner_xy = cadastre.corner_xy[result.inlier_pairs[:, 0]]
    corner_rel = corner_xy - view.c0[:2]
    ends = np.asarray(result.inlier_segments_px, float)
    if segments_camera.has_distortion:
        ends = segments_camera.distort_pixels(ends.reshape(-1, 2)).reshape(ends.shape)
    lens = _Lens(camera, None) if camera.has_distortion else None
    plane = result.height_plane
    z = corner_xy @ plane[:2] + plane[2]
    _, depth = view.project(np.zeros(1), np.zeros((1, 2)), corner_rel, z)
    depth = depth[0][depth[0] > 0]
    depth_m = float(np.median(depth)) if len(depth) else 100.0
    return _Inliers(
        view, corner_rel, ends, lens, _at_image_scale(options, view.focal, depth_m)
    )


def _solve_inliers(
    p: _Inliers, free_focal: bool, focal_sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Huber least squares over (alpha, c_x, c_y[, log focal], two tilts) of
    one image's inliers, the vertical under its weak prior.

    Returns the solution x, the residuals' Jacobian at it (robust-weighted,
    rows: 2 per inlier, then the priors of the free focal and the tilts) and
    the axes of the tilts (2, 3).
    """
    from scipy.optimize import least_squares

    view, o = p.view, p.options
    tilt_axes = _tilt_basis(view.n)
    free = (free_focal, True, False)
    x0 = np.zeros(5 + int(free_focal))
    depth = max(1.0, float(np.median(np.linalg.norm(p.corner_rel, axis=1))))
    x_scale = np.r_[1.0, depth, depth, np.ones(2 + int(free_focal))] / view.focal
    prior_px = np.array(
        [1.0 / focal_sigma, *(2 * [1.0 / math.radians(o.vertical_sigma_deg)])]
    )
    sol = least_squares(
        _residuals,
        x0,
        args=(view, p.corner_rel, p.ends, free, tilt_axes, prior_px, p.lens),
        loss="huber",
        f_scale=o.inlier_threshold_px,
        x_scale=x_scale,
        max_nfev=o.refine_max_iterations * (len(x0) + 1),
        method="trf",
        ftol=1e-4,
        xtol=1e-4,
    )
    return sol.x, sol.jac, tilt_axes


def _reassociate(
    result: RegistrationResult,
    camera: Camera,
    segments_px: np.ndarray,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> tuple[RegistrationResult, float]:
    """:func:`refine_with_camera` and the consensus of its result: the sum
    over the inlier corners of ``1 - (rms residual / threshold)^2`` (a soft
    inlier count, 0 on failure)."""
    from obliq_colmap.cadastre import visible_corners

    # The pose that the old inliers give with the new camera ...
    p = _inlier_problem(result, camera, segments_camera, cadastre, options)
    x, _, tilt_axes = _solve_inliers(p, False, 1.0)
    v = _perturbed_view(p.view, 0.0, x[3:5], tilt_axes)
    ends = p.ends
    if p.lens is not None:
        ends = camera.undistort_pixels(ends.reshape(-1, 2)).reshape(ends.shape)
    k = np.arange(len(ends))
    inl = _prepare_segments(ends, v, p.options, index=k)
    # The ground moves with the pose (the camera height is held).
    plane = _final_plane(v, inl, p.corner_rel, k, k, float(x[0]), x[1:3], p.options)
    plane = np.r_[plane[:2], plane[2] + plane[:2] @ x[1:3]]  # relative to c0
    c0 = np.r_[v.c0[:2] + x[1:3], v.c0[2]]
    view = _View(K=v.K, Kinv=v.Kinv, R0=v.rotation(float(x[0])), n=v.n, c0=c0)
    # ... then every pair near it scored again (step 5 of the registration).
    seg = np.asarray(segments_px, float).reshape(-1, 2, 2)
    raw = seg
    if segments_camera.has_distortion:
        raw = segments_camera.distort_pixels(seg.reshape(-1, 2)).reshape(seg.shape)
    und = raw
    if camera.has_distortion:
        und = camera.undistort_pixels(raw.reshape(-1, 2)).reshape(raw.shape)
    segs = _prepare_segments(und, view, options)
    vis = visible_corners(
        cadastre,
        camera,
        view.pose(0.0, np.zeros(2)),
        ground_height=float(plane[2]),
        height_range_m=options.height_range_m,
        margin_px=options.ransac_radius_px,
    )
    corner_rel = cadastre.corner_xy[vis] - c0[:2]
    ground = _plane_at(plane[None], corner_rel)[0]
    _, depth = view.project(np.zeros(1), np.zeros((1, 2)), corner_rel, ground)
    depth = depth[0][depth[0] > 0]
    failed = dataclasses.replace(
        result, success=False, message="no consensus with the head's camera"
    )
    if len(segs) < options.min_segments or len(depth) < options.min_inliers:
        return failed, 0.0
    depth_m = float(np.median(depth))
    o = _at_image_scale(options, view.focal, depth_m)
    cand = _candidates(
        view,
        segs,
        corner_rel,
        0.0,
        np.zeros(2),
        ground,
        4.0 * o.inlier_threshold_px,
        o.along_segment_stretch * o.inlier_threshold_px * depth_m / view.focal * 2.0
        + 2.0,
    )
    fit = _refine_rounds(
        view,
        segs,
        raw,
        corner_rel,
        vis,
        cand,
        0.0,
        np.zeros(2),
        plane,
        _lens_of(camera, None, o),
        (False, True, False),
        depth_m,
        cadastre,
        o,
    )
    ci, sj = fit.ci, fit.sj
    if len(ci) < options.min_inliers:
        return failed, 0.0
    r2 = np.mean(fit.resid**2, axis=1)
    score = float(np.sum(np.maximum(0.0, 1.0 - r2 / o.inlier_threshold_px**2)))
    rms = float(np.sqrt(np.mean(fit.resid**2)))
    plane = fit.plane
    centroid = corner_rel[ci].mean(axis=0)
    new = dataclasses.replace(
        result,
        cam_from_world=fit.view.pose(fit.alpha, fit.c_xy),
        vertical_direction=fit.view.n.copy(),
        vertical_source="refined",
        camera=camera,
        inlier_pairs=np.column_stack([vis[ci], segs.index[sj]]).astype(int),
        inlier_segments_px=seg[segs.index[sj]].copy(),
        height_plane=np.r_[plane[:2], plane[2] - plane[:2] @ c0[:2]],
        ground_height=float(plane[:2] @ centroid + plane[2]),
        num_inliers=len(ci),
        residual_rms_px=rms,
        message=f"{len(ci)} inlier corners with its head's camera, RMS {rms:.2f} px",
    )
    return new, score


def refine_with_camera(
    result: RegistrationResult,
    camera: Camera,
    segments_px: np.ndarray,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> RegistrationResult:
    """A successful ``result`` refined again with the intrinsics held at
    ``camera`` (its head's): its inliers give the pose with the new camera,
    then the pairs near that pose are scored again and refined as the
    registration's last step does (the pose and the vertical move). A
    focal error biases the inliers themselves: the pairs that fit it are
    kept, those it pushes out are not, so refining the old inliers alone
    leaves most of the error (measured on ``paper``).

    ``segments_px``: the image's (N, 2, 2) vertical segments, undistorted
    pixels of ``segments_camera`` (the frame of the result's
    ``inlier_segments_px``, which the new result keeps). ``success`` False
    when fewer than ``options.min_inliers`` pairs remain.
    """
    return _reassociate(
        result, camera, segments_px, segments_camera, cadastre, options
    )[0]


def focal_profile(
    result: RegistrationResult,
    camera: Camera,
    scales: np.ndarray,
    segments_px: np.ndarray,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> np.ndarray:
    """(G,) consensus of one registered image (:func:`_reassociate`'s soft
    inlier count) with ``camera``'s focal length scaled by each of (G,)
    ``scales`` and held; the images of one lens sum theirs."""
    return np.array(
        [
            _reassociate(
                result,
                camera.with_focal_scaled(float(k)),
                segments_px,
                segments_camera,
                cadastre,
                options,
            )[1]
            for k in scales
        ]
    )


def _parabola_peak(x: np.ndarray, y: np.ndarray) -> float:
    """Abscissa of the vertex of the parabola through three equally spaced
    (x, y) (3,), within [x[0], x[2]]; x[1] when it is not concave."""
    h = x[1] - x[0]
    curv = y[0] - 2.0 * y[1] + y[2]
    if not curv < 0:
        return float(x[1])
    return float(np.clip(x[1] + 0.5 * h * (y[0] - y[2]) / curv, x[0], x[2]))


def consensus_peak(
    profile: Callable[[np.ndarray], np.ndarray], sigma: float, max_steps: int = 2
) -> float:
    """The log focal scale where a summed consensus profile peaks.

    ``profile`` maps (G,) log scales to (G,) scores (the sum of the images'
    :func:`focal_profile`). A grid of ``sigma`` (the priors' relative focal
    error) over +-2 sigma, one step further where the best is at an end (at
    most ``max_steps`` times), the parabola through the best and its
    neighbours, then the same on a grid of sigma / 3 around that: 8
    evaluations unless extended. The profile of one head is smooth and
    unimodal over several sigma (``paper``: its soft inlier count falls by
    ~10 % 2 % off the peak and ~40 % 4 % off).
    """
    grid = sigma * np.arange(-2.0, 2.5)
    score = profile(grid)
    for _ in range(max_steps):
        best = int(np.argmax(score))
        if 0 < best < len(grid) - 1:
            break
        x = grid[:1] - sigma if best == 0 else grid[-1:] + sigma
        grid, score = np.r_[grid, x], np.r_[score, profile(x)]
        order = np.argsort(grid)
        grid, score = grid[order], score[order]
    i = int(np.clip(np.argmax(score), 1, len(grid) - 2))
    fine = _parabola_peak(grid[i - 1 : i + 2], score[i - 1 : i + 2])
    fine = fine + sigma / 3.0 * np.array([-1.0, 0.0, 1.0])
    return _parabola_peak(fine, profile(fine))


# --------------------------------------------------------------------------
# Overlay
# --------------------------------------------------------------------------

#: BGR colours of the overlay: map before (prior), map after, inlier segments,
#: inlier corners' verticals.
OVERLAY_COLORS = {
    "before": (0, 0, 255),
    "after": (0, 255, 0),
    "segment": (0, 255, 255),
    "corner": (255, 0, 255),
}


def _project_edges(
    cadastre, camera: Camera, pose: Pose, plane_abs: np.ndarray, ground: float
) -> np.ndarray:
    """(E, 2, 2) pixels of the map edges at the ground; NaN when behind."""
    xy = cadastre.edge_xy.reshape(-1, 2)
    if np.all(np.isfinite(plane_abs)):
        z = plane_abs[0] * xy[:, 0] + plane_abs[1] * xy[:, 1] + plane_abs[2]
    else:
        z = np.full(len(xy), ground)
    X = pose.transform(np.column_stack([xy, z]))
    px = camera.img_from_cam(X)
    px[X[:, 2] <= 0] = np.nan
    return px.reshape(-1, 2, 2)


def draw_registration_overlay(
    image: np.ndarray,
    cadastre,
    camera: Camera,
    prior_pose: Pose,
    result: RegistrationResult,
) -> np.ndarray:
    """Draw the map before (prior pose, red) and after registration (green).

    The footprint edges are drawn at the ground (the result's height plane,
    else its ground height), through the camera's distortion; the inlier
    segments are drawn in yellow and their corners' verticals (from the
    ground up, 15 m) in magenta.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 array (BGR).
    cadastre : Cadastre (local frame, as registered).
    camera : Camera, the rough intrinsics used for the registration.
    prior_pose : Pose, the prior ``cam_from_world`` (local frame).
    result : RegistrationResult.

    Returns
    -------
    (H, W, 3) uint8 BGR array, a new image.
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 2:
        out = cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR)
    elif img.ndim == 3 and img.shape[2] == 3:
        out = img.astype(np.uint8).copy()
    else:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
    H, W = out.shape[:2]
    limit = 4.0 * max(H, W)

    def draw(segments: np.ndarray, color, thickness=1) -> None:
        for a, b in segments:
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                continue
            if np.any(np.abs(np.r_[a, b]) > limit):
                continue
            cv2.line(
                out,
                (int(round(a[0])), int(round(a[1]))),
                (int(round(b[0])), int(round(b[1]))),
                color,
                thickness,
                cv2.LINE_AA,
            )

    ground = (
        result.ground_height
        if math.isfinite(result.ground_height)
        else prior_pose.center[2] - 300.0
    )
    draw(
        _project_edges(cadastre, camera, prior_pose, np.full(3, np.nan), ground),
        OVERLAY_COLORS["before"],
    )
    if result.success:
        pose = result.cam_from_world
        draw(
            _project_edges(cadastre, camera, pose, result.height_plane, ground),
            OVERLAY_COLORS["after"],
        )
        corners = result.inlier_pairs[:, 0]
        xy = cadastre.corner_xy[corners]
        p = result.height_plane
        z = p[0] * xy[:, 0] + p[1] * xy[:, 1] + p[2]
        bottom = camera.img_from_cam(pose.transform(np.column_stack([xy, z])))
        top = camera.img_from_cam(pose.transform(np.column_stack([xy, z + 15.0])))
        draw(np.stack([bottom, top], axis=1), OVERLAY_COLORS["corner"])
        seg = result.inlier_segments_px
        if len(seg) and camera.has_distortion:
            # Back to the distorted image.
            uv = (seg.reshape(-1, 2) - camera.K[:2, 2]) / np.diag(camera.K)[:2]
            seg = camera.img_from_cam(np.column_stack([uv, np.ones(len(uv))]))
            seg = seg.reshape(-1, 2, 2)
        draw(seg, OVERLAY_COLORS["segment"], 2)
    return out
