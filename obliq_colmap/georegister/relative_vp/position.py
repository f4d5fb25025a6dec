"""Step 3: the camera centre with the rotation known (a linear 2-point
RANSAC over 2D-3D correspondences)."""

from __future__ import annotations

import numpy as np

from obliq_colmap.geometry import rotation_angle_deg

from .options import RelativeVPOptions


def _centres(P: np.ndarray, X: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Least-squares points nearest to lines: (H, S, 3, 3) projectors
    ``I - w w^T`` across each line, (H, S, 3) points on them, (H, S)
    weights; (H, 3) centres (NaN where the lines are parallel)."""
    A = np.einsum("hs,hsab->hab", weight, P)
    b = np.einsum("hs,hsab,hsb->ha", weight, P, X)
    ok = np.abs(np.linalg.det(A)) > 1e-12 * np.einsum("hii->h", A) ** 3
    c = np.full(b.shape, np.nan)
    if ok.any():
        c[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return c


def _reprojection_px(
    R: np.ndarray, centre: np.ndarray, rays: np.ndarray, X: np.ndarray, f: float
) -> np.ndarray:
    """(H, N) errors (px, focal ``f``) of (N, 3) points X seen along the
    (N, 3) camera rays (z = 1) from (H, 3) centres; inf behind the camera."""
    Xc = (X[None] - centre[:, None]) @ R.T  # (H, N, 3)
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = f * np.linalg.norm(Xc[..., :2] / z[..., None] - rays[None, :, :2], axis=2)
    return np.where(z > 0, err, np.inf)


def centre_from_rotation(
    R: np.ndarray,
    rays: np.ndarray,
    X: np.ndarray,
    focal_px: float,
    options: RelativeVPOptions,
    rng: np.random.Generator | int | None = None,
) -> tuple[np.ndarray | None, np.ndarray]:
    """The camera centre with ``cam_from_world`` rotation R known.

    Parameters
    ----------
    R : (3, 3) cam_from_world rotation.
    rays : (N, 3) camera-frame rays (normalised coordinates, z = 1) of the
        image's keypoints.
    X : (N, 3) the model points they observe.
    focal_px : pixels per unit of normalised coordinates (for the threshold).

    Returns
    -------
    centre (3,) in the model frame (None: fewer than ``min_inliers`` or
    than ``min_inlier_ratio`` of N) and the (N,) inlier mask.

    Each correspondence holds the centre on the line through X_j along the
    world ray ``R^T rays_j``; two such lines (4 equations) give the centre
    as their least-squares meeting point. All pairs at once (at most
    ``max_pairs``), scored by inliers; the winner refit on its inliers with
    weights ``1 / range^2`` (distance to a line over the range is the
    angular, i.e. pixel, error), three times.
    """
    rng = np.random.default_rng(options.seed if rng is None else rng)
    n = len(X)
    inl = np.zeros(n, bool)
    if n < max(2, options.min_inliers):
        return None, inl
    w = rays @ R  # world directions (rows: R^T r)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    P = np.eye(3)[None] - w[:, :, None] * w[:, None, :]  # (N, 3, 3)
    i, j = np.triu_indices(n, 1)
    if len(i) > options.max_pairs:
        pick = rng.choice(len(i), options.max_pairs, replace=False)
        i, j = i[pick], j[pick]
    pairs = np.stack([i, j], 1)  # (H, 2)
    c = _centres(P[pairs], X[pairs], np.ones(pairs.shape))
    good = np.isfinite(c).all(1)
    if not good.any():
        return None, inl
    sub = np.arange(n)
    if n > options.max_score_points:
        sub = rng.choice(n, options.max_score_points, replace=False)
    err = _reprojection_px(R, c[good], rays[sub], X[sub], focal_px)
    ninl = (err < options.ransac_threshold_px).sum(1)
    best = c[good][int(np.argmax(ninl))]
    for _ in range(3):
        inl = _reprojection_px(R, best[None], rays, X, focal_px)[0]
        inl = inl < options.ransac_threshold_px
        if inl.sum() < 2:
            break
        rng_sq = np.sum((X[inl] - best) ** 2, axis=1)
        refit = _centres(P[inl][None], X[inl][None], (1.0 / rng_sq)[None])[0]
        if not np.isfinite(refit).all():
            break
        best = refit
    inl = _reprojection_px(R, best[None], rays, X, focal_px)[0] < (
        options.ransac_threshold_px
    )
    if inl.sum() < max(options.min_inliers, options.min_inlier_ratio * n):
        return None, inl
    return best, inl


def place_with_rotations(
    candidates: np.ndarray,
    reference: np.ndarray,
    rays: np.ndarray,
    X: np.ndarray,
    focal_px: float,
    options: RelativeVPOptions,
) -> tuple[int, np.ndarray | None, np.ndarray, int]:
    """Among (C, 3, 3) rotation candidates within
    ``max_rotation_from_reference_deg`` of the (3, 3) reference, the one
    whose position has the most inliers.

    Returns (candidate index or -1, centre (3,) or None, (N,) inlier mask,
    number of candidates tried).
    """
    ang = np.atleast_1d(rotation_angle_deg(candidates, reference[None]))
    near = np.flatnonzero(ang <= options.max_rotation_from_reference_deg)
    best = (-1, None, np.zeros(len(X), bool))
    for k in near[np.argsort(ang[near])]:  # at most a few (2-8) candidates
        c, inl = centre_from_rotation(candidates[k], rays, X, focal_px, options)
        if c is not None and inl.sum() > best[2].sum():
            best = (int(k), c, inl)
    return (*best, len(near))
