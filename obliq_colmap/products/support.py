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

__all__ = [
    "across_shift",
    "edge_distance",
    "edge_offsets",
    "edge_support",
    "vertical_edge_distance",
    "vertical_segments",
]


def vertical_segments(
    gray: np.ndarray, camera: Camera, pose: Pose, options: DiscrepancyOptions
) -> np.ndarray:
    """(N, 2, 2) the image's line segments (raw, distorted px) that point at
    its vertical VP (from the pose: the image of the world's z axis), at
    least ``min_length_px`` long."""
    raw = detect_segments(gray).endpoints  # (N, 2, 2) distorted px
    # the VP test on undistorted ends; the segments kept in raw pixels
    # (where the model's projections land)
    segs = camera.undistort_pixels(raw.reshape(-1, 2)).reshape(-1, 2, 2)
    v = camera.K @ (pose.rotation @ np.array([0.0, 0.0, 1.0]))  # homogeneous VP
    mid = np.column_stack([segs.mean(axis=1), np.ones(len(segs))])
    line = np.cross(mid, v)
    line /= np.linalg.norm(line[:, :2], axis=1, keepdims=True) + 1e-12
    ends = np.concatenate([segs, np.ones((len(segs), 2, 1))], axis=2)
    dist = np.abs(np.einsum("nkj,nj->nk", ends, line)).max(axis=1)
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
    keep = (dist <= options.vertical_tol_px) & (length >= options.min_length_px)
    return raw[keep]


def edge_distance(shape: tuple[int, int], segments: np.ndarray) -> np.ndarray:
    """(H, W) float32 distance (px) to the nearest of ``segments`` (N, 2, 2)
    drawn into an image of ``shape`` (H, W)."""
    mask = np.full(shape, 255, np.uint8)
    for a, b in np.round(segments).astype(int):  # a few hundred segments
        cv2.line(mask, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 0, 1)
    return cv2.distanceTransform(mask, cv2.DIST_L2, 3)


def vertical_edge_distance(
    gray: np.ndarray, camera: Camera, pose: Pose, options: DiscrepancyOptions
) -> np.ndarray:
    """(H, W) float32 distance (px) to the nearest segment through the
    image's vertical VP (:func:`vertical_segments`)."""
    return edge_distance(gray.shape[:2], vertical_segments(gray, camera, pose, options))


def edge_offsets(
    camera: Camera,
    pose: Pose,
    segments: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    window_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Where each corner's vertical edge lies across the image of the
    corner's vertical, below a pixel.

    The shift grid reads the edges through a distance map of whole pixels
    with a tolerance of ``support_px``: a building's best shift scatters by
    ~0.2 m (1.5 px) about the truth where the segments themselves are good
    to a few tenths of a pixel.

    Parameters
    ----------
    segments : (N, 2, 2) the image's vertical segments (:func:`vertical_segments`).
    bottom, top : (K, 3) the ends of each corner's vertical (model frame).
    window_px : a segment is this corner's when both its ends lie within
        this across the image line and it overlaps it along it.

    Returns
    -------
    offset : (K,) signed distance (px) of the nearest such segment (the mean
        of its ends) across the line; NaN where none.
    jac : (K, 2) how far the line moves across itself (px) per metre of a
        horizontal shift of the corner in x and y.
    """
    a = camera.img_from_cam(pose.transform(bottom))
    b = camera.img_from_cam(pose.transform(top))
    d = b - a
    length = np.linalg.norm(d, axis=1)
    d /= length[:, None] + 1e-12
    n = np.column_stack([-d[:, 1], d[:, 0]])  # across, (K, 2)
    offset = np.full(len(a), np.nan)
    # corners x segments x ends in chunks: a 4,000 px image holds thousands
    # of segments
    for k in range(0, len(a) if len(segments) else 0, 256):
        c = slice(k, k + 256)
        rel = segments[None] - a[c, None, None, :]  # (k, N, 2 ends, 2)
        across = np.einsum("knej,kj->kne", rel, n[c])
        along = np.einsum("knej,kj->kne", rel, d[c])
        mine = (
            (np.abs(across) <= window_px).all(axis=2)
            & (along.max(axis=2) >= 0)
            & (along.min(axis=2) <= length[c, None])
        )
        off = np.where(mine, across.mean(axis=2), np.inf)  # (k, N)
        best = off[np.arange(len(off)), np.abs(off).argmin(axis=1)]
        offset[c] = np.where(np.isfinite(best), best, np.nan)
    mid = 0.5 * (bottom + top)
    q0 = camera.img_from_cam(pose.transform(mid))
    jac = np.empty((len(a), 2))
    for axis in (0, 1):
        step = np.zeros(3)
        step[axis] = 0.1
        q = camera.img_from_cam(pose.transform(mid + step))
        jac[:, axis] = np.einsum("kj,kj->k", q - q0, n) / 0.1
    return offset, jac


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


def edge_support(
    task: dict,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
    segments : (N, 2, 2) its vertical segments (:func:`vertical_segments`),
        for the shift's fit below the grid (:func:`edge_offsets`).
    """
    img, _ = read_image(task["path"])
    cam, pose, o = task["camera"], task["pose"], task["options"]
    if img is None:
        S = len(task["shifts"])
        return (
            np.zeros(0, int),
            np.zeros((0, S), int),
            np.zeros((0, S), bool),
            np.zeros((0, 2, 2)),
        )
    segments = vertical_segments(img, cam, pose, o)
    dmap = edge_distance(img.shape[:2], segments)
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
    return k, sup, across, segments
