"""Observed camera parameters: an INS attitude and GNSS centres (3 residual
rows per image), the principal points of uncalibrated cameras (2 rows per
camera), the vertical vanishing points of stage 1 (2 rows per image).

Each prior adds its terms to the camera block of the normal equations
(:meth:`add_to`) and its exact cost (:meth:`cost`); the solver builds them
with ``of(problem, setup, options)``, None where the option or the prior is
absent.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import calibration_matrix, skew, tangent_basis
from . import residuals as res
from .camera_block import CameraBlock, add_block, add_entries
from .problem import BundleOptions, BundleProblem
from .setup import Setup, State


class PosePrior:
    """An observed pose part: 3 rows ``errors(st) / sigma`` per active image
    (``k``), weight ``w = 1 / sigma^2``."""

    k: np.ndarray
    w: float
    #: Its name as a group of observations (:mod:`.components`).
    group_name = "prior"

    @property
    def n_rows(self) -> int:
        """Residual rows (observations) it adds to the redundancy."""
        return 3 * len(self.k)

    def errors(self, st: State) -> np.ndarray:
        raise NotImplementedError

    def cost(self, st: State) -> float:
        e = self.errors(st)
        return 0.5 * self.w * float(np.sum(e * e))

    def weighted_sum_of_squares(self, st: State) -> float:
        """``r^T W r`` of its rows (with their robust weights, if any)."""
        return 2.0 * self.cost(st)


class AttitudePrior(PosePrior):
    """Each active image's rotation observed: ``e = Log(R R_prior^T) / sigma``
    (3 rows, radians over radians), linearised in the solver's increment
    ``R <- Exp(omega) R`` as ``d e / d omega = I / sigma`` (exact at e = 0;
    the cost is evaluated exactly, so LM stays correct)."""

    group_name = "attitude prior"

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

    def add_to(self, H_cc: CameraBlock, g_c: np.ndarray, st: State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        add_entries(H_cc, self.cols, self.cols, self.w)
        np.add.at(g_c, self.cols, self.w * self.errors(st))


class CentrePrior(PosePrior):
    """Each active image's camera centre observed: ``e = (c - c_prior - s) /
    sigma`` (3 rows, metres over metres), ``s`` the priors' horizontal
    offset (held at zero unless ``S.shift_col``); linear in the solver's
    increments ``c <- c + dc``, ``s <- s + ds``."""

    group_name = "centre prior"

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

    def add_to(self, H_cc: CameraBlock, g_c: np.ndarray, st: State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        e = self.errors(st)
        add_entries(H_cc, self.cols, self.cols, self.w)
        np.add.at(g_c, self.cols, self.w * e)
        if self.shift_col >= 0:  # d e / d s = -(I2 over a zero row)
            s = self.shift_col + np.arange(2)
            add_entries(H_cc, s, s, self.w * len(self.k))
            for j in range(2):
                add_entries(H_cc, self.cols[:, j], s[j], -self.w)
                add_entries(H_cc, s[j], self.cols[:, j], -self.w)
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

    group_name = "principal point prior"

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

    def add_to(self, H_cc: CameraBlock, g_c: np.ndarray, st: State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r``, in place."""
        for cols, B, w, e in zip(
            self.cols, self.B, self.w_cam, self.errors(st), strict=True
        ):
            add_block(H_cc, cols, cols, w * (B.T @ B))
            g_c[cols] += w * (B.T @ e)


#: World down (z up) in the world frame.
_DOWN = np.array([0.0, 0.0, -1.0])


