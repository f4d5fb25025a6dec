"""Options and results of an evaluation: :class:`EvaluateOptions`, the per-image
:class:`ImageEvaluation`, the block's :class:`EvaluationSummary` and the
:class:`Evaluation` that holds them (JSON and table out)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

#: Per-image status values. Only ``"registered"`` is a success.
STATUS_REGISTERED = "registered"
STATUS_FAILED = "failed"  # mean deviation >= threshold
STATUS_BEHIND = "behind"  # a visible corner is behind the estimated camera
STATUS_MISSING = "missing"  # in the ground truth, not in the result
STATUS_NO_CORNERS = "no_corners"  # no visible corner: not measurable

#: The choices of ``EvaluateOptions.vertical_offset``.
VERTICAL_OFFSETS = ("corners", "cameras", "search")


@dataclass(kw_only=True)
class EvaluateOptions:
    """Options of :func:`evaluate_block` and :func:`evaluate_model`.

    Attributes
    ----------
    registered_threshold_px : float
        An image is registered when its mean corner deviation (px) is below
        this (docs/DESIGN.md: 2 px).
    across_vertical : bool
        Measure only the deviation across the TRUE image direction of the
        world vertical through each corner (for per-image stages).
    remove_vertical_offset : bool
        Remove one vertical offset (m) before measuring: the median over the
        matched images of their own offsets, see ``vertical_offset``.
    vertical_offset : str
        An image's own offset: ``"corners"``, the height (m) by which its
        estimated camera must be lowered for its projections of its visible
        true corners to fit those of the true camera best (least squares;
        the centre-height difference where it sees no corner in front);
        ``"cameras"``, its estimated minus true camera-centre height.
        Or no median of the images' own: ``"search"``, the ONE offset that
        minimises the median over the images of their mean deviation
        (missing images infinite), searched within ``search_range_m`` of the
        camera-height offset (the measure of issue 25 and of the external
        scenes' README).
    search_range_m : float
        Half-width (m) of the ``"search"`` interval around the median of the
        estimated minus true camera heights.
    """

    registered_threshold_px: float = 2.0
    across_vertical: bool = False
    remove_vertical_offset: bool = True
    vertical_offset: str = "corners"
    search_range_m: float = 20.0

    def __post_init__(self) -> None:
        if not (
            self.registered_threshold_px > 0
            and math.isfinite(self.registered_threshold_px)
        ):
            raise ValueError(
                "registered_threshold_px must be a positive number, got "
                f"{self.registered_threshold_px!r}"
            )
        if not (self.search_range_m > 0 and math.isfinite(self.search_range_m)):
            raise ValueError(
                f"search_range_m must be a positive number, got {self.search_range_m!r}"
            )
        if self.vertical_offset not in VERTICAL_OFFSETS:
            raise ValueError(
                f"vertical_offset must be one of {VERTICAL_OFFSETS}, got "
                f"{self.vertical_offset!r}"
            )


@dataclass
class ImageEvaluation:
    """The errors of one image.

    Errors are NaN where they cannot be measured (a missing image; deviations
    of an image with no visible corner or with all of them behind the camera).

    Attributes
    ----------
    name : str, image name as in both models.
    status : str, one of ``registered``, ``failed``, ``behind``, ``missing``,
        ``no_corners``.
    rotation_error_deg : float, angle of ``R_est @ R_true.T``.
    center_error_m : float, distance of the estimated centre (vertical offset
        removed) from the true centre.
    horizontal_error_m : float, its horizontal (x, y) part.
    vertical_error_m : float, its signed vertical part, estimated minus true
        after the offset (m).
    mean_deviation_px, max_deviation_px : float, over the visible corners in
        front of the estimated camera; across the projected vertical only with
        ``across_vertical``.
    num_corners : int, visible corners of the true camera.
    num_behind : int, of those, behind the estimated camera.
    """

    name: str
    status: str
    rotation_error_deg: float = math.nan
    center_error_m: float = math.nan
    horizontal_error_m: float = math.nan
    vertical_error_m: float = math.nan
    mean_deviation_px: float = math.nan
    max_deviation_px: float = math.nan
    num_corners: int = 0
    num_behind: int = 0

    @property
    def registered(self) -> bool:
        return self.status == STATUS_REGISTERED


@dataclass
class EvaluationSummary:
    """Block-level figures of an :class:`Evaluation`.

    Attributes
    ----------
    num_total : int, ground-truth images with at least one visible corner.
    num_registered, num_failed, num_behind, num_missing : int, of those.
    num_no_corners : int, ground-truth images with no visible corner (not in
        the total).
    num_extra : int, result images that are not in the ground truth (ignored).
    vertical_offset_m : float, removed offset, estimated minus true (m).
    deviation_median_px, deviation_p95_px, deviation_max_px : float, over the
        per-image MEAN deviations of the measured images (in the result, with
        at least one corner in front of the estimated camera).
    rotation_error_median_deg, center_error_median_m,
    horizontal_error_median_m, vertical_error_median_m : float, medians over
        the images of the ground truth present in the result (vertical: of the
        absolute value).
    camera_offset_m : float, median over the matched images of the estimated
        minus true camera-centre height (m), before any offset is removed.
    deviation_median_all_px, deviation_p95_all_px : float, over the per-image
        MEAN deviations of ALL measurable images, the missing ones and those
        with a corner behind the estimated camera counted as infinite (the
        judged figures of issue 25; ``null`` in JSON when infinite).
    """

    num_total: int
    num_registered: int
    num_failed: int
    num_behind: int
    num_missing: int
    num_no_corners: int
    num_extra: int
    vertical_offset_m: float
    deviation_median_px: float
    deviation_p95_px: float
    deviation_max_px: float
    rotation_error_median_deg: float
    center_error_median_m: float
    horizontal_error_median_m: float
    vertical_error_median_m: float
    camera_offset_m: float = math.nan
    deviation_median_all_px: float = math.nan
    deviation_p95_all_px: float = math.nan

    @property
    def registered_fraction(self) -> float:
        return self.num_registered / self.num_total if self.num_total else math.nan


@dataclass
class Evaluation:
    """Per-image errors and the summary of one model against the ground truth.

    Attributes
    ----------
    images : list of ImageEvaluation, sorted by name (all ground-truth images).
    summary : EvaluationSummary.
    options : EvaluateOptions used.
    extra_images : names in the result but not in the ground truth.
    result_path, gt_path : str or None, the evaluated folders (set by
        :func:`evaluate_model`).
    gt_format : str or None, the scene's format (``GroundTruth.format``; set
        by :func:`evaluate_model`).
    """

    images: list[ImageEvaluation]
    summary: EvaluationSummary
    options: EvaluateOptions
    extra_images: list[str] = field(default_factory=list)
    result_path: str | None = None
    gt_path: str | None = None
    gt_format: str | None = None

    def image(self, name: str) -> ImageEvaluation:
        """The evaluation of the image called ``name``."""
        for im in self.images:
            if im.name == name:
                return im
        raise KeyError(name)

    def to_json(self) -> dict:
        """A JSON-ready dict; non-finite numbers become ``null``."""
        summary = asdict(self.summary)
        summary["registered_fraction"] = self.summary.registered_fraction
        return json_safe(
            {
                "result_path": self.result_path,
                "gt_path": self.gt_path,
                "gt_format": self.gt_format,
                "options": asdict(self.options),
                "summary": summary,
                "extra_images": list(self.extra_images),
                "images": [asdict(im) for im in self.images],
            }
        )

    def format_table(self) -> str:
        """The per-image table and the summary, as printed by the CLI."""
        return format_table(self)


# The report of an evaluation: JSON-safe values and the printed table.


def json_safe(obj):
    """``obj`` with numpy scalars as Python ones and non-finite floats as None."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _fmt(value: float, digits: int) -> str:
    return "-" if not math.isfinite(value) else f"{value:.{digits}f}"


