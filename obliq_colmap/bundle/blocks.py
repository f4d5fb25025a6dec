"""Unknowns eliminated by their 3x3 blocks: the layout and algebra shared by
the tie points (:mod:`.ties`) and the facade lines (:mod:`.facade_lines`).

Each observation has two rows that touch one image's camera columns and one
3-vector unknown (a tie point's position; a facade line's height, offset and
direction), so the unknowns' block of the normal equations is
block-diagonal, (T, 3, 3). Damping each block by ``lam H_pp`` (Marquardt's
scaling with the block instead of its diagonal; any positive definite
scaling is a valid trust region) makes the eliminated part
``W^T H_pp^-1 W / (1 + lam)``: formed once per linearisation, not once per
trial step. Whitened by the Cholesky factor of each block (``H_pp = L L^T``,
coordinates ``L^T X``), the three coordinates decouple, and ``L^-1 W`` has
the heights' structure: one row per whitened coordinate and observation over
the observing image's columns, which
:class:`~obliq_colmap.bundle.coupling.Coupling` multiplies out per image pair.

A subclass gives :meth:`EliminatedBlocks.evaluate` (residuals and both
Jacobians of its observations, in the layout's order), optionally
:meth:`EliminatedBlocks.prior` (rows on the unknowns alone), and the name of
its unknowns in :class:`~obliq_colmap.bundle.setup.State`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import residuals as res
from .camera_block import CameraBlock, add_block
from .coupling import Coupling, runs
from .loss import robust_loss
from .problem import BundleOptions
from .setup import Setup, State

__all__ = ["EliminatedBlocks", "ObservationGroup", "write_intrinsics"]

#: Observations per evaluation call (as the map rows' chunks).
_CHUNK = 8192


class ObservationGroup(NamedTuple):
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

    def full_params(self, params: list[np.ndarray]) -> np.ndarray:
        """(8, 1) or (8, n) general parameters of the group's rows."""
        full = self.E @ np.stack([params[c] for c in self.cams], 1)
        return full if len(self.cams) == 1 else full[:, self.cam_local]


def write_intrinsics(
    S: Setup, g: ObservationGroup, d_params: np.ndarray, Jc: np.ndarray
) -> None:
    """Write the refined intrinsics' columns of a group's (2, P, n) parameter
    derivatives into ``Jc`` (O, 2, L), in place."""
    for s, i, j in g.cam_runs:
        basis = S.refined[s]
        q = basis.shape[1]
        if q:
            Jc[i:j, :, 6 : 6 + q] = np.einsum(
                "rpn,pq->nrq", d_params[:, :, i - g.start : j - g.start], basis
            )


