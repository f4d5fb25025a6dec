"""The report of an evaluation: JSON-safe values and the printed table."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from obliq_colmap.evaluate.results import EvaluateOptions, Evaluation


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
