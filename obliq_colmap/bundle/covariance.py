"""A-posteriori precision: the camera block's cofactor matrix and each image's
predicted deviation in pixels.

:func:`eliminate_heights` eliminates the heights (and fitted anchor
offsets), :func:`private_share` says how much of a group's rows they take
and :func:`private_refit` what fitting them takes of its squares,
:func:`gauge_cofactor` inverts the gauge-constrained reduced
system, :func:`corner_offset_meat` carries the map corners' shared error
into it; :func:`image_jacobians` and :func:`image_precision` propagate it
to the projections of each image's constrained points. The solver calls
them through this module (``covariance.image_precision``), so a diagnosis
can wrap them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from ..geometry import skew
from . import residuals as res
from .linear import kkt_inverse
from .setup import Setup, State


class _HeightBlocks(NamedTuple):
    """Each height's 2 x 2 block ``[[a, b], [b, c]]`` of ``J^T W J`` over
    (height, anchor offset) with the priors, over the rows ``mask``."""

    mask: np.ndarray  # (N,) rows with a height
    hid: np.ndarray  # (N_h,) their height
    jh: np.ndarray  # (N_h,) d r / d height
    jd: np.ndarray  # (N_h,) d r / d offset
    a: np.ndarray  # (n_heights,) with the height prior
    b: np.ndarray  # (n_heights,)
    c: np.ndarray  # (n_heights,) with the offset prior (1 without an offset)
    a_rows: np.ndarray  # (n_heights,) ``a`` from the rows alone
    c_rows: np.ndarray  # (n_heights,) ``c`` from the rows alone
    ok: np.ndarray  # (n_heights,) invertible


def _height_blocks(
    S: Setup, Jc, Jh, w, height_prior: np.ndarray, offset_w: float
) -> _HeightBlocks | None:
    """The heights' blocks (:class:`_HeightBlocks`); None without heights. A
    height without an offset direction gets ``c = 1``, a placeholder that
    couples nothing."""
    nh, m = S.n_heights, S.has_h
    if not (nh and m.any()):
        return None
    hid, wm, jh = S.hidx[m], w[m], Jh[m]
    # d r / d offset = d r / d (x, y) . dir = -(d r / d centre_xy) . dir
    jd = -np.einsum("ij,ij->i", Jc[m, 3:5], S.offset_dir[m])
    has_d = np.bincount(hid, np.any(S.offset_dir[m] != 0, axis=1), nh) > 0
    a0 = np.bincount(hid, wm * jh * jh, nh)
    b = np.bincount(hid, wm * jh * jd, nh)
    c0 = np.bincount(hid, wm * jd * jd, nh)
    a = a0 + height_prior
    c = c0 + np.where(has_d, offset_w, 1.0)
    ok = a * c - b * b > 0  # a height without information couples nothing
    return _HeightBlocks(m, hid, jh, jd, a, b, c, a0, c0, ok)


def eliminate_heights(
    S: Setup, H_cc, Jc, Jh, w, height_prior: np.ndarray, offset_w: float
) -> np.ndarray:
    """(n_red, n_red) ``J^T W J``'s camera block with the point unknowns
    eliminated (undamped Schur complement): each height, and with it, where
    its rows have an offset direction (``S.offset_dir``), the anchor's
    offset along it (prior weight ``offset_w``): one 2 x 2 block per height.

    Parameters
    ----------
    H_cc : (n_red, n_red) camera block of ``J^T W J``.
    Jc : (N, L) camera Jacobian; ``Jh`` (N,) height Jacobian; ``w`` (N,)
        weights (zero: a row not in the matrix); ``height_prior``
        (n_heights,) prior weight per height.
    """
    n, nh, L = S.n_red, S.n_heights, S.L
    A_red = H_cc.copy()
    hb = _height_blocks(S, Jc, Jh, w, height_prior, offset_w)
    if hb is not None:
        m, hid, jh, jd, b, c, ok = hb.mask, hb.hid, hb.jh, hb.jd, hb.b, hb.c, hb.ok
        wm = w[m]
        det = np.where(ok, hb.a * c - b * b, 1.0)
        # Cholesky factor of each block's inverse [[c, -b], [-b, a]] / det,
        # so that E^T inv E = G G^T with one sparse G: two columns per height.
        l11 = np.sqrt(np.where(ok, c / det, 0.0))
        l21 = np.where(ok, -b / det, 0.0) / np.where(ok, l11, 1.0)
        l22 = np.sqrt(np.where(ok, 1.0 / np.where(ok, c, 1.0), 0.0))
        vals = np.concatenate(
            [
                Jc[m] * (wm * (jh * l11[hid] + jd * l21[hid]))[:, None],
                Jc[m] * (wm * jd * l22[hid])[:, None],
            ]
        ).ravel()
        rows = np.tile(S.cols[m].ravel(), 2)  # camera columns, padding n
        cols = np.repeat(np.r_[hid, hid + nh], L)
        G = sp.csr_matrix((vals, (rows, cols)), (n + 1, 2 * nh))
        A_red -= (G @ G.T).toarray()[:n, :n]
    return A_red


def private_share(
    S: Setup, Jc, Jh, w, height_prior: np.ndarray, offset_w: float
) -> float:
    """The share of the redundancy that the heights and anchor offsets take
    from the rows weighted by ``w`` (and from the height prior's rows, which
    the solver counts among them; the offset prior's it does not):
    ``sum tr(M^-1 B)`` over the heights' 2 x 2 blocks, ``M`` with the
    priors, ``B`` without the offset prior.

    Two unknowns per track counted whole take two rows from a track that
    the outlier rounds left with one observation; such a track takes one
    (its height or offset is then held by the prior). Counted whole, a group
    of mostly two-view tracks gets a redundancy near or below zero and a
    variance component of tens, or none at all. Exact for the rows' own
    unknowns; the camera block's share is ``tr(Q N_g)``
    (:meth:`~.components.Group.redundancy`), which leaves out a term of the
    order of the offset prior's pull.
    """
    hb = _height_blocks(S, Jc, Jh, w, height_prior, offset_w)
    if hb is None:
        return 0.0
    a, b, c, ok = hb.a, hb.b, hb.c, hb.ok
    counted = hb.a_rows + height_prior  # the height prior's rows count
    det = np.where(ok, a * c - b * b, 1.0)
    # tr([[a, b], [b, c]]^-1 [[counted, b], [b, c_rows]])
    share = np.where(ok, (c * counted + a * hb.c_rows - 2.0 * b * b) / det, 0.0)
    return float(share.sum())


def private_refit(
    S: Setup,
    Jc,
    Jh,
    r: np.ndarray,
    w,
    height_prior: np.ndarray,
    prior_residual: np.ndarray,
    offset_w: float,
) -> float:
    """How much the weighted squares of the rows ``w`` weights (and of the
    height prior's rows) drop when each height and its anchor offset are
    fitted to them with the cameras held: ``sum g^T M^-1 g`` over the
    heights' 2 x 2 blocks, ``g`` the gradient of the half cost by (height,
    offset), ``M`` with the priors (one Gauss-Newton step, exact for the
    linearised rows).

    The solve holds each anchor offset where the tracks' last
    re-triangulation put it, while the redundancy (:func:`private_share`)
    counts it as an unknown the rows determine: a two-view track the views
    separate height and offset on keeps a residual in the solve and takes
    both of its rows from the redundancy. Its squares over that redundancy
    are counted twice; the variance component wants the squares at the
    optimum of the unknowns it counts.

    r : (N,) residuals; ``prior_residual`` (n_heights,) each height less
    its prior's mean (zero without a prior).
    """
    hb = _height_blocks(S, Jc, Jh, w, height_prior, offset_w)
    if hb is None:
        return 0.0
    m, hid, nh = hb.mask, hb.hid, S.n_heights
    wr = w[m] * r[m]
    gh = np.bincount(hid, wr * hb.jh, nh) + height_prior * prior_residual
    gd = np.bincount(hid, wr * hb.jd, nh)
    a, b, c, ok = hb.a, hb.b, hb.c, hb.ok
    det = np.where(ok, a * c - b * b, 1.0)
    drop = np.where(ok, (c * gh * gh - 2.0 * b * gh * gd + a * gd * gd) / det, 0.0)
    return float(drop.sum())


def corner_offset_meat(
    S: Setup, Jc: np.ndarray, w: np.ndarray, sigma_m: float
) -> np.ndarray:
    """(n_red, n_red) ``K K^T``: what the map corners' own error adds to the
    camera block's covariance between its cofactors (``Q K K^T Q``).

    The solve keeps each map corner where the map has it, so a corner's
    error (``sigma_m`` per horizontal axis) moves every one of its rows, in
    every image, together; the solution moves by ``Q J^T W B`` times it (B
    the rows' derivative by the corner's offset: the opposite of the
    camera centre's). ``K = J^T W B sigma_m``, two columns per corner.
    Counting the corners as unknowns of the precision instead (a Schur
    complement) predicts the estimator that would solve for them, which
    weighs a corner seen in 26 images like one seen in two: 2-3x too
    optimistic on a street placed on a dozen corners.

    Jc : (N, L) camera Jacobian, its columns 3:5 the centre's x and y;
    w : (N,) the solve's weights (zero: a row not in this group).
    """
    n, L = S.n_red, S.L
    m = (w > 0) & (S.kind == 0)
    if not m.any():
        return np.zeros((n, n))
    _, cid = np.unique(np.round(S.xy[m], 4), axis=0, return_inverse=True)
    cid = cid.ravel()
    nc = int(cid.max()) + 1
    ws = w[m] * sigma_m
    vals = np.concatenate(
        [Jc[m] * (-ws * Jc[m, 3])[:, None], Jc[m] * (-ws * Jc[m, 4])[:, None]]
    ).ravel()
    rows = np.tile(S.cols[m].ravel(), 2)  # camera columns, padding n
    cols = np.repeat(np.r_[cid, cid + nc], L)
    K = sp.csr_matrix((vals, (rows, cols)), (n + 1, 2 * nc))
    return (K @ K.T).toarray()[:n, :n]


def gauge_cofactor(S: Setup, A_red: np.ndarray) -> np.ndarray:
    """(n_red, n_red) cofactor matrix of the gauge-constrained solution: the
    camera block of the inverse of ``[[A_red, A^T], [A, 0]]`` (the datum is
    the gauge ``S.A``); times the variance factor, its covariance. NaN
    where it is singular."""
    n = S.n_red
    # Jacobi scaling: the columns (radians, metres, pixels, distortion) differ
    # by orders of magnitude; scaled, the condition number is the geometry's.
    d = np.sqrt(np.clip(np.diag(A_red), 0.0, None))
    if not np.all(d > 0):
        return np.full((n, n), np.nan)  # a direction without any observation
    try:
        inv = kkt_inverse(A_red / np.outer(d, d), S.A / d)
    except np.linalg.LinAlgError:
        return np.full((n, n), np.nan)
    return inv / np.outer(d, d)


def image_jacobians(S: Setup, st: State):
    """Per active image slot k: ``(k, J, cols)``, J (n, 2, 6 + q) the
    Jacobian of the projections of its rows' world points (map corners,
    facade anchors at their heights) by its pose (rotation increment,
    centre) and its camera's q refined intrinsics, cols their global
    columns in the camera block."""
    h_all = st.heights[np.maximum(S.hidx, 0)] if S.n_heights else S.zfix
    height = np.where(S.has_h, h_all, S.zfix)
    for a, b, cols in S.image_runs:
        k = int(S.img[a])
        slot = int(S.img_cam[k])
        basis = S.refined[slot]
        X = np.column_stack([S.xy[a:b], height[a:b]])
        Xc = (X - st.c[k]) @ st.R[k].T  # (n, 3)
        model = S.camera_model[slot]
        _, d_pt, d_par = res.project_with_jacobian(model, st.params[slot], Xc)
        J = np.concatenate(
            [
                -d_pt @ skew(Xc),  # R <- Exp(omega) R
                -d_pt @ st.R[k],  # c <- c + dc
                d_par @ basis,
            ],
            axis=2,
        )
        yield k, J, cols[: 6 + basis.shape[1]]


def image_precision(S: Setup, st: State, cov: np.ndarray) -> dict[int, float]:
    """Per active image slot: RMS over its rows' world points of the
    standard deviation (px, 2D) of their projection, from ``cov`` of its
    pose and its camera's refined intrinsics (:func:`image_jacobians`)."""
    out: dict[int, float] = {}
    for k, J, cols in image_jacobians(S, st):
        C = cov[np.ix_(cols, cols)]
        var = np.einsum("npi,ij,npj->n", J, C, J)
        out[k] = float(np.sqrt(np.mean(var))) if np.all(np.isfinite(var)) else np.nan
    return out


def pose_covariances(S: Setup, cov: np.ndarray) -> dict[int, np.ndarray]:
    """Per active image slot: the (6, 6) covariance of its pose (rotation
    increment omega, rad, ``R <- Exp(omega) R``; centre, m) from ``cov``."""
    out = {}
    for k in S.active_images:
        cols = S.pose_col[k] + np.arange(6)
        out[int(k)] = cov[np.ix_(cols, cols)].copy()
    return out
