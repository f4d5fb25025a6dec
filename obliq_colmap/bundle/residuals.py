"""Residuals of the cadastral-line bundle (paper eq. 3) with analytic Jacobians.

Every function here is vectorised over N residuals and pure (no state).

Camera models
-------------
All supported COLMAP models (:data:`obliq_colmap.geometry.SUPPORTED_MODELS`)
are evaluated through one general form with the eight parameters
``(fx, fy, cx, cy, k1, k2, p1, p2)`` of OPENCV; a model's own parameters map
to it linearly, ``full = params @ expansion_matrix(model).T``, so the
Jacobian with respect to the model's parameters is ``J_full @ E``.
Projection (COLMAP's, see :func:`obliq_colmap.geometry.img_from_cam`)::

    (u, v)   = (x / z, y / z)                        normalised coordinates
    (ud, vd) = (u, v) + distortion(u, v)              k1, k2 radial; p1, p2 tangential
    pixel    = (fx ud + cx, fy vd + cy)               COLMAP pixel convention

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

from ..geometry import SUPPORTED_MODELS, Camera, Pose

__all__ = [
    "FULL_PARAM_NAMES",
    "ResidualJacobians",
    "expansion_matrix",
    "focal_principal_extra_indices",
    "horizontal_residuals",
    "project",
    "project_with_jacobian",
    "project_with_vertical",
    "rotation_exp",
    "vertical_residuals",
]

#: The general parameter vector all supported models are expanded to.
FULL_PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")

_FULL_INDEX = {
    # model parameter name -> rows of the full vector it feeds
    "f": (0, 1),
    "fx": (0,),
    "fy": (1,),
    "cx": (2,),
    "cy": (3,),
    "k": (4,),
    "k1": (4,),
    "k2": (5,),
    "p1": (6,),
    "p2": (7,),
}


def expansion_matrix(model: str) -> np.ndarray:
    """(8, P) matrix E with ``full = E @ params`` for a supported COLMAP model."""
    if model not in SUPPORTED_MODELS:
        raise ValueError(
            f"camera model {model!r} is not supported; "
            f"supported: {', '.join(SUPPORTED_MODELS)}"
        )
    names = SUPPORTED_MODELS[model]
    E = np.zeros((8, len(names)))
    for col, name in enumerate(names):
        E[list(_FULL_INDEX[name]), col] = 1.0
    return E


def focal_principal_extra_indices(model: str) -> tuple[list[int], list[int], list[int]]:
    """Indices into a model's params: (focal lengths, principal point, extra)."""
    names = SUPPORTED_MODELS[model]
    focal = [i for i, n in enumerate(names) if n in ("f", "fx", "fy")]
    pp = [i for i, n in enumerate(names) if n in ("cx", "cy")]
    extra = [i for i, n in enumerate(names) if i not in focal and i not in pp]
    return focal, pp, extra


