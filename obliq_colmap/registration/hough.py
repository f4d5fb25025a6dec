"""Steps 2-3 of the registration: Hough votes of (corner, segment) pairs over
a grid of poses (alpha, c_x, c_y[, ground height]) (:func:`hough`) and the
peaks of the accumulator (:class:`HoughGrid`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace

import numpy as np

from obliq_colmap.registration import ransac_core
from obliq_colmap.registration.raster import (
    HeightBand,
    VoteRows,
    Workspace,
    rasterise,
    t_interval,
)
from obliq_colmap.registration.segments import Segments
from obliq_colmap.registration.view import View


@dataclass
class HoughPeak:
    alpha: float
    c_xy: np.ndarray
    height: float  # NaN without a height axis
    votes: float


@dataclass
class HoughGrid:
    """A smoothed Hough accumulator over (alpha, c_1, c_2[, height]).

    The centre is ``c_center + k1 d1 u1 + k2 d2 u2`` for cell indices k1, k2
    centred on zero; ``u1`` is the camera's lateral direction and ``u2`` its
    horizontal viewing direction.
    """

    acc: np.ndarray  # (na, n1, n2, nh)
    alphas: np.ndarray  # (na,) radians
    c_center: np.ndarray  # (2,)
    axes: np.ndarray  # (2, 2) rows u1, u2
    steps: np.ndarray  # (2,) d1, d2 metres
    h_lo: float
    d_alpha: float
    d_h: float  # inf without a height axis

    @property
    def d_c(self) -> float:
        return float(self.steps.max())

    def center_of(self, k1, k2) -> np.ndarray:
        n1, n2 = self.acc.shape[1:3]
        return (
            self.c_center
            + (k1 - n1 // 2) * self.steps[0] * self.axes[0]
            + (k2 - n2 // 2) * self.steps[1] * self.axes[1]
        )

    def _at(self, ka, k1, k2, kh) -> HoughPeak:
        h = self.h_lo + (kh + 0.5) * self.d_h if math.isfinite(self.d_h) else math.nan
        return HoughPeak(
            float(self.alphas[ka]),
            self.center_of(k1, k2),
            float(h),
            float(self.acc[ka, k1, k2, kh]),
        )

    def peak(self) -> HoughPeak:
        return self._at(*np.unravel_index(int(np.argmax(self.acc)), self.acc.shape))

    def peaks_by_height(self, num: int, separation: int) -> list[HoughPeak]:
        """The best pose at each of the ``num`` strongest heights, the heights
        local maxima of the height profile (the best vote over all poses) at
        least ``separation`` cells apart, strongest first.

        Spurious heights (chance alignments of the map with clutter, far
        above or below the ground) can form many strong pose peaks at one
        height; ranking heights rather than 4-D peaks keeps the true ground
        among the candidates that are verified.
        """
        nh = self.acc.shape[3]
        flat = self.acc.reshape(-1, nh)
        # The first pose cell of each height's maximum, as argmax along the
        # strided axis 0 (3x slower) gives it; the accumulator has no NaN.
        profile = flat.max(axis=0)  # (nh,)
        best = np.argmax(flat == profile, axis=0)  # (nh,) pose cell per height
        order = np.argsort(-profile, kind="stable")
        chosen: list[int] = []
        for kh in order:
            if len(chosen) == num or profile[kh] <= 0:
                break
            if all(abs(int(kh) - c) > separation for c in chosen):
                chosen.append(int(kh))
        out = []
        for kh in chosen:
            ka, k1, k2 = np.unravel_index(int(best[kh]), self.acc.shape[:3])
            out.append(self._at(ka, k1, k2, kh))
        return out

    def peaks(self, num: int, separation: tuple[int, int, int, int]) -> list[HoughPeak]:
        """The ``num`` strongest local maxima, at least ``separation`` cells apart
        on some axis (non-maximum suppression), strongest first."""
        from scipy.ndimage import maximum_filter

        size = tuple(
            min(2 * s + 1, n) for s, n in zip(separation, self.acc.shape, strict=True)
        )
        local = self.acc == maximum_filter(self.acc, size=size, mode="constant")
        idx = np.argwhere(local & (self.acc > 0))
        values = self.acc[tuple(idx.T)]
        order = np.argsort(-values, kind="stable")
        sep = np.asarray(separation)
        chosen: list[np.ndarray] = []
        for k in order:
            if len(chosen) == num:
                break
            if all(np.any(np.abs(idx[k] - c) > sep) for c in chosen):
                chosen.append(idx[k])
        return [self._at(*c) for c in chosen]


def _horizontal_axes(view: View) -> np.ndarray:
    """(2, 2): the camera's lateral and viewing directions on the ground."""
    forward = view.R0[2, :2]  # optical axis in the world, horizontal part
    if np.linalg.norm(forward) < 0.2:  # near-nadir: the image's up direction
        forward = -view.R0[1, :2]
    forward = forward / np.linalg.norm(forward)
    lateral = np.array([forward[1], -forward[0]])
    return np.stack([lateral, forward])


