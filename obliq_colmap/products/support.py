"""The images' support of the map's corners: vertical edges at the final
poses (:func:`vertical_edge_distance`) sampled along each corner's vertical
under a grid of footprint shifts (:func:`edge_support`, one image per call,
run in worker processes by :func:`~.discrepancies.find_discrepancies`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.images import read_image
from obliq_colmap.lines import detect_segments

if TYPE_CHECKING:
    from obliq_colmap.products.discrepancy_options import DiscrepancyOptions

__all__ = ["across_shift", "edge_support", "vertical_edge_distance"]


def vertical_edge_distance(
    gray: np.ndarray, camera: Camera, pose: Pose, options: DiscrepancyOptions
) -> np.ndarray:
    """(H, W) float32 distance (px) to the nearest segment through the
    image's vertical VP (from the pose: the image of the world's z axis)."""
    raw = detect_segments(gray).endpoints  # (N, 2, 2) distorted px
    # the VP test on undistorted ends, the edge map in raw pixels (where the
    # model's projections land).
    segs = camera.undistort_pixels(raw.reshape(-1, 2)).reshape(-1, 2, 2)
    v = camera.K @ (pose.rotation @ np.array([0.0, 0.0, 1.0]))  # homogeneous VP
    mid = np.column_stack([segs.mean(axis=1), np.ones(len(segs))])
    line = np.cross(mid, v)
    line /= np.linalg.norm(line[:, :2], axis=1, keepdims=True) + 1e-12
    ends = np.concatenate([segs, np.ones((len(segs), 2, 1))], axis=2)
    dist = np.abs(np.einsum("nkj,nj->nk", ends, line)).max(axis=1)
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
    keep = (dist <= options.vertical_tol_px) & (length >= options.min_length_px)
    mask = np.full(gray.shape[:2], 255, np.uint8)
    for a, b in np.round(raw[keep]).astype(int):  # a few hundred segments
        cv2.line(mask, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 0, 1)
    return cv2.distanceTransform(mask, cv2.DIST_L2, 3)


def across_shift(
    camera: Camera, pose: Pose, base: np.ndarray, moved: np.ndarray
) -> np.ndarray:
    """(K, S) image distance (px) of each moved point from the image of the
    vertical through its base point, across that image line.

    base : (K, 3) a point on each corner's vertical; moved : (K, S, 3) the
    same point under each shift. A horizontal shift along the view moves the
    vertical's image along itself (the same as a change of height, which an
    unknown eave cannot tell apart); only the part across it is evidence of
    a shift.
    """
    top = base + np.array([0.0, 0.0, 1.0])
    a = camera.img_from_cam(pose.transform(base))
    b = camera.img_from_cam(pose.transform(top))
    d = b - a
    d /= np.linalg.norm(d, axis=1, keepdims=True) + 1e-12
    K, S = moved.shape[:2]
    q = camera.img_from_cam(pose.transform(moved.reshape(-1, 3))).reshape(K, S, 2)
    r = q - a[:, None]
    return np.abs(r[..., 0] * d[:, None, 1] - r[..., 1] * d[:, None, 0])


def edge_support(task: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One image's support of every corner it should see, under every shift.

    ``task``: image file, camera, pose, options, and the map's arrays:
    corner_xy (C, 2), corner_wall_normals (C, 2, 2), corner_z0 / z1 (C,)
    (the sampled height range), shifts (S, 2).

    Returns
    -------
    corners : (K,) int, the corners the image should see.
    supported : (K, S) int, supported samples per corner and shift.
    across : (K, S) bool, the shift moves the corner's vertical across its
        image by more than ``across_px`` (:func:`across_shift`).
    """
    img, _ = read_image(task["path"])
    cam, pose, o = task["camera"], task["pose"], task["options"]
    if img is None:
        S = len(task["shifts"])
        return np.zeros(0, int), np.zeros((0, S), int), np.zeros((0, S), bool)
    dmap = vertical_edge_distance(img, cam, pose, o)
    xy, n = task["corner_xy"], task["corner_wall_normals"]
    c = pose.center
    facing = ((c[None, None, :2] - xy[:, None, :]) * n).sum(-1).max(axis=1) > 0
    t = (np.arange(o.num_samples) + 0.5) / o.num_samples
    z = (
        task["corner_z0"][:, None]
        + t[None] * (task["corner_z1"] - task["corner_z0"])[:, None]
    )
    Xc = pose.transform(np.column_stack([xy, z[:, o.num_samples // 2]]))
    px = cam.img_from_cam(Xc)
    H, W = dmap.shape
    inside = (
        (Xc[:, 2] > 0)
        & (px[:, 0] >= 0)
        & (px[:, 0] < W)
        & (px[:, 1] >= 0)
        & (px[:, 1] < H)
    )
    k = np.flatnonzero(facing & inside & np.isfinite(z).all(axis=1))
    S = task["shifts"]
    P = np.empty((len(k), len(S), o.num_samples, 3))
    P[..., :2] = xy[k, None, None, :] + S[None, :, None, :]
    P[..., 2] = z[k, None, :]
    q = cam.img_from_cam(pose.transform(P.reshape(-1, 3)))
    col = np.clip(np.floor(q[:, 0]), -1, W).astype(int)
    row = np.clip(np.floor(q[:, 1]), -1, H).astype(int)
    ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    d = np.full(len(q), np.inf, np.float32)
    d[ok] = dmap[row[ok], col[ok]]
    sup = (d <= o.support_px).reshape(len(k), len(S), o.num_samples).sum(axis=2)
    mid = P[:, :, o.num_samples // 2]  # (K, S, 3)
    across = across_shift(cam, pose, mid[:, 0], mid) > o.across_px
    return k, sup, across
