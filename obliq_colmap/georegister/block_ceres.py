"""The block adjustment in Ceres (``BlockAdjustmentOptions.solver="ceres"``):
the check of the project's solver on the same problem.

pycolmap's Ceres bundle adjuster on the model itself (the SfM tracks, C++
reprojection costs through its camera models, Cauchy loss), plus the rows
it lacks as pyceres Python cost functions: a prior on each control point's
coordinates, each image's vertical VP, the map's corner-to-line rows (one
block per image, :class:`MapLineRows`), the facade rows (one block per
image, :class:`FacadeRowsCost`, on one height block per facade track; two
solves around the obliq solver's outlier round) and, without control
points, the block's mean camera height held (:class:`MeanCameraHeight`,
the project's gauge as a stiff row). ``pyceres.solve`` releases the GIL.
The priors' centres (``prior_center_sigma_m``) are the obliq solver's only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pyceres
import pycolmap

from obliq_colmap.bundle.residuals import horizontal_residuals
from obliq_colmap.geometry import (
    calibration_matrix,
    rotation_from_quat_xyzw,
    skew,
    tangent_basis,
)

from .block import (
    BlockAdjustmentOptions,
    BlockAdjustmentSummary,
    VerticalRow,
    facade_outlier_round,
    facade_row_weighting,
    map_row_weighting,
)
from .facade_rows import FacadeRows
from .map_rows import MapRows

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


def quaternion_rotation_jacobian(q: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N, 3, 4) derivative of ``R(q) X`` by ``q = [x, y, z, w]`` (a unit
    quaternion, Eigen's formula ``X + 2 w (v x X) + 2 v x (v x X)``; exact
    along the sphere's tangent, all that Ceres' quaternion manifold uses).
    X: (N, 3)."""
    v, w = np.asarray(q[:3], float), float(q[3])
    X = np.asarray(X, float).reshape(-1, 3)
    n = len(X)
    J = np.empty((n, 3, 4))
    J[:, :, 3] = 2.0 * np.cross(v, X)
    # d/dv of 2 w (v x X) = -2 w [X]x; of 2 v x (v x X) = 2 (v.X I + v X^T - 2 X v^T)
    J[:, :, :3] = -2.0 * w * skew(X) + 2.0 * (
        (X @ v)[:, None, None] * np.eye(3)
        + v[None, :, None] * X[:, None, :]
        - 2.0 * X[:, :, None] * v[None, None, :]
    )
    return J


def _line_jacobian_by_point(
    camera: pycolmap.Camera, Xc: np.ndarray, n: np.ndarray
) -> np.ndarray:
    """(N, 3) derivative of ``n . img_from_cam(Xc)`` by the camera-frame
    point (central differences through pycolmap's camera model, vectorised
    over the rows; the step relative to the point's depth). Xc, n: (N, 3),
    (N, 2)."""
    h = 1e-6 * np.maximum(np.abs(Xc[:, 2]), 1e-3)
    out = np.empty((len(Xc), 3))
    for k in range(3):
        e = np.zeros_like(Xc)
        e[:, k] = h
        d = camera.img_from_cam(Xc + e) - camera.img_from_cam(Xc - e)
        out[:, k] = np.sum(n * d, axis=1) / (2.0 * h)
    return out


