"""``obliq-colmap export_products``: terrain, building heights, LoD1 model
and map discrepancies from a registration.

    obliq-colmap export_products --input_path OUT_MODEL --cadastre_path MAP
                                 --output_path PRODUCTS_DIR [--image_path DIR]
                                 [--cell_size 5] [--num_workers N]

OUT_MODEL is what ``register`` wrote (model, georef.json); MAP the map it was
registered to. With ``--image_path`` the map discrepancies are searched too.
"""

from __future__ import annotations

import argparse
import logging

from obliq_colmap.errors import InputError
from obliq_colmap.products.run import ProductsOptions, make_products
from obliq_colmap.products.terrain import TerrainOptions

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input_path", required=True, help="result model of register")
    parser.add_argument(
        "--cadastre_path", required=True, help="the map (GeoJSON) it was registered to"
    )
    parser.add_argument(
        "--output_path", required=True, help="products folder (new or empty)"
    )
    parser.add_argument(
        "--image_path", help="the images: also search the map discrepancies"
    )
    parser.add_argument(
        "--cell_size",
        type=float,
        default=5.0,
        help="terrain grid cell size, m (default 5)",
    )
    parser.add_argument(
        "--num_workers", type=int, default=0, help="processes (default 0: all cores)"
    )


def run(args: argparse.Namespace) -> int:
    try:
        options = ProductsOptions(
            terrain=TerrainOptions(cell_size_m=args.cell_size),
            num_workers=args.num_workers,
        )
    except ValueError as exc:  # an option out of range: a user mistake
        raise InputError(None, f"--cell_size: {exc}") from None
    summary = make_products(
        args.input_path, args.cadastre_path, args.output_path, args.image_path, options
    )
    logger.info(
        "wrote %s: %d of %d buildings with an eave height",
        args.output_path,
        summary["buildings"]["with_eave_height"],
        summary["buildings"]["mapped"],
    )
    return 0
