"""The closed-form minimal solver of the initial registration, and RANSAC helpers.

With the vertical direction known, a camera is ``X_cam = R0 R_z(alpha) (X - c)``
(paper eq. 1, ``R0`` = R_vanish: any rotation with ``R0 e_z = -n``, ``n`` the
vertical direction in the camera frame pointing down the world). For an image
line ``l`` through the vertical vanishing point and a map corner ``(x, y)``,

    l^T K R0 R_z(alpha) (X - c) = 0

is LINEAR and homogeneous in ``w = (cos alpha, sin alpha, u_x, u_y)`` with
``u = R_z(alpha) c`` (docs/DESIGN.md, "Conventions"): with ``m = R0^T K^T l``
(``m_z = 0`` because ``l`` passes through the VP ``K n``),

    [m_x x + m_y y,  m_y x - m_x y,  -m_x,  -m_y] . w = 0.

Neither the corner's height nor the camera height appears: a vertical edge
projects onto the same image line at every height, and moving the camera
along the vertical moves every point along its line through the VP. Three
constraints give a 1-D null space (the generalised cross product of the three
rows), scaled so that ``cos^2 + sin^2 = 1``; its two signs are ``alpha`` and
``alpha + pi`` with the same centre, and cheirality picks one. The camera
height is held (at the prior) instead of the paper's perpendicular auxiliary
constraint, which fixes it arbitrarily; see docs/DESIGN.md.

Everything is vectorised over a batch of samples: thousands of hypotheses cost
a few milliseconds. The algebraic residual is for generating hypotheses only;
:mod:`obliq_colmap.registration.refine` refines the winner on geometric
residuals.

References
----------
M. Habbecke, L. Kobbelt, "Automatic registration of oblique aerial images with
cadastral maps", ECCV workshops 2010, section 2.2, eq. 1-2.
M. A. Fischler, R. C. Bolles, "Random sample consensus", CACM 24(6), 1981.
R. Hartley, A. Zisserman, "Multiple view geometry", 2nd ed., section 4.7.1
(the adaptive number of RANSAC trials).
"""

from __future__ import annotations

import math

import numpy as np

#: Relative size below which a null vector counts as degenerate (a rank drop
#: of the 3 x 4 system: repeated or collinear constraints).
_DEGENERATE_REL = 1e-9


def constraint_rows(m_xy: np.ndarray, corner_xy: np.ndarray) -> np.ndarray:
    """Rows of the linear vertical-line constraints.

    Parameters
    ----------
    m_xy : (..., 2) array
        First two components of ``m = R0^T K^T l`` for each image line ``l``
        (unit normal in pixels), the VP-aligned frame.
    corner_xy : (..., 2) array
        Map corner positions, metres, relative to the reference point of the
        centre (any fixed point near the camera, for conditioning).

    Returns
    -------
    (..., 4) array: the row ``[m_x x + m_y y, m_y x - m_x y, -m_x, -m_y]``,
    dotted with ``(cos alpha, sin alpha, u_x, u_y)``, ``u = R_z(alpha) c``.
    """
    m_xy = np.asarray(m_xy, float)
    xy = np.asarray(corner_xy, float)
    mx, my = m_xy[..., 0], m_xy[..., 1]
    x, y = xy[..., 0], xy[..., 1]
    return np.stack([mx * x + my * y, my * x - mx * y, -mx, -my], axis=-1)


