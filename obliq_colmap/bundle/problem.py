"""Input, options and results of the bundle; the linked image components.

:class:`BundleProblem` is plain data in the local map frame (metres, pixels);
:class:`BundleOptions` configures :func:`~obliq_colmap.bundle.solve_bundle`;
:class:`BundleResult` and :class:`BundleSummary` are what it returns.
:func:`image_components` finds the groups of images linked by shared height
unknowns, each with its own vertical datum.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..geometry import Camera, Pose
from .loss import LOSSES

CORNER_HEIGHT_MODES = ("free", "fixed")
GAUGES = ("component_mean_camera_height", "none")


@dataclass(kw_only=True)
class BundleOptions:
    """Options of :func:`solve_bundle`."""

    #: Robust loss on each residual: "huber", "cauchy" or "none".
    loss: str = "huber"
    #: Scale of the robust loss, pixels (residuals below it count fully).
    loss_scale_px: float = 2.0
    #: A priori standard deviations (px) of the two residual kinds, cost weight
    #: 1 / sigma^2 (the robust loss keeps its scale in pixels): map corners carry
    #: the map's vertex noise (~1 px), facade edges only the image noise (~0.3 px).
    vertical_sigma_px: float = 1.0
    horizontal_sigma_px: float = 1.0
    #: The two vertical rows of one segment (:func:`vertical_row_pairs`) as
    #: their sum and their difference, each over sqrt 2: the sum weighted by
    #: ``vertical_sigma_px`` (the map's vertex noise moves both ends alike),
    #: the difference by this sd (px; only the segment's own direction
    #: noise). None: each row by ``vertical_sigma_px`` (equal sds: the same
    #: model). Meant for rows on each segment's own line; on lines through
    #: one vanishing point the difference is that VP again, not a new
    #: observation.
    vertical_direction_sigma_px: float | None = None
    #: Maximum number of Levenberg-Marquardt iterations (accepted or not).
    max_iterations: int = 100
    #: Stop when an accepted step lowers the cost by less than this fraction.
    function_tolerance: float = 1e-8
    #: Stop when |step| <= tol * (|x| + tol), x = centres, intrinsics, heights.
    parameter_tolerance: float = 1e-8
    #: Refine the focal length(s) of every camera.
    refine_focal_length: bool = True
    #: Refine fx and fy of two-focal models (PINHOLE, OPENCV) independently; False
    #: keeps the aspect ratio (as the paper): without map heights a vertical
    #: stretch of the scene is nearly a gauge freedom that fx != fy would absorb.
    refine_aspect_ratio: bool = False
    #: Refine the principal point of every camera.
    refine_principal_point: bool = True
    #: Refine the distortion parameters of every camera.
    refine_extra_params: bool = False
    #: "free": one unknown height per map corner, shared by its observations
    #: in all images; "fixed": corners at ``BundleProblem.corner_heights``.
    corner_heights: str = "free"
    #: Standard deviation, metres, of a weak prior pulling free corner heights
    #: towards their initial values (None: no prior). 1 px of cost per sigma.
    corner_height_prior_m: float | None = 5.0
    #: Standard deviation (deg) of each image's rotation about its prior
    #: (``BundleProblem.prior_rotations``, a calibrated INS); None: no prior. It
    #: holds the rotation, which an image's map constraints determine worst.
    rotation_prior_sigma_deg: float | None = None
    #: Standard deviation of each refined camera's principal point about the
    #: priors' (``BundleProblem.prior_principal_points``), as a fraction of
    #: the camera's larger image side; None: free. An uncalibrated camera's
    #: principal point lies within about 1 % of the image size of its centre.
    principal_point_prior_sigma: float | None = None
    #: Standard deviation (m) of each image's camera centre about its prior
    #: (``BundleProblem.prior_centers``: survey-grade GNSS with the lever arm
    #: applied, in the priors' frame and datum); None: no prior. Centres known
    #: to ~0.1 m fix the block's tilt and each centre, which the map's
    #: constraints trade against the rotation.
    position_prior_sigma_m: float | None = None
    #: With ``position_prior_sigma_m``: estimate one horizontal offset (2
    #: unknowns) of the priors' centres against the map (a GNSS frame off the
    #: cadastre's, a lever arm left out), which would otherwise bend every image
    #: along its weak direction. The priors' heights stay the vertical datum.
    estimate_prior_offset: bool = True
    #: Vertical datum: "component_mean_camera_height" (per linked component,
    #: hard constraint) or "none" (rank-deficient; damping only). With
    #: ``position_prior_sigma_m`` the observed centres hold it instead.
    gauge: str = "component_mean_camera_height"
    #: Gauss-Newton steps on the heights alone (cameras fixed) before the
    #: joint solve; 0 disables.
    height_initialisation_steps: int = 3
    #: Initial Marquardt damping factor lambda.
    initial_damping: float = 1e-4
    #: BLAS threads inside the solver (threadpoolctl); None leaves it alone.
    blas_threads: int | None = 1
    #: Compute each image's a-posteriori precision at the optimum
    #: (:attr:`BundleResult.image_precision_px`): one more linearisation and
    #: one dense inverse of the reduced camera system.
    compute_precision: bool = True
    #: The precision inverts the dense reduced camera system, O(n^3) in its n
    #: parameters (6 per image + the intrinsics): above this n it is skipped
    #: (NaN, and a log line).
    precision_max_camera_params: int = 3000
    #: The precision from a variance component per observation group (map
    #: corners, segment directions, facade rows, tie points, VPs, priors;
    #: :mod:`~obliq_colmap.bundle.components`): each group's noise as its own
    #: residuals show it, the covariance the sandwich over the groups. False:
    #: one pooled variance factor scales the cofactor matrix.
    variance_components: bool = True
    #: A group with less redundancy than this keeps its stated sd (factor 1).
    component_min_redundancy: float = 10.0
    #: Prior standard deviation (m) of the anchor offsets counted in the
    #: precision (``BundleProblem.horizontal_offset_normal``).
    horizontal_offset_sigma_m: float = 10.0
    #: Observe each image's vertical vanishing point
    #: (``BundleProblem.vertical_vps``, stage 1's VP with its covariance): 2
    #: rows per image, the angle between the world's vertical as the camera
    #: sees it and the VP's direction through the camera's current intrinsics.
    #: It holds each image's tilt, which the map's constraints leave loose
    #: along the block's weak vertical mode (tilt, height, focal).
    vp_observations: bool = True
    #: Factor on stage 1's stated standard deviation of each VP (its
    #: covariance times the square): estimated between the rounds
    #: (:func:`~obliq_colmap.adjustment.with_variance_components`), since the
    #: stated covariance can be several times too optimistic.
    vp_sigma_scale: float = 1.0
    #: Cauchy scale of the VP rows, in (scaled) standard deviations of the
    #: whitened 2-vector: a VP on a wrong pencil (degrees off) loses its pull.
    #: ``math.inf``: no robust loss (plain least squares).
    vp_loss_scale: float = 3.0
    #: The map's vertex error (m, each axis), propagated into the precision
    #: as an error every row of a corner, in every image, shares (the solve
    #: keeps the corners fixed; ``covariance.corner_offset_meat``), which
    #: independent rows would count as averaging out. None: the corners
    #: known exactly (with ``corner_heights="fixed"`` only).
    map_corner_sigma_m: float | None = None
    #: With ``vp_observations``: the VP rows enter the fit. False: they are
    #: only evaluated against the fit without them (``BundleResult.vp_loo``,
    #: ``vp_test``: their factor and tests before they get any weight).
    vp_in_fit: bool = True
    #: Each scalar facade row (``facade_lines`` False) weighted by its own
    #: segment's line fit where the row reads it: the row is the segment's
    #: line at the projection of its track's anchor, which can lie outside
    #: the segment; a line fitted to edge points spread over its length L
    #: has, at a distance s from its midpoint, the offset variance
    #: ``sigma^2 (1 + 12 s^2 / L^2)`` (least squares on uniform points).
    #: Each row's sd is ``horizontal_sigma_px`` times the square root of that
    #: factor over the factors' median (computed at each solve's start from
    #: ``BundleProblem.horizontal_ends``; rows without ends: factor 1). False:
    #: every facade row has ``horizontal_sigma_px``.
    facade_row_extrapolation: bool = False
    #: A priori standard deviation (px) of a tie point's observation
    #: (``BundleProblem.tie_xy``, each axis); cost weight 1 / sigma^2.
    tie_sigma_px: float = 1.0
    #: Scale (px) of the robust loss on each tie observation's 2D error (the
    #: loss ``loss`` on ``|r|^2``, as Ceres' loss on a 2-row block): a wrong
    #: match loses its pull.
    tie_loss_scale_px: float = 3.0
    #: Each facade track a horizontal 3D line (height, offset across its map
    #: edge, direction), each observation two rows, one per segment end
    #: (:mod:`~obliq_colmap.bundle.facade_lines`; needs
    #: ``BundleProblem.horizontal_ends`` and ``facade_direction``). False: one
    #: row per observation, the point ``(anchor, h_j)`` on the segment's line.
    facade_lines: bool = False

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("loss", self.loss, LOSSES),
            ("corner_heights", self.corner_heights, CORNER_HEIGHT_MODES),
            ("gauge", self.gauge, GAUGES),
        ):
            if value not in allowed:
                raise ValueError(
                    f"BundleOptions.{name}={value!r}; allowed: {', '.join(allowed)}"
                )
        if self.loss_scale_px <= 0:
            raise ValueError(f"loss_scale_px must be > 0, got {self.loss_scale_px}")
        if self.vertical_sigma_px <= 0 or self.horizontal_sigma_px <= 0:
            raise ValueError("vertical_sigma_px and horizontal_sigma_px must be > 0")
        if (
            self.vertical_direction_sigma_px is not None
            and not self.vertical_direction_sigma_px > 0
        ):
            raise ValueError("vertical_direction_sigma_px must be > 0 or None")
        if self.corner_height_prior_m is not None and self.corner_height_prior_m <= 0:
            raise ValueError("corner_height_prior_m must be > 0 or None")
        if (
            self.rotation_prior_sigma_deg is not None
            and not self.rotation_prior_sigma_deg > 0
        ):
            raise ValueError("rotation_prior_sigma_deg must be > 0 or None")
        if (
            self.position_prior_sigma_m is not None
            and not self.position_prior_sigma_m > 0
        ):
            raise ValueError("position_prior_sigma_m must be > 0 or None")
        if (
            self.principal_point_prior_sigma is not None
            and not self.principal_point_prior_sigma > 0
        ):
            raise ValueError("principal_point_prior_sigma must be > 0 or None")
        if self.horizontal_offset_sigma_m <= 0:
            raise ValueError("horizontal_offset_sigma_m must be > 0")
        if self.map_corner_sigma_m is not None and not self.map_corner_sigma_m > 0:
            raise ValueError("map_corner_sigma_m must be > 0 or None")
        if not (self.vp_sigma_scale > 0 and np.isfinite(self.vp_sigma_scale)):
            raise ValueError("vp_sigma_scale must be a finite number > 0")
        if not (self.vp_loss_scale > 0):
            raise ValueError("vp_loss_scale must be > 0")
        if not (self.tie_sigma_px > 0 and self.tie_loss_scale_px > 0):
            raise ValueError("tie_sigma_px and tie_loss_scale_px must be > 0")


def _as(a, shape_tail: tuple[int, ...], name: str, dtype=float) -> np.ndarray:
    arr = np.asarray(a, dtype=dtype)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = ", ".join(["N", *map(str, shape_tail)])
        raise ValueError(f"{name} must have shape ({want}), got {arr.shape}")
    return arr


@dataclass(kw_only=True)
class BundleProblem:
    """Plain-data input of the bundle; positions in the local map frame (metres).

    Attributes
    ----------
    cameras : dict camera_id -> Camera
        Initial intrinsics; one camera per physical head.
    poses : dict image_id -> Pose
        Initial ``cam_from_world`` of every image.
    image_camera : dict image_id -> camera_id
    image_ids : sequence of int, optional
        Order of images for the ``*_image`` index arrays; default ``sorted(poses)``.
    corner_xy : (C, 2) array
        Map corner positions.
    corner_heights : (C,) array
        Initial heights of the corners (reference heights when fixed), metres.
    vertical_image, vertical_corner : (M,) int arrays
        Image (index into ``image_ids``) and corner of each vertical constraint.
    vertical_line : (M, 3) array
        Homogeneous vertical image line (pixels) of each.
    facade_heights : (J,) array
        Initial heights ``h_j`` of the facade-edge constraints, metres.
    horizontal_image, horizontal_height : (H,) int arrays
        Image index and facade-height index of each horizontal constraint.
    horizontal_anchor_xy : (H, 2) array
        Map-edge anchor ``(x, y)`` of each (the edge centre), metres.
    horizontal_line : (H, 3) array
        Homogeneous horizontal image line (pixels) of each.
    horizontal_offset_normal : (H, 2) array, optional
        Where each anchor's position across its map edge was itself fitted
        to these observations (facade tracks re-triangulated as 3D lines):
        the unit horizontal direction of that offset. The solve keeps the
        anchors fixed; the precision (:attr:`BundleResult.image_precision_px`)
        counts one offset unknown per facade height along it (prior sigma
        ``BundleOptions.horizontal_offset_sigma_m``). None: anchors known.
    prior_rotations : dict image_id -> (3, 3) array, optional
        Prior ``cam_from_world`` rotation of each image (the INS), used with
        ``BundleOptions.rotation_prior_sigma_deg``.
    prior_centers : dict image_id -> (3,) array, optional
        Prior camera centre of each image (GNSS), same frame as ``poses``,
        used with ``BundleOptions.position_prior_sigma_m``.
    prior_principal_points : dict camera_id -> (2,) array, optional
        The priors' principal point (px) of each camera, used with
        ``BundleOptions.principal_point_prior_sigma`` (None: the start
        cameras').
    vertical_vps : dict image_id -> (3,) array, optional
        Each observed image's vertical vanishing point, homogeneous, in
        UNDISTORTED pixels (stage 1's frame: the priors' camera with its
        distortion removed), used with ``BundleOptions.vp_observations``.
        Its direction is taken through the current camera's pinhole part
        (``K^-1 v``): exact for models without distortion, and where the
        solved distortion equals the one the pixels were undistorted with;
        otherwise it neglects the change of distortion (the VP of an
        oblique view lies far outside the image, where a radial model does
        not extrapolate anyway).
    vertical_vp_covariances : dict image_id -> (3, 3) array, optional
        Stage 1's covariance of each VP of ``vertical_vps`` (rank 2, of the
        unit homogeneous vector); required with it.
    tie_xyz : (T, 3) array, optional
        Initial positions of the tie points (features matched across the
        images), metres; free unknowns of the solve.
    tie_image, tie_point : (O,) int arrays, optional
        Image (index into ``image_ids``) and tie point of each observation.
    tie_xy : (O, 2) array, optional
        Observed pixel of each, RAW (distorted) pixels, COLMAP convention.
    tie_sd : (O,) array, optional
        Each observation's standard deviation relative to the others' (> 0;
        its keypoint's scale over the median: a SIFT keypoint is located to
        a share of its scale): its rows are divided by it, so that
        ``BundleOptions.tie_sigma_px`` is the sd at 1. None: all 1. The
        adjustment's rounds give it to the first solve with tie points
        only (``adjustment.rounds._ties_kept``).
    tie_prior_xyz, tie_prior_sigma : (T, 3) arrays, optional
        Observed coordinates of tie points (control points of a survey) and
        their standard deviations, metres: one row ``(X - X_given) /
        sigma`` per finite sigma (inf: that axis free, e.g. a 2D control
        point's height; its given value is then ignored and may be NaN).
        None: no tie point observed.
    horizontal_ends : (H, 2, 2) array, optional
        The observed segment of each horizontal constraint, its two ends in
        RAW pixels (``BundleOptions.facade_lines``).
    facade_direction : (J, 2) array, optional
        Direction of each facade track's map edge (``facade_lines``).
    facade_offsets, facade_angles : (J,) arrays, optional
        Start of each track's offset across its map edge (m, along
        ``(u_y, -u_x)`` of its direction u) and of its angle about the
        vertical from that direction (rad); zeros by default.
    facade_angle_sigma : (J,) array, optional
        Prior standard deviation (rad) of each track's angle: the map edge's
        direction is good to its vertices' noise over its length; 2 deg
        where not given.
    facade_level : (J,) bool array, optional
        Which tracks are level lines (floors, eaves), observed at both ends;
        the others (near the ground, following the terrain) keep one row per
        observation at their start offset. None: all level.
    """

    cameras: dict[int, Camera]
    poses: dict[int, Pose]
    image_camera: dict[int, int]
    corner_xy: np.ndarray
    corner_heights: np.ndarray
    vertical_image: np.ndarray
    vertical_corner: np.ndarray
    vertical_line: np.ndarray
    facade_heights: np.ndarray
    horizontal_image: np.ndarray
    horizontal_height: np.ndarray
    horizontal_anchor_xy: np.ndarray
    horizontal_line: np.ndarray
    image_ids: tuple[int, ...] | None = None
    horizontal_offset_normal: np.ndarray | None = None
    prior_rotations: dict[int, np.ndarray] | None = None
    prior_centers: dict[int, np.ndarray] | None = None
    prior_principal_points: dict[int, np.ndarray] | None = None
    vertical_vps: dict[int, np.ndarray] | None = None
    vertical_vp_covariances: dict[int, np.ndarray] | None = None
    tie_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tie_image: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tie_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tie_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    tie_sd: np.ndarray | None = None
    tie_prior_xyz: np.ndarray | None = None
    tie_prior_sigma: np.ndarray | None = None
    horizontal_ends: np.ndarray | None = None
    facade_direction: np.ndarray | None = None
    facade_offsets: np.ndarray | None = None
    facade_angles: np.ndarray | None = None
    facade_angle_sigma: np.ndarray | None = None
    facade_level: np.ndarray | None = None

    @property
    def has_facade_lines(self) -> bool:
        """Whether the facade tracks can be solved as 3D lines."""
        return self.horizontal_ends is not None and self.facade_direction is not None

    def __post_init__(self) -> None:
        if self.image_ids is None:
            self.image_ids = tuple(sorted(self.poses))
        self.image_ids = tuple(int(i) for i in self.image_ids)
        missing = [i for i in self.image_ids if i not in self.poses]
        if missing:
            raise ValueError(f"image_ids without a pose: {missing[:10]}")
        bad = [
            i for i in self.image_ids if self.image_camera.get(i) not in self.cameras
        ]
        for name, prior in (
            ("rotation", self.prior_rotations),
            ("centre", self.prior_centers),
        ):
            missing = [
                i for i in self.image_ids if prior is not None and i not in prior
            ]
            if missing:
                raise ValueError(f"image_ids without a prior {name}: {missing[:10]}")
        if bad:
            raise ValueError(f"images without a known camera: {bad[:10]}")
        if self.vertical_vps is not None:
            covs = self.vertical_vp_covariances or {}
            missing = [i for i in self.vertical_vps if i not in covs]
            if missing:
                raise ValueError(f"vertical VPs without a covariance: {missing[:10]}")
            for i, v in self.vertical_vps.items():
                if np.shape(v) != (3,) or np.shape(covs[i]) != (3, 3):
                    raise ValueError(
                        f"vertical VP of image {i}: want (3,) and (3, 3) arrays"
                    )
        self.corner_xy = _as(self.corner_xy, (2,), "corner_xy")
        self.corner_heights = _as(self.corner_heights, (), "corner_heights")
        self.vertical_image = _as(self.vertical_image, (), "vertical_image", np.int64)
        self.vertical_corner = _as(
            self.vertical_corner, (), "vertical_corner", np.int64
        )
        self.vertical_line = _as(self.vertical_line, (3,), "vertical_line")
        self.facade_heights = _as(self.facade_heights, (), "facade_heights")
        self.horizontal_image = _as(
            self.horizontal_image, (), "horizontal_image", np.int64
        )
        self.horizontal_height = _as(
            self.horizontal_height, (), "horizontal_height", np.int64
        )
        self.horizontal_anchor_xy = _as(
            self.horizontal_anchor_xy, (2,), "horizontal_anchor_xy"
        )
        self.horizontal_line = _as(self.horizontal_line, (3,), "horizontal_line")
        if self.horizontal_offset_normal is not None:
            self.horizontal_offset_normal = _as(
                self.horizontal_offset_normal, (2,), "horizontal_offset_normal"
            )
        self._check_facade_lines()
        self.tie_xyz = _as(self.tie_xyz, (3,), "tie_xyz")
        self.tie_image = _as(self.tie_image, (), "tie_image", np.int64)
        self.tie_point = _as(self.tie_point, (), "tie_point", np.int64)
        self.tie_xy = _as(self.tie_xy, (2,), "tie_xy")
        if self.tie_sd is not None:
            self.tie_sd = _as(self.tie_sd, (), "tie_sd")
            if not np.all(self.tie_sd > 0):
                raise ValueError("tie_sd must be > 0")
        self._check_tie_priors()
        nc, ni, nj = len(self.corner_xy), len(self.image_ids), len(self.facade_heights)
        checks = [
            ("corner_heights", len(self.corner_heights) == nc),
            ("vertical_corner", len(self.vertical_corner) == len(self.vertical_image)),
            ("vertical_line", len(self.vertical_line) == len(self.vertical_image)),
            (
                "horizontal_height",
                len(self.horizontal_height) == len(self.horizontal_image),
            ),
            (
                "horizontal_anchor_xy",
                len(self.horizontal_anchor_xy) == len(self.horizontal_image),
            ),
            (
                "horizontal_line",
                len(self.horizontal_line) == len(self.horizontal_image),
            ),
            (
                "horizontal_offset_normal",
                self.horizontal_offset_normal is None
                or len(self.horizontal_offset_normal) == len(self.horizontal_image),
            ),
            ("tie_point", len(self.tie_point) == len(self.tie_image)),
            ("tie_xy", len(self.tie_xy) == len(self.tie_image)),
            ("tie_sd", self.tie_sd is None or len(self.tie_sd) == len(self.tie_image)),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"{name} has the wrong length")
        for name, idx, n in (
            ("vertical_image", self.vertical_image, ni),
            ("vertical_corner", self.vertical_corner, nc),
            ("horizontal_image", self.horizontal_image, ni),
            ("horizontal_height", self.horizontal_height, nj),
            ("tie_image", self.tie_image, ni),
            ("tie_point", self.tie_point, len(self.tie_xyz)),
        ):
            if len(idx) and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"{name} out of range [0, {n})")
        for name, lines in (
            ("vertical_line", self.vertical_line),
            ("horizontal_line", self.horizontal_line),
        ):
            if len(lines) and np.any(np.linalg.norm(lines[:, :2], axis=1) == 0):
                raise ValueError(f"{name} has lines with a = b = 0")

    def _check_tie_priors(self) -> None:
        if (self.tie_prior_xyz is None) != (self.tie_prior_sigma is None):
            raise ValueError("tie_prior_xyz and tie_prior_sigma go together")
        if self.tie_prior_xyz is None:
            return
        self.tie_prior_xyz = _as(self.tie_prior_xyz, (3,), "tie_prior_xyz")
        self.tie_prior_sigma = _as(self.tie_prior_sigma, (3,), "tie_prior_sigma")
        T = len(self.tie_xyz)
        if len(self.tie_prior_xyz) != T or len(self.tie_prior_sigma) != T:
            raise ValueError(f"tie_prior_xyz and tie_prior_sigma need {T} rows")
        if not np.all(self.tie_prior_sigma > 0):
            raise ValueError("tie_prior_sigma must be > 0 (inf: no row)")
        rows = np.isfinite(self.tie_prior_sigma)
        if not np.all(np.isfinite(self.tie_prior_xyz[rows])):
            raise ValueError("tie_prior_xyz must be finite where its sigma is")

    def _check_facade_lines(self) -> None:
        J, H = len(self.facade_heights), len(self.horizontal_image)
        if self.horizontal_ends is not None:
            self.horizontal_ends = np.asarray(self.horizontal_ends, float)
            if self.horizontal_ends.shape != (H, 2, 2):
                raise ValueError(f"horizontal_ends must have shape ({H}, 2, 2)")
        for name, tail in (
            ("facade_direction", (2,)),
            ("facade_offsets", ()),
            ("facade_angles", ()),
            ("facade_angle_sigma", ()),
            ("facade_level", ()),
        ):
            value = getattr(self, name)
            if value is not None:
                value = _as(
                    value, tail, name, bool if name == "facade_level" else float
                )
                if len(value) != J:
                    raise ValueError(f"{name} has the wrong length")
            setattr(self, name, value)
        if self.facade_angle_sigma is not None and not np.all(
            self.facade_angle_sigma > 0
        ):
            raise ValueError("facade_angle_sigma must be > 0")

    def facade_line_start(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(J,) offsets, angles and angle sigmas of the facade lines, with
        their defaults (0, 0, 2 deg) where not given."""
        J = len(self.facade_heights)
        return (
            np.zeros(J) if self.facade_offsets is None else self.facade_offsets,
            np.zeros(J) if self.facade_angles is None else self.facade_angles,
            np.full(J, np.radians(2.0))
            if self.facade_angle_sigma is None
            else self.facade_angle_sigma,
        )

    def without_ties(self) -> BundleProblem:
        """A copy without tie points (the rest shared)."""
        return dataclasses.replace(
            self,
            tie_xyz=np.zeros((0, 3)),
            tie_image=np.zeros(0, np.int64),
            tie_point=np.zeros(0, np.int64),
            tie_xy=np.zeros((0, 2)),
            tie_sd=None,
            tie_prior_xyz=None,
            tie_prior_sigma=None,
        )


