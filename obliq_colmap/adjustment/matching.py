"""Matching horizontal facade edges across images (stage 3, second step).

Habbecke & Kobbelt, section 2.3: after the per-image registrations the
images disagree in height by an offset that varies linearly over the map (a
slightly wrong vertical tilts an image's ground plane). For each pair of
images sharing walls, RANSAC with samples of three finds that bivariate
linear height offset among the candidate pairs of segments (same wall, same
gradient sign); every pair that agrees with the winner is a match. Matches
are chained across images into tracks: one track is one 3D horizontal edge
with one unknown height ``h_j`` (the bundle's facade-edge constraint).

Heights here are the per-image heights ABOVE THE IMAGE'S OWN GROUND PLANE
(:mod:`~obliq_colmap.adjustment.facades`): they agree between images to a
metre or two, so candidates are searched within ``max_offset_m`` only (window
rows repeat every floor, ~3 m, with the same gradient sign).

The pairwise offsets also give each image's height datum error: stage 2
holds the prior camera height, so image k sees the whole scene shifted by
``e_k`` (its ground plane ``g_k = G + e_k``). For a matched edge the absolute
heights differ by ``e_A - e_B``; least squares over all pairs (one gauge per
connected group of images: zero mean) gives the camera-height corrections
that initialise the bundle (issue 5: "initialise camera heights from the
pairwise planar height offsets").

The results (:class:`~obliq_colmap.adjustment.tracks.PairMatch`,
:class:`~obliq_colmap.adjustment.tracks.FacadeTracks`) are in
:mod:`~obliq_colmap.adjustment.tracks`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from obliq_colmap.adjustment.facades import FacadeEdges
from obliq_colmap.adjustment.tracks import FacadeTracks, PairMatch

__all__ = [
    "MatchingOptions",
    "chain_tracks",
    "datum_corrections",
    "match_facade_edges",
    "match_pair",
    "points_along_edges",
]

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class MatchingOptions:
    """Options of :func:`match_facade_edges`."""

    #: Candidate pairs differ by at most this in height above ground (m).
    max_offset_m: float = 2.5
    #: Inlier threshold of the planar-offset RANSAC, pixels along the
    #: projected vertical, in the coarser of the two images (the paper: 2 px;
    #: 1 px here, which measured better on the `paper` preset).
    #: Pixels of the image the segments were detected in
    #: (``FacadeEdges.pixel_scale``: their localisation noise lives there).
    inlier_threshold_px: float = 1.0
    #: Image pairs need this many shared walls with candidates.
    min_shared_walls: int = 3
    #: A pair's winner needs this many inlier matches ...
    min_matches: int = 6
    #: ... on at least this many walls.
    min_match_walls: int = 3
    #: RANSAC: hypotheses per batch, least / most hypotheses, confidence.
    batch_size: int = 256
    min_trials: int = 256
    max_trials: int = 4096
    confidence: float = 0.999
    #: Largest tilt difference between two images (deg): bounds the slope of
    #: the planar offset (a per-image vertical error of ~0.5 deg is typical).
    max_tilt_deg: float = 1.5
    #: Largest relative scale difference of heights between two images
    #: (their focal lengths, refined per image, differ by about this).
    max_scale: float = 0.05
    #: Samples whose three anchors span a triangle smaller than this (m^2)
    #: are degenerate for a plane and replaced by a constant offset.
    min_sample_area_m2: float = 25.0
    #: Observations of one track in one image must agree in height to this
    #: (m); else the track joined different edges and is dropped.
    track_height_tolerance_m: float = 0.5
    #: Random seed (deterministic results).
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_offset_m <= 0 or self.inlier_threshold_px <= 0:
            raise ValueError("max_offset_m and inlier_threshold_px must be > 0")
        if not 0 < self.confidence < 1:
            raise ValueError("confidence must be in (0, 1)")


# --------------------------------------------------------------------------
# One pair
# --------------------------------------------------------------------------


def points_along_edges(edge_xy: np.ndarray, edge_length: np.ndarray, s: np.ndarray):
    """(N, 2) points at distance s (N,) along edges (N, 2, 2)."""
    d = (edge_xy[:, 1] - edge_xy[:, 0]) / edge_length[:, None]
    return edge_xy[:, 0] + s[:, None] * d


def _candidates(fa: FacadeEdges, fb: FacadeEdges, max_offset_m: float):
    """Pairs of rows on the same wall, same polarity, heights within the bound.

    Returns (ia, ib) int arrays. Vectorised by sorting on (wall, polarity).
    """
    key_a = fa.edge * 2 + (fa.polarity > 0)
    key_b = fb.edge * 2 + (fb.polarity > 0)
    ob = np.argsort(key_b, kind="stable")
    kb = key_b[ob]
    lo = np.searchsorted(kb, key_a, "left")
    hi = np.searchsorted(kb, key_a, "right")
    counts = hi - lo
    ia = np.repeat(np.arange(len(fa)), counts)
    start = np.repeat(lo, counts)
    offs = np.arange(len(ia)) - np.repeat(np.cumsum(counts) - counts, counts)
    ib = ob[start + offs]
    near = np.abs(fa.height[ia] - fb.height[ib]) <= max_offset_m
    return ia[near], ib[near]


def _plane_hypotheses(
    xy: np.ndarray, dz: np.ndarray, samples: np.ndarray, min_area: float
) -> np.ndarray:
    """(T, 4) offset models through sample triples (T, 3), see :func:`_design`.

    The plane part through the three samples, no scale term; nearly collinear
    triples (area < min_area, m^2) give the constant mean offset.
    """
    P = xy[samples]  # (T, 3, 2)
    Z = dz[samples]  # (T, 3)
    A = np.concatenate([P, np.ones(P.shape[:2] + (1,))], axis=2)  # (T, 3, 3)
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    ok = area >= min_area
    models = np.zeros((len(samples), 4))
    models[:, 2] = Z.mean(axis=1)
    if ok.any():
        models[ok, :3] = np.linalg.solve(A[ok], Z[ok][..., None])[..., 0]
    return models


def _design(xy: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 4) rows ``(x, y, 1, t)`` of the offset model ``dz = m . row``.

    A plane over the map (a tilt difference between the two images, paper
    Fig. 5) plus a term proportional to the height above ground (a scale
    difference: focal lengths a percent apart make heights a percent apart).
    ``xy`` relative to the candidates' centroid, metres.
    """
    return np.column_stack([xy, np.ones(len(xy)), t])


