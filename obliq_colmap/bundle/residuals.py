"""Residuals of the cadastral-line bundle (paper eq. 3) with analytic Jacobians.

Every function here is vectorised over N residuals and pure (no state).

Camera models
-------------
Projections come from :mod:`obliq_colmap.bundle.projection` (every supported
COLMAP model through one general 8-parameter form); the residuals contract
their chains per row in closed form over (N,) arrays instead of forming the
(N, 2, 3) Jacobians of the projection. The projection functions are
also importable from here (``residuals.project``, ...).

Pose parameterisation (solver convention)
-----------------------------------------
A pose is ``cam_from_world`` as a rotation R and the camera centre c:
``X_cam = R (X - c)``. Updates are a LEFT-multiplied rotation vector omega
(expressed in the camera frame) and an additive centre step::

    R <- Exp(omega) R,        c <- c + delta_c

so ``d X_cam / d omega = -[X_cam]_x`` and ``d X_cam / d c = -R``. A 3D point
``(x, y, h)`` with unknown height h moves by ``d X_cam / d h = R e_z``.

Residuals
---------
Lines are homogeneous ``l = (a, b, c)`` with ``a^2 + b^2 = 1`` (normalised
here anyway); ``n = (a, b)`` is the unit normal and ``e = n . p + c`` is the
signed perpendicular distance of the pixel ``p`` from the line.

* vertical (map corner): ``r = e`` in pixels, with p the projection of
  ``(x_i, y_i, h_i)``.
* horizontal (facade edge), ``dist_z`` of eq. 3: the distance from the
  projection ``p`` of ``x_j + h_j e_z`` to the line, measured along the image
  direction of the projected vertical through ``p``::

      d = d p(X + s e_z) / d s |_{s=0}  =  J_pi(X_cam) R e_z    (pixels / metre)
      r = e / |n . d_hat|,   d_hat = d / |d|

  i.e. the length of the segment from p to the line along d_hat; ``r / |d|``
  is the height error in metres. The Jacobian is exact: with
  ``s = |n . d_hat|`` and ``sigma = sign(n . d_hat)``::

      dr = (n / s) . dp  -  (e / s^2) (sigma / |d|) (n - (n . d_hat) d_hat) . dd

  where dd needs the second derivatives of the projection (the Hessian of
  the distortion, contracted with the direction). Precondition: the line is
  not parallel to the projected vertical (``|n . d_hat|`` well above 0;
  horizontal facade lines are close to perpendicular to it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry import SUPPORTED_MODELS, Camera, Pose, rotation_exp
from .projection import (
    FULL_INDEX,
    FULL_PARAM_NAMES,
    Lens,
    expansion_matrix,
    focal_principal_extra_indices,
    full_params,
    project,
    project_with_jacobian,
    project_with_vertical,
)

__all__ = [
    "FULL_PARAM_NAMES",
    "ResidualJacobians",
    "expansion_matrix",
    "focal_principal_extra_indices",
    "horizontal_residuals",
    "horizontal_rows",
    "project",
    "project_with_jacobian",
    "project_with_vertical",
    "reprojection_rows",
    "rotation_exp",
    "vertical_residuals",
    "vertical_rows",
]


@dataclass
class ResidualJacobians:
    """Residuals of one kind and their Jacobians (all (N, ...) arrays).

    Attributes
    ----------
    residuals : (N,) pixels.
    d_pose : (N, 6) derivative w.r.t. (omega, c): left rotation vector
        (radians, camera frame) and camera centre (metres, world).
    d_params : (N, P) derivative w.r.t. the camera model's parameters.
    d_height : (N,) derivative w.r.t. the point's height (pixels / metre).
    """

    residuals: np.ndarray
    d_pose: np.ndarray | None = None
    d_params: np.ndarray | None = None
    d_height: np.ndarray | None = None


def _unit_lines(lines: np.ndarray) -> np.ndarray:
    """(N, 3) homogeneous lines to (3, N) rows ``(n0, n1, c)``, unit normal."""
    L = np.asarray(lines, float)
    if L.ndim != 2 or L.shape[1] != 3:
        raise ValueError(f"lines must have shape (N, 3), got {L.shape}")
    return L.T / np.hypot(L[:, 0], L[:, 1])


def _rows_of(rotations, centers, points_world) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations and (N, 3) points to the kernels' (3, 3, N) and
    (3, N) ``X - c`` (views where possible)."""
    R = np.asarray(rotations, float).transpose(1, 2, 0)
    return R, (np.asarray(points_world, float) - centers).T


