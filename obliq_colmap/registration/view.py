"""The VP-aligned frame of one image (:class:`View`): poses ``(alpha, c_xy)``
with the vertical fixed, projections of the corners' verticals, heights of
segment bottoms; the view re-focused and re-tilted for the refinement; height
planes ``z = a x + b y + c`` in the view's relative coordinates."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from obliq_colmap.geometry import Camera, Pose, rotation_aligning, rotation_z
from obliq_colmap.registration import ransac_core

#: The world's up axis (local frame).
EZ = np.array([0.0, 0.0, 1.0])


@dataclass
class View:
    """Camera geometry of one image with the vertical fixed.

    ``X_cam = R0 R_z(alpha) (X - c)``; hypotheses are (alpha, c_xy) with c_xy
    relative to ``c0[:2]`` and the camera height held at ``c0[2]``. Corner
    coordinates are handled relative to ``c0[:2]`` too (conditioning).
    """

    K: np.ndarray
    Kinv: np.ndarray
    R0: np.ndarray
    n: np.ndarray
    c0: np.ndarray

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def rotation(self, alpha: float) -> np.ndarray:
        return self.R0 @ rotation_z(alpha)

    def pose(self, alpha: float, c_xy: np.ndarray) -> Pose:
        c = np.array([self.c0[0] + c_xy[0], self.c0[1] + c_xy[1], self.c0[2]])
        return Pose.from_center(self.rotation(alpha), c)

    def corner_lines(
        self, alpha: np.ndarray, c_xy: np.ndarray, corner_rel: np.ndarray
    ) -> np.ndarray:
        """Images of the corners' verticals, ``K^-T (n x R (X - c))``.

        Parameters
        ----------
        alpha : (H,) radians; c_xy : (H, 2) m; corner_rel : (P, 2) or (H, P, 2) m.

        Returns
        -------
        (H, P, 3) lines with unit (a, b); oriented so that a rotation about the
        vertical moves every point by the same sign of distance.
        """
        d = (
            corner_rel - c_xy[:, None, :]
            if corner_rel.ndim == 2
            else corner_rel - c_xy[:, None, :]
        )
        h_cam = ransac_core.horizontal_in_camera(self.R0, alpha, d)  # (H, P, 3)
        lines = np.cross(self.n, h_cam) @ self.Kinv  # (K^-T v)^T = v^T K^-1
        norm = np.linalg.norm(lines[..., :2], axis=-1, keepdims=True)
        return lines / np.where(norm > 0, norm, 1.0)

    def project(
        self,
        alpha: np.ndarray,
        c_xy: np.ndarray,
        corner_rel: np.ndarray,
        z: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels and depths of corners at heights ``z``.

        Parameters
        ----------
        alpha : (H,); c_xy : (H, 2); corner_rel : (P, 2) or (H, P, 2);
        z : (H, P) or (P,) absolute heights (m).

        Returns
        -------
        px : (H, P, 2) undistorted pixels (NaN behind); depth : (H, P).
        """
        d = corner_rel - c_xy[:, None, :]
        X = ransac_core.horizontal_in_camera(self.R0, alpha, d)  # (H, P, 3)
        X = X + np.asarray(z - self.c0[2])[..., None] * self.R0[:, 2]
        depth = X[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = X[..., :2] / np.where(depth > 0, depth, np.nan)[..., None]
        px = uv @ self.K[:2, :2].T + self.K[:2, 2]
        return px, depth

    def bottom_heights(
        self,
        alpha: np.ndarray,
        c_xy: np.ndarray,
        corner_rel: np.ndarray,
        bottom_px: np.ndarray,
    ) -> np.ndarray:
        """Heights of the segments' bottoms on the corners' verticals.

        The bottom's viewing ray meets the corner's vertical (up to the small
        offset across it) where its horizontal run equals the corner's
        distance along the ray's horizontal direction.

        Parameters
        ----------
        alpha : (H,); c_xy : (H, 2); corner_rel : (H, P, 2) or (P, 2);
        bottom_px : (H, P, 2) or (P, 2) undistorted pixels.

        Returns
        -------
        (H, P) absolute heights (m); NaN where the corner is behind the ray.
        """
        ray_cam = (
            np.concatenate([bottom_px, np.ones(bottom_px.shape[:-1] + (1,))], axis=-1)
            @ self.Kinv.T
        )  # (..., 3)
        ray0 = ray_cam @ self.R0  # R0^T ray: VP-aligned frame, (..., 3)
        ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
        # R_z(alpha)^T ray0: world direction.
        rx = ca * ray0[..., 0] + sa * ray0[..., 1]
        ry = -sa * ray0[..., 0] + ca * ray0[..., 1]
        rz = np.broadcast_to(ray0[..., 2], rx.shape)
        d = corner_rel - c_xy[:, None, :]
        r2 = rx * rx + ry * ry
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d[..., 0] * rx + d[..., 1] * ry) / r2
            h = self.c0[2] + t * rz
        return np.where(t > 0, h, np.nan)


