"""``obliq-colmap export_dense``: a COLMAP dense-matching workspace from a
registration.

    obliq-colmap export_dense --input_path OUT_MODEL --image_path DIR
                              --output_path DENSE_DIR [--max_image_size N]
                              [--min_num_points 20] [--min_track_length 3]

DENSE_DIR gets COLMAP's ``image_undistorter`` layout (images/, sparse/,
stereo/ with patch-match.cfg and fusion.cfg), ``georef.json`` and
``dense.json``; run ``run-colmap-geometric.sh`` in it on a machine with CUDA.
"""

from __future__ import annotations

import argparse
import logging

from obliq_colmap.dense import DenseOptions, export_dense
from obliq_colmap.errors import InputError

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input_path", required=True, help="result model of register")
    parser.add_argument("--image_path", required=True, help="the model's images")
    parser.add_argument(
        "--output_path", required=True, help="dense workspace folder (new or empty)"
    )
    parser.add_argument(
        "--max_image_size",
        type=int,
        default=-1,
        help="longest side of the undistorted images, px (default -1: full size)",
    )
    parser.add_argument(
        "--min_num_points",
        type=int,
        default=DenseOptions.min_num_points,
        help="points an image needs in front of it for its depth range "
        f"(default {DenseOptions.min_num_points})",
    )
    parser.add_argument(
        "--min_track_length",
        type=int,
        default=DenseOptions.min_track_length,
        help="leave points seen in fewer images out of the workspace "
        f"(default {DenseOptions.min_track_length}; 2 keeps all, as COLMAP)",
    )


def run(args: argparse.Namespace) -> int:
    try:
        options = DenseOptions(
            max_image_size=args.max_image_size,
            min_num_points=args.min_num_points,
            min_track_length=args.min_track_length,
        )
    except ValueError as exc:  # an option out of range: a user mistake
        raise InputError(None, str(exc)) from None
    summary = export_dense(args.input_path, args.image_path, args.output_path, options)
    logger.info(
        "wrote %s: %d of %d images with a depth range and source images",
        args.output_path,
        summary["num_kept"],
        summary["num_images"],
    )
    return 0
