"""The second pass: segments constrained through a known vanishing point.

The derivative perpendicular to the line from the VP through each pixel,
non-maximum suppression and hysteresis, chains fitted through the VP (ends
trimmed out of the fit), pieces of one line merged, ends moved out to where
the contrast halves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from obliq_colmap.geometry import Camera, tangent_basis
from obliq_colmap.lines import (
    EdgePoints,
    Segments,
    as_gray_u8,
    bilinear_many,
    connected_pairs,
    edge_points,
    fit_lines,
    gradients,
    scatter_matrices,
    segment_extents,
    split_at_gaps,
)
from obliq_colmap.vanishing.options import SecondPassOptions
from obliq_colmap.vanishing.pencil import (
    normaliser,
    pencil_fit,
)


@dataclass
class SecondPass:
    """Second-pass segments with their edge points' scatter (normalised)."""

    segments: Segments
    scatter: np.ndarray  # (G, 3, 3)

    def through(self, vp: np.ndarray, T: np.ndarray) -> Segments:
        """The same segments refitted through another (nearby) VP."""
        if len(self.scatter) == 0:
            return self.segments
        vn = T @ vp
        _, lines = pencil_fit(self.scatter, vn / np.linalg.norm(vn))
        return self._on(lines, T)

    def free(self, T: np.ndarray) -> Segments:
        """The same segments, each fitted on its own edge points: its own
        direction, which a wrong VP does not bend (the bundle's vertical rows
        measure the direction; fitted through stage 1's VP they carried its
        error into the block)."""
        if len(self.scatter) == 0:
            return self.segments
        lines, _ = fit_lines(self.scatter)
        return self._on(lines, T)

    def _on(self, lines: np.ndarray, T: np.ndarray) -> Segments:
        """The segments' ends moved onto (G, 3) normalised ``lines``."""
        ends_n = self.segments.endpoints @ T[:2, :2].T + T[:2, 2]
        G = len(lines)
        ends_n = _extents_on(
            ends_n.reshape(-1, 2), np.repeat(np.arange(G), 2), lines, G
        )
        Tinv = np.linalg.inv(T)
        ends = ends_n @ Tinv[:2, :2].T + Tinv[:2, 2]
        return Segments(ends, self.segments.normal, self.segments.strength)


