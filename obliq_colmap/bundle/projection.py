"""Projection of camera-frame points for every supported COLMAP model, with
analytic Jacobians (the residuals' building block).

All supported COLMAP models (:data:`obliq_colmap.geometry.SUPPORTED_MODELS`)
are evaluated through one general form with the eight parameters
``(fx, fy, cx, cy, k1, k2, p1, p2)`` of OPENCV; a model's own parameters map
to it linearly, ``full = params @ expansion_matrix(model).T``, so the
Jacobian with respect to the model's parameters is ``J_full @ E``.
Terms a model lacks are skipped, not evaluated with zero coefficients (the
pinhole models have no distortion, SIMPLE_RADIAL and RADIAL no tangential
terms). Projection (COLMAP's, see :func:`obliq_colmap.geometry.img_from_cam`)::

    (u, v)   = (x / z, y / z)                        normalised coordinates
    (ud, vd) = (u, v) + distortion(u, v)              k1, k2 radial; p1, p2 tangential
    pixel    = (fx ud + cx, fy vd + cy)               COLMAP pixel convention
"""

from __future__ import annotations

import numpy as np

from ..geometry import SUPPORTED_MODELS

__all__ = [
    "FULL_INDEX",
    "FULL_PARAM_NAMES",
    "Lens",
    "expansion_matrix",
    "focal_principal_extra_indices",
    "full_params",
    "project",
    "project_with_jacobian",
    "project_with_vertical",
]

#: The general parameter vector all supported models are expanded to.
FULL_PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")

