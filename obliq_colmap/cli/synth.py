"""``obliq-colmap synth``: generate a synthetic oblique city with ground truth."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os

from obliq_colmap.cli import bool01
from obliq_colmap.errors import InputError
from obliq_colmap.synthetic.options import DISTORTION_MODELS, PRESETS, preset

logger = logging.getLogger(__name__)


#: command-line option -> SceneOptions field (all optional overrides).
_OVERRIDES: dict[str, tuple[str, type, str]] = {
    "image_width": (
        "image_width_px",
        int,
        "image width in px (height keeps 3:2); "
        "the field of view is kept, so the GSD scales",
    ),
    "grid_rows": ("grid_rows", int, "images per direction along the view"),
    "grid_cols": ("grid_cols", int, "images per direction across the view"),
    "prior_position_m": (
        "prior_position_m",
        float,
        "prior centre noise per horizontal axis (m)",
    ),
    "prior_height_m": ("prior_height_m", float, "prior centre height noise (m)"),
    "prior_rotation_deg": (
        "prior_rotation_deg",
        float,
        "prior rotation noise per axis (deg)",
    ),
    "prior_focal_percent": (
        "prior_focal_percent",
        float,
        "prior focal error per camera (%%)",
    ),
    "prior_vertical_datum_offset_m": (
        "prior_vertical_datum_offset_m",
        float,
        "added to all prior camera heights (m)",
    ),
    "slope_deg": ("slope_deg", float, "terrain slope (deg)"),
    "tilt_deg": ("tilt_deg", float, "camera tilt from nadir (deg)"),
    "nadir_head": (
        "nadir_head",
        bool01,
        "1: a fifth, nadir camera (a five-camera oblique system), images D_rc.jpg",
    ),
    "horizontal_fov_deg": (
        "horizontal_fov_deg",
        float,
        "horizontal field of view (deg); the GSD is kept, so a narrower lens "
        "flies higher",
    ),
    "vertex_noise_m": ("cadastre_vertex_noise_m", float, "cadastre vertex noise (m)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--output_path", required=True, help="scene folder to create (must be empty)"
    )
    parser.add_argument(
        "--preset",
        default="paper",
        choices=sorted(PRESETS),
        help="named scene (default paper)",
    )
    parser.add_argument("--seed", type=int, default=1, help="scene seed (default 1)")
    parser.add_argument(
        "--num_workers",
        type=int,
        default=os.cpu_count() or 1,
        help="rendering processes (default: number of CPUs)",
    )
    parser.add_argument(
        "--distortion",
        choices=sorted(DISTORTION_MODELS),
        default=None,
        help="lens distortion of the true cameras (default: the preset's)",
    )
    parser.add_argument("--no_progress", action="store_true", help="no progress bar")
    group = parser.add_argument_group("Scene (override the preset)")
    for name, (_, typ, help_) in _OVERRIDES.items():
        group.add_argument(f"--{name}", type=typ, default=None, help=help_)


def run(args: argparse.Namespace) -> int:
    from obliq_colmap.synthetic import generate_scene

    overrides = {
        field: getattr(args, name)
        for name, (field, _, _) in _OVERRIDES.items()
        if getattr(args, name) is not None
    }
    if args.distortion is not None:
        overrides["distortion"] = args.distortion
    try:
        options = preset(args.preset, **overrides)
    except ValueError as exc:
        raise InputError(None, f"invalid scene options: {exc}") from None
    if args.num_workers < 1:
        raise InputError(None, f"--num_workers must be >= 1, got {args.num_workers}")
    logger.info(
        "synth: preset %s, seed %d, %dx%d px, %d images, overrides %s",
        args.preset,
        args.seed,
        options.image_width_px,
        options.image_height_px,
        options.street_num_images
        if options.scene_kind == "street"
        else (5 if options.nadir_head else 4) * options.grid_rows * options.grid_cols,
        {k: v for k, v in dataclasses.asdict(options).items() if k in overrides}
        or "none",
    )
    generate_scene(
        args.output_path,
        options,
        seed=args.seed,
        show_progress=not args.no_progress,
        num_workers=args.num_workers,
        preset=args.preset,
    )
    return 0
