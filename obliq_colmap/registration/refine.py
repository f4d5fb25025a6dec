"""Step 5 of the registration: one-to-one inlier assignment, Levenberg-Marquardt
refinement of the pose (with the focal length, the vertical and the radial
distortion when enough inliers allow), the refine / re-score rounds
(:func:`refine_rounds`) and the final height plane."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from obliq_colmap.geometry import Camera
from obliq_colmap.registration.options import RegistrationOptions
from obliq_colmap.registration.ransac import Candidates, candidates
from obliq_colmap.registration.segments import (
    Segments,
    mahalanobis2,
    prepare_segments,
)
from obliq_colmap.registration.view import (
    View,
    fit_planes,
    perturbed_view,
    plane_at,
    tilt_basis,
)


def _inlier_assignment(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    cand: Candidates,
    alpha: float,
    c_xy: np.ndarray,
    plane: np.ndarray,
    options: RegistrationOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one inlier pairs (best Mahalanobis distance first).

    Returns (corner indices, segment indices), both (K,).
    """
    xy = corner_rel[cand.corner]
    z = plane_at(plane[None], xy)
    px, _ = view.project(np.array([alpha]), c_xy[None], xy, z)
    d2 = mahalanobis2(px, segs, cand.segment, options.along_segment_stretch)[0]
    inl = np.flatnonzero(d2 <= options.inlier_threshold_px**2)
    inl = inl[np.argsort(d2[inl], kind="stable")]
    used_c, used_s = set(), set()
    keep = []
    for k in inl:
        ci, sj = int(cand.corner[k]), int(cand.segment[k])
        if ci in used_c or sj in used_s:
            continue
        used_c.add(ci)
        used_s.add(sj)
        keep.append(k)
    keep = np.asarray(keep, int)
    return cand.corner[keep], cand.segment[keep]


@dataclass
class Lens:
    """The current camera's distortion, for residuals from RAW segments.

    ``camera``: the current intrinsics (its pinhole part is the view's
    ``K``); ``k_index``: index of the radial ``k1`` in its params, or None
    when it is not refined; ``k_prior``, ``k_sigma``: centre and 1-sigma of
    its prior (unitless).
    """

    camera: Camera
    k_index: int | None
    k_prior: float = 0.0
    k_sigma: float = math.inf

    def camera_at(self, log_focal: float, dk: float) -> Camera:
        """The camera with its focal scaled by ``exp(log_focal)`` and ``k1 + dk``."""
        cam = self.camera.with_focal_scaled(math.exp(log_focal))
        if self.k_index is not None:
            cam.params[self.k_index] += dk
        return cam

    def undistorted(self, raw: np.ndarray, log_focal: float, dk: float) -> np.ndarray:
        """(K, 2, 2) raw endpoints to undistorted pixels of that camera."""
        cam = self.camera_at(log_focal, dk)
        return cam.undistort_pixels(raw.reshape(-1, 2)).reshape(raw.shape)


def radial_index(model: str) -> int | None:
    """Index of the first radial distortion term in a model's params."""
    from obliq_colmap.geometry import SUPPORTED_MODELS

    names = SUPPORTED_MODELS[model]
    for name in ("k", "k1"):
        if name in names:
            return names.index(name)
    return None


def residuals(
    params: np.ndarray,
    view: View,
    corner_rel: np.ndarray,
    ends: np.ndarray,
    free: tuple[bool, bool, bool],
    tilt_axes: np.ndarray,
    prior_px: np.ndarray,
    lens: Lens | None = None,
) -> np.ndarray:
    """Distances (px) of both endpoints of each segment to its corner's
    vertical, then the prior terms of the free focal / tilt / k1 (1 px per
    sigma).

    ``params`` = (alpha, c_x, c_y[, log focal][, tilt_1, tilt_2][, dk1]) as
    ``free`` (focal, vertical, distortion) says; ``prior_px`` (3,) = 1 / sigma
    of (log focal, tilt_1, tilt_2). With a ``lens``, ``ends`` are RAW pixels,
    undistorted here with the candidate focal length and k1 (the distortion
    depends on both); without, undistorted pixels of the view's ``K``.
    """
    alpha, cx, cy = params[:3]
    v = view
    extra = []
    k = 3
    log_f = 0.0
    if free[0]:
        log_f = params[k]
        extra.append(log_f * prior_px[0])
        k += 1
    tilt = None
    if free[1]:
        tilt = params[k : k + 2]
        extra += list(tilt * prior_px[1:])
        k += 2
    dk = 0.0
    if free[2]:
        dk = params[k]
        k0 = lens.camera.params[lens.k_index]
        extra.append((k0 + dk - lens.k_prior) / lens.k_sigma)
    if free[0] or free[1]:
        v = perturbed_view(view, log_f, tilt, tilt_axes)
    if lens is not None:
        ends = lens.undistorted(ends, log_f, dk)
    lines = v.corner_lines(np.array([alpha]), np.array([[cx, cy]]), corner_rel)[0]
    r = np.sum(ends * lines[:, None, :2], axis=2) + lines[:, None, 2]  # (K, 2)
    return np.r_[r.ravel(), extra]


