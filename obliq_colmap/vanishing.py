"""The vertical vanishing point of an image and the segments through it.

Stage 1b of the pipeline (Habbecke & Kobbelt, section 2.1):

1. Line segments (:mod:`obliq_colmap.lines`), at reduced resolution for big
   images, with lens distortion removed from the endpoints.
2. RANSAC over segment pairs: the intersection of two segments' lines is a
   hypothesis, kept only where the prior (:class:`VPPrior`) allows it, and
   scored by the segments whose line through their midpoint and the
   hypothesis passes near their endpoints (length-weighted MSAC). All
   hypotheses of a batch are evaluated at once.
3. Maximum-likelihood refinement over the inliers: the VP minimising the sum
   of squared endpoint distances to the best line through the VP of each
   segment (the per-segment line is eliminated in closed form), with its
   covariance.
4. Competing VPs: the other strong pencils (street and facade directions)
   are found by RANSAC too, and every segment belongs to the VP it fits best
   (alternating with the ML refinement). In oblique aerial images a street
   seen along the camera's azimuth passes through the nadir point, i.e.
   through the vertical VP: its curbs, markings and parked cars look like
   verticals inside a strip and pulled the VP along it by up to 5 deg. When a
   competitor allowed by the prior is more significant than the vertical (a
   street's many short segments can win the pair-RANSAC), the two swap roles.
   Steps 2-4 run from several starts (``VanishingOptions.start_cones``):
   with an INS prior each in the prior's cone scaled, with the others each
   with its own RANSAC draws; when their VPs disagree, the second pass (5.)
   runs for each and the longest total of vertical segments decides.
5. Second pass (:func:`vertical_segments`): the derivative perpendicular to
   the line from the VP through each pixel, non-maximum suppression and
   hysteresis on it, chains fitted as lines constrained through the VP
   (points within ``end_trim_px`` of a chain's ends, bent by the junction
   with roof or ground, left out of the fit), ends moved out to where the
   contrast halves (the end of the blurred edge). The VP is then refined once
   more on these full-resolution edge points, on the chains within a robust
   noise bound that fit it better than any competing VP.

Everything is homogeneous (a VP at infinity, ``w = 0``, is legal); internally
pixel coordinates are centred and scaled (``T``) for conditioning. The
vertical direction ``n = +-normalise(K^-1 v)`` is oriented down the world:
``n . d_prior > 0`` with the INS prior's predicted down direction, otherwise
``n_y > 0`` (DESIGN.md, conventions).

Significance: the best hypothesis is judged a contrario: the number of
segments consistent with it is compared with the number expected if the
segment orientations were random (Poisson tail, times the number of
hypotheses RANSAC may test), in three length classes (the best counts, the
number of tests tripled). An image without vertical structure (water,
fields, sky, noise) gives a "no_vp" result instead of a confident wrong VP.

References
----------
M. Habbecke, L. Kobbelt, "Automatic registration of oblique aerial images with
cadastral maps", ECCV workshops 2010, section 2.1.
A. Klaus et al., "MetropoGIS: a semi-automatic city documentation system",
PCV 2002, section 3.1.
A. Almansa, A. Desolneux, S. Vamech, "Vanishing point detection without any a
priori information", PAMI 25, 2003 (the a contrario significance test).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.special import pdtrc

from obliq_colmap.geometry import Camera
from obliq_colmap.lines import (
    EdgePoints,
    LineOptions,
    Segments,
    as_gray_u8,
    bilinear_many,
    connected_pairs,
    detect_segments,
    edge_points,
    gradients,
    scatter_matrices,
    segment_extents,
    split_at_gaps,
)

logger = logging.getLogger(__name__)

PRIOR_KINDS = ("none", "aerial", "ins")
STATUSES = ("ok", "low_confidence", "no_vp")


# --------------------------------------------------------------------------
# Prior, options, result
# --------------------------------------------------------------------------


@dataclass(kw_only=True, frozen=True)
class VPPrior:
    """Where the vertical vanishing point may lie.

    Attributes
    ----------
    kind : str
        "none": anywhere within ``max_angle_deg`` of the image's vertical axis,
        above or below the image, at least ``min_distance_h`` image heights from
        the centre. "aerial": the paper's prior, y >= ``min_y_h`` image heights
        (at least one image height below the image for the default 2), within
        ``max_angle_deg`` of the vertical axis (which excludes horizontal
        directions at infinity that satisfy y >= 2h only in the limit). "ins":
        the vertical direction within ``cone_deg`` of ``down_cam`` (needs
        intrinsics); covers near-nadir images whose VP is inside the frame.
    down_cam : (3,) array or None
        ins: predicted direction of the world's down axis in the camera frame,
        ``R_prior @ (0, 0, -1)``.
    cone_deg : float
        ins: half-angle of the cone of allowed vertical directions, degrees.
    max_angle_deg : float
        none/aerial: largest angle between the image's y axis and the direction
        from the image centre to the VP, degrees.
    min_distance_h : float
        none: least |y| distance of the VP from the image centre, image heights
        (0.5: outside the image's vertical extent).
    min_y_h : float
        aerial: least y coordinate of the VP, image heights.
    """

    kind: str = "none"
    down_cam: np.ndarray | None = None
    cone_deg: float = 5.0
    max_angle_deg: float = 30.0
    min_distance_h: float = 0.5
    min_y_h: float = 2.0

    def __post_init__(self) -> None:
        if self.kind not in PRIOR_KINDS:
            raise ValueError(
                f"unknown prior kind {self.kind!r}; allowed: {', '.join(PRIOR_KINDS)}"
            )
        if self.kind == "ins":
            if self.down_cam is None:
                raise ValueError("an 'ins' prior needs down_cam")
            d = np.asarray(self.down_cam, float).reshape(3)
            object.__setattr__(self, "down_cam", d / np.linalg.norm(d))

    @classmethod
    def none(cls, max_angle_deg: float = 30.0) -> VPPrior:
        """No prior knowledge: within +-``max_angle_deg`` of the vertical axis."""
        return cls(kind="none", max_angle_deg=max_angle_deg)

    @classmethod
    def aerial(cls, min_y_h: float = 2.0, max_angle_deg: float = 45.0) -> VPPrior:
        """The paper's oblique-aerial prior: VP far below the image."""
        return cls(kind="aerial", min_y_h=min_y_h, max_angle_deg=max_angle_deg)

    @classmethod
    def from_rotation(cls, cam_from_world_rotation: np.ndarray, cone_deg: float = 5.0):
        """INS prior from a rough ``cam_from_world`` rotation (3, 3)."""
        R = np.asarray(cam_from_world_rotation, float).reshape(3, 3)
        return cls(
            kind="ins", down_cam=R @ np.array([0.0, 0.0, -1.0]), cone_deg=cone_deg
        )


@dataclass(kw_only=True)
class SecondPassOptions:
    """Options of :func:`vertical_segments` (pixels of the full image)."""

    #: Gaussian smoothing before the derivative, pixels.
    sigma_px: float = 1.0
    #: hysteresis thresholds on the directional derivative, grey levels/px.
    low: float = 2.0
    high: float = 6.0
    #: largest angle between the gradient and the direction perpendicular to
    #: the line towards the VP, degrees.
    max_gradient_angle_deg: float = 20.0
    #: edge points farther than this from their chain's line are dropped, px.
    max_point_distance_px: float = 1.5
    #: largest RMS distance of a segment's edge points to its line, px.
    max_rms_px: float = 0.6
    #: chains are cut where consecutive points are farther apart, px.
    max_gap_px: float = 4.0
    #: shortest segment kept, px.
    min_length_px: float = 15.0
    #: least number of edge points per pixel of segment length.
    min_density: float = 0.6
    #: merge pieces of one line (same side brighter) across gaps up to
    #: ``merge_max_gap_px`` when both lie within ``merge_max_distance_px``.
    merge: bool = True
    merge_max_distance_px: float = 1.0
    merge_max_gap_px: float = 12.0
    #: segment ends are moved outwards along their line to where the
    #: contrast across it halves, by at most this much, px (0: off).
    extend_max_px: float = 6.0
    #: edge points within this distance of either end of their chain are
    #: left out of the line fit (still part of the extent), px.
    end_trim_px: float = 3.0


@dataclass(kw_only=True)
class VanishingOptions:
    """Options of :func:`detect_vertical_vp`."""

    #: segment detection (first pass).
    lines: LineOptions = field(default_factory=LineOptions)
    #: second pass (:func:`vertical_segments`); skipped when None.
    second_pass: SecondPassOptions | None = field(default_factory=SecondPassOptions)
    #: refine the VP once more on the second pass's edge points ...
    refine_with_second_pass: bool = True
    #: ... on the chains whose RMS distance to their line through the VP is
    #: at most this many robust standard deviations of those RMS values (and
    #: at most ``second_pass.max_rms_px``).
    second_pass_rms_factor: float = 3.0
    #: RANSAC: largest distance of a segment endpoint to the line through the
    #: segment's midpoint and the hypothesis, pixels of the detection image.
    inlier_threshold_px: float = 1.0
    #: RANSAC: shortest segment used, pixels of the detection image.
    min_length_px: float = 12.0
    #: none/aerial priors: segments further than this from the image's
    #: vertical direction are not considered, degrees.
    candidate_max_angle_deg: float = 60.0
    #: RANSAC: a segment's weight in sampling and scoring is length**power;
    #: 0.5 balances long edges (precise) against many short ones (a few long
    #: street edges that pass near the VP must not outvote the buildings).
    score_length_power: float = 0.5
    #: RANSAC: hypotheses per batch, least and most hypotheses, confidence.
    batch_size: int = 512
    min_trials: int = 256
    max_trials: int = 4096
    confidence: float = 0.999
    #: random seed (or pass a numpy Generator to the function).
    seed: int = 0
    #: The first pass (steps 2-4) runs once per factor: with an INS prior
    #: each start searches the prior's cone times its factor; the other
    #: priors have no cone, and each start draws its own RANSAC samples
    #: (one start, before 2026-12-03, left 4 of 252 synthetic `paper` images
    #: 8.6-17 deg off with status "ok": docs/bench_vanishing.md, eighth
    #: round). Some images hold two pencils of
    #: near-equal first-pass score: the verticals of part of the image
    #: together with long street edges meet degrees off the true VP, and
    #: which one RANSAC returns depends on its draws (`paper` seed 4, S_11: 4
    #: of 12 seeds 2-5 deg off) or on the cone (`hard` seed 1, S_11 and S_20:
    #: 8-11 deg off in the 12 deg cone, right in a 6 deg one; `paper` seed 3,
    #: E_12: its INS 7 deg off, outside the 6 deg cone); stage 2 failed on
    #: all of them. When the starts disagree, each distinct VP gets its
    #: second pass and the one whose second-pass segments are longest in
    #: total wins: a wrong VP leaves the verticals elsewhere in the image
    #: unaligned (S_11: 5,000-6,400 px against 7,300-9,600 px). Without a
    #: second pass the first start counts. Cost: one first pass per start
    #: (~7 ms) and a second pass per distinct VP (~0.1 s at 2004 px).
    start_cones: tuple[float, ...] = (1.0, 0.5, 2.0)
    #: Two starts' VPs closer than this (deg, directions through the
    #: intrinsics or the nominal camera) are one VP ...
    starts_same_deg: float = 0.5
    #: ... and this without a cone, where the starts differ only in their
    #: draws: a restart is there to find another pencil (the wrong ones it
    #: replaced lay 8.6-17 deg off), not to re-decide within one, where real
    #: aerial images scatter by a degree (Rennes `00_5021` at 4008 px:
    #: 0.8-0.9 deg; each extra second pass there costs ~0.4 s).
    restarts_same_deg: float = 2.0
    #: ML refinement: re-selection rounds of the inliers.
    refine_rounds: int = 3
    #: competing vanishing points: up to this many other VPs (street and
    #: facade directions) are found by RANSAC among the candidate segments;
    #: each segment then belongs to the VP it fits best (alternating
    #: assignment and ML refinement). Lines of a horizontal direction whose
    #: pencil passes near the vertical VP inside some image strip (a street
    #: seen along the camera's azimuth, with its curbs, markings and cars) are
    #: otherwise taken for verticals and pull the VP along that strip.
    competing_vps: int = 3
    #: a competing VP needs at least this many segments that fit it better
    #: than the vertical VP ...
    competing_min_segments: int = 8
    #: ... and directions (nominal camera when the intrinsics are unknown) at
    #: least this far from the vertical, degrees.
    competing_min_angle_deg: float = 20.0
    #: RANSAC hypotheses per competing VP (one batch).
    competing_batch_size: int = 128
    #: with intrinsics, a candidate vertical VP (the RANSAC winner or a
    #: competitor the prior allows) scores its significance plus that of its
    #: most significant competitor within this many degrees of orthogonal
    #: (the horizontal directions of streets and facades), and candidates
    #: with such a partner of significance >= ``ok_min_significance`` go
    #: first; 0: significance alone. Without intrinsics orthogonality is
    #: unknown and not used.
    orthogonal_support_tol_deg: float = 4.0
    #: fewer inlier segments than this: no VP at all.
    min_inliers: int = 4
    #: status "ok" needs this many inliers ...
    ok_min_inliers: int = 10
    #: ... a significance of at least this (-log10 of the number of false
    #: alarms) ...
    ok_min_significance: float = 3.0
    #: ... and a 1-sigma angular uncertainty of the vertical direction of at
    #: most this (nominal focal max(W, H) when the intrinsics are unknown), deg.
    ok_max_std_deg: float = 1.0

    def __post_init__(self) -> None:
        if not self.start_cones or min(self.start_cones) <= 0:
            raise ValueError(
                f"start_cones needs positive factors, got {self.start_cones}"
            )


@dataclass
class VanishingResult:
    """The vertical vanishing point of one image (failure is a value).

    Attributes
    ----------
    status : str, "ok", "low_confidence" or "no_vp".
    message : str, why, in words.
    vp : (3,) float array or None
        Homogeneous unit vector (x, y, w), COLMAP pixels of the distortion-free
        image (K's image when a camera with distortion was given); w >= 0 and
        w = 0 for a VP at infinity.
    covariance : (3, 3) float array or None, of ``vp`` (rank 2).
    vertical_direction : (3,) float array or None
        Unit vertical direction in the camera frame, pointing down the world;
        only with intrinsics.
    direction_std_deg : float, 1-sigma angular uncertainty of the vertical
        direction (nominal focal max(W, H) when the intrinsics are unknown).
    significance : float, -log10 of the number of false alarms (> 0: the VP is
        unlikely to be chance).
    segments : Segments, first-pass segments (undistorted, full resolution).
    inliers : (N,) bool array, the first-pass inliers of ``vp``.
    vertical_segments : Segments or None, second-pass segments.
    n_hypotheses : int, RANSAC hypotheses evaluated.
    time_s : dict, wall time per step, seconds.
    competing_vps : (K, 3) float array, the other vanishing points the
        segments were assigned against (homogeneous unit vectors, pixels of
        the distortion-free image; horizontal directions of streets and
        facades in oblique aerial images).
    """

    status: str
    message: str = ""
    vp: np.ndarray | None = None
    covariance: np.ndarray | None = None
    vertical_direction: np.ndarray | None = None
    direction_std_deg: float = float("inf")
    significance: float = 0.0
    segments: Segments = field(default_factory=Segments)
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    vertical_segments: Segments | None = None
    n_hypotheses: int = 0
    time_s: dict = field(default_factory=dict)
    competing_vps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __bool__(self) -> bool:
        return self.status != "no_vp"

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def vp_pixel(self) -> np.ndarray | None:
        """(2,) pixel position of the VP, or None (no VP, or at infinity)."""
        if self.vp is None or abs(self.vp[2]) < 1e-12:
            return None
        return self.vp[:2] / self.vp[2]


# --------------------------------------------------------------------------
# Homogeneous helpers
# --------------------------------------------------------------------------


def _nominal_K(W: int, H: int) -> np.ndarray:
    """The nominal camera (focal max(W, H), centred) when K is unknown."""
    return np.array([[max(W, H), 0, W / 2], [0, max(W, H), H / 2], [0, 0, 1.0]])


def _normaliser(width: int, height: int) -> tuple[np.ndarray, float]:
    """T mapping pixels to centred coordinates scaled by half the longer side."""
    s = max(width, height) / 2.0
    T = np.array([[1 / s, 0, -width / 2 / s], [0, 1 / s, -height / 2 / s], [0, 0, 1.0]])
    return T, s


def _canonical_sign(v: np.ndarray) -> np.ndarray:
    """Flip homogeneous vectors (..., 3) so that w >= 0 (y >= 0 at infinity)."""
    w = v[..., 2]
    key = np.where(np.abs(w) > 1e-12 * np.linalg.norm(v, axis=-1), w, v[..., 1])
    return v * np.where(key < 0, -1.0, 1.0)[..., None]


_EYE3 = np.eye(3)


def _tangent_basis(v: np.ndarray) -> np.ndarray:
    """(..., 3, 2) orthonormal bases of the planes perpendicular to unit v (..., 3).

    Smooth in v within each of three regions (chosen by v's smallest |component|);
    the quantities computed from it do not depend on the choice of basis.
    """
    v = np.asarray(v, float)
    if v.ndim == 1:
        return _tangent_basis_1(v)
    e = _EYE3[np.argmin(np.abs(v), axis=-1)]
    u1 = _cross(v, e)
    u1 /= np.linalg.norm(u1, axis=-1, keepdims=True)
    return np.stack([u1, _cross(v, u1)], axis=-1)


def _tangent_basis_1(v: np.ndarray) -> np.ndarray:
    """:func:`_tangent_basis` of one (3,) vector in scalar arithmetic.

    Called thousands of times per image on single VPs, where numpy's per-call
    overhead is most of the cost.
    """
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    ax, ay, az = abs(x), abs(y), abs(z)
    # v x e_k for the axis k of the smallest |component| (first on ties).
    if ax <= ay and ax <= az:
        a, b, c = 0.0, z, -y
    elif ay <= az:
        a, b, c = -z, 0.0, x
    else:
        a, b, c = y, -x, 0.0
    n = math.sqrt(a * a + b * b + c * c)
    a, b, c = a / n, b / n, c / n
    return np.array([[a, y * c - z * b], [b, z * a - x * c], [c, x * b - y * a]])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (np.cross has a large call overhead)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def _pencil_forms(S: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, ...]:
    """The 2x2 forms of :func:`_pencil_fit` for (P, 3, 2) bases U.

    ``A_c = U^T S_c U`` (its 3 distinct entries, from the 9 entries of each S
    in one matrix product over all (P, G)) and ``B = U[:2]^T U[:2]`` (the form
    of ``a^2 + b^2`` of the line ``U x``).

    Returns
    -------
    a00, a01, a11 : (P, G) arrays; b00, b01, b11 : (P, 1) arrays.
    """
    P = len(U)
    u0, u1 = U[:, :, 0], U[:, :, 1]  # (P, 3)
    W = np.concatenate(
        [
            (u0[:, :, None] * u0[:, None, :]).reshape(P, 1, 9),
            (u0[:, :, None] * u1[:, None, :]).reshape(P, 1, 9),
            (u1[:, :, None] * u1[:, None, :]).reshape(P, 1, 9),
        ],
        axis=1,
    ).reshape(3 * P, 9)
    A = (W @ S.reshape(len(S), 9).T).reshape(P, 3, len(S))
    b00 = (u0[:, 0] * u0[:, 0] + u0[:, 1] * u0[:, 1])[:, None]
    b01 = (u0[:, 0] * u1[:, 0] + u0[:, 1] * u1[:, 1])[:, None]
    b11 = (u1[:, 0] * u1[:, 0] + u1[:, 1] * u1[:, 1])[:, None]
    return A[:, 0], A[:, 1], A[:, 2], b00, b01, b11


def _smallest_root(a00, a01, a11, b00, b01, b11) -> np.ndarray:
    """Smallest generalised eigenvalue of (A, B), clipped at 0 (broadcasting)."""
    qa = b00 * b11 - b01 * b01
    qb = a00 * b11 + a11 * b00 - 2 * a01 * b01
    qc = a00 * a11 - a01 * a01
    disc = np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0.0))
    # Smaller root of qa l^2 - qb l + qc = 0 in the cancellation-free form.
    return np.maximum(2 * qc / np.maximum(qb + disc, 1e-300), 0.0)


