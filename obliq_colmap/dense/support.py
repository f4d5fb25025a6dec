"""Depth-range support for images with too few points of their own.

COLMAP's MVS takes an image's depth range only from the points whose track
includes the image. ``register`` observes its points in every image where
they project and may be visible; an image can still end up with few (the
block's edge, a track dropped by the bundle). There the block's other points
that project into the image, in front of it, are added to its observations
in the workspace's copy of the model: the same rule ``register`` applies to
map corners (occlusion by buildings is not tested), so the depth range and
the shared points COLMAP derives come from the block's own 3D points.
"""

from __future__ import annotations

import numpy as np

from obliq_colmap.colmap_io import Block, Point3D

__all__ = ["add_frustum_support", "read_points"]


def read_points(rec) -> list[Point3D]:
    """The points3D of a ``pycolmap.Reconstruction`` with their tracks at
    their measured pixels and their colours."""
    points = []
    for point in rec.points3D.values():
        obs = [
            (
                int(el.image_id),
                np.array(rec.images[el.image_id].points2D[el.point2D_idx].xy),
            )
            for el in point.track.elements
        ]
        points.append(Point3D(np.array(point.xyz), obs, np.array(point.color)))
    return points


def _in_frustum(
    block: Block, image_id: int, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Points X (N, 3) that project inside the image, in front of it:
    ((K,) indices, (K, 2) pixels)."""
    im = block.images[image_id]
    cam = block.cameras[im.camera_id]
    Xc = im.cam_from_world.transform(X)
    front = Xc[:, 2] > 0
    px = np.full((len(X), 2), np.nan)
    px[front] = cam.img_from_cam(Xc[front])
    ok = front & np.all(np.isfinite(px), axis=1)
    ok[ok] = (
        (px[ok, 0] >= 0)
        & (px[ok, 1] >= 0)
        & (px[ok, 0] <= cam.width)
        & (px[ok, 1] <= cam.height)
    )
    keep = np.flatnonzero(ok)
    return keep, px[keep]


def add_frustum_support(
    block: Block, points: list[Point3D], image_ids: list[int]
) -> dict[int, int]:
    """Observe, in each image of ``image_ids``, the points that project into
    it and do not have it in their track yet (``points`` changed in place).

    Returns image id -> number of observations added.
    """
    if not points:
        return {i: 0 for i in image_ids}
    X = np.array([p.xyz for p in points])
    added = {}
    for i in image_ids:
        keep, px = _in_frustum(block, i, X)
        n = 0
        for k, xy in zip(keep, px, strict=True):
            if all(j != i for j, _ in points[k].observations):
                points[k].observations.append((i, xy))
                n += 1
        added[i] = n
    return added
