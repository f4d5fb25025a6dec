"""The whole upright block onto the map at once from corner-to-ray pairs
(issue 27 item 3 for level cameras; MetropoGIS 3.3-3.4).

Stage 2 registers one oblique image from its own segments; a street image
shows two or three building corners among a few hundred window and door
edges, and its camera is not above the scene, so it registers none. Here
all images are registered TOGETHER: in the upright model a vertical segment
is a vertical plane through its camera centre, i.e. a 2D ray ``(o, d)``
from the camera's xy (:class:`~.automatic.Rays`), and the map corner ``c``
it images, mapped into the model's xy by ``x = [[a, -b], [b, a]] c + t``,
lies on it (``cross(d, x - o) = 0``, linear in ``(a, b, t)``; its value
the corner's distance from the ray, :func:`pair_inliers`).

1. Prior (:func:`prior_similarity`): the priors' camera positions give the
   similarity and its uncertainty; the heading is combined with the one the
   priors' ROTATIONS give (:func:`heading_from_rotations`: a phone's
   compass beats the GPS positions along a 70 m line).
2. Candidates (:func:`candidate_pairs`): the corners each camera can see at
   its position under that similarity (:func:`corners_seen`: the frustum
   and facing test of :func:`~obliq_colmap.cadastre.visible_corners` and a
   line of sight in plan, :mod:`.sight`), paired with every segment whose
   ray passes within the angular window the prior's uncertainty allows.
3. Hypotheses (:func:`best_similarities`): per corner, the few places in the
   model where most of its candidate rays from two images meet
   (:func:`corner_points`); every two places of two corners give a
   similarity in closed form (:func:`solve_two_points`), all scored in
   batches (:func:`count_inliers`): per (image, corner) the LENGTH of the
   longest segment within the threshold (the map's noise in metres or the
   segments' in angle). Counting pairs instead let a wrong scale win on
   street seed 1: a facade of window edges puts SOME short segment near
   every corner under almost any similarity; the edge at a building's
   corner runs the facade's height.
4. Guided matching (:func:`nearest_pairs`): every ray against every corner
   in sight under the winner, per (image, corner) the longest segment
   within the threshold, then the 4-DOF refit (:func:`~.automatic.fit_block`,
   stage 2's angular residuals with a Cauchy loss), twice.

The first version drew random minimal samples of four candidate pairs
(two corners, each with two rays from different images meeting near it,
solved as four linear rows): street seed 1 had 1.3 million such ray pairs
of 20 corners (the positions' heading window, 2.3 deg sd, before the
rotations'); the places per corner are few enough (~100) to try every two.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from obliq_colmap.cadastre import Cadastre, visible_corners
from obliq_colmap.geometry import Camera, Pose

from .automatic import Rays, rays_in_map
from .sight import corners_in_sight

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class BlockLinesOptions:
    """The block placement from all images' corner-to-ray pairs."""

    #: candidate windows span this many sds of the prior similarity's error
    window_sigmas: float = 3.0
    #: an image's prior position error (m, per axis) when the priors' own
    #: scatter about the similarity is smaller (a phone's GPS: ~5 m)
    min_prior_position_sigma_m: float = 1.0
    #: corners farther than this from the camera are not candidates (m)
    max_range_m: float = 80.0
    min_range_m: float = 2.0
    #: the map's vertex noise (m, sd): the map rows' sd at the pairs' range
    map_noise_m: float = 0.15
    #: inlier: the corner within this distance of the ray (m; 2 sd of a map
    #: with 0.15 m vertex noise, stage 2's ``inlier_threshold_m``) ...
    inlier_threshold_m: float = 0.3
    #: ... or within this angle (deg; the segment's own noise), the larger
    inlier_threshold_deg: float = 0.15
    #: two rays of one corner meet within this many sds of the corner's
    #: position under the prior
    place_gate_sigmas: float = 3.0
    #: the places where a corner's rays meet are counted on cells of this
    #: size (map metres) ...
    cluster_cell_m: float = 0.3
    #: ... and the most supported of them kept, per corner
    points_per_corner: int = 8
    #: two corners of a hypothesis at least this far apart (m; adjacent
    #: buildings' footprints share their corner points)
    min_corner_spacing_m: float = 1.0
    #: the best hypotheses that move some corner more than ``start_spacing_m``
    #: from each other are each refined by guided matching, and the best
    #: refined one kept (street seed 3: the best raw hypothesis refined to a
    #: 0.9 deg / 2 % wrong fit, rms 0.47 deg, where the truth's score is higher)
    num_starts: int = 8
    start_spacing_m: float = 0.5
    batch_size: int = 250
    guided_rounds: int = 3
    #: the refits weigh each pair by its own angular sd (:func:`pair_sd_deg`,
    #: also the scale of its Cauchy loss): the map's noise at its range (0.15 m
    #: is 0.9 deg at 10 m, 0.2 deg at 40 m) and this noise of a segment (deg)
    segment_sigma_deg: float = 0.05
    #: fewer pairs after guided matching than this is a failure
    min_inliers: int = 12


