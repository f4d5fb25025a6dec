"""Evaluation against ground truth: the measuring instrument for every accuracy figure.

A result model (our output: a LOCAL frame with ``georef.json`` beside it) is
compared image by image with the exact model of a scene (``gt/``, absolute
coordinates) and with the scene's true 3D building corners
(``gt_buildings.json``). Two scene formats are read as they are, told apart
by content (:func:`read_ground_truth`): ``obliq-colmap synth`` output, and the
external format of ``../shared/data/external_oblique`` (visibility in
``gt_visibility.json``). Per image:

1. the rotation error (deg) of ``cam_from_world``;
2. the camera-centre error (m, total, horizontal and vertical) after removing
   ONE vertical offset for the whole model: the vertical datum of a result is
   only as good as that of its priors (see docs/DESIGN.md, "COLMAP interface"), so
   a constant height offset is not an error of ours. The offset is the median
   over the matched images of the height by which each image's estimated
   camera must be lowered for its projections of the true corners to fit
   best (``vertical_offset="corners"``), or of the estimated minus the true
   centre height (``"cameras"``). A camera raised and pitched to image the
   scene alike (the bundle's weak mode along its viewing ray) keeps its scene
   datum but not its centre height, so the median of centre heights misses
   the datum (issue 5). Or
   (``"search"``, the measure of issue 25) the ONE offset that minimises the
   median over the images of their mean deviation (3. below; missing images
   infinite), searched within +-20 m of the camera-height offset;
3. the reprojection deviation (mean and max, px) of the true corners visible in
   the image, projected by the ESTIMATED camera (its own intrinsics and
   distortion, its centre lowered by the vertical offset) versus by the TRUE
   camera. The image is registered when the mean deviation is below
   ``registered_threshold_px`` and no visible corner is behind the estimated
   camera.

With ``across_vertical`` only the component of the deviation across the image
of the world vertical through each corner is measured, for the output of
per-image stages, which cannot observe camera height, terrain height or the
tilt/focal trade-off: those all move points along the projected verticals.

Images of the ground truth missing from the result count as failures (and as
infinite in ``deviation_median_all_px`` / ``deviation_p95_all_px``). Images
of the ground truth with no visible corner cannot be measured: they are listed
(status ``"no_corners"``) but are not part of the total.

The baseline is the scene's own ``priors/`` model measured the same way
(:func:`evaluate_baseline`).

Entry points: :func:`evaluate_model` (folders) and :func:`evaluate_block`
(blocks in memory). In: an estimated and a true :class:`~obliq_colmap.colmap_io.Block`
(absolute frame, metres), the true corners (K, 3) and each image's visible
corner indices. Out: an :class:`Evaluation` (per image: rotation error deg,
centre errors m, mean and max deviation px, status; the block's summary).

Modules, in reading order:

- ``results``: the options (:class:`EvaluateOptions`), the result types, their
  JSON-safe values and the printed table;
- ``measure``: one image's corner deviations, its own vertical offset, and
  the search of the block's one offset (``vertical_offset="search"``);
- ``block``: :func:`evaluate_block`, the evaluation of a block;
- ``scene``: the files: the two scene formats, result models, :func:`evaluate_model`.
"""

from obliq_colmap.evaluate.block import evaluate_block
from obliq_colmap.evaluate.measure import (
    corner_deviations_px,
    mean_deviation_by_offset,
    scene_height_offset,
    search_block_offset,
)
from obliq_colmap.evaluate.results import (
    STATUS_BEHIND,
    STATUS_FAILED,
    STATUS_MISSING,
    STATUS_NO_CORNERS,
    STATUS_REGISTERED,
    VERTICAL_OFFSETS,
    EvaluateOptions,
    Evaluation,
    EvaluationSummary,
    ImageEvaluation,
    format_table,
)
from obliq_colmap.evaluate.scene import (
    GT_BUILDINGS_FILE,
    GT_FORMAT_EXTERNAL,
    GT_FORMAT_SYNTHETIC,
    GT_MODEL_DIR,
    GT_VISIBILITY_FILE,
    PRIORS_MODEL_DIR,
    GroundTruth,
    evaluate_baseline,
    evaluate_model,
    read_absolute_block,
    read_ground_truth,
)

__all__ = [
    "GT_BUILDINGS_FILE",
    "GT_FORMAT_EXTERNAL",
    "GT_FORMAT_SYNTHETIC",
    "GT_MODEL_DIR",
    "GT_VISIBILITY_FILE",
    "PRIORS_MODEL_DIR",
    "STATUS_BEHIND",
    "STATUS_FAILED",
    "STATUS_MISSING",
    "STATUS_NO_CORNERS",
    "STATUS_REGISTERED",
    "VERTICAL_OFFSETS",
    "EvaluateOptions",
    "Evaluation",
    "EvaluationSummary",
    "GroundTruth",
    "ImageEvaluation",
    "corner_deviations_px",
    "evaluate_baseline",
    "evaluate_block",
    "evaluate_model",
    "format_table",
    "mean_deviation_by_offset",
    "read_absolute_block",
    "read_ground_truth",
    "scene_height_offset",
    "search_block_offset",
]
