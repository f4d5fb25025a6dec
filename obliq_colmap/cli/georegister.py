"""``obliq-colmap georegister``: an existing COLMAP SfM model onto the map.

    obliq-colmap georegister --input_path SFM_MODEL --image_path DIR
        [--cadastre_path FILE] [--control_points_path GCP_FILE]
        [--priors_path PRIORS_MODEL] [--check_points NAME,...]
        [--camera_kind terrestrial|oblique|auto] [--crs EPSG:n]
        [--automatic_method auto|per_image|block]
        [--add_missing_images 0|1] --output_path OUT_MODEL

Writes, like ``register``, the model files, ``georef.json`` (local frame:
``world_abs = model_xyz + origin``) and ``report.json`` directly into
--output_path (atomically). Control points: OpenSfM/ODM ``gcp_list.txt`` or
OpenSfM's ``ground_control_points.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from obliq_colmap.colmap_io import GEOREF_FILE
from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder
from obliq_colmap.georegister.block import BLOCK_SOLVERS, BlockAdjustmentOptions
from obliq_colmap.georegister.options import (
    AUTOMATIC_METHODS,
    CAMERA_KINDS,
    GeoregisterOptions,
    VerticalOptions,
)
from obliq_colmap.georegister.run import georegister

logger = logging.getLogger(__name__)

REPORT_FILE = "report.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input_path", required=True, help="the SfM model folder")
    parser.add_argument("--image_path", required=True, help="folder of its images")
    parser.add_argument("--output_path", required=True, help="model folder to create")
    parser.add_argument("--cadastre_path", help="footprint map (GeoJSON, ...)")
    parser.add_argument(
        "--control_points_path", help="gcp_list.txt or ground_control_points.json"
    )
    parser.add_argument(
        "--priors_path", help="COLMAP model of rough GPS/INS poses (automatic mode)"
    )
    parser.add_argument(
        "--check_points",
        default="",
        help="comma-separated control point names withheld as check points",
    )
    parser.add_argument(
        "--camera_kind",
        default="auto",
        choices=CAMERA_KINDS,
        help="the vanishing-point prior: terrestrial (level camera), oblique "
        "(VP below the image), auto (both; default)",
    )
    parser.add_argument(
        "--automatic_method", default="auto", choices=AUTOMATIC_METHODS,
        help="automatic mode (map and priors, no control points): per_image "
        "(stage 2 registers each oblique image, one similarity from all their "
        "pairs), block (all images' vertical segments against the map at "
        "once: level cameras, a street), auto (block when the vertical came "
        "from the terrestrial VP prior; default)",
    )  # fmt: skip
    parser.add_argument("--crs", help="output CRS (default: the map's / the points')")
    parser.add_argument(
        "--block_adjustment", type=int, choices=(0, 1), default=1,
        help="bundle block adjustment after the similarity: SfM tracks, control "
        "points weighted by their accuracy, each image's vertical VP; the lens "
        "refined (default 1)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_solver", choices=BLOCK_SOLVERS, default="obliq",
        help="solver of the block adjustment: obliq (the project's bundle, "
        "default) or ceres (pycolmap's Ceres adjuster, the check; same problem)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_map_rows", type=int, choices=(0, 1), default=1,
        help="where a map is given, stage 2's corner-to-segment pairs as rows of "
        "the block adjustment (both solvers); in the automatic mode they and the "
        "priors' camera heights hold the block's datum (default 1)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_map_vertex_sigma", type=float, default=0.15, metavar="M",
        help="the map's vertex accuracy (m, each axis): the block's covariance "
        "carries each corner's error, shared by all its rows, through the "
        "adjustment; 0: the corners known exactly (default 0.15)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_facade_rows", type=int, choices=(0, 1), default=1,
        help="with the map rows, the map's facade edges (horizontal edges on the "
        "registered walls, matched across the images into tracks of one height) "
        "as rows too (both solvers; default 1)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_map_directions", choices=("vp", "measured"),
        default="measured",
        help="the map rows' segment lines: each segment's own fit (measured, "
        "default) or through the image's VP as stage 2 matched them (vp)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_refine_focal_length", type=int, choices=(0, 1),
        default=0,
        help="refine each camera's focal length in the block adjustment "
        "(default 0: with 2-3 control points it trades against the cameras' "
        "distance)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_refine_principal_point", type=int, choices=(0, 1),
        default=1,
        help="refine each camera's principal point in the block adjustment "
        "(default 1)",
    )  # fmt: skip
    parser.add_argument(
        "--block_adjustment_map_sigma_px", type=float, default=None,
        help="a priori sd of a map row, px (default: 1 px, the map's vertex "
        "noise on an oblique image; level cameras: that noise at the median "
        "range of their pairs, at least 1 px)",
    )  # fmt: skip
    parser.add_argument(
        "--add_missing_images", type=int, choices=(0, 1), default=0,
        help="images in --image_path that the model lacks: their rotation from "
        "vanishing points against a registered neighbour, their position from "
        "two or more SIFT matches to the model's points; added to the output "
        "(default 0)",
    )  # fmt: skip
    parser.add_argument("--no_progress", action="store_true")


def _path(value: str | None) -> Path | None:
    return None if value is None else Path(value)


def options_from_args(args: argparse.Namespace) -> GeoregisterOptions:
    """The command's options from its parsed arguments (also what the
    benchmarks use to run the same problem in-process)."""
    return GeoregisterOptions(
        vertical=VerticalOptions(camera_kind=args.camera_kind),
        check_points=tuple(n for n in args.check_points.split(",") if n),
        automatic_method=args.automatic_method,
        crs=args.crs,
        block_adjustment=bool(args.block_adjustment),
        block=BlockAdjustmentOptions(
            solver=args.block_adjustment_solver,
            map_rows=bool(args.block_adjustment_map_rows),
            facade_rows=bool(args.block_adjustment_facade_rows),
            map_vertex_sigma_m=args.block_adjustment_map_vertex_sigma or None,
            map_measured_directions=args.block_adjustment_map_directions == "measured",
            map_sigma_px=args.block_adjustment_map_sigma_px,
            refine_principal_point=bool(args.block_adjustment_refine_principal_point),
            refine_focal_length=bool(args.block_adjustment_refine_focal_length),
        ),
        add_missing_images=bool(args.add_missing_images),
        cadastre_path=_path(args.cadastre_path),
        control_points_path=_path(args.control_points_path),
        priors_path=_path(args.priors_path),
        progress=not args.no_progress,
    )


def run(args: argparse.Namespace) -> int:
    options = options_from_args(args)
    if not Path(args.image_path).is_dir():
        raise InputError(args.image_path, "image folder not found")
    result = georegister(Path(args.input_path), Path(args.image_path), options)
    with AtomicFolder(args.output_path) as tmp:
        result.reconstruction.write_binary(str(tmp))
        (tmp / GEOREF_FILE).write_text(
            json.dumps(result.georef.to_json(), indent=2) + "\n"
        )
        (tmp / REPORT_FILE).write_text(json.dumps(result.report, indent=2) + "\n")
    report = result.report
    if "placement" in report:
        pl = report["placement"]
        logger.info(
            "georegister (automatic): %d segment-corner pairs, rms %.3f deg; wrote %s",
            pl["num_pairs"], pl["rms_deg"], args.output_path,
        )  # fmt: skip
    else:
        cp = report["control_points"]
        logger.info(
            "georegister: %d control points, horizontal %.3f m median; wrote %s",
            cp.get("num_points", 0),
            cp.get("horizontal_m_median", float("nan")),
            args.output_path,
        )
    return 0