def robust_rows(
    r: np.ndarray, scale_px: float, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Raw rows ``r`` (px) to residuals whose squares are the bundle's cost
    of each, ``rho(r^2) / sigma^2`` with Cauchy's ``rho`` at ``scale_px``:
    ``sign(r) sqrt(rho(r^2)) / sigma``, and their derivatives by ``r``
    (``rho'(r^2) r / s``, 1 / sigma at r = 0). The robust loss inside the
    residual rather than a Ceres loss function, which acts on the norm of
    a whole residual block: one block per image keeps the Python callbacks
    to a few dozen per evaluation (one block per row: thousands). The
    cost, hence the optimum, is the bundle's; Ceres' Gauss-Newton model of
    it differs (no Triggs correction)."""
    b = float(scale_px) ** 2
    r2 = r * r
    s = np.sign(r) * np.sqrt(b * np.log1p(r2 / b))
    small = np.abs(r) < 1e-9
    f = np.where(small, 1.0, r / np.where(small, 1.0, s)) / (1.0 + r2 / b)
    return s / sigma_px, f / sigma_px


class MapLineRows(pyceres.CostFunction):
    """The map's corner-to-line rows of ONE image (:mod:`.map_rows`), as the
    project's bundle has them: each row ``r = n . pi(R X + t) + c`` (px, the
    fixed point ``X`` on the corner's vertical projected through the
    camera's model against the segment's unit line ``(n, c)``), its cost
    ``1/2 rho(r^2) / sigma^2`` with Cauchy's ``rho`` at ``scale`` px, the
    loss inside the residual (:func:`robust_rows`). On pycolmap's pose
    block ``[qx qy qz qw tx ty tz]`` and the camera's parameter block.
    """

    def __init__(
        self,
        X: np.ndarray,
        lines: np.ndarray,
        camera: pycolmap.Camera,
        sigma_px: float,
        scale_px: float,
    ) -> None:
        super().__init__()
        self.X = np.asarray(X, float).reshape(-1, 3)
        lines = np.asarray(lines, float).reshape(-1, 3)
        self.lines = lines / np.linalg.norm(lines[:, :2], axis=1)[:, None]
        # a copy whose params are set per evaluation
        self.camera = pycolmap.Camera(
            model=camera.model,
            width=camera.width,
            height=camera.height,
            params=np.array(camera.params),
        )
        self.sigma, self.scale = float(sigma_px), float(scale_px)
        self.set_num_residuals(len(self.X))
        self.set_parameter_block_sizes([7, len(camera.params)])

    def _rows(self, q, t, params) -> tuple[np.ndarray, np.ndarray]:
        """(N,) raw residuals r (px) and (N, 3) camera-frame points."""
        self.camera.params = params
        Xc = self.X @ rotation_from_quat_xyzw(q).T + t
        uv = self.camera.img_from_cam(Xc)
        return np.sum(self.lines[:, :2] * uv, axis=1) + self.lines[:, 2], Xc

    def raw_residuals(self, pose: np.ndarray, params: np.ndarray) -> np.ndarray:
        """(N,) the rows' distances (px) at a pose block and camera params."""
        pose = np.asarray(pose, float)
        return self._rows(pose[:4], pose[4:], np.asarray(params, float))[0]

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
        pose = np.asarray(parameters[0], float)
        q, t = pose[:4], pose[4:]
        params = np.asarray(parameters[1], float)
        r, Xc = self._rows(q, t, params)
        if not np.all(np.isfinite(r)):
            return False  # a point behind the camera: Ceres rejects the step
        residuals[:], f = robust_rows(r, self.scale, self.sigma)
        if jacobians is None:
            return True
        if jacobians[0] is not None:
            d_pt = _line_jacobian_by_point(self.camera, Xc, self.lines[:, :2])
            J = np.empty((len(r), 7))
            dq = quaternion_rotation_jacobian(q, self.X)  # (N, 3, 4)
            J[:, :4] = np.einsum("ni,nij->nj", d_pt, dq)
            J[:, 4:] = d_pt
            jacobians[0][:] = (J * f[:, None]).ravel()
        if jacobians[1] is not None:
            J = np.empty((len(r), len(params)))
            for k in range(len(params)):
                h = 1e-6 * max(1.0, abs(params[k]))
                e = np.zeros(len(params))
                e[k] = h
                up = self._rows(q, t, params + e)[0]
                down = self._rows(q, t, params - e)[0]
                J[:, k] = (up - down) / (2.0 * h)
            self.camera.params = params
            jacobians[1][:] = (J * f[:, None]).ravel()
        return True


def _pose_chain(q: np.ndarray, t: np.ndarray, d_pose: np.ndarray) -> np.ndarray:
    """(N, 7) derivative by pycolmap's pose block ``[q, t]`` of rows whose
    derivative by the bundle's pose parameters ``(omega, c)`` is ``d_pose``
    (N, 6): ``R <- Exp(omega) R`` and the centre ``c = -R^T t``. Along the
    quaternion's tangent (all that Ceres' manifold uses) ``dR = [omega]x R``
    with ``[omega]x = dR R^T``, and ``dc = -dR^T t``; ``dc / dt = -R^T``."""
    R = rotation_from_quat_xyzw(q)
    # dR[k][:, j] = d (R e_j) / d q_k
    dR = quaternion_rotation_jacobian(q, np.eye(3)).transpose(2, 1, 0)  # (4, 3, 3)
    M = dR @ R.T
    omega = 0.5 * np.stack(
        [M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]],
        axis=1,
    )  # (4, 3)
    dc = -np.einsum("kji,j->ki", dR, np.asarray(t, float))  # (4, 3)
    out = np.empty((len(d_pose), 7))
    out[:, :4] = d_pose[:, :3] @ omega.T + d_pose[:, 3:] @ dc.T
    out[:, 4:] = -d_pose[:, 3:] @ R.T
    return out


