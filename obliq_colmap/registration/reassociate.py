"""A registered image seen through another camera (its head's): the pose its
inliers give with that camera, then every pair near it scored and refined
again (:func:`refine_with_camera`), with a soft inlier count as its
consensus (:func:`reassociate`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from obliq_colmap.geometry import Camera, rotation_aligning
from obliq_colmap.registration.options import (
    RegistrationOptions,
    RegistrationResult,
    at_image_scale,
)
from obliq_colmap.registration.ransac import candidates
from obliq_colmap.registration.refine import (
    Lens,
    final_plane,
    lens_of,
    refine_rounds,
    residuals,
)
from obliq_colmap.registration.segments import prepare_segments
from obliq_colmap.registration.view import View, perturbed_view, plane_at, tilt_basis


@dataclass
class _Inliers:
    """One registered image's inlier pairs as a refinement problem.

    ``view`` is at the result's pose (alpha 0, c_xy 0); ``corner_rel`` (K, 2)
    the inlier corners relative to its centre; ``ends`` (K, 2, 2) their
    segments, RAW pixels with a ``lens``, else undistorted pixels of
    ``view.K``; ``options`` at the image's scale (inlier threshold).
    """

    view: View
    corner_rel: np.ndarray
    ends: np.ndarray
    lens: Lens | None
    options: RegistrationOptions


def _inlier_problem(
    result: RegistrationResult,
    camera: Camera,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> _Inliers:
    """The inliers of a successful ``result`` seen through ``camera``.

    ``segments_camera``: the camera in whose undistorted pixels the result's
    ``inlier_segments_px`` are. Another focal length than the result's keeps
    the vanishing point's pixel (the detected quantity) and turns the pose
    about the camera centre by the smallest rotation that follows it.
    """
    pose = result.cam_from_world
    n_old = -pose.rotation[:, 2]  # the world's down in the camera frame
    vp = result.camera.K @ n_old
    n = np.linalg.solve(camera.K, vp)
    n = n / np.linalg.norm(n)
    R0 = rotation_aligning(n_old, n) @ pose.rotation
    view = View(K=camera.K, Kinv=np.linalg.inv(camera.K), R0=R0, n=n, c0=pose.center)
    corner_xy = cadastre.corner_xy[result.inlier_pairs[:, 0]]
    corner_rel = corner_xy - view.c0[:2]
    ends = np.asarray(result.inlier_segments_px, float)
    if segments_camera.has_distortion:
        ends = segments_camera.distort_pixels(ends.reshape(-1, 2)).reshape(ends.shape)
    lens = Lens(camera, None) if camera.has_distortion else None
    plane = result.height_plane
    z = corner_xy @ plane[:2] + plane[2]
    _, depth = view.project(np.zeros(1), np.zeros((1, 2)), corner_rel, z)
    depth = depth[0][depth[0] > 0]
    depth_m = float(np.median(depth)) if len(depth) else 100.0
    return _Inliers(
        view, corner_rel, ends, lens, at_image_scale(options, view.focal, depth_m)
    )


def _solve_inliers(
    p: _Inliers, free_focal: bool, focal_sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Huber least squares over (alpha, c_x, c_y[, log focal], two tilts) of
    one image's inliers, the vertical under its weak prior.

    Returns the solution x, the residuals' Jacobian at it (robust-weighted,
    rows: 2 per inlier, then the priors of the free focal and the tilts) and
    the axes of the tilts (2, 3).
    """
    from scipy.optimize import least_squares

    view, o = p.view, p.options
    tilt_axes = tilt_basis(view.n)
    free = (free_focal, True, False)
    x0 = np.zeros(5 + int(free_focal))
    depth = max(1.0, float(np.median(np.linalg.norm(p.corner_rel, axis=1))))
    x_scale = np.r_[1.0, depth, depth, np.ones(2 + int(free_focal))] / view.focal
    prior_px = np.array(
        [1.0 / focal_sigma, *(2 * [1.0 / math.radians(o.vertical_sigma_deg)])]
    )
    sol = least_squares(
        residuals,
        x0,
        args=(view, p.corner_rel, p.ends, free, tilt_axes, prior_px, p.lens),
        loss="huber",
        f_scale=o.inlier_threshold_px,
        x_scale=x_scale,
        max_nfev=o.refine_max_iterations * (len(x0) + 1),
        method="trf",
        ftol=1e-4,
        xtol=1e-4,
    )
    return sol.x, sol.jac, tilt_axes


