"""The ``register`` run: :func:`run_register`, from the inputs to a
:class:`~obliq_colmap.pipeline.output.RunResult` (not yet written).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np

from obliq_colmap import __version__
from obliq_colmap.adjustment import Stage3
from obliq_colmap.bundle import BundleResult
from obliq_colmap.colmap_io import Georef, Point3D
from obliq_colmap.errors import InputError
from obliq_colmap.pipeline.block import block_stage
from obliq_colmap.pipeline.initial import initial_stage
from obliq_colmap.pipeline.inputs import image_tasks, load_inputs
from obliq_colmap.pipeline.options import PipelineOptions
from obliq_colmap.pipeline.output import (
    RunResult,
    bundle_tie_records,
    color_points,
    constrained_points,
    result_block,
    run_report,
    tie_point_records,
)
from obliq_colmap.pipeline.overlays import STAGE2_FOLDER, final_overlays
from obliq_colmap.pipeline.verdicts import warn_unconfirmed_vertical
from obliq_colmap.pipeline.workers import draw_overlay, worker_pool
from obliq_colmap.registration import block_ground_height
from obliq_colmap.state import BlockState

__all__ = ["run_register"]

logger = logging.getLogger(__name__)


def run_register(
    image_path: str | Path,
    cadastre_path: str | Path,
    input_path: str | Path,
    options: PipelineOptions | None = None,
) -> RunResult:
    """Register a block of oblique images to a footprint map.

    Parameters
    ----------
    image_path : folder of the images (names as in the priors).
    cadastre_path : GeoJSON footprint map (projected metric CRS).
    input_path : COLMAP priors model (rough poses in the map's frame).
    options : PipelineOptions.

    Returns
    -------
    RunResult, to be written with :func:`~obliq_colmap.pipeline.write_run`.

    Raises
    ------
    InputError
        User mistakes in the inputs.
    """
    options = options or PipelineOptions()
    t_run = time.perf_counter()
    timings: dict[str, float] = {}
    inputs = load_inputs(image_path, cadastre_path, input_path, options)
    cad = inputs.cadastre
    tasks = image_tasks(inputs, options)
    logger.info(
        "%d images, %d cameras, map: %d buildings, %d corners (origin %s, %s)",
        len(tasks),
        len(inputs.cameras),
        cad.num_buildings,
        cad.num_corners,
        cad.origin[:2].tolist(),
        cad.crs,
    )
    origin3 = np.array([cad.origin[0], cad.origin[1], 0.0])
    init_args = (inputs.cadastre_path, inputs.cadastre_options, origin3)
    workers = min(options.workers, len(tasks))
    with worker_pool(
        workers, init_args, cad, options.progress, options.dask_scheduler
    ) as pool:
        outcomes, _, rescued = initial_stage(pool, tasks, options, timings)
        starts = {t.image_id: t.start for t in tasks}  # the head pass sets them
        if outcomes and all(o.status == "unreadable" for o in outcomes):
            # a folder of which no image reads is the user's input, not a
            # failed registration
            raise InputError(
                image_path,
                f"none of its {len(outcomes)} images can be read, e.g."
                f" {outcomes[0].message}",
            )
        for o in outcomes:
            if o.status == "unreadable" or not o.registered:
                logger.warning("%s: left out: %s", o.name, o.message)
        if options.overlay_path is not None:
            folder = Path(options.overlay_path) / STAGE2_FOLDER
            folder.mkdir(parents=True, exist_ok=True)
            jobs = [
                (t, o.registration, folder)
                for t, o in zip(tasks, outcomes, strict=True)
                if o.registration is not None
            ]
            pool.map(draw_overlay, jobs, "overlays")
    by_id = {o.image_id: o for o in outcomes}
    bundle_result: BundleResult | None = None
    stage3: Stage3 | None = None
    reregistered: list[str] = []
    if options.stop_after == "bundle" and any(o.registered for o in outcomes):
        state, bundle_result, stage3, reregistered = block_stage(
            inputs, tasks, outcomes, options, timings, (workers, init_args)
        )
    else:
        warn_unconfirmed_vertical(outcomes)
        state = BlockState.from_outcomes([o for o in outcomes if o.registered])
    registered = [o for o in outcomes if o.registered]
    ground = block_ground_height([o.registration for o in registered], 1)
    z0 = float(np.round(ground)) if ground is not None else 0.0
    georef = Georef(
        origin=np.array([cad.origin[0], cad.origin[1], z0]),
        crs=cad.crs,
        extra={
            "vertical_datum": "the priors' (input_path) heights, unchanged",
            "software": f"obliq-colmap {__version__}",
        },
    )
    block = result_block(inputs, state)
    if options.overlay_path is not None:
        stage = "bundle's" if bundle_result is not None else "registered (stage 2)"
        final_overlays(inputs, block, state, by_id, Path(options.overlay_path), stage)
    points = constrained_points(inputs, block, state, by_id, bundle_result, stage3)
    ties: list[Point3D] = []
    solved = stage3.bundle_problem if stage3 is not None else None
    if bundle_result is not None and solved is not None and len(solved.tie_image):
        # the bundle's own tie points, in the block's frame
        ties = bundle_tie_records(solved, bundle_result, set(block.images))
        points += ties
    elif (
        options.adjustment.tie_points
        and options.stop_after == "bundle"
        and len(block.images) >= 2
    ):
        # the bundle was skipped or failed: its tie points, triangulated
        t_ties = time.perf_counter()
        ties = tie_point_records(
            inputs, block, z0, options.adjustment.tie_point_options
        )
        points += ties
        timings["tie_points_output"] = time.perf_counter() - t_ties
    color_points(inputs.image_path, block, points)
    block = block.shifted(np.array([0.0, 0.0, z0]))
    for p in points:
        p.xyz = p.xyz - np.array([0.0, 0.0, z0])
    timings["total"] = time.perf_counter() - t_run
    report = run_report(inputs, outcomes, rescued, bundle_result, georef, timings)
    report["reregistered"] = reregistered
    if options.adjustment.tie_points:
        per_image = Counter(i for p in ties for i, _ in p.observations)
        counts = [per_image.get(i, 0) for i in block.images]
        report["tie_points"] = {
            "num_points": len(ties),
            "num_observations": sum(counts),
            "min_per_image": min(counts, default=0),
            "median_per_image": float(np.median(counts)) if counts else 0.0,
        }
    if stage3 is not None:
        report["facades"] = stage3.report(by_id)
    report["options"] = {
        "stop_after": options.stop_after,
        "num_workers": workers,
        "dask_scheduler": options.dask_scheduler,
        "vp_cone_deg": options.cone_deg,
        "camera_model": options.camera_model,
        "refine_focal_length": options.adjustment.bundle.refine_focal_length,
        "refine_principal_point": options.adjustment.bundle.refine_principal_point,
        "refine_extra_params": options.adjustment.bundle.refine_extra_params,
        "bundle_rotation_sigma_deg": options.adjustment.bundle.rotation_prior_sigma_deg,
        "bundle_position_sigma_m": options.adjustment.bundle.position_prior_sigma_m,
        "bundle_position_offset": options.adjustment.bundle.estimate_prior_offset,
        "min_constraints_kept": options.min_constraints_kept,
        "max_precision_ratio": options.max_precision_ratio,
        "max_end_offset_ratio": options.max_end_offset_ratio,
        "warn_predicted_sd_px": options.warn_predicted_sd_px,
        "max_prior_rejected_fraction": options.max_prior_rejected_fraction,
        "facade_height_range_m": list(options.adjustment.facades.height_range_m),
    }
    report["num_points3D"] = len(points)
    return RunResult(block, georef, points, by_id, report, bundle_result, starts)