def _fit_model(
    D: np.ndarray, dz: np.ndarray, w: np.ndarray, prior_sigma: np.ndarray
) -> np.ndarray:
    """Weighted least squares of ``dz = D m`` with zero-mean priors on m.

    ``prior_sigma`` (4,): 1-sigma of (slope x, slope y, offset, scale);
    the priors keep an ill-conditioned fit (collinear anchors, one height)
    at small tilts and scales.
    """
    sw = np.sqrt(w)
    A = np.vstack([D * sw[:, None], np.diag(1.0 / prior_sigma)])
    b = np.r_[dz * sw, np.zeros(4)]
    return np.linalg.lstsq(A, b, rcond=None)[0]


def match_pair(
    fa: FacadeEdges,
    fb: FacadeEdges,
    anchors_a: np.ndarray,
    anchors_b: np.ndarray,
    options: MatchingOptions,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """RANSAC over the candidate pairs of two images.

    Parameters
    ----------
    fa, fb : the two images' FacadeEdges.
    anchors_a, anchors_b : (Ka, 2), (Kb, 2) map positions of their rows.

    Returns
    -------
    rows_a, rows_b : (M,) matched rows (mutually best per row), empty on
        failure; model (4,) of :func:`_design` (about the candidates'
        centroid); number of candidates; number of trials.
    """
    empty = np.zeros(0, np.int64)
    ia, ib = _candidates(fa, fb, options.max_offset_m)
    n = len(ia)
    if n < 3 or len(np.unique(fa.edge[ia])) < options.min_shared_walls:
        return empty, empty, np.zeros(4), n, 0
    xy = 0.5 * (anchors_a[ia] + anchors_b[ib])
    xy = xy - xy.mean(axis=0)
    t = 0.5 * (fa.height[ia] + fb.height[ib])
    dz = fa.height[ia] - fb.height[ib]
    D = _design(xy, t)
    # Threshold in metres: inlier_threshold_px (detection pixels) in the
    # coarser image.
    thr = options.inlier_threshold_px * np.maximum(
        fa.pixel_scale[ia] / fa.px_per_m[ia], fb.pixel_scale[ib] / fb.px_per_m[ib]
    )
    max_slope = math.tan(math.radians(options.max_tilt_deg))
    prior_sigma = np.array(
        [max_slope / 2, max_slope / 2, options.max_offset_m, options.max_scale / 2]
    )
    walls = fa.edge[ia]
    best_score, best, trials = -1.0, np.zeros(4), 0
    needed = float(options.max_trials)
    while trials < min(needed, options.max_trials):
        T = options.batch_size
        smp = rng.integers(0, n, size=(T, 3))
        # distinct walls in a sample (else the plane is not constrained)
        distinct = (
            (walls[smp[:, 0]] != walls[smp[:, 1]])
            & (walls[smp[:, 0]] != walls[smp[:, 2]])
            & (walls[smp[:, 1]] != walls[smp[:, 2]])
        )
        smp = smp[distinct]
        trials += T
        if len(smp) == 0:
            continue
        models = _plane_hypotheses(xy, dz, smp, options.min_sample_area_m2)
        models = models[np.all(np.abs(models[:, :2]) <= max_slope, axis=1)]
        if len(models) == 0:
            continue
        inl = np.abs(dz[:, None] - D @ models.T) <= thr[:, None]
        score = inl.sum(axis=0)
        k = int(np.argmax(score))
        if score[k] > best_score:
            best_score, best = float(score[k]), models[k]
            ratio = best_score / n
            if ratio >= 1.0:
                needed = 0.0
            elif ratio > 0:
                needed = math.log(1 - options.confidence) / math.log(1 - ratio**3)
        if trials >= options.min_trials and trials >= needed:
            break
    # Refit on the inliers (with the scale term), re-score.
    model = best
    for _ in range(2):
        inl = np.abs(dz - D @ model) <= thr
        if inl.sum() < 3:
            return empty, empty, model, n, trials
        model = _fit_model(D[inl], dz[inl], 1.0 / thr[inl] ** 2, prior_sigma)
    r = np.abs(dz - D @ model) / thr  # in thresholds
    inl = np.flatnonzero(r <= 1.0)
    keep = _mutual_best(ia[inl], ib[inl], r[inl])
    ia, ib = ia[inl][keep], ib[inl][keep]
    if len(ia) < options.min_matches or len(np.unique(fa.edge[ia])) < (
        options.min_match_walls
    ):
        return empty, empty, model, n, trials
    return ia, ib, model, n, trials


def _mutual_best(ia: np.ndarray, ib: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Indices of the pairs that are the best (smallest r) for both rows."""
    order = np.lexsort((r, ia))
    first_a = order[np.r_[True, ia[order][1:] != ia[order][:-1]]]
    order = np.lexsort((r, ib))
    first_b = order[np.r_[True, ib[order][1:] != ib[order][:-1]]]
    return np.intersect1d(first_a, first_b)


# --------------------------------------------------------------------------
# The block
# --------------------------------------------------------------------------


def _shared_walls(facades: Sequence[FacadeEdges], num_edges: int) -> sp.csr_matrix:
    """(I, I) upper-triangular counts of the walls two images share."""
    rows, cols = [], []
    for k, f in enumerate(facades):
        walls = np.unique(f.edge)
        rows.append(np.full(len(walls), k))
        cols.append(walls)
    if not rows:
        return sp.csr_matrix((0, 0))
    M = sp.csr_matrix(
        (
            np.ones(sum(len(r) for r in rows)),
            (np.concatenate(rows), np.concatenate(cols)),
        ),
        shape=(len(facades), num_edges),
    )
    return sp.triu(M @ M.T, k=1).tocsr()


def match_facade_edges(
    facades: Sequence[FacadeEdges],
    grounds: np.ndarray,
    cadastre,
    options: MatchingOptions | None = None,
) -> FacadeTracks:
    """Match facade edges over all image pairs and chain them into tracks.

    Parameters
    ----------
    facades : per image its FacadeEdges (index = image index).
    grounds : (I, 3) array, each image's ground plane ``z = g0 x + g1 y + g2``
        (local metres, the image's own height datum).
    cadastre : Cadastre (edge geometry).
    options : MatchingOptions

    Returns
    -------
    FacadeTracks (empty when nothing matched).
    """
    options = options or MatchingOptions()
    rng = np.random.default_rng(options.seed)
    grounds = np.asarray(grounds, float).reshape(-1, 3)
    num = len(facades)
    anchors = [
        points_along_edges(cadastre.edge_xy[f.edge], cadastre.edge_length[f.edge], f.s)
        for f in facades
    ]
    shared = _shared_walls(facades, cadastre.num_edges).tocoo()
    pairs: list[PairMatch] = []
    for a, b, count in zip(shared.row, shared.col, shared.data, strict=True):
        if count < options.min_shared_walls:
            continue
        ra, rb, model, n_cand, n_trials = match_pair(
            facades[a], facades[b], anchors[a], anchors[b], options, rng
        )
        if len(ra) == 0:
            continue
        xy = 0.5 * (anchors[a][ra] + anchors[b][rb])
        # absolute heights H = g + t; e_a - e_b = H_a - H_b
        ha = xy @ grounds[a, :2] + grounds[a, 2] + facades[a].height[ra]
        hb = xy @ grounds[b, :2] + grounds[b, 2] + facades[b].height[rb]
        pairs.append(
            PairMatch(
                int(a),
                int(b),
                ra,
                rb,
                model,
                float(np.median(ha - hb)),
                n_cand,
                n_trials,
            )
        )
    logger.info(
        "facade matching: %d image pairs with matches, %d matches",
        len(pairs),
        sum(p.num_matches for p in pairs),
    )
    correction = datum_corrections(pairs, num)
    return chain_tracks(facades, anchors, grounds, correction, pairs, options)


def datum_corrections(pairs: Sequence[PairMatch], num_images: int) -> np.ndarray:
    """(I,) height datum error ``e_k`` of each image from the pairwise offsets.

    Weighted least squares of ``e_a - e_b = datum_offset`` (weight: the
    number of matches), zero mean in each connected group of images; NaN for
    images without matches.
    """
    e = np.full(num_images, np.nan)
    if not pairs:
        return e
    a = np.array([p.a for p in pairs])
    b = np.array([p.b for p in pairs])
    d = np.array([p.datum_offset for p in pairs])
    w = np.sqrt([p.num_matches for p in pairs], dtype=float)
    G = sp.csr_matrix((np.ones(len(a)), (a, b)), shape=(num_images, num_images))
    _, label = connected_components(G, directed=False)
    linked = np.zeros(num_images, bool)
    linked[a] = linked[b] = True
    for comp in np.unique(label[linked]):
        members = np.flatnonzero((label == comp) & linked)
        pos = {int(m): k for k, m in enumerate(members)}
        sel = np.flatnonzero(np.isin(a, members))
        A = np.zeros((len(sel) + 1, len(members)))
        rhs = np.zeros(len(sel) + 1)
        for r, p in enumerate(sel):
            A[r, pos[int(a[p])]] = w[p]
            A[r, pos[int(b[p])]] = -w[p]
            rhs[r] = w[p] * d[p]
        A[-1] = 1.0  # gauge: zero mean
        e[members] = np.linalg.lstsq(A, rhs, rcond=None)[0]
    return e


def chain_tracks(
    facades: Sequence[FacadeEdges],
    anchors: Sequence[np.ndarray],
    grounds: np.ndarray,
    correction: np.ndarray,
    pairs: Sequence[PairMatch],
    options: MatchingOptions,
) -> FacadeTracks:
    """Chain pairwise matches into tracks (connected components)."""
    if not pairs:
        return FacadeTracks(datum_correction=correction, pairs=list(pairs))
    offset = np.cumsum([0] + [len(f) for f in facades])
    u = np.concatenate([offset[p.a] + p.rows_a for p in pairs])
    v = np.concatenate([offset[p.b] + p.rows_b for p in pairs])
    n_nodes = int(offset[-1])
    G = sp.csr_matrix((np.ones(len(u)), (u, v)), shape=(n_nodes, n_nodes))
    _, label = connected_components(G, directed=False)
    nodes = np.unique(np.concatenate([u, v]))
    image = np.searchsorted(offset, nodes, side="right") - 1
    row = nodes - offset[image]
    comp = label[nodes]
    # Per observation: wall, segment, absolute corrected height (all images'
    # rows concatenated, indexed by node).
    wall = np.concatenate([f.edge for f in facades])[nodes]
    seg = np.concatenate([f.segment for f in facades])[nodes]
    xy = np.concatenate(anchors)[nodes]
    t = np.concatenate([f.height for f in facades])[nodes]
    h = (
        np.sum(xy * grounds[image, :2], axis=1)
        + grounds[image, 2]
        + t
        - np.nan_to_num(correction[image])
    )
    bad = np.zeros(len(nodes), bool)
    # A segment in tracks of two walls: it belongs to at most one of them.
    key = image.astype(np.int64) * (1 << 32) + seg
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    bad |= cnt[inv] > 1
    # One track, one image: all its observations at one height.
    key = comp.astype(np.int64) * len(facades) + image
    _, inv = np.unique(key, return_inverse=True)
    hmax = np.full(inv.max() + 1, -np.inf)
    hmin = np.full(inv.max() + 1, np.inf)
    np.maximum.at(hmax, inv, h)
    np.minimum.at(hmin, inv, h)
    spread = (hmax - hmin)[inv] > options.track_height_tolerance_m
    _, cinv = np.unique(comp, return_inverse=True)
    bad_comp = np.zeros(cinv.max() + 1, bool)
    bad_comp[cinv[spread]] = True
    bad |= bad_comp[cinv]
    keep = ~bad
    image, row, comp, wall, xy, h = (x[keep] for x in (image, row, comp, wall, xy, h))
    # Tracks seen in at least two images.
    key = comp.astype(np.int64) * len(facades) + image
    uniq = np.unique(key)
    comp_of = uniq // len(facades)
    ids, n_images = np.unique(comp_of, return_counts=True)
    good = ids[n_images >= 2]
    sel = np.isin(comp, good)
    image, row, comp, wall, xy, h = (x[sel] for x in (image, row, comp, wall, xy, h))
    tracks, track = np.unique(comp, return_inverse=True)
    J = len(tracks)
    if J == 0:
        return FacadeTracks(datum_correction=correction, pairs=list(pairs))
    cnt = np.bincount(track, minlength=J).astype(float)
    anchor = (
        np.column_stack(
            [np.bincount(track, xy[:, 0], J), np.bincount(track, xy[:, 1], J)]
        )
        / cnt[:, None]
    )
    edge = np.zeros(J, np.int64)
    edge[track] = wall
    height = np.bincount(track, h, J) / cnt
    # (the mean of points on one map edge lies on it: the anchor is on the edge)
    return FacadeTracks(
        image=image.astype(np.int64),
        row=row.astype(np.int64),
        track=track.astype(np.int64),
        anchor_xy=anchor,
        edge=edge,
        height=height,
        datum_correction=correction,
        pairs=list(pairs),
    )
