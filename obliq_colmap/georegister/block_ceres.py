"""The bundle block adjustment of the second workflow (MetropoGIS 3.5).

After the similarity, the whole block is adjusted at once: the SfM tracks as
reprojection residuals through pycolmap's camera models (the model's own
points and observations, pycolmap's Ceres bundle adjuster), the control
points as observed 3D points (a prior on each coordinate weighted by its
stated accuracy; a 2D point's height is free) AND through their image
observations (they are tracks of the model), and each image's vertical
vanishing point as an observation of its camera's vertical (two rows: the
world's down as the camera sees it against stage 1's direction, weighted by
its sd). The principal point and the distortion are refined: an SfM model's
lens is what limits the similarity alone (Herz-Jesu: the principal point
8-9 px off moved the cameras ~9 cm). The focal length is held by default:
with two or three control points it trades against the cameras' distance
(an SfM-like paper block: centres 0.33 m -> 2.1 m with it refined, 0.50 m
without; Herz-Jesu 0.031 -> 0.024 m).

The prior and the vertical rows are few (one per control point, one per
image) and are Python cost functions; the tracks, by far the most rows, are
pycolmap's C++ costs. The solve is ``pyceres.solve``, which releases the GIL.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pyceres
import pycolmap

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class BlockAdjustmentOptions:
    """What the block adjustment refines and how it weighs the tracks."""

    refine_focal_length: bool = False  # see the module docstring
    refine_principal_point: bool = True
    refine_extra_params: bool = True
    #: robust loss of the track residuals (Cauchy), pixels
    loss_scale_px: float = 1.0
    #: floor of a VP's sd, degrees (stage 1's formal sd can be tiny)
    min_vertical_sd_deg: float = 0.02
    max_num_iterations: int = 100


@dataclass
class BlockAdjustmentSummary:
    """What one adjustment did."""

    initial_cost: float
    final_cost: float
    iterations: int
    num_control_rows: int
    num_vertical_rows: int
    termination: str


class PointPrior(pyceres.CostFunction):
    """``(X - X_given) / sigma`` per axis (sigma inf: no row weight)."""

    def __init__(self, given: np.ndarray, sigma: np.ndarray) -> None:
        super().__init__()
        self.given = np.asarray(given, float)
        self.w = np.where(np.isfinite(sigma), 1.0 / np.asarray(sigma, float), 0.0)
        self.given = np.where(np.isfinite(self.given), self.given, 0.0)
        self.set_num_residuals(3)
        self.set_parameter_block_sizes([3])

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
        x = np.asarray(parameters[0])
        residuals[:] = self.w * (x - self.given)
        if jacobians is not None and jacobians[0] is not None:
            jacobians[0][:] = np.diag(self.w).ravel()
        return True


def _rotation(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a quaternion (x, y, z, w), normalised."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


class VerticalObservation(pyceres.CostFunction):
    """The world's down as the camera sees it, ``R (0, 0, -1)``, against the
    observed direction d (unit, camera frame): its two components across d
    (in radians for small angles) over the sd. On the 7-vector pose block
    ``[qx qy qz qw tx ty tz]`` of pycolmap (rig = camera)."""

    def __init__(self, direction: np.ndarray, sd_rad: float) -> None:
        super().__init__()
        d = np.asarray(direction, float)
        self.d = d / np.linalg.norm(d)
        a = np.cross(self.d, [1.0, 0, 0] if abs(self.d[0]) < 0.9 else [0, 1.0, 0])
        a /= np.linalg.norm(a)
        self.basis = np.stack([a, np.cross(self.d, a)]) / sd_rad  # (2, 3)
        self.set_num_residuals(2)
        self.set_parameter_block_sizes([7])

    def _r(self, q: np.ndarray) -> np.ndarray:
        return self.basis @ (_rotation(q) @ np.array([0.0, 0.0, -1.0]))

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
        p = np.asarray(parameters[0], float)
        residuals[:] = self._r(p[:4])
        if jacobians is not None and jacobians[0] is not None:
            J = np.zeros((2, 7))
            h = 1e-7
            for k in range(4):
                e = np.zeros(4)
                e[k] = h
                J[:, k] = (self._r(p[:4] + e) - self._r(p[:4] - e)) / (2 * h)
            jacobians[0][:] = J.ravel()
        return True


def adjust_block(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, tuple[np.ndarray, float]],
    options: BlockAdjustmentOptions | None = None,
) -> BlockAdjustmentSummary:
    """Adjust ``rec`` in place.

    control_point_ids : point3D_id -> ((3,) given position in rec's frame,
        (3,) sigmas in m, inf for a free axis).
    verticals : image_id -> ((3,) observed down direction in the camera
        frame, its sd in deg).
    """
    options = options or BlockAdjustmentOptions()
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = options.refine_focal_length
    ba.refine_principal_point = options.refine_principal_point
    ba.refine_extra_params = options.refine_extra_params
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = options.loss_scale_px
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba, config, rec)
    problem = adjuster.problem
    n_ctrl = 0
    for pid, (given, sigma) in control_point_ids.items():
        xyz = rec.points3D[pid].xyz
        if problem.has_parameter_block(xyz):
            problem.add_residual_block(PointPrior(given, sigma), None, [xyz])
            n_ctrl += 1
    n_vert = 0
    floor = np.radians(options.min_vertical_sd_deg)
    for image_id, (down, sd_deg) in verticals.items():
        frame = rec.frame(rec.images[image_id].frame_id)
        pose = frame.rig_from_world.params
        if not problem.has_parameter_block(pose):
            continue
        sd = max(np.radians(sd_deg), floor)
        problem.add_residual_block(VerticalObservation(down, sd), None, [pose])
        n_vert += 1
    solver = pyceres.SolverOptions()
    solver.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    solver.max_num_iterations = options.max_num_iterations
    solver.num_threads = 1
    summary = pyceres.SolverSummary()
    pyceres.solve(solver, problem, summary)
    logger.info(
        "block adjustment: cost %.4g -> %.4g in %d iterations (%d control "
        "points, %d verticals)",
        summary.initial_cost, summary.final_cost, summary.num_successful_steps,
        n_ctrl, n_vert,
    )  # fmt: skip
    del adjuster  # after the solve: the problem refers to rec's arrays
    return BlockAdjustmentSummary(
        initial_cost=float(summary.initial_cost),
        final_cost=float(summary.final_cost),
        iterations=int(summary.num_successful_steps + summary.num_unsuccessful_steps),
        num_control_rows=n_ctrl,
        num_vertical_rows=n_vert,
        termination=str(summary.termination_type),
    )
