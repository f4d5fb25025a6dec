"""The bundle block adjustment of the second workflow (MetropoGIS 3.5).

After the similarity, the whole block is adjusted at once: the SfM tracks as
reprojection residuals through the model's camera models (Cauchy loss on
each observation's 2D error), the control points as observed 3D points (a
prior on each coordinate weighted by its stated accuracy; a 2D point's
height is free) AND through their image observations (they are tracks of
the model), and each image's vertical vanishing point as an observation of
its camera's vertical (two rows: the world's down as the camera sees it
against the VP's direction through the camera's CURRENT pinhole part, so
that the VP moves with a refined principal point, weighted by its sd). The
principal point and the distortion are refined: an SfM model's lens is what
limits the similarity alone (Herz-Jesu: the principal point 8-9 px off moved
the cameras ~9 cm). The focal length is held by default: with two or three
control points it trades against the cameras' distance (an SfM-like paper
block: centres 0.33 m -> 2.1 m with it refined, 0.50 m without; Herz-Jesu
0.031 -> 0.024 m).

Two solvers of the same problem (``BlockAdjustmentOptions.solver``):
"obliq", the project's bundle (:mod:`obliq_colmap.bundle`: the tracks as
tie points eliminated by their 3x3 blocks, the control points' coordinates
as rows on those blocks; :mod:`.block_bundle`), the default; "ceres",
pycolmap's Ceres adjuster with pyceres cost functions for the priors, the
VPs, the map rows, the facade rows and the automatic mode's gauge
(:mod:`.block_ceres`),
kept as the check. The obliq solver also returns each camera's pose
covariance (:class:`BlockUncertainty`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pycolmap

from .facade_rows import outlier_free
from .map_rows import MapRows

logger = logging.getLogger(__name__)

#: ``BlockAdjustmentOptions.solver`` (``--block_adjustment_solver``).
BLOCK_SOLVERS = ("obliq", "ceres")


@dataclass(kw_only=True)
class BlockAdjustmentOptions:
    """What the block adjustment refines, how it weighs the tracks and which
    solver runs it."""

    refine_focal_length: bool = False  # see the module docstring
    refine_principal_point: bool = True
    refine_extra_params: bool = True
    #: robust loss of the track residuals (Cauchy), pixels
    loss_scale_px: float = 1.0
    #: floor of a VP's sd, degrees (stage 1's formal sd can be tiny)
    min_vertical_sd_deg: float = 0.02
    max_num_iterations: int = 100
    #: stop when an accepted step lowers the cost by less than this fraction
    #: (Ceres' default; both solvers)
    function_tolerance: float = 1e-6
    #: "obliq" (the project's bundle) or "ceres" (pycolmap + pyceres)
    solver: str = "obliq"
    #: the map's corner lines as rows where a map is given (stage 2's inlier
    #: pairs, :mod:`.map_rows`; both solvers): in the automatic mode they
    #: hold the block's datum horizontally (no control points)
    map_rows: bool = True
    #: a priori sd of a map row (px; register's ``vertical_sigma_px``: the
    #: map's vertex noise) and its robust loss's scale is ``loss_scale_px``;
    #: None: 1 px, or for level cameras the map's noise at their pairs'
    #: median range (the automatic mode's block placement)
    map_sigma_px: float | None = None
    #: each map row's line the segment's own fit (not the line through its
    #: image's VP that stage 2 matched; :func:`.map_rows.image_pairs`):
    #: through the VP the 3-point paper block's tilt went 0.017 -> 0.029 deg
    #: with the rows, with their own fits to 0.008 deg (journal, 2026-12-06)
    map_measured_directions: bool = True
    #: rows farther than this from their lines before the adjustment are
    #: left out (px)
    map_gate_px: float = 5.0
    #: the map's stated vertex accuracy (m, each axis): in the adjustment's
    #: precision every map corner's offset is an unknown with this sd, which
    #: all its rows share (the solve keeps the corners); None: the corners
    #: known exactly
    map_vertex_sigma_m: float | None = 0.15
    #: with the map rows, the map's facade edges (horizontal edges on the
    #: walls stage 2 registered, matched across the images into tracks of
    #: one height each, :mod:`.facade_rows`) as rows too (both solvers)
    facade_rows: bool = True
    #: the vertical datum where no control point holds it (the automatic
    #: mode): None, the block's mean camera height held where the automatic
    #: mode put it (from the priors' heights; the bundle's gauge row); a
    #: number, each camera centre observed at the priors' with this sd (m)
    #: and one horizontal offset estimated. The priors' 5 m height noise
    #: then tilts the block (paper seed 2: 0.021 deg with 50 m, 0.034 deg
    #: with 5 m, 0.19 deg with 1 m; journal, 2026-12-06)
    prior_center_sigma_m: float | None = None
    #: each camera's pose covariance from the adjustment's cofactor matrix
    #: (obliq solver: :class:`BlockUncertainty`)
    covariance: bool = True

    def __post_init__(self) -> None:
        if not (
            (self.map_sigma_px is None or self.map_sigma_px > 0)
            and self.map_gate_px > 0
        ):
            raise ValueError("map_sigma_px and map_gate_px must be > 0")
        if self.map_vertex_sigma_m is not None and not self.map_vertex_sigma_m > 0:
            raise ValueError("map_vertex_sigma_m must be > 0 or None")
        if self.prior_center_sigma_m is not None and not self.prior_center_sigma_m > 0:
            raise ValueError("prior_center_sigma_m must be > 0 or None")
        if self.solver not in BLOCK_SOLVERS:
            raise ValueError(
                f"solver={self.solver!r}; allowed: {', '.join(BLOCK_SOLVERS)}"
            )


def map_row_weighting(options: BlockAdjustmentOptions) -> tuple[float, float]:
    """The map rows' a priori sd and their Cauchy scale (px), the same in
    both solvers: the sd ``map_sigma_px`` (1 px by default), the scale at
    least that sd (the bundle's loss keeps its scale in raw px; a level
    camera's rows at 6 px would all sit far out on a 1 px Cauchy)."""
    sigma = 1.0 if options.map_sigma_px is None else float(options.map_sigma_px)
    return sigma, max(float(options.loss_scale_px), sigma)


def facade_row_weighting(options: BlockAdjustmentOptions) -> tuple[float, float]:
    """The facade rows' a priori sd and their Cauchy scale (px), the same in
    both solvers: 1 px (their segments' noise; the bundle's
    ``horizontal_sigma_px``) and the map rows' scale."""
    return 1.0, map_row_weighting(options)[1]


def facade_outlier_round(
    map_rows: MapRows,
    image_ids,
    residuals_px: np.ndarray,
    heights: np.ndarray,
) -> MapRows:
    """``map_rows`` with its facade rows after one outlier round (both
    solvers, between their two solves): the rows of ``image_ids`` (as
    ``FacadeRows.select`` orders them, the order the solve had them in)
    without those :func:`.facade_rows.outlier_free` finds at the solve's
    (H,) residuals (px) and (J,) track heights."""
    solved = map_rows.facades.select(image_ids)
    kept = outlier_free(solved, residuals_px, heights)
    logger.info(
        "facade rows: %d of %d kept after the first solve", len(kept), len(solved)
    )
    return dataclasses.replace(map_rows, facades=kept)


@dataclass
class BlockUncertainty:
    """The adjusted block's a-posteriori precision (the project's bundle;
    :attr:`~obliq_colmap.bundle.BundleResult.pose_covariance`).

    pose_covariance : image_id -> (6, 6) covariance of (rotation increment
        omega, rad, ``R <- Exp(omega) R``; centre, m).
    image_precision_px : image_id -> predicted sd (px) of the projections of
        its map rows' points (NaN for an image without map rows).
    variance_factor : a-posteriori variance of unit weight (tracks at 1 px,
        map rows at their sd, control points at their stated sigmas), pooled.
    variance_components : group name -> (factor, redundancy): each
        observation group's own (:mod:`obliq_colmap.bundle.components`); the
        covariance is their sandwich.
    """

    pose_covariance: dict[int, np.ndarray]
    image_precision_px: dict[int, float]
    variance_factor: float
    variance_components: dict[str, tuple[float, float]] = field(default_factory=dict)


@dataclass
class BlockAdjustmentSummary:
    """What one adjustment did (costs are ``1/2 sum rho``, the same in both
    solvers for the same state)."""

    initial_cost: float
    final_cost: float
    iterations: int
    num_control_rows: int
    num_vertical_rows: int
    termination: str
    #: corner-to-line rows of the map (two per stage-2 inlier pair)
    num_map_rows: int = 0
    #: facade rows (one per observation of a facade track) and their tracks
    num_facade_rows: int = 0
    num_facade_tracks: int = 0
    solver: str = "obliq"
    #: wall time of the whole adjustment (problem built, solved, written back), s
    time_s: float = math.nan
    #: the block's covariance where computed (not in :meth:`report`)
    uncertainty: BlockUncertainty | None = field(default=None, repr=False)

    def report(self) -> dict[str, Any]:
        """The summary for report.json (without the covariance, which has
        its own section: :func:`.uncertainty.block_uncertainty_report`)."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name != "uncertainty"
        }


@dataclass
class VerticalRow:
    """One image's vertical VP as the adjustment observes it.

    vp : (3,) unit homogeneous VP in the camera's undistorted pixels (its
        pinhole part at the start).
    sd_rad : its sd as an angle (floored).
    """

    vp: np.ndarray
    sd_rad: float


def vertical_rows(
    rec: pycolmap.Reconstruction,
    verticals: dict[int, tuple[np.ndarray, float]],
    min_sd_deg: float,
) -> dict[int, VerticalRow]:
    """Each image's observed down direction (camera frame, through its
    camera's pinhole at the start) back to the VP pixel it was measured as:
    ``v = K d``, the observation both solvers take through the current K."""
    from obliq_colmap.geometry import calibration_matrix

    rows = {}
    for image_id, (down, sd_deg) in verticals.items():
        if image_id not in rec.images or not rec.images[image_id].has_pose:
            continue
        cam = rec.images[image_id].camera
        K = calibration_matrix(cam.model.name, np.asarray(cam.params, float))
        v = K @ (np.asarray(down, float) / np.linalg.norm(down))
        sd = math.radians(max(float(sd_deg), min_sd_deg))
        rows[image_id] = VerticalRow(v / np.linalg.norm(v), sd)
    return rows


def adjust_block(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, tuple[np.ndarray, float]],
    options: BlockAdjustmentOptions | None = None,
    map_rows: MapRows | None = None,
    prior_centers: dict[int, np.ndarray] | None = None,
) -> BlockAdjustmentSummary:
    """Adjust ``rec`` in place (every registered image, camera and point).

    control_point_ids : point3D_id -> ((3,) given position in rec's frame,
        (3,) sigmas in m, inf for a free axis).
    verticals : image_id -> ((3,) observed down direction in the camera
        frame, through the camera's pinhole at the start, its sd in deg).
    map_rows : the map's corner-to-line rows (:mod:`.map_rows`), used where
        ``options.map_rows`` (both solvers).
    prior_centers : image_id -> (3,) a camera centre from the priors (rec's
        frame), each observed at ``options.prior_center_sigma_m`` (where
        not None; obliq solver only) with one horizontal offset estimated.
        Without control points and without them, the block's mean camera
        height is held (both solvers).
    """
    options = options or BlockAdjustmentOptions()
    t0 = time.perf_counter()
    rows = vertical_rows(rec, verticals, options.min_vertical_sd_deg)
    if not options.map_rows:
        map_rows = None
    if options.solver == "ceres":
        use_priors = bool(prior_centers) and options.prior_center_sigma_m is not None
        if use_priors:
            logger.warning(
                "block adjustment (ceres): the priors' centres are the obliq "
                "solver's only; the mean camera height is held instead"
            )
        from .block_ceres import adjust_block_ceres

        # the obliq solver's gauge without control points (block_bundle)
        hold = not control_point_ids
        summary = adjust_block_ceres(
            rec, control_point_ids, rows, options, map_rows, hold
        )
    else:
        from .block_bundle import adjust_block_bundle

        summary = adjust_block_bundle(
            rec, control_point_ids, rows, options, map_rows, prior_centers
        )
    summary.time_s = time.perf_counter() - t0
    return summary