@dataclass
class PriorSimilarity:
    """The priors' similarity ``map_xy = s R(theta) model_xy + t`` and its
    uncertainty: sds of the scale (relative), the heading (rad) and the
    model's centroid ``ref`` (2,) mapped (m, per axis)."""

    scale: float
    theta: float
    translation: np.ndarray  # (2,)
    ref: np.ndarray
    sd_scale: float
    sd_theta: float
    sd_ref_m: float

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) model points in the map frame."""
        c, s = np.cos(self.theta), np.sin(self.theta)
        R = np.array([[c, -s], [s, c]])
        return self.scale * np.asarray(xy) @ R.T + self.translation

    def position_sd(self, xy: np.ndarray) -> np.ndarray:
        """(N,) sd (m) of (N, 2) model points mapped (the three errors
        independent: at the centroid, along and across the arm from it)."""
        rho = self.scale * np.linalg.norm(np.asarray(xy) - self.ref, axis=1)
        return np.sqrt(
            self.sd_ref_m**2 + (rho * self.sd_scale) ** 2 + (rho * self.sd_theta) ** 2
        )


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def heading_from_rotations(
    R_model: np.ndarray, R_prior: np.ndarray
) -> tuple[float, float]:
    """The heading (rad) of the block from each image's prior rotation
    against its upright model rotation ((N, 3, 3) cam_from_world each:
    ``R_model = R_prior R_z(theta)``), the median, and its sd (1.4826 x
    the median absolute deviation over sqrt(N)). A phone's compass (5 deg
    per image) gives 0.7 deg over a 36-image street where the GPS
    positions along a 70 m line give 2 deg (and were 7 deg off on seed 2)."""
    M = np.transpose(R_prior, (0, 2, 1)) @ R_model
    th = np.arctan2(M[:, 1, 0], M[:, 0, 0])
    ref = np.arctan2(np.sin(th).sum(), np.cos(th).sum())
    d = _wrap(th - ref)
    med = float(np.median(d))
    sd = 1.4826 * float(np.median(np.abs(d - med))) / np.sqrt(len(d))
    return float(_wrap(ref + med)), max(sd, 1e-4)


def prior_similarity(
    model_xy: np.ndarray,
    prior_xy: np.ndarray,
    min_sigma_m: float,
    rotation_heading: tuple[float, float] | None = None,
) -> PriorSimilarity:
    """The similarity of (N, 2) model centres onto the priors' (N, 2) by
    least squares, its heading combined with ``rotation_heading`` ((theta,
    sd) from :func:`heading_from_rotations`) by their inverse variances,
    the sd widened by the Birge ratio where the two disagree; then scale
    and translation refitted at that heading. The centres' sd is their
    scatter (1.4826 x the median absolute residual, at least
    ``min_sigma_m``)."""
    ref = model_xy.mean(0)
    x, y = (model_xy - ref).T
    n = len(x)
    A = np.zeros((2 * n, 4))
    A[0::2] = np.c_[x, -y, np.ones(n), np.zeros(n)]
    A[1::2] = np.c_[y, x, np.zeros(n), np.ones(n)]
    p = np.linalg.lstsq(A, prior_xy.ravel(), rcond=None)[0]
    r = A @ p - prior_xy.ravel()
    sigma = max(1.4826 * float(np.median(np.abs(r))), min_sigma_m)
    cov = sigma**2 * np.linalg.inv(A.T @ A)
    scale, theta = float(np.hypot(p[0], p[1])), float(np.arctan2(p[1], p[0]))
    g = np.array([-p[1], p[0]]) / scale**2
    sd_theta = float(np.sqrt(g @ cov[:2, :2] @ g))
    if rotation_heading is not None:
        th_r, sd_r = rotation_heading
        w = np.array([1 / sd_theta**2, 1 / sd_r**2])
        d = float(_wrap(th_r - theta))
        birge = max(1.0, abs(d) / np.hypot(sd_theta, sd_r))
        theta = float(_wrap(theta + w[1] * d / w.sum()))
        sd_theta = birge / float(np.sqrt(w.sum()))
    # scale and translation at that heading: linear in (s, t_x, t_y)
    c, s = np.cos(theta), np.sin(theta)
    rot = (model_xy - ref) @ np.array([[c, s], [-s, c]])  # R(theta) (m - ref)
    B = np.zeros((2 * n, 3))
    B[0::2] = np.c_[rot[:, 0], np.ones(n), np.zeros(n)]
    B[1::2] = np.c_[rot[:, 1], np.zeros(n), np.ones(n)]
    q = np.linalg.lstsq(B, prior_xy.ravel(), rcond=None)[0]
    cq = sigma**2 * np.linalg.inv(B.T @ B)
    scale = float(q[0])
    t = q[1:] - scale * np.array([[c, -s], [s, c]]) @ ref
    return PriorSimilarity(
        scale,
        theta,
        t,
        ref,
        float(np.sqrt(cq[0, 0])) / scale,
        sd_theta,
        float(np.sqrt(max(cq[1, 1], cq[2, 2]))),
    )


@dataclass
class CandidatePairs:
    """(P,) candidate (ray, corner) pairs, sorted by ray; ``window`` (P,)
    their prior angular sd (rad)."""

    ray: np.ndarray
    corner: np.ndarray
    window: np.ndarray

    def __len__(self) -> int:
        return len(self.ray)


def _bearing_offset(
    origin: np.ndarray, bearing: np.ndarray, corner_xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) signed angle (rad) from each bearing (N, 2) to its corner (N, 2)
    seen from its origin (N, 2), and (N,) the range along the bearing."""
    v = corner_xy - origin
    along = np.sum(bearing * v, axis=1)
    cross = bearing[:, 0] * v[:, 1] - bearing[:, 1] * v[:, 0]
    return np.arctan2(cross, along), along