def _pencil_costs_each(S: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(P, G) cost of :func:`_pencil_fit` of each group for each of (P, 3) V."""
    return _smallest_root(*_pencil_forms(S, _tangent_basis(V)))


def _pencil_costs(S: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Total cost ``sum_c lambda_c(v)`` of :func:`_pencil_fit` for each of (P, 3) V."""
    return _pencil_costs_each(S, V).sum(axis=1)


def _pencil_cost(S: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(G,) the cost of :func:`_pencil_fit` alone (no lines)."""
    return _pencil_costs_each(S, np.asarray(v, float)[None])[0]


def _pencil_fit(S: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best line through v for each group of points, in closed form.

    Minimises ``l^T S_c l / (a^2 + b^2)`` over lines ``l = U x`` of the pencil
    through v (a 2x2 generalised eigenproblem; valid for v at infinity).

    Parameters
    ----------
    S : (G, 3, 3) scatter matrices (:func:`lines.scatter_matrices`).
    v : (3,) unit homogeneous point.

    Returns
    -------
    cost : (G,) sum of squared point-to-line distances of each group.
    lines : (G, 3) the lines, unit normal (a, b).
    """
    U = _tangent_basis(v)  # (3, 2)
    a00, a01, a11, b00, b01, b11 = (f[0] for f in _pencil_forms(S, U[None]))
    lam = _smallest_root(a00, a01, a11, b00, b01, b11)
    # Eigenvector: a row of (A - lam B), rotated; use the larger row.
    m00, m01, m11 = a00 - lam * b00, a01 - lam * b01, a11 - lam * b11
    use0 = m01 * m01 + m00 * m00 >= m11 * m11 + m01 * m01
    x0 = np.where(use0, -m01, -m11)
    x1 = np.where(use0, m00, m01)
    lines = x0[:, None] * U[:, 0] + x1[:, None] * U[:, 1]
    nab = np.sqrt(lines[:, 0] ** 2 + lines[:, 1] ** 2)[:, None]
    lines = lines / np.where(nab > 0, nab, 1.0)
    return lam, lines


# Central-difference stencil of refine_vp, (9, 2): (a, b) for a, b in -1, 0, 1.
_STENCIL = np.array([(a, b) for a in (-1.0, 0.0, 1.0) for b in (-1.0, 0.0, 1.0)])


def refine_vp(
    S: np.ndarray, v0: np.ndarray, max_iterations: int = 20
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Maximum-likelihood VP from groups of points whose lines pass through it.

    Minimises ``f(v) = sum_c min_{l through v} sum_i d(p_ci, l)^2`` (the line of
    each group eliminated in closed form, :func:`_pencil_fit`) by Newton steps
    on the unit sphere (2 parameters; gradient and Hessian by central
    differences, the 9 stencil points evaluated in one vectorised call).

    Parameters
    ----------
    S : (G, 3, 3) scatter matrices in normalised coordinates.
    v0 : (3,) starting point, homogeneous.

    Returns
    -------
    v : (3,) unit homogeneous VP.
    covariance : (3, 3) covariance of v (rank 2): ``2 sigma^2 H^-1`` with
        sigma^2 = f / (n_points - G - 2), n_points the summed weights.
    cost : float, f(v).
    dof : int, degrees of freedom of the residual.
    """
    v = np.asarray(v0, float) / np.linalg.norm(v0)
    h = 1e-5
    grid = _STENCIL * h  # (9, 2)

    def stencil(v_):
        """(9, 3) points around v_ and v_'s tangent basis (3, 2)."""
        B = _tangent_basis(v_)
        P = v_ + grid @ B.T
        return P / np.linalg.norm(P, axis=1, keepdims=True), B

    def derivatives(vals):
        """Value, gradient and Hessian (hxx, hxy, hyy) from the 9 stencil costs."""
        vals = vals.reshape(3, 3).tolist()
        g = ((vals[2][1] - vals[0][1]) / (2 * h), (vals[1][2] - vals[1][0]) / (2 * h))
        hxx = (vals[2][1] - 2 * vals[1][1] + vals[0][1]) / h**2
        hyy = (vals[1][2] - 2 * vals[1][1] + vals[1][0]) / h**2
        hxy = (vals[2][2] - vals[2][0] - vals[0][2] + vals[0][0]) / (4 * h * h)
        return vals[1][1], g, (hxx, hxy, hyy)

    ts = 0.5 ** np.arange(6)
    P9, B = stencil(v)
    f0, g, H = derivatives(_pencil_costs(S, P9))
    for _ in range(max_iterations):
        step = _newton_step(g, H)
        # Converged when the predicted decrease is below 1e-8 of the cost: the
        # remaining step is then ~sqrt(1e-8 x n_points) < 0.01 of the VP's
        # standard deviation (1e-12, rounding noise, took a third more steps).
        if -0.5 * (g[0] * step[0] + g[1] * step[1]) <= 1e-8 * max(f0, 1e-300) + 1e-300:
            break
        # Newton steps can be large far from the optimum: cap, then try a few
        # step lengths at once, together with the stencil around the full
        # step (usually taken), so that one call prices both.
        norm = math.hypot(step[0], step[1])
        if norm > 0.2:
            step = (step[0] * 0.2 / norm, step[1] * 0.2 / norm)
        P = v + np.outer(ts, step[0] * B[:, 0] + step[1] * B[:, 1])
        P /= np.linalg.norm(P, axis=1, keepdims=True)
        P9, B9 = stencil(P[0])
        vals = _pencil_costs(S, np.vstack([P, P9]))
        k = int(np.argmin(vals[: len(ts)]))
        if vals[k] > f0:
            break
        v = P[k]
        if k == 0:
            B, (f0, g, H) = B9, derivatives(vals[len(ts) :])
        else:
            P9, B = stencil(v)
            f0, g, H = derivatives(_pencil_costs(S, P9))
    H = np.array([[H[0], H[1]], [H[1], H[2]]])
    n_points = float(np.sum(S[:, 2, 2]))
    G = len(S)
    dof = int(round(n_points)) - G - 2
    sigma2 = f0 / dof if dof > 0 else np.inf
    try:
        cov_t = 2.0 * sigma2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov_t = np.full((2, 2), np.inf)
    return v, B @ cov_t @ B.T, f0, dof


def _newton_step(g: tuple, H: tuple) -> tuple[float, float]:
    """-H^-1 g for a 2x2 symmetric H = (hxx, hxy, hyy), eigenvalues floored.

    Eigenvalues below 1e-9 of the largest are raised to it (a valley along
    the weakly determined direction: a bounded step instead of a wild one).
    Closed form of the 2x2 eigen-decomposition (numpy's costs more per call
    than the rest of a Newton iteration).
    """
    a, b, c = H
    m, r = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    w1, w2 = m - r, m + r  # ascending
    theta = 0.5 * math.atan2(2 * b, a - c)  # (cos, sin): eigenvector of w2
    q2 = (math.cos(theta), math.sin(theta))
    q1 = (-q2[1], q2[0])
    floor = 1e-9 * max(w2, 1e-300) + 1e-300
    w1, w2 = max(w1, floor), max(w2, floor)
    p1 = (q1[0] * g[0] + q1[1] * g[1]) / w1
    p2 = (q2[0] * g[0] + q2[1] * g[1]) / w2
    return (-(q1[0] * p1 + q2[0] * p2), -(q1[1] * p1 + q2[1] * p2))


def _endpoint_scatter(ends_n: np.ndarray) -> np.ndarray:
    """(G, 3, 3) scatter matrices of segments' two endpoints (normalised)."""
    G = len(ends_n)
    return scatter_matrices(ends_n.reshape(-1, 2), np.repeat(np.arange(G), 2), G)


def _midpoint_distance(v: np.ndarray, mid: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Endpoint distances to the lines through midpoints and VPs.

    Parameters
    ----------
    v : (H, 3) homogeneous VPs; mid : (S, 2) midpoints; half : (S, 2) the
        vectors from the midpoints to endpoint 1. All normalised coordinates.

    Returns
    -------
    (H, S) distances, normalised units.
    """
    a, b, c = v[:, 0:1], v[:, 1:2], v[:, 2:3]
    # l = (mx, my, 1) x (a, b, c); its normal (lx, ly):
    lx = mid[None, :, 1] * c - b
    ly = a - mid[None, :, 0] * c
    num = np.abs(lx * half[None, :, 0] + ly * half[None, :, 1])
    return num / np.maximum(np.sqrt(lx * lx + ly * ly), 1e-300)


# --------------------------------------------------------------------------
# Prior
# --------------------------------------------------------------------------


class _PriorTest:
    """Vectorised test of hypotheses (normalised homogeneous) against a prior."""

    def __init__(
        self,
        prior: VPPrior,
        width: int,
        height: int,
        T: np.ndarray,
        K: np.ndarray | None,
    ) -> None:
        self.prior, self.W, self.H = prior, width, height
        self.Tinv = np.linalg.inv(T)
        self.K = K
        if prior.kind == "ins":
            if K is None:
                raise ValueError("the 'ins' prior needs intrinsics (a camera)")
            self.Kinv = np.linalg.inv(K)
            self.cos_cone = np.cos(np.radians(prior.cone_deg))

    def __call__(self, v_n: np.ndarray) -> np.ndarray:
        v = v_n @ self.Tinv.T  # (H, 3) pixel homogeneous
        p = self.prior
        if p.kind == "ins":
            d = v @ self.Kinv.T
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            return np.abs(d @ p.down_cam) >= self.cos_cone
        v = _canonical_sign(v)
        x, y, w = v[:, 0], v[:, 1], v[:, 2]
        dx, dy = x - 0.5 * self.W * w, y - 0.5 * self.H * w
        in_cone = np.abs(dx) <= np.tan(np.radians(p.max_angle_deg)) * np.abs(dy)
        if p.kind == "aerial":
            below = y >= p.min_y_h * self.H * w
            return in_cone & below & (dy > 0)
        return in_cone & (np.abs(dy) >= p.min_distance_h * self.H * w)


def _candidates(
    segs: Segments, prior: VPPrior, K: np.ndarray | None, options: VanishingOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Which segments can point to a VP the prior allows, and their tolerance.

    Returns
    -------
    mask : (N,) bool.
    half_range : (N,) float, half the range of orientations (rad) a candidate
        may have; used for the chance probability of the significance test.
    """
    d = segs.directions
    if prior.kind != "ins":
        # Angle from the image's vertical axis, 0..pi/2.
        ang = np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1]))
        lim = np.radians(options.candidate_max_angle_deg)
        return ang <= lim, np.full(len(d), lim)
    # INS: the predicted VP and 8 directions on its cone, projected.
    Kinv = np.linalg.inv(K)
    c = prior.down_cam
    B = _tangent_basis(c)
    t = np.tan(np.radians(prior.cone_deg))
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    dirs = c[None] + t * (
        np.cos(phi)[:, None] * B[:, 0] + np.sin(phi)[:, None] * B[:, 1]
    )
    vps = np.vstack([c, dirs]) @ K.T  # (9, 3) pixel homogeneous
    m = segs.midpoints
    # Directions from the midpoints to the 9 points (homogeneous-safe).
    u = vps[None, :, :2] - m[:, None, :] * vps[None, :, 2:3]  # (N, 9, 2)
    ang_u = np.arctan2(u[..., 1], u[..., 0])
    dev = np.abs((ang_u[:, 1:] - ang_u[:, :1] + np.pi / 2) % np.pi - np.pi / 2)
    half_range = dev.max(axis=1) + np.radians(2.0)
    # Midpoints inside the cone's image: any orientation.
    rays = np.hstack([m, np.ones((len(m), 1))]) @ Kinv.T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    inside = np.abs(rays @ c) >= np.cos(np.radians(prior.cone_deg))
    half_range = np.where(inside, np.pi / 2, np.minimum(half_range, np.pi / 2))
    a = np.arctan2(d[:, 1], d[:, 0])
    seg_dev = np.abs((a - ang_u[:, 0] + np.pi / 2) % np.pi - np.pi / 2)
    return seg_dev <= half_range, half_range


# --------------------------------------------------------------------------
# RANSAC
# --------------------------------------------------------------------------


def _ransac(
    lines_n: np.ndarray,
    mid_n: np.ndarray,
    half_n: np.ndarray,
    length: np.ndarray,
    thr_n: float,
    prior_ok,
    options: VanishingOptions,
    rng: np.random.Generator,
    cap: np.ndarray | None = None,
    sample: np.ndarray | None = None,
    max_trials: int | None = None,
    batch_size: int | None = None,
) -> tuple[np.ndarray | None, np.ndarray, int]:
    """Best VP hypothesis from pairs of segments (length-weighted MSAC).

    Pairs are drawn with probabilities proportional to the segment weights,
    in batches; every hypothesis of a batch is scored against every segment
    at once. The number of batches adapts to the best inlier fraction by
    weight (a pair is all-inlier with probability ~ w^2).

    ``cap`` (S,), optional: a segment counts only where its distance is below
    its cap (the distance to another VP: exclusive scoring). ``sample`` (S,)
    bool, optional: the segments pairs are drawn from.

    Returns
    -------
    vp_n : (3,) unit homogeneous VP (normalised coordinates) or None.
    inliers : (S,) bool.
    n_hypotheses : int, hypotheses that passed the prior and were scored.
    """
    S = len(lines_n)
    pool = np.arange(S) if sample is None else np.flatnonzero(sample)
    if len(pool) < 2:
        return None, np.zeros(S, bool), 0
    max_trials = options.max_trials if max_trials is None else max_trials
    batch = options.batch_size if batch_size is None else batch_size
    p = length[pool] / length[pool].sum()
    best_score, best_v, n_hyp, trials = -1.0, None, 0, 0
    needed = max_trials
    chunk = max(1, 2_000_000 // S)

    def inliers_of(v):
        d = _midpoint_distance(v[None], mid_n, half_n)[0]
        return (d <= thr_n) & (d < cap) if cap is not None else d <= thr_n

    min_trials = min(options.min_trials, max_trials)
    while trials < min(needed, max_trials) or trials < min_trials:
        if trials >= max_trials:
            break
        i = pool[rng.choice(len(pool), batch, p=p)]
        j = pool[rng.choice(len(pool), batch, p=p)]
        trials += batch
        keep = i != j
        v = _cross(lines_n[i[keep]], lines_n[j[keep]])
        nv = np.linalg.norm(v, axis=1)
        v = v[nv > 1e-12] / nv[nv > 1e-12, None]
        v = v[prior_ok(v)]
        n_hyp += len(v)
        for k in range(0, len(v), chunk):
            d = _midpoint_distance(v[k : k + chunk], mid_n, half_n)
            m = np.maximum(0.0, 1.0 - (d / thr_n) ** 2)
            if cap is not None:
                m *= d < cap
            score = m @ length
            h = int(np.argmax(score))
            if score[h] > best_score:
                best_score, best_v = float(score[h]), v[k + h]
        if best_v is not None:
            inl = inliers_of(best_v)
            w = float(length[inl].sum() / length[pool].sum())
            pw = min(max(w * w, 1e-12), 1 - 1e-12)
            needed = int(np.ceil(np.log(1 - options.confidence) / np.log1p(-pw)))
    if best_v is None:
        return None, np.zeros(S, bool), n_hyp
    return best_v, inliers_of(best_v), n_hyp


def _significance(k: np.ndarray, p_chance: np.ndarray, n_tests: float) -> np.ndarray:
    """-log10 NFA of k consistent segments among candidates (Poisson tail).

    ``k`` : int or (P,) ints, consistent segments per hypothesis;
    ``p_chance`` are the probabilities that each candidate is consistent by
    chance; the two segments defining a hypothesis are discounted.
    """
    mu = float(np.sum(p_chance)) * max(len(p_chance) - 2, 0) / max(len(p_chance), 1)
    kk = np.asarray(k) - 2
    log_tests = np.log10(max(n_tests, 1.0))
    # P(X >= kk) for X ~ Poisson(mu); a tail below the smallest double is
    # -inf (as scipy.stats.poisson.logsf gives).
    with np.errstate(divide="ignore"):
        log_tail = np.log10(pdtrc(np.maximum(kk, 1) - 1, max(mu, 1e-12)))
    return np.where(kk <= 0, -log_tests, -(log_tests + log_tail))


# --------------------------------------------------------------------------
# Vertical direction
# --------------------------------------------------------------------------


def vertical_direction(
    vp: np.ndarray, K: np.ndarray, down_cam: np.ndarray | None = None
) -> np.ndarray:
    """Unit vertical direction (3,) in the camera frame, pointing down the world.

    ``n = +-normalise(K^-1 vp)``, with ``n . down_cam > 0`` when a predicted down
    direction is known, otherwise ``n_y > 0``.
    """
    n = np.linalg.solve(K, np.asarray(vp, float))
    n /= np.linalg.norm(n)
    ref = n @ down_cam if down_cam is not None else n[1]
    return -n if ref < 0 else n


def _direction_std_deg(vp: np.ndarray, cov: np.ndarray, K: np.ndarray) -> float:
    """1-sigma angle (deg) of normalise(K^-1 vp) from the covariance of vp."""
    Kinv = np.linalg.inv(K)
    m = Kinv @ vp
    nm = np.linalg.norm(m)
    J = (np.eye(3) - np.outer(m, m) / nm**2) / nm @ Kinv
    c = J @ cov @ J.T
    tr = float(np.trace(c))
    return float(np.degrees(np.sqrt(tr))) if np.isfinite(tr) and tr >= 0 else np.inf


# --------------------------------------------------------------------------
# Second pass
# --------------------------------------------------------------------------


@dataclass
class _SecondPass:
    """Second-pass segments with their edge points' scatter (normalised)."""

    segments: Segments
    scatter: np.ndarray  # (G, 3, 3)

    def through(self, vp: np.ndarray, T: np.ndarray) -> Segments:
        """The same segments refitted through another (nearby) VP."""
        if len(self.scatter) == 0:
            return self.segments
        vn = T @ vp
        _, lines = _pencil_fit(self.scatter, vn / np.linalg.norm(vn))
        ends_n = self.segments.endpoints @ T[:2, :2].T + T[:2, 2]
        G = len(lines)
        ends_n = _extents_on(
            ends_n.reshape(-1, 2), np.repeat(np.arange(G), 2), lines, G
        )
        Tinv = np.linalg.inv(T)
        ends = ends_n @ Tinv[:2, :2].T + Tinv[:2, 2]
        return Segments(ends, self.segments.normal, self.segments.strength)


def _second_pass(
    image: np.ndarray,
    vp: np.ndarray,
    options: SecondPassOptions,
    camera: Camera | None,
    T: np.ndarray,
    grads: tuple[np.ndarray, np.ndarray] | None = None,
) -> _SecondPass:
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
    empty = _SecondPass(Segments(), np.zeros((0, 3, 3)))
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
    _, lines = _pencil_fit(scatter_matrices(xy, group, G), vn)
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
    cost, lines = _pencil_fit(Sc, vn)
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
    return _SecondPass(Segments(ends_px[keep], normal[keep], strength[keep]), Sc[keep])


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
    U = _tangent_basis(vn)
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
    _, lines2 = _pencil_fit(S2, vn)
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
    T, _ = _normaliser(W, H)
    return _second_pass(image_gray, np.asarray(vp, float), options, camera, T).segments


# --------------------------------------------------------------------------
# The stage
# --------------------------------------------------------------------------


def _refine_segments(
    ends_n: np.ndarray, v: np.ndarray, inl: np.ndarray, thr_n: float, rounds: int
):
    """ML refinement on the inlier segments, re-selecting the inliers."""
    S_all = _endpoint_scatter(ends_n)
    cov = np.full((3, 3), np.inf)
    for _ in range(max(rounds, 1)):
        if inl.sum() < 3:
            break
        v, cov, _, _ = refine_vp(S_all[inl], v)
        new = np.sqrt(_pencil_cost(S_all, v) / 2.0) <= thr_n
        if np.array_equal(new, inl):
            break
        inl = new
    return v, cov, inl


def _segment_residuals(S_all: np.ndarray, vps: list[np.ndarray]) -> np.ndarray:
    """(M, G) RMS endpoint distance of each segment to its best line through each VP."""
    return np.sqrt(_pencil_costs_each(S_all, np.array(vps)) / 2.0)


def _with_competitors(
    ends_n,
    lines_n,
    mid_n,
    half_n,
    weight,
    v,
    inl,
    thr_n,
    Kn,
    prior_ok,
    significance_of,
    options,
    rng,
    intrinsics_known=False,
):
    """Vertical VP refined against competing VPs (exclusive assignment).

    1. ML refinement of the vertical VP on its inliers (:func:`_refine_segments`).
    2. Up to ``options.competing_vps`` times: RANSAC for another VP among the
       segments, scored only on segments that fit it better than every VP
       found so far, its hypotheses at least ``competing_min_angle_deg`` from
       the vertical direction; kept with ``competing_min_segments`` such
       segments.
    3. Alternation (:func:`_alternate`): every segment goes to the VP it
       fits best (RMS endpoint distance to the best line through the VP), the
       vertical VP is refined by ML on its segments, until stable.
    4. If a competitor that the prior allows as the vertical is more
       significant (``significance_of``; with intrinsics plus the
       significance of its best nearly orthogonal partner), they swap, and
       3. again.

    Returns the vertical VP, its covariance, its inliers (S,) bool, and the
    competing VPs (normalised homogeneous).
    """
    v, cov, inl = _refine_segments(ends_n, v, inl, thr_n, options.refine_rounds)
    if options.competing_vps <= 0 or inl.sum() < 3:
        return v, cov, inl, []
    S_all = _endpoint_scatter(ends_n)
    Kinv = np.linalg.inv(Kn)
    cos_sep = np.cos(np.radians(options.competing_min_angle_deg))

    def direction(h):
        d = h @ Kinv.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    comps: list[np.ndarray] = []
    for _ in range(options.competing_vps):
        dv = direction(v)

        def far_from_vertical(h, dv=dv):
            return np.abs(direction(h) @ dv) <= cos_sep

        cap = _midpoint_distance(np.vstack([v] + comps), mid_n, half_n).min(axis=0)
        free = cap > 0.5 * thr_n
        h, hinl, _ = _ransac(
            lines_n,
            mid_n,
            half_n,
            weight,
            thr_n,
            far_from_vertical,
            options,
            rng,
            cap=cap,
            sample=free,
            # Streets and facades are strong pencils: one small batch.
            max_trials=options.competing_batch_size,
            batch_size=options.competing_batch_size,
        )
        if h is None or hinl.sum() < options.competing_min_segments:
            break
        comps.append(h)
    if not comps:
        return v, cov, inl, []
    vps = [v] + comps
    vps, cov, assign = _alternate(S_all, vps, cov, thr_n, direction, cos_sep, options)
    # The vertical is the most significant pencil the prior allows: a street
    # seen along its length (dashes, curbs, cars: many short segments) can
    # outscore the buildings in pair-RANSAC; if a competitor the prior allows
    # is more significant, the two swap roles.
    allowed = prior_ok(np.array(vps))
    use_ortho = intrinsics_known and options.orthogonal_support_tol_deg > 0
    need = allowed.copy()
    if use_ortho:
        d = direction(np.array(vps))
        ortho = np.abs(d @ d.T) <= np.sin(
            np.radians(options.orthogonal_support_tol_deg)
        )
        need |= (ortho & allowed[:, None]).any(axis=0)
    # Significance only where it is used (each costs three pencil fits).
    sig = np.full(len(vps), -np.inf)
    sig[need] = significance_of(np.array(vps)[need])
    score = np.where(allowed, sig, -np.inf)
    if use_ortho:
        # With intrinsics, the vertical is orthogonal to the horizontal
        # directions (streets, facades) whose pencils compete with it; a
        # pencil of street lines and facade rows that merely looks vertical
        # inside a strip (paper seed 2, S_11: 42 deg off with significance
        # 100) has no orthogonal partner. Each allowed candidate is scored
        # with the significance of its best orthogonal partner added, and a
        # candidate with a significant orthogonal partner goes before any
        # without one.
        partner = np.where(ortho, np.maximum(sig, 0.0)[None, :], 0.0).max(axis=1)
        score = np.where(allowed, sig + partner, -np.inf)
        paired = allowed & (partner >= options.ok_min_significance)
        if paired.any():
            score = np.where(paired, score, -np.inf)
    best = int(np.argmax(score))
    if best != 0 and score[best] > score[0]:
        vps[0], vps[best] = vps[best], vps[0]
        v2, cov2, _, _ = refine_vp(S_all[assign == best], vps[0])
        if np.all(np.isfinite(v2)):
            vps[0], cov = v2, cov2
        vps, cov, assign = _alternate(
            S_all, vps, cov, thr_n, direction, cos_sep, options
        )
    inl = assign == 0
    return vps[0], cov, inl, vps[1:]


def _alternate(S_all, vps, cov, thr_n, direction, cos_sep, options):
    """Assign segments to their best VP and refine, until stable.

    The competitors (``vps[1:]``) are refined once, a few Newton steps (they
    only claim their segments); the vertical VP ``vps[0]`` in every round.
    """
    vps = list(vps)
    assign, first_round = None, True
    for _ in range(max(options.refine_rounds, 1)):
        D = _segment_residuals(S_all, vps)
        new = np.where(D.min(axis=0) <= thr_n, np.argmin(D, axis=0), -1)
        if assign is not None and np.array_equal(new, assign):
            break
        assign = new
        if first_round:
            for m in range(1, len(vps)):
                sel = assign == m
                if sel.sum() >= 3:
                    vm = refine_vp(S_all[sel], vps[m], max_iterations=3)[0]
                    # A competitor must not drift onto the vertical.
                    if np.abs(direction(vm) @ direction(vps[0])) <= cos_sep:
                        vps[m] = vm
            first_round = False
        sel = assign == 0
        if sel.sum() >= 3:
            vm, cm, _, _ = refine_vp(S_all[sel], vps[0])
            if np.all(np.isfinite(vm)):
                vps[0], cov = vm, cm
    return vps, cov, assign


def estimate_vertical_vp(
    segments: Segments,
    image_size: tuple[int, int],
    options: VanishingOptions | None = None,
    camera: Camera | None = None,
    prior: VPPrior | None = None,
    rng: np.random.Generator | int | None = None,
) -> VanishingResult:
    """Vertical VP from segments (steps 2 and 3 of the module docstring).

    Parameters
    ----------
    segments : Segments, undistorted COLMAP pixels of the full image.
    image_size : (width, height) in pixels.
    options, camera, prior : as :func:`detect_vertical_vp`.
    rng : Generator, seed or None (then ``options.seed``).

    Returns
    -------
    VanishingResult (without second-pass segments).
    """
    options = options or VanishingOptions()
    prior = prior or VPPrior.none()
    if prior.kind == "ins" and camera is None:
        raise ValueError("the 'ins' prior needs intrinsics (a camera)")
    rng = np.random.default_rng(options.seed if rng is None else rng)
    W, H = image_size
    T, s = _normaliser(W, H)
    K = camera.K if camera is not None else None
    Knom = K if K is not None else _nominal_K(W, H)
    limit = options.lines.max_image_size_px
    factor = max(1.0, max(W, H) / limit) if limit else 1.0
    thr_px = options.inlier_threshold_px * factor
    thr_n = thr_px / s
    t0 = time.perf_counter()

    use = segments.lengths >= options.min_length_px * factor
    cand, half_range = _candidates(segments, prior, K, options)
    use &= cand
    idx = np.flatnonzero(use)
    result = VanishingResult(
        status="no_vp", segments=segments, inliers=np.zeros(len(segments), bool)
    )
    if len(idx) < options.min_inliers:
        result.message = (
            f"no vertical structure: {len(idx)} candidate segments "
            f"(need {options.min_inliers})"
        )
        return result
    ends_n = segments.endpoints[idx] @ T[:2, :2].T + T[:2, 2]  # (S, 2, 2)
    mid_n = ends_n.mean(axis=1)
    half_n = 0.5 * (ends_n[:, 1] - ends_n[:, 0])
    lines_n = np.cross(
        np.concatenate([ends_n[:, 0], np.ones((len(idx), 1))], 1),
        np.concatenate([ends_n[:, 1], np.ones((len(idx), 1))], 1),
    )
    lines_n /= np.linalg.norm(lines_n, axis=1, keepdims=True)
    length = segments.lengths[idx]
    prior_ok = _PriorTest(prior, W, H, T, K)
    weight = length**options.score_length_power
    v, inl, n_hyp = _ransac(
        lines_n, mid_n, half_n, weight, thr_n, prior_ok, options, rng
    )
    result.n_hypotheses = n_hyp
    result.time_s["ransac"] = time.perf_counter() - t0
    if v is None:
        result.message = "no pair of segments meets where the prior allows a VP"
        return result

    t0 = time.perf_counter()
    # Background model: every segment has a uniform orientation (deviation
    # from the line to the VP uniform in [0, pi/2]); k counts those consistent
    # with the VP, whichever VP they were assigned to. The prior only limits
    # where hypotheses may lie (fewer tests); using the candidates' narrow
    # orientation band as the chance range would make a strong pencil of 400
    # verticals look like chance under a tight INS cone. The test is made in
    # three length classes (at least 1, 2 and 4 times min_length_px), the
    # best one counting, with the number of tests multiplied by 3: a pencil of
    # many short segments and one of a few long ones in a textured image
    # (where hundreds of short segments make any VP look like chance) are
    # both recognised. Number of tests: the hypotheses RANSAC may examine
    # (fixed a priori by max_trials), not all pairs of segments.
    n_tests = 3 * min(len(idx) * (len(idx) - 1) / 2, options.max_trials)
    # The classes are nested: one scatter for the first, masks for the others.
    sel = segments.lengths >= options.min_length_px * factor
    L1 = segments.lengths[sel]
    S_sig = _endpoint_scatter(segments.endpoints[sel] @ T[:2, :2].T + T[:2, 2])
    p_chance = np.minimum(
        1.0, np.arcsin(np.minimum(1.0, thr_px / (0.5 * L1))) / (np.pi / 2)
    )
    classes = [
        m
        for m in (mult * options.min_length_px * factor <= L1 for mult in (1, 2, 4))
        if m.any()
    ]

    def significance_of(V):
        """(P,) significance of each of (P, 3) VPs (normalised)."""
        V = np.asarray(V, float).reshape(-1, 3)
        best = np.full(len(V), -np.inf)
        if not classes:
            return best
        consistent = np.sqrt(_pencil_costs_each(S_sig, V) / 2.0) <= thr_n  # (P, G)
        for m in classes:
            k = np.count_nonzero(consistent[:, m], axis=1)
            best = np.maximum(best, _significance(k, p_chance[m], n_tests))
        return best

    v, cov, inl, comps = _with_competitors(
        ends_n,
        lines_n,
        mid_n,
        half_n,
        weight,
        v,
        inl,
        thr_n,
        T @ Knom,
        prior_ok,
        significance_of,
        options,
        rng,
        intrinsics_known=K is not None,
    )
    if comps:
        c = np.array(comps) @ np.linalg.inv(T).T
        result.competing_vps = _canonical_sign(
            c / np.linalg.norm(c, axis=1, keepdims=True)
        )
    result.time_s["refine"] = time.perf_counter() - t0
    if not prior_ok(v[None])[0]:
        # The structure converges where the prior says the VP cannot be (e.g.
        # nearly parallel verticals whose refinement crosses infinity to the
        # other side): by the prior's definition there is no vertical VP.
        vpx = _canonical_sign(np.linalg.inv(T) @ v)
        result.message = (
            "the vertical structure converges outside the prior's region "
            f"(homogeneous VP {np.round(vpx / np.linalg.norm(vpx), 5).tolist()})"
        )
        return result
    sig = float(significance_of(v)[0])
    result.inliers[idx[inl]] = True
    _set_vp(result, v, cov, T, K, Knom, prior)
    result.significance = sig
    _set_status(result, options)
    return result


def _set_vp(result, v_n, cov_n, T, K, Knom, prior) -> None:
    """Store the VP (pixels, canonical sign), its covariance and direction.

    ``Knom`` (intrinsics or a nominal camera) gives the direction's angular
    uncertainty; None keeps the result's current one.
    """
    Tinv = np.linalg.inv(T)
    v = Tinv @ v_n
    nv = np.linalg.norm(v)
    J = (np.eye(3) - np.outer(v, v) / nv**2) / nv @ Tinv
    v = v / nv
    cov = J @ cov_n @ J.T
    flip = _canonical_sign(v)
    result.vp = flip
    result.covariance = cov
    if Knom is not None:
        result.direction_std_deg = _direction_std_deg(flip, cov, Knom)
    if K is not None:
        result.vertical_direction = vertical_direction(
            flip, K, prior.down_cam if prior.kind == "ins" else None
        )


def _set_status(result: VanishingResult, options: VanishingOptions) -> None:
    k, sig, std = result.n_inliers, result.significance, result.direction_std_deg
    if k < options.min_inliers or sig <= 0:
        result.status = "no_vp"
        result.message = (
            f"no vertical structure: best VP has {k} consistent segments, "
            f"not more than chance (significance {sig:.1f})"
        )
        result.vp = result.covariance = result.vertical_direction = None
        return
    reasons = []
    if k < options.ok_min_inliers:
        reasons.append(f"{k} inlier segments < {options.ok_min_inliers}")
    if sig < options.ok_min_significance:
        reasons.append(f"significance {sig:.1f} < {options.ok_min_significance}")
    if not std <= options.ok_max_std_deg:
        reasons.append(f"direction std {std:.2f} deg > {options.ok_max_std_deg}")
    result.status = "low_confidence" if reasons else "ok"
    result.message = (
        "; ".join(reasons)
        if reasons
        else (f"{k} inlier segments, direction std {std:.3f} deg")
    )


def _refine_on_chains(
    sp: _SecondPass,
    v_n: np.ndarray,
    comps: np.ndarray,
    options: VanishingOptions,
    s_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The VP refined on the second pass's chains, and the chains to return.

    Parameters
    ----------
    sp : the second pass (scatter in normalised coordinates).
    v_n : (3,) unit VP, normalised coordinates.
    comps : (K, 3) unit competing VPs, normalised coordinates.
    s_px : pixels per normalised unit.

    Returns
    -------
    v_n : (3,) the refined VP; keep : (G,) bool, the chains through it within
    ``second_pass.max_rms_px`` that fit it better than any competing VP.
    """
    S = sp.scatter
    n_pts = np.maximum(S[:, 2, 2], 1)
    max_cost = (options.second_pass.max_rms_px / s_px) ** 2
    # Chains that fit a competing VP (a street's direction) better than the
    # vertical one are not vertical edges.
    other = np.full(len(S), np.inf)
    if len(comps):
        other = _pencil_costs_each(S, comps).min(axis=0) / n_pts
    cost = _pencil_cost(S, v_n) / n_pts
    # Re-select the segments with each refined VP: a few long non-vertical
    # edges that passed near the first-pass VP (streets receding towards the
    # horizon) drop out as the VP improves.
    use = (cost <= max_cost) & (cost <= np.maximum(other, 0.25 * max_cost))
    if use.sum() < 3:
        use[:] = True
    for _ in range(max(options.refine_rounds, 1) + 2):
        v_n, _, _, _ = refine_vp(S[use], v_n)
        cost = _pencil_cost(S, v_n) / n_pts
        # Robust scale of the chains' RMS distances: straight edges through
        # the VP share one noise level. The VP is refined on the chains within
        # ``second_pass_rms_factor`` of it; a chain goes to a competing VP only
        # when that fits it better by more than this noise (near the line
        # joining the two VPs both fit equally well).
        scale2 = (1.4826 * np.median(np.sqrt(cost[use]))) ** 2
        thr = min(max_cost, options.second_pass_rms_factor**2 * scale2)
        new = (cost <= thr) & (cost - other <= scale2)
        if np.array_equal(new, use) or new.sum() < 3:
            break
        use = new
    return v_n, (cost <= max_cost) & (cost < other)


def _start_priors(prior: VPPrior, factors: Sequence[float]) -> list[VPPrior]:
    """One prior per first-pass start: the INS cone times each factor (at
    most 80 deg); the other kinds have no cone: the prior itself as often
    (each start draws its own RANSAC samples)."""
    if prior.kind != "ins":
        return [prior] * len(factors)
    return [
        dataclasses.replace(prior, cone_deg=min(80.0, prior.cone_deg * f))
        for f in factors
    ]


def _same_vp(a: np.ndarray, b: np.ndarray, K: np.ndarray, same_deg: float) -> bool:
    """Whether homogeneous VPs a, b (3,) are one: their directions through K
    within ``same_deg`` (sign-free)."""
    da, db = np.linalg.solve(K, a), np.linalg.solve(K, b)
    cos = abs(float(da @ db)) / (np.linalg.norm(da) * np.linalg.norm(db))
    return cos >= math.cos(math.radians(same_deg))


def _distinct(
    results: list[VanishingResult], K: np.ndarray, same_deg: float
) -> list[VanishingResult]:
    """The results with a VP that is not :func:`_same_vp` as any earlier
    one, in order; the first result alone when none has a VP."""
    kept: list[VanishingResult] = []
    for r in results:
        if r.vp is not None and not any(
            _same_vp(r.vp, k.vp, K, same_deg) for k in kept
        ):
            kept.append(r)
    return kept or results[:1]


def _with_second_pass(
    result: VanishingResult,
    img: np.ndarray,
    grads: tuple[np.ndarray, np.ndarray],
    options: VanishingOptions,
    camera: Camera | None,
    prior: VPPrior,
) -> float:
    """Run the second pass for ``result`` in place (its vertical segments,
    and the VP refined on them); returns their total length, px (0 without
    a VP)."""
    if result.vp is None:
        return 0.0
    H, W = img.shape
    t0 = time.perf_counter()
    T, s_px = _normaliser(W, H)
    sp = _second_pass(img, result.vp, options.second_pass, camera, T, grads)
    result.time_s["second_pass"] = time.perf_counter() - t0
    if options.refine_with_second_pass and len(sp.scatter) >= 3:
        t0 = time.perf_counter()
        v_n = T @ result.vp
        v_n = v_n / np.linalg.norm(v_n)
        comps = result.competing_vps @ T.T
        comps /= np.linalg.norm(comps, axis=1, keepdims=True)
        v_n, keep = _refine_on_chains(sp, v_n, comps, options, s_px)
        sp = _SecondPass(sp.segments.subset(keep), sp.scatter[keep])
        # The edge points of a chain are correlated (smoothing, optics), so
        # their formal covariance is ~10x too optimistic; the first pass's
        # (calibrated on independent segments) is kept as a conservative
        # figure for the refined VP.
        cov_px = result.covariance
        K = camera.K if camera is not None else None
        _set_vp(result, v_n, np.zeros((3, 3)), T, K, None, prior)
        result.covariance = cov_px
        result.time_s["refine_second"] = time.perf_counter() - t0
    result.vertical_segments = sp.through(result.vp, T)
    e = result.vertical_segments.endpoints
    return float(np.linalg.norm(e[:, 1] - e[:, 0], axis=1).sum()) if len(e) else 0.0


def detect_vertical_vp(
    image_gray: np.ndarray,
    options: VanishingOptions | None = None,
    camera: Camera | None = None,
    prior: VPPrior | None = None,
    rng: np.random.Generator | int | None = None,
) -> VanishingResult:
    """The vertical vanishing point of one image, and the vertical segments.

    A pure function of its arguments (safe to run in a process pool).

    Parameters
    ----------
    image_gray : (H, W) uint8 array (or (H, W, 3) BGR).
    options : VanishingOptions or None for the defaults.
    camera : Camera or None
        Intrinsics: with them the vertical direction is returned, the INS prior
        is possible, and lens distortion is removed from the segments first.
    prior : VPPrior or None (``VPPrior.none()``).
    rng : numpy Generator, seed, or None (``options.seed``).

    Returns
    -------
    VanishingResult
        ``status`` "no_vp" (with a message) instead of an exception when the
        image has no usable vertical structure.
    """
    options = options or VanishingOptions()
    prior = prior or VPPrior.none()
    img = as_gray_u8(image_gray)
    H, W = img.shape
    if camera is not None and (camera.width, camera.height) != (W, H):
        raise ValueError(
            f"camera is {camera.width}x{camera.height} but the image is {W}x{H}"
        )
    t_start = time.perf_counter()
    t0 = time.perf_counter()
    segs = detect_segments(img, options.lines).undistorted(camera)
    t_lines = time.perf_counter() - t0
    rng = np.random.default_rng(options.seed if rng is None else rng)
    K = camera.K if camera is not None else _nominal_K(W, H)
    same_deg = (
        options.starts_same_deg if prior.kind == "ins" else options.restarts_same_deg
    )
    # Every start is a whole first pass: stopping a restart whose RANSAC
    # lands near a known VP lost `paper` seed 5 N_21 (11.8 deg off), whose
    # refinement swaps to the vertical pencil from a competitor's winner.
    results = _distinct(
        [
            estimate_vertical_vp(segs, (W, H), options, camera, p, rng)
            for p in _start_priors(prior, options.start_cones)
        ],
        K,
        same_deg,
    )
    if options.second_pass is None or results[0].vp is None:
        result = results[0]
    else:
        t0 = time.perf_counter()
        grads = gradients(img, options.second_pass.sigma_px)
        # One VP: its second pass as always; several: the one whose second
        # pass finds the most vertical edge length (``start_cones``).
        lengths = [
            _with_second_pass(r, img, grads, options, camera, prior) for r in results
        ]
        # Among VPs that the second pass brought together, the first start's
        # (the prior's own cone): the longest second pass picks the pencil,
        # not the most accurate VP within it.
        best = results[int(np.argmax(lengths))]
        result = next(r for r in results if _same_vp(best.vp, r.vp, K, same_deg))
        result.time_s["second_pass_all"] = time.perf_counter() - t0
        if len(results) > 1:
            logger.debug(
                "%d distinct VPs from %d starts; second-pass lengths %s px",
                len(results),
                len(options.start_cones),
                np.round(lengths).tolist(),
            )
    result.time_s["lines"] = t_lines
    result.time_s["total"] = time.perf_counter() - t_start
    logger.debug("%s: %s", result.status, result.message)
    return result
