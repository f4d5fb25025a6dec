"""Static layout of one solve and the evaluation of residuals and Jacobians.

:class:`Setup` fixes, once per solve, the residual order (sorted by camera
model, kind, camera and image so that every evaluation group is a slice),
the parameter columns of the camera block (6 per active image, the refined
intrinsics per camera, the priors' offset), the height indices, the linked
components and the gauge rows. :class:`State` holds the unknowns;
:func:`evaluate` gives the residuals (px) and, on request, the camera
Jacobian (N, L) and the height Jacobian (N,).
"""

from __future__ import annotations

import numpy as np

from . import residuals as res
from .coupling import Coupling, runs
from .linear import SPARSE_MIN_UNKNOWNS
from .problem import BundleOptions, BundleProblem, image_components, vertical_row_pairs


def _intrinsics_basis(model: str, params: np.ndarray, opts: BundleOptions):
    """(P, Q) basis of the refined steps of one camera's P parameters."""
    focal, pp, extra = res.focal_principal_extra_indices(model)
    cols = []
    if opts.refine_focal_length:
        if len(focal) == 2 and not opts.refine_aspect_ratio:
            col = np.zeros(len(params))
            col[focal[0]] = 1.0
            col[focal[1]] = params[focal[1]] / params[focal[0]]
            cols.append(col)
        else:
            cols += [np.eye(len(params))[i] for i in focal]
    if opts.refine_principal_point:
        cols += [np.eye(len(params))[i] for i in pp]
    if opts.refine_extra_params:
        cols += [np.eye(len(params))[i] for i in extra]
    return np.array(cols).T.reshape(len(params), len(cols))


