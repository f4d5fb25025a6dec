"""Tie points in the bundle: reprojection rows of free 3D points.

A tie point (a feature matched across images, ``BundleProblem.tie_xyz``) is a
free 3D unknown; each observation gives two rows, projection minus observed
pixel over its relative sd (``BundleProblem.tie_sd``), weighted
``1 / tie_sigma_px^2`` under the robust loss on the observation's squared 2D
error so whitened. The tie points tie the images to each other
in 3D, where the map's rows tie each image to the map alone; across heads
they are what holds each head's tilt, focal and height to the others'. The
points are eliminated by their 3x3 blocks (:mod:`.blocks`).

Tie points may be observed themselves (``BundleProblem.tie_prior_xyz``:
control points of a survey, each axis at its stated sigma): those rows touch
the point alone, so they join its 3x3 block (:func:`coordinate_prior`) and
cost nothing in the reduced camera system.
"""

from __future__ import annotations

import numpy as np

from . import residuals as res
from .blocks import EliminatedBlocks, write_intrinsics
from .problem import BundleOptions, BundleProblem
from .setup import Setup, State

__all__ = ["TieRows", "coordinate_prior"]


def coordinate_prior(
    xyz: np.ndarray, given: np.ndarray, weight: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Rows ``sqrt(w) (X - X_given)`` per axis on T points.

    Parameters
    ----------
    xyz : (T, 3) current points, metres.
    given : (T, 3) observed points (any finite value where the weight is 0).
    weight : (T, 3) ``1 / sigma^2`` per axis, 0 for a free axis.

    Returns
    -------
    H : (T, 3, 3) the rows' normal blocks ``J^T W J`` (diagonal: J = I).
    g : (T, 3) their gradient ``J^T W r``.
    cost : float, ``1/2 sum w (X - X_given)^2``.
    """
    d = xyz - given
    g = weight * d
    H = np.zeros((len(xyz), 3, 3))
    H[:, [0, 1, 2], [0, 1, 2]] = weight
    return H, g, 0.5 * float(np.sum(g * d))


class TieRows(EliminatedBlocks):
    """The tie observations (sorted as :class:`EliminatedBlocks` lays them
    out; ``order`` maps back to the problem's order)."""

    state_attr = "points"
    group_name = "tie points"

    def __init__(self, P: BundleProblem, S: Setup, opts: BundleOptions) -> None:
        super().__init__(
            S,
            opts,
            P.tie_image,
            P.tie_point,
            len(P.tie_xyz),
            1.0 / opts.tie_sigma_px**2,
            opts.tie_loss_scale_px,
        )
        self.xy = np.ascontiguousarray(P.tie_xy[self.order].T)  # (2, O)
        #: (O,) 1 / each observation's relative sd, in the layout's order
        self.inv_sd = (
            np.ones(len(self.img)) if P.tie_sd is None else 1.0 / P.tie_sd[self.order]
        )
        # the observed coordinates (weight 0 on a free axis or a free point)
        self.prior_w = self.prior_xyz = None
        if P.tie_prior_xyz is not None:
            finite = np.isfinite(P.tie_prior_sigma)
            self.prior_w = np.where(finite, 1.0 / P.tie_prior_sigma**2, 0.0)
            self.prior_xyz = np.where(finite, P.tie_prior_xyz, 0.0)

    def prior(self, st: State) -> tuple[np.ndarray, np.ndarray, float] | None:
        """The observed coordinates' rows (:func:`coordinate_prior`)."""
        if self.prior_w is None:
            return None
        return coordinate_prior(st.points, self.prior_xyz, self.prior_w)

    @property
    def n_prior_rows(self) -> int:
        return 0 if self.prior_w is None else int(np.count_nonzero(self.prior_w))

    def evaluate(self, S: Setup, st: State, jac: bool):
        """(O, 2) residuals (px at the relative sd 1: each observation's over
        its ``tie_sd``) and, if jac, the (O, 2, L) camera and (O, 2, 3) point
        Jacobians, alike."""
        r, Jc, Jp, Rk = self.outputs(S, st, jac)
        for g in self.groups:
            a, b = g.start, g.end
            img = self.img[a:b]
            R = np.take(Rk, img, axis=2)
            D = st.points[self.point[a:b]].T - st.c[img].T
            full = g.full_params(st.params)
            out = res.reprojection_rows(g.model, full, R, D, self.xy[:, a:b], jac)
            r[a:b] = out[0].T
            if jac:
                _, d_pose, d_params, d_point = out
                Jc[a:b, :, :6] = d_pose.transpose(2, 0, 1)
                Jp[a:b] = d_point.transpose(2, 0, 1)
                write_intrinsics(S, g, d_params, Jc)
        r *= self.inv_sd[:, None]
        if jac:
            Jc *= self.inv_sd[:, None, None]
            Jp *= self.inv_sd[:, None, None]
        return r, Jc, Jp