def hough(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    pair_i: np.ndarray,
    pair_j: np.ndarray,
    alpha_center: float,
    alpha_half: float,
    c_center: np.ndarray,
    c_half: float,
    cell_px: tuple[float, float, float],
    depth_m: float,
    max_cells: int,
    heights: tuple[float, float, float] | None = None,
) -> HoughGrid:
    """Vote of candidate pairs over a grid of poses (Hough transform).

    For a fixed alpha, pair k's constraint ``r0 cos + r1 sin - g . c = 0``
    (``g = R_z(alpha)^T m_xy``, :func:`ransac_core.constraint_rows`) is a straight
    line in the plane of the centre; it is sampled at the cell centres of
    the axis along which it runs and the other coordinate is rounded to a
    cell. With ``heights`` the accumulator has a fourth axis, the height of
    the segment's bottom on the corner's vertical at that pose: a pair votes
    only at the ground height it implies, which separates the true pairs (all
    at the ground) from the many chance pairs along each vertical.

    The cells are anisotropic because of two near-degeneracies of an oblique
    view: a heading change moves the image almost like a lateral shift of
    the camera, and a forward shift almost like a change of the ground
    height. Coarse cells along alpha and the forward axis are compensated by
    the lateral axis and the height, which are sampled finely.

    Each (alpha, pair) line is rasterised over its exact interval of votes
    (:func:`rasterise`), vectorised over lines and votes; the result is
    bit-identical to an enumeration vote by vote in (alpha, pair, t) order.

    Parameters
    ----------
    pair_i, pair_j : (P,) corner and segment of each pair.
    alpha_center, alpha_half : radians; c_center (2,), c_half : metres, the
        search window (relative to the prior).
    cell_px : (alpha, lateral, forward) cell sizes, pixels of image motion
        at ``depth_m``.
    max_cells : the cells grow until the accumulator has at most this many.
    heights : (lo, hi, step) metres, or None for a 3-D vote.

    Returns
    -------
    HoughGrid, the accumulator smoothed over 3 cells per axis.
    """
    f = view.focal
    d_alpha = cell_px[0] / f
    steps = np.array([cell_px[1], cell_px[2]]) * depth_m / f
    if heights is not None:
        h_lo, h_hi, d_h = heights
        nh = max(1, int(math.ceil((h_hi - h_lo) / d_h)))
    else:
        h_lo, d_h, nh = 0.0, math.inf, 1
    while True:
        na = 2 * int(math.ceil(alpha_half / d_alpha)) + 1
        n1, n2 = (2 * np.ceil(c_half / steps).astype(int) + 1).tolist()
        if na * n1 * n2 * nh <= max_cells or (na == 1 and n1 == 1 and n2 == 1):
            break
        d_alpha *= 1.2
        steps *= 1.2
    axes = _horizontal_axes(view)
    alphas = alpha_center + (np.arange(na) - na // 2) * d_alpha
    xy = corner_rel[pair_i]  # (P, 2)
    m = segs.m_xy[pair_j]  # (P, 2)
    rows = ransac_core.constraint_rows(m, xy - c_center)  # c relative to c_center
    weight = np.minimum(segs.length[pair_j], 60.0)
    if heights is not None:
        ray0 = (
            np.column_stack([segs.bottom[pair_j], np.ones(len(pair_j))])
            @ view.Kinv.T
            @ view.R0
        )  # (P, 3) bottom rays, VP-aligned frame
    slab = n1 * n2 * nh
    acc = np.zeros(na * slab, dtype=np.float32)
    half = np.array([n1 // 2, n2 // 2])
    band_of = None
    if heights is not None:
        # Every pair's votes lie on a segment of cells whose heights are
        # computed in closed form (:func:`_vote_rows`).
        h_hi = h_lo + nh * d_h
        band_of = (ray0, xy - c_center, float(view.c0[2]), h_lo, h_hi, d_h, nh, n1 * n2)
    P = len(pair_i)
    # Rows (alpha, pair) in pieces of ~2^16 rows, several alphas at once or
    # one alpha's pairs in pieces of 2^14 (the coarse vote's ~10^5): the
    # rows' temporaries stay in the cache; an alpha's pieces are joined for
    # its sum.
    pc = min(P, _ROW_PIECE)
    chunk = 1 if pc < P else max(1, (1 << 16) // max(P, 1))
    work = Workspace()
    for k0 in range(0, na, chunk):
        ka = np.arange(k0, min(na, k0 + chunk))
        ca = np.cos(alphas[ka])[:, None]
        sa = np.sin(alphas[ka])[:, None]
        pieces = [
            _vote_rows(
                ca,
                sa,
                m[p0 : p0 + pc],
                rows[p0 : p0 + pc],
                weight[p0 : p0 + pc],
                axes,
                steps,
                half,
                None if band_of is None else _pair_slice(band_of, p0, pc),
            )
            for p0 in range(0, P, pc)
        ]
        lines, band, ia = _join_pieces(pieces)
        group_ends = np.searchsorted(ia, np.arange(len(ka) + 1))
        off = k0 * slab
        acc[off : off + len(ka) * slab] += rasterise(
            lines, band, slab, groups=len(ka), work=work, group_ends=group_ends
        )
    from scipy.ndimage import uniform_filter

    acc = np.ascontiguousarray(acc.reshape(na, nh, n1, n2).transpose(0, 2, 3, 1))
    acc = uniform_filter(acc, size=(3, 3, 3, min(nh, 3)), mode="constant")
    grid = HoughGrid(
        acc,
        alphas,
        np.asarray(c_center, float),
        axes,
        steps,
        h_lo,
        float(d_alpha),
        float(d_h),
    )
    return grid


#: Pairs per piece of Hough rows (:func:`hough`).
_ROW_PIECE = 1 << 14


def _vote_rows(
    ca: np.ndarray,
    sa: np.ndarray,
    m: np.ndarray,
    rows: np.ndarray,
    weight: np.ndarray,
    axes: np.ndarray,
    steps: np.ndarray,
    half: np.ndarray,
    band_of: tuple | None,
) -> tuple[VoteRows, HeightBand | None, np.ndarray]:
    """The Hough rows of some alphas and pairs that cross the window.

    For a fixed alpha, pair k's constraint is the line ``a1 k1 + a2 k2 =
    rhs`` in cell units of the centre; it is iterated along the axis along
    which it runs. Only the rows that cross the window are returned (a third
    to a half do not), the same elementwise expressions on fewer rows.

    Parameters
    ----------
    ca, sa : (A, 1) cos and sin of the alphas; m : (P, 2) ``m_xy`` of the
    pairs' segments; rows : (P, 4) their constraint rows; weight : (P,);
    axes, steps, half : of the grid (:class:`HoughGrid`); band_of : None, or
    (ray0 (P, 3), d_rel (P, 2), c0_z, h_lo, h_hi, d_h, nh, stride) for a
    height axis.

    Returns
    -------
    The rows, (alpha, pair) order; their height band or None; (R,) the
    alpha (index into ``ca``) of each row.
    """
    mx, my = m[:, 0], m[:, 1]
    rhs = rows[:, 0] * ca + rows[:, 1] * sa  # = g . (c - c_center)
    gx, gy = ca * mx + sa * my, -sa * mx + ca * my
    # In cell units: a1 k1 + a2 k2 = rhs.
    a1 = (gx * axes[0, 0] + gy * axes[0, 1]) * steps[0]
    a2 = (gx * axes[1, 0] + gy * axes[1, 1]) * steps[1]
    iter_2 = np.abs(a1) >= np.abs(a2)  # iterate k2, solve k1 (else swap)
    den = np.where(iter_2, a1, a2)
    with np.errstate(divide="ignore", invalid="ignore"):
        A_o = rhs / den  # other = A_o + B_o t (cell units)
        B_o = -np.where(iter_2, a2, a1) / den
    half_it = np.where(iter_2, half[1], half[0])
    half_o = np.where(iter_2, half[0], half[1])
    t_lo, t_hi = t_interval(A_o, B_o, -half_o - 0.5, half_o + 0.5)
    t_lo, t_hi = np.maximum(t_lo, -half_it), np.minimum(t_hi, half_it)
    sel = np.flatnonzero(t_lo <= t_hi)  # rows (alpha, pair)
    ia, ip = np.divmod(sel, len(m))
    A_o, B_o, iter_2 = A_o.ravel()[sel], B_o.ravel()[sel], iter_2.ravel()[sel]
    t_lo, t_hi = t_lo.ravel()[sel], t_hi.ravel()[sel]
    band = None
    if band_of is not None:
        ray0, d_rel, c0_z, h_lo, h_hi, d_h, nh, stride = band_of
        ca, sa = ca[ia, 0], sa[ia, 0]
        ray, d = ray0[ip], d_rel[ip]
        # Horizontal run of the corner from the search centre along each
        # bottom ray's heading is linear in the centre, hence in the cell
        # index along the iterated axis. Centre offsets e1 = E1a + E1b t,
        # e2 = E2a + E2b t (m).
        E1a = np.where(iter_2, A_o * steps[0], 0.0)
        E1b = np.where(iter_2, B_o * steps[0], steps[0])
        E2a = np.where(iter_2, 0.0, A_o * steps[1])
        E2b = np.where(iter_2, steps[1], B_o * steps[1])
        rx = ca * ray[:, 0] + sa * ray[:, 1]
        ry = -sa * ray[:, 0] + ca * ray[:, 1]
        r2 = rx * rx + ry * ry
        u1r = axes[0, 0] * rx + axes[0, 1] * ry
        u2r = axes[1, 0] * rx + axes[1, 1] * ry
        with np.errstate(divide="ignore", invalid="ignore"):
            # Run along the ray: tt = TA + TB t (> 0: in front).
            TA = (d[:, 0] * rx + d[:, 1] * ry - E1a * u1r - E2a * u2r) / r2
            TB = -(E1b * u1r + E2b * u2r) / r2
        hA = c0_z + TA * ray[:, 2]
        hB = TB * ray[:, 2]
        lo, hi = t_interval(hA, hB, h_lo, h_hi)
        t_lo, t_hi = np.maximum(t_lo, lo), np.minimum(t_hi, hi)
        lo, hi = t_interval(TA, TB, 0.0, np.inf)
        t_lo, t_hi = np.maximum(t_lo, lo), np.minimum(t_hi, hi)
        band = HeightBand(hA, hB, TA, TB, h_lo, d_h, nh, float(stride))
    # Cell of vote t of a row: base + stride_t t + stride_o k_other
    # (+ n1 n2 ih), relative to its alpha's slab (each alpha is summed
    # alone). The votes are laid out (alpha, height, k1, k2): a line's
    # successive votes then touch nearby cells (the height changes slowly
    # along it), which keeps the accumulation in cache; transposed to
    # (alpha, k1, k2, height) at the end.
    s1, s2 = float(2 * half[1] + 1), 1.0
    lines = VoteRows(
        A_o,
        B_o,
        np.where(iter_2, half[0], half[1]),
        t_lo,
        t_hi,
        np.full(len(sel), half[0] * s1 + half[1] * s2),
        np.where(iter_2, s2, s1),
        np.where(iter_2, s1, s2),
        weight[ip],
    )
    return lines, band, ia


def _pair_slice(band_of: tuple, p0: int, n: int) -> tuple:
    """``band_of`` of :func:`_vote_rows` for the pairs ``p0:p0 + n``."""
    ray0, d_rel, *rest = band_of
    return (ray0[p0 : p0 + n], d_rel[p0 : p0 + n], *rest)


def _join_pieces(pieces: list) -> tuple[VoteRows, HeightBand | None, np.ndarray]:
    """The results of :func:`_vote_rows` over consecutive pair ranges of one
    alpha (or one piece of several alphas), concatenated."""
    if len(pieces) == 1:
        return pieces[0]
    lines = VoteRows(
        *(
            np.concatenate([getattr(p[0], f.name) for p in pieces])
            for f in dataclasses.fields(VoteRows)
        )
    )
    band = pieces[0][1]
    if band is not None:
        band = replace(
            band,
            **{
                k: np.concatenate([getattr(p[1], k) for p in pieces])
                for k in ("hA", "hB", "TA", "TB")
            },
        )
    return lines, band, np.concatenate([p[2] for p in pieces])
