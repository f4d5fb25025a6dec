"""The registration overlay: the map drawn on the image before (prior) and
after registration, with the inlier segments and their corners' verticals
(:func:`draw_registration_overlay`)."""

from __future__ import annotations

import math

import numpy as np

from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.registration.options import RegistrationResult

#: BGR colours of the overlay: map before (prior), map after, inlier segments,
#: inlier corners' verticals.
OVERLAY_COLORS = {
    "before": (0, 0, 255),
    "after": (0, 255, 0),
    "segment": (0, 255, 255),
    "corner": (255, 0, 255),
}


def _project_edges(
    cadastre, camera: Camera, pose: Pose, plane_abs: np.ndarray, ground: float
) -> np.ndarray:
    """(E, 2, 2) pixels of the map edges at the ground; NaN when behind."""
    xy = cadastre.edge_xy.reshape(-1, 2)
    if np.all(np.isfinite(plane_abs)):
        z = plane_abs[0] * xy[:, 0] + plane_abs[1] * xy[:, 1] + plane_abs[2]
    else:
        z = np.full(len(xy), ground)
    X = pose.transform(np.column_stack([xy, z]))
    px = camera.img_from_cam(X)
    px[X[:, 2] <= 0] = np.nan
    return px.reshape(-1, 2, 2)


def draw_registration_overlay(
    image: np.ndarray,
    cadastre,
    camera: Camera,
    prior_pose: Pose,
    result: RegistrationResult,
) -> np.ndarray:
    """Draw the map before (prior pose, red) and after registration (green).

    The footprint edges are drawn at the ground (the result's height plane,
    else its ground height), through the camera's distortion; the inlier
    segments are drawn in yellow and their corners' verticals (from the
    ground up, 15 m) in magenta.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 array (BGR).
    cadastre : Cadastre (local frame, as registered).
    camera : Camera, the rough intrinsics used for the registration.
    prior_pose : Pose, the prior ``cam_from_world`` (local frame).
    result : RegistrationResult.

    Returns
    -------
    (H, W, 3) uint8 BGR array, a new image.
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 2:
        out = cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR)
    elif img.ndim == 3 and img.shape[2] == 3:
        out = img.astype(np.uint8).copy()
    else:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
    H, W = out.shape[:2]
    limit = 4.0 * max(H, W)

    def draw(segments: np.ndarray, color, thickness=1) -> None:
        for a, b in segments:
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                continue
            if np.any(np.abs(np.r_[a, b]) > limit):
                continue
            cv2.line(
                out,
                (int(round(a[0])), int(round(a[1]))),
                (int(round(b[0])), int(round(b[1]))),
                color,
                thickness,
                cv2.LINE_AA,
            )

    ground = (
        result.ground_height
        if math.isfinite(result.ground_height)
        else prior_pose.center[2] - 300.0
    )
    draw(
        _project_edges(cadastre, camera, prior_pose, np.full(3, np.nan), ground),
        OVERLAY_COLORS["before"],
    )
    if result.success:
        pose = result.cam_from_world
        draw(
            _project_edges(cadastre, camera, pose, result.height_plane, ground),
            OVERLAY_COLORS["after"],
        )
        corners = result.inlier_pairs[:, 0]
        xy = cadastre.corner_xy[corners]
        p = result.height_plane
        z = p[0] * xy[:, 0] + p[1] * xy[:, 1] + p[2]
        bottom = camera.img_from_cam(pose.transform(np.column_stack([xy, z])))
        top = camera.img_from_cam(pose.transform(np.column_stack([xy, z + 15.0])))
        draw(np.stack([bottom, top], axis=1), OVERLAY_COLORS["corner"])
        seg = result.inlier_segments_px
        if len(seg) and camera.has_distortion:
            # Back to the distorted image.
            uv = (seg.reshape(-1, 2) - camera.K[:2, 2]) / np.diag(camera.K)[:2]
            seg = camera.img_from_cam(np.column_stack([uv, np.ones(len(uv))]))
            seg = seg.reshape(-1, 2, 2)
        draw(seg, OVERLAY_COLORS["segment"], 2)
    return out
