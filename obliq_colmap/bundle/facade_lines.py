"""Facade edges as 3D horizontal lines: both ends of every observed segment.

With ``BundleOptions.facade_lines`` each facade track j is a horizontal 3D
line with three unknowns, eliminated by their 3x3 blocks (:mod:`.blocks`):

    X(s) = A_j + d_j n(theta_j) + h_j e_z + s u(theta_j)

``A_j`` the track's anchor on its map edge (``BundleProblem.
horizontal_anchor_xy``), ``u(theta) = Rz(theta) u0_j`` the line's direction,
``theta_j`` its angle about the vertical from the map edge's direction
``u0_j`` (``BundleProblem.facade_direction``), ``n(theta) = Rz(theta) n0_j``
with ``n0_j = (u0_y, -u0_x)``, ``d_j`` the offset across the edge (a roof
rim overhangs, a parapet stands back) and ``h_j`` the height.

Each observation (a segment, raw pixels ``BundleProblem.horizontal_ends``)
gives two rows, one per end: the line's point ``X(s_k)`` where the end's ray
meets the line's vertical plane, projected, its distance from the segment's
line along the projected vertical (the ``dist_z`` of
:func:`~obliq_colmap.bundle.residuals.horizontal_rows`). The positions
``s_k`` are fixed at the start of a solve: sliding along the line moves the
projection along the segment, which the residual does not see. With one
point per observation the line's direction was unused, and with it each
image's horizon: an eave is horizontal in the world, and seen from several
views its 3D direction holds the block's tilt, which a rigid rotation of the
whole block would otherwise keep (the map's corners barely move under it).

Priors: ``d_j`` about 0 with ``BundleOptions.horizontal_offset_sigma_m``;
``theta_j`` about 0 with ``BundleProblem.facade_angle_sigma`` (the map edge's
direction is good to its vertices' noise over its length), so that a line
seen once is still defined. The robust loss acts on each observation's mean
square over its rows, at ``BundleOptions.loss_scale_px``.

Only LEVEL tracks are lines (``BundleProblem.facade_level``): floors and
eaves are level, while edges near the ground (kerbs, the foot of a wall)
follow the terrain, and forced level they tilt the block towards its slope
(urban-101, 1.5 deg of slope: 0.33 deg with those tracks alone). A track
that is not level keeps one row per observation, its point nearest the
anchor, with its offset and angle held at their start: the scalar model's
row, in this block.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import residuals as res
from .blocks import EliminatedBlocks, write_intrinsics
from .loss import robust_loss
from .problem import BundleOptions, BundleProblem
from .setup import Setup, State

__all__ = ["FacadeLineRows", "rotate"]


def rotate(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(N, 2) horizontal vectors turned by (N,) angles (rad, counter-clockwise)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])


def _perp(v: np.ndarray) -> np.ndarray:
    """(N, 2) vectors turned by +90 deg: d/dtheta of ``rotate(v, theta)``."""
    return np.column_stack([-v[:, 1], v[:, 0]])


class FacadeLineRows(EliminatedBlocks):
    """The facade observations as two rows each on their track's 3D line.

    ``State.lines`` (J, 3): height h (m), offset d (m), angle theta (rad).
    """

    state_attr = "lines"
    group_name = "facade lines"

    def __init__(
        self, P: BundleProblem, S: Setup, opts: BundleOptions, st: State
    ) -> None:
        J = len(P.facade_heights)
        super().__init__(
            S,
            opts,
            P.horizontal_image,
            P.horizontal_height,
            J,
            1.0 / opts.horizontal_sigma_px**2,
            opts.loss_scale_px,
        )
        o = self.order
        lines = P.horizontal_line[o]
        lines = lines / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
        self.line = np.ascontiguousarray(lines.T)  # (3, O) unit lines
        # Each track's anchor (all its observations share one) and map edge.
        self.anchor = np.zeros((J, 2))
        self.anchor[P.horizontal_height] = P.horizontal_anchor_xy
        u0 = np.asarray(P.facade_direction, float)
        self.u0 = u0 / np.linalg.norm(u0, axis=1, keepdims=True)
        self.n0 = np.column_stack([self.u0[:, 1], -self.u0[:, 0]])
        offsets, _, angle_sigma = P.facade_line_start()
        level = np.ones(J, bool) if P.facade_level is None else P.facade_level
        held = 1.0 / _HELD**2
        self.offset_w = np.where(level, 1.0 / opts.horizontal_offset_sigma_m**2, held)
        self.angle_w = np.where(level, 1.0 / angle_sigma**2, held)
        self.offset0 = np.where(level, 0.0, offsets)  # the prior's centre
        # (O, 2) rows in use: both ends of a level track's observations, the
        # point nearest the anchor (end 0 at s = 0) of the others.
        self.rows = np.ones((len(self.img), 2))
        self.rows[~level[self.point], 1] = 0.0
        self.s = self._positions(P, S, st)  # (O, 2), metres along the line

    def frame(self, st: State, a: int, b: int):
        """Per observation of ``[a, b)`` its line's point nearest the anchor
        (n, 3), direction u and normal n (n, 2) and offset d (n,)."""
        tr = self.point[a:b]
        h, d, th = st.lines[tr].T
        u, n = rotate(self.u0[tr], th), rotate(self.n0[tr], th)
        base = self.anchor[tr] + d[:, None] * n
        return np.column_stack([base, h]), u, n, d

    def points(self, st: State, a: int, b: int):
        """The (2n, 3) line points of the ends of observations ``[a, b)``
        (end 0 of each, then end 1), and :meth:`frame`'s u, n and d."""
        base, u, n, d = self.frame(st, a, b)
        xy = np.concatenate([base[:, :2] + self.s[a:b, k, None] * u for k in (0, 1)])
        return np.column_stack([xy, np.tile(base[:, 2], 2)]), u, n, d

    def _positions(self, P: BundleProblem, S: Setup, st: State) -> np.ndarray:
        """(O, 2) end positions along the lines at ``st``; 0 for the rows
        of tracks that are not level."""
        return _end_positions(P, S, self, st) * self.rows[:, 1:]

    def evaluate(self, S: Setup, st: State, jac: bool):
        """(O, 2) residuals (px, end 0 and end 1) and, if jac, the (O, 2, L)
        camera and (O, 2, 3) line Jacobians (h, d, theta)."""
        r, Jc, Jp, Rk = self.outputs(S, st, jac)
        for g in self.groups:
            a, b = g.start, g.end
            n = b - a
            img = np.tile(self.img[a:b], 2)
            X, u, nrm, d = self.points(st, a, b)
            R = np.take(Rk, img, axis=2)
            D = X.T - st.c[img].T
            full = g.full_params(st.params)
            full = full if full.shape[1] == 1 else np.tile(full, 2)
            line = np.tile(self.line[:, a:b], 2)
            out = res.horizontal_rows(g.model, full, R, D, line, jac)
            r[a:b] = out[0].reshape(2, n).T * self.rows[a:b]
            if not jac:
                continue
            _, d_pose, d_params, _ = out
            Jc[a:b, :, :6] = d_pose.reshape(6, 2, n).transpose(2, 1, 0)
            dp = d_params.reshape(len(d_params), 2, n).transpose(1, 0, 2)
            write_intrinsics(S, g, dp, Jc)
            # The rows depend on X - c: d r / d X = - d r / d c.
            dX = -d_pose[3:6].reshape(3, 2, n)  # (xyz, end, obs)
            s = self.s[a:b].T  # (end, obs)
            du, dn = _perp(u), _perp(nrm)
            Jp[a:b, :, 0] = dX[2].T
            Jp[a:b, :, 1] = (dX[0] * nrm[:, 0] + dX[1] * nrm[:, 1]).T
            turn_x = s * du[:, 0] + d * dn[:, 0]
            turn_y = s * du[:, 1] + d * dn[:, 1]
            Jp[a:b, :, 2] = (dX[0] * turn_x + dX[1] * turn_y).T
            Jc[a:b] *= self.rows[a:b, :, None]
            Jp[a:b] *= self.rows[a:b, :, None]
        return r, Jc, Jp

    def losses(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(O,) rho and rho' of each observation, the loss on the mean square
        of its rows (times their number: the cost of that many rows)."""
        o = self.opts
        m = self.rows.sum(1)
        rho, drho = robust_loss(o.loss, self.loss_scale_px, np.sum(r * r, 1) / m)
        return m * rho, drho

    def prior(self, st: State):
        T = self.n_points
        d, th = st.lines[:, 1] - self.offset0, st.lines[:, 2]
        H = np.zeros((T, 3, 3))
        H[:, 1, 1] = self.offset_w
        H[:, 2, 2] = self.angle_w
        g = np.column_stack([np.zeros(T), self.offset_w * d, self.angle_w * th])
        cost = 0.5 * float(np.sum(self.offset_w * d * d + self.angle_w * th * th))
        return H, g, cost

    @property
    def n_prior_rows(self) -> int:
        return 2 * self.n_points

    @property
    def redundancy(self) -> int:
        return int(self.rows.sum()) + self.n_prior_rows - 3 * self.n_points

    def reanchor(
        self, P: BundleProblem, S: Setup, st: State, tol_m: float = 0.01
    ) -> bool:
        """Move the end positions to where the ends' rays meet the lines at
        ``st``; whether any moved by more than ``tol_m``."""
        s = self._positions(P, S, st)
        moved = bool(np.max(np.abs(s - self.s), initial=0.0) > tol_m)
        self.s = s
        return moved

    def observation_residuals(self, S: Setup, st: State) -> np.ndarray:
        """(O,) one figure per observation in the PROBLEM's order: the RMS of
        its rows' residuals with the sign of their sum (px)."""
        r = self.evaluate(S, st, jac=False)[0]
        out = np.empty(len(r))
        rms = np.sqrt(np.sum(r * r, 1) / self.rows.sum(1))
        out[self.order] = np.sign(r.sum(1)) * rms
        return out


#: Standard deviation (m, rad) that holds the offset and angle of a track that
#: is not level at their start.
_HELD = 1e-4


def _end_positions(
    P: BundleProblem, S: Setup, rows: FacadeLineRows, st: State
) -> np.ndarray:
    """(O, 2) position along its track's line (m from the line's point
    nearest the anchor) of each segment end, where its ray (through the
    camera of the state ``st``) meets the line's vertical plane there; 0
    where the ray runs along it."""
    s = np.zeros((len(rows.img), 2))
    o = rows.order
    ends = P.horizontal_ends[o]  # (O, 2, 2) raw pixels
    base, u, n, _ = rows.frame(st, 0, len(rows.img))
    for k in np.unique(rows.img):
        sel = np.flatnonzero(rows.img == k)
        slot = S.img_cam[k]
        cam = dataclasses.replace(
            P.cameras[S.camera_ids[slot]], params=st.params[slot].copy()
        )
        uv = cam.cam_from_img(ends[sel].reshape(-1, 2)).reshape(-1, 2, 2)
        for e in (0, 1):
            ray = np.column_stack([uv[:, e], np.ones(len(sel))]) @ st.R[k]
            q = base[sel]
            n3 = np.column_stack([n[sel], np.zeros(len(sel))])
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.einsum("ni,ni->n", n3, q - st.c[k]) / np.einsum(
                    "ni,ni->n", ray, n3
                )
            x = st.c[k] + t[:, None] * ray
            s[sel, e] = np.einsum("ni,ni->n", x[:, :2] - q[:, :2], u[sel])
    return np.where(np.isfinite(s), s, 0.0)