class FacadeRowsCost(pyceres.CostFunction):
    """The facade rows of ONE image (:mod:`.facade_rows`) as the project's
    bundle has them (``BundleProblem.horizontal_*``, its residual
    :func:`~obliq_colmap.bundle.residuals.horizontal_residuals`, called
    here): each row the point ``(anchor_xy, h)`` at its track's height over
    the track's anchor, projected through the camera's model, its distance
    (px) to the segment's line in raw pixels measured along the projected
    vertical (eq. 3's ``dist_z``), its cost ``1/2 rho(r^2) / sigma^2``
    with Cauchy's ``rho`` at ``scale`` px inside the residual
    (:func:`robust_rows`).

    Parameter blocks: pycolmap's pose ``[qx qy qz qw tx ty tz]``, the
    camera's parameters, then one height (1 double) per track the image
    sees, in the order of ``track`` (0 .. T-1 here). Analytic Jacobians:
    the bundle's by ``(omega, c)``, the parameters and the height, the pose
    chained to the block by :func:`_pose_chain`.
    """

    def __init__(
        self,
        anchor_xy: np.ndarray,
        track: np.ndarray,
        lines: np.ndarray,
        model: str,
        num_params: int,
        sigma_px: float,
        scale_px: float,
    ) -> None:
        super().__init__()
        self.anchor = np.asarray(anchor_xy, float).reshape(-1, 2)
        self.track = np.asarray(track, np.int64)
        self.lines = np.asarray(lines, float).reshape(-1, 3)
        self.model = model
        self.num_tracks = int(self.track.max()) + 1 if len(self.track) else 0
        self.sigma, self.scale = float(sigma_px), float(scale_px)
        self.set_num_residuals(len(self.track))
        self.set_parameter_block_sizes([7, num_params] + [1] * self.num_tracks)

    def _rows(self, pose, params, heights, jacobians: bool):
        """The bundle's rows (:class:`ResidualJacobians`) and the points'
        depths, at a pose block, camera params and (T,) heights."""
        pose = np.asarray(pose, float)
        R = rotation_from_quat_xyzw(pose[:4])
        c = -R.T @ pose[4:]
        X = np.c_[self.anchor, np.asarray(heights, float)[self.track]]
        n = len(X)
        rows = horizontal_residuals(
            self.model,
            np.asarray(params, float),
            np.broadcast_to(R, (n, 3, 3)),
            np.broadcast_to(c, (n, 3)),
            X,
            self.lines,
            jacobians,
        )
        return rows, (X - c) @ R[2]

    def raw_residuals(self, pose, params, heights) -> np.ndarray:
        """(N,) the rows' distances (px) at a pose block, camera params and
        (T,) heights of this image's tracks."""
        return self._rows(pose, params, heights, False)[0].residuals

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
        pose = np.asarray(parameters[0], float)
        heights = np.array([parameters[2 + k][0] for k in range(self.num_tracks)])
        rows, depth = self._rows(pose, parameters[1], heights, jacobians is not None)
        r = rows.residuals
        if not (np.all(depth > 0) and np.all(np.isfinite(r))):
            return False  # a point behind the camera: Ceres rejects the step
        residuals[:], f = robust_rows(r, self.scale, self.sigma)
        if jacobians is None:
            return True
        if jacobians[0] is not None:
            J = _pose_chain(pose[:4], pose[4:], rows.d_pose)
            jacobians[0][:] = (J * f[:, None]).ravel()
        if jacobians[1] is not None:
            jacobians[1][:] = (rows.d_params * f[:, None]).ravel()
        # each height's column: its track's rows, zero elsewhere
        dh = np.zeros((self.num_tracks, len(r)))
        dh[self.track, np.arange(len(r))] = rows.d_height * f
        for k in range(self.num_tracks):
            if jacobians[2 + k] is not None:
                jacobians[2 + k][:] = dh[k]
        return True


