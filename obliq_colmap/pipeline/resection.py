"""Images placed by their tie points in the solved block (the start of their
second registration).

An image that stage 2 could not register (few building corners with
vertical edges: low-rise houses, facades in shadow) still shares ground
texture with its neighbours. Its tie observations of tracks that the solved
block triangulates give 2D-3D pairs, and pycolmap's absolute pose (LO-RANSAC
and refinement, the head's solved camera) places it; that pose, far better
than its prior, is the start of its registration against the map
(:func:`~obliq_colmap.pipeline.block.reregister_failed`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

import numpy as np
import pycolmap

from obliq_colmap.adjustment import TiePointOptions, TiePoints, tie_points
from obliq_colmap.adjustment.ties import reprojection_errors, triangulate_tie_tracks
from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.pipeline.workers import ImageTask
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = ["block_tie_points", "tie_resections"]

logger = logging.getLogger(__name__)

#: A resection needs this many inlier tie observations, and this share of
#: the image's pairs (a wrong pose explains few).
MIN_INLIERS = 30
MIN_INLIER_RATIO = 0.5
#: Tracks triangulated in the block are kept within this reprojection error
#: (px) in every block image that sees them.
MAX_TRACK_ERROR_PX = 2.0


def block_tie_points(
    inputs: Inputs,
    state: BlockState,
    tasks: Sequence[ImageTask],
    outcomes: Sequence[ImageOutcome],
    options: TiePointOptions,
) -> TiePoints:
    """SIFT tie points of the registered images and of the failed ones that
    were read (their tracks; the bundle triangulates them). Pairs are chosen
    from the per-image poses, a failed image's from its prior."""
    failed = {
        t.image_id: t
        for t, o in zip(tasks, outcomes, strict=True)
        if t.image_id not in state.poses and o.status != "unreadable"
    }
    ids = sorted(state.poses) + sorted(failed)
    # paths: the SIFT workers read (and down-sample) the images themselves
    files = [inputs.image_path / inputs.priors.images[i].name for i in ids]

    def camera(i: int) -> Camera:
        return (
            state.cameras[i]
            if i in state.poses
            else failed[i].start or failed[i].camera
        )

    def pose(i: int) -> Pose:
        return state.poses[i] if i in state.poses else failed[i].prior

    ground = state.ground_height()
    # No reprojection test at these poses: they are what the bundle corrects
    # (houses-102: 549 of ~2,600 points would pass at 3 px).
    unchecked = dataclasses.replace(options, max_reproj_error_px=math.inf)
    ties = tie_points(
        files,
        [camera(i).to_pycolmap() for i in ids],
        [pose(i).to_rigid3d() for i in ids],
        ground,
        unchecked,
    )
    return dataclasses.replace(ties, image_ids=tuple(ids))


def tie_resections(
    state: BlockState,
    ties: TiePoints,
    todo: dict[int, Camera],
    chained: frozenset[int] = frozenset(),
) -> dict[int, Pose]:
    """Per image of ``todo`` (image id -> its head's camera) its
    ``cam_from_world`` from its tie observations of the tracks the solved
    block ``state`` triangulates (at least two of its images, within
    :data:`MAX_TRACK_ERROR_PX` in each), where the absolute pose has at least
    :data:`MIN_INLIERS` inliers and :data:`MIN_INLIER_RATIO` of the pairs.

    ``chained``: images of ``todo`` that join the block once placed, so that
    their tracks place the rest in another round (a head that has no image in
    the block, the nadir camera of a five-camera system: its images overlap
    each other more than the oblique ones).
    """
    poses, cameras = dict(state.poses), dict(state.cameras)
    out: dict[int, Pose] = {}
    while True:
        placed = _resect_once(
            poses, cameras, ties, {i: c for i, c in todo.items() if i not in out}
        )
        out.update(placed)
        grown = {i: p for i, p in placed.items() if i in chained}
        if not grown:
            return out
        poses.update(grown)
        cameras.update({i: todo[i] for i in grown})


def _resect_once(
    poses: dict[int, Pose],
    cameras: dict[int, Camera],
    ties: TiePoints,
    todo: dict[int, Camera],
) -> dict[int, Pose]:
    """One round of :func:`tie_resections` against the block ``poses``."""
    ids = np.asarray(ties.image_ids)
    obs_id = ids[ties.obs_image] if len(ids) else np.zeros(0, np.int64)
    block = np.isin(obs_id, list(poses))
    if not todo or block.sum() < 2:
        return {}
    # the block's images, in a local order
    local = sorted(set(obs_id[block].tolist()))
    pos = {i: k for k, i in enumerate(local)}
    img = np.array([pos[i] for i in obs_id[block]], np.int64)
    track = ties.obs_point[block]
    seen = np.bincount(track, minlength=int(ties.obs_point.max()) + 1)
    two = seen[track] >= 2
    img, track, xy = img[two], track[two], ties.obs_xy[block][two]
    if len(track) == 0:
        return {}
    used, t_local = np.unique(track, return_inverse=True)
    cams = [cameras[i].to_pycolmap() for i in local]
    rigs = [poses[i].to_rigid3d() for i in local]
    xyz = triangulate_tie_tracks(cams, rigs, t_local, img, xy)
    err = reprojection_errors(cams, rigs, xyz, t_local, img, xy)
    worst = np.zeros(len(used))
    np.maximum.at(worst, t_local, np.where(np.isfinite(err), err, np.inf))
    good = worst <= MAX_TRACK_ERROR_PX
    point_of = np.full(len(seen), -1)
    point_of[used[good]] = np.flatnonzero(good)
    # A seeded RANSAC: unseeded, pycolmap draws from its thread's generator,
    # whose state is whatever the process ran before (houses-102, stage-2
    # seed 1: an image written 169 px off or left out depending on the scene
    # run before it in the same process).
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.random_seed = 0
    out = {}
    for image_id, camera in todo.items():
        mine = (obs_id == image_id) & (point_of[ties.obs_point] >= 0)
        n = int(mine.sum())
        if n < MIN_INLIERS:
            continue
        X = xyz[point_of[ties.obs_point[mine]]]
        found = pycolmap.estimate_and_refine_absolute_pose(
            ties.obs_xy[mine], X, camera.to_pycolmap(), estimation
        )
        if found is None:
            continue
        k = int(found["num_inliers"])
        if k >= MIN_INLIERS and k >= MIN_INLIER_RATIO * n:
            out[image_id] = Pose.from_rigid3d(found["cam_from_world"])
            logger.info(
                "image %d placed by %d of its %d tie observations in the block",
                image_id,
                k,
                n,
            )
    return out