FULL_INDEX = {
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
        E[list(FULL_INDEX[name]), col] = 1.0
    return E


def focal_principal_extra_indices(model: str) -> tuple[list[int], list[int], list[int]]:
    """Indices into a model's params: (focal lengths, principal point, extra)."""
    names = SUPPORTED_MODELS[model]
    focal = [i for i, n in enumerate(names) if n in ("f", "fx", "fy")]
    pp = [i for i, n in enumerate(names) if n in ("cx", "cy")]
    extra = [i for i, n in enumerate(names) if i not in focal and i not in pp]
    return focal, pp, extra


def _model_terms(model: str) -> tuple[bool, bool, bool]:
    """Distortion terms a model has: (k1, k2, tangential p1 and p2)."""
    names = SUPPORTED_MODELS[model]
    return "k" in names or "k1" in names, "k2" in names, "p1" in names


def full_params(
    model: str, params: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Model params, (P,) or (N, P), to the general vector as (8, 1) or (8, N)
    rows (one row per entry of :data:`FULL_PARAM_NAMES`); and E."""
    E = expansion_matrix(model)
    p = np.asarray(params, float)
    if p.ndim == 1:
        p = p[None, :]
    if p.shape[-1] != E.shape[1] or p.shape[0] not in (1, n):
        raise ValueError(
            f"{model} params must have shape ({E.shape[1]},) or ({n}, {E.shape[1]}),"
            f" got {np.shape(params)}"
        )
    # E is a 0/1 selection: copying rows is exact and cheaper than p @ E.T.
    rows, cols = np.nonzero(E)
    full = np.zeros((8, p.shape[0]))
    full[rows] = p[:, cols].T
    return full, E


def _check_points(points_cam: np.ndarray, name: str = "points_cam") -> np.ndarray:
    X = np.asarray(points_cam, float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {X.shape}")
    return X


class Lens:
    """Normalised coordinates, distortion and its Jacobian of N camera points.

    All attributes are (N,) arrays, or scalars / (1,) arrays where they do
    not vary (per-camera parameters, absent terms). Terms a model lacks are
    skipped rather than evaluated with zero coefficients: no distortion for
    the pinhole models, no tangential terms for SIMPLE_RADIAL and RADIAL
    (the fast path of the usual aerial cameras), no k2 unless the model has it.

    Parameters
    ----------
    model : str
    full : (8, 1) or (8, N) general parameters (:func:`full_params`).
    x, y, z : (N,) camera-frame coordinates; z <= 0 gives NaN.
    jacobian : also the entries of ``J_uv = d(ud, vd) / d(u, v)`` (symmetric:
        ``j01 = j10``).
    """

    def __init__(
        self,
        model: str,
        full: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        z: np.ndarray,
        jacobian: bool = True,
    ) -> None:
        self.has_k1, self.has_k2, self.tangential = _model_terms(model)
        self.fx, self.fy, self.cx, self.cy = full[0], full[1], full[2], full[3]
        self.k1 = full[4] if self.has_k1 else 0.0
        self.k2 = full[5] if self.has_k2 else 0.0
        self.p1, self.p2 = (full[6], full[7]) if self.tangential else (0.0, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            self.iz = 1.0 / np.where(z > 0, z, np.nan)  # NaN behind the camera
        self.u = u = x * self.iz
        self.v = v = y * self.iz
        self.uu, self.vv, self.uv = uu, vv, uv = u * u, v * v, u * v
        self.r2 = r2 = uu + vv
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        if self.has_k2:
            radial = k1 * r2 + k2 * r2 * r2
            self.g = k1 + 2.0 * k2 * r2  # d radial / d r2
        elif self.has_k1:
            radial, self.g = k1 * r2, k1
        else:
            radial, self.g = None, 0.0
        if radial is None:
            self.ud, self.vd = u, v
        else:
            self.ud, self.vd = u + u * radial, v + v * radial
        if self.tangential:
            self.ud = self.ud + 2.0 * p1 * uv + p2 * (r2 + 2 * uu)
            self.vd = self.vd + 2.0 * p2 * uv + p1 * (r2 + 2 * vv)
        if not jacobian:
            return
        if radial is None:
            j00 = j11 = 1.0
            j01 = 0.0
        else:
            g = self.g
            j00 = 1 + radial + 2 * uu * g
            j01 = 2 * uv * g
            j11 = 1 + radial + 2 * vv * g
        if self.tangential:
            j00 = j00 + 2 * p1 * v + 6 * p2 * u
            j01 = j01 + 2 * p1 * u + 2 * p2 * v
            j11 = j11 + 2 * p2 * u + 6 * p1 * v
        self.j00, self.j01, self.j11 = j00, j01, j11

    def pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(N,) pixel coordinates (COLMAP convention)."""
        return self.fx * self.ud + self.cx, self.fy * self.vd + self.cy

    def hessian(self) -> tuple[np.ndarray, ...] | None:
        """The four distinct second derivatives of (ud, vd) by (u, v)
        (``H000, H001 = H010 = H100, H011 = H101 = H110, H111``); None if zero."""
        if not (self.has_k1 or self.tangential):
            return None
        u, v, g = self.u, self.v, self.g
        h000, h001, h011, h111 = 6 * u * g, 2 * v * g, 2 * u * g, 6 * v * g
        if self.has_k2:
            gp8 = 8.0 * self.k2  # 4 gp, gp = d g / d r2 = 2 k2
            h000 = h000 + gp8 * u * self.uu
            h001 = h001 + gp8 * self.uu * v
            h011 = h011 + gp8 * u * self.vv
            h111 = h111 + gp8 * v * self.vv
        if self.tangential:
            p1, p2 = self.p1, self.p2
            h000, h001 = h000 + 6 * p2, h001 + 2 * p1
            h011, h111 = h011 + 2 * p2, h111 + 6 * p1
        return h000, h001, h011, h111

    def along(self, V0, V1, V2) -> tuple[np.ndarray, ...]:
        """Image velocity of the point moving along the camera-frame direction
        V: w = d(u, v), q = J_uv w (distorted, not yet scaled by fx, fy)."""
        iz = self.iz
        w0, w1 = (V0 - self.u * V2) * iz, (V1 - self.v * V2) * iz
        q0 = self.j00 * w0 + self.j01 * w1
        q1 = self.j01 * w0 + self.j11 * w1
        return w0, w1, q0, q1

    def back(self, a0, a1) -> tuple[np.ndarray, ...]:
        """(b0, b1) = (a0, a1) J_uv: a row vector on (ud, vd) pulled back to (u, v)."""
        return a0 * self.j00 + a1 * self.j01, a0 * self.j01 + a1 * self.j11

    def jac_full(self) -> np.ndarray:
        """(N, 2, 8) d pixel / d (fx, fy, cx, cy, k1, k2, p1, p2)."""
        u, v, r2, uv = self.u, self.v, self.r2, self.uv
        fx, fy = self.fx, self.fy
        J = np.zeros((u.shape[0], 2, 8))
        J[:, 0, 0] = self.ud
        J[:, 1, 1] = self.vd
        J[:, 0, 2] = 1.0
        J[:, 1, 3] = 1.0
        J[:, 0, 4], J[:, 1, 4] = fx * u * r2, fy * v * r2
        J[:, 0, 5], J[:, 1, 5] = fx * u * r2 * r2, fy * v * r2 * r2
        J[:, 0, 6], J[:, 1, 6] = fx * 2 * uv, fy * (r2 + 2 * self.vv)
        J[:, 0, 7], J[:, 1, 7] = fx * (r2 + 2 * self.uu), fy * 2 * uv
        return J

    def jac_points(self) -> np.ndarray:
        """(N, 2, 3) d pixel / d X_cam = diag(fx, fy) J_uv d(u, v)/d X_cam."""
        u, v, iz = self.u, self.v, self.iz
        J = np.empty((u.shape[0], 2, 3))
        for row, f, ja, jb in (
            (0, self.fx, self.j00, self.j01),
            (1, self.fy, self.j01, self.j11),
        ):
            a, b = f * ja * iz, f * jb * iz
            J[:, row, 0], J[:, row, 1], J[:, row, 2] = a, b, -(a * u + b * v)
        return J


def _lens(model: str, params: np.ndarray, X: np.ndarray, jacobian: bool = True):
    full, E = full_params(model, params, X.shape[0])
    return Lens(model, full, X[:, 0], X[:, 1], X[:, 2], jacobian), E


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
    D, _ = _lens(model, params, _check_points(points_cam), jacobian=False)
    return np.stack(D.pixels(), 1)


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
    D, E = _lens(model, params, _check_points(points_cam))
    return np.stack(D.pixels(), 1), D.jac_points(), D.jac_full() @ E


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
    D, E = _lens(model, params, X)
    u, v, iz, r2, uv = D.u, D.v, D.iz, D.r2, D.uv
    fx, fy, j00, j01, j11 = D.fx, D.fy, D.j00, D.j01, D.j11
    n = u.shape[0]
    V2 = V[:, 2]
    w0, w1, q0, q1 = D.along(V[:, 0], V[:, 1], V2)
    # d q / d(u, v) = H w (H the Hessian of the distortion, symmetric).
    H = D.hessian()
    if H is None:
        dq0_du = dq0_dv = dq1_dv = 0.0
    else:
        h000, h001, h011, h111 = H
        dq0_du, dq0_dv = h000 * w0 + h001 * w1, h001 * w0 + h011 * w1
        dq1_dv = h011 * w0 + h111 * w1
    dq1_du = dq0_dv
    # d w / d X (x, y, z columns); d w0 / dy = d w1 / dx = 0.
    dw_xy = -V2 * iz * iz
    dw0_dz = (-w0 + u * V2 * iz) * iz
    dw1_dz = (-w1 + v * V2 * iz) * iz
    dd_dX = np.empty((n, 2, 3))
    for row, f, dq_du, dq_dv, ja, jb in (
        (0, fx, dq0_du, dq0_dv, j00, j01),
        (1, fy, dq1_du, dq1_dv, j01, j11),
    ):
        dd_dX[:, row, 0] = f * (dq_du * iz + ja * dw_xy)
        dd_dX[:, row, 1] = f * (dq_dv * iz + jb * dw_xy)
        dd_dX[:, row, 2] = f * (
            -(dq_du * u + dq_dv * v) * iz + ja * dw0_dz + jb * dw1_dz
        )
    # d p / d X = diag(f) J_uv J_n, which is also d d / d dirs.
    dp_dX = D.jac_points()
    # d d / d (fx, fy, cx, cy, k1, k2, p1, p2): (d J_uv / d k) w for the k's.
    dd_dfull = np.zeros((n, 2, 8))
    dd_dfull[:, 0, 0] = q0
    dd_dfull[:, 1, 1] = q1
    t = 2 * uv * w1  # shared: 2uv w1
    dd_dfull[:, 0, 4] = fx * ((r2 + 2 * D.uu) * w0 + t)
    dd_dfull[:, 1, 4] = fy * (2 * uv * w0 + (r2 + 2 * D.vv) * w1)
    dd_dfull[:, 0, 5] = fx * r2 * ((r2 + 4 * D.uu) * w0 + 2 * t)
    dd_dfull[:, 1, 5] = fy * r2 * (4 * uv * w0 + (r2 + 4 * D.vv) * w1)
    dd_dfull[:, 0, 6] = fx * (2 * v * w0 + 2 * u * w1)
    dd_dfull[:, 1, 6] = fy * (2 * u * w0 + 6 * v * w1)
    dd_dfull[:, 0, 7] = fx * (6 * u * w0 + 2 * v * w1)
    dd_dfull[:, 1, 7] = fy * (2 * v * w0 + 2 * u * w1)
    d = np.stack([fx * q0, fy * q1], 1)
    return (
        np.stack(D.pixels(), 1),
        d,
        dp_dX,
        D.jac_full() @ E,
        dd_dX,
        dp_dX,
        dd_dfull @ E,
    )
