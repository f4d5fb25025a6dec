"""``obliq-colmap report``: the HTML inspection report of a registration."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from obliq_colmap.report.build import ReportOptions, build_report

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Write an HTML report of a registration: the per-image table, the map "
        "projected onto every image before (priors) and after registration, "
        "residual histograms, the cameras' uncertainty and plan views. The "
        "output folder holds index.html, report.json and images/; it opens "
        "offline."
    )
    parser.add_argument(
        "--input_path", required=True, type=Path, help="model written by register"
    )
    parser.add_argument("--image_path", required=True, type=Path, help="image folder")
    parser.add_argument(
        "--cadastre_path", required=True, type=Path, help="the footprint GeoJSON"
    )
    parser.add_argument(
        "--output_path", required=True, type=Path, help="new (or empty) report folder"
    )
    parser.add_argument(
        "--priors_path",
        type=Path,
        default=None,
        help="the priors model register read (default: the one recorded in the "
        "model's report.json; without either, no 'before' overlays)",
    )


def run(args: argparse.Namespace) -> int:
    page = build_report(
        ReportOptions(
            args.input_path,
            args.image_path,
            args.cadastre_path,
            args.output_path,
            args.priors_path,
        )
    )
    logger.info("wrote %s", page)
    return 0