class Setup:
    """Static layout: residual order, parameter columns, groups, gauge."""

    def __init__(self, problem: BundleProblem, options: BundleOptions) -> None:
        P, opts = problem, options
        self.image_ids = P.image_ids
        K = len(P.image_ids)
        self.camera_ids = sorted({P.image_camera[i] for i in P.image_ids})
        cam_slot = {cid: s for s, cid in enumerate(self.camera_ids)}
        self.img_cam = np.array([cam_slot[P.image_camera[i]] for i in P.image_ids])
        free = opts.corner_heights == "free"
        #: The facade tracks as 3D lines (:mod:`.facade_lines`, eliminated by
        #: their blocks), not as the scalar rows and heights here.
        self.facade_lines = opts.facade_lines and P.has_facade_lines
        h_img, h_height, h_anchor, h_line, nJ = (
            (
                np.zeros(0, np.int64),
                np.zeros(0, np.int64),
                np.zeros((0, 2)),
                np.zeros((0, 3)),
                0,
            )
            if self.facade_lines
            else (
                P.horizontal_image,
                P.horizontal_height,
                P.horizontal_anchor_xy,
                P.horizontal_line,
                len(P.facade_heights),
            )
        )
        self.n_facade_heights = nJ
        nv, nh = len(P.vertical_image), len(h_img)

        # Residuals: vertical then horizontal, then sorted (stably) by camera
        # model, kind, camera and image, so that each evaluation group (one
        # model and kind) and each of its cameras and images is a slice.
        img = np.concatenate([P.vertical_image, h_img])
        kind = np.concatenate([np.zeros(nv, np.int8), np.ones(nh, np.int8)])
        xy = np.concatenate([P.corner_xy[P.vertical_corner], h_anchor])
        line = np.concatenate([P.vertical_line, h_line])
        line = line / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
        hidx = np.concatenate(
            [nJ + P.vertical_corner if free else np.full(nv, -1), h_height]
        )
        zfix = np.concatenate([P.corner_heights[P.vertical_corner], np.zeros(nh)])
        offset = np.zeros((nv + nh, 2))
        if P.horizontal_offset_normal is not None and nh:
            offset[nv:] = P.horizontal_offset_normal
        models = [P.cameras[c].model for c in self.camera_ids]
        self.camera_model = models
        #: (width, height) px of each camera slot (the frames points fall in).
        self.camera_size = [
            (P.cameras[c].width, P.cameras[c].height) for c in self.camera_ids
        ]
        model_rank = np.searchsorted(sorted(set(models)), models)
        cam = self.img_cam[img]
        order = np.lexsort((img, cam, kind, model_rank[cam]))
        self.order = order
        self.nv, self.nh = nv, nh
        self.img, self.kind, self.xy = img[order], kind[order], xy[order]
        self.line, self.hidx, self.zfix = line[order], hidx[order], zfix[order]
        self.offset_dir = offset[order]  # (N, 2), zero: no offset unknown
        self.cam = self.img_cam[self.img]
        self.n_heights = nJ + (len(P.corner_xy) if free else 0)
        self.has_h = self.hidx >= 0
        # Heights whose anchor offset was fitted to the observations: each
        # such offset is one more unknown in the redundancy.
        with_offset = self.has_h & np.any(self.offset_dir != 0, axis=1)
        self.n_offsets = len(np.unique(self.hidx[with_offset]))
        # The rows with a height as runs (all rows, or all but the vertical
        # ones when the corners are fixed): slices are cheaper than a mask.
        self.h_runs = [(a, b) for a, b in runs(self.has_h) if self.has_h[a]]
        # Cost weight of each residual: 1 / sigma^2 of its kind.
        sigma = np.array([opts.vertical_sigma_px, opts.horizontal_sigma_px])
        self.weight = 1.0 / sigma[self.kind] ** 2
        #: Positions (in the residual order) of the two rows of each segment
        #: that :func:`evaluate` turns into their sum and difference
        #: (``BundleOptions.vertical_direction_sigma_px``); the difference
        #: rows carry that sd.
        self.pair_a = self.pair_b = np.zeros(0, np.int64)
        #: Scale (px) of each row's robust loss: ``BundleOptions.loss_scale_px``,
        #: on the difference rows in proportion to their sd (a direction
        #: several of its sds off is an outlier long before it is 2 px off).
        self.loss_scale = np.full(len(order), opts.loss_scale_px)
        if opts.vertical_direction_sigma_px is not None:
            a, b = vertical_row_pairs(P)
            position = np.empty(len(order), np.int64)
            position[order] = np.arange(len(order))
            a, b = position[a], position[b]
            # Mixing two rows must not mix two height unknowns (each row
            # touches one in the Schur complement): with free corner heights
            # a pair shares its corner's or is left as two rows.
            same = self.hidx[a] == self.hidx[b]
            self.pair_a, self.pair_b = a[same], b[same]
            self.weight[self.pair_b] = 1.0 / opts.vertical_direction_sigma_px**2
            self.loss_scale[self.pair_b] *= (
                opts.vertical_direction_sigma_px / opts.vertical_sigma_px
            )

        if opts.facade_row_extrapolation and nh:
            sd = facade_row_sd(P)
            q = np.flatnonzero(order >= nv)  # the facade rows, sorted order
            r = order[q] - nv
            self.weight[q] /= sd[r] ** 2
            self.loss_scale[q] *= sd[r]

        # Active images and cameras; parameter columns of the camera block.
        # an image is active with map rows or tie observations
        counts = np.bincount(self.img, minlength=K)
        counts += np.bincount(P.tie_image, minlength=K)
        if self.facade_lines:
            counts += np.bincount(P.horizontal_image, minlength=K)
        self.active_images = np.flatnonzero(counts > 0)
        col = 0
        self.pose_col = np.full(K, -1)
        for k in self.active_images:
            self.pose_col[k] = col
            col += 6
        # Per camera a (P, Q) basis of its refined parameter steps:
        # params += basis @ step (one column per free parameter; fx and fy
        # share one column unless the aspect ratio is refined).
        self.refined: list[np.ndarray] = []
        self.intr_col = np.full(len(self.camera_ids), -1)
        active_cams = set(self.img_cam[self.active_images].tolist())
        for s, cid in enumerate(self.camera_ids):
            cam = P.cameras[cid]
            basis = _intrinsics_basis(cam.model, cam.params, opts)
            if s not in active_cams:
                basis = basis[:, :0]
            self.refined.append(basis)
            if basis.shape[1]:
                self.intr_col[s] = col
                col += basis.shape[1]
        # Observed centres (GNSS) hold every component's vertical datum, and
        # may sit off the map horizontally by one offset (two columns).
        self.centred = (
            opts.position_prior_sigma_m is not None and P.prior_centers is not None
        )
        self.shift_col = -1
        if self.centred and opts.estimate_prior_offset:
            self.shift_col = col
            col += 2
        self.n_red = col
        # Large blocks gather the camera block sparse (:mod:`.camera_block`).
        self.sparse_camera = self.n_red >= SPARSE_MIN_UNKNOWNS
        self.L = 6 + max((b.shape[1] for b in self.refined), default=0)
        # (N, L) global columns of each residual's camera-side Jacobian; the
        # padding column n_red is dropped after assembly.
        N = len(self.img)
        cols = np.full((N, self.L), self.n_red)
        cols[:, :6] = self.pose_col[self.img][:, None] + np.arange(6)
        for s, basis in enumerate(self.refined):
            q = basis.shape[1]
            m = self.cam == s
            cols[np.ix_(m, 6 + np.arange(q))] = self.intr_col[s] + np.arange(q)
        self.cols = cols
        # Runs of rows of one image: (start, end, the image's columns).
        self.image_runs = [(a, b, cols[a]) for a, b in runs(self.img)]
        # Evaluation groups: one camera model and kind, at most _CHUNK rows.
        self.groups = [
            _Group(self, models[self.cam[a]], int(self.kind[a]), c, min(c + _CHUNK, b))
            for a, b in runs(model_rank[self.cam] * 2 + self.kind)
            for c in range(a, b, _CHUNK)
        ]

        # Components and gauge rows (over the camera block).
        # Images are linked by a shared height, tie point or facade line.
        hmask = self.has_h
        n_ties = len(P.tie_xyz)
        line_img, line_track = (
            (P.horizontal_image, P.horizontal_height)
            if self.facade_lines
            else (np.zeros(0, np.int64),) * 2
        )
        self.num_components, self.labels = image_components(
            K,
            np.concatenate([self.img[hmask], P.tie_image, line_img]),
            np.concatenate(
                [
                    self.hidx[hmask],
                    self.n_heights + P.tie_point,
                    self.n_heights + n_ties + line_track,
                ]
            ),
        )
        self.components = [
            tuple(P.image_ids[k] for k in np.flatnonzero(self.labels == c))
            for c in range(self.num_components)
        ]
        rows = []
        if opts.gauge == "component_mean_camera_height" and not self.centred:
            for c in range(self.num_components):
                members = [
                    k for k in np.flatnonzero(self.labels == c) if self.pose_col[k] >= 0
                ]
                if members:
                    a = np.zeros(self.n_red)
                    a[self.pose_col[members] + 5] = 1.0 / len(members)
                    rows.append(a)
        self.A = np.array(rows).reshape(-1, self.n_red)
        # Buffers reused by every linearisation (see :meth:`buffer`).
        self._buffers: dict[str, np.ndarray] = {}
        # Layout of the height x camera coupling E.
        self.coupling = Coupling(
            self.img[hmask],
            self.hidx[hmask],
            cols[hmask],
            self.n_heights,
            self.n_red,
            sparse=self.sparse_camera,
        )