def _ray_corner_grid(rays: Rays, seen: list[np.ndarray]):
    """Per image with rays and corners in sight (``seen``, per image): (M,)
    ray and (M,) corner indices of every ray of the image against every
    corner it sees."""
    for i, corners in enumerate(seen):
        r_idx = np.flatnonzero(rays.image == i)
        if len(corners) and len(r_idx):
            yield np.repeat(r_idx, len(corners)), np.tile(corners, len(r_idx))


def corners_seen(
    cad: Cadastre,
    camera: Camera,
    pose: Pose,
    max_range_m: float,
    margin_px: float,
) -> np.ndarray:
    """(K,) corners a level camera at ``pose`` (map frame) can see: the
    frustum (the corner's vertical from 30 m below the camera to 30 m above),
    a facing wall, within range, in sight in plan; one of the corners that
    stand at one point (adjacent buildings' footprints share them)."""
    idx = visible_corners(
        cad, camera, pose, pose.center[2] - 30.0, (0.0, 60.0), margin_px,
        use_building_heights=False,
    )  # fmt: skip
    xy = pose.center[:2]
    idx = idx[np.linalg.norm(cad.corner_xy[idx] - xy, axis=1) <= max_range_m]
    idx = idx[corners_in_sight(cad, xy, idx)]
    _, first = np.unique(np.round(cad.corner_xy[idx], 2), axis=0, return_index=True)
    return idx[np.sort(first)]


