"""The heads (cameras, camera_id) in stage 2: one lens and one focal length
per head from all its images.

* :func:`head_cameras` / :func:`head_pass`: every image registered again
  from its head's median lens and focal (``refine_distortion``).
* :func:`head_focal_pass`: one focal length per head from the consensus of
  all its images, then its images refined with it held
  (``head_focal_min_images``).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from obliq_colmap.geometry import Camera
from obliq_colmap.parallel import WorkerPool
from obliq_colmap.pipeline.options import PipelineOptions
from obliq_colmap.pipeline.workers import (
    ImageTask,
    profile_job,
    refine_job,
    reregister,
    reregister_options,
    set_registration,
)
from obliq_colmap.registration import consensus_peak
from obliq_colmap.state import ImageOutcome

__all__ = ["head_cameras", "head_focal_pass", "head_pass"]

logger = logging.getLogger(__name__)


def head_cameras(
    tasks: Sequence[ImageTask], outcomes: Sequence[ImageOutcome], min_inliers: int
) -> dict[int, Camera]:
    """Per camera_id, the median intrinsics of its images whose stage 2
    refined the lens with at least ``min_inliers`` inlier corners.

    The images of one head share one lens and focal length; one image's
    estimate is weak (focal, k1 and pitch share a near-degenerate mode and
    the priors pull them back), their median much less so.
    """
    params: dict[int, list[np.ndarray]] = {}
    cams: dict[int, Camera] = {}
    for t, o in zip(tasks, outcomes, strict=True):
        r = o.registration
        if r is None or not (r.success and r.distortion_refined):
            continue
        if r.num_inliers < min_inliers or o.camera is None:
            continue
        cid = t.camera.camera_id
        params.setdefault(cid, []).append(o.camera.params)
        cams[cid] = o.camera
    return {
        cid: Camera(
            cams[cid].model,
            cams[cid].width,
            cams[cid].height,
            np.median(np.array(p), axis=0),
            cid,
        )
        for cid, p in params.items()
    }


def head_pass(
    pool: WorkerPool,
    tasks: list[ImageTask],
    outcomes: list[ImageOutcome],
    options: PipelineOptions,
) -> list[str]:
    """Register every image again from its head's median lens and focal
    (:func:`head_cameras`); keep the result with more inlier corners. The
    tasks keep that start (for the rescue). Returns the improved images."""
    heads = head_cameras(tasks, outcomes, options.rescue_min_inliers)
    todo = [
        k
        for k, (t, o) in enumerate(zip(tasks, outcomes, strict=True))
        if o.registration is not None
        and t.camera.camera_id in heads
        and len(o.segments) >= options.registration.min_segments
    ]
    if not todo:
        return []
    logger.info(
        "stage 2 again from the heads' lenses: %s",
        {cid: np.round(c.params, 4).tolist() for cid, c in heads.items()},
    )
    for k in todo:
        tasks[k] = dataclasses.replace(tasks[k], start=heads[tasks[k].camera.camera_id])
    jobs = [
        (tasks[k], outcomes[k].segments, outcomes[k].vertical_direction, None)
        for k in todo
    ]
    tries = pool.map(reregister, jobs, "stage 2, heads' lenses")
    names = []
    for k, new in zip(todo, tries, strict=True):
        old = outcomes[k].registration
        if new.success and (not old.success or new.num_inliers >= old.num_inliers):
            set_registration(outcomes[k], new)
            names.append(outcomes[k].name)
    return names


def _head_profile(
    pool: WorkerPool, jobs: list[tuple], base: Camera, log_scales: np.ndarray
) -> np.ndarray:
    """(G,) sum over a head's images of their consensus with ``base``'s
    focal scaled by ``exp`` of each of (G,) ``log_scales``; ``jobs``:
    (result, segments, segments_camera, options) per image."""
    args = [(j[0], base, np.exp(log_scales), *j[1:]) for j in jobs]
    return np.sum(pool.map(profile_job, args, "heads' focal"), axis=0)


def head_focal_pass(
    pool: WorkerPool,
    tasks: list[ImageTask],
    outcomes: list[ImageOutcome],
    options: PipelineOptions,
) -> dict[int, Camera]:
    """One focal length per head from all its images, then each of its
    registered images refined again with it held.

    One image observes its focal length poorly, and its inliers were chosen
    with the priors' focal, so its refinement keeps most of the priors'
    error, the same for all the images of a head; their median, and any
    pooled estimate from those inliers, keeps it too (measured on
    ``paper``). What the images agree on instead: the consensus (soft inlier
    count) of each image re-scored with a candidate focal held
    (:func:`~obliq_colmap.registration.focal_profile`), summed over the head,
    peaks near the true focal. The peak is searched on a grid of the priors'
    focal sigma (widened when it lies at an end), then refined on a grid of a
    third of it, each by a parabola. A head with fewer than
    ``options.head_focal_min_images`` images with enough inliers keeps the
    per-image results. The tasks of the heads start from the pooled camera
    afterwards (the rescue).

    Returns the heads' cameras (camera_id -> Camera).
    """
    reg = options.registration
    counted = [
        k
        for k, o in enumerate(outcomes)
        if o.registered
        and o.registration.camera is not None
        and o.registration.num_inliers >= reg.min_inliers_intrinsics
    ]
    per_head = Counter(tasks[k].camera.camera_id for k in counted)
    counted = [
        k
        for k in counted
        if per_head[tasks[k].camera.camera_id] >= options.head_focal_min_images
    ]
    if not counted:
        return {}

    def job(k: int) -> tuple:
        o = outcomes[k]
        opts = reregister_options(tasks[k], o.vertical_direction, None)
        return (o.registration, o.segments, tasks[k].camera, opts)

    jobs: dict[int, list[tuple]] = {}
    base: dict[int, Camera] = {}
    for k in counted:
        jobs.setdefault(tasks[k].camera.camera_id, []).append(job(k))
    for cid, js in jobs.items():
        # The images' lens (median), at the priors' focal length.
        cam = js[0][0].camera
        params = np.median(np.array([j[0].camera.params for j in js]), axis=0)
        cam = Camera(cam.model, cam.width, cam.height, params, cid)
        prior = next(t.camera for t in tasks if t.camera.camera_id == cid)
        base[cid] = cam.with_focal_scaled(_mean_focal(prior) / _mean_focal(cam))
    sigma = max(reg.prior_focal_sigma, 0.01)
    heads = {}
    for cid, js in jobs.items():
        profile = functools.partial(_head_profile, pool, js, base[cid])
        peak = consensus_peak(profile, sigma)
        heads[cid] = base[cid].with_focal_scaled(math.exp(peak))
    logger.info(
        "the heads' focal lengths from all their images: %s",
        {cid: round(_mean_focal(c), 1) for cid, c in heads.items()},
    )
    todo = [
        k
        for k, o in enumerate(outcomes)
        if o.registered and tasks[k].camera.camera_id in heads
    ]
    args = []
    for k in todo:
        r, seg, seg_cam, opts = job(k)
        args.append((r, heads[tasks[k].camera.camera_id], seg, seg_cam, opts))
    new = pool.map(refine_job, args, "heads' focal: refine")
    for k, r in zip(todo, new, strict=True):
        if r.success:
            set_registration(outcomes[k], r)
    for k, t in enumerate(tasks):
        if t.camera.camera_id in heads:
            tasks[k] = dataclasses.replace(t, start=heads[t.camera.camera_id])
    return heads


def _mean_focal(camera: Camera) -> float:
    return float(np.mean(np.diag(camera.K)[:2]))