#: Offset variance of a least-squares line through points spread evenly over
#: its length L, at a distance s from their centre: (1 + 12 s^2 / L^2) times
#: that at the centre (var(intercept) + s^2 var(slope), var(slope) = 12
#: sigma^2 / (n L^2)).
_LINE_FIT_SLOPE_FACTOR = 12.0


def facade_row_sd(P: BundleProblem) -> np.ndarray:
    """(H,) relative sd of each scalar facade row: its segment's line fit
    read at the projection of the row's anchor point (at the problem's start
    poses and cameras), ``sqrt(1 + 12 s^2 / L^2)`` over its median
    (``BundleOptions.facade_row_extrapolation``). Rows without segment ends
    (``horizontal_ends`` None) or with a degenerate one: 1."""
    H = len(P.horizontal_image)
    ends = P.horizontal_ends
    if ends is None or H == 0:
        return np.ones(H)
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    ok = length > 1e-9
    u = (ends[:, 1] - ends[:, 0]) / np.where(ok, length, 1.0)[:, None]
    mid = ends.mean(axis=1)
    s = np.zeros(H)
    for k, i in enumerate(P.image_ids):
        m = np.flatnonzero(P.horizontal_image == k)
        if not len(m):
            continue
        X = np.column_stack(
            [P.horizontal_anchor_xy[m], P.facade_heights[P.horizontal_height[m]]]
        )
        x = P.cameras[P.image_camera[i]].img_from_cam(P.poses[i].transform(X))
        s[m] = np.sum((x - mid[m]) * u[m], axis=1) / np.where(ok[m], length[m], 1.0)
    s = np.where(ok & np.isfinite(s), s, 0.0)
    sd = np.sqrt(1.0 + _LINE_FIT_SLOPE_FACTOR * s * s)
    return sd / np.median(sd)