def candidate_pairs(
    rays: Rays,
    seen: list[np.ndarray],
    cad: Cadastre,
    prior: PriorSimilarity,
    options: BlockLinesOptions,
) -> CandidatePairs:
    """Every ray against the corners its image sees (``seen``, per image)
    whose bearing under the prior is within ``window_sigmas`` of the ray's."""
    origin, bearing = rays_in_map(rays, prior.scale, prior.theta, prior.translation)
    pos_sd = prior.position_sd(rays.origin)
    out_r, out_c, out_w = [], [], []
    for rr, cc in _ray_corner_grid(rays, seen):
        ang, rng = _bearing_offset(origin[rr], bearing[rr], cad.corner_xy[cc])
        sd = np.hypot(pos_sd[rr] / np.maximum(rng, 1e-3), prior.sd_theta)
        ok = (rng >= options.min_range_m) & (np.abs(ang) <= options.window_sigmas * sd)
        out_r.append(rr[ok])
        out_c.append(cc[ok])
        out_w.append(sd[ok])
    if not out_r:
        return CandidatePairs(np.zeros(0, int), np.zeros(0, int), np.zeros(0))
    ray, corner, window = (np.concatenate(v) for v in (out_r, out_c, out_w))
    order = np.argsort(ray, kind="stable")
    return CandidatePairs(ray[order], corner[order], window[order])


def map_to_model(p: np.ndarray, corner_xy: np.ndarray) -> np.ndarray:
    """(..., N, 2) corners mapped by (..., 4) p into the model's xy."""
    a, b = p[..., 0, None], p[..., 1, None]
    x = a * corner_xy[..., 0] - b * corner_xy[..., 1] + p[..., 2, None]
    y = b * corner_xy[..., 0] + a * corner_xy[..., 1] + p[..., 3, None]
    return np.stack([x, y], axis=-1)


def pair_inliers(
    p: np.ndarray,
    origin: np.ndarray,
    bearing: np.ndarray,
    corner_xy: np.ndarray,
    options: BlockLinesOptions,
) -> np.ndarray:
    """(H, P) bool: pair k is an inlier of hypothesis h (p (H, 4); rays and
    corners (P, 2), frames centred as in :func:`best_similarities`): the mapped
    corner in front of the ray and within the threshold of it, in map metres
    (the model's distance divided by the hypothesis's scale) or in angle."""
    x = map_to_model(p, corner_xy)  # (H, P, 2)
    v = x - origin
    along = np.sum(bearing * v, axis=-1)
    perp = np.abs(bearing[..., 0] * v[..., 1] - bearing[..., 1] * v[..., 0])
    scale = np.hypot(p[:, 0], p[:, 1])[:, None]  # model units per map metre
    thr = np.maximum(
        options.inlier_threshold_m * scale,
        np.tan(np.radians(options.inlier_threshold_deg)) * along,
    )
    return (along > options.min_range_m * scale) & (perp <= thr)