class VanishingPointObservation(PosePrior):
    """Each observed image's vertical vanishing point (stage 1): 2 rows.

    With ``d = R (0, 0, -1)`` the world's down direction as the camera sees
    it and ``m = +-normalise(K^-1 v)`` the VP's direction through the
    camera's CURRENT pinhole part (the VP moves with the focal length and the
    principal point), the error is ``e = T (m x d)``: the rotation vector
    from ``m`` to ``d`` (its length the sine of their angle) in a tangent
    basis ``T`` (2, 3) of the observation's direction at the start. It is
    whitened by stage 1's covariance of ``v`` propagated to that tangent
    plane (at the start; times ``BundleOptions.vp_sigma_scale``): ``z = L e``,
    ``L^T L = C_e^-1``. Robust: Cauchy on ``|z|^2`` (scale
    ``BundleOptions.vp_loss_scale``), so that a VP on a wrong pencil loses
    its pull; IRLS weights as the solver's map rows.

    Jacobians: rotation, analytic (``R <- Exp(omega) R``: ``dd = -[d]x
    omega``); intrinsics, exact through ``K`` (linear in fx, fy, cx, cy; the
    distortion terms do not move the pinhole direction): ``dm = -P K^-1 dK
    m / |K^-1 v|``, P the projector across ``m``.
    """

    group_name = "vertical VPs"

    def __init__(
        self,
        S: Setup,
        slots: np.ndarray,
        vps: np.ndarray,
        covariances: np.ndarray,
        params: list[np.ndarray],
        sigma_scale: float,
        loss_scale: float,
    ) -> None:
        vps = vps / np.linalg.norm(vps, axis=1, keepdims=True)
        keep, V, T, L = [], [], [], []
        for k, v, C in zip(slots, vps, covariances, strict=True):
            s = int(S.img_cam[k])
            Kinv = np.linalg.inv(calibration_matrix(S.camera_model[s], params[s]))
            u = Kinv @ v
            nu = np.linalg.norm(u)
            m = u / nu
            Jm = (np.eye(3) - np.outer(m, m)) / nu @ Kinv
            Cm = Jm @ C @ Jm.T
            Tk = tangent_basis(m).T  # (2, 3) rows
            A = -Tk @ skew(m)  # d e / d m at d = m
            Ce = A @ Cm @ A.T * sigma_scale**2
            try:
                Lk = np.linalg.cholesky(np.linalg.inv(Ce)).T  # L^T L = Ce^-1
            except np.linalg.LinAlgError:
                continue  # a degenerate covariance: no observation
            if not np.all(np.isfinite(Lk)):
                continue
            keep.append(int(k))
            V.append(v)
            T.append(Tk)
            L.append(Lk)
        self.k = np.array(keep, int)
        self.v = np.array(V).reshape(-1, 3)
        self.T = np.array(T).reshape(-1, 2, 3)
        self.L = np.array(L).reshape(-1, 2, 2)
        self.slot = S.img_cam[self.k]
        self.model = [S.camera_model[s] for s in self.slot]
        self.rot_cols = S.pose_col[self.k][:, None] + np.arange(3)
        self.basis = [S.refined[s] for s in self.slot]
        self.intr_cols = [
            S.intr_col[s] + np.arange(S.refined[s].shape[1])
            if S.intr_col[s] >= 0
            else np.zeros(0, int)
            for s in self.slot
        ]
        self.sigma_scale = sigma_scale
        self.c2 = loss_scale**2
        #: False: evaluated only (:meth:`statistics` with weight 0).
        self.in_fit = True

    @classmethod
    def of(cls, P: BundleProblem, S: Setup, opts: BundleOptions):
        if not opts.vp_observations or not P.vertical_vps:
            return None
        index = {iid: k for k, iid in enumerate(P.image_ids)}
        active = set(S.active_images.tolist())
        ids = [
            i for i in P.vertical_vps if i in index and index[i] in active
        ]  # images with map rows only: the others have no columns
        if not ids:
            return None
        ids.sort(key=lambda i: index[i])
        slots = np.array([index[i] for i in ids], int)
        vps = np.array([np.asarray(P.vertical_vps[i], float) for i in ids])
        covs = np.array([np.asarray(P.vertical_vp_covariances[i], float) for i in ids])
        params = [np.asarray(P.cameras[c].params, float) for c in S.camera_ids]
        obs = cls(S, slots, vps, covs, params, opts.vp_sigma_scale, opts.vp_loss_scale)
        obs.in_fit = opts.vp_in_fit
        return obs if len(obs.k) else None

    @property
    def n_rows(self) -> int:
        return 2 * len(self.k)

    def _directions(self, st: State, k: int):
        """(m, K^-1) of observation ``k``: the VP's unit direction through
        the current intrinsics (either orientation)."""
        Kinv = np.linalg.inv(
            calibration_matrix(self.model[k], st.params[int(self.slot[k])])
        )
        u = Kinv @ self.v[k]
        return u / np.linalg.norm(u), Kinv

    def angles(self, st: State) -> tuple[np.ndarray, np.ndarray]:
        """(K', 2) errors ``e`` (radians, tangent) and (K', 3) down
        directions ``d`` at ``st``."""
        d = st.R[self.k] @ _DOWN  # (K', 3)
        e = np.zeros((len(self.k), 2))
        for j in range(len(self.k)):
            m, _ = self._directions(st, j)
            if m @ d[j] < 0:
                m = -m
            e[j] = self.T[j] @ np.cross(m, d[j])
        return e, d

    def errors(self, st: State) -> np.ndarray:
        """(K', 2) whitened errors ``z = L e`` (scaled standard deviations)."""
        e, _ = self.angles(st)
        return np.einsum("kij,kj->ki", self.L, e)

    def chi2_stated(self, st: State) -> np.ndarray:
        """(K',) ``|z|^2`` against stage 1's stated covariance (scale 1)."""
        z = self.errors(st)
        return np.sum(z * z, axis=1) * self.sigma_scale**2

    def cost(self, st: State) -> float:
        z = self.errors(st)
        s = np.sum(z * z, axis=1)
        if not np.isfinite(self.c2):  # no robust loss (inf * log1p(0) is NaN)
            return 0.5 * float(np.sum(s))
        return 0.5 * float(np.sum(self.c2 * np.log1p(s / self.c2)))

    def weighted_sum_of_squares(self, st: State) -> float:
        """``sum w |z|^2`` with the Cauchy loss's IRLS weights."""
        z = self.errors(st)
        s = np.sum(z * z, axis=1)
        return float(np.sum(s / (1.0 + s / self.c2)))

    def jacobians(self, st: State):
        """Per observation: (z (2,), J_rot (2, 3), J_intr (2, q)), whitened."""
        d_all = st.R[self.k] @ _DOWN
        for j in range(len(self.k)):
            d = d_all[j]
            m, Kinv = self._directions(st, j)
            if m @ d < 0:
                m = -m
            T, L = self.T[j], self.L[j]
            z = L @ (T @ np.cross(m, d))
            # e = T [m]x d; d d = -[d]x omega
            J_rot = L @ (-T @ skew(m) @ skew(d))
            basis = self.basis[j]
            q = basis.shape[1]
            J_intr = np.zeros((2, q))
            if q:
                P = np.eye(3) - np.outer(m, m)
                params = st.params[int(self.slot[j])]
                for c in range(q):
                    # K is linear in its parameters; d(K^-1 v) = -K^-1 dK K^-1 v,
                    # so d m = -P K^-1 dK m per unit step (either orientation).
                    dK = calibration_matrix(self.model[j], params + basis[:, c])
                    dK -= calibration_matrix(self.model[j], params)
                    dm = -P @ (Kinv @ dK @ m)
                    J_intr[:, c] = L @ (-T @ skew(d) @ dm)
            yield j, z, J_rot, J_intr

    def add_to(self, H_cc: CameraBlock, g_c: np.ndarray, st: State) -> None:
        """Its terms of ``J^T W J`` and ``J^T W r`` (IRLS weight of the
        Cauchy loss), in place."""
        for j, z, J_rot, J_intr in self.jacobians(st):
            w = 1.0 / (1.0 + float(z @ z) / self.c2)
            J = np.concatenate([J_rot, J_intr], axis=1)
            cols = np.concatenate([self.rot_cols[j], self.intr_cols[j]])
            add_block(H_cc, cols, cols, w * (J.T @ J))
            g_c[cols] += w * (J.T @ z)

    def statistics(self, st: State, cofactor: np.ndarray) -> dict[str, np.ndarray]:
        """Per observation its share of the redundancy and its comparison
        with the solution without it, at ``st`` with ``cofactor`` the camera
        block's cofactor matrix (the inverse of the normal equations with
        these rows in, at their IRLS weights; unit variance factor).

        With ``z`` the whitened 2-vector, ``w`` its IRLS weight, ``J`` its
        whitened Jacobian and ``M = J Q J^T``:

        - ``omega`` (K',) ``= w |z|^2``: its part of ``v^T P v``;
        - ``redundancy`` (K',) ``= tr(I - w M)`` (Förstner's redundancy
          number of the 2 rows: 0 where the block's fit rests on this VP
          alone, 2 where the other observations fix the image's vertical);
        - ``loo_residual`` (K', 2): its residual at the solution without it
          (leave it out; exact for the linearised model),
          ``z0 = (I - w M)^-1 z``, and ``loo_cofactor`` (K', 2, 2): the
          others' cofactor of that direction, ``A = M (I - w M)^-1``;
        - ``test`` (K',) ``= z0^T (I + A)^-1 z0``: chi-square with 2 degrees
          of freedom where the VP and the current scale are right, whatever
          weight the VP had in the fit.

        All in the current whitened units (stage 1's covariance times
        ``sigma_scale^2``); NaN where ``cofactor`` is not finite.
        """
        n = len(self.k)
        out = {
            "omega": np.zeros(n),
            "redundancy": np.full(n, np.nan),
            "test": np.full(n, np.nan),
            "loo_residual": np.full((n, 2), np.nan),
            "loo_cofactor": np.full((n, 2, 2), np.nan),
        }
        ok = np.all(np.isfinite(cofactor))
        out["w"] = np.zeros(n)
        for j, z, _, _ in self.jacobians(st):
            out["w"][j] = 1.0 / (1.0 + float(z @ z) / self.c2) if self.in_fit else 0.0
        for j, z, J_rot, J_intr in self.jacobians(st):
            w = out["w"][j]
            out["omega"][j] = w * float(z @ z)
            if not ok:
                continue
            J = np.concatenate([J_rot, J_intr], axis=1)
            cols = np.concatenate([self.rot_cols[j], self.intr_cols[j]])
            M = J @ cofactor[np.ix_(cols, cols)] @ J.T
            R = np.eye(2) - w * M
            try:
                z0 = np.linalg.solve(R, z)
                A = M @ np.linalg.inv(R)
                t = float(z0 @ np.linalg.solve(np.eye(2) + A, z0))
            except np.linalg.LinAlgError:
                continue
            out["redundancy"][j] = float(np.trace(R))
            out["loo_residual"][j] = z0
            out["loo_cofactor"][j] = A
            out["test"][j] = t
        return out