def run_second_pass(
    image: np.ndarray,
    vp: np.ndarray,
    options: SecondPassOptions,
    camera: Camera | None,
    T: np.ndarray,
    grads: tuple[np.ndarray, np.ndarray] | None = None,
) -> SecondPass:
    img = as_gray_u8(image)
    H, W = img.shape
    gx, gy = grads if grads is not None else gradients(img, options.sigma_px)
    # The derivative is taken in the image as seen; with lens distortion the
    # local direction to the VP is approximated with the distorted position
    # (tolerated by max_gradient_angle_deg); the fit below is undistorted.
    vx, vy, vw = (float(c) for c in vp / np.abs(vp).max())

    def across_vp_line(x, y, gx_, gy_):
        # x (1, W), y (H, 1): the field is separable up to the norm. float32
        # is enough for a direction; v scaled so nothing overflows.
        ux = np.float32(vx) - x * np.float32(vw)
        uy = np.float32(vy) - y * np.float32(vw)
        # In place: two full-image arrays instead of six.
        inv = ux * ux + uy * uy
        np.sqrt(inv, out=inv)
        np.maximum(inv, np.float32(1e-30), out=inv)
        np.divide(np.float32(1.0), inv, out=inv)
        nx = np.multiply(-uy, inv)
        inv *= ux
        return nx, inv

    pts: EdgePoints = edge_points(
        gx,
        gy,
        across_vp_line,
        options.low,
        options.high,
        options.max_gradient_angle_deg,
    )
    empty = SecondPass(Segments(), np.zeros((0, 3, 3)))
    if len(pts.xy) == 0:
        return empty
    xy_px = pts.xy
    if camera is not None and camera.has_distortion:
        xy_px = camera.undistort_pixels(xy_px)
    s = 1.0 / T[0, 0]
    xy = xy_px @ T[:2, :2].T + T[:2, 2]  # normalised
    vn = T @ np.asarray(vp, float)
    vn /= np.linalg.norm(vn)
    group = pts.group
    d_sign = np.sign(pts.derivative)

    # Fit each chain through the VP, drop far points, cut at gaps, refit.
    G = pts.n_groups
    absd = np.abs(pts.derivative)
    _, lines = pencil_fit(scatter_matrices(xy, group, G), vn)
    r = np.abs(np.sum(xy * lines[group, :2], axis=1) + lines[group, 2]) * s
    good = r <= options.max_point_distance_px
    xy, group, xy_px = xy[good], group[good], xy_px[good]
    absd, d_sign = absd[good], d_sign[good]
    tangent = np.stack([-lines[:, 1], lines[:, 0]], axis=1)
    pos = np.sum(xy * tangent[group], axis=1)
    group, order = split_at_gaps(xy, group, tangent, options.max_gap_px / s)
    xy, absd, d_sign, pos = xy[order], absd[order], d_sign[order], pos[order]
    G = int(group.max()) + 1 if len(group) else 0
    if G == 0:
        return empty
    count = np.bincount(group, minlength=G).astype(float)
    if options.end_trim_px > 0:
        # Points near a chain's ends (junctions with roof, ground, other
        # edges) leave the line in one direction: left out of the fit.
        first = np.r_[0, np.flatnonzero(np.diff(group)) + 1]
        last = np.r_[first[1:], len(group)] - 1
        trim = options.end_trim_px / s
        w = (pos - pos[first][group] >= trim) & (pos[last][group] - pos >= trim)
    else:
        w = np.ones(len(group), bool)
    short = np.bincount(group, weights=w, minlength=G) < 3
    w = (w | short[group]).astype(float)
    Sc = scatter_matrices(xy, group, G, weights=w)
    cost, lines = pencil_fit(Sc, vn)
    ends = _extents_on(xy, group, lines, G)
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1) * s
    rms = np.sqrt(cost / np.maximum(Sc[:, 2, 2], 1)) * s
    sign = np.bincount(group, weights=d_sign, minlength=G)
    strength = np.bincount(group, weights=absd, minlength=G) / np.maximum(count, 1)
    # Fragments shorter than a quarter of the minimum length (at most 3 px)
    # are noise far more often than pieces of a broken edge.
    keep = (
        (rms <= options.max_rms_px)
        & (count >= 3)
        & (length >= min(3.0, 0.25 * options.min_length_px))
    )
    # Merge pieces of one line through the VP before the length test.
    if options.merge:
        Sc, ends, sign, strength, count, lines = _merge_pencil(
            Sc[keep],
            ends[keep],
            sign[keep],
            strength[keep],
            count[keep],
            lines[keep],
            vn,
            options.merge_max_distance_px / s,
            options.merge_max_gap_px / s,
        )
        keep = np.ones(len(Sc), bool)
    Tinv = np.linalg.inv(T)
    ends_px = ends @ Tinv[:2, :2].T + Tinv[:2, 2]
    # Edge normal n was (-uy, ux) with u towards the VP; D > 0: brighter on +n.
    mid = ends_px.mean(axis=1)
    ux = vx - mid[:, 0] * vw
    uy = vy - mid[:, 1] * vw
    nrm = np.sqrt(ux * ux + uy * uy)
    nrm = np.where(nrm > 0, nrm, 1.0)
    normal = (
        np.stack([-uy / nrm, ux / nrm], axis=1) * np.where(sign >= 0, 1, -1)[:, None]
    )
    if options.extend_max_px > 0:
        ends_px = _extend_ends(
            ends_px, normal, strength, gx, gy, camera, options.extend_max_px
        )
    length = np.linalg.norm(ends_px[:, 1] - ends_px[:, 0], axis=1)
    keep &= (length >= options.min_length_px) & (count >= options.min_density * length)
    return SecondPass(Segments(ends_px[keep], normal[keep], strength[keep]), Sc[keep])


def _extend_ends(ends, normal, strength, gx, gy, camera, max_px, step=0.5):
    """Move segment ends outwards to where the edge's contrast halves.

    Near a junction (wall meeting roof or ground) the gradient turns and the
    edge points stop a few pixels short of the edge's end. Along the segment's
    line beyond each end, the derivative across the line (towards the bright
    side) is sampled every ``step`` px; the end moves to where it first falls
    below half the segment's mean strength (the end of a blurred step edge),
    by linear interpolation, at most ``max_px``. Never shortens a segment.
    """
    if len(ends) == 0:
        return ends
    d = ends[:, 1] - ends[:, 0]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    k = np.arange(1, int(round(max_px / step)) + 1) * step  # (K,)
    G, K = len(ends), len(k)
    half = 0.5 * strength[:, None, None]  # (G, 1, 1)
    # Both ends at once: end e moves by sgn[e] * k along d, (G, 2, K, 2).
    sgn = np.array([-1.0, 1.0])
    pts = ends[:, :, None, :] + (sgn[:, None] * k)[None, :, :, None] * d[:, None, None]
    flat = pts.reshape(-1, 2)
    if camera is not None and camera.has_distortion:
        flat = camera.distort_pixels(flat)
    bx, by = bilinear_many((gx, gy), flat)
    D = (
        bx.reshape(G, 2, K) * normal[:, 0, None, None]
        + by.reshape(G, 2, K) * normal[:, 1, None, None]
    )
    below = half > D
    # Index of the first sample below half strength (K: none).
    first = np.where(below.any(axis=2), np.argmax(below, axis=2), K)  # (G, 2)
    prev = np.take_along_axis(D, np.maximum(first - 1, 0)[..., None], axis=2)[..., 0]
    prev = np.where(first > 0, prev, half[..., 0] * 2)
    cur = np.take_along_axis(D, np.minimum(first, K - 1)[..., None], axis=2)[..., 0]
    # Linear interpolation of the half-strength crossing between samples.
    frac = np.clip((prev - half[..., 0]) / np.maximum(prev - cur, 1e-9), 0.0, 1.0)
    dist = np.where(first >= K, max_px, np.maximum(first - 1 + frac, 0.0) * step)
    dist = np.where(first == 0, frac * step, dist)
    return ends + (sgn * dist)[..., None] * d[:, None, :]