def count_inliers(
    p: np.ndarray,
    rays: Rays,
    cand: CandidatePairs,
    corner_xy: np.ndarray,
    options: BlockLinesOptions,
) -> np.ndarray:
    """(H,) score per hypothesis: over every (image, corner), the length
    (px) of its longest inlier segment. A street's facades are dense with
    window edges, so a corner finds SOME short segment near its ray under
    almost any similarity; the vertical edge at a building's corner runs
    the facade's height (the true pairs' segments: median 41 px, the tenth
    longest 451 px, among all segments' 39 / 59 px on street seed 1)."""
    group = rays.image[cand.ray].astype(np.int64) * len(corner_xy) + cand.corner
    order = np.argsort(group, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(group[order]) != 0])
    ray, corner = cand.ray[order], cand.corner[order]
    o, b, c = rays.origin[ray], rays.bearing[ray], corner_xy[corner]
    w = rays.length[ray]
    out = np.zeros(len(p))
    if len(starts) == 0:
        return out
    for lo in range(0, len(p), options.batch_size):
        inl = pair_inliers(p[lo : lo + options.batch_size], o, b, c, options)
        out[lo : lo + options.batch_size] = np.maximum.reduceat(
            inl * w, starts, axis=1
        ).sum(axis=1)
    return out


def _ray_pair_points(
    rays: Rays, first: np.ndarray, second: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) where ray ``first`` meets ray ``second`` (model xy) and (N,)
    bool: they meet in front of both cameras, not near parallel."""
    o1, d1 = rays.origin[first], rays.bearing[first]
    o2, d2 = rays.origin[second], rays.bearing[second]
    den = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    w = o2 - o1
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (w[:, 0] * d2[:, 1] - w[:, 1] * d2[:, 0]) / den
        t2 = (w[:, 0] * d1[:, 1] - w[:, 1] * d1[:, 0]) / den
    ok = (np.abs(den) > np.sin(np.radians(2.0))) & (t1 > 0) & (t2 > 0)
    return o1 + t1[:, None] * d1, ok


@dataclass
class CornerPoints:
    """(H,) places in the model's xy where a map corner may stand: the
    clusters of the points where its candidate rays from two images meet.
    corner (H,), xy (H, 2) model, support (H,) ray pairs meeting there."""

    corner: np.ndarray
    xy: np.ndarray
    support: np.ndarray

    def __len__(self) -> int:
        return len(self.corner)


def corner_points(
    rays: Rays,
    cand: CandidatePairs,
    cad: Cadastre,
    prior: PriorSimilarity,
    options: BlockLinesOptions,
) -> CornerPoints:
    """Per map corner, the ``points_per_corner`` model places where most of
    its candidate rays from different images meet (near where the prior
    puts the corner): the true vertical edge is seen from many images, each
    window edge near it too, so these are few places, and the block's
    similarity is the one that puts many corners on theirs
    (:func:`best_similarities`). The meeting points are counted on a grid of
    ``cluster_cell_m`` (map metres, in model units at the prior's scale)."""
    cell = options.cluster_cell_m / prior.scale
    corner_out, xy_out, support_out = [], [], []
    order = np.argsort(cand.corner, kind="stable")
    bounds = np.flatnonzero(np.diff(cand.corner[order])) + 1
    for group in np.split(order, bounds):
        if len(group) < 2:
            continue
        i, j = np.triu_indices(len(group), 1)
        ri, rj = cand.ray[group[i]], cand.ray[group[j]]
        diff = rays.image[ri] != rays.image[rj]
        ri, rj = ri[diff], rj[diff]
        X, ok = _ray_pair_points(rays, ri, rj)
        corner = cand.corner[group[0]]
        off = np.linalg.norm(prior.apply(X) - cad.corner_xy[corner], axis=1)
        gate = options.place_gate_sigmas * prior.position_sd(X)
        ok &= off <= gate + options.inlier_threshold_m
        # two long segments meeting count most (see count_inliers)
        weight = np.minimum(rays.length[ri], rays.length[rj])[ok]
        X = X[ok]
        if len(X) == 0:
            continue
        cells, inverse, counts = np.unique(
            np.floor(X / cell).astype(np.int64),
            axis=0,
            return_inverse=True,
            return_counts=True,
        )
        inverse = inverse.ravel()
        support = np.bincount(inverse, weight, minlength=len(cells))
        top = np.argsort(-support, kind="stable")[: options.points_per_corner]
        sums = np.zeros((len(cells), 2))
        np.add.at(sums, inverse, X)
        corner_out.append(np.full(len(top), corner))
        xy_out.append(sums[top] / counts[top, None])
        support_out.append(support[top])
    if not corner_out:
        return CornerPoints(np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int))
    return CornerPoints(
        np.concatenate(corner_out), np.concatenate(xy_out), np.concatenate(support_out)
    )