@dataclass
class BundleSummary:
    """What happened in one solve; ``brief()`` gives a one-line report."""

    initial_cost: float
    final_cost: float
    initial_rmse_vertical_px: float
    final_rmse_vertical_px: float
    initial_rmse_horizontal_px: float
    final_rmse_horizontal_px: float
    num_iterations: int
    num_successful_steps: int
    time_s: float
    termination: str
    converged: bool
    #: Linked image groups (image ids); each has its own vertical datum.
    components: list[tuple[int, ...]]
    num_vertical: int
    num_horizontal: int
    num_heights: int
    num_camera_params: int

    def brief(self) -> str:
        return (
            f"bundle: {self.num_vertical} vertical + {self.num_horizontal} horizontal"
            f" residuals, {self.num_camera_params} camera params, {self.num_heights}"
            f" heights, {len(self.components)} component(s); cost"
            f" {self.initial_cost:.6g} -> {self.final_cost:.6g}; RMSE px vertical"
            f" {self.initial_rmse_vertical_px:.4g} ->"
            f" {self.final_rmse_vertical_px:.4g},"
            f" horizontal {self.initial_rmse_horizontal_px:.4g} ->"
            f" {self.final_rmse_horizontal_px:.4g}; {self.num_iterations} iterations,"
            f" {self.time_s:.3f} s, {self.termination}"
        )