def work_buffer(S: Setup, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """A work array of ``shape`` kept by ``S`` across the linearisations of
    one solve: the camera Jacobian and the coupling's blocks of a large
    block are ~100 MB each, and a fresh array costs its first-touch page
    faults every iteration (~10 % of a 1000-image solve). Its contents are
    the caller's to set; the previous linearisation's are overwritten."""
    buf = S._buffers.get(name)
    if buf is None or buf.shape != shape:
        buf = S._buffers[name] = np.empty(shape)
    return buf


#: Rows per residual evaluation call: the per-row temporaries (~60 of them
#: with Jacobians) then stay small and in cache.
_CHUNK = 8192


class _Group:
    """Static rows of one evaluation group (a camera model and a residual
    kind): the slice ``[start, end)`` of the residual order, as (., n) rows."""

    def __init__(self, S: Setup, model: str, kind: int, start: int, end: int):
        self.model, self.kind, self.start, self.end = model, kind, start, end
        sl = slice(start, end)
        self.img = S.img[sl]
        self.line = np.ascontiguousarray(S.line[sl].T)  # (3, n) unit lines
        self.xy = np.ascontiguousarray(S.xy[sl].T)  # (2, n)
        self.has_h, self.zfix = S.has_h[sl], S.zfix[sl]
        self.hidx = np.maximum(S.hidx[sl], 0)
        # The group's cameras, each a run of rows: (slot, start, end) local.
        cam = S.cam[sl]
        self.cam_runs = [(int(cam[a]), a, b) for a, b in runs(cam)]
        self.cams = [c for c, _, _ in self.cam_runs]
        self.cam_local = np.searchsorted(self.cams, cam)
        self.E = res.expansion_matrix(model)

    def full_params(self, params: list[np.ndarray]) -> np.ndarray:
        """(8, 1) or (8, n) general parameters of the rows."""
        full = self.E @ np.stack([params[c] for c in self.cams], 1)  # (8, cams)
        return full if len(self.cams) == 1 else full[:, self.cam_local]


class State:
    def __init__(self, R, c, params, heights, shift=None, points=None, lines=None):
        self.R, self.c, self.params, self.heights = R, c, params, heights
        # horizontal offset of the priors' centres against the map (m;
        # BundleOptions.estimate_prior_offset)
        self.shift = np.zeros(2) if shift is None else shift
        #: (T, 3) tie points (m)
        self.points = np.zeros((0, 3)) if points is None else points
        #: (J, 3) facade lines: height (m), offset (m), angle (rad)
        self.lines = np.zeros((0, 3)) if lines is None else lines

    @classmethod
    def start(cls, P: BundleProblem, S: Setup) -> State:
        """The problem's start: its poses, cameras and heights (the corner
        heights too where they are free unknowns), tie points and facade
        lines."""
        free = S.n_heights > S.n_facade_heights
        facade = [] if S.facade_lines else P.facade_heights
        lines = None
        if S.facade_lines:
            offsets, angles, _ = P.facade_line_start()
            lines = np.column_stack([P.facade_heights, offsets, angles]).astype(float)
        return cls(
            np.stack([P.poses[i].rotation for i in P.image_ids]),
            np.stack([P.poses[i].center for i in P.image_ids]),
            [P.cameras[c].params.copy() for c in S.camera_ids],
            np.concatenate([facade, P.corner_heights if free else []]),
            points=P.tie_xyz.copy(),
            lines=lines,
        )

    def copy(self):
        return State(
            self.R.copy(),
            self.c.copy(),
            [p.copy() for p in self.params],
            self.heights.copy(),
            self.shift.copy(),
            self.points.copy(),
            self.lines.copy(),
        )


def evaluate(setup: Setup, st: State, jac: bool):
    """Residuals (N,) and, if jac, camera Jacobian (N, L) and height Jacobian (N,).

    The camera Jacobian is the transpose of an (L, N) array, so that each
    group writes its rows contiguously; it lives in a buffer of ``setup``
    that the next evaluation with ``jac`` overwrites.
    """
    N = len(setup.img)
    r = np.empty(N)
    JcT = None
    if jac:
        JcT = work_buffer(setup, "jacobian", (setup.L, N))
        JcT[6:] = 0.0  # the pose rows are all written below
    Jh = np.zeros(N) if jac else None
    Rk = st.R.transpose(1, 2, 0)  # (3, 3, K)
    ck = st.c.T  # (3, K)
    for g in setup.groups:
        R = np.take(Rk, g.img, axis=2)  # (3, 3, n)
        c = np.take(ck, g.img, axis=1)
        D = np.empty_like(c)  # X - c
        np.subtract(g.xy, c[:2], out=D[:2])
        h = np.where(g.has_h, st.heights[g.hidx], g.zfix) if len(st.heights) else g.zfix
        np.subtract(h, c[2], out=D[2])
        fn = res.vertical_rows if g.kind == 0 else res.horizontal_rows
        out = fn(g.model, g.full_params(st.params), R, D, g.line, jac)
        r[g.start : g.end] = out[0]
        if jac:
            _, d_pose, d_params, d_height = out
            JcT[:6, g.start : g.end] = d_pose
            for s, a, b in g.cam_runs:
                basis = setup.refined[s]
                if basis.shape[1]:
                    rows = slice(g.start + a, g.start + b)
                    JcT[6 : 6 + basis.shape[1], rows] = basis.T @ d_params[:, a:b]
            Jh[g.start : g.end] = d_height
    if jac:
        Jh[~setup.has_h] = 0.0
    if len(setup.pair_a):
        a, b = setup.pair_a, setup.pair_b
        sum_and_difference(r, a, b)
        if jac:
            sum_and_difference(JcT, a, b)
            sum_and_difference(Jh, a, b)
    return r, (JcT.T if jac else None), Jh


_RSQRT2 = 1.0 / np.sqrt(2.0)


def sum_and_difference(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """In place along the last axis: ``x[..., a], x[..., b]`` -> their sum
    and difference over sqrt 2 (orthogonal: its own inverse)."""
    xa, xb = x[..., a], x[..., b]
    x[..., a] = (xa + xb) * _RSQRT2
    x[..., b] = (xa - xb) * _RSQRT2