def solve_two_points(model_xy: np.ndarray, corner_xy: np.ndarray) -> np.ndarray:
    """(B, 4) p with ``model = [[a, -b], [b, a]] corner + t`` exactly
    through B samples of two points ((B, 2, 2) each, centred frames)."""
    cx, cy = corner_xy[..., 0], corner_xy[..., 1]
    one, zero = np.ones_like(cx), np.zeros_like(cx)
    A = np.concatenate(
        [
            np.stack([cx, -cy, one, zero], axis=-1),
            np.stack([cy, cx, zero, one], axis=-1),
        ],
        axis=1,
    )  # (B, 4, 4)
    rhs = np.concatenate([model_xy[..., 0], model_xy[..., 1]], axis=1)
    return np.linalg.solve(A, rhs[..., None])[..., 0]


@dataclass
class LinesFit:
    """A hypothesis: ``p`` (4,) map xy -> model xy about the centroids
    (``map_ref`` (2,), ``model_ref`` (2,)), its score (:func:`count_inliers`,
    px) and how many hypotheses were scored."""

    p: np.ndarray
    map_ref: np.ndarray
    model_ref: np.ndarray
    score: float
    num_hypotheses: int

    def model_to_map(self) -> tuple[float, float, np.ndarray]:
        """(scale, theta, (2,) t) of ``map_xy = scale R(theta) model_xy + t``."""
        a, b = self.p[0], self.p[1]
        s2 = a * a + b * b
        Rinv = np.array([[a, b], [-b, a]]) / s2  # inverse of [[a, -b], [b, a]]
        scale, theta = 1.0 / np.sqrt(s2), float(np.arctan2(-b, a))
        # model - model_ref = A (map - map_ref) + p_t
        t = self.map_ref - Rinv @ (self.p[2:] + self.model_ref)
        return float(scale), theta, t


def best_similarities(
    rays: Rays,
    cand: CandidatePairs,
    cad: Cadastre,
    prior: PriorSimilarity,
    options: BlockLinesOptions,
) -> list[LinesFit]:
    """The best-scoring similarities (:func:`distinct_best`) among those
    through every two places of two different corners (:func:`corner_points`;
    all of them: a few hundred places give a few ten thousand hypotheses,
    scored in batches). Empty when there are not two corners with a place."""
    pts = corner_points(rays, cand, cad, prior, options)
    where = cad.corner_xy[pts.corner]
    i, j = np.triu_indices(len(pts), 1)
    apart = np.linalg.norm(where[i] - where[j], axis=1) > options.min_corner_spacing_m
    i, j = i[apart], j[apart]
    logger.info(
        "block lines: %d candidate pairs, %d places of %d corners, %d hypotheses",
        len(cand), len(pts), len(np.unique(pts.corner)), len(i),
    )  # fmt: skip
    if len(i) == 0:
        return []
    # centred frames: the rows' columns are then of one size
    model_ref = rays.origin.mean(0)
    map_ref = where.mean(0)
    centred = Rays(rays.origin - model_ref, rays.bearing, rays.image, rays.length)
    corner_c = cad.corner_xy - map_ref
    p = solve_two_points(
        np.stack([pts.xy[i], pts.xy[j]], axis=1) - model_ref,
        np.stack([where[i], where[j]], axis=1) - map_ref,
    )
    scores = count_inliers(p, centred, cand, corner_c, options)
    keep = distinct_best(p, scores, corner_c[np.unique(cand.corner)], options)
    return [LinesFit(p[k], map_ref, model_ref, float(scores[k]), len(p)) for k in keep]