class MeanCameraHeight(pyceres.CostFunction):
    """``(mean_k c_z,k - h0) / sd`` over the given images' pose blocks, ``c =
    -R^T t``: the project's gauge ``component_mean_camera_height`` (a hard
    constraint there) as a stiff row, for the automatic mode without control
    points. At ``sd`` = 1e-4 m it held the test block's mean to 2e-9 m (the
    map rows' fixed heights pull on it only weakly) in 14 iterations; at
    1e-6 m Ceres needed 44, at 1e-9 m it stopped at 100 far from the
    optimum."""

    def __init__(self, num_images: int, h0: float, sd_m: float = 1e-4) -> None:
        super().__init__()
        self.k, self.h0, self.w = num_images, float(h0), 1.0 / sd_m
        self.set_num_residuals(1)
        self.set_parameter_block_sizes([7] * num_images)

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
        z, ez = 0.0, np.array([[0.0, 0.0, 1.0]])
        for k in range(self.k):
            p = np.asarray(parameters[k], float)
            R = rotation_from_quat_xyzw(p[:4])
            # c_z = -(R e_z) . t
            z -= float(R[:, 2] @ p[4:])
            if jacobians is not None and jacobians[k] is not None:
                J = np.empty(7)
                J[:4] = -p[4:] @ quaternion_rotation_jacobian(p[:4], ez)[0]
                J[4:] = -R[:, 2]
                jacobians[k][:] = self.w * J / self.k
        residuals[0] = self.w * (z / self.k - self.h0)
        return True


def _posed_images(problem: pyceres.Problem, rec: pycolmap.Reconstruction, image_ids):
    """(image_id, image, pose block, camera params block) of each distinct
    image of ``image_ids`` whose pose is in ``problem``."""
    for image_id in np.unique(image_ids):
        image = rec.images[int(image_id)]
        pose = rec.frame(image.frame_id).rig_from_world.params
        if problem.has_parameter_block(pose):
            yield image_id, image, pose, rec.cameras[image.camera_id].params


def _add_map_rows(
    problem: pyceres.Problem,
    rec: pycolmap.Reconstruction,
    rows: MapRows,
    options: BlockAdjustmentOptions,
) -> list[MapLineRows]:
    """One :class:`MapLineRows` block per image with rows (and a pose in
    the problem); the cost functions, kept alive with the problem."""
    sigma, scale = map_row_weighting(options)
    costs = []
    for image_id, image, pose, params in _posed_images(problem, rec, rows.image_id):
        sel = rows.image_id == image_id
        X = np.c_[rows.xy[sel], rows.height[sel]]
        cost = MapLineRows(X, rows.line[sel], image.camera, sigma, scale)
        problem.add_residual_block(cost, None, [pose, params])
        costs.append(cost)
    return costs


def _hold_mean_height(
    problem: pyceres.Problem, rec: pycolmap.Reconstruction
) -> MeanCameraHeight:
    """The mean camera height of the registered images held where it is."""
    ids = sorted(rec.reg_image_ids())
    poses = [rec.frame(rec.images[i].frame_id).rig_from_world.params for i in ids]
    h0 = float(np.mean([rec.images[i].projection_center()[2] for i in ids]))
    cost = MeanCameraHeight(len(ids), h0)
    problem.add_residual_block(cost, None, poses)
    return cost


