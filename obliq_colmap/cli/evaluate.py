"""``obliq-colmap evaluate``: measure a result model against a scene's truth,
or any model against control points (check points, for real data).

    obliq-colmap evaluate --input_path MODEL --control_points_path GCP_FILE
                          [--check_points NAME,...] [--output_path report.json]

    obliq-colmap evaluate --input_path RESULT_MODEL --gt_path SCENE
                          [--baseline] [--across_vertical]
                          [--registered_threshold_px 2]
                          [--vertical_offset corners|cameras|search]
                          [--output_path report.json]

SCENE is an ``obliq-colmap synth`` scene or an external one
(``../shared/data/external_oblique/*``: ``gt/``, ``gt_buildings.json``,
``gt_visibility.json``), told apart by content. ``--vertical_offset search``
is the measure of issue 25: the ONE vertical offset minimising the median of
the images' mean deviations, within +-20 m of the camera-height offset.

With ``--baseline`` the scene's ``priors/`` model is evaluated; ``--input_path``
is then optional, and when given both are evaluated (the JSON report holds the
baseline under the key ``"baseline"``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from obliq_colmap.errors import InputError
from obliq_colmap.evaluate import (
    VERTICAL_OFFSETS,
    EvaluateOptions,
    evaluate_baseline,
    evaluate_model,
)
from obliq_colmap.evaluate.control import (
    evaluate_control_points,
    format_control_table,
)
from obliq_colmap.files import write_json_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--input_path",
        help="result model folder (local frame with georef.json, or absolute); "
        "optional with --baseline",
    )
    parser.add_argument(
        "--control_points_path",
        help="instead of --gt_path: control points (gcp_list.txt or "
        "ground_control_points.json) triangulated in the model from their "
        "observations and scored against their coordinates (m and px)",
    )
    parser.add_argument(
        "--check_points",
        default="",
        help="with --control_points_path: the names reported as check points "
        "(comma-separated; default all)",
    )
    parser.add_argument(
        "--gt_path",
        help="scene folder with gt/, priors/ and gt_buildings.json (synthetic) "
        "or also gt_visibility.json (external format)",
    )
    parser.add_argument(
        "--baseline",
        action="store_true",
        help="evaluate the scene's rough priors (SCENE/priors) the same way",
    )
    parser.add_argument(
        "--across_vertical",
        action="store_true",
        help="measure only the deviation across the projected world vertical "
        "(for per-image stages, which cannot observe heights)",
    )
    parser.add_argument(
        "--registered_threshold_px",
        type=float,
        default=EvaluateOptions().registered_threshold_px,
        help="an image is registered when its mean corner deviation is below "
        "this (px, default %(default)s)",
    )
    parser.add_argument(
        "--keep_vertical_offset",
        action="store_true",
        help="do not remove the model's vertical offset",
    )
    parser.add_argument(
        "--vertical_offset",
        choices=VERTICAL_OFFSETS,
        default=EvaluateOptions().vertical_offset,
        help="the model's vertical offset is the median over the images of "
        "the height that best fits each image's projections of its true "
        "corners (corners) or of its camera-centre height error (cameras), "
        "or the one offset that minimises the "
        "median over the images of their mean deviation, missing images "
        "infinite (search, within --search_range_m of the median camera-height "
        "error); default %(default)s",
    )
    parser.add_argument(
        "--search_range_m",
        type=float,
        default=EvaluateOptions().search_range_m,
        help="half-width of the interval of --vertical_offset search "
        "(m, default %(default)s)",
    )
    parser.add_argument("--output_path", help="write the report as JSON to this file")


def _write_json(path: Path, data: dict) -> None:
    if not path.parent.is_dir():
        raise InputError(path.parent, "parent folder of --output_path does not exist")
    if path.is_dir():
        raise InputError(path, "--output_path is a folder; expected a JSON file name")
    write_json_atomic(path, data, indent=2, allow_nan=False)


def _run_control_points(args: argparse.Namespace) -> int:
    if args.input_path is None:
        raise InputError(None, "--control_points_path needs --input_path (the model)")
    if args.output_path is not None and not Path(args.output_path).parent.is_dir():
        raise InputError(
            Path(args.output_path).parent,
            "parent folder of --output_path does not exist",
        )
    checks = tuple(n for n in args.check_points.split(",") if n)
    report = evaluate_control_points(args.input_path, args.control_points_path, checks)
    print(f"# {args.input_path}: {args.control_points_path}")
    print(format_control_table(report))
    if args.output_path is not None:
        _write_json(Path(args.output_path), report)
    return 0


def run(args: argparse.Namespace) -> int:
    if (args.gt_path is None) == (args.control_points_path is None):
        raise InputError(
            None, "give exactly one of --gt_path and --control_points_path"
        )
    if args.control_points_path is not None:
        return _run_control_points(args)
    if args.input_path is None and not args.baseline:
        raise InputError(None, "--input_path is required unless --baseline is given")
    try:
        options = EvaluateOptions(
            registered_threshold_px=args.registered_threshold_px,
            across_vertical=args.across_vertical,
            remove_vertical_offset=not args.keep_vertical_offset,
            vertical_offset=args.vertical_offset,
            search_range_m=args.search_range_m,
        )
    except ValueError as exc:
        raise InputError(None, str(exc)) from None
    if args.output_path is not None:
        out = Path(args.output_path)
        if not out.parent.is_dir():  # fail before the work
            raise InputError(
                out.parent, "parent folder of --output_path does not exist"
            )

    report: dict | None = None
    if args.input_path is not None:
        result = evaluate_model(args.input_path, args.gt_path, options)
        print(f"# {result.result_path}")
        print(result.format_table())
        report = result.to_json()
    if args.baseline:
        base = evaluate_baseline(args.gt_path, options)
        if report is not None:
            print()
        print(f"# baseline: {base.result_path}")
        print(base.format_table())
        if report is None:
            report = base.to_json()
        else:
            report["baseline"] = base.to_json()
    if args.output_path is not None:
        _write_json(Path(args.output_path), report)
    return 0