def _pose_height_chain(dX, X_cam, R, dV=None) -> tuple[np.ndarray, np.ndarray]:
    """(3,) rows d r / d X_cam (and d r / d dir for the direction R e_z) to
    (6, N) d r / d (omega, c) and (N,) d r / d h.

    ``d X_cam / d omega = -[X_cam]_x`` gives ``X_cam x dr/dX``; the direction
    rotates with the camera too; ``d X_cam / d c = -R``, ``d X_cam / d h = R e_z``.
    """
    x, y, z = X_cam
    a, b, c = dX
    out = np.empty((6, a.shape[0]))
    out[0] = y * c - z * b
    out[1] = z * a - x * c
    out[2] = x * b - y * a
    if dV is not None:
        V0, V1, V2 = R[0, 2], R[1, 2], R[2, 2]
        out[0] += V1 * dV[2] - V2 * dV[1]
        out[1] += V2 * dV[0] - V0 * dV[2]
        out[2] += V0 * dV[1] - V1 * dV[0]
    for j in range(3):
        out[3 + j] = -(a * R[0, j] + b * R[1, j] + c * R[2, j])
    return out, -out[5]  # d r / d h = dX . R e_z = -(d r / d c_z)


def _param_chain(model, D: Lens, gp, gd=None, w=None, q=None) -> np.ndarray:
    """(P, N) derivative w.r.t. the model's parameters.

    ``gp = (gp0, gp1)``: weights of the pixel's derivative; ``gd``: of the
    directional derivative ``d = diag(f) J_uv w`` (``w``, ``q = J_uv w`` from
    :meth:`Lens.along`), None for the vertical residual.
    """
    u, v, r2, uv, fx, fy = D.u, D.v, D.r2, D.uv, D.fx, D.fy
    gp0, gp1 = gp
    a0, a1 = gp0 * fx, gp1 * fy
    if gd is not None:
        c0, c1 = gd[0] * fx, gd[1] * fy
        w0, w1 = w

    def column(i: int) -> np.ndarray:
        # d r / d full[i], full = (fx, fy, cx, cy, k1, k2, p1, p2).
        if i == 0:
            return gp0 * D.ud if gd is None else gp0 * D.ud + gd[0] * q[0]
        if i == 1:
            return gp1 * D.vd if gd is None else gp1 * D.vd + gd[1] * q[1]
        if i in (2, 3):
            return gp0 if i == 2 else gp1
        uu2, vv2 = 2 * D.uu, 2 * D.vv
        if i == 4:
            out = (a0 * u + a1 * v) * r2
            if gd is not None:
                out = out + c0 * ((r2 + uu2) * w0 + 2 * uv * w1)
                out = out + c1 * (2 * uv * w0 + (r2 + vv2) * w1)
            return out
        if i == 5:
            out = (a0 * u + a1 * v) * r2 * r2
            if gd is not None:
                t = c0 * ((r2 + 2 * uu2) * w0 + 4 * uv * w1)
                t = t + c1 * (4 * uv * w0 + (r2 + 2 * vv2) * w1)
                out = out + r2 * t
            return out
        if i == 6:
            out = a0 * 2 * uv + a1 * (r2 + vv2)
            if gd is not None:
                out = (
                    out
                    + c0 * (2 * v * w0 + 2 * u * w1)
                    + c1 * (2 * u * w0 + 6 * v * w1)
                )
            return out
        out = a0 * (r2 + uu2) + a1 * 2 * uv
        if gd is not None:
            out = out + c0 * (6 * u * w0 + 2 * v * w1) + c1 * (2 * v * w0 + 2 * u * w1)
        return out

    names = SUPPORTED_MODELS[model]
    J = np.empty((len(names), u.shape[0]))
    for row, name in enumerate(names):
        idx = FULL_INDEX[name]
        J[row] = column(idx[0]) if len(idx) == 1 else column(idx[0]) + column(idx[1])
    return J


def _lens_of(model, full, R, D, jacobian):
    """X_cam = R (X - c) as (3,) rows, and its :class:`Lens`."""
    X_cam = tuple(R[i, 0] * D[0] + R[i, 1] * D[1] + R[i, 2] * D[2] for i in range(3))
    return X_cam, Lens(model, full, *X_cam, jacobian)


