"""Observed camera parameters: an INS attitude and GNSS centres (3 residual
rows per image), the principal points of uncalibrated cameras (2 rows per
camera).

Each prior adds its terms to the camera block of the normal equations
(:meth:`add_to`) and its exact cost (:meth:`cost`); the solver builds them
with ``of(problem, setup, options)``, None where the option or the prior is
absent.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from . import residuals as res
from .problem import BundleOptions, BundleProblem
from .setup import Setup, State


class PosePrior:
    """An observed pose part: 3 rows ``errors(st) / sigma`` per active image
    (``k``), weight ``w = 1 / sigma^2``."""

    k: np.ndarray
    w: float

    @property
    def n_rows(self) -> int:
        """Residual rows (observations) it adds to the redundancy."""
        return 3 * len(self.k)

    def errors(self, st: State) -> np.ndarray:
        raise NotImplementedError

    def cost(self, st: State) -> float:
        e = self.errors(st)
        return 0.5 * self.w * float(np.sum(e * e))


class AttitudePrior(PosePrior):
    """Each active image's rotation observed: ``e = Log(R R_prior^T) / sigma``
    (3 rows, radians over radians), linearised in the solver's increment
    ``R <- Exp(omega) R`` as ``d e / d omega = I / sigma`` (exact at e = 0;
    the cost is evaluated exactly, so LM stays correct)."""

    def __init__(self, S: Setup, prior: np.ndarray, sigma_rad: float) -> None:
        self.k = S.active_images  # (K',) slots of the images with rows
        self.cols = S.pose_col[self.k][:, None] + np.arange(3)  # (K', 3)
        self.prior = prior[self.k]  # (K', 3, 3)
        self.w = 1.0 / sigma_rad**2

    @classmethod
    def of(cls, P: BundleProblem, S: Setup, opts: BundleOptions):
        if opts.rotation_prior_sigma_deg is None or P.prior_rotations is None:
            return None
        prior = np.stack([np.asarray(P.prior_rotations[i], float) for i in P.image_ids])
        return cls(S, prior, np.deg2rad(opts.rotation_prior_sigma_deg))

    def errors(self, st: State) -> np.ndarray:
        """(K', 3) rotation vectors of R R_prior^T, radians."""
        R = st.R[self.k] @ np.transpose(self.prior, (0, 2, 1))
        return Rotation.from_matrix(R).as_rotvec()

    def add_to(self, H_cc: np.ndarray, g_c: np.ndarray, st: State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        H_cc[self.cols, self.cols] += self.w
        np.add.at(g_c, self.cols, self.w * self.errors(st))


class CentrePrior(PosePrior):
    """Each active image's camera centre observed: ``e = (c - c_prior - s) /
    sigma`` (3 rows, metres over metres), ``s`` the priors' horizontal
    offset (held at zero unless ``S.shift_col``); linear in the solver's
    increments ``c <- c + dc``, ``s <- s + ds``."""

    def __init__(self, S: Setup, prior: np.ndarray, sigma_m: float) -> None:
        self.k = S.active_images
        self.cols = S.pose_col[self.k][:, None] + np.arange(3, 6)  # (K', 3)
        self.prior = prior[self.k]  # (K', 3)
        self.w = 1.0 / sigma_m**2
        self.shift_col = S.shift_col

    @classmethod
    def of(cls, P: BundleProblem, S: Setup, opts: BundleOptions):
        if opts.position_prior_sigma_m is None or P.prior_centers is None:
            return None
        prior = np.stack([np.asarray(P.prior_centers[i], float) for i in P.image_ids])
        return cls(S, prior, opts.position_prior_sigma_m)

    def errors(self, st: State) -> np.ndarray:
        """(K', 3) centre minus offset prior, metres."""
        e = st.c[self.k] - self.prior
        e[:, :2] -= st.shift
        return e

    def add_to(self, H_cc: np.ndarray, g_c: np.ndarray, st: State) -> None:
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


class PrincipalPointPrior(PosePrior):
    """Each refined camera's principal point observed at the priors':
    ``e = (pp - pp_prior) / sigma`` (2 rows per camera, pixels over pixels),
    linear in the camera's parameter step ``params += basis @ d``.

    An uncalibrated camera's principal point is known to lie near the image
    centre; free, it trades with the tilt, the focal length and the camera
    height along the block's weak vertical mode and can wander by a hundred
    pixels where a head's images leave that mode open (long lenses, few
    facades).
    """

    def __init__(
        self,
        S: Setup,
        prior_pp: list[np.ndarray],
        sigma_frac: float,
        sizes: list[tuple[int, int]],
    ) -> None:
        self.slots, self.cols, self.B, self.index, self.prior = [], [], [], [], []
        scale = []
        for s, basis in enumerate(S.refined):
            _, pp, _ = res.focal_principal_extra_indices(S.camera_model[s])
            B = basis[list(pp), :]  # (2, q): d pp / d step
            if S.intr_col[s] < 0 or not np.any(B):
                continue
            self.slots.append(s)
            self.cols.append(S.intr_col[s] + np.arange(basis.shape[1]))
            self.B.append(B)
            self.index.append(list(pp))
            self.prior.append(np.asarray(prior_pp[s], float).reshape(2))
            scale.append(sigma_frac * max(sizes[s]))
        self.k = np.array(self.slots, int)
        #: Per camera weight 1 / sigma^2 (sigma in px of its own image).
        self.w_cam = 1.0 / np.square(np.array(scale, float))
        self.w = 1.0

    @classmethod
    def of(cls, P: BundleProblem, S: Setup, opts: BundleOptions):
        sigma = opts.principal_point_prior_sigma
        if sigma is None or not opts.refine_principal_point:
            return None
        given = P.prior_principal_points or {}
        prior_pp = [
            given[c] if c in given else P.cameras[c].K[:2, 2] for c in S.camera_ids
        ]
        prior = cls(S, prior_pp, sigma, S.camera_size)
        return prior if len(prior.k) else None

    @property
    def n_rows(self) -> int:
        return 2 * len(self.k)

    def errors(self, st: State) -> np.ndarray:
        """(M, 2) principal point minus the priors', px."""
        return np.array(
            [
                st.params[s][i] - p
                for s, i, p in zip(self.slots, self.index, self.prior, strict=True)
            ]
        ).reshape(-1, 2)

    def cost(self, st: State) -> float:
        e = self.errors(st)
        return 0.5 * float(np.sum(self.w_cam[:, None] * e * e))

    def add_to(self, H_cc: np.ndarray, g_c: np.ndarray, st: State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        for cols, B, w, e in zip(
            self.cols, self.B, self.w_cam, self.errors(st), strict=True
        ):
            H_cc[np.ix_(cols, cols)] += w * (B.T @ B)
            g_c[cols] += w * (B.T @ e)