def _refine(
    view: View,
    corner_rel: np.ndarray,
    ends: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    free: tuple[bool, bool, bool],
    options: RegistrationOptions,
    lens: Lens | None = None,
) -> tuple[View, Camera | None, float, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over (alpha, c_x, c_y[, focal][, two tilts][, k1])
    with a Huber loss.

    ``free`` = (focal, vertical, distortion): which of the extra parameters
    move. The focal length is observable from one image through the spread
    of the pencil of projected verticals (a 1-D homography from the azimuths
    of the corners around the camera); the vertical through the directions
    of the segments and the positions of corners at different distances; the
    radial distortion through the cubic growth of the lateral offsets towards
    the image borders (pose and focal move the verticals affinely). All get
    a weak prior (``prior_focal_sigma``, ``vertical_sigma_deg``,
    ``distortion_sigma_px``) so that a few inliers cannot drag them far.

    ``lens``: the current camera when it has (or refines) distortion; then
    ``ends`` are the segments' RAW endpoints (K, 2, 2), else undistorted
    pixels of ``view.K``.

    Returns the (possibly re-focused and re-tilted) view, the camera with the
    refined focal and k1 (None without a ``lens``), alpha, c_xy and the final
    residuals (K, 2) in px.
    """
    from scipy.optimize import least_squares

    free = (free[0], free[1], free[2] and lens is not None and lens.k_index is not None)
    tilt_axes = tilt_basis(view.n)
    n_extra = int(free[0]) + 2 * int(free[1]) + int(free[2])
    x0 = np.r_[alpha, c_xy, np.zeros(n_extra)]

    depth = max(1.0, float(np.median(np.linalg.norm(corner_rel - c_xy, axis=1))))
    x_scale = np.r_[1.0 / view.focal, np.full(2, depth / view.focal)]
    x_scale = np.r_[x_scale, np.full(n_extra - int(free[2]), 1.0 / view.focal)]
    if free[2]:
        # k1 moving the image corners by one pixel.
        x_scale = np.r_[x_scale, 1.0 / _corner_px_per_k(lens.camera)]
    prior_px = np.array(
        [
            1.0 / max(options.prior_focal_sigma, options.focal_sigma_min),
            1.0 / math.radians(options.vertical_sigma_deg),
            1.0 / math.radians(options.vertical_sigma_deg),
        ]
    )
    sol = least_squares(
        residuals,
        x0,
        args=(view, corner_rel, ends, free, tilt_axes, prior_px, lens),
        loss="huber",
        f_scale=options.inlier_threshold_px,
        x_scale=x_scale,
        max_nfev=options.refine_max_iterations * (len(x0) + 1),
        method="trf",
    )
    x = sol.x
    log_f = x[3] if free[0] else 0.0
    if free[0] or free[1]:
        tilt = x[3 + int(free[0]) : 5 + int(free[0])] if free[1] else None
        view = perturbed_view(view, log_f, tilt, tilt_axes)
    camera = None
    if lens is not None:
        camera = lens.camera_at(log_f, x[-1] if free[2] else 0.0)
        lens = Lens(camera, None)
    r = residuals(
        x[:3], view, corner_rel, ends, (False,) * 3, tilt_axes, prior_px, lens
    )
    return view, camera, float(x[0]), x[1:3].copy(), r.reshape(-1, 2)


@dataclass
class Fit:
    """Step 5's outcome: the refined view, segments (undistorted with the
    refined lens), lens, pose (alpha, c_xy), relative height plane (3,), the
    inlier pairs (ci into corner_rel, sj into segs, both (K,)), their
    residuals (K, 2) px, and whether the distortion moved."""

    view: View
    segs: Segments
    lens: Lens | None
    alpha: float
    c_xy: np.ndarray
    plane: np.ndarray
    ci: np.ndarray
    sj: np.ndarray
    resid: np.ndarray
    distortion_refined: bool


def lens_of(
    camera: Camera, k_index: int | None, options: RegistrationOptions
) -> Lens | None:
    """The current camera when its distortion matters (has or refines one):
    the residuals then come from the raw segments, undistorted with it."""
    if not (camera.has_distortion or k_index is not None):
        return None
    k_prior = float(camera.params[k_index]) if k_index is not None else 0.0
    k_sigma = options.distortion_sigma_px / _corner_px_per_k(camera)
    return Lens(camera, k_index, k_prior, k_sigma)


def refine_rounds(
    view: View,
    segs: Segments,
    raw: np.ndarray,
    corner_rel: np.ndarray,
    vis: np.ndarray,
    cand: Candidates,
    alpha: float,
    c_xy: np.ndarray,
    plane: np.ndarray,
    lens: Lens | None,
    moving: tuple[bool, bool, bool],
    depth_m: float,
    cadastre,
    options: RegistrationOptions,
) -> Fit:
    """Step 5: the inliers of a pose, refined and re-scored
    (``options.refine_rounds``), then the pose alone on the final inliers.

    ``raw``: the segments' raw pixels (N, 2, 2) (for a ``lens``); ``vis``:
    the cadastre's indices of ``corner_rel``; ``cand``: the candidate pairs
    of the starting pose; ``moving``: (focal, vertical, distortion) may move
    (each from ``options.min_inliers_intrinsics`` inliers on); ``options`` at
    the image's scale.
    """
    ci, sj = _inlier_assignment(
        view, segs, corner_rel, cand, alpha, c_xy, plane, options
    )
    resid = np.zeros((0, 2))
    k_index = lens.k_index if lens is not None else None
    distortion_refined = False

    def refine(free):
        if lens is None:
            v, _, a, c, r = _refine(
                view, corner_rel[ci], segs.ends[sj], alpha, c_xy, free, options
            )
            return v, None, a, c, r
        ends = raw[segs.index[sj]]
        return _refine(view, corner_rel[ci], ends, alpha, c_xy, free, options, lens)

    for _ in range(options.refine_rounds):
        if len(ci) < options.min_inliers:
            break
        # The focal, the vertical and the distortion move only with enough
        # inliers.
        enough = len(ci) >= options.min_inliers_intrinsics
        free = (
            moving[0] and enough,
            moving[1] and enough,
            moving[2] and k_index is not None and enough,
        )
        distortion_refined |= free[2]
        new_view, new_cam, alpha, c_xy, resid = refine(free)
        # Whole buildings that do not fit (a building shifted in the map).
        bld = cadastre.corner_building[vis[ci]]
        res_pair = np.sqrt(np.mean(resid**2, axis=1))
        bad = np.zeros(len(ci), bool)
        for b in np.unique(bld):
            sel = bld == b
            if (
                np.median(res_pair[sel])
                > options.building_outlier_factor * options.inlier_threshold_px
            ):
                bad |= sel
        if bad.any() and (~bad).sum() >= options.min_inliers:
            ci, sj = ci[~bad], sj[~bad]
            new_view, new_cam, alpha, c_xy, resid = refine(free)
        view = new_view
        if lens is not None:
            # The segments again, undistorted with the refined camera.
            lens = dataclasses.replace(lens, camera=new_cam)
            und = new_cam.undistort_pixels(raw.reshape(-1, 2)).reshape(raw.shape)
            segs = prepare_segments(und, view, options, index=segs.index)
        plane = final_plane(view, segs, corner_rel, ci, sj, alpha, c_xy, options)
        # Re-score every pair near the refined pose.
        ground = plane_at(plane[None], corner_rel)[0]
        cand = candidates(
            view,
            segs,
            corner_rel,
            alpha,
            c_xy,
            ground,
            4.0 * options.inlier_threshold_px,
            options.along_segment_stretch
            * options.inlier_threshold_px
            * depth_m
            / view.focal
            * 2.0
            + 2.0,
        )
        ci, sj = _inlier_assignment(
            view, segs, corner_rel, cand, alpha, c_xy, plane, options
        )
    if len(ci) >= options.min_inliers:
        _, _, alpha, c_xy, resid = refine((False, False, False))
        plane = final_plane(view, segs, corner_rel, ci, sj, alpha, c_xy, options)
    return Fit(view, segs, lens, alpha, c_xy, plane, ci, sj, resid, distortion_refined)


def _corner_px_per_k(camera: Camera) -> float:
    """Displacement (px) at the image corners per unit of radial ``k1``."""
    f = float(np.mean(np.diag(camera.K)[:2]))
    r = 0.5 * math.hypot(camera.width, camera.height) / f  # normalised radius
    return f * r**3


def final_plane(
    view: View,
    segs: Segments,
    corner_rel: np.ndarray,
    ci: np.ndarray,
    sj: np.ndarray,
    alpha: float,
    c_xy: np.ndarray,
    options: RegistrationOptions,
) -> np.ndarray:
    """Height plane through the inliers' bottom heights (relative coordinates)."""
    ridge = (options.height_sigma_m / options.slope_sigma) ** 2
    h = view.bottom_heights(
        np.array([alpha]), c_xy[None], corner_rel[ci], segs.bottom[sj]
    )  # (1, K)
    plane = fit_planes(corner_rel[ci][None], h, None, ridge)
    for _ in range(2):  # Huber-like reweighting against occluded bottoms
        res = h - plane_at(plane, corner_rel[ci][None])
        s = 2.0 * options.height_sigma_m
        w = np.where(np.abs(res) <= s, 1.0, s / np.maximum(np.abs(res), 1e-9))
        plane = fit_planes(corner_rel[ci][None], h, w, ridge)
    return plane[0]