def _extents_on(xy, group, lines, G):
    return segment_extents(xy, group, lines, G)


#: merge candidates per chain: its neighbours in the order of the pencil angle.
_MERGE_WINDOW = 6


def _merge_pencil(
    Sc,
    ends,
    sign,
    strength,
    count,
    lines,
    vn,
    max_dist,
    max_gap,
):
    """Merge segments on (nearly) the same line through the VP, same polarity.

    Segments are ordered by their line's angle in the pencil; neighbours whose
    endpoints lie within ``max_dist`` of each other's line and whose gap along
    the line is at most ``max_gap`` are merged (transitively), and the merged
    groups refitted through the VP from the summed scatter matrices.
    Candidates are the
    ``_MERGE_WINDOW`` neighbours in pencil order (many chains share nearly
    one line through the VP; 20 instead of 6 changed nothing measurable).
    Across polarity (the background behind a corner changing from brighter
    to darker than the wall) nothing is merged: measured, that gained 1-2 %
    recall for 4 % precision.
    """
    n = len(Sc)
    if n < 2:
        return Sc, ends, sign, strength, count, lines
    U = tangent_basis(vn)
    x = lines @ U  # (n, 2) pencil coordinates of each line
    ang = np.arctan2(x[:, 1], x[:, 0]) % np.pi
    order = np.argsort(ang)
    # All candidate pairs at once: each segment with its ``window`` successors
    # in pencil order (with wrap-around).
    nw = min(_MERGE_WINDOW, n - 1)
    i = np.tile(order, nw)
    j = np.concatenate([np.roll(order, -w) for w in range(1, nw + 1)])
    ok = (sign[i] >= 0) == (sign[j] >= 0)
    li, lj, ei, ej = lines[i], lines[j], ends[i], ends[j]
    # Distances of j's endpoints to i's line and vice versa, and the gap
    # between the two along i's line.
    dj = np.abs(
        ej[:, :, 0] * li[:, 0, None] + ej[:, :, 1] * li[:, 1, None] + li[:, 2, None]
    )
    di = np.abs(
        ei[:, :, 0] * lj[:, 0, None] + ei[:, :, 1] * lj[:, 1, None] + lj[:, 2, None]
    )
    si = -ei[:, :, 0] * li[:, 1, None] + ei[:, :, 1] * li[:, 0, None]
    sj = -ej[:, :, 0] * li[:, 1, None] + ej[:, :, 1] * li[:, 0, None]
    gap = np.maximum(sj.min(1) - si.max(1), si.min(1) - sj.max(1))
    ok &= (np.maximum(di.max(1), dj.max(1)) <= max_dist) & (gap <= max_gap)
    pi, pj = i[ok], j[ok]
    G, grp = connected_pairs(n, pi, pj)
    if n == G:
        return Sc, ends, sign, strength, count, lines
    S2 = np.zeros((G, 3, 3))
    np.add.at(S2, grp, Sc)
    _, lines2 = pencil_fit(S2, vn)
    pts = ends.reshape(-1, 2)
    ends2 = _extents_on(pts, np.repeat(grp, 2), lines2, G)
    count2 = np.bincount(grp, weights=count, minlength=G)
    sign2 = np.bincount(grp, weights=sign, minlength=G)
    strength2 = np.bincount(grp, weights=strength * count, minlength=G) / count2
    return S2, ends2, sign2, strength2, count2, lines2


def vertical_segments(
    image_gray: np.ndarray,
    vp: np.ndarray,
    options: SecondPassOptions | None = None,
    camera: Camera | None = None,
) -> Segments:
    """Segments through a known vanishing point (the paper's second pass).

    1. The derivative D perpendicular to the line from ``vp`` through each
       pixel (pixels whose gradient points elsewhere are suppressed).
    2. Non-maximum suppression and hysteresis on D (:func:`lines.edge_points`).
    3. Each chain of edge points is fitted by the line through ``vp`` that
       minimises the squared point distances (ML under the constraint), cut at
       gaps, and pieces of one line are merged.

    Parameters
    ----------
    image_gray : (H, W) uint8 array, full resolution.
    vp : (3,) homogeneous VP, COLMAP pixels of the distortion-free image.
    options : SecondPassOptions or None.
    camera : Camera or None; with distortion the edge points are undistorted
        before fitting.

    Returns
    -------
    Segments
        Through ``vp`` exactly, in undistorted COLMAP pixels; normals point to
        the brighter side; strength is the mean |D|, grey levels/px.
    """
    options = options or SecondPassOptions()
    H, W = np.asarray(image_gray).shape[:2]
    T, _ = normaliser(W, H)
    return run_second_pass(
        image_gray, np.asarray(vp, float), options, camera, T
    ).segments
