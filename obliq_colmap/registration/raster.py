"""Rasterisation of the Hough vote's straight lines of cells
(:func:`rasterise`): each row's exact interval of votes, then the votes
generated densely in cache-sized blocks and summed per cell in the order of a
vote-by-vote enumeration (bit-identical to it)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


def t_interval(
    A: np.ndarray, B: np.ndarray, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Integer t with ``lo <= A + B t <= hi``, per row: (t_lo, t_hi) float
    arrays (t_lo > t_hi when empty; infinite bounds where B = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - A) / B, (hi - A) / B
    t_lo = np.ceil(np.minimum(t1, t2))
    t_hi = np.floor(np.maximum(t1, t2))
    # B = 0 (all t or none) and non-finite rows are rare: set sparsely. With
    # a finite lo they all have a non-finite t1, a cheaper first sieve.
    if np.all(np.isfinite(lo)):
        odd = np.flatnonzero(~np.isfinite(t1))
        a, b = np.ravel(A)[odd], np.ravel(B)[odd]
        odd = odd[(b == 0) | ~np.isfinite(a) | np.isnan(b)]
        odd = np.unravel_index(odd, t1.shape)
    else:
        odd = np.nonzero((B == 0) | ~np.isfinite(A) | np.isnan(B))
    if len(odd[0]):
        a, b = A[odd], B[odd]
        lo_o = lo[odd] if np.ndim(lo) else lo
        hi_o = hi[odd] if np.ndim(hi) else hi
        inside = (lo_o <= a) & (hi_o >= a)
        bad = ~np.isfinite(a) | np.isnan(b)
        t_lo[odd] = np.where(inside & ~bad, -np.inf, np.inf)
        t_hi[odd] = np.where(inside & ~bad, np.inf, -np.inf)
    return t_lo, t_hi


@dataclass
class HeightBand:
    """The height axis of a vote (rows as in :class:`VoteRows`): vote t of a
    row falls into height cell ``ih = floor((hA + hB t - h_lo) / d_h)``,
    which must lie in [0, nh), and only in front of the ray, ``TA + TB t >
    0``; ``stride`` is the cell offset of one height step."""

    hA: np.ndarray
    hB: np.ndarray
    TA: np.ndarray
    TB: np.ndarray
    h_lo: float
    d_h: float
    nh: int
    stride: float


@dataclass
class VoteRows:
    """R straight lines to rasterise, one per (alpha, pair), in cell units.

    Vote t (integer, ``t_lo <= t <= t_hi``) of row r lands in the cell
    ``base + stride_t t + stride_o k``, ``k = rint(A + B t)`` the other
    coordinate, which must satisfy ``|k| <= half_o``; ``weight`` (R,) per row.
    All arrays (R,) float (``half_o`` int).
    """

    A: np.ndarray
    B: np.ndarray
    half_o: np.ndarray
    t_lo: np.ndarray
    t_hi: np.ndarray
    base: np.ndarray
    stride_t: np.ndarray
    stride_o: np.ndarray
    weight: np.ndarray


def _vote_ok(
    rows: VoteRows, band: HeightBand | None, r: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Whether vote ``t`` (K,) of rows ``r`` (K,) lands in the accumulator:
    the same float expressions as :func:`rasterise` evaluates per vote."""
    ok = np.abs(np.rint(rows.A[r] + rows.B[r] * t)) <= rows.half_o[r]
    if band is not None:
        ih = np.floor((band.hA[r] + band.hB[r] * t - band.h_lo) / band.d_h)
        ok &= (ih >= 0) & (ih < band.nh) & (band.TA[r] + band.TB[r] * t > 0)
    return ok


