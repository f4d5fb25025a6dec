"""The ``register`` job: oblique images + footprint map + rough priors ->
COLMAP model.

Entry: :func:`run_register` (image folder, GeoJSON footprint map, COLMAP
priors model, :class:`PipelineOptions`) -> :class:`RunResult`, written
atomically by :func:`write_run` (the COLMAP model and ``georef.json`` in a
local frame, ``report.json``).

Data in: the images; the map (projected metric CRS; its origin becomes the
local frame's); the priors (rough poses ``cam_from_world`` and intrinsics,
in the map's CRS and the priors' vertical datum). Data out: the registered
images' poses and intrinsics in the local frame (origin: the map's origin at
the block's rounded ground height), the constrained points with tracks
(map corners, facade tracks), and per image and per stage the report.

Stages (paper 000, sections 2.1-2.4):

1. ``initial``, per image and in parallel: the vertical vanishing point with
   the INS prior and the VP-constrained vertical segments
   (:mod:`obliq_colmap.vanishing`), then the registration to the map by
   RANSAC over corner-to-line pairs (:mod:`obliq_colmap.registration`). Weak
   images are registered once more from the block's ground heights (all
   priors share one vertical datum).
2. ``bundle`` (:mod:`obliq_colmap.adjustment`): horizontal facade edges per
   image, matched across images into tracks, and the bundle adjustment over
   all cameras, intrinsics and track heights in rounds; failed images
   registered again against the solved block; the images the solved block
   got wrong left out.
3. Output: the model, ``georef.json`` and ``report.json``.

A failed image is a value (:class:`~obliq_colmap.state.ImageOutcome` with a
message), never an exception: it is named in a warning and left out of the
model. The run's shared state (outcomes, inputs, the block as it stands)
lives in :mod:`obliq_colmap.state`.

Modules, in reading order:

* :mod:`~obliq_colmap.pipeline.options`: :class:`PipelineOptions`.
* :mod:`~obliq_colmap.pipeline.inputs`: the inputs read and checked, the
  per-image tasks.
* :mod:`~obliq_colmap.pipeline.workers`: the per-image functions that run in
  worker processes, and the pool.
* :mod:`~obliq_colmap.pipeline.heads`: one lens and focal length per head.
* :mod:`~obliq_colmap.pipeline.initial`: stages 1-2 over the block, the
  rescue of weak images.
* :mod:`~obliq_colmap.pipeline.verdicts`: the images stage 3 got wrong, left
  out.
* :mod:`~obliq_colmap.pipeline.block`: stage 3 in the run: the bundle, the
  pose priors' check, the re-registration against the solved block.
* :mod:`~obliq_colmap.pipeline.output`: the result block, points, report.
* :mod:`~obliq_colmap.pipeline.run`: :func:`run_register`.
"""

from obliq_colmap.adjustment import AdjustmentOptions
from obliq_colmap.lines import RefineOptions
from obliq_colmap.pipeline.block import (
    block_stage,
    check_pose_priors,
    reregister_failed,
)
from obliq_colmap.pipeline.heads import head_cameras, head_focal_pass, head_pass
from obliq_colmap.pipeline.initial import initial_stage, rescue_heights
from obliq_colmap.pipeline.inputs import image_tasks, load_inputs
from obliq_colmap.pipeline.options import (
    STOP_AFTER,
    PipelineOptions,
    default_head_focal_min_images,
)
from obliq_colmap.pipeline.output import (
    REPORT_FILE,
    RunResult,
    constrained_points,
    result_block,
    run_report,
    summary_table,
    write_run,
)
from obliq_colmap.pipeline.run import run_register
from obliq_colmap.pipeline.verdicts import (
    UNCONFIRMED_VERTICAL_NOTE,
    block_verdicts,
    leave_out_rejected,
    unsupported_placements,
    warn_imprecise,
    warn_unconfirmed_vertical,
    warn_vp_disagreement,
)
from obliq_colmap.pipeline.workers import (
    ImageTask,
    initial_image,
    overlay_name,
    set_registration,
    worker_pool,
)
from obliq_colmap.registration import RegistrationOptions
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = [
    "REPORT_FILE",
    "STOP_AFTER",
    "AdjustmentOptions",
    "BlockState",
    "ImageOutcome",
    "ImageTask",
    "Inputs",
    "PipelineOptions",
    "RefineOptions",
    "RegistrationOptions",
    "RunResult",
    "block_stage",
    "block_verdicts",
    "check_pose_priors",
    "constrained_points",
    "default_head_focal_min_images",
    "head_cameras",
    "head_focal_pass",
    "head_pass",
    "image_tasks",
    "initial_image",
    "initial_stage",
    "leave_out_rejected",
    "unsupported_placements",
    "warn_imprecise",
    "warn_unconfirmed_vertical",
    "UNCONFIRMED_VERTICAL_NOTE",
    "warn_vp_disagreement",
    "load_inputs",
    "overlay_name",
    "reregister_failed",
    "rescue_heights",
    "result_block",
    "run_register",
    "run_report",
    "set_registration",
    "summary_table",
    "worker_pool",
    "write_run",
]
