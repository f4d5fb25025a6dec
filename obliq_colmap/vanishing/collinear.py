"""Segments that lie on one image line: the evidence a pencil really has.

A line of the image broken into pieces (a street's dashed centre line, a curb
behind parked cars, one window column's jambs) is one line, whatever the
number of pieces LSD returns. A vanishing point is fixed by how many distinct
lines pass through it, not by how many pieces: counting pieces lets one
street seen along its length outvote the short vertical edges of a district
of low-rise houses (houses-102: 272 pieces on 124 lines against the truth's
160 on 143; docs/journal/independent-scenes.md, 2026-12-05 "pieces of one
line").
"""

from __future__ import annotations

import numpy as np

from obliq_colmap.geometry import tangent_basis

#: rows of the pair matrix handled at once (memory: rows x segments floats).
_CHUNK = 256


def line_length(ends: np.ndarray, tol: float) -> np.ndarray:
    """The total length of the segments on each segment's line (itself included).

    Two segments are on one line when the total-least-squares line of their
    four endpoints passes within ``tol`` of each, whatever the gap between
    them: far apart, when each one's direction agrees with the line joining
    them to within its own precision (``tol`` over half its length), i.e.
    as far as the two segments can tell they are one line. Rows of street
    trees, parked cars, curbs and dashes along a street are such lines;
    verticals through one VP are not, except where they share a line of its
    pencil (a facade's column of window jambs). Pairs, not chains: the sum
    counts the length lying along each segment's own line. O(S^2) in
    chunks (about 0.1 s for 1,400 segments).

    Parameters
    ----------
    ends : (S, 2, 2) endpoints (any units, ``tol`` in the same).
    tol : largest endpoint distance to the common line.

    Returns
    -------
    (S,) float, >= each segment's own length.
    """
    S = len(ends)
    mid = ends.mean(axis=1)
    d = ends[:, 1] - ends[:, 0]
    L = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    total = L.copy()
    if S < 2:
        return total
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / L[:, None]  # unit normals
    c = -np.sum(n * mid, axis=1)
    for a in range(0, S, _CHUNK):
        b = min(S, a + _CHUNK)
        # Cheap screen: each midpoint near the other's line, allowing the
        # line's direction error (tol over half its length) over the distance.
        dist_ij = np.abs(n[a:b] @ mid.T + c[a:b, None])  # mid j to line i
        dist_ji = np.abs(mid[a:b] @ n.T + c[None])  # mid i to line j
        D = np.linalg.norm(mid[a:b, None] - mid[None], axis=2)
        slack_i = tol * (1.0 + 2.0 * D / L[a:b, None])
        slack_j = tol * (1.0 + 2.0 * D / L[None])
        cand = (dist_ij <= slack_i) & (dist_ji <= slack_j)
        cand[np.arange(b - a), np.arange(a, b)] = False
        i, j = np.nonzero(cand)
        if not len(i):
            continue
        i = i + a
        pts = np.concatenate([ends[i], ends[j]], axis=1)  # (P, 4, 2)
        ctr = pts.mean(axis=1, keepdims=True)
        q = pts - ctr
        cxx = np.sum(q[..., 0] ** 2, axis=1)
        cyy = np.sum(q[..., 1] ** 2, axis=1)
        cxy = np.sum(q[..., 0] * q[..., 1], axis=1)
        # Normal of the TLS line: eigenvector of the smaller eigenvalue.
        theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy) + 0.5 * np.pi
        nn = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        res = np.abs(np.einsum("pkd,pd->pk", q, nn)).max(axis=1)
        same = res <= tol
        total += np.bincount(i[same], weights=L[j[same]], minlength=S)
    return total


def distinct_lines(ends: np.ndarray, v: np.ndarray, tol: float) -> int:
    """How many distinct lines through the VP ``v`` the segments lie on.

    Parameters
    ----------
    ends : (S, 2, 2) endpoints of segments consistent with ``v``
        (normalised coordinates).
    v : (3,) homogeneous VP, the same coordinates.
    tol : two segments are on one line through ``v`` when the line through
        ``v`` and one's midpoint passes within ``tol`` of the other's.

    Returns
    -------
    int
    """
    if len(ends) < 2:
        return len(ends)
    v = np.asarray(v, float) / np.linalg.norm(v)
    mid = np.concatenate([ends.mean(axis=1), np.ones((len(ends), 1))], axis=1)
    lines = np.cross(mid, v)
    x = lines @ tangent_basis(v)
    order = np.argsort(np.arctan2(x[:, 1], x[:, 0]) % np.pi)
    ln = lines[order] / np.maximum(
        np.linalg.norm(lines[order, :2], axis=1, keepdims=True), 1e-300
    )
    gap = np.abs(np.sum(ln[:-1] * mid[order[1:]], axis=1))
    return 1 + int(np.count_nonzero(gap > tol))
