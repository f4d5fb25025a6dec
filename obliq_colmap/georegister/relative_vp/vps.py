"""Step 1-2: an image's horizontal VPs (RANSAC with the vertical known) and
the rotation candidates against a registered neighbour."""

from __future__ import annotations

import numpy as np
import pycolmap

from obliq_colmap.geometry import Camera
from obliq_colmap.vanishing import VanishingOptions, VPPrior, detect_vertical_vp

from .options import HorizontalVPs, ImageVPs, RelativeVPOptions


def _plane_normals(endpoints: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals, camera frame, of the planes through the camera
    centre and each segment of (N, 2, 2) undistorted pixels."""
    ones = np.ones((len(endpoints), 1))
    a = np.concatenate([endpoints[:, 0], ones], 1)
    b = np.concatenate([endpoints[:, 1], ones], 1)
    n = np.cross(a, b) @ K  # the line l (N, 3); its plane's normal is K^T l
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _endpoint_distances(endpoints: np.ndarray, vps: np.ndarray) -> np.ndarray:
    """(M, N) largest distance (px) of each segment's endpoints to the line
    through its midpoint and each VP; VPs (M, 3) homogeneous (w = 0 legal)."""
    mid = np.concatenate([endpoints.mean(1), np.ones((len(endpoints), 1))], 1)
    lines = np.cross(mid[None], vps[:, None])  # (M, N, 3)
    lines /= np.maximum(np.linalg.norm(lines[..., :2], axis=2, keepdims=True), 1e-12)
    ab, c = lines[..., :2], lines[..., 2]
    d0 = np.abs(np.einsum("mnk,nk->mn", ab, endpoints[:, 0]) + c)
    d1 = np.abs(np.einsum("mnk,nk->mn", ab, endpoints[:, 1]) + c)
    return np.maximum(d0, d1)


def _refine_horizontal(
    normals: np.ndarray, weight: np.ndarray, basis: np.ndarray
) -> np.ndarray:
    """(3,) unit h in span(basis (3, 2)) minimising sum w (n . h)^2 over the
    (S, 3) plane normals: the smallest eigenvector of a 2 x 2 matrix."""
    a = normals @ basis  # (S, 2)
    M = (a * weight[:, None]).T @ a
    _, vec = np.linalg.eigh(M)
    h = basis @ vec[:, 0]
    return h / np.linalg.norm(h)


def horizontal_vps(
    endpoints: np.ndarray,
    K: np.ndarray,
    down: np.ndarray,
    options: RelativeVPOptions,
    exclude: np.ndarray | None = None,
    rng: np.random.Generator | int | None = None,
) -> HorizontalVPs:
    """Horizontal VPs of an image whose vertical is known.

    Parameters
    ----------
    endpoints : (N, 2, 2) segment endpoints, undistorted COLMAP pixels.
    K : (3, 3) pinhole matrix of those pixels.
    down : (3,) unit world down in the camera frame (stage 1).
    exclude : (N,) bool, segments already explained (the vertical pencil).
    rng : Generator or seed (default ``options.seed``).

    Returns
    -------
    HorizontalVPs, strongest first; empty when no direction has
    ``min_horizontal_inliers`` segments.
    """
    rng = np.random.default_rng(options.seed if rng is None else rng)
    endpoints = np.asarray(endpoints, float).reshape(-1, 2, 2)
    n_all = len(endpoints)
    out = HorizontalVPs(inliers=np.zeros((0, n_all), bool))
    down = np.asarray(down, float) / np.linalg.norm(down)
    lengths = np.linalg.norm(endpoints[:, 1] - endpoints[:, 0], axis=1)
    normals = _plane_normals(endpoints, K)
    nd = np.abs(normals @ down)
    near = np.sin(np.radians(options.exclude_near_deg))
    # |n.d| ~ 0: the plane holds the vertical (a vertical segment, any h
    # fits it); |n.d| ~ 1: the segment lies on the horizon line, through
    # every horizontal VP. Neither can choose a horizontal direction.
    usable = (lengths >= options.min_segment_length_px) & (nd > near)
    usable &= nd < np.cos(np.radians(options.exclude_near_deg))
    if exclude is not None:
        usable &= ~np.asarray(exclude, bool)
    # an orthonormal basis of the plane perpendicular to down
    e1 = np.cross(down, [1.0, 0.0, 0.0] if abs(down[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(down, e1)], 1)  # (3, 2)
    found, counts, masks = [], [], []
    free = usable.copy()
    thr = options.inlier_threshold_px
    for _ in range(options.max_horizontal_vps):
        idx = np.flatnonzero(free)
        if len(idx) < options.min_horizontal_inliers:
            break
        # hypotheses: one segment each, drawn by length (long ones first)
        m = min(options.num_hypotheses, len(idx))
        p = lengths[idx] / lengths[idx].sum()
        hyp = rng.choice(idx, size=m, replace=False, p=p)
        h = np.cross(normals[hyp], down)  # (M, 3), perpendicular to down
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        dist = _endpoint_distances(endpoints[idx], h @ K.T)  # (M, S)
        # truncated quadratic (MSAC), weighted by length
        score = (np.clip(1.0 - (dist / thr) ** 2, 0.0, None) * lengths[idx]).sum(1)
        best = h[int(np.argmax(score))]
        for _ in range(3):  # refit on the inliers, re-score
            inl = idx[_endpoint_distances(endpoints[idx], (K @ best)[None])[0] < thr]
            if len(inl) < 2:
                break
            best = _refine_horizontal(normals[inl], lengths[inl] ** 2, basis)
        inl = idx[_endpoint_distances(endpoints[idx], (K @ best)[None])[0] < thr]
        if len(inl) < options.min_horizontal_inliers:
            break
        free[inl] = False
        # a pencil close to one already found is its spill-over, not a facade
        if found:
            cos = np.abs(np.array(found) @ best).max()
            if np.degrees(np.arccos(min(cos, 1.0))) < options.min_separation_deg:
                continue
        mask = np.zeros(n_all, bool)
        mask[inl] = True
        found.append(best)
        counts.append(len(inl))
        masks.append(mask)
    if found:
        out = HorizontalVPs(np.array(found), np.array(counts), np.array(masks))
    return out


def image_vps(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    options: RelativeVPOptions,
    vanishing: VanishingOptions | None = None,
) -> ImageVPs:
    """Stage 1 (terrestrial prior) and :func:`horizontal_vps` on one image.

    gray : (H, W) uint8 image; camera : its intrinsics (distortion removed
    from the segments by stage 1).
    """
    cam = Camera(
        camera.model.name, camera.width, camera.height, np.asarray(camera.params)
    )
    res = detect_vertical_vp(
        gray,
        vanishing or VanishingOptions(seed=options.seed),
        camera=cam,
        prior=VPPrior.none(),
    )
    if res.status != "ok" or res.vertical_direction is None:
        return ImageVPs("no_vertical_vp", f"no vertical VP ({res.message})")
    down = np.asarray(res.vertical_direction, float)
    hv = horizontal_vps(
        res.segments.endpoints, cam.K, down, options, exclude=res.inliers
    )
    if len(hv.directions) == 0:
        return ImageVPs(
            "no_horizontal_vp",
            f"no horizontal VP with >= {options.min_horizontal_inliers} segments",
            down,
        )
    return ImageVPs("ok", f"{len(hv.directions)} horizontal VP(s)", down, hv)


# --------------------------------------------------------------------------
# Step 2: the rotation
# --------------------------------------------------------------------------


def _triads(down: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(K, 3, 3) right-handed frames with columns (h, down x h, down) for
    (K, 3) directions h perpendicular to the unit (3,) down."""
    h = h - (h @ down)[:, None] * down
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    return np.stack([h, np.cross(down, h), np.broadcast_to(down, h.shape)], 2)


def rotation_candidates(
    down_cam: np.ndarray,
    h_cam: np.ndarray,
    down_world: np.ndarray,
    h_world: np.ndarray,
) -> np.ndarray:
    """All ``cam_from_world`` rotations that take the world's down to
    ``down_cam`` and one of the world's horizontal directions to one of the
    camera's, either sign.

    down_cam (3,), h_cam (I, 3): the new image's vertical and horizontal
    directions (camera frame); down_world (3,), h_world (J, 3): the same in
    the model frame (from the neighbour). Returns (2 I J, 3, 3).
    """
    h_cam = np.concatenate([h_cam, -h_cam])  # a VP's direction has no sign
    C = _triads(down_cam / np.linalg.norm(down_cam), h_cam)  # (2I, 3, 3)
    W = _triads(down_world / np.linalg.norm(down_world), h_world)  # (J, 3, 3)
    # R W_j = C_i: the world frame's axes onto the camera's
    R = np.einsum("iab,jcb->ijac", C, W)
    return R.reshape(-1, 3, 3)
