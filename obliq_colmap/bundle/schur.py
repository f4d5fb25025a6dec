"""Normal equations and the damped step with the heights eliminated (Schur).

The camera block C (6 per image + refined intrinsics; dense for a few
hundred unknowns, gathered sparse above :data:`~.linear.SPARSE_MIN_UNKNOWNS`,
:mod:`.camera_block`) and the DIAGONAL height block h; Marquardt damping
``H + lambda * clip(diag H, 1e-6, 1e32)`` on both; the Schur complement
``S = H_CC - E^T D_h^-1 E`` solved with the gauge constraints as a KKT
system (:mod:`.linear`: dense, sparse for large blocks), then
back-substitution of the heights.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .camera_block import add_block, diagonal, empty
from .coupling import Coupling
from .linear import kkt_solve
from .setup import Setup, work_buffer


def normal_equations(S: Setup, Jc, Jh, r, w):
    """Blocks of J^T W J and J^T W r: the camera block (a dense array, or
    :class:`~.camera_block.SparseTerms` to be summed after the other rows'
    terms: :func:`~.camera_block.finish`), diagonal heights, and the (Nh, L)
    blocks F of the coupling E (rows with a height; products with E by
    :class:`Coupling`)."""
    H_cc = empty(S.n_red, S.sparse_camera)
    g_c = np.zeros(S.n_red + 1)
    for a, b, cols in S.image_runs:
        wJ = Jc[a:b] * w[a:b, None]  # per run: no (N, L) temporary
        add_block(H_cc, cols, cols, Jc[a:b].T @ wJ)
        g_c[cols] += wJ.T @ r[a:b]
    m = S.has_h
    H_hh = np.bincount(S.hidx[m], (w * Jh * Jh)[m], S.n_heights)
    g_h = np.bincount(S.hidx[m], (w * Jh * r)[m], S.n_heights)
    # The rows with a height, in a buffer of S (the blocks of E, ~100 MB for
    # a large block, live until the next linearisation).
    n_h = sum(b - a for a, b in S.h_runs)
    F = work_buffer(S, "coupling", (n_h, Jc.shape[1]))
    start = 0
    for a, b in S.h_runs:
        np.multiply(Jc[a:b], (w[a:b] * Jh[a:b])[:, None], out=F[start : start + b - a])
        start += b - a
    if not S.sparse_camera:
        H_cc = H_cc[:-1, :-1]  # SparseTerms drop the padding when summed
    return H_cc, g_c[:-1], H_hh, g_h, F


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
        if self.E_rest is not None and coupling.sparse:
            self.E_rest = sp.csr_matrix(self.E_rest)

    def at(self, H_hh: np.ndarray, g_h: np.ndarray, lam: float):
        """(C, C) ``E^T Dinv E`` (dense, or CSR for a sparse camera block)
        and (C,) ``E^T Dinv g_h`` at damping ``lam``."""
        out, rhs = self.base / (1.0 + lam), self.base_rhs / (1.0 + lam)
        if self.E_rest is not None:
            h = H_hh[self.rest]
            dinv = 1.0 / (h + lam * np.clip(h, 1e-6, 1e32))
            E, dg = self.E_rest, dinv * g_h[self.rest]
            if sp.issparse(E):
                out, rhs = out + E.T @ sp.diags(dinv) @ E, rhs + E.T @ dg
            else:
                out, rhs = out + E.T @ (dinv[:, None] * E), rhs + dg @ E
        return out, rhs


def damped_step(S: Setup, H_cc, g_c, H_hh, g_h, F, lam, schur: Schur, blocks=()):
    """Solve the damped normal equations by the Schur complement on the
    heights and on the unknowns of each of ``blocks``
    (:class:`~obliq_colmap.bundle.blocks.EliminatedBlocks`, linearised: the
    tie points, the facade lines). Returns the camera and height steps, the
    list of each block's (T, 3) steps and the damping diagonals of the
    cameras and heights."""
    D_c = np.clip(diagonal(H_cc), 1e-6, 1e32)
    D_h = np.clip(H_hh, 1e-6, 1e32)
    dinv = 1.0 / (H_hh + lam * D_h)
    A_red, rhs = H_cc, -g_c
    if S.n_heights:
        reduced, coupled = schur.at(H_hh, g_h, lam)
        A_red, rhs = A_red - reduced, rhs + coupled
    for blk in blocks:
        t_reduced, t_coupled = blk.schur(lam)
        A_red, rhs = A_red - t_reduced, rhs + t_coupled
    if sp.issparse(A_red):
        A_red = A_red + sp.diags(lam * D_c)
    else:
        A_red = A_red.copy() if A_red is H_cc else A_red
        A_red[np.diag_indices_from(A_red)] += lam * D_c
    dc = kkt_solve(A_red, S.A, rhs)  # dense, or sparse LU for large blocks
    dh = -dinv * (g_h + S.coupling.matvec(F, dc)) if S.n_heights else np.zeros(0)
    dp = [blk.step(dc, lam) for blk in blocks]
    return dc, dh, dp, D_c, D_h