def make_view(camera: Camera, prior: Pose, n: np.ndarray) -> View:
    K = camera.K
    R_prior = prior.rotation
    # The smallest rotation bringing the prior's vertical onto the detected one.
    R0 = rotation_aligning(R_prior @ EZ, -n) @ R_prior
    return View(K=K, Kinv=np.linalg.inv(K), R0=R0, n=n, c0=prior.center.copy())


def tilt_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3) two unit vectors orthogonal to n (axes of small tilts)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def perturbed_view(
    view: View, log_focal: float, tilt: np.ndarray | None, tilt_axes: np.ndarray
) -> View:
    """The view with its focal length scaled by ``exp(log_focal)`` and its
    vertical tilted by ``tilt`` (2,) radians about ``tilt_axes``.

    The focal change keeps the vanishing point's PIXEL fixed (the detected
    quantity): the vertical direction ``n = K^-1 v`` follows the new ``K``
    by the smallest rotation; the tilt then moves the vanishing point.
    """
    from obliq_colmap.geometry import rotation_from_axis_angle

    K = view.K.copy()
    K[0, 0] *= math.exp(log_focal)
    K[1, 1] *= math.exp(log_focal)
    Kinv = np.linalg.inv(K)
    n_f = Kinv @ (view.K @ view.n)
    dR = rotation_aligning(view.n, n_f)
    if tilt is not None:
        dR = (
            rotation_from_axis_angle(tilt[0] * tilt_axes[0] + tilt[1] * tilt_axes[1])
            @ dR
        )
    n = dR @ view.n
    return View(K=K, Kinv=Kinv, R0=dR @ view.R0, n=n / np.linalg.norm(n), c0=view.c0)


def fit_planes(
    xy: np.ndarray, h: np.ndarray, weights: np.ndarray | None, ridge: float
) -> np.ndarray:
    """Ridge least-squares planes ``h = a x + b y + c`` for a batch.

    Parameters
    ----------
    xy : (H, S, 2) m (relative coordinates); h : (H, S) m; weights : (H, S) or
    None; ridge : damping of (a, b), m^2 (``(height_sigma / slope_sigma)^2``).

    Returns
    -------
    (H, 3) array (a, b, c) in the same relative coordinates; NaN where the
    heights are NaN.
    """
    w = np.ones(h.shape) if weights is None else weights
    w = np.where(np.isfinite(h), w, 0.0)
    hz = np.where(np.isfinite(h), h, 0.0)
    sw = w.sum(axis=1)  # (H,)
    sw_safe = np.where(sw > 0, sw, 1.0)
    mx = (w[..., None] * xy).sum(axis=1) / sw_safe[:, None]  # (H, 2)
    mh = (w * hz).sum(axis=1) / sw_safe
    d = xy - mx[:, None, :]
    dh = hz - mh[:, None]
    A = np.einsum("hs,hsi,hsj->hij", w, d, d) + ridge * np.eye(2)
    b = np.einsum("hs,hsi,hs->hi", w, d, dh)
    ab = np.linalg.solve(A, b[..., None])[..., 0]  # (H, 2)
    c = mh - np.sum(ab * mx, axis=1)
    out = np.column_stack([ab, c])
    out[sw <= 0] = np.nan
    return out


def plane_at(plane: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Heights of (H, 3) planes at (P, 2) or (H, P, 2) points -> (H, P)."""
    return (
        plane[:, None, 0] * xy[..., 0]
        + plane[:, None, 1] * xy[..., 1]
        + plane[:, None, 2]
    )