class EliminatedBlocks:
    """Static layout of the observations of 3-vector unknowns and their
    per-build blocks.

    The observations are sorted by camera model, camera and image (each
    evaluation group a slice, each image a run); ``order`` maps the layout's
    order back to the caller's.

    Parameters
    ----------
    S : Setup
    image, block : (O,) int arrays, image index and unknown of each
        observation (the caller's order).
    n_blocks : int, the number of unknowns T.
    weight : float, cost weight of each row (1 / sigma^2).
    loss_scale_px : float, scale of the robust loss (``BundleOptions.loss``)
        on each observation's squared 2-row error.
    """

    #: The attribute of :class:`State` holding the (T, 3) unknowns.
    state_attr = ""
    #: Its name as a group of observations (:mod:`.components`).
    group_name = ""

    def __init__(
        self,
        S: Setup,
        opts: BundleOptions,
        image: np.ndarray,
        block: np.ndarray,
        n_blocks: int,
        weight: float,
        loss_scale_px: float,
    ) -> None:
        self.opts = opts
        self.n_points = n_blocks
        self.weight = weight
        self.loss_scale_px = loss_scale_px
        models = S.camera_model
        rank = np.searchsorted(sorted(set(models)), models)
        cam = S.img_cam[image]
        order = np.lexsort((image, cam, rank[cam]))
        self.order = order
        self.img = image[order]
        self.point = block[order]
        self.cam = S.img_cam[self.img]
        n_obs, L = len(self.img), S.L
        cols = np.full((n_obs, L), S.n_red)
        cols[:, :6] = S.pose_col[self.img][:, None] + np.arange(6)
        for s, basis in enumerate(S.refined):
            m = self.cam == s
            q = basis.shape[1]
            cols[np.ix_(m, 6 + np.arange(q))] = S.intr_col[s] + np.arange(q)
        self.cols = cols
        self.image_runs = [(a, b, cols[a]) for a, b in runs(self.img)]
        self.groups: list[ObservationGroup] = []
        for a, b in runs(rank[self.cam]):
            for c in range(a, b, _CHUNK):
                e = min(c + _CHUNK, b)
                cam_runs = [
                    (int(self.cam[c + i]), c + i, c + j) for i, j in runs(self.cam[c:e])
                ]
                cams = [k for k, _, _ in cam_runs]
                self.groups.append(
                    ObservationGroup(
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

    # --- to be given by a subclass --------------------------------------------

    def evaluate(self, S: Setup, st: State, jac: bool):
        """(O, 2) residuals (px) and, if jac, the (O, 2, L) camera and
        (O, 2, 3) unknowns' Jacobians, in the layout's order."""
        raise NotImplementedError

    def prior(self, st: State) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Rows on the unknowns alone, as their (T, 3, 3) normal block, (T, 3)
        gradient and cost at ``st``; None: none."""
        return None

    @property
    def n_prior_rows(self) -> int:
        """The number of rows :meth:`prior` stands for (the redundancy)."""
        return 0

    # --- residuals -----------------------------------------------------------

    def outputs(self, S: Setup, st: State, jac: bool):
        """For :meth:`evaluate`: the (O, 2) residuals, (O, 2, L) camera and
        (O, 2, 3) unknowns' Jacobians to fill (None without ``jac``), and
        the rotations as a (3, 3, K) array."""
        n_obs = len(self.img)
        r = np.empty((n_obs, 2))
        Jc = np.zeros((n_obs, 2, S.L)) if jac else None
        Jp = np.empty((n_obs, 2, 3)) if jac else None
        return r, Jc, Jp, st.R.transpose(1, 2, 0)

    def unknowns(self, st: State) -> np.ndarray:
        return getattr(st, self.state_attr)

    def losses(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(O,) rho and rho' of each observation's squared 2D error."""
        o = self.opts
        return robust_loss(o.loss, self.loss_scale_px, np.sum(r * r, axis=1))

    def cost(self, S: Setup, st: State) -> float:
        r, _, _ = self.evaluate(S, st, jac=False)
        c = 0.5 * self.weight * float(np.sum(self.losses(r)[0]))
        prior = self.prior(st)
        if prior is not None:
            c += prior[2]
        return c if np.isfinite(c) else np.inf

    def weighted_sum_of_squares(self, S: Setup, st: State) -> float:
        """``r^T W r`` with the robust weights, and the prior rows' part (the
        variance factor's numerator)."""
        r = self.evaluate(S, st, jac=False)[0]
        wss = self.weight * float(np.sum(self.losses(r)[1] * np.sum(r * r, 1)))
        prior = self.prior(st)
        return wss + (2.0 * prior[2] if prior is not None else 0.0)

    @property
    def redundancy(self) -> int:
        """Rows minus unknowns."""
        return 2 * len(self.img) + self.n_prior_rows - 3 * self.n_points

    # --- normal equations ----------------------------------------------------

    def linearise(self, S: Setup, st: State, H_cc: CameraBlock, g_c: np.ndarray):
        """Add the rows' camera terms to ``H_cc``, ``g_c`` (in place) and keep
        the unknowns' blocks and the whitened coupling of this linearisation."""
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
        prior = self.prior(st)
        if prior is not None:
            H_pp, g_p = H_pp + prior[0], g_p + prior[1]
        F = np.einsum("ora,orl->oal", wJp, Jc)  # (O, 3, L): W's blocks
        # Cholesky of each block (a tiny ridge: a point seen along nearly
        # parallel rays is weak in depth, not undefined)
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
        and (C,) ``W^T B^-1 g_p`` for the damped blocks ``B = (1 + lam) H_pp``."""
        return self.reduced / (1.0 + lam), self.rhs / (1.0 + lam)

    def step(self, dc: np.ndarray, lam: float) -> np.ndarray:
        """(T, 3) steps ``-B^-1 (g_p + W dc)`` for the camera step dc."""
        y = (self.gt + self.coupling.matvec(self.Ft, dc)).reshape(-1, 3)
        return -np.einsum("pba,pb->pa", self.Linv, y) / (1.0 + lam)

    def predicted(self, dp: np.ndarray, lam: float) -> float:
        """The unknowns' part of LM's predicted decrease (damping ``lam H_pp``)."""
        quad = float(np.einsum("pa,pab,pb->", dp, self.H_pp, dp))
        return 0.5 * (lam * quad - float(np.sum(self.g_p * dp)))