@dataclass
class BundleResult:
    """Refined unknowns, final residuals and the summary.

    Attributes
    ----------
    cameras : dict camera_id -> Camera (copies, refined).
    poses : dict image_id -> Pose (refined ``cam_from_world``).
    facade_heights : (J,) array, metres.
    corner_heights : (C,) array, metres (the input values when fixed).
    vertical_residuals_px : (M,) final residuals in the problem's order.
    vertical_pair_residuals_px : (Q, 2) array
        With ``BundleOptions.vertical_direction_sigma_px``: each segment's
        two rows as their sum and difference over sqrt 2 (px), the rows the
        solve weighted; empty otherwise.
    horizontal_residuals_px : (H,) final residuals in the problem's order
        (with ``BundleOptions.facade_lines`` per observation the RMS of its
        two ends' residuals, with the sign of their sum).
    summary : BundleSummary
    image_precision_px : dict image_id -> float
        Predicted RMS deviation (px) of the image's constrained points (map
        corners and facade-edge anchors at their solved heights) projected by
        its solved camera, from the a-posteriori covariance of its pose and
        intrinsics (heights marginalised, datum by the gauge, each observation
        group's part scaled by its variance component, or all by the pooled
        variance factor). NaN where not computed or not determinable.
    pose_covariance : dict image_id -> (6, 6) array
        Where the precision is computed: the a-posteriori covariance of the
        image's pose, rotation increment omega (rad, ``R <- Exp(omega) R``)
        then centre (m, local frame), datum by the gauge.
    variance_factor : float
        A-posteriori variance of unit weight, ``r^T W r / redundancy``, all
        observations pooled.
    variance_components : dict group name -> (float, float)
        Where the precision is computed with them
        (``BundleOptions.variance_components``): each observation group's
        variance component (its ``r^T W r`` over its redundancy: the factor
        on its stated variance) and its redundancy.
    prior_offset_m : (2,) array or None
        The priors' centres' horizontal offset against the map (m, priors
        minus solved), where estimated (``BundleOptions.estimate_prior_offset``).
    vp_angle_deg : dict image_id -> float
        With VP observations: the final angle (deg) between each observed
        image's solved vertical and its VP's direction.
    vp_chi2 : dict image_id -> float
        The same residual whitened by stage 1's STATED covariance (scale 1):
        chi-square with 2 degrees of freedom where that covariance is right
        (the rounds estimate ``BundleOptions.vp_sigma_scale`` from it).
    vp_omega, vp_redundancy, vp_test : dict image_id -> float
        With VP observations, at the current scale
        (:meth:`~obliq_colmap.bundle.priors.VanishingPointObservation.statistics`):
        the VP's weighted squared residual, its redundancy number (0..2) and
        its chi-square (2 dof) test against the solution without it. Empty
        where the cofactor matrix is not computed (more camera parameters
        than ``BundleOptions.precision_max_camera_params``).
    tie_xyz : (T, 3) array
        The solved tie points (metres; empty without them).
    tie_residuals_px : (O, 2) array
        Final reprojection errors of their observations, problem order.
    tie_residuals_scaled_px : (O, 2) array
        The same over each observation's ``tie_sd``, scaled by sqrt(2n /
        (2n - 3)), n the point's observations (its 3 unknowns fit part of
        its 2n rows): their spread is the noise's at the relative sd 1.
    facade_offsets, facade_angles : (J,) arrays
        With ``BundleOptions.facade_lines``: each track's solved offset (m)
        across its map edge and angle (rad) from its direction; else empty.
    vp_loo : dict image_id -> ((2,) array, (2, 2) array)
        With them: the VP's residual at the solution without it and the
        others' cofactor of that direction, whitened by stage 1's STATED
        covariance (scale 1): ``E[z0 z0^T] = s^2 I + A`` with ``s`` the
        true factor on stage 1's sd.
    """

    cameras: dict[int, Camera]
    poses: dict[int, Pose]
    facade_heights: np.ndarray
    corner_heights: np.ndarray
    vertical_residuals_px: np.ndarray
    horizontal_residuals_px: np.ndarray
    summary: BundleSummary = field(repr=False)
    vertical_pair_residuals_px: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2))
    )
    image_precision_px: dict[int, float] = field(default_factory=dict)
    pose_covariance: dict[int, np.ndarray] = field(default_factory=dict)
    variance_factor: float = float("nan")
    variance_components: dict[str, tuple[float, float]] = field(default_factory=dict)
    prior_offset_m: np.ndarray | None = None
    vp_angle_deg: dict[int, float] = field(default_factory=dict)
    vp_chi2: dict[int, float] = field(default_factory=dict)
    vp_omega: dict[int, float] = field(default_factory=dict)
    vp_redundancy: dict[int, float] = field(default_factory=dict)
    vp_test: dict[int, float] = field(default_factory=dict)
    vp_loo: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    tie_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tie_residuals_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    tie_residuals_scaled_px: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2))
    )
    facade_offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))
    facade_angles: np.ndarray = field(default_factory=lambda: np.zeros(0))


