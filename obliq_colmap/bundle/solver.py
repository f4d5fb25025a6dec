"""Global cadastral-line bundle adjustment (paper section 2.3, eq. 3).

Unknowns: per image the 6 extrinsics (rotation, camera centre), per camera
(COLMAP camera_id, shared by all images of one head) the refined intrinsic
parameters, and scalar heights: one per facade-edge constraint j (``h_j``)
and, by default, one per map corner (``h_i``, shared by the corner's
observations in all images).

Residuals (see :mod:`obliq_colmap.bundle.residuals`, all in pixels):

* vertical: signed distance of the projected corner ``(x_i, y_i, h_i)`` to
  the detected vertical image line;
* horizontal: ``dist_z``, the distance of the projected facade point
  ``(x_j, y_j, h_j)`` to the detected horizontal line, measured along the
  projected vertical.

Robust loss by IRLS weights ``rho'(r^2)`` (Huber or Cauchy, scale in pixels);
the cost is ``1/2 sum rho(r^2)`` (plus the optional corner-height prior),
the same as Ceres' with the same loss.

Algorithm (Levenberg-Marquardt with the heights eliminated):

1. Evaluate residuals and analytic Jacobians, vectorised per camera model.
2. Normal equations in the camera block C (6 per image + refined intrinsics
   per camera, dense: a few hundred unknowns) and the height block h, which
   is DIAGONAL because every residual touches at most one height.
3. Marquardt damping ``H + lambda * clip(diag H, 1e-6, 1e32)`` on both blocks.
4. Schur complement ``S = H_CC - E^T D_h^-1 E`` (E: sparse height-camera
   coupling), dense solve of S with the gauge constraints (below) as a KKT
   system, back-substitution of the heights.
5. Accept the step if the robust cost decreases (gain ratio > 1e-3);
   Nielsen's update of lambda.

Gauge: the map fixes x, y, heading and scale; only the vertical datum is
free (all heights and the camera centres of a group of linked images shift
together). Images are linked when they share a height unknown (union-find
via connected components of the image-height graph). For each component one
hard linear constraint keeps the mean camera-centre height of its images at
its initial value (``gauge="component_mean_camera_height"``). Components are
reported in the summary.

Free corner heights are almost unobservable (the whole vertical edge
projects onto the same line at the true pose), so an optional weak prior
``(h_i - h_i0) / sigma`` keeps them at their initial value unless the data
say otherwise; at the true pose it costs nothing.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from ..geometry import Camera, Pose, rotation_exp, skew
from . import residuals as res

__all__ = [
    "BundleOptions",
    "BundleProblem",
    "BundleResult",
    "BundleSummary",
    "image_components",
    "solve_bundle",
]

logger = logging.getLogger(__name__)

LOSSES = ("huber", "cauchy", "none")
CORNER_HEIGHT_MODES = ("free", "fixed")
GAUGES = ("component_mean_camera_height", "none")


# --------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------


@dataclass(kw_only=True)
class BundleOptions:
    """Options of :func:`solve_bundle`."""

    #: Robust loss on each residual: "huber", "cauchy" or "none".
    loss: str = "huber"
    #: Scale of the robust loss, pixels (residuals below it count fully).
    loss_scale_px: float = 2.0
    #: A priori standard deviations (px) of the two residual kinds: each
    #: residual's cost is weighted by 1 / sigma^2 (the robust loss keeps its
    #: scale in pixels). Variance components, e.g. re-estimated from a first
    #: solve's residuals: map corners carry the map's vertex noise (~1 px),
    #: facade edges only the image noise (~0.3 px).
    vertical_sigma_px: float = 1.0
    horizontal_sigma_px: float = 1.0
    #: Maximum number of Levenberg-Marquardt iterations (accepted or not).
    max_iterations: int = 100
    #: Stop when an accepted step lowers the cost by less than this fraction.
    function_tolerance: float = 1e-8
    #: Stop when |step| <= tol * (|x| + tol), x = centres, intrinsics, heights.
    parameter_tolerance: float = 1e-8
    #: Refine the focal length(s) of every camera.
    refine_focal_length: bool = True
    #: Refine fx and fy of two-focal models (PINHOLE, OPENCV) independently;
    #: False moves them together (aspect ratio kept, as the paper's). The map
    #: has no heights, so a vertical stretch of the whole scene is nearly a
    #: gauge freedom that fx != fy would absorb (measured: fx and fy drifted
    #: 8 % apart on the sample with 2 images per camera).
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
    #: Standard deviation, degrees, of each image's rotation about its prior
    #: (``BundleProblem.prior_rotations``: a calibrated INS, attitude as an
    #: observation); None: no prior. It holds each image's rotation, which
    #: its constraints determine worst (docs/BENCHMARKS.md, issue 5).
    rotation_prior_sigma_deg: float | None = None
    #: Standard deviation, metres, of each image's camera centre about its
    #: prior (``BundleProblem.prior_centers``: survey-grade GNSS, e.g. PPK
    #: with the lever arm applied, in the frame and vertical datum of the
    #: priors); None: no prior. Centres known to ~0.1 m fix the block's tilt
    #: and each image's centre, which the map's constraints trade against
    #: its rotation (docs/BENCHMARKS.md, issue 5).
    position_prior_sigma_m: float | None = None
    #: With ``position_prior_sigma_m``: estimate one horizontal offset of the
    #: priors' centres against the map (2 unknowns per solve): a GNSS frame
    #: off the cadastre's, a lever arm left out. Without it such an offset
    #: bends every image along its weak direction (measured: 0.58 m put the
    #: `paper` block at 0.81 px instead of 0.25). The vertical has no map
    #: reference: the priors' heights stay the datum.
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
    #: The precision inverts the dense reduced camera system: O(n^3) in its
    #: n parameters (6 per image + the intrinsics); the inverse alone takes
    #: 0.004 / 0.33 / 2.2 / 18 s at n = 250 / 1,500 / 3,000 / 6,000 on one
    #: core here. Above this n it is skipped (NaN, and a log line).
    precision_max_camera_params: int = 3000
    #: Prior standard deviation (m) of the anchor offsets counted in the
    #: precision (``BundleProblem.horizontal_offset_normal``).
    horizontal_offset_sigma_m: float = 10.0

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
        if self.horizontal_offset_sigma_m <= 0:
            raise ValueError("horizontal_offset_sigma_m must be > 0")


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
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"{name} has the wrong length")
        for name, idx, n in (
            ("vertical_image", self.vertical_image, ni),
            ("vertical_corner", self.vertical_corner, nc),
            ("horizontal_image", self.horizontal_image, ni),
            ("horizontal_height", self.horizontal_height, nj),
        ):
            if len(idx) and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"{name} out of range [0, {n})")
        for name, lines in (
            ("vertical_line", self.vertical_line),
            ("horizontal_line", self.horizontal_line),
        ):
            if len(lines) and np.any(np.linalg.norm(lines[:, :2], axis=1) == 0):
                raise ValueError(f"{name} has lines with a = b = 0")


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
    horizontal_residuals_px : (H,) final residuals in the problem's order.
    summary : BundleSummary
    image_precision_px : dict image_id -> float
        Predicted RMS deviation (px) of the image's constrained points (map
        corners and facade-edge anchors at their solved heights) projected by
        its solved camera, from the a-posteriori covariance of its pose and
        intrinsics (heights marginalised, datum by the gauge, scaled by the
        variance factor). NaN where not computed or not determinable.
    variance_factor : float
        A-posteriori variance of unit weight, ``r^T W r / redundancy``.
    prior_offset_m : (2,) array or None
        The priors' centres' horizontal offset against the map (m, priors
        minus solved), where estimated (``BundleOptions.estimate_prior_offset``).
    """

    cameras: dict[int, Camera]
    poses: dict[int, Pose]
    facade_heights: np.ndarray
    corner_heights: np.ndarray
    vertical_residuals_px: np.ndarray
    horizontal_residuals_px: np.ndarray
    summary: BundleSummary = field(repr=False)
    image_precision_px: dict[int, float] = field(default_factory=dict)
    variance_factor: float = float("nan")
    prior_offset_m: np.ndarray | None = None


