"""Ground truth measured against the z-buffer: visible corners, vertical edges, VP.

Visibility of a 3D point is a depth test against the rendered z-buffer of the
true camera: the point (or, for an edge or corner, a point 0.25-0.3 m from it
on an adjacent wall) is visible when its camera depth is at most the z-buffer
depth at its pixel plus a tolerance of ``max(0.5 m, 3 pixel footprints)``.
"""

from __future__ import annotations

import numpy as np

from obliq_colmap.geometry import Camera, Pose, project

EDGE_KINDS = ("corner", "texture", "clutter")


def depth_tolerance(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """Depth-test tolerance (m) at camera depths ``depth`` (m)."""
    return np.maximum(0.5, 3.0 * depth / camera.K[0, 0])


def within_field(camera: Camera, pose: Pose, points: np.ndarray) -> np.ndarray:
    """(N,) bool: in front and inside the image's field in UNDISTORTED terms.

    A wide lens's radial polynomial folds points far outside the field back
    into the image (SIMPLE_RADIAL with k = -0.03 beyond ~73 deg off axis, a
    street camera's neighbours), so the pixel test alone is not enough.
    """
    X = pose.transform(np.asarray(points, float).reshape(-1, 3))
    W, H = camera.width, camera.height
    edge = camera.cam_from_img(np.array([[0, 0], [W, 0], [W, H], [0, H], [W / 2, 0]]))
    r_max = 1.01 * np.linalg.norm(edge, axis=1).max()
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.linalg.norm(X[:, :2] / X[:, 2:], axis=1)
    return (X[:, 2] > 0) & (r <= r_max)


def points_visible(
    camera: Camera, pose: Pose, zbuffer: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Depth test of (N, 3) local points against a (H, W) z-buffer.

    Returns
    -------
    visible : (N,) bool, inside the image, in front and not occluded.
    pixels : (N, 2) projections (COLMAP pixel convention).
    """
    xy, z = project(camera, pose, points)
    H, W = zbuffer.shape
    with np.errstate(invalid="ignore"):
        inside = (
            (z > 0)
            & (xy[:, 0] >= 0)
            & (xy[:, 0] < W)
            & (xy[:, 1] >= 0)
            & (xy[:, 1] < H)
        )
    if camera.has_distortion:
        inside &= within_field(camera, pose, points)
    vis = np.zeros(len(points), bool)
    i = np.nonzero(inside)[0]
    col = np.floor(xy[i, 0]).astype(int)
    row = np.floor(xy[i, 1]).astype(int)
    zb = zbuffer[row, col]
    vis[i] = z[i] <= zb + depth_tolerance(camera, z[i])
    return vis, xy


def visible_corners(
    corners: dict, camera: Camera, pose: Pose, zbuffer: np.ndarray
) -> np.ndarray:
    """Indices of the corners visible in one image.

    A corner is visible when it projects into the image and a point on one
    of its two adjacent walls, 0.3 m from the corner along the wall and 0.3 m
    towards the wall's interior vertically (up for ground corners, down for
    eave corners), passes the depth test.

    Parameters
    ----------
    corners : dict of :func:`obliq_colmap.synthetic.city.corners` (local).

    Returns
    -------
    (K,) int array of corner indices.
    """
    xyz = corners["xyz"]
    if len(xyz) == 0:
        return np.zeros(0, int)
    kinds = np.asarray(corners["kind"])
    dz = np.where(kinds == "ground", 0.3, np.where(kinds == "eave", -0.3, 0.0))
    xy, _ = project(camera, pose, xyz)
    H, W = zbuffer.shape
    with np.errstate(invalid="ignore"):
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
    if camera.has_distortion:
        inside &= within_field(camera, pose, xyz)
    vis = np.zeros(len(xyz), bool)
    for d in (corners["dir_a"], corners["dir_b"]):
        sample = xyz + np.column_stack([0.3 * d, dz])
        v, _ = points_visible(camera, pose, zbuffer, sample)
        vis |= v
    return np.nonzero(vis & inside)[0]


def vertical_edge_segments(
    edges: dict,
    camera: Camera,
    pose: Pose,
    zbuffer: np.ndarray,
    min_length_px: float = 4.0,
    step_px: float = 1.0,
) -> dict:
    """Visible image segments of 3D vertical edges.

    Each edge is sampled about every ``step_px`` pixels; every sample is
    depth-tested (edges between two faces on a point 0.25 m into each
    adjacent face, either suffices; edges inside a face on the point itself);
    runs of consecutive visible samples become segments.

    Parameters
    ----------
    edges : dict of :func:`obliq_colmap.synthetic.city.vertical_edges` (local).

    Returns
    -------
    dict with ``segments`` (M, 2, 2) image pixels (distorted, as rendered),
    ``segments_undistorted`` (M, 2, 2) pixels of the pinhole part ``K``,
    ``kind`` (M,) str array of "corner" / "texture" / "clutter",
    ``edge_index`` (M,) int into ``edges``, ``points3D`` (M, 2, 3) local
    end points.
    """
    p0, p1 = edges["p0"], edges["p1"]
    H, W = zbuffer.shape
    xy0, z0 = project(camera, pose, p0)
    xy1, z1 = project(camera, pose, p1)
    with np.errstate(invalid="ignore"):
        front = (z0 > 0) & (z1 > 0)
        lo, hi = np.minimum(xy0, xy1), np.maximum(xy0, xy1)
        cand = (
            front & (hi[:, 0] >= 0) & (lo[:, 0] < W) & (hi[:, 1] >= 0) & (lo[:, 1] < H)
        )
    idx = np.nonzero(cand)[0]
    length = np.linalg.norm(xy1[idx] - xy0[idx], axis=1)
    n = np.clip(np.ceil(length / step_px).astype(int) + 1, 2, 4000)
    e = np.repeat(idx, n)
    k = np.arange(len(e)) - np.repeat(np.cumsum(n) - n, n)
    t = k / np.repeat(n - 1, n)
    P = p0[e] + t[:, None] * (p1[e] - p0[e])
    da, db = edges["dir_a"][e], edges["dir_b"][e]
    inner = np.linalg.norm(da, axis=1) == 0
    vis = np.zeros(len(P), bool)
    v, xy = points_visible(camera, pose, zbuffer, P)
    vis[inner] = v[inner]
    for d in (da, db):
        off = np.column_stack([0.25 * d, np.zeros(len(d))])
        vv, _ = points_visible(camera, pose, zbuffer, P + off)
        vis |= vv & ~inner
    with np.errstate(invalid="ignore"):
        vis &= (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
    same_prev = np.r_[False, e[1:] == e[:-1]]
    same_next = np.r_[e[:-1] == e[1:], False]
    prev_vis = np.r_[False, vis[:-1]] & same_prev
    next_vis = np.r_[vis[1:], False] & same_next
    starts = np.nonzero(vis & ~prev_vis)[0]
    ends = np.nonzero(vis & ~next_vis)[0]
    seg = np.stack([xy[starts], xy[ends]], 1)  # (M, 2, 2)
    keep = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) >= min_length_px
    starts, ends, seg = starts[keep], ends[keep], seg[keep]
    und = camera.undistort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
    kinds = np.asarray(EDGE_KINDS)[edges["kind"][e[starts]]]
    return {
        "segments": seg,
        "segments_undistorted": und,
        "kind": kinds,
        "edge_index": e[starts],
        "points3D": np.stack([P[starts], P[ends]], 1),
    }


def vertical_vp(camera: Camera, pose: Pose) -> np.ndarray:
    """(3,) homogeneous vertical vanishing point, unit norm, in UNDISTORTED pixels.

    The image of the world up direction ``K R (0, 0, 1)`` (the same point as
    the image of the nadir); the sign is chosen so that the third component is
    non-negative when it is not zero.
    """
    v = camera.K @ pose.rotation @ np.array([0.0, 0.0, 1.0])
    v = v / np.linalg.norm(v)
    return -v if v[2] < 0 else v