@dataclass
class _FacadeBlocks:
    """The facade rows in one Ceres problem: one cost per image, one height
    block per track (kept alive with the problem)."""

    rows: FacadeRows
    costs: list[tuple[FacadeRowsCost, np.ndarray, list[np.ndarray]]]
    heights: list[np.ndarray]

    def heights_now(self) -> np.ndarray:
        return np.array([h[0] for h in self.heights])

    def raw_residuals(self, rec: pycolmap.Reconstruction) -> np.ndarray:
        """(H,) every row's distance (px) in the rows' order, at rec's
        cameras and poses and the height blocks."""
        out = np.full(len(self.rows), np.nan)
        for cost, sel, blocks in self.costs:
            image = rec.images[int(self.rows.image_id[sel[0]])]
            pose = rec.frame(image.frame_id).rig_from_world.params
            params = rec.cameras[image.camera_id].params
            out[sel] = cost.raw_residuals(pose, params, [b[0] for b in blocks])
        return out


def _add_facade_rows(
    problem: pyceres.Problem,
    rec: pycolmap.Reconstruction,
    rows: FacadeRows,
    options: BlockAdjustmentOptions,
) -> _FacadeBlocks:
    """One height block per track (at ``rows.height``) and one
    :class:`FacadeRowsCost` per image with rows (and a pose in the
    problem)."""
    sigma, scale = facade_row_weighting(options)
    heights = [np.array([h], float) for h in rows.height]
    costs = []
    for image_id, image, pose, params in _posed_images(problem, rec, rows.image_id):
        sel = np.flatnonzero(rows.image_id == image_id)
        tracks, local = np.unique(rows.track[sel], return_inverse=True)
        cost = FacadeRowsCost(
            rows.anchor_xy[rows.track[sel]],
            local,
            rows.line[sel],
            image.camera.model.name,
            len(params),
            sigma,
            scale,
        )
        blocks = [heights[t] for t in tracks]
        problem.add_residual_block(cost, None, [pose, params, *blocks])
        costs.append((cost, sel, blocks))
    return _FacadeBlocks(rows, costs, heights)


def adjust_block_ceres(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, VerticalRow],
    options: BlockAdjustmentOptions,
    map_rows: MapRows | None = None,
    hold_mean_height: bool = False,
) -> BlockAdjustmentSummary:
    """:func:`~obliq_colmap.georegister.block.adjust_block` in Ceres; with
    ``map_rows`` the map's rows (and its facade rows, their track heights
    unknowns: a first solve, one outlier round as the obliq solver's,
    :func:`.block.facade_outlier_round`, and a second solve from the
    first's block), with ``hold_mean_height`` the block's mean camera
    height held (the obliq solver's gauge without control points)."""
    image_ids = sorted(rec.reg_image_ids())
    facades = start = None
    if map_rows is not None and map_rows.facades is not None:
        facades = map_rows.facades.select(image_ids)
        if len(facades):
            from .block_bundle import initial_facade_heights

            start = initial_facade_heights(
                rec, control_point_ids, verticals, options, map_rows
            ).facades.height
    first = _solve(
        rec, control_point_ids, verticals, options, map_rows, facades,
        hold_mean_height, start,
    )  # fmt: skip
    summary, iterations = first.summary, first.iterations
    if first.facades is not None and len(first.facades.rows):
        # one outlier round on the facade rows, then the adjustment again
        # from the solved block (the obliq solver's procedure)
        kept = facade_outlier_round(
            map_rows,
            image_ids,
            first.facades.raw_residuals(rec),
            first.facades.heights_now(),
        )
        second = _solve(
            rec, control_point_ids, verticals, options, kept, kept.facades,
            hold_mean_height,
        )  # fmt: skip
        summary.final_cost = second.summary.final_cost
        summary.termination = second.summary.termination
        summary.num_map_rows = second.summary.num_map_rows
        summary.num_facade_rows = second.summary.num_facade_rows
        summary.num_facade_tracks = second.summary.num_facade_tracks
        iterations += second.iterations
    summary.iterations = iterations
    return summary