# --------------------------------------------------------------------------
# Loss
# --------------------------------------------------------------------------


def _loss(kind: str, scale: float, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """rho(r^2) and rho'(r^2) (Ceres' conventions, rho(s) = s for small s)."""
    if kind == "none":
        return r2, np.ones_like(r2)
    b = scale * scale
    if kind == "huber":
        big = r2 > b
        sq = np.sqrt(np.where(big, r2, b))
        return np.where(big, 2.0 * scale * sq - b, r2), np.where(big, scale / sq, 1.0)
    # cauchy
    return b * np.log1p(r2 / b), 1.0 / (1.0 + r2 / b)


# --------------------------------------------------------------------------
# Components
# --------------------------------------------------------------------------


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


# --------------------------------------------------------------------------
# Solver
# --------------------------------------------------------------------------


def _intrinsics_basis(model: str, params: np.ndarray, opts: BundleOptions):
    """(P, Q) basis of the refined steps of one camera's P parameters."""
    focal, pp, extra = res.focal_principal_extra_indices(model)
    cols = []
    if opts.refine_focal_length:
        if len(focal) == 2 and not opts.refine_aspect_ratio:
            col = np.zeros(len(params))
            col[focal[0]] = 1.0
            col[focal[1]] = params[focal[1]] / params[focal[0]]
            cols.append(col)
        else:
            cols += [np.eye(len(params))[i] for i in focal]
    if opts.refine_principal_point:
        cols += [np.eye(len(params))[i] for i in pp]
    if opts.refine_extra_params:
        cols += [np.eye(len(params))[i] for i in extra]
    return np.array(cols).T.reshape(len(params), len(cols))


class _Setup:
    """Static layout: residual order, parameter columns, groups, gauge."""

    def __init__(self, problem: BundleProblem, options: BundleOptions) -> None:
        P, opts = problem, options
        self.image_ids = P.image_ids
        K = len(P.image_ids)
        self.camera_ids = sorted({P.image_camera[i] for i in P.image_ids})
        cam_slot = {cid: s for s, cid in enumerate(self.camera_ids)}
        self.img_cam = np.array([cam_slot[P.image_camera[i]] for i in P.image_ids])
        nv, nh = len(P.vertical_image), len(P.horizontal_image)
        free = opts.corner_heights == "free"
        nJ = len(P.facade_heights)

        # Residuals: vertical then horizontal, then sorted (stably) by camera
        # model, kind, camera and image, so that each evaluation group (one
        # model and kind) and each of its cameras and images is a slice.
        img = np.concatenate([P.vertical_image, P.horizontal_image])
        kind = np.concatenate([np.zeros(nv, np.int8), np.ones(nh, np.int8)])
        xy = np.concatenate([P.corner_xy[P.vertical_corner], P.horizontal_anchor_xy])
        line = np.concatenate([P.vertical_line, P.horizontal_line])
        line = line / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
        hidx = np.concatenate(
            [nJ + P.vertical_corner if free else np.full(nv, -1), P.horizontal_height]
        )
        zfix = np.concatenate([P.corner_heights[P.vertical_corner], np.zeros(nh)])
        offset = np.zeros((nv + nh, 2))
        if P.horizontal_offset_normal is not None:
            offset[nv:] = P.horizontal_offset_normal
        models = [P.cameras[c].model for c in self.camera_ids]
        self.camera_model = models
        model_rank = np.searchsorted(sorted(set(models)), models)
        cam = self.img_cam[img]
        order = np.lexsort((img, cam, kind, model_rank[cam]))
        self.order = order
        self.nv, self.nh = nv, nh
        self.img, self.kind, self.xy = img[order], kind[order], xy[order]
        self.line, self.hidx, self.zfix = line[order], hidx[order], zfix[order]
        self.offset_dir = offset[order]  # (N, 2), zero: no offset unknown
        self.cam = self.img_cam[self.img]
        self.n_heights = nJ + (len(P.corner_xy) if free else 0)
        self.has_h = self.hidx >= 0
        # Heights whose anchor offset was fitted to the observations: each
        # such offset is one more unknown in the redundancy.
        with_offset = self.has_h & np.any(self.offset_dir != 0, axis=1)
        self.n_offsets = len(np.unique(self.hidx[with_offset]))
        # The rows with a height as runs (all rows, or all but the vertical
        # ones when the corners are fixed): slices are cheaper than a mask.
        self.h_runs = [(a, b) for a, b in _runs(self.has_h) if self.has_h[a]]
        # Cost weight of each residual: 1 / sigma^2 of its kind.
        sigma = np.array([opts.vertical_sigma_px, opts.horizontal_sigma_px])
        self.weight = 1.0 / sigma[self.kind] ** 2

        # Active images and cameras; parameter columns of the camera block.
        counts = np.bincount(self.img, minlength=K)
        self.active_images = np.flatnonzero(counts > 0)
        col = 0
        self.pose_col = np.full(K, -1)
        for k in self.active_images:
            self.pose_col[k] = col
            col += 6
        # Per camera a (P, Q) basis of its refined parameter steps:
        # params += basis @ step (one column per free parameter; fx and fy
        # share one column unless the aspect ratio is refined).
        self.refined: list[np.ndarray] = []
        self.intr_col = np.full(len(self.camera_ids), -1)
        active_cams = set(self.img_cam[self.active_images].tolist())
        for s, cid in enumerate(self.camera_ids):
            cam = P.cameras[cid]
            basis = _intrinsics_basis(cam.model, cam.params, opts)
            if s not in active_cams:
                basis = basis[:, :0]
            self.refined.append(basis)
            if basis.shape[1]:
                self.intr_col[s] = col
                col += basis.shape[1]
        # Observed centres (GNSS) hold every component's vertical datum, and
        # may sit off the map horizontally by one offset (two columns).
        self.centred = (
            opts.position_prior_sigma_m is not None and P.prior_centers is not None
        )
        self.shift_col = -1
        if self.centred and opts.estimate_prior_offset:
            self.shift_col = col
            col += 2
        self.n_red = col
        self.L = 6 + max((b.shape[1] for b in self.refined), default=0)
        # (N, L) global columns of each residual's camera-side Jacobian; the
        # padding column n_red is dropped after assembly.
        N = len(self.img)
        cols = np.full((N, self.L), self.n_red)
        cols[:, :6] = self.pose_col[self.img][:, None] + np.arange(6)
        for s, basis in enumerate(self.refined):
            q = basis.shape[1]
            m = self.cam == s
            cols[np.ix_(m, 6 + np.arange(q))] = self.intr_col[s] + np.arange(q)
        self.cols = cols
        # Runs of rows of one image: (start, end, the image's columns).
        self.image_runs = [(a, b, cols[a]) for a, b in _runs(self.img)]
        # Evaluation groups: one camera model and kind, at most _CHUNK rows.
        self.groups = [
            _Group(self, models[self.cam[a]], int(self.kind[a]), c, min(c + _CHUNK, b))
            for a, b in _runs(model_rank[self.cam] * 2 + self.kind)
            for c in range(a, b, _CHUNK)
        ]

        # Components and gauge rows (over the camera block).
        hmask = self.has_h
        self.num_components, self.labels = image_components(
            K, self.img[hmask], self.hidx[hmask]
        )
        self.components = [
            tuple(P.image_ids[k] for k in np.flatnonzero(self.labels == c))
            for c in range(self.num_components)
        ]
        rows = []
        if opts.gauge == "component_mean_camera_height" and not self.centred:
            for c in range(self.num_components):
                members = [
                    k for k in np.flatnonzero(self.labels == c) if self.pose_col[k] >= 0
                ]
                if members:
                    a = np.zeros(self.n_red)
                    a[self.pose_col[members] + 5] = 1.0 / len(members)
                    rows.append(a)
        self.A = np.array(rows).reshape(-1, self.n_red)
        # Layout of the height x camera coupling E.
        self.coupling = _Coupling(
            self.img[hmask], self.hidx[hmask], cols[hmask], self.n_heights, self.n_red
        )


#: Rows per residual evaluation call: the per-row temporaries (~60 of them
#: with Jacobians) then stay small and in cache; measured at the paper's
#: scale, 44k rows at once took 2.1x the time of chunks of 4k-16k.
_CHUNK = 8192


def _runs(key: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of the runs of equal values of ``key`` (N,)."""
    edge = np.flatnonzero(np.diff(key, prepend=-1, append=-1) != 0)
    return [(int(a), int(b)) for a, b in zip(edge[:-1], edge[1:], strict=False)]


class _Group:
    """Static rows of one evaluation group (a camera model and a residual
    kind): the slice ``[start, end)`` of the residual order, as (., n) rows."""

    def __init__(self, S: _Setup, model: str, kind: int, start: int, end: int):
        self.model, self.kind, self.start, self.end = model, kind, start, end
        sl = slice(start, end)
        self.img = S.img[sl]
        self.line = np.ascontiguousarray(S.line[sl].T)  # (3, n) unit lines
        self.xy = np.ascontiguousarray(S.xy[sl].T)  # (2, n)
        self.has_h, self.zfix = S.has_h[sl], S.zfix[sl]
        self.hidx = np.maximum(S.hidx[sl], 0)
        # The group's cameras, each a run of rows: (slot, start, end) local.
        cam = S.cam[sl]
        self.cam_runs = [(int(cam[a]), a, b) for a, b in _runs(cam)]
        self.cams = [c for c, _, _ in self.cam_runs]
        self.cam_local = np.searchsorted(self.cams, cam)
        self.E = res.expansion_matrix(model)

    def full_params(self, params: list[np.ndarray]) -> np.ndarray:
        """(8, 1) or (8, n) general parameters of the rows."""
        full = self.E @ np.stack([params[c] for c in self.cams], 1)  # (8, cams)
        return full if len(self.cams) == 1 else full[:, self.cam_local]


class _Coupling:
    """Static layout of the height-camera coupling E (heights x camera columns).

    Residual row i with a height adds its (L,) block ``F_i = w_i Jh_i Jc_i``
    to ``E[hidx_i, cols_i]``; ``cols_i`` are its image's columns (6 pose,
    then the camera's intrinsics, shared by the camera's images; padding
    column ``n_red``). Kept: the CSR pattern of E (with duplicates), and
    for ``E^T D E = sum_j D_j e_j e_j^T`` every pair of blocks (a, b) of one
    height with ``img[a] <= img[b]``, grouped by image pair, so that the term
    is one L x L product per image pair (a few hundred) instead of a sparse
    matrix product.

    Parameters
    ----------
    img, hidx : (Nh,) int arrays, image and height of each row with a height.
    cols : (Nh, L) int array, camera-block columns of each such row.
    n_heights, n_red : int, the numbers of heights and camera-block columns.
    """

    def __init__(self, img, hidx, cols, n_heights: int, n_red: int) -> None:
        Nh, L = cols.shape
        n1 = n_red + 1
        self.hidx, self.cols = hidx, cols
        self.shape, self.L = (n_heights, n_red), L
        order = np.argsort(hidx, kind="stable")
        counts = np.bincount(hidx, minlength=n_heights)
        # Pairs (a, a) need no gather: each run of rows of one image adds
        # F_run^T F_run to its diagonal block. The other ordered pairs of
        # rows of one height (rows sorted by height, each paired with every
        # row of its group): those of two images once (img[a] < img[b]), both
        # orders of those of one image.
        self.runs = _runs(img)
        self.run_cols = cols[[a for a, _ in self.runs]].reshape(-1, L)
        start = np.cumsum(counts) - counts
        size = counts[hidx[order]]
        first_of = np.repeat(np.cumsum(size) - size, size)
        a = np.repeat(np.arange(Nh), size)
        b = np.repeat(start[hidx[order]], size) + np.arange(len(a)) - first_of
        a, b = order[a], order[b]
        ok = (img[a] < img[b]) | ((img[a] == img[b]) & (a != b))
        a, b = a[ok], b[ok]
        pair = img[a] * (int(img.max(initial=0)) + 1) + img[b]
        o = np.argsort(pair, kind="stable")
        self.a, self.b, pair = a[o], b[o], pair[o]
        first = np.flatnonzero(np.diff(pair, prepend=-1))
        self.bounds = np.append(first, len(o))
        # Where each block goes in the padded (n1, n1) term: the runs', then
        # the image pairs'; a pair of two images also, transposed, to
        # (cols_b, cols_a).
        ca = np.concatenate([self.run_cols, cols[self.a[first]]])
        cb = np.concatenate([self.run_cols, cols[self.b[first]]])
        off = np.concatenate(
            [np.zeros(len(self.runs), bool), img[self.a[first]] != img[self.b[first]]]
        )
        self.offdiag = off
        self.flat = np.concatenate(
            [
                (ca[:, :, None] * n1 + cb[:, None, :]).ravel(),
                (ca[off][:, :, None] + cb[off][:, None, :] * n1).ravel(),
            ]
        )

    def matrix(self, F: np.ndarray) -> sp.csr_matrix:
        """E (n_heights, n_red) from the (Nh, L) blocks (for diagnostics)."""
        rows = np.broadcast_to(self.hidx[:, None], self.cols.shape)
        valid = self.cols < self.shape[1]  # not the padding column
        E = sp.coo_matrix((F[valid], (rows[valid], self.cols[valid])), self.shape)
        return E.tocsr()

    def rmatvec(self, F: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n_red,) ``E^T y`` for (n_heights,) ``y``."""
        yr = y[self.hidx]
        per_run = np.empty((len(self.runs), self.L))
        for p, (a, b) in enumerate(self.runs):
            np.matmul(yr[a:b], F[a:b], out=per_run[p])
        n1 = self.shape[1] + 1
        return np.bincount(self.run_cols.ravel(), per_run.ravel(), n1)[:-1]

    def matvec(self, F: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(n_heights,) ``E x`` for (n_red,) ``x``."""
        xp = np.append(x, 0.0)  # the padding column
        per_row = np.empty(len(F))
        for (a, b), cols in zip(self.runs, self.run_cols, strict=True):
            np.matmul(F[a:b], xp[cols], out=per_row[a:b])
        return np.bincount(self.hidx, per_row, self.shape[0])

    def dense_rows(self, F: np.ndarray, heights: np.ndarray) -> np.ndarray:
        """(len(heights), n_red) the rows ``E[heights]``, dense (a few)."""
        pos = np.full(self.shape[0], -1)
        pos[heights] = np.arange(len(heights))
        sel = np.flatnonzero(pos[self.hidx] >= 0)
        out = np.zeros((len(heights), self.shape[1] + 1))
        np.add.at(out, (pos[self.hidx[sel]][:, None], self.cols[sel]), F[sel])
        return out[:, :-1]

    def gram(self, F: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """(n_red, n_red) ``E^T diag(scale^2) E`` for per-height ``scale``."""
        Fs = F * scale[self.hidx][:, None]
        nr = len(self.runs)
        blocks = np.empty((nr + len(self.bounds) - 1, self.L, self.L))
        for p, (s, e) in enumerate(self.runs):
            np.matmul(Fs[s:e].T, Fs[s:e], out=blocks[p])
        for p in range(len(self.bounds) - 1):
            # Gathered per image pair: small, in cache.
            s, e = self.bounds[p], self.bounds[p + 1]
            FA = np.take(Fs, self.a[s:e], axis=0)
            FB = np.take(Fs, self.b[s:e], axis=0)
            np.matmul(FA.T, FB, out=blocks[nr + p])
        vals = np.concatenate([blocks.ravel(), blocks[self.offdiag].ravel()])
        n1 = self.shape[1] + 1
        return np.bincount(self.flat, vals, minlength=n1 * n1).reshape(n1, n1)[:-1, :-1]


class _State:
    def __init__(self, R, c, params, heights, shift=None):
        self.R, self.c, self.params, self.heights = R, c, params, heights
        # horizontal offset of the priors' centres against the map (m;
        # BundleOptions.estimate_prior_offset)
        self.shift = np.zeros(2) if shift is None else shift

    @classmethod
    def start(cls, P: BundleProblem, S: _Setup) -> _State:
        """The problem's start: its poses, cameras and heights (the corner
        heights too where they are free unknowns)."""
        free = S.n_heights > len(P.facade_heights)
        return cls(
            np.stack([P.poses[i].rotation for i in P.image_ids]),
            np.stack([P.poses[i].center for i in P.image_ids]),
            [P.cameras[c].params.copy() for c in S.camera_ids],
            np.concatenate([P.facade_heights, P.corner_heights if free else []]),
        )

    def copy(self):
        return _State(
            self.R.copy(),
            self.c.copy(),
            [p.copy() for p in self.params],
            self.heights.copy(),
            self.shift.copy(),
        )


def _evaluate(setup: _Setup, st: _State, jac: bool):
    """Residuals (N,) and, if jac, camera Jacobian (N, L) and height Jacobian (N,).

    The camera Jacobian is the transpose of an (L, N) array, so that each
    group writes its rows contiguously.
    """
    N = len(setup.img)
    r = np.empty(N)
    JcT = np.zeros((setup.L, N)) if jac else None
    Jh = np.zeros(N) if jac else None
    Rk = st.R.transpose(1, 2, 0)  # (3, 3, K)
    ck = st.c.T  # (3, K)
    for g in setup.groups:
        R = np.take(Rk, g.img, axis=2)  # (3, 3, n)
        c = np.take(ck, g.img, axis=1)
        D = np.empty_like(c)  # X - c
        np.subtract(g.xy, c[:2], out=D[:2])
        h = np.where(g.has_h, st.heights[g.hidx], g.zfix) if len(st.heights) else g.zfix
        np.subtract(h, c[2], out=D[2])
        fn = res.vertical_rows if g.kind == 0 else res.horizontal_rows
        out = fn(g.model, g.full_params(st.params), R, D, g.line, jac)
        r[g.start : g.end] = out[0]
        if jac:
            _, d_pose, d_params, d_height = out
            JcT[:6, g.start : g.end] = d_pose
            for s, a, b in g.cam_runs:
                basis = setup.refined[s]
                if basis.shape[1]:
                    rows = slice(g.start + a, g.start + b)
                    JcT[6 : 6 + basis.shape[1], rows] = basis.T @ d_params[:, a:b]
            Jh[g.start : g.end] = d_height
    if jac:
        Jh[~setup.has_h] = 0.0
    return r, (JcT.T if jac else None), Jh


def solve_bundle(
    problem: BundleProblem, options: BundleOptions | None = None
) -> BundleResult:
    """Refine all extrinsics, intrinsics and heights of eq. 3.

    Parameters
    ----------
    problem : BundleProblem
    options : BundleOptions, optional

    Returns
    -------
    BundleResult
        Refined copies; the problem is not modified.

    Raises
    ------
    ValueError
        If a constrained point is behind its camera at the start.
    """
    options = options or BundleOptions()
    if options.blas_threads is None:
        return _solve(problem, options)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=options.blas_threads, user_api="blas"):
        return _solve(problem, options)


def _solve(problem: BundleProblem, opts: BundleOptions) -> BundleResult:
    t0 = time.perf_counter()
    P = problem
    S = _Setup(P, opts)
    free = opts.corner_heights == "free"
    nJ = len(P.facade_heights)
    st = _State.start(P, S)
    heights0 = st.heights.copy()
    prior_w = (
        1.0 / opts.corner_height_prior_m**2
        if free and opts.corner_height_prior_m is not None
        else 0.0
    )
    prior_mask = np.zeros(S.n_heights, bool)
    prior_mask[nJ:] = prior_w > 0

    # Observed poses (INS attitude, GNSS centres): 3 rows per active image.
    pose_priors = [
        p
        for p in (_AttitudePrior.of(P, S, opts), _CentrePrior.of(P, S, opts))
        if p is not None
    ]

    def cost_of(r: np.ndarray, st: _State) -> float:
        rho, _ = _loss(opts.loss, opts.loss_scale_px, r * r)
        c = 0.5 * float(np.sum(S.weight * rho))
        if prior_w:
            dh = (st.heights - heights0)[prior_mask]
            c += 0.5 * prior_w * float(dh @ dh)
        c += sum(p.cost(st) for p in pose_priors)
        return c if np.isfinite(c) else np.inf

    def rmse(r: np.ndarray) -> tuple[float, float]:
        v, h = r[S.kind == 0], r[S.kind == 1]
        f = lambda a: float(np.sqrt(np.mean(a * a))) if len(a) else float("nan")  # noqa: E731
        return f(v), f(h)

    r, Jc, Jh = _evaluate(S, st, jac=True)
    if not np.all(np.isfinite(r)):
        bad = np.flatnonzero(~np.isfinite(r))
        raise ValueError(
            f"{len(bad)} constrained points are behind their camera (or project to "
            f"infinity) at the start, e.g. in image {P.image_ids[S.img[bad[0]]]}"
        )
    cost = cost_of(r, st)
    initial_cost, initial_rmse = cost, rmse(r)

    # Height-only Gauss-Newton steps (cameras fixed): cheap, diagonal.
    for _ in range(opts.height_initialisation_steps):
        if not S.n_heights:
            break
        _, w = _loss(opts.loss, opts.loss_scale_px, r * r)
        w = w * S.weight
        Hh = np.bincount(S.hidx[S.has_h], (w * Jh * Jh)[S.has_h], S.n_heights)
        gh = np.bincount(S.hidx[S.has_h], (w * Jh * r)[S.has_h], S.n_heights)
        Hh = Hh + prior_w * prior_mask
        gh = gh + prior_w * prior_mask * (st.heights - heights0)
        trial = st.copy()
        trial.heights = st.heights - gh / np.maximum(Hh, 1e-12)
        r_t, _, _ = _evaluate(S, trial, jac=False)
        c_t = cost_of(r_t, trial)
        if not c_t < cost:
            break
        st, cost = trial, c_t
        r, Jc, Jh = _evaluate(S, st, jac=True)

    lam, nu = opts.initial_damping, 2.0
    it = n_ok = 0
    termination = "max_iterations"
    converged = False
    need_build = True
    while it < opts.max_iterations:
        it += 1
        if need_build:
            _, w = _loss(opts.loss, opts.loss_scale_px, r * r)
            w = w * S.weight
            H_cc, g_c, H_hh, g_h, F = _normal_equations(S, Jc, Jh, r, w)
            for p in pose_priors:
                p.add_to(H_cc, g_c, st)
            H_hh = H_hh + prior_w * prior_mask
            g_h = g_h + prior_w * prior_mask * (st.heights - heights0)
            schur = _Schur(S.coupling, H_hh, g_h, F)
            need_build = False
        dc, dh, D_c, D_h = _damped_step(S, H_cc, g_c, H_hh, g_h, F, lam, schur)
        predicted = 0.5 * (
            lam * (dc @ (D_c * dc) + dh @ (D_h * dh)) - (g_c @ dc + g_h @ dh)
        )
        trial = _apply(S, st, dc, dh)
        r_t, _, _ = _evaluate(S, trial, jac=False)
        c_t = cost_of(r_t, trial)
        x_norm = np.sqrt(
            np.sum(st.c[S.active_images] ** 2)
            + sum(float(p @ p) for p in st.params)
            + float(st.heights @ st.heights)
        )
        step_norm = np.sqrt(dc @ dc + dh @ dh)
        small_step = step_norm <= opts.parameter_tolerance * (
            x_norm + opts.parameter_tolerance
        )
        logger.debug(
            "  try lam %.3g pred %.6g cost %.9g trial %.9g", lam, predicted, cost, c_t
        )
        if predicted <= max(opts.function_tolerance * cost, 1e-30 * len(r)):
            termination, converged = "function_tolerance (predicted decrease)", True
            break
        rho = (cost - c_t) / predicted if np.isfinite(c_t) else -np.inf
        if rho > 1e-3:
            decrease = cost - c_t
            st, cost, r = trial, c_t, r_t
            n_ok += 1
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            lam = max(lam, 1e-16)
            nu = 2.0
            logger.debug("it %d cost %.9g lambda %.2g", it, cost, lam)
            if decrease <= opts.function_tolerance * (cost + decrease):
                termination, converged = "function_tolerance", True
                break
            if small_step:
                termination, converged = "parameter_tolerance", True
                break
            r, Jc, Jh = _evaluate(S, st, jac=True)
            need_build = True
        else:
            if small_step:
                termination, converged = "parameter_tolerance", True
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                termination = "no further decrease (damping > 1e16)"
                break

    final_rmse = rmse(r)
    precision, variance_factor = {}, float("nan")
    if opts.compute_precision and S.n_red > opts.precision_max_camera_params:
        logger.info(
            "bundle: no precision for %d camera parameters (more than %d)",
            S.n_red,
            opts.precision_max_camera_params,
        )
    elif opts.compute_precision and len(r):
        r, Jc, Jh = _evaluate(S, st, jac=True)
        _, w = _loss(opts.loss, opts.loss_scale_px, r * r)
        w = w * S.weight
        H_cc = _normal_equations(S, Jc, Jh, r, w)[0]
        for p in pose_priors:
            p.add_to(H_cc, np.zeros(S.n_red), st)
        offset_w = 1.0 / opts.horizontal_offset_sigma_m**2
        cov = _camera_covariance(S, H_cc, Jc, Jh, w, prior_w * prior_mask, offset_w)
        redundancy = (
            len(r)
            + int(prior_mask.sum())
            + len(S.A)
            - S.n_red
            - S.n_heights
            - S.n_offsets
        )
        redundancy += 3 * len(S.active_images) * len(pose_priors)
        if redundancy > 0:
            variance_factor = float(np.sum(w * r * r)) / redundancy
            variance_factor += 2.0 * sum(p.cost(st) for p in pose_priors) / redundancy
            dh = (st.heights - heights0)[prior_mask]
            variance_factor += prior_w * float(dh @ dh) / redundancy
            precision = _image_precision(S, st, variance_factor * cov)
    r_problem = np.empty_like(r)
    r_problem[S.order] = r
    cameras = {}
    for s, cid in enumerate(S.camera_ids):
        c0 = P.cameras[cid]
        cameras[cid] = Camera(c0.model, c0.width, c0.height, st.params[s], c0.camera_id)
    for cid, cam in P.cameras.items():
        cameras.setdefault(
            cid, Camera(cam.model, cam.width, cam.height, cam.params, cam.camera_id)
        )
    poses = {
        iid: Pose.from_center(st.R[k], st.c[k]) for k, iid in enumerate(P.image_ids)
    }
    summary = BundleSummary(
        initial_cost=initial_cost,
        final_cost=cost,
        initial_rmse_vertical_px=initial_rmse[0],
        final_rmse_vertical_px=final_rmse[0],
        initial_rmse_horizontal_px=initial_rmse[1],
        final_rmse_horizontal_px=final_rmse[1],
        num_iterations=it,
        num_successful_steps=n_ok,
        time_s=time.perf_counter() - t0,
        termination=termination,
        converged=converged,
        components=S.components,
        num_vertical=S.nv,
        num_horizontal=S.nh,
        num_heights=S.n_heights,
        num_camera_params=S.n_red,
    )
    logger.info(summary.brief())
    if S.shift_col >= 0:
        logger.info(
            "bundle: the priors' centres sit %.3f m east, %.3f m north of the map's"
            " frame",
            -st.shift[0],
            -st.shift[1],
        )
    return BundleResult(
        cameras=cameras,
        poses=poses,
        facade_heights=st.heights[:nJ].copy(),
        corner_heights=st.heights[nJ:].copy() if free else P.corner_heights.copy(),
        vertical_residuals_px=r_problem[: S.nv],
        horizontal_residuals_px=r_problem[S.nv :],
        summary=summary,
        image_precision_px={
            iid: precision.get(k, float("nan")) for k, iid in enumerate(P.image_ids)
        },
        variance_factor=variance_factor,
        prior_offset_m=-st.shift.copy() if S.shift_col >= 0 else None,
    )


def _normal_equations(S: _Setup, Jc, Jh, r, w):
    """Blocks of J^T W J and J^T W r: dense camera block, diagonal heights,
    and the (Nh, L) blocks F of the coupling E (rows with a height; products
    with E by :class:`_Coupling`)."""
    n = S.n_red + 1
    H_cc = np.zeros((n, n))
    g_c = np.zeros(n)
    wJ = Jc * w[:, None]
    for a, b, cols in S.image_runs:
        H_cc[np.ix_(cols, cols)] += Jc[a:b].T @ wJ[a:b]
        g_c[cols] += wJ[a:b].T @ r[a:b]
    m = S.has_h
    H_hh = np.bincount(S.hidx[m], (w * Jh * Jh)[m], S.n_heights)
    g_h = np.bincount(S.hidx[m], (w * Jh * r)[m], S.n_heights)
    F = np.multiply(Jc, (w * Jh)[:, None], order="C")
    if S.h_runs != [(0, len(r))]:
        F = np.concatenate([F[a:b] for a, b in S.h_runs] or [F[:0]])
    return H_cc[:-1, :-1], g_c[:-1], H_hh, g_h, F


class _Schur:
    """``E^T Dinv E`` and ``E^T Dinv g_h``, ``Dinv = (H_hh + lam D_h)^-1``,
    for any damping ``lam`` of one build.

    Where the height block's damping is its own diagonal (``D_h = H_hh``,
    unclipped) they are ``E^T H_hh^-1 E / (1 + lam)`` and
    ``E^T H_hh^-1 g_h / (1 + lam)``: that part is formed once per
    linearisation, not once per trial step, from the blocks F per image pair
    (:class:`_Coupling`); the clipped rows (few) are added per step.
    """

    def __init__(self, coupling: _Coupling, H_hh: np.ndarray, g_h, F) -> None:
        own = (H_hh >= 1e-6) & (H_hh <= 1e32)  # where clip(H_hh) = H_hh
        scale = np.zeros(len(H_hh))
        scale[own] = 1.0 / np.sqrt(H_hh[own])
        self.base = coupling.gram(F, scale)
        self.base_rhs = coupling.rmatvec(F, scale * scale * g_h)
        self.rest = np.flatnonzero(~own)
        self.E_rest = coupling.dense_rows(F, self.rest) if len(self.rest) else None

    def at(self, H_hh: np.ndarray, g_h: np.ndarray, lam: float):
        """(C, C) ``E^T Dinv E`` and (C,) ``E^T Dinv g_h`` at damping ``lam``."""
        out, rhs = self.base / (1.0 + lam), self.base_rhs / (1.0 + lam)
        if self.E_rest is not None:
            h = H_hh[self.rest]
            dinv = 1.0 / (h + lam * np.clip(h, 1e-6, 1e32))
            out = out + self.E_rest.T @ (dinv[:, None] * self.E_rest)
            rhs = rhs + (dinv * g_h[self.rest]) @ self.E_rest
        return out, rhs


def _damped_step(S: _Setup, H_cc, g_c, H_hh, g_h, F, lam, schur: _Schur):
    """Solve the damped normal equations by the Schur complement on the heights."""
    D_c = np.clip(np.diag(H_cc), 1e-6, 1e32)
    D_h = np.clip(H_hh, 1e-6, 1e32)
    dinv = 1.0 / (H_hh + lam * D_h)
    if S.n_heights:
        reduced, coupled = schur.at(H_hh, g_h, lam)
        rhs = -g_c + coupled
    else:
        reduced = 0.0
        rhs = -g_c
    A_red = H_cc - reduced
    A_red[np.diag_indices_from(A_red)] += lam * D_c
    ng = len(S.A)
    if ng:
        n = S.n_red
        kkt = np.zeros((n + ng, n + ng))
        kkt[:n, :n] = A_red
        kkt[:n, n:] = S.A.T
        kkt[n:, :n] = S.A
        sol = np.linalg.solve(kkt, np.concatenate([rhs, np.zeros(ng)]))
        dc = sol[:n]
    else:
        dc = np.linalg.solve(A_red, rhs)
    dh = -dinv * (g_h + S.coupling.matvec(F, dc)) if S.n_heights else np.zeros(0)
    return dc, dh, D_c, D_h


class _PosePrior:
    """An observed pose part: 3 rows ``errors(st) / sigma`` per active image
    (``k``), weight ``w = 1 / sigma^2``."""

    k: np.ndarray
    w: float

    def errors(self, st: _State) -> np.ndarray:
        raise NotImplementedError

    def cost(self, st: _State) -> float:
        e = self.errors(st)
        return 0.5 * self.w * float(np.sum(e * e))


class _AttitudePrior(_PosePrior):
    """Each active image's rotation observed: ``e = Log(R R_prior^T) / sigma``
    (3 rows, radians over radians), linearised in the solver's increment
    ``R <- Exp(omega) R`` as ``d e / d omega = I / sigma`` (exact at e = 0;
    the cost is evaluated exactly, so LM stays correct)."""

    def __init__(self, S: _Setup, prior: np.ndarray, sigma_rad: float) -> None:
        self.k = S.active_images  # (K',) slots of the images with rows
        self.cols = S.pose_col[self.k][:, None] + np.arange(3)  # (K', 3)
        self.prior = prior[self.k]  # (K', 3, 3)
        self.w = 1.0 / sigma_rad**2

    @classmethod
    def of(cls, P: BundleProblem, S: _Setup, opts: BundleOptions):
        if opts.rotation_prior_sigma_deg is None or P.prior_rotations is None:
            return None
        prior = np.stack([np.asarray(P.prior_rotations[i], float) for i in P.image_ids])
        return cls(S, prior, np.deg2rad(opts.rotation_prior_sigma_deg))

    def errors(self, st: _State) -> np.ndarray:
        """(K', 3) rotation vectors of R R_prior^T, radians."""
        R = st.R[self.k] @ np.transpose(self.prior, (0, 2, 1))
        return Rotation.from_matrix(R).as_rotvec()

    def add_to(self, H_cc: np.ndarray, g_c: np.ndarray, st: _State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        H_cc[self.cols, self.cols] += self.w
        np.add.at(g_c, self.cols, self.w * self.errors(st))


class _CentrePrior(_PosePrior):
    """Each active image's camera centre observed: ``e = (c - c_prior - s) /
    sigma`` (3 rows, metres over metres), ``s`` the priors' horizontal
    offset (held at zero unless ``S.shift_col``); linear in the solver's
    increments ``c <- c + dc``, ``s <- s + ds``."""

    def __init__(self, S: _Setup, prior: np.ndarray, sigma_m: float) -> None:
        self.k = S.active_images
        self.cols = S.pose_col[self.k][:, None] + np.arange(3, 6)  # (K', 3)
        self.prior = prior[self.k]  # (K', 3)
        self.w = 1.0 / sigma_m**2
        self.shift_col = S.shift_col

    @classmethod
    def of(cls, P: BundleProblem, S: _Setup, opts: BundleOptions):
        if opts.position_prior_sigma_m is None or P.prior_centers is None:
            return None
        prior = np.stack([np.asarray(P.prior_centers[i], float) for i in P.image_ids])
        return cls(S, prior, opts.position_prior_sigma_m)

    def errors(self, st: _State) -> np.ndarray:
        """(K', 3) centre minus offset prior, metres."""
        e = st.c[self.k] - self.prior
        e[:, :2] -= st.shift
        return e

    def add_to(self, H_cc: np.ndarray, g_c: np.ndarray, st: _State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        e = self.errors(st)
        H_cc[self.cols, self.cols] += self.w
        np.add.at(g_c, self.cols, self.w * e)
        if self.shift_col >= 0:  # d e / d s = -(I2 over a zero row)
            s = self.shift_col + np.arange(2)
            H_cc[s, s] += self.w * len(self.k)
            for j in range(2):
                H_cc[self.cols[:, j], s[j]] -= self.w
                H_cc[s[j], self.cols[:, j]] -= self.w
            g_c[s] -= self.w * e[:, :2].sum(axis=0)


def _camera_covariance(
    S: _Setup, H_cc, Jc, Jh, w, height_prior: np.ndarray, offset_w: float
) -> np.ndarray:
    """(n_red, n_red) cofactor matrix of the camera block at the optimum.

    The point unknowns are eliminated (undamped Schur complement): each
    height, and with it, where its rows have an offset direction
    (``S.offset_dir``), the anchor's offset along it (prior weight
    ``offset_w``): one 2 x 2 block per height. The datum is the gauge: the
    camera block of the inverse of ``[[A_red, A^T], [A, 0]]`` is the
    cofactor matrix of the gauge-constrained solution; times the variance
    factor, its covariance. NaN where it is singular.

    Parameters
    ----------
    H_cc : (n_red, n_red) camera block of ``J^T W J``.
    Jc : (N, L) camera Jacobian; ``Jh`` (N,) height Jacobian; ``w`` (N,)
        weights; ``height_prior`` (n_heights,) prior weight per height.
    """
    n, nh, L = S.n_red, S.n_heights, S.L
    A_red = H_cc.copy()
    m = S.has_h
    if nh and m.any():
        hid, wm, jh = S.hidx[m], w[m], Jh[m]
        # d r / d offset = d r / d (x, y) . dir = -(d r / d centre_xy) . dir
        jd = -np.einsum("ij,ij->i", Jc[m, 3:5], S.offset_dir[m])
        has_d = np.bincount(hid, np.any(S.offset_dir[m] != 0, axis=1), nh) > 0
        a = np.bincount(hid, wm * jh * jh, nh) + height_prior
        b = np.bincount(hid, wm * jh * jd, nh)
        c = np.bincount(hid, wm * jd * jd, nh) + np.where(has_d, offset_w, 1.0)
        det = a * c - b * b
        ok = det > 0  # a height without information couples nothing
        # Cholesky factor of each block's inverse [[c, -b], [-b, a]] / det,
        # so that E^T inv E = G G^T with one sparse G: two columns per height.
        l11 = np.sqrt(np.where(ok, c / np.where(ok, det, 1.0), 0.0))
        l21 = np.where(ok, -b / np.where(ok, det, 1.0), 0.0) / np.where(ok, l11, 1.0)
        l22 = np.sqrt(np.where(ok, 1.0 / np.where(ok, c, 1.0), 0.0))
        vals = np.concatenate(
            [
                Jc[m] * (wm * (jh * l11[hid] + jd * l21[hid]))[:, None],
                Jc[m] * (wm * jd * l22[hid])[:, None],
            ]
        ).ravel()
        rows = np.tile(S.cols[m].ravel(), 2)  # camera columns, padding n
        cols = np.repeat(np.r_[hid, hid + nh], L)
        G = sp.csr_matrix((vals, (rows, cols)), (n + 1, 2 * nh))
        A_red -= (G @ G.T).toarray()[:n, :n]
    ng = len(S.A)
    # Jacobi scaling: the columns (radians, metres, pixels, distortion) differ
    # by orders of magnitude; scaled, the condition number is the geometry's.
    d = np.sqrt(np.clip(np.diag(A_red), 0.0, None))
    if not np.all(d > 0):
        return np.full((n, n), np.nan)  # a direction without any observation
    kkt = np.zeros((n + ng, n + ng))
    kkt[:n, :n] = A_red / np.outer(d, d)
    kkt[:n, n:] = (S.A / d).T
    kkt[n:, :n] = S.A / d
    try:
        inv_kkt = np.linalg.inv(kkt)
    except np.linalg.LinAlgError:
        return np.full((n, n), np.nan)
    return inv_kkt[:n, :n] / np.outer(d, d)


def _image_jacobians(S: _Setup, st: _State):
    """Per active image slot k: ``(k, J, cols)``, J (n, 2, 6 + q) the
    Jacobian of the projections of its rows' world points (map corners,
    facade anchors at their heights) by its pose (rotation increment,
    centre) and its camera's q refined intrinsics, cols their global
    columns in the camera block."""
    h_all = st.heights[np.maximum(S.hidx, 0)] if S.n_heights else S.zfix
    height = np.where(S.has_h, h_all, S.zfix)
    for a, b, cols in S.image_runs:
        k = int(S.img[a])
        slot = int(S.img_cam[k])
        basis = S.refined[slot]
        X = np.column_stack([S.xy[a:b], height[a:b]])
        Xc = (X - st.c[k]) @ st.R[k].T  # (n, 3)
        model = S.camera_model[slot]
        _, d_pt, d_par = res.project_with_jacobian(model, st.params[slot], Xc)
        J = np.concatenate(
            [
                -d_pt @ skew(Xc),  # R <- Exp(omega) R
                -d_pt @ st.R[k],  # c <- c + dc
                d_par @ basis,
            ],
            axis=2,
        )
        yield k, J, cols[: 6 + basis.shape[1]]


def _image_precision(S: _Setup, st: _State, cov: np.ndarray) -> dict[int, float]:
    """Per active image slot: RMS over its rows' world points of the
    standard deviation (px, 2D) of their projection, from ``cov`` of its
    pose and its camera's refined intrinsics (:func:`_image_jacobians`)."""
    out: dict[int, float] = {}
    for k, J, cols in _image_jacobians(S, st):
        C = cov[np.ix_(cols, cols)]
        var = np.einsum("npi,ij,npj->n", J, C, J)
        out[k] = float(np.sqrt(np.mean(var))) if np.all(np.isfinite(var)) else np.nan
    return out


def _apply(S: _Setup, st: _State, dc: np.ndarray, dh: np.ndarray) -> _State:
    """New state: R <- Exp(omega) R, c <- c + dc, params += d, heights += dh."""
    new = st.copy()
    k = S.active_images
    blocks = dc[S.pose_col[k][:, None] + np.arange(6)]  # (K_active, 6)
    new.R[k] = rotation_exp(blocks[:, :3]) @ st.R[k]
    new.c[k] = st.c[k] + blocks[:, 3:]
    for s, basis in enumerate(S.refined):
        if basis.shape[1]:
            new.params[s] += basis @ dc[S.intr_col[s] + np.arange(basis.shape[1])]
    new.heights = st.heights + dh
    if S.shift_col >= 0:
        new.shift = st.shift + dc[S.shift_col : S.shift_col + 2]
    return new
