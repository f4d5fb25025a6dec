"""Tie points in the bundle: reprojection rows of free 3D points.

A tie point (a feature matched across images, ``BundleProblem.tie_xyz``) is a
free 3D unknown; each observation gives two rows, projection minus observed
pixel, weighted ``1 / tie_sigma_px^2`` under the robust loss on the
observation's squared 2D error. The tie points tie the images to each other
in 3D, where the map's rows tie each image to the map alone; across heads
they are what holds each head's tilt, focal and height to the others'. The
points are eliminated by their 3x3 blocks (:mod:`.blocks`).
"""

from __future__ import annotations

import numpy as np

from . import residuals as res
from .blocks import EliminatedBlocks, write_intrinsics
from .problem import BundleOptions, BundleProblem
from .setup import Setup, State

__all__ = ["TieRows"]


class TieRows(EliminatedBlocks):
    """The tie observations (sorted as :class:`EliminatedBlocks` lays them
    out; ``order`` maps back to the problem's order)."""

    state_attr = "points"

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

    def evaluate(self, S: Setup, st: State, jac: bool):
        """(O, 2) residuals (px) and, if jac, the (O, 2, L) camera and (O, 2, 3)
        point Jacobians."""
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
        return r, Jc, Jp