def distinct_best(
    p: np.ndarray, scores: np.ndarray, probes: np.ndarray, options: BlockLinesOptions
) -> list[int]:
    """Indices of the ``num_starts`` best hypotheses (p (H, 4), scores (H,))
    that differ from each other: each moves some of the (K, 2) ``probes``
    (the candidate corners, centred map xy) more than ``start_spacing_m``
    from where every better one puts it."""
    order = np.argsort(-scores, kind="stable")[: 50 * options.num_starts]
    # model xy of the probes under each hypothesis, in map metres
    x = (
        map_to_model(p[order], probes)
        / np.hypot(p[order, 0], p[order, 1])[:, None, None]
    )
    kept: list[int] = []
    for k in range(len(order)):
        if kept:
            moved = np.linalg.norm(x[kept] - x[k], axis=2).max(axis=1)
            if moved.min() <= options.start_spacing_m:
                continue
        kept.append(k)
        if len(kept) == options.num_starts:
            break
    return [int(order[k]) for k in kept]


def pair_sd_deg(
    rays: Rays,
    cad: Cadastre,
    pairs: np.ndarray,
    scale: float,
    theta: float,
    t: np.ndarray,
    options: BlockLinesOptions,
) -> np.ndarray:
    """(P,) each pair's angular sd (deg) under ``map = scale R(theta) model +
    t``: the map's vertex noise at the corner's range, and the segment's
    direction noise (``segment_sigma_deg``)."""
    origin = rays_in_map(rays, scale, theta, t)[0][pairs[:, 0]]
    rng = np.linalg.norm(cad.corner_xy[pairs[:, 1]] - origin, axis=1)
    return np.hypot(
        np.degrees(options.map_noise_m / np.maximum(rng, 1e-3)),
        options.segment_sigma_deg,
    )


def nearest_pairs(
    rays: Rays,
    seen: list[np.ndarray],
    cad: Cadastre,
    scale: float,
    theta: float,
    t: np.ndarray,
    options: BlockLinesOptions,
) -> np.ndarray:
    """(K, 2) (ray, corner) under ``map = scale R(theta) model + t``: each
    ray's nearest corner in sight of its image (``seen``) within the inlier
    threshold, then per (image, corner) only the longest such ray (the
    others are window edges near it by chance; :func:`count_inliers`)."""
    origin, bearing = rays_in_map(rays, scale, theta, t)
    out = []
    for rr, cc in _ray_corner_grid(rays, seen):
        ang, rng = _bearing_offset(origin[rr], bearing[rr], cad.corner_xy[cc])
        perp = np.abs(np.sin(ang)) * np.hypot(*(cad.corner_xy[cc] - origin[rr]).T)
        thr = np.maximum(
            options.inlier_threshold_m,
            np.tan(np.radians(options.inlier_threshold_deg)) * rng,
        )
        ok = (rng >= options.min_range_m) & (np.abs(ang) < np.pi / 2) & (perp <= thr)
        if not ok.any():
            continue
        rr, cc, perp = rr[ok], cc[ok], perp[ok]
        order = np.lexsort((perp, rr))
        first = np.r_[True, rr[order][1:] != rr[order][:-1]]
        rr, cc = rr[order][first], cc[order][first]
        order = np.lexsort((-rays.length[rr], cc))
        first = np.r_[True, cc[order][1:] != cc[order][:-1]]
        out.append(np.c_[rr[order][first], cc[order][first]])
    return np.concatenate(out) if out else np.zeros((0, 2), int)
