"""The block adjustment in Ceres (``BlockAdjustmentOptions.solver="ceres"``):
the check of the project's solver on the same problem.

pycolmap's Ceres bundle adjuster on the model itself (the SfM tracks, C++
reprojection costs through its camera models, Cauchy loss), plus the few
rows it lacks as pyceres Python cost functions: a prior on each control
point's coordinates and each image's vertical VP. ``pyceres.solve``
releases the GIL.
"""

from __future__ import annotations

import logging

import numpy as np
import pyceres
import pycolmap

from obliq_colmap.geometry import (
    calibration_matrix,
    rotation_from_quat_xyzw,
    tangent_basis,
)

from .block import BlockAdjustmentOptions, BlockAdjustmentSummary, VerticalRow

logger = logging.getLogger(__name__)


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


class VerticalObservation(pyceres.CostFunction):
    """The world's down as the camera sees it, ``d = R (0, 0, -1)``, against
    the VP's direction ``m = +-normalise(K^-1 v)`` through the camera's
    current pinhole part: ``T (m x d) / sd`` (2 rows; T a tangent basis at
    the start's direction), as the project's
    :class:`~obliq_colmap.bundle.priors.VanishingPointObservation` with an
    isotropic covariance. On pycolmap's pose block ``[qx qy qz qw tx ty tz]``
    (rig = camera) and the camera's parameter block."""

    def __init__(self, row: VerticalRow, model: str, params: np.ndarray) -> None:
        super().__init__()
        self.v, self.model = row.vp, model
        self.T = tangent_basis(self._direction(params)).T / row.sd_rad  # (2, 3)
        self.set_num_residuals(2)
        self.set_parameter_block_sizes([7, len(params)])

    def _direction(self, params: np.ndarray) -> np.ndarray:
        u = np.linalg.solve(calibration_matrix(self.model, params), self.v)
        return u / np.linalg.norm(u)

    def _r(self, q: np.ndarray, params: np.ndarray) -> np.ndarray:
        d = rotation_from_quat_xyzw(q) @ np.array([0.0, 0.0, -1.0])
        m = self._direction(params)
        return self.T @ np.cross(m if m @ d >= 0 else -m, d)

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
        q = np.asarray(parameters[0], float)[:4]
        params = np.asarray(parameters[1], float)
        residuals[:] = self._r(q, params)
        if jacobians is None:
            return True
        # central differences: two rows per image, a few per solve
        if jacobians[0] is not None:
            J = np.zeros((2, 7))
            for k in range(4):
                e = np.zeros(4)
                e[k] = 1e-7
                J[:, k] = (self._r(q + e, params) - self._r(q - e, params)) / 2e-7
            jacobians[0][:] = J.ravel()
        if jacobians[1] is not None:
            J = np.zeros((2, len(params)))
            for k in range(len(params)):
                h = 1e-6 * max(1.0, abs(params[k]))
                e = np.zeros(len(params))
                e[k] = h
                J[:, k] = (self._r(q, params + e) - self._r(q, params - e)) / (2 * h)
            jacobians[1][:] = J.ravel()
        return True


def adjust_block_ceres(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, VerticalRow],
    options: BlockAdjustmentOptions,
) -> BlockAdjustmentSummary:
    """:func:`~obliq_colmap.georegister.block.adjust_block` in Ceres."""
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
    for image_id, row in verticals.items():
        image = rec.images[image_id]
        pose = rec.frame(image.frame_id).rig_from_world.params
        params = rec.cameras[image.camera_id].params
        if not problem.has_parameter_block(pose):
            continue
        cost = VerticalObservation(row, image.camera.model.name, np.array(params))
        problem.add_residual_block(cost, None, [pose, params])
        n_vert += 1
    solver = pyceres.SolverOptions()
    solver.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    solver.max_num_iterations = options.max_num_iterations
    solver.function_tolerance = options.function_tolerance
    solver.num_threads = 1
    summary = pyceres.SolverSummary()
    pyceres.solve(solver, problem, summary)
    logger.info(
        "block adjustment (ceres): cost %.6g -> %.6g in %d iterations (%d "
        "control points, %d verticals)",
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
        solver="ceres",
    )
