"""``obliq-colmap export``: write a result model as absolute, OPK or text.

    obliq-colmap export --input_path MODEL --output_path OUT \\
                        --output_type absolute|opk|text
"""

from __future__ import annotations

import argparse
import logging

from obliq_colmap.priors import export_model
from obliq_colmap.priors.export import OUTPUT_TYPES

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--input_path", required=True, help="result model folder (with georef.json)"
    )
    parser.add_argument(
        "--output_path",
        required=True,
        help="model folder to create (absolute, text) or file to write (opk)",
    )
    parser.add_argument(
        "--output_type",
        required=True,
        choices=OUTPUT_TYPES,
        help="absolute: binary model in the map's coordinates (float32 readers "
        "lose precision there); opk: 'imageName X Y Z Omega Phi Kappa' text "
        "(Pix4D convention, degrees); text: the local model as COLMAP text files",
    )


def run(args: argparse.Namespace) -> int:
    out = export_model(args.input_path, args.output_path, args.output_type)
    logger.info("wrote %s (%s)", out, args.output_type)
    return 0