def image_components(
    num_images: int, image_index: np.ndarray, height_index: np.ndarray
) -> tuple[int, np.ndarray]:
    """Connected components of images linked by shared height unknowns.

    Parameters
    ----------
    num_images : int
    image_index, height_index : (N,) int arrays
        One entry per residual that touches a height (image, height index).

    Returns
    -------
    num_components : int
    labels : (num_images,) int array, component of each image, 0-based,
        numbered in order of first appearance.
    """
    image_index = np.asarray(image_index, np.int64)
    height_index = np.asarray(height_index, np.int64)
    nh = int(height_index.max()) + 1 if len(height_index) else 0
    n = num_images + nh
    g = sp.coo_matrix(
        (np.ones(len(image_index)), (image_index, num_images + height_index)),
        shape=(n, n),
    )
    _, labels = connected_components(g, directed=False)
    labels = labels[:num_images]
    _, first, inv = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    labels = order[inv]
    return int(labels.max()) + 1 if num_images else 0, labels


def vertical_row_pairs(problem: BundleProblem) -> tuple[np.ndarray, np.ndarray]:
    """The vertical rows that are the two ends of one segment.

    A segment observed at a map corner gives two rows, its corner's vertical
    at the heights of its two ends, on one image line: consecutive rows of
    the same image, line and corner position (their height unknowns may
    differ). Rows left alone (the other end dropped as an outlier) are in
    no pair.

    Returns
    -------
    (Q,) and (Q,) int arrays: the first and the second row of each pair, in
    the problem's order.
    """
    img, xy, line = problem.vertical_image, problem.corner_xy, problem.vertical_line
    pos = xy[problem.vertical_corner]
    same = (
        (img[1:] == img[:-1])
        & np.all(line[1:] == line[:-1], axis=1)
        & np.all(pos[1:] == pos[:-1], axis=1)
    )
    # Within a run of identical rows, pairs from the run's start: (0, 1),
    # (2, 3), ...
    k = np.flatnonzero(same)
    new_run = np.diff(np.r_[-2, k]) != 1
    start_of = k[new_run][np.cumsum(new_run) - 1]
    a = k[(k - start_of) % 2 == 0].astype(np.int64)
    return a, a + 1
