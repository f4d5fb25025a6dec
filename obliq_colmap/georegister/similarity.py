"""The similarity that puts an upright model on the control points (MetropoGIS 3.4).

With the vertical known (the model rotated upright: its z is up), four
unknowns remain: scale s, heading theta and the translation t, in

    map = s R_z(theta) model + t.

Two control points fix them in closed form (the horizontal vector between
them gives s and theta, the points' mean the translation; the vertical offset
from the points with a height). With three or more: weighted least squares,
linear in ``(a, b) = s (cos theta, sin theta)`` and t (horizontal rows
weighted by ``1 / sigma_h^2``, vertical rows by ``1 / sigma_v^2``; a 2D point
gives horizontal rows only), made robust by least median of squares over
all pairs (the closed form of each pair) and a refit on the inliers.
Without a vertical, :func:`similarity_7dof` (Umeyama) needs three 3D points.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pycolmap

from obliq_colmap.errors import InputError


@dataclass
class Similarity:
    """``map = scale * R @ model + t`` with its fit.

    inliers : (N,) bool, the points used; residuals_m : (N, 3) map minus
    transformed model (NaN height for 2D points).
    """

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    inliers: np.ndarray
    residuals_m: np.ndarray

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) model points in the map frame."""
        return self.scale * np.asarray(xyz, float) @ self.rotation.T + self.translation

    def sim3d(self) -> pycolmap.Sim3d:
        return pycolmap.Sim3d(
            self.scale, pycolmap.Rotation3d(self.rotation), self.translation
        )

    @property
    def heading_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.rotation[1, 0], self.rotation[0, 0])))


def _rz(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _vertical_offset(scale, model, target, w_v) -> float:
    has = np.isfinite(target[:, 2]) & (w_v > 0)
    if not has.any():
        raise InputError(
            None,
            "no control point with a height: the vertical position of the model "
            "is not determined (give at least one 3D control point)",
        )
    dz = target[has, 2] - scale * model[has, 2]
    return float(np.sum(w_v[has] * dz) / np.sum(w_v[has]))


def _fit(model, target, w_h, w_v) -> tuple[float, float, np.ndarray]:
    """Weighted least squares of (a, b, tx, ty), then tz: (scale, theta, t)."""
    x, y = model[:, 0], model[:, 1]
    n = len(x)
    A = np.zeros((2 * n, 4))
    A[0::2] = np.c_[x, -y, np.ones(n), np.zeros(n)]
    A[1::2] = np.c_[y, x, np.zeros(n), np.ones(n)]
    rhs = target[:, :2].ravel()
    sw = np.sqrt(np.repeat(w_h, 2))
    sol = np.linalg.lstsq(A * sw[:, None], rhs * sw, rcond=None)[0]
    a, b = sol[:2]
    scale, theta = float(np.hypot(a, b)), float(np.arctan2(b, a))
    tz = _vertical_offset(scale, model, target, w_v)
    return scale, theta, np.array([sol[2], sol[3], tz])


def _residuals(scale, theta, t, model, target) -> np.ndarray:
    return target - (scale * model @ _rz(theta).T + t)


def similarity_upright(
    model: np.ndarray,
    target: np.ndarray,
    sigma_h: np.ndarray,
    sigma_v: np.ndarray,
    inlier_sigmas: float = 3.0,
) -> Similarity:
    """The 4-DOF similarity from (N, 3) upright model points to map points.

    ``target[:, 2]`` NaN marks a 2D point. N = 2: closed form (exact through
    both points horizontally); N >= 3: robust weighted least squares.
    """
    model, target = np.asarray(model, float), np.asarray(target, float)
    n = len(model)
    if n < 2:
        raise InputError(None, f"{n} control point(s): at least 2 are needed")
    w_h = 1.0 / np.asarray(sigma_h, float) ** 2
    w_v = np.where(np.isfinite(target[:, 2]), 1.0 / np.asarray(sigma_v, float) ** 2, 0)
    base = np.hypot(*(model[:, None, :2] - model[None, :, :2]).transpose(2, 0, 1))
    if base[np.triu_indices(n, 1)].max() <= 1e-9:
        raise InputError(None, "the control points coincide in the model")
    inliers = np.ones(n, bool)
    if n >= 4:
        # least median of squares over the pairs' closed forms
        best, best_med = None, np.inf
        for i, j in combinations(range(n), 2):
            if base[i, j] <= 1e-9:
                continue
            pair = np.array([i, j])
            s, th, t = _fit(model[pair], target[pair], w_h[pair], np.ones(2))
            r = _residuals(s, th, t, model, target)
            med = float(np.median(np.sum(r[:, :2] ** 2, axis=1) * w_h))
            if med < best_med:
                best, best_med = (s, th, t), med
        s, th, t = best
        r = _residuals(s, th, t, model, target)
        # normalised horizontal residuals; their robust scale (LMedS's, with
        # its small-sample factor) or 1 (the stated sigmas), whichever is larger
        z = np.sqrt(np.sum(r[:, :2] ** 2, axis=1) * w_h)
        spread = max(1.4826 * (1 + 5.0 / (n - 2)) * np.sqrt(best_med), 1.0)
        inliers = z <= inlier_sigmas * spread
    s, th, t = _fit(model[inliers], target[inliers], w_h[inliers], w_v[inliers])
    res = _residuals(s, th, t, model, target)
    return Similarity(s, _rz(th), t, inliers, res)


def similarity_7dof(model: np.ndarray, target: np.ndarray) -> Similarity:
    """Umeyama's least-squares similarity from >= 3 3D points (no vertical)."""
    model, target = np.asarray(model, float), np.asarray(target, float)
    if len(model) < 3 or not np.all(np.isfinite(target)):
        raise InputError(
            None, "without a vertical, 3 control points with heights are needed"
        )
    mu_m, mu_t = model.mean(0), target.mean(0)
    M, T = model - mu_m, target - mu_t
    U, S, Vt = np.linalg.svd(T.T @ M / len(model))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D) / np.mean(np.sum(M**2, axis=1)))
    t = mu_t - scale * R @ mu_m
    res = target - (scale * model @ R.T + t)
    return Similarity(scale, R, t, np.ones(len(model), bool), res)
