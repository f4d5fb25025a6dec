"""Options of stage 3: facade edges, matching, the bundle and its rounds."""

from __future__ import annotations

from dataclasses import dataclass, field

from obliq_colmap.adjustment.facades import FacadeOptions
from obliq_colmap.adjustment.matching import MatchingOptions
from obliq_colmap.adjustment.tie_options import TiePointOptions
from obliq_colmap.bundle import BundleOptions

__all__ = ["AdjustmentOptions"]


@dataclass(kw_only=True)
class AdjustmentOptions:
    """Options of stage 3 (:func:`bundle_stage`)."""

    facades: FacadeOptions = field(default_factory=FacadeOptions)
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    #: The bundle (its corner points are always fixed: vertical_constraints).
    #: Cauchy at 1 px: the facade tracks fit to ~0.15 px, so a wrong match is
    #: many scales out and must lose its pull. The distortion terms of a model
    #: that has them are refined (a lens the priors do not describe bends every
    #: vertical); ``refine_extra_params=False`` holds a calibrated lens. Each
    #: principal point is held near the priors' with 0.4 % of the larger image
    #: side (8 px at 2004 px): through a long lens a shift of the principal
    #: point is nearly a turn of the camera, so a head's images hardly
    #: separate the two and the prior decides; a looser prior lets the heads'
    #: principal points follow the weak vertical mode (pitch, height and focal
    #: traded), a held one costs wide lenses, whose data do separate them
    #: (measured: journal, independent scenes, 2026-12-07 session of 06:00).
    #: The facade rows' line-fit weighting (``facade_row_extrapolation``) is
    #: off: better on our generator's scenes, worse on the external
    #: renderer's houses (journal, stage 3, 2026-12-06 session of 19:59).
    bundle: BundleOptions = field(
        default_factory=lambda: BundleOptions(
            loss="cauchy",
            loss_scale_px=1.0,
            refine_extra_params=True,
            principal_point_prior_sigma=0.004,
        )
    )
    #: Bundle rounds after the first that drop the constraints whose residual
    #: exceeds ``outlier_factor`` robust standard deviations (of their kind)
    #: and at least ``outlier_floor_px``, then solve again from the result.
    #: The floor is in pixels of the image its segments were detected in (the
    #: facade lines: ``Segments.pixel_scale``), where their noise lives.
    outlier_rounds: int = 5
    outlier_factor: float = 3.0
    outlier_floor_px: float = 1.0
    #: Huber scale (px) of the first bundle round (then the bundle's own
    #: loss); 0 uses the bundle's own loss throughout.
    initial_loss_scale_px: float = 0.0
    #: Between rounds: re-triangulate each facade track as a 3D horizontal
    #: line near its wall (roof rims overhang), and weight the residual kinds
    #: by their robust standard deviations.
    track_lines: bool = True
    variance_components: bool = True
    #: Prior 1-sigma (m) of a track's offset from its wall: weak, since roof
    #: rims overhang and parapets stand back from the map edge.
    track_offset_sigma_m: float = 10.0
    #: SIFT tie points matched across the block (the failed images too),
    #: observed in the bundle from its second solve (3D points, 2 rows per
    #: observation), placing the images stage 2 failed on for their second
    #: registration, and written with their tracks. On: urban-101 27 -> 33 of
    #: 36 below 2 px; SIFT and matching on the CPU cost ~1.5 s per image.
    tie_points: bool = True
    tie_point_options: TiePointOptions = field(default_factory=TiePointOptions)
    #: An image pair whose tie tracks sit, at the block solved without them,
    #: a median error above this factor times the pairs' median and this
    #: floor (px) is left out (a two-view geometry verified on repeated
    #: texture).
    tie_pair_factor: float = 3.0
    tie_pair_floor_px: float = 3.0
    #: The vertical rows on each segment's own line (its edge points' fit),
    #: not on the line through stage 1's VP (:func:`vertical_constraints`);
    #: the two rows of a segment then enter as their sum (the map's noise)
    #: and difference (the segment's direction), each with its own estimated
    #: sd (``BundleOptions.vertical_direction_sigma_px``). Where stage 1's VP
    #: is degrees off (short walls of detached houses), every segment through
    #: it is turned alike, and that is what tilted such blocks.
    measured_vertical_directions: bool = True
    #: The map's vertex noise (m, 1 sigma per horizontal axis): carried into
    #: the bundle's precision as an error every row of a corner shares
    #: (``BundleOptions.map_corner_sigma_m``), and with the facade lines
    #: (``bundle.facade_lines``) each line's prior angle about its map edge,
    #: ``sqrt(2)`` times it over the edge's length.
    map_vertex_sigma_m: float = 0.15
    #: With the facade lines: a track this far (m) or more above the ground is
    #: a level line (floors, eaves); nearer the ground, edges follow the
    #: terrain (kerbs, the foot of a wall) and keep one row per observation.
    level_height_m: float = 2.0

    def __post_init__(self) -> None:
        if self.outlier_rounds < 0 or self.outlier_factor <= 0:
            raise ValueError("outlier_rounds must be >= 0 and outlier_factor > 0")
        if not self.map_vertex_sigma_m > 0:
            raise ValueError("map_vertex_sigma_m must be > 0")
        if self.track_offset_sigma_m <= 0:
            raise ValueError("track_offset_sigma_m must be > 0")