def null_vectors(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Null vectors of a batch of 3 x 4 systems, scaled to ``w0^2 + w1^2 = 1``.

    The null vector of a rank-3 (3, 4) matrix is its generalised cross product:
    ``w_k = (-1)^k det(A with column k removed)``.

    Parameters
    ----------
    rows : (B, 3, 4) array, three constraint rows per sample
        (:func:`constraint_rows`).

    Returns
    -------
    w : (B, 4) array ``(cos alpha, sin alpha, u_x, u_y)``, one of the two signs
        (the caller picks the sign by cheirality); NaN where degenerate.
    valid : (B,) bool array, False for degenerate samples (rank < 3, or a
        solution with ``cos^2 + sin^2`` ~ 0: a camera at infinity).
    """
    A = np.asarray(rows, float)
    if A.ndim != 3 or A.shape[1:] != (3, 4):
        raise ValueError(f"rows must be (B, 3, 4), got shape {A.shape}")
    # Columns normalised for conditioning (the angle columns are in metres, the
    # centre columns are unitless); undone below.
    scale = np.linalg.norm(A, axis=1)  # (B, 4)
    scale = np.where(scale > 0, scale, 1.0)
    An = A / scale[:, None, :]
    w = np.empty((len(A), 4))
    for k in range(4):
        cols = [j for j in range(4) if j != k]
        w[:, k] = (-1) ** k * np.linalg.det(An[:, :, cols])
    w = w / scale  # null vector of A: A (w / s) = An w = 0
    norm_rows = np.prod(np.linalg.norm(An, axis=2), axis=1)  # Hadamard bound
    wn = np.linalg.norm(w * scale, axis=1)
    r = np.hypot(w[:, 0], w[:, 1])
    valid = (wn > _DEGENERATE_REL * np.maximum(norm_rows, 1e-300)) & (r > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = w / np.where(valid, r, np.nan)[:, None]
    return w, valid


def pose_parameters(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(alpha, c_xy)`` from null vectors ``(cos, sin, u_x, u_y)``.

    Parameters
    ----------
    w : (B, 4) array with ``w0^2 + w1^2 = 1``.

    Returns
    -------
    alpha : (B,) array, radians.
    c_xy : (B, 2) array, metres, relative to the reference point of
        :func:`constraint_rows`. ``c = R_z(-alpha) u``.
    """
    w = np.asarray(w, float)
    cos, sin = w[:, 0], w[:, 1]
    alpha = np.arctan2(sin, cos)
    ux, uy = w[:, 2], w[:, 3]
    c_xy = np.stack([cos * ux + sin * uy, -sin * ux + cos * uy], axis=1)
    return alpha, c_xy


def horizontal_in_camera(
    R0: np.ndarray, alpha: np.ndarray, d_xy: np.ndarray
) -> np.ndarray:
    """Camera-frame images of horizontal world vectors ``R0 R_z(alpha) (dx, dy, 0)``.

    Parameters
    ----------
    R0 : (3, 3) array, ``R_vanish``.
    alpha : (B,) array, radians.
    d_xy : (B, P, 2) array of horizontal world vectors (metres).

    Returns
    -------
    (B, P, 3) array.
    """
    ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
    dx, dy = d_xy[..., 0], d_xy[..., 1]
    rx = ca * dx - sa * dy
    ry = sa * dx + ca * dy
    return rx[..., None] * R0[:, 0] + ry[..., None] * R0[:, 1]


def choose_sign(
    w: np.ndarray,
    valid: np.ndarray,
    R0: np.ndarray,
    corner_xy: np.ndarray,
    side_dir: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Pick the sign of each null vector by cheirality.

    A corner and the image segment it is matched to must lie on the same side
    of the camera's vertical axis: the horizontal vector from the camera to
    the corner, in the camera frame, and the component orthogonal to ``n`` of
    the segment's viewing ray point the same way. This is height-free, and for
    an oblique camera it is the usual "in front of the camera" test; for a
    nadir camera it is the half-line of the segment from the VP. Flipping the
    sign of ``w`` (alpha + pi, same centre) flips every side, so one sign
    passes for all three pairs or the sample is inconsistent.

    Parameters
    ----------
    w : (B, 4) null vectors, valid : (B,) bool (:func:`null_vectors`).
    R0 : (3, 3) ``R_vanish``.
    corner_xy : (B, 3, 2) the samples' corners relative to the reference point.
    side_dir : (B, 3, 3) for each sample pair, the segment's viewing ray with
        its component along ``n`` removed (camera frame).

    Returns
    -------
    w : (B, 4) with the chosen sign; valid : (B,) bool, False where neither sign
        puts all three pairs on their segment's side.
    """
    alpha, c_xy = pose_parameters(np.where(valid[:, None], w, 0.0))
    h_cam = horizontal_in_camera(R0, alpha, corner_xy - c_xy[:, None, :])  # (B, 3, 3)
    side = np.sum(h_cam * side_dir, axis=2)  # (B, 3)
    plus = np.all(side > 0, axis=1)
    minus = np.all(side < 0, axis=1)
    w = np.where(minus[:, None], -w, w)
    return w, valid & (plus | minus)


def solve_minimal(
    m_xy: np.ndarray,
    corner_xy: np.ndarray,
    R0: np.ndarray,
    side_dir: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses from batches of three corner / vertical-line pairs.

    Parameters
    ----------
    m_xy : (B, 3, 2) array, ``(R0^T K^T l)_xy`` of the samples' lines.
    corner_xy : (B, 3, 2) array, corners relative to the reference point (m).
    R0 : (3, 3) array, ``R_vanish``.
    side_dir : (B, 3, 3) array, see :func:`choose_sign`.

    Returns
    -------
    alpha : (B,) radians; c_xy : (B, 2) metres, relative to the reference point;
    valid : (B,) bool (degenerate or inconsistent samples are False, their
    alpha and c_xy are NaN).
    """
    rows = constraint_rows(m_xy, corner_xy)  # (B, 3, 4)
    w, valid = null_vectors(rows)
    w, valid = choose_sign(w, valid, R0, corner_xy, side_dir)
    alpha, c_xy = pose_parameters(w)
    alpha = np.where(valid, alpha, np.nan)
    c_xy = np.where(valid[:, None], c_xy, np.nan)
    return alpha, c_xy, valid


def required_trials(
    inlier_ratio: float, sample_size: int = 3, confidence: float = 0.99
) -> float:
    """RANSAC trials for ``confidence`` of one all-inlier sample.

    ``log(1 - confidence) / log(1 - inlier_ratio ** sample_size)`` (Hartley &
    Zisserman, eq. 4.18). The ratio is clipped to (0, 1): 0 gives infinity,
    1 gives one trial (the logarithm of 0 is avoided).

    Parameters
    ----------
    inlier_ratio : float in [0, 1].
    sample_size : int.
    confidence : float in (0, 1).

    Returns
    -------
    float, possibly ``inf``.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    p = float(inlier_ratio) ** int(sample_size)
    if p <= 0.0:
        return math.inf
    if p >= 1.0:
        return 1.0
    return math.ceil(math.log(1.0 - confidence) / math.log1p(-p))


def sample_pairs(
    rng: np.random.Generator,
    num_samples: int,
    pair_corner: np.ndarray,
    pair_segment: np.ndarray,
    sample_size: int = 3,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Random samples of distinct pairs with distinct corners and segments.

    Parameters
    ----------
    rng : numpy Generator.
    num_samples : int, samples wanted (fewer are returned when some draws
        repeat a corner or a segment; they are dropped, not redrawn, so the
        stream of random numbers does not depend on the data beyond its size).
    pair_corner, pair_segment : (P,) int arrays, the corner and the segment of
        each candidate pair.
    sample_size : int.
    weights : (P,) array or None, sampling weights (uniform if None).

    Returns
    -------
    (S, sample_size) int array of pair indices, S <= num_samples.
    """
    num_pairs = len(pair_corner)
    if num_pairs < sample_size:
        return np.zeros((0, sample_size), int)
    if weights is None:
        idx = rng.integers(0, num_pairs, size=(num_samples, sample_size))
    else:
        cdf = np.cumsum(np.asarray(weights, float))
        u = rng.uniform(0.0, cdf[-1], size=(num_samples, sample_size))
        idx = np.minimum(np.searchsorted(cdf, u, side="right"), num_pairs - 1)
    ok = np.ones(num_samples, bool)
    for a in range(sample_size):
        for b in range(a + 1, sample_size):
            ok &= pair_corner[idx[:, a]] != pair_corner[idx[:, b]]
            ok &= pair_segment[idx[:, a]] != pair_segment[idx[:, b]]
    return idx[ok]
