"""``obliq-colmap export_products``: terrain, building heights, LoD1 model
and map discrepancies from a registration.

    obliq-colmap export_products --input_path OUT_MODEL --cadastre_path MAP
                                 --output_path PRODUCTS_DIR [--image_path DIR]
                                 [--cell_size 5] [--num_workers N]
                                 [--find_missing 1] [--min_building_area 40]

OUT_MODEL is what ``register`` wrote (model, georef.json); MAP the map it was
registered to. With ``--image_path`` the roofs the views agree on give
eaves to the buildings whose walls gave none and to towers read at their
podium, the map discrepancies are searched too, and the buildings the
images show where the map has none (``missing.geojson``).
"""

from __future__ import annotations

import argparse
import logging

from obliq_colmap.errors import InputError
from obliq_colmap.products.missing import MissingOptions
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
        "--image_path",
        help="the images: eaves told by the roofs, and the map discrepancies",
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
    parser.add_argument(
        "--find_missing",
        type=int,
        choices=(0, 1),
        default=1,
        help="with --image_path: also report buildings missing from the map "
        "(missing.geojson: elevated tie points outside the footprints, a roof "
        "plane in a height sweep, vertical walls at its corners; default 1)",
    )
    parser.add_argument(
        "--min_building_area",
        type=float,
        default=40.0,
        help="a building missing from the map is reported when its roof plane "
        "covers at least this, m^2 (default 40: garages and sheds are not)",
    )


def run(args: argparse.Namespace) -> int:
    try:
        options = ProductsOptions(
            terrain=TerrainOptions(cell_size_m=args.cell_size),
            missing=MissingOptions(min_area_m2=args.min_building_area),
            find_missing=bool(args.find_missing),
            num_workers=args.num_workers,
        )
    except ValueError as exc:  # an option out of range: a user mistake
        raise InputError(None, f"--cell_size / --min_building_area: {exc}") from None
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