def reassociate(
    result: RegistrationResult,
    camera: Camera,
    segments_px: np.ndarray,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> tuple[RegistrationResult, float]:
    """:func:`refine_with_camera` and the consensus of its result: the sum
    over the inlier corners of ``1 - (rms residual / threshold)^2`` (a soft
    inlier count, 0 on failure)."""
    from obliq_colmap.cadastre import visible_corners

    # The pose that the old inliers give with the new camera ...
    p = _inlier_problem(result, camera, segments_camera, cadastre, options)
    x, _, tilt_axes = _solve_inliers(p, False, 1.0)
    v = perturbed_view(p.view, 0.0, x[3:5], tilt_axes)
    ends = p.ends
    if p.lens is not None:
        ends = camera.undistort_pixels(ends.reshape(-1, 2)).reshape(ends.shape)
    k = np.arange(len(ends))
    inl = prepare_segments(ends, v, p.options, index=k)
    # The ground moves with the pose (the camera height is held).
    plane = final_plane(v, inl, p.corner_rel, k, k, float(x[0]), x[1:3], p.options)
    plane = np.r_[plane[:2], plane[2] + plane[:2] @ x[1:3]]  # relative to c0
    c0 = np.r_[v.c0[:2] + x[1:3], v.c0[2]]
    view = View(K=v.K, Kinv=v.Kinv, R0=v.rotation(float(x[0])), n=v.n, c0=c0)
    # ... then every pair near it scored again (step 5 of the registration).
    seg = np.asarray(segments_px, float).reshape(-1, 2, 2)
    raw = seg
    if segments_camera.has_distortion:
        raw = segments_camera.distort_pixels(seg.reshape(-1, 2)).reshape(seg.shape)
    und = raw
    if camera.has_distortion:
        und = camera.undistort_pixels(raw.reshape(-1, 2)).reshape(raw.shape)
    segs = prepare_segments(und, view, options)
    vis = visible_corners(
        cadastre,
        camera,
        view.pose(0.0, np.zeros(2)),
        ground_height=float(plane[2]),
        height_range_m=options.height_range_m,
        margin_px=options.ransac_radius_px,
    )
    corner_rel = cadastre.corner_xy[vis] - c0[:2]
    ground = plane_at(plane[None], corner_rel)[0]
    _, depth = view.project(np.zeros(1), np.zeros((1, 2)), corner_rel, ground)
    depth = depth[0][depth[0] > 0]
    failed = dataclasses.replace(
        result, success=False, message="no consensus with the head's camera"
    )
    if len(segs) < options.min_segments or len(depth) < options.min_inliers:
        return failed, 0.0
    depth_m = float(np.median(depth))
    o = at_image_scale(options, view.focal, depth_m)
    cand = candidates(
        view,
        segs,
        corner_rel,
        0.0,
        np.zeros(2),
        ground,
        4.0 * o.inlier_threshold_px,
        o.along_segment_stretch * o.inlier_threshold_px * depth_m / view.focal * 2.0
        + 2.0,
    )
    fit = refine_rounds(
        view,
        segs,
        raw,
        corner_rel,
        vis,
        cand,
        0.0,
        np.zeros(2),
        plane,
        lens_of(camera, None, o),
        (False, True, False),
        depth_m,
        cadastre,
        o,
    )
    ci, sj = fit.ci, fit.sj
    if len(ci) < options.min_inliers:
        return failed, 0.0
    r2 = np.mean(fit.resid**2, axis=1)
    score = float(np.sum(np.maximum(0.0, 1.0 - r2 / o.inlier_threshold_px**2)))
    rms = float(np.sqrt(np.mean(fit.resid**2)))
    plane = fit.plane
    centroid = corner_rel[ci].mean(axis=0)
    new = dataclasses.replace(
        result,
        cam_from_world=fit.view.pose(fit.alpha, fit.c_xy),
        vertical_direction=fit.view.n.copy(),
        vertical_source="refined",
        camera=camera,
        inlier_pairs=np.column_stack([vis[ci], segs.index[sj]]).astype(int),
        inlier_segments_px=seg[segs.index[sj]].copy(),
        height_plane=np.r_[plane[:2], plane[2] - plane[:2] @ c0[:2]],
        ground_height=float(plane[:2] @ centroid + plane[2]),
        num_inliers=len(ci),
        residual_rms_px=rms,
        message=f"{len(ci)} inlier corners with its head's camera, RMS {rms:.2f} px",
    )
    return new, score


def refine_with_camera(
    result: RegistrationResult,
    camera: Camera,
    segments_px: np.ndarray,
    segments_camera: Camera,
    cadastre,
    options: RegistrationOptions,
) -> RegistrationResult:
    """A successful ``result`` refined again with the intrinsics held at
    ``camera`` (its head's): its inliers give the pose with the new camera,
    then the pairs near that pose are scored again and refined as the
    registration's last step does (the pose and the vertical move). A
    focal error biases the inliers themselves: the pairs that fit it are
    kept, those it pushes out are not, so refining the old inliers alone
    leaves most of the error (measured on ``paper``).

    ``segments_px``: the image's (N, 2, 2) vertical segments, undistorted
    pixels of ``segments_camera`` (the frame of the result's
    ``inlier_segments_px``, which the new result keeps). ``success`` False
    when fewer than ``options.min_inliers`` pairs remain.
    """
    return reassociate(result, camera, segments_px, segments_camera, cadastre, options)[
        0
    ]
