"""Normal equations and the damped step with the heights eliminated (Schur).

The camera block C (6 per image + refined intrinsics, dense: a few hundred
unknowns) and the DIAGONAL height block h; Marquardt damping
``H + lambda * clip(diag H, 1e-6, 1e32)`` on both; the Schur complement
``S = H_CC - E^T D_h^-1 E`` solved with the gauge constraints as a KKT
system (:mod:`.linear`: dense, sparse for large blocks), then
back-substitution of the heights.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .coupling import Coupling
from .linear import kkt_solve
from .setup import Setup


def normal_equations(S: Setup, Jc, Jh, r, w):
    """Blocks of J^T W J and J^T W r: dense camera block, diagonal heights,
    and the (Nh, L) blocks F of the coupling E (rows with a height; products
    with E by :class:`Coupling`)."""
    n = S.n_red + 1
    H_cc = np.zeros((n, n))
    g_c = np.zeros(n)
    wJ = Jc * w[:, None]
    for a, b, cols in S.image_runs:
        H_cc[np.ix_(cols, cols)] += Jc[a:b].T @ wJ[a:b]
        g_c[cols] += wJ[a:b].T @ r[a:b]
    m = S.has_h
    H_hh = np.bincount(S.hidx[m], (w * Jh * Jh)[m], S.n_heights)
    g_h = np.bincount(S.hidx[m], (w * Jh * r)[m], S.n_heights)
    F = np.multiply(Jc, (w * Jh)[:, None], order="C")
    if S.h_runs != [(0, len(r))]:
        F = np.concatenate([F[a:b] for a, b in S.h_runs] or [F[:0]])
    return H_cc[:-1, :-1], g_c[:-1], H_hh, g_h, F


class Schur:
    """``E^T Dinv E`` and ``E^T Dinv g_h``, ``Dinv = (H_hh + lam D_h)^-1``,
    for any damping ``lam`` of one build.

    Where the height block's damping is its own diagonal (``D_h = H_hh``,
    unclipped) they are ``E^T H_hh^-1 E / (1 + lam)`` and
    ``E^T H_hh^-1 g_h / (1 + lam)``: that part is formed once per
    linearisation, not once per trial step, from the blocks F per image pair
    (:class:`Coupling`); the clipped rows (few) are added per step.
    """

    def __init__(self, coupling: Coupling, H_hh: np.ndarray, g_h, F) -> None:
        own = (H_hh >= 1e-6) & (H_hh <= 1e32)  # where clip(H_hh) = H_hh
        scale = np.zeros(len(H_hh))
        scale[own] = 1.0 / np.sqrt(H_hh[own])
        self.base = coupling.gram(F, scale)
        self.base_rhs = coupling.rmatvec(F, scale * scale * g_h)
        self.rest = np.flatnonzero(~own)
        self.E_rest = coupling.dense_rows(F, self.rest) if len(self.rest) else None

    def at(self, H_hh: np.ndarray, g_h: np.ndarray, lam: float):
        """(C, C) ``E^T Dinv E`` and (C,) ``E^T Dinv g_h`` at damping ``lam``."""
        out, rhs = self.base / (1.0 + lam), self.base_rhs / (1.0 + lam)
        if self.E_rest is not None:
            h = H_hh[self.rest]
            dinv = 1.0 / (h + lam * np.clip(h, 1e-6, 1e32))
            out = out + self.E_rest.T @ (dinv[:, None] * self.E_rest)
            rhs = rhs + (dinv * g_h[self.rest]) @ self.E_rest
        return out, rhs


def damped_step(S: Setup, H_cc, g_c, H_hh, g_h, F, lam, schur: Schur, ties=None):
    """Solve the damped normal equations by the Schur complement on the
    heights and, with ``ties`` (:class:`~obliq_colmap.bundle.ties.TieRows`,
    linearised), on the tie points. Returns the camera, height and (T, 3)
    point steps and the damping diagonals of the cameras and heights."""
    D_c = np.clip(np.diag(H_cc), 1e-6, 1e32)
    D_h = np.clip(H_hh, 1e-6, 1e32)
    dinv = 1.0 / (H_hh + lam * D_h)
    if S.n_heights:
        reduced, coupled = schur.at(H_hh, g_h, lam)
        rhs = -g_c + coupled
    else:
        reduced = 0.0
        rhs = -g_c
    A_red = H_cc - reduced
    if ties is not None:
        t_reduced, t_coupled = ties.schur(lam)
        A_red = A_red - t_reduced
        rhs = rhs + t_coupled
    A_red[np.diag_indices_from(A_red)] += lam * D_c
    dc = kkt_solve(A_red, S.A, rhs)  # dense, or sparse LU for large blocks
    dh = -dinv * (g_h + S.coupling.matvec(F, dc)) if S.n_heights else np.zeros(0)
    dp = ties.step(dc, lam) if ties is not None else np.zeros((0, 3))
    return dc, dh, dp, D_c, D_h


# --- 3-D point blocks (tie points) -------------------------------------------
# Kept apart from the heights' path above: a tie point is a full 3x3 block,
# eliminated by batched 3x3 inverses (numpy), one block per point.


def point_normal_blocks(Jc, Jp, r, w, pidx, n_points: int):
    """Blocks of the normal equations over the rows of tie-point residuals.

    Jc: (N, C) camera columns of each row, Jp: (N, 3) point columns, r, w:
    (N,) residual and weight, pidx: (N,) point of each row. Returns H_pp
    (P, 3, 3), g_p (P, 3), the coupling W (P, 3, C) = sum J_p^T w J_c per
    point, and the camera part H_cc (C, C), g_c (C,) of these rows.
    """
    wJp = Jp * w[:, None]
    H_pp = np.zeros((n_points, 3, 3))
    np.add.at(H_pp, pidx, wJp[:, :, None] * Jp[:, None, :])
    g_p = np.zeros((n_points, 3))
    np.add.at(g_p, pidx, wJp * r[:, None])
    # sum over each point's rows as a sparse (P, N) selector times dense rows:
    # np.add.at on the (P, 3, C) array took 1.8x as long at the paper's scale
    sel = sp.csr_matrix(
        (np.ones(len(pidx)), (pidx, np.arange(len(pidx)))), shape=(n_points, len(pidx))
    )
    W = np.stack([sel @ (Jc * wJp[:, a : a + 1]) for a in range(3)], axis=1)
    wJc = Jc * w[:, None]
    return H_pp, g_p, W, Jc.T @ wJc, wJc.T @ r


def point_schur(H_pp, g_p, W, lam: float):
    """Eliminate the damped point blocks ``H_pp + lam clip(diag H_pp)``.

    Returns (C, C) ``W^T Hinv W``, (C,) ``W^T Hinv g_p`` and the (P, 3, 3)
    inverses Hinv for :func:`point_back_substitution`.
    """
    d = np.clip(np.diagonal(H_pp, axis1=1, axis2=2), 1e-6, 1e32)
    damped = H_pp + lam * d[:, :, None] * np.eye(3)
    Hinv = np.linalg.inv(damped)
    HW = Hinv @ W  # (P, 3, C)
    reduced = np.einsum("pkc,pkd->cd", W, HW, optimize=True)
    coupled = np.einsum("pkc,pk->c", HW, g_p, optimize=True)
    return reduced, coupled, Hinv


def point_back_substitution(Hinv, g_p, W, dc) -> np.ndarray:
    """(P, 3) point steps ``-Hinv (g_p + W dc)`` for the camera step dc (C,)."""
    return -np.einsum("pij,pj->pi", Hinv, g_p + W @ dc)
