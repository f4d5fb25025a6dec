"""Stages 1 and 2 over the block (``register --stop_after initial``):
:func:`initial_stage` runs every image's vanishing point and registration in
the worker pool, the heads' passes (:mod:`~obliq_colmap.pipeline.heads`) and
the rescue of weak images from the block's ground heights
(:func:`rescue_heights`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence

import numpy as np

from obliq_colmap.parallel import WorkerPool
from obliq_colmap.pipeline.heads import head_focal_pass, head_pass
from obliq_colmap.pipeline.options import PipelineOptions
from obliq_colmap.pipeline.workers import (
    ImageTask,
    chance_checked,
    initial_image,
    reregister,
    set_registration,
)
from obliq_colmap.registration import RegistrationResult, radial_index
from obliq_colmap.state import ImageOutcome

__all__ = ["initial_stage", "rescue_heights"]

logger = logging.getLogger(__name__)


def initial_stage(
    pool: WorkerPool,
    tasks: list[ImageTask],
    options: PipelineOptions,
    timings: dict[str, float],
) -> tuple[list[ImageOutcome], list[RegistrationResult | None], list[str]]:
    """Stages 1 and 2 of every image, as ``register --stop_after initial``:
    the vanishing point and the registration per image, the pass from the
    heads' lenses (``refine_distortion``), the heads' focal lengths from all
    their images (:func:`head_focal_pass`), the rescue of weak images.

    ``tasks`` may be changed (the head pass sets their start camera);
    ``timings`` gets the wall time of each step (s).

    Returns
    -------
    The outcomes (one per task, in order), the registration of each after its
    first pass alone (None: unreadable), and the names of the rescued images.
    """
    t0 = time.perf_counter()
    outcomes = pool.map(initial_image, tasks, "vanishing + registration")
    timings["initial"] = time.perf_counter() - t0
    # set_registration replaces, never mutates: these stay the first pass's.
    first_pass = [o.registration for o in outcomes]
    if options.registration.refine_distortion and any(
        radial_index(t.result_camera.model) is not None for t in tasks
    ):
        t0 = time.perf_counter()
        head_pass(pool, tasks, outcomes, options)
        timings["head_pass"] = time.perf_counter() - t0
    if options.head_focal_min_images > 0:
        t0 = time.perf_counter()
        head_focal_pass(pool, tasks, outcomes, options)
        timings["head_focal"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rescued = _rescue(pool, tasks, outcomes, options)
    timings["rescue"] = time.perf_counter() - t0
    return outcomes, first_pass, rescued


def rescue_heights(
    results: Sequence[RegistrationResult], min_inliers: int, step_m: float
) -> np.ndarray:
    """Candidate ground heights for a weak image: those of the confident ones.

    One image's ground height is only as good as its focal length and tilt (a
    3 % focal error moves the camera ~3 % of the viewing distance along its
    axis, i.e. tens of metres in height at 45 deg), so the confident images of
    a block spread by +-20 m around the true datum. Each of their heights,
    merged within ``step_m``, is a plausible start for a weak image.

    Returns
    -------
    (K,) sorted heights (m), empty when no result is confident.
    """
    h = np.sort(
        [
            r.ground_height
            for r in results
            if r.success
            and r.num_inliers >= min_inliers
            and math.isfinite(r.ground_height)
        ]
    )
    if len(h) == 0:
        return h
    keep = np.concatenate([[True], np.diff(h) > step_m])
    groups = np.cumsum(keep) - 1
    return np.bincount(groups, h) / np.bincount(groups)


def _rescue(
    pool: WorkerPool,
    tasks: list[ImageTask],
    outcomes: list[ImageOutcome],
    options: PipelineOptions,
) -> list[str]:
    """Register weak images again from the block's ground heights; keep the best."""
    if options.rescue_min_inliers <= 0:
        return []
    results = [o.registration for o in outcomes if o.registration is not None]
    heights = rescue_heights(
        results, options.rescue_min_inliers, options.registration.coarse_height_step_m
    )
    weak = [
        i
        for i, o in enumerate(outcomes)
        if o.registration is not None
        and o.registration.num_inliers < options.rescue_min_inliers
        and len(o.segments) >= options.registration.min_segments
    ]
    if not weak or len(heights) == 0:
        return []
    logger.info(
        "%d weak image(s) registered again from the block's ground heights %s m",
        len(weak),
        np.round(heights, 1).tolist(),
    )
    # The tries go untested; only each image's best meets the chance test
    # (each test costs a few searches).
    untested = {
        i: dataclasses.replace(
            tasks[i],
            registration=dataclasses.replace(tasks[i].registration, chance_trials=0),
        )
        for i in weak
    }
    jobs = [
        (untested[i], outcomes[i].segments, outcomes[i].vertical_direction, float(h))
        for i in weak
        for h in heights
    ]
    tries = pool.map(reregister, jobs, "rescue")
    checks = []
    for k, i in enumerate(weak):
        mine = tries[k * len(heights) : (k + 1) * len(heights)]
        mine = list(zip(heights, mine, strict=True))
        h, best = max(mine, key=lambda hr: (hr[1].success, hr[1].num_inliers))
        old = outcomes[i].registration
        if best.success and (not old.success or best.num_inliers > old.num_inliers):
            o = outcomes[i]
            checks.append(
                (i, (tasks[i], o.segments, o.vertical_direction, float(h), best))
            )
    tested = pool.map(chance_checked, [c[1] for c in checks], "rescue: chance test")
    names = []
    for (i, _), best in zip(checks, tested, strict=True):
        old = outcomes[i].registration
        if best.success and (not old.success or best.num_inliers > old.num_inliers):
            set_registration(outcomes[i], best)
            outcomes[i].rescued = True
            names.append(outcomes[i].name)
    return names