def vertical_rows(model: str, full, R, D, line, jacobians: bool = True):
    """:func:`vertical_residuals` on rows: the solver's entry point.

    Parameters
    ----------
    model : str
    full : (8, 1) or (8, N) general parameters (``params @ E.T``, transposed).
    R : (3, 3, N) array, ``R[i, j]`` the entries of each residual's rotation.
    D : (3, N) array, ``X - c`` (world point minus camera centre).
    line : (3, N) array, unit-normal lines ``(n0, n1, c)``.
    jacobians : bool

    Returns
    -------
    r : (N,); and if ``jacobians``, d_pose (6, N), d_params (P, N), d_height (N,).
    """
    n0, n1, lc = line
    X_cam, L = _lens_of(model, full, R, D, jacobians)
    px, py = L.pixels()
    r = n0 * px + n1 * py + lc
    if not jacobians:
        return (r,)
    # d r / d X_cam = n^T diag(f) J_uv d(u, v) / d X_cam.
    b0, b1 = L.back(n0 * L.fx, n1 * L.fy)
    iz = L.iz
    dX = (b0 * iz, b1 * iz, -(b0 * L.u + b1 * L.v) * iz)
    d_pose, d_height = _pose_height_chain(dX, X_cam, R)
    return r, d_pose, _param_chain(model, L, (n0, n1)), d_height


def horizontal_rows(model: str, full, R, D, line, jacobians: bool = True):
    """:func:`horizontal_residuals` on rows; arguments and results as
    :func:`vertical_rows`."""
    n0, n1, lc = line
    X_cam, L = _lens_of(model, full, R, D, True)
    px, py = L.pixels()
    e = n0 * px + n1 * py + lc
    # d = J_pi(X_cam) R e_z, the image direction of the projected vertical.
    w0, w1, q0, q1 = L.along(R[0, 2], R[1, 2], R[2, 2])
    d0, d1 = L.fx * q0, L.fy * q1
    dn = np.sqrt(d0 * d0 + d1 * d1)
    nd = n0 * d0 + n1 * d1
    if not jacobians:
        return (e * dn / np.abs(nd),)
    dot = nd / dn  # n . d_hat
    s = np.abs(dot)
    r = e / s
    # Weights of dp (gp) and of dd (gd) in dr, as in the module docstring.
    gp0, gp1 = n0 / s, n1 / s
    t = -(e / s**2 * np.sign(dot) / dn)
    gd0, gd1 = t * (n0 - dot * d0 / dn), t * (n1 - dot * d1 / dn)
    # Pull both back through diag(f) J_uv: b for dp, B for dd (and d dd / d dir).
    b0, b1 = L.back(gp0 * L.fx, gp1 * L.fy)
    c0, c1 = gd0 * L.fx, gd1 * L.fy
    B0, B1 = L.back(c0, c1)
    # dd / d(u, v) through J_uv's own derivative: (c0, c1) . (H w).
    H = L.hessian()
    if H is not None:
        h000, h001, h011, h111 = H
        m = h001 * w0 + h011 * w1  # d q0 / dv = d q1 / du
        b0 = b0 + c0 * (h000 * w0 + h001 * w1) + c1 * m
        b1 = b1 + c0 * m + c1 * (h011 * w0 + h111 * w1)
    # Through d(u, v) / d X_cam and d w / d X_cam.
    u, v, iz = L.u, L.v, L.iz
    wz = R[2, 2] * iz
    P0, P1 = b0 - B0 * wz, b1 - B1 * wz
    dX = (P0 * iz, P1 * iz, -(P0 * u + P1 * v + B0 * w0 + B1 * w1) * iz)
    dV = (B0 * iz, B1 * iz, -(B0 * u + B1 * v) * iz)
    d_pose, d_height = _pose_height_chain(dX, X_cam, R, dV)
    d_params = _param_chain(model, L, (gp0, gp1), (gd0, gd1), (w0, w1), (q0, q1))
    return r, d_pose, d_params, d_height