@dataclass
class _Solved:
    summary: BlockAdjustmentSummary
    iterations: int
    facades: _FacadeBlocks | None


def _solve(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, VerticalRow],
    options: BlockAdjustmentOptions,
    map_rows: MapRows | None,
    facades: FacadeRows | None,
    hold_mean_height: bool,
    start_heights: np.ndarray | None = None,
) -> _Solved:
    """One Ceres solve of the block in place (see
    :func:`adjust_block_ceres`); the facade rows' height blocks hold the
    solved heights. With ``start_heights`` (J,) the solve starts from
    those (its initial cost still the one at ``facades.height``)."""
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
    line_costs = []
    if map_rows is not None and len(map_rows):
        line_costs = _add_map_rows(problem, rec, map_rows, options)
    fac = None
    if facades is not None and len(facades) and map_rows is not None:
        fac = _add_facade_rows(problem, rec, facades, options)
    gauge = _hold_mean_height(problem, rec) if hold_mean_height else None
    solver = pyceres.SolverOptions()
    solver.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    if fac is not None:
        # each image's facade block holds all its tracks' heights: Ceres
        # cannot eliminate them with the points (no independent set), and
        # the reduced system they stay in is slow to factor (the paper
        # block, automatic: 73 s of 86 in the linear solver); conjugate
        # gradients on it, Schur-Jacobi preconditioned: 10 s. To a relative
        # residual of 1e-3 (Ceres' default 0.1 left the test block's weak
        # focal mode unconverged after 100 iterations; 1e-3: 53)
        solver.linear_solver_type = pyceres.LinearSolverType.ITERATIVE_SCHUR
        solver.preconditioner_type = pyceres.PreconditionerType.SCHUR_JACOBI
        solver.eta = 1e-3
    solver.max_num_iterations = options.max_num_iterations
    solver.function_tolerance = options.function_tolerance
    solver.num_threads = 1
    initial_cost = None
    if fac is not None and start_heights is not None:
        # the cost at the given heights, then the start's
        solver.max_num_iterations = 0
        summary = pyceres.SolverSummary()
        pyceres.solve(solver, problem, summary)
        initial_cost = summary.initial_cost
        solver.max_num_iterations = options.max_num_iterations
        for block, h in zip(fac.heights, start_heights, strict=True):
            block[0] = h
    summary = pyceres.SolverSummary()
    pyceres.solve(solver, problem, summary)
    if initial_cost is not None:
        summary.initial_cost = initial_cost
    n_map = sum(c.num_residuals() for c in line_costs)
    n_fac = 0 if fac is None else sum(c.num_residuals() for c, _, _ in fac.costs)
    n_tracks = 0 if fac is None else len(fac.heights)
    logger.info(
        "block adjustment (ceres): cost %.6g -> %.6g in %d iterations (%d "
        "control points, %d verticals, %d map rows, %d facade rows of %d "
        "tracks%s)",
        summary.initial_cost, summary.final_cost, summary.num_successful_steps,
        n_ctrl, n_vert, n_map, n_fac, n_tracks,
        ", mean camera height held" if gauge else "",
    )  # fmt: skip
    del adjuster  # after the solve: the problem refers to rec's arrays
    iterations = int(summary.num_successful_steps + summary.num_unsuccessful_steps)
    return _Solved(
        BlockAdjustmentSummary(
            initial_cost=float(summary.initial_cost),
            final_cost=float(summary.final_cost),
            iterations=iterations,
            num_control_rows=n_ctrl,
            num_vertical_rows=n_vert,
            termination=str(summary.termination_type),
            solver="ceres",
            num_map_rows=n_map,
            num_facade_rows=n_fac,
            num_facade_tracks=n_tracks,
        ),
        iterations,
        fac,
    )
