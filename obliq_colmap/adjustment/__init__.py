"""Stage 3, the block adjustment: from the per-image registrations (stage 2)
to one adjusted block (paper sections 2.3-2.4).

Entry: :func:`bundle_stage` (inputs, per-image outcomes, the block as stage 2
left it, :class:`AdjustmentOptions`) -> :class:`AdjustedBlock` (the block
after the bundle, the bundle's result, the :class:`Stage3` record), then
:func:`judge` -> :class:`Verdicts` (the images the solved block got wrong),
which the pipeline leaves out.

Data in: per image its registration (pose ``cam_from_world`` in the map's
local frame, metres; intrinsics; inlier corner-to-segment pairs, UNDISTORTED
pixels of the priors' camera), its first-pass line segments (same pixels,
with their bright side) and its ground plane ``z = a x + b y + c``; the
cadastre (map edges and corners, local frame). Data out: poses and one
camera per head (camera_id) in the block's height datum, per-track heights
(m) and per-image diagnostics (RMS, share of constraints kept, precision,
edge-end offsets, px).

Modules, in reading order:

* :mod:`~obliq_colmap.adjustment.facades`: horizontal facade edges of one
  registered image, lifted onto the walls of the map (heights above the
  image's own ground).
* :mod:`~obliq_colmap.adjustment.matching`: facade edges matched pairwise
  (RANSAC on a planar height offset), chained into tracks; per-image height
  datum corrections.
* :mod:`~obliq_colmap.adjustment.tracks`: the matches (:class:`PairMatch`,
  :class:`FacadeTracks`) and tracks as 3D horizontal lines.
* :mod:`~obliq_colmap.adjustment.options`: :class:`AdjustmentOptions`.
* :mod:`~obliq_colmap.adjustment.problem`: the facade stage over the block
  (:class:`Stage3`), the corners' vertical constraints, the bundle problem.
* :mod:`~obliq_colmap.adjustment.verdicts`: the rejected, imprecise and
  misplaced images.
* :mod:`~obliq_colmap.adjustment.rounds`: :func:`bundle_stage`, the solve in
  rounds (outliers, track lines, variance components).

The block as it stands (:class:`~obliq_colmap.state.BlockState`) and the
per-image outcomes are the run's shared state (:mod:`obliq_colmap.state`);
this package does not import the pipeline.
"""

from obliq_colmap.adjustment.facades import FacadeEdges, FacadeOptions, facade_edges
from obliq_colmap.adjustment.matching import (
    MatchingOptions,
    chain_tracks,
    datum_corrections,
    match_facade_edges,
    match_pair,
    points_along_edges,
)
from obliq_colmap.adjustment.options import AdjustmentOptions
from obliq_colmap.adjustment.problem import (
    Stage3,
    build_bundle_problem,
    facade_stage,
    heights_on_vertical,
    raw_lines,
    vertical_constraints,
)
from obliq_colmap.adjustment.rounds import (
    AdjustedBlock,
    bundle_stage,
    vp_components,
    with_track_lines,
    with_variance_components,
    within_robust_bound,
    without_outliers,
)
from obliq_colmap.adjustment.tie_options import TiePointOptions
from obliq_colmap.adjustment.ties import TiePoints, tie_points
from obliq_colmap.adjustment.tracks import FacadeTracks, PairMatch, triangulate_tracks
from obliq_colmap.adjustment.verdicts import (
    Verdicts,
    edge_end_offsets,
    end_offset_ratios,
    imprecise_images,
    judge,
    misplaced_images,
    rejected_images,
)
from obliq_colmap.state import BlockState

__all__ = [
    "AdjustedBlock",
    "AdjustmentOptions",
    "BlockState",
    "FacadeEdges",
    "FacadeOptions",
    "FacadeTracks",
    "MatchingOptions",
    "PairMatch",
    "Stage3",
    "TiePointOptions",
    "TiePoints",
    "Verdicts",
    "build_bundle_problem",
    "bundle_stage",
    "chain_tracks",
    "datum_corrections",
    "edge_end_offsets",
    "end_offset_ratios",
    "facade_edges",
    "facade_stage",
    "heights_on_vertical",
    "imprecise_images",
    "judge",
    "match_facade_edges",
    "match_pair",
    "misplaced_images",
    "points_along_edges",
    "rejected_images",
    "tie_points",
    "triangulate_tracks",
    "raw_lines",
    "vertical_constraints",
    "with_track_lines",
    "vp_components",
    "with_variance_components",
    "within_robust_bound",
    "without_outliers",
]