def _full_params(
    model: str, params: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Model params, (P,) or (N, P), to the (N, 8) general vector; and E."""
    E = expansion_matrix(model)
    p = np.asarray(params, float)
    if p.ndim == 1:
        p = p[None, :]
    if p.shape[-1] != E.shape[1] or p.shape[0] not in (1, n):
        raise ValueError(
            f"{model} params must have shape ({E.shape[1]},) or ({n}, {E.shape[1]}),"
            f" got {np.shape(params)}"
        )
    return np.broadcast_to(p @ E.T, (n, 8)), E


def _check_points(points_cam: np.ndarray, name: str = "points_cam") -> np.ndarray:
    X = np.asarray(points_cam, float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {X.shape}")
    return X


class _Distortion:
    """Normalised coordinates, distortion, its Jacobian; shared by all routines."""

    def __init__(self, full: np.ndarray, X: np.ndarray) -> None:
        self.fx, self.fy, self.cx, self.cy = (
            full[:, 0],
            full[:, 1],
            full[:, 2],
            full[:, 3],
        )
        self.k1, self.k2, self.p1, self.p2 = (
            full[:, 4],
            full[:, 5],
            full[:, 6],
            full[:, 7],
        )
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            self.iz = 1.0 / np.where(z > 0, z, np.nan)  # NaN behind the camera
        self.u, self.v = X[:, 0] * self.iz, X[:, 1] * self.iz
        u, v = self.u, self.v
        self.r2 = r2 = u * u + v * v
        self.radial = self.k1 * r2 + self.k2 * r2 * r2
        self.g = self.k1 + 2.0 * self.k2 * r2  # d radial / d r2
        uv = u * v
        self.ud = u + u * self.radial + 2.0 * self.p1 * uv + self.p2 * (r2 + 2 * u * u)
        self.vd = v + v * self.radial + 2.0 * self.p2 * uv + self.p1 * (r2 + 2 * v * v)

    def pixels(self) -> np.ndarray:
        return np.stack([self.fx * self.ud + self.cx, self.fy * self.vd + self.cy], 1)

    def jac_uv(self) -> np.ndarray:
        """(N, 2, 2) d(ud, vd) / d(u, v)."""
        u, v, g, p1, p2 = self.u, self.v, self.g, self.p1, self.p2
        J = np.empty((u.shape[0], 2, 2))
        J[:, 0, 0] = 1 + self.radial + 2 * u * u * g + 2 * p1 * v + 6 * p2 * u
        J[:, 0, 1] = 2 * u * v * g + 2 * p1 * u + 2 * p2 * v
        J[:, 1, 0] = 2 * u * v * g + 2 * p2 * v + 2 * p1 * u
        J[:, 1, 1] = 1 + self.radial + 2 * v * v * g + 2 * p2 * u + 6 * p1 * v
        return J

    def jac_normalise(self) -> np.ndarray:
        """(N, 2, 3) d(u, v) / d X_cam."""
        iz = self.iz
        J = np.zeros((iz.shape[0], 2, 3))
        J[:, 0, 0] = iz
        J[:, 0, 2] = -self.u * iz
        J[:, 1, 1] = iz
        J[:, 1, 2] = -self.v * iz
        return J

    def jac_full(self) -> np.ndarray:
        """(N, 2, 8) d pixel / d (fx, fy, cx, cy, k1, k2, p1, p2)."""
        u, v, r2, fx, fy = self.u, self.v, self.r2, self.fx, self.fy
        J = np.zeros((u.shape[0], 2, 8))
        J[:, 0, 0] = self.ud
        J[:, 1, 1] = self.vd
        J[:, 0, 2] = 1.0
        J[:, 1, 3] = 1.0
        J[:, 0, 4], J[:, 1, 4] = fx * u * r2, fy * v * r2
        J[:, 0, 5], J[:, 1, 5] = fx * u * r2 * r2, fy * v * r2 * r2
        J[:, 0, 6], J[:, 1, 6] = fx * 2 * u * v, fy * (r2 + 2 * v * v)
        J[:, 0, 7], J[:, 1, 7] = fx * (r2 + 2 * u * u), fy * 2 * u * v
        return J


def project(model: str, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Camera-frame points to pixels (same as :func:`geometry.img_from_cam`).

    Parameters
    ----------
    model : str
        COLMAP model name.
    params : (P,) or (N, P) array
        Model parameters in COLMAP's order (one row per point if 2-D).
    points_cam : (N, 3) array
        Camera-frame points, metres; z <= 0 gives NaN.

    Returns
    -------
    (N, 2) array of pixels (COLMAP convention).
    """
    X = _check_points(points_cam)
    full, _ = _full_params(model, params, X.shape[0])
    return _Distortion(full, X).pixels()


def project_with_jacobian(
    model: str, params: np.ndarray, points_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projection and its analytic Jacobians.

    Parameters
    ----------
    model : str
        COLMAP model name (a key of ``SUPPORTED_MODELS``).
    params : (P,) or (N, P) array
        Model parameters in COLMAP's order.
    points_cam : (N, 3) array
        Camera-frame points, metres.

    Returns
    -------
    xy : (N, 2) array
        Pixels.
    d_xy_d_points : (N, 2, 3) array
        Derivative with respect to the camera-frame point (pixels / metre).
    d_xy_d_params : (N, 2, P) array
        Derivative with respect to the model's parameters.
    """
    X = _check_points(points_cam)
    full, E = _full_params(model, params, X.shape[0])
    D = _Distortion(full, X)
    A = np.stack([D.fx, D.fy], 1)[:, :, None]  # (N, 2, 1) diag(fx, fy)
    J_X = A * (D.jac_uv() @ D.jac_normalise())
    return D.pixels(), J_X, D.jac_full() @ E


def project_with_vertical(
    model: str, params: np.ndarray, points_cam: np.ndarray, dirs_cam: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Projection p, its directional derivative d along ``dirs_cam``, Jacobians.

    ``d = J_pi(X) dirs_cam`` is the image velocity of the point moving along
    the (camera-frame) direction; for ``dirs_cam = R e_z`` it is the image
    direction of the projected world vertical, in pixels per metre.

    Parameters
    ----------
    model : str
    params : (P,) or (N, P) array
    points_cam : (N, 3) array, camera frame, metres.
    dirs_cam : (N, 3) array, camera frame.

    Returns
    -------
    p : (N, 2) pixels.
    d : (N, 2) pixels per unit of the direction.
    dp_dX : (N, 2, 3)
    dp_dparams : (N, 2, P)
    dd_dX : (N, 2, 3)
    dd_ddir : (N, 2, 3)
    dd_dparams : (N, 2, P)
    """
    X = _check_points(points_cam)
    V = _check_points(dirs_cam, "dirs_cam")
    full, E = _full_params(model, params, X.shape[0])
    D = _Distortion(full, X)
    u, v, iz, g, r2 = D.u, D.v, D.iz, D.g, D.r2
    gp = 2.0 * D.k2  # d g / d r2
    p1, p2, fx, fy = D.p1, D.p2, D.fx, D.fy
    n = u.shape[0]
    # Entries of J_uv = d(ud, vd) / d(u, v).
    uv2 = 2 * u * v
    j00 = 1 + D.radial + 2 * u * u * g + 2 * p1 * v + 6 * p2 * u
    j01 = uv2 * g + 2 * p1 * u + 2 * p2 * v
    j10 = uv2 * g + 2 * p2 * v + 2 * p1 * u
    j11 = 1 + D.radial + 2 * v * v * g + 2 * p2 * u + 6 * p1 * v
    # w = d(u, v) along the direction; q = J_uv w (distorted); d = (fx q0, fy q1).
    V0, V1, V2 = V[:, 0], V[:, 1], V[:, 2]
    w0, w1 = (V0 - u * V2) * iz, (V1 - v * V2) * iz
    q0, q1 = j00 * w0 + j01 * w1, j10 * w0 + j11 * w1
    # Second derivatives of (ud, vd); by symmetry only four distinct ones:
    # H000, H001 = H010 = H100, H011 = H101 = H110, H111.
    h000 = 6 * u * g + 4 * u**3 * gp + 6 * p2
    h001 = 2 * v * g + 2 * u * uv2 * gp + 2 * p1
    h011 = 2 * u * g + 2 * v * uv2 * gp + 2 * p2
    h111 = 6 * v * g + 4 * v**3 * gp + 6 * p1
    dq0_du, dq0_dv = h000 * w0 + h001 * w1, h001 * w0 + h011 * w1
    dq1_du, dq1_dv = h001 * w0 + h011 * w1, h011 * w0 + h111 * w1
    # d w / d X (x, y, z columns); d w0 / dy = d w1 / dx = 0.
    dw_xy = -V2 * iz * iz
    dw0_dz = (-w0 + u * V2 * iz) * iz
    dw1_dz = (-w1 + v * V2 * iz) * iz
    dd_dX = np.empty((n, 2, 3))
    dd_dX[:, 0, 0] = fx * (dq0_du * iz + j00 * dw_xy)
    dd_dX[:, 0, 1] = fx * (dq0_dv * iz + j01 * dw_xy)
    dd_dX[:, 0, 2] = fx * (
        -(dq0_du * u + dq0_dv * v) * iz + j00 * dw0_dz + j01 * dw1_dz
    )
    dd_dX[:, 1, 0] = fy * (dq1_du * iz + j10 * dw_xy)
    dd_dX[:, 1, 1] = fy * (dq1_dv * iz + j11 * dw_xy)
    dd_dX[:, 1, 2] = fy * (
        -(dq1_du * u + dq1_dv * v) * iz + j10 * dw0_dz + j11 * dw1_dz
    )
    # d p / d X = diag(f) J_uv J_n, which is also d d / d dirs.
    dp_dX = np.empty((n, 2, 3))
    dp_dX[:, 0, 0], dp_dX[:, 0, 1] = fx * j00 * iz, fx * j01 * iz
    dp_dX[:, 0, 2] = -fx * (j00 * u + j01 * v) * iz
    dp_dX[:, 1, 0], dp_dX[:, 1, 1] = fy * j10 * iz, fy * j11 * iz
    dp_dX[:, 1, 2] = -fy * (j10 * u + j11 * v) * iz
    # d d / d (fx, fy, cx, cy, k1, k2, p1, p2): (d J_uv / d k) w for the k's.
    dd_dfull = np.zeros((n, 2, 8))
    dd_dfull[:, 0, 0] = q0
    dd_dfull[:, 1, 1] = q1
    t = uv2 * w1  # shared: 2uv w1
    dd_dfull[:, 0, 4] = fx * ((r2 + 2 * u * u) * w0 + t)
    dd_dfull[:, 1, 4] = fy * (uv2 * w0 + (r2 + 2 * v * v) * w1)
    dd_dfull[:, 0, 5] = fx * r2 * ((r2 + 4 * u * u) * w0 + 2 * t)
    dd_dfull[:, 1, 5] = fy * r2 * (2 * uv2 * w0 + (r2 + 4 * v * v) * w1)
    dd_dfull[:, 0, 6] = fx * (2 * v * w0 + 2 * u * w1)
    dd_dfull[:, 1, 6] = fy * (2 * u * w0 + 6 * v * w1)
    dd_dfull[:, 0, 7] = fx * (6 * u * w0 + 2 * v * w1)
    dd_dfull[:, 1, 7] = fy * (2 * v * w0 + 2 * u * w1)
    d = np.stack([fx * q0, fy * q1], 1)
    return D.pixels(), d, dp_dX, D.jac_full() @ E, dd_dX, dp_dX, dd_dfull @ E


# --------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3) vectors to (N, 3, 3) cross-product matrices."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def rotation_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, vectorised: (K, 3) rotation vectors to (K, 3, 3)."""
    omega = np.asarray(omega, float)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    K = _skew(omega)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * K + b * (K @ K)


# --------------------------------------------------------------------------
# Residuals
# --------------------------------------------------------------------------


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
    L = np.asarray(lines, float)
    if L.ndim != 2 or L.shape[1] != 3:
        raise ValueError(f"lines must have shape (N, 3), got {L.shape}")
    return L / np.linalg.norm(L[:, :2], axis=1, keepdims=True)


def _pose_chain(dr_dX: np.ndarray, X_cam: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N, 3) d r / d X_cam to (N, 6) d r / d (omega, c) for the point term."""
    d_omega = np.cross(X_cam, dr_dX)  # dr/dX . (-[X]_x omega) = (X x dr/dX) . omega
    d_c = -np.einsum("ni,nij->nj", dr_dX, R)
    return np.concatenate([d_omega, d_c], axis=1)


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
    lines = _unit_lines(lines)
    X_cam = np.einsum("nij,nj->ni", rotations, points_world - centers)
    nrm = lines[:, :2]
    if not jacobians:
        p = project(model, params, X_cam)
        return ResidualJacobians(np.einsum("ni,ni->n", nrm, p) + lines[:, 2])
    p, dp_dX, dp_dparams = project_with_jacobian(model, params, X_cam)
    r = np.einsum("ni,ni->n", nrm, p) + lines[:, 2]
    dr_dX = np.einsum("ni,nij->nj", nrm, dp_dX)
    return ResidualJacobians(
        r,
        _pose_chain(dr_dX, X_cam, rotations),
        np.einsum("ni,nij->nj", nrm, dp_dparams),
        np.einsum("ni,ni->n", dr_dX, rotations[:, :, 2]),
    )


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
    lines = _unit_lines(lines)
    X_cam = np.einsum("nij,nj->ni", rotations, points_world - centers)
    ez_cam = rotations[:, :, 2]  # (N, 3) world vertical in the camera frame
    nrm = lines[:, :2]
    if not jacobians:
        # Only d is needed: the directional derivative J_pi ez_cam.
        p, dp_dX, _ = project_with_jacobian(model, params, X_cam)
        d = np.einsum("nij,nj->ni", dp_dX, ez_cam)
        e = np.einsum("ni,ni->n", nrm, p) + lines[:, 2]
        dn = np.linalg.norm(d, axis=1)
        return ResidualJacobians(e * dn / np.abs(np.einsum("ni,ni->n", nrm, d)))
    p, d, dp_dX, dp_dparams, dd_dX, dd_ddir, dd_dparams = project_with_vertical(
        model, params, X_cam, ez_cam
    )
    e = np.einsum("ni,ni->n", nrm, p) + lines[:, 2]
    dn = np.linalg.norm(d, axis=1)
    d_hat = d / dn[:, None]
    dot = np.einsum("ni,ni->n", nrm, d_hat)
    sigma = np.sign(dot)
    s = np.abs(dot)
    r = e / s
    g_p = nrm / s[:, None]  # (N, 2) weight of dp
    g_d = -(e / s**2 * sigma / dn)[:, None] * (nrm - dot[:, None] * d_hat)  # of dd
    dr_dX = np.einsum("ni,nij->nj", g_p, dp_dX) + np.einsum("ni,nij->nj", g_d, dd_dX)
    dr_ddir = np.einsum("ni,nij->nj", g_d, dd_ddir)
    d_pose = _pose_chain(dr_dX, X_cam, rotations)
    # The direction R e_z rotates with the camera: d dir / d omega = -[dir]_x.
    d_pose[:, :3] += np.cross(ez_cam, dr_ddir)
    d_params = np.einsum("ni,nij->nj", g_p, dp_dparams) + np.einsum(
        "ni,nij->nj", g_d, dd_dparams
    )
    return ResidualJacobians(r, d_pose, d_params, np.einsum("ni,ni->n", dr_dX, ez_cam))


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