def _fmt_inf(value: float, digits: int) -> str:
    return "inf" if value == math.inf else _fmt(value, digits)


def format_table(evaluation: Evaluation) -> str:
    """The per-image table followed by the summary lines.

    Columns: name, rotation error (deg), centre error (m), mean and max
    deviation (px), number of visible corners, status.
    """
    images = evaluation.images
    width = max([len("image")] + [len(im.name) for im in images])
    dev = "dev" + ("_across" if evaluation.options.across_vertical else "")
    header = (
        f"{'image':<{width}}  {'rot_deg':>8}  {'centre_m':>8}  "
        f"{'mean_' + dev + '_px':>{len(dev) + 8}}  "
        f"{'max_' + dev + '_px':>{len(dev) + 7}}  "
        f"{'corners':>7}  status"
    )
    lines = [header, "-" * len(header)]
    for im in images:
        lines.append(
            f"{im.name:<{width}}  {_fmt(im.rotation_error_deg, 4):>8}  "
            f"{_fmt(im.center_error_m, 3):>8}  "
            f"{_fmt(im.mean_deviation_px, 3):>{len(dev) + 8}}  "
            f"{_fmt(im.max_deviation_px, 3):>{len(dev) + 7}}  "
            f"{im.num_corners:>7}  {im.status}"
        )
    s = evaluation.summary
    lines += [
        "",
        f"registered {s.num_registered} / {s.num_total} images "
        f"(threshold {evaluation.options.registered_threshold_px:g} px"
        f"{', across verticals' if evaluation.options.across_vertical else ''}); "
        f"failed {s.num_failed}, behind {s.num_behind}, missing {s.num_missing}, "
        f"no corners {s.num_no_corners}, extra {s.num_extra}",
        f"mean deviation per image: median {_fmt(s.deviation_median_px, 3)} px, "
        f"p95 {_fmt(s.deviation_p95_px, 3)} px, max {_fmt(s.deviation_max_px, 3)} px",
        "  with missing and behind images as infinite: median "
        f"{_fmt_inf(s.deviation_median_all_px, 3)} px, "
        f"p95 {_fmt_inf(s.deviation_p95_all_px, 3)} px",
        f"median rotation error {_fmt(s.rotation_error_median_deg, 4)} deg, "
        f"centre error {_fmt(s.center_error_median_m, 3)} m "
        f"(horizontal {_fmt(s.horizontal_error_median_m, 3)} m, "
        f"vertical {_fmt(s.vertical_error_median_m, 3)} m) after a vertical offset of "
        f"{_fmt(s.vertical_offset_m, 3)} m",
        f"vertical offset: {offset_label(evaluation.options)}; camera-height "
        f"offset {_fmt(s.camera_offset_m, 3)} m",
    ]
    return "\n".join(lines)


def offset_label(options: EvaluateOptions) -> str:
    """How the removed vertical offset was chosen, for the report."""
    if not options.remove_vertical_offset:
        return "kept"
    if options.vertical_offset == "search":
        return (
            "search: minimises the median deviation within "
            f"+-{options.search_range_m:g} m of the camera-height offset"
        )
    return f"{options.vertical_offset}: median of the images' own"
