"""Options of ``obliq-colmap georegister`` (:class:`GeoregisterOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from obliq_colmap.control.model import (
    DEFAULT_SIGMA_HORIZONTAL_M,
    DEFAULT_SIGMA_VERTICAL_M,
)
from obliq_colmap.georegister.block import BlockAdjustmentOptions
from obliq_colmap.georegister.block_lines import BlockLinesOptions
from obliq_colmap.georegister.relative_vp import RelativeVPOptions
from obliq_colmap.registration import RegistrationOptions

#: ``--camera_kind``: which prior stage 1 searches the vertical VP with.
CAMERA_KINDS = ("terrestrial", "oblique", "auto")
#: ``--automatic_method``: how the automatic mode places the block.
AUTOMATIC_METHODS = ("auto", "per_image", "block")


@dataclass(kw_only=True)
class VerticalOptions:
    """The model's vertical from the images' vertical vanishing points."""

    #: "terrestrial": the VP within 30 deg of the image's vertical axis, above
    #: or below (a camera held roughly level); "oblique": the aerial prior
    #: (VP below the image); "auto": both, the more significant one kept.
    camera_kind: str = "auto"
    #: images whose VP direction is this many robust sigmas from the
    #: average are outliers (the robust loss's scale, Cauchy).
    outlier_sigmas: float = 3.0
    #: at least this many images with a VP, or the vertical is unknown.
    min_images: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        if self.camera_kind not in CAMERA_KINDS:
            raise ValueError(
                f"camera_kind={self.camera_kind!r}; allowed: {', '.join(CAMERA_KINDS)}"
            )


@dataclass(kw_only=True)
class GeoregisterOptions:
    """Everything ``georegister`` needs besides its paths."""

    vertical: VerticalOptions = field(default_factory=VerticalOptions)
    #: names of control points withheld from the estimation (check points).
    check_points: tuple[str, ...] = ()
    #: stated accuracy of control points without one in the file, m.
    sigma_horizontal_m: float = DEFAULT_SIGMA_HORIZONTAL_M
    sigma_vertical_m: float = DEFAULT_SIGMA_VERTICAL_M
    #: target CRS of the output (default: the control points' / map's).
    crs: str | None = None
    #: the bundle block adjustment after the similarity (``block``)
    block_adjustment: bool = True
    block: BlockAdjustmentOptions = field(default_factory=BlockAdjustmentOptions)
    #: images under --image_path that the model lacks placed from VPs and a
    #: few matches (``relative_vp``) and added to the model
    add_missing_images: bool = False
    relative_vp: RelativeVPOptions = field(default_factory=RelativeVPOptions)
    #: the automatic mode: "per_image", stage 2 on every image (oblique
    #: cameras), then one similarity from all their pairs; "block", all
    #: images' segments against the map at once (level cameras, whose
    #: images stage 2 cannot register alone); "auto": "block" when the
    #: vertical came from the terrestrial VP prior, else "per_image"
    automatic_method: str = "auto"
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    block_lines: BlockLinesOptions = field(default_factory=BlockLinesOptions)
    cadastre_path: Path | None = None
    control_points_path: Path | None = None
    priors_path: Path | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if self.automatic_method not in AUTOMATIC_METHODS:
            raise ValueError(
                f"automatic_method={self.automatic_method!r}; allowed: "
                f"{', '.join(AUTOMATIC_METHODS)}"
            )