def reprojection_rows(model: str, full, R, D, xy, jacobians: bool = True):
    """Reprojection residuals of observed 3D points (tie points) on rows.

    Two rows per observation, ``projection - observation`` in x and in y
    (pixels). Each row is the vertical residual of a line through the
    observation (normal (1, 0) or (0, 1)), so its chain is the same; the
    point's own Jacobian is minus the centre's (the rows depend on X - c).

    Parameters
    ----------
    model, full, R : as :func:`vertical_rows`.
    D : (3, N) array, ``X - c`` (tie point minus camera centre).
    xy : (2, N) array, observed pixels (raw, COLMAP convention).
    jacobians : bool

    Returns
    -------
    r : (2, N) residuals (x row, y row); and if ``jacobians``, d_pose
    (2, 6, N), d_params (2, P, N), d_point (2, 3, N).
    """
    X_cam, L = _lens_of(model, full, R, D, jacobians)
    px, py = L.pixels()
    r = np.stack([px - xy[0], py - xy[1]])
    if not jacobians:
        return (r,)
    iz = L.iz
    d_pose, d_params = [], []
    for gp in ((1.0, 0.0), (0.0, 1.0)):
        b0, b1 = L.back(gp[0] * L.fx, gp[1] * L.fy)
        dX = (b0 * iz, b1 * iz, -(b0 * L.u + b1 * L.v) * iz)
        d_pose.append(_pose_height_chain(dX, X_cam, R)[0])
        d_params.append(_param_chain(model, L, gp))
    d_pose = np.stack(d_pose)
    return r, d_pose, np.stack(d_params), -d_pose[:, 3:6]


def _as_residuals(out: tuple) -> ResidualJacobians:
    if len(out) == 1:
        return ResidualJacobians(out[0])
    r, d_pose, d_params, d_height = out
    return ResidualJacobians(r, d_pose.T, d_params.T, d_height)


def vertical_residuals(
    model: str,
    params: np.ndarray,
    rotations: np.ndarray,
    centers: np.ndarray,
    points_world: np.ndarray,
    lines: np.ndarray,
    jacobians: bool = True,
) -> ResidualJacobians:
    """Signed pixel distance of projected map corners to vertical image lines.

    Parameters
    ----------
    model : str
        COLMAP model of all N residuals' cameras.
    params : (P,) or (N, P) array
        Camera parameters (COLMAP order).
    rotations : (N, 3, 3) array
        ``cam_from_world`` rotation of each residual's image.
    centers : (N, 3) array
        Camera centres, world (local) frame, metres.
    points_world : (N, 3) array
        Corner points ``(x_i, y_i, h_i)``, metres.
    lines : (N, 3) array
        Homogeneous image lines (pixels), normalised here.
    jacobians : bool
        Also return the Jacobians.

    Returns
    -------
    ResidualJacobians
        ``d_height`` is the derivative w.r.t. ``h_i``.
    """
    line = _unit_lines(lines)
    full, _ = full_params(model, params, line.shape[1])
    R, D = _rows_of(rotations, centers, points_world)
    return _as_residuals(vertical_rows(model, full, R, D, line, jacobians))


def horizontal_residuals(
    model: str,
    params: np.ndarray,
    rotations: np.ndarray,
    centers: np.ndarray,
    points_world: np.ndarray,
    lines: np.ndarray,
    jacobians: bool = True,
) -> ResidualJacobians:
    """``dist_z`` of eq. 3: distance to the line along the projected vertical.

    ``r = e / |n . d_hat|`` (pixels), see the module docstring for the exact
    derivative. Arguments as :func:`vertical_residuals`, with
    ``points_world = (x_j, y_j, h_j)`` the facade-edge point.
    """
    line = _unit_lines(lines)
    full, _ = full_params(model, params, line.shape[1])
    R, D = _rows_of(rotations, centers, points_world)
    return _as_residuals(horizontal_rows(model, full, R, D, line, jacobians))


def horizontal_residuals_by_image(
    cameras: Sequence[Camera],
    poses: Sequence[Pose],
    image: np.ndarray,
    points_world: np.ndarray,
    lines: np.ndarray,
) -> np.ndarray:
    """(H,) ``dist_z`` residuals (px) of observations in several images.

    ``image`` (H,) indexes ``cameras`` and ``poses`` (one per image);
    ``points_world`` (H, 3), ``lines`` (H, 3) raw pixels. For diagnostics at
    given cameras (e.g. the true ones), outside the solver.
    """
    r = np.full(len(image), np.nan)
    for k, (cam, pose) in enumerate(zip(cameras, poses, strict=True)):
        sel = np.flatnonzero(image == k)
        if len(sel) == 0:
            continue
        r[sel] = horizontal_residuals(
            cam.model,
            cam.params,
            np.repeat(pose.rotation[None], len(sel), 0),
            np.repeat(pose.center[None], len(sel), 0),
            points_world[sel],
            lines[sel],
            jacobians=False,
        ).residuals
    return r