def _trim(
    rows: VoteRows, band: HeightBand | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows' exact vote intervals: (row index (R',), t_lo (R',), t_hi (R',))
    of the rows with votes, such that every integer t in [t_lo, t_hi] passes
    :func:`_vote_ok` and no other t of [rows.t_lo, rows.t_hi] does.

    ``rows.t_lo``, ``rows.t_hi`` bound the conditions in exact arithmetic, so
    they may be off by rounding at their ends. Each condition is monotone in
    t also in floating point (``fl(A + fl(B t))`` is monotone, so are rint,
    floor and the comparisons), so the passing t of a row form one interval:
    moving each end inwards while it fails finds it, in a few vectorised
    rounds over the few rows whose end fails. The first round tests both
    ends of every row on the rows' coefficients gathered once.
    """
    count = np.maximum(rows.t_hi - rows.t_lo + 1, 0)
    r = np.flatnonzero(count > 0)
    lo, hi = rows.t_lo[r], rows.t_hi[r]
    sub = VoteRows(rows.A[r], rows.B[r], rows.half_o[r], lo, hi, *(None,) * 4)
    sub_band = None
    if band is not None:
        sub_band = replace(
            band, hA=band.hA[r], hB=band.hB[r], TA=band.TA[r], TB=band.TB[r]
        )
    every = slice(None)
    fail_hi = ~_vote_ok(sub, sub_band, every, hi)  # hi is not moved before its turn
    for end, step in ((lo, 1.0), (hi, -1.0)):
        fail = ~_vote_ok(sub, sub_band, every, lo) if step > 0 else fail_hi
        k = np.flatnonzero(fail & (lo <= hi))
        end[k] += step
        while len(k):
            k = k[lo[k] <= hi[k]]
            k = k[~_vote_ok(sub, sub_band, k, end[k])]
            end[k] += step
    keep = lo <= hi
    return r[keep], lo[keep], hi[keep]


#: Votes (dense t x row entries) generated at once by :func:`rasterise`:
#: its three float64 temporaries of this size stay in the L2 / L3 cache.
_RASTER_BLOCK = 1 << 16


class Workspace:
    """Scratch arrays reused across the calls of one vote (fresh arrays of
    megabytes cost page faults on every first touch: measured 10-20 % of
    the coarse vote's CPU time as system time)."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def array(self, name: str, size: int, dtype) -> np.ndarray:
        """A (size,) array of ``dtype`` with arbitrary contents."""
        a = self._arrays.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            # With headroom: the next call's rows are a few more.
            a = np.empty(size + size // 4, dtype)
            self._arrays[name] = a
        return a[:size]


def rasterise(
    rows: VoteRows,
    band: HeightBand | None,
    size: int,
    groups: int = 1,
    work: Workspace | None = None,
    group_ends: np.ndarray | None = None,
) -> np.ndarray:
    """Sum of the rows' weights over the cells they cross.

    The rows form ``groups`` consecutive groups that vote into disjoint
    ranges of ``size`` cells (the alphas of the Hough vote; cell indices
    relative to the range), of equal length or group g the rows
    ``group_ends[g]:group_ends[g + 1]``: returns (groups * size,) float64.

    Every row's votes are an interval of t (:func:`_trim`); they are generated
    densely, (t - t_lo) x rows (the inner loops run over rows, not over a
    row's few votes), in blocks that fit the cache, the entries past a row's
    end sent to a spare cell. A group's votes reach one ``np.bincount`` in
    row order, t ascending, so that each cell sums the same terms in the same
    order as an enumeration vote by vote.
    """
    work = work or Workspace()
    out = np.zeros(groups * size)
    r, lo, hi = _trim(rows, band)
    if len(r) == 0:
        return out
    count = hi - lo + 1
    width = int(count.max())
    steps = np.arange(width, dtype=float)[:, None]
    block = max(1, _RASTER_BLOCK // width)
    buf = work.array("buf", 3 * width * block, float).reshape(3, width * block)
    A, B, base = rows.A[r], rows.B[r], rows.base[r]
    stride_t, stride_o = rows.stride_t[r], rows.stride_o[r]
    if band is not None:
        hA, hB = band.hA[r], band.hB[r]
    if group_ends is None:
        group_ends = np.arange(groups + 1) * (len(rows.A) // groups)
    ends = np.searchsorted(r, group_ends)
    for g in range(groups):
        g0, g1 = ends[g], ends[g + 1]
        if g0 == g1:
            continue
        n = g1 - g0
        cells = work.array("cells", n * width, np.int64).reshape(n, width)
        for b0 in range(g0, g1, block):
            b = slice(b0, min(b0 + block, g1))
            nb = b.stop - b0
            # Contiguous (width, rows) arrays (putmask copies strided ones).
            t, k, cell = (x[: width * nb].reshape(width, nb) for x in buf)
            np.add(lo[b], steps, out=t)
            np.multiply(B[b], t, out=k)
            k += A[b]
            np.rint(k, out=k)
            np.multiply(stride_o[b], k, out=cell)
            cell += base[b]
            if band is not None:
                np.multiply(hB[b], t, out=k)
                k += hA[b]
                k -= band.h_lo
                k /= band.d_h
                np.floor(k, out=k)
                k *= band.stride
                cell += k
            np.multiply(stride_t[b], t, out=k)
            cell += k
            np.putmask(cell, steps >= count[b], size)  # spare
            # Integer-valued floats: the cast to the cell index is exact.
            np.copyto(cells[b0 - g0 : b.stop - g0], cell.T, casting="unsafe")
        weights = work.array("weights", n * width, float).reshape(n, width)
        weights[...] = rows.weight[r[g0:g1], None]
        out[g * size : (g + 1) * size] = np.bincount(
            cells.ravel(), weights=weights.ravel(), minlength=size + 1
        )[:size]
    return out
