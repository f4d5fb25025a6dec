"""Tie points in the bundle: reprojection rows and their eliminated 3x3 blocks.

A tie point (a feature matched across images, ``BundleProblem.tie_xyz``) is a
free 3D unknown; each observation gives two rows, projection minus observed
pixel, weighted ``1 / tie_sigma_px^2`` under the robust loss on the
observation's squared 2D error. The tie points tie the images to each other
in 3D, where the map's rows tie each image to the map alone; across heads
they are what holds each head's tilt, focal and height to the others'.

Elimination. Every row touches one point, so the points' block of the
normal equations is block-diagonal, (T, 3, 3). Damping each point's block by
``lam H_pp`` (Marquardt's scaling with the block instead of its diagonal;
any positive definite scaling is a valid trust region) makes the eliminated
part ``W^T H_pp^-1 W / (1 + lam)``: formed once per linearisation, not once
per trial step. Whitened by the Cholesky factor of each block
(``H_pp = L L^T``, coordinates ``L^T X``), the three coordinates of a point
decouple, and ``L^-1 W`` has the heights' structure: one row per whitened
coordinate and observation over the observing image's columns, which
:class:`~obliq_colmap.bundle.coupling.Coupling` multiplies out per image pair.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import residuals as res
from .camera_block import CameraBlock, add_block
from .coupling import Coupling, runs
from .loss import robust_loss
from .problem import BundleOptions, BundleProblem
from .setup import Setup, State

__all__ = ["TieRows"]

#: Observations per evaluation call (as the map rows' chunks).
_CHUNK = 8192


class _TieGroup(NamedTuple):
    """Observations ``[start, end)`` of one camera model: its cameras' runs
    (slot, start, end), expansion matrix, camera slots and each row's
    position among them."""

    model: str
    start: int
    end: int
    cam_runs: list[tuple[int, int, int]]
    E: np.ndarray
    cams: list[int]
    cam_local: np.ndarray


class TieRows:
    """Static layout of the tie observations and their per-build blocks.

    The observations are sorted by camera model, camera and image (each
    evaluation group a slice, each image a run); ``order`` maps back to the
    problem's order.
    """

    def __init__(self, P: BundleProblem, S: Setup, opts: BundleOptions) -> None:
        self.opts = opts
        self.n_points = len(P.tie_xyz)
        models = S.camera_model
        rank = np.searchsorted(sorted(set(models)), models)
        cam = S.img_cam[P.tie_image]
        order = np.lexsort((P.tie_image, cam, rank[cam]))
        self.order = order
        self.img = P.tie_image[order]
        self.point = P.tie_point[order]
        self.xy = np.ascontiguousarray(P.tie_xy[order].T)  # (2, O)
        self.cam = S.img_cam[self.img]
        n_obs, L = len(self.img), S.L
        self.weight = 1.0 / opts.tie_sigma_px**2
        cols = np.full((n_obs, L), S.n_red)
        cols[:, :6] = S.pose_col[self.img][:, None] + np.arange(6)
        for s, basis in enumerate(S.refined):
            m = self.cam == s
            q = basis.shape[1]
            cols[np.ix_(m, 6 + np.arange(q))] = S.intr_col[s] + np.arange(q)
        self.cols = cols
        self.image_runs = [(a, b, cols[a]) for a, b in runs(self.img)]
        self.groups = []
        for a, b in runs(rank[self.cam]):
            for c in range(a, b, _CHUNK):
                e = min(c + _CHUNK, b)
                cam_runs = [
                    (int(self.cam[c + i]), c + i, c + j) for i, j in runs(self.cam[c:e])
                ]
                cams = [k for k, _, _ in cam_runs]
                self.groups.append(
                    _TieGroup(
                        models[self.cam[c]],
                        c,
                        e,
                        cam_runs,
                        res.expansion_matrix(models[self.cam[c]]),
                        cams,
                        np.searchsorted(cams, self.cam[c:e]),
                    )
                )
        # The whitened coupling: 3 rows per observation, one per coordinate.
        self.coupling = Coupling(
            np.repeat(self.img, 3),
            (3 * self.point[:, None] + np.arange(3)).ravel(),
            np.repeat(cols, 3, axis=0),
            3 * self.n_points,
            S.n_red,
            sparse=S.sparse_camera,
        )

    # --- residuals -----------------------------------------------------------

    def evaluate(self, S: Setup, st: State, jac: bool):
        """(O, 2) residuals (px) and, if jac, the (O, 2, L) camera and (O, 2, 3)
        point Jacobians."""
        n_obs = len(self.img)
        r = np.empty((n_obs, 2))
        Jc = np.zeros((n_obs, 2, S.L)) if jac else None
        Jp = np.empty((n_obs, 2, 3)) if jac else None
        Rk = st.R.transpose(1, 2, 0)
        for g in self.groups:
            a, b, cam_runs = g.start, g.end, g.cam_runs
            img = self.img[a:b]
            R = np.take(Rk, img, axis=2)
            D = st.points[self.point[a:b]].T - st.c[img].T
            full = g.E @ np.stack([st.params[c] for c in g.cams], 1)
            if len(g.cams) > 1:
                full = full[:, g.cam_local]
            out = res.reprojection_rows(g.model, full, R, D, self.xy[:, a:b], jac)
            r[a:b] = out[0].T
            if jac:
                _, d_pose, d_params, d_point = out
                Jc[a:b, :, :6] = d_pose.transpose(2, 0, 1)
                Jp[a:b] = d_point.transpose(2, 0, 1)
                for s, i, j in cam_runs:
                    basis = S.refined[s]
                    q = basis.shape[1]
                    if q:
                        Jc[i:j, :, 6 : 6 + q] = np.einsum(
                            "rpn,pq->nrq", d_params[:, :, i - a : j - a], basis
                        )
        return r, Jc, Jp

    def losses(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(O,) rho and rho' of each observation's squared 2D error."""
        o = self.opts
        return robust_loss(o.loss, o.tie_loss_scale_px, np.sum(r * r, axis=1))

    def cost(self, S: Setup, st: State) -> float:
        r, _, _ = self.evaluate(S, st, jac=False)
        c = 0.5 * self.weight * float(np.sum(self.losses(r)[0]))
        return c if np.isfinite(c) else np.inf

    # --- normal equations ----------------------------------------------------

    def linearise(self, S: Setup, st: State, H_cc: CameraBlock, g_c: np.ndarray):
        """Add the rows' camera terms to ``H_cc``, ``g_c`` (in place) and keep
        the point blocks and the whitened coupling of this linearisation."""
        r, Jc, Jp = self.evaluate(S, st, jac=True)
        w = self.weight * self.losses(r)[1]  # (O,)
        wJc = Jc * w[:, None, None]
        for a, b, cols in self.image_runs:
            ok = cols < S.n_red  # not the padding column
            c, q = cols[ok], int(ok.sum())
            A = Jc[a:b][:, :, ok].reshape(-1, q)
            wA = wJc[a:b][:, :, ok].reshape(-1, q)
            add_block(H_cc, c, c, A.T @ wA)
            g_c[c] += wA.T @ r[a:b].ravel()
        T = self.n_points
        wJp = Jp * w[:, None, None]
        Hpp_o = np.einsum("ora,orb->oab", wJp, Jp)  # (O, 3, 3)
        H_pp = np.zeros((T, 9))
        for e in range(9):
            H_pp[:, e] = np.bincount(self.point, Hpp_o.reshape(-1, 9)[:, e], T)
        H_pp = H_pp.reshape(T, 3, 3)
        gp_o = np.einsum("ora,or->oa", wJp, r)
        g_p = np.stack([np.bincount(self.point, gp_o[:, a], T) for a in range(3)], 1)
        F = np.einsum("ora,orl->oal", wJp, Jc)  # (O, 3, L): W's blocks
        # Cholesky of each point block (a tiny ridge: a point seen along
        # nearly parallel rays is weak in depth, not undefined)
        ridge = 1e-12 * np.trace(H_pp, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        Lp = np.linalg.cholesky(H_pp + ridge + 1e-300 * np.eye(3))
        self.Linv = np.linalg.inv(Lp)  # (T, 3, 3)
        self.H_pp, self.g_p = H_pp, g_p
        self.Ft = np.einsum("oab,obl->oal", self.Linv[self.point], F).reshape(-1, S.L)
        self.gt = np.einsum("pab,pb->pa", self.Linv, g_p).ravel()
        ones = np.ones(3 * T)
        self.reduced = self.coupling.gram(self.Ft, ones)
        self.rhs = self.coupling.rmatvec(self.Ft, self.gt)

    def schur(self, lam: float):
        """(C, C) ``W^T B^-1 W`` (dense, or CSR for a sparse camera block)
        and (C,) ``W^T B^-1 g_p`` for the damped point blocks
        ``B = (1 + lam) H_pp``."""
        return self.reduced / (1.0 + lam), self.rhs / (1.0 + lam)

    def step(self, dc: np.ndarray, lam: float) -> np.ndarray:
        """(T, 3) point steps ``-B^-1 (g_p + W dc)`` for the camera step dc."""
        y = (self.gt + self.coupling.matvec(self.Ft, dc)).reshape(-1, 3)
        return -np.einsum("pba,pb->pa", self.Linv, y) / (1.0 + lam)

    def predicted(self, dp: np.ndarray, lam: float) -> float:
        """The points' part of LM's predicted decrease (damping ``lam H_pp``)."""
        quad = float(np.einsum("pa,pab,pb->", dp, self.H_pp, dp))
        return 0.5 * (lam * quad - float(np.sum(self.g_p * dp)))
