"""``obliq-colmap register``: oblique images + footprint map + priors -> COLMAP model.

    obliq-colmap register --image_path DIR --cadastre_path FOOTPRINTS.geojson \\
                          --input_path PRIORS_MODEL --output_path OUT_MODEL \\
                          [--stop_after initial|bundle] [--num_workers N] \\
                          [--dask_scheduler ADDRESS|local] \\
                          [--overlay_path DIR] [--camera_model MODEL] ...

Writes the COLMAP binary model, ``georef.json`` and ``report.json`` directly in
``--output_path`` (atomically) and prints one line per image.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import re
import sys
from pathlib import Path

from obliq_colmap.cadastre import CadastreOptions
from obliq_colmap.cli import bool01
from obliq_colmap.files import check_output_path
from obliq_colmap.geometry import SUPPORTED_MODELS
from obliq_colmap.parallel import available_cores
from obliq_colmap.pipeline import (
    STOP_AFTER,
    AdjustmentOptions,
    PipelineOptions,
    RefineOptions,
    RegistrationOptions,
    default_head_focal_min_images,
    run_register,
    summary_table,
    write_run,
)
from obliq_colmap.priors import PriorsOptions

logger = logging.getLogger(__name__)


#: The options dataclasses' fields as the command line names them, so that a
#: value out of range is reported with the option the user typed.
OPTION_OF_FIELD = {
    "prior_position_sigma_m": "--prior_position_sigma",
    "area_margin_m": "--cadastre_margin",
    "heading_step_deg": "--heading_step",
    "prior_rotation_sigma_deg": "--prior_rotation_sigma",
    "prior_focal_sigma": "--prior_focal_sigma",
    "ground_height": "--ground_height",
    "head_focal_min_images": "--head_focal_min_images",
    "rotation_prior_sigma_deg": "--bundle_rotation_sigma",
    "position_prior_sigma_m": "--bundle_position_sigma",
    "principal_point_prior_sigma": "--bundle_principal_point_sigma",
    "loss_scale_px": "--loss_scale",
    "map_vertex_sigma_m": "--map_vertex_sigma",
}


def _option_error(message: str) -> None:
    """An option out of its range: one line naming the command-line option,
    exit code 2 (as argparse does)."""
    for field, option in OPTION_OF_FIELD.items():
        message = re.sub(rf"\b(\w+Options\.)?{field}\b", option, message)
    print(f"obliq-colmap register: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    io = parser.add_argument_group("Input / output")
    io.add_argument("--image_path", required=True, help="folder of the images")
    io.add_argument(
        "--cadastre_path",
        required=True,
        help="building footprints (Polygon/MultiPolygon): GeoJSON (projected with a"
        " 'crs' member, or RFC 7946 longitude/latitude), Shapefile or GeoPackage",
    )
    io.add_argument(
        "--crs",
        default=None,
        help="the projected CRS of the priors (e.g. EPSG:25832): the map is"
        " reprojected into it (default: the map's own projected CRS, or the UTM"
        " zone of a longitude/latitude map); recorded in georef.json",
    )
    io.add_argument(
        "--cadastre_margin",
        type=float,
        default=CadastreOptions.area_margin_m,
        metavar="M",
        help="read the map within this distance (m) of the prior camera centres "
        "(default %(default)g; raise it for flights above ~1,200 m)",
    )
    io.add_argument(
        "--input_path",
        required=True,
        help="priors in the map's frame: a COLMAP model folder, or an "
        "'image_name X Y Z omega phi kappa' text file (Pix4D convention, degrees)",
    )
    io.add_argument(
        "--camera_path",
        help="intrinsics for text priors: a COLMAP model, cameras.txt/.bin or "
        "database (a model listing the images assigns cameras by name)",
    )
    io.add_argument(
        "--heading_step",
        type=float,
        default=PipelineOptions.heading_step_deg,
        metavar="DEG",
        help="priors with positions only (geo.txt, database pose priors): each "
        "image's heading is searched on a grid of this step through stage 2, "
        "its tilt from its vanishing point (default %(default)g; 0 refuses "
        "such priors)",
    )
    io.add_argument(
        "--camera_params",
        help="intrinsics for text priors, all images: [MODEL:]p1,p2,... in "
        "COLMAP's order and pixels (e.g. SIMPLE_RADIAL:3000,2000,1333,0)",
    )
    io.add_argument(
        "--output_path",
        required=True,
        help="result model folder (created; may exist if empty)",
    )
    io.add_argument(
        "--overlay_path", help="write one overlay PNG per image into this folder"
    )
    run = parser.add_argument_group("Run")
    run.add_argument(
        "--stop_after",
        choices=STOP_AFTER,
        default="bundle",
        help="last stage (default %(default)s)",
    )
    run.add_argument(
        "--num_workers",
        type=int,
        default=available_cores(),
        help="processes for the per-image stages (default: available cores, "
        "%(default)s)",
    )
    run.add_argument(
        "--dask_scheduler",
        metavar="ADDRESS|local",
        help="run the per-image stages on a Dask cluster: a scheduler's address "
        "(tcp://host:8786; the workers must see --image_path and --cadastre_path "
        "at the same paths) or 'local' for a LocalCluster of --num_workers "
        "one-thread processes; same results as without (needs the extra "
        "obliq-colmap[dask])",
    )
    run.add_argument("--no_progress", action="store_true", help="no progress bars")
    run.add_argument(
        "--head_focal_min_images",
        type=int,
        default=None,
        help="stage 2: estimate each camera's (head's) focal length from all its "
        "images when at least this many registered with enough inliers (0: off). "
        "Default: 3 with --stop_after initial (paper preset: 97-100 %% of the "
        "images below 2 px across the verticals instead of 89-94 %%), else 0 (the "
        "bundle estimates the focal lengths itself); 0 with --refine_focal_length 0",
    )
    prior = parser.add_argument_group("Priors")
    defaults = RegistrationOptions()
    prior.add_argument(
        "--prior_position_sigma",
        type=float,
        default=defaults.prior_position_sigma_m,
        help="1-sigma horizontal error of the prior centres, m (default %(default)s)",
    )
    prior.add_argument(
        "--prior_rotation_sigma",
        type=float,
        default=defaults.prior_rotation_sigma_deg,
        help="1-sigma error of the prior rotations, deg (default %(default)s)",
    )
    prior.add_argument(
        "--prior_focal_sigma",
        type=float,
        default=defaults.prior_focal_sigma,
        help="relative 1-sigma error of the prior focal lengths (default %(default)s)",
    )
    prior.add_argument(
        "--ground_height",
        type=float,
        help="ground height under the images in the priors' vertical datum, m "
        "(default: estimated per image)",
    )
    vanishing = parser.add_argument_group("Vanishing point")
    vanishing.add_argument(
        "--vp_line_weights",
        type=bool01,
        default=int(PipelineOptions().vanishing.line_weights),
        metavar="{0,1}",
        help="stage 1's RANSAC gives the pieces of one image line (a dashed "
        "centre line, a curb behind parked cars) one line's weight between "
        "them: streets seen along the heading no longer pull the vertical VP "
        "(better on suburban scenes of an external renderer, worse on some of "
        "our own; docs/STATUS.md) (default %(default)s)",
    )
    bundle = parser.add_argument_group("Bundle")
    bdefaults = AdjustmentOptions().bundle
    bundle.add_argument(
        "--camera_model",
        choices=sorted(SUPPORTED_MODELS),
        help="COLMAP camera model of the result (default: the priors')",
    )
    bundle.add_argument(
        "--refine_focal_length",
        type=bool01,
        default=bdefaults.refine_focal_length,
        metavar="{0,1}",
        help="refine focal lengths, per image in stage 2 and per camera in the "
        "bundle; 0 keeps the priors' (calibrated) focal lengths (default 1)",
    )
    bundle.add_argument(
        "--refine_principal_point",
        type=bool01,
        default=bdefaults.refine_principal_point,
        metavar="{0,1}",
        help="refine principal points (default 1)",
    )
    bundle.add_argument(
        "--refine_extra_params",
        type=bool01,
        default=bdefaults.refine_extra_params,
        metavar="{0,1}",
        help="refine the distortion of a camera model that has distortion terms "
        "(--camera_model SIMPLE_RADIAL, ...): the radial k1 per image in stage 2, "
        "then every distortion parameter per camera in the bundle, from the "
        "median of its images' k1; 0 holds the priors' (calibrated) distortion "
        "(default 1)",
    )
    bundle.add_argument(
        "--refine_facade_segments",
        type=bool01,
        default=0,
        metavar="{0,1}",
        help="refit the facade segments to sub-pixel edges on the full-resolution "
        "image (less noise; better on the paper preset, worse with unknown "
        "lenses: docs/STATUS.md; default 0)",
    )
    bundle.add_argument(
        "--bundle_rotation_sigma",
        type=float,
        default=bdefaults.rotation_prior_sigma_deg,
        metavar="DEG",
        help="use the priors' rotations as observations in the bundle with this "
        "1-sigma, deg (a calibrated INS: e.g. 0.01; checked as "
        "--bundle_position_sigma is); default: not used (the rough priors of "
        "--prior_rotation_sigma only guide stage 2)",
    )
    bundle.add_argument(
        "--bundle_position_sigma",
        type=float,
        default=bdefaults.position_prior_sigma_m,
        metavar="M",
        help="use the priors' camera centres as observations in the bundle with "
        "this 1-sigma per axis, m (survey-grade GNSS with the lever arm applied, "
        "in the map's horizontal frame: e.g. 0.1). Give the real accuracy: a "
        "sigma far below it bends the block to the priors (when the bundle then "
        "disagrees with most images and not without them, the run stops with "
        "an error); default: not used (the rough priors of "
        "--prior_position_sigma only guide stage 2)",
    )
    bundle.add_argument(
        "--bundle_position_offset",
        type=bool01,
        default=int(bdefaults.estimate_prior_offset),
        metavar="{0,1}",
        help="with --bundle_position_sigma: estimate one horizontal offset of the "
        "priors' centres against the map (a GNSS frame off the cadastre's, a lever "
        "arm left out; report.json's bundle.prior_offset_m); 0 where both frames "
        "agree to centimetres (default %(default)s)",
    )
    bundle.add_argument(
        "--bundle_principal_point_sigma",
        type=float,
        default=bdefaults.principal_point_prior_sigma or 0.0,
        metavar="F",
        help="hold each refined principal point near the priors' with this "
        "1-sigma, a fraction of the larger image side (through a long lens the "
        "block hardly tells a principal point's shift from a turn, so this "
        "prior decides it; a lens known to have its principal point far off "
        "the centre needs it in the priors or a larger sigma); 0: free "
        "(default %(default)s)",
    )
    bundle.add_argument(
        "--map_vertex_sigma",
        type=float,
        default=AdjustmentOptions().map_vertex_sigma_m,
        metavar="M",
        help="the cadastre's vertex noise (m, 1 sigma per axis): the bundle "
        "keeps the map's corners where the map has them and carries this error, "
        "shared by every view of a corner, into each image's predicted precision "
        "and its warnings (default %(default)s)",
    )
    bundle.add_argument(
        "--bundle_vp_observations",
        type=bool01,
        default=int(bdefaults.vp_observations),
        metavar="{0,1}",
        help="observe each image's vertical vanishing point in the bundle (stage "
        "1's VP where its status is ok, weighted by its covariance times a factor "
        "estimated between the rounds from each VP against the block without it; "
        "the VPs the block contradicts are dropped): it holds each image's tilt "
        "(default %(default)s)",
    )
    bundle.add_argument(
        "--bundle_measured_verticals",
        type=bool01,
        default=int(AdjustmentOptions().measured_vertical_directions),
        metavar="{0,1}",
        help="each vertical segment in the bundle on its own fitted line (its "
        "measured direction, weighted by the sd the rounds estimate for it), not "
        "on the line through stage 1's vanishing point, whose error would tilt "
        "every segment of the image alike (default %(default)s)",
    )
    bundle.add_argument(
        "--bundle_facade_lines",
        type=bool01,
        default=int(AdjustmentOptions().bundle.facade_lines),
        metavar="{0,1}",
        help="each facade track in the bundle a horizontal 3D line (height, offset "
        "across its map edge, direction), observed at both ends of every segment: "
        "the eaves' direction holds the block's tilt; 0: one point per segment "
        "(default %(default)s)",
    )
    bundle.add_argument(
        "--tie_points",
        type=bool01,
        default=int(AdjustmentOptions().tie_points),
        metavar="{0,1}",
        help="match SIFT tie points across the registered block (pairs from the "
        "poses' ground footprints, neighbouring heads included; pycolmap two-view "
        "verification), observe them in the bundle from its second solve (3D "
        "points; image pairs the first solve shows on a wrong geometry left out) "
        "and write them with their tracks to points3D.bin (default %(default)s)",
    )
    bundle.add_argument(
        "--loss_scale",
        type=float,
        default=bdefaults.loss_scale_px,
        help="scale of the robust loss, px (default %(default)s)",
    )


def run(args: argparse.Namespace) -> int:
    output_path = Path(args.output_path)
    check_output_path(output_path)  # fail before hours of work, not after
    if args.num_workers < 1:
        _option_error("--num_workers must be >= 1")
    head_focal = args.head_focal_min_images
    if head_focal is None:
        head_focal = (
            default_head_focal_min_images(args.stop_after)
            if args.refine_focal_length
            else 0
        )
    elif head_focal > 0 and not args.refine_focal_length:
        _option_error(
            "--head_focal_min_images estimates the heads' focal lengths, which "
            "--refine_focal_length 0 keeps: give one of the two"
        )
    try:
        options = PipelineOptions(
            stop_after=args.stop_after,
            heading_step_deg=args.heading_step,
            priors=PriorsOptions(
                camera_path=args.camera_path, camera_params=args.camera_params
            ),
            cadastre=CadastreOptions(crs=args.crs, area_margin_m=args.cadastre_margin),
            num_workers=args.num_workers,
            dask_scheduler=args.dask_scheduler,
            camera_model=args.camera_model,
            overlay_path=Path(args.overlay_path) if args.overlay_path else None,
            progress=not args.no_progress,
            head_focal_min_images=head_focal,
            vanishing=dataclasses.replace(
                PipelineOptions().vanishing,
                line_weights=bool(args.vp_line_weights),
            ),
            refine_segments=RefineOptions() if args.refine_facade_segments else None,
            registration=RegistrationOptions(
                prior_position_sigma_m=args.prior_position_sigma,
                prior_rotation_sigma_deg=args.prior_rotation_sigma,
                prior_focal_sigma=args.prior_focal_sigma,
                ground_height=args.ground_height,
                # A calibrated focal is held from the start: stage 2's
                # per-image focal would otherwise become the bundle's start.
                refine_focal=args.refine_focal_length,
                refine_distortion=args.refine_extra_params,
            ),
            adjustment=AdjustmentOptions(
                bundle=dataclasses.replace(
                    AdjustmentOptions().bundle,
                    refine_focal_length=args.refine_focal_length,
                    refine_principal_point=args.refine_principal_point,
                    refine_extra_params=args.refine_extra_params,
                    rotation_prior_sigma_deg=args.bundle_rotation_sigma,
                    position_prior_sigma_m=args.bundle_position_sigma,
                    estimate_prior_offset=bool(args.bundle_position_offset),
                    principal_point_prior_sigma=(
                        args.bundle_principal_point_sigma or None
                    ),
                    vp_observations=bool(args.bundle_vp_observations),
                    facade_lines=bool(args.bundle_facade_lines),
                    loss_scale_px=args.loss_scale,
                ),
                tie_points=bool(args.tie_points),
                measured_vertical_directions=bool(args.bundle_measured_verticals),
                map_vertex_sigma_m=args.map_vertex_sigma,
            ),
        )
    except ValueError as exc:  # an option out of its range
        _option_error(str(exc))
    result = run_register(args.image_path, args.cadastre_path, args.input_path, options)
    print(summary_table(result.report))
    if not result.block.images:
        logger.error("no image could be registered; nothing written")
        return 1
    write_run(output_path, result)
    logger.info(
        "wrote %d images, %d points to %s",
        len(result.block.images),
        len(result.points3D),
        output_path,
    )
    return 0
