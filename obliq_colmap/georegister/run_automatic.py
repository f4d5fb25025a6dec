"""The automatic mode of ``georegister`` (issue 27 item 3): the block onto the
map from its images' vertical segments and the map's corners, started from
the images' rough positions (``--priors_path``); the geometry is in
:mod:`.automatic`."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap import __version__
from obliq_colmap.cadastre import CadastreOptions, build_cadastre, read_footprints
from obliq_colmap.colmap_io import Georef
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.priors import PriorsOptions, read_priors
from obliq_colmap.registration import register_image

from .automatic import Rays, fit_block, segment_rays
from .block import BlockAdjustmentSummary, adjust_block
from .block_lines import pair_sd_deg
from .common import (
    GeoregisterResult,
    add_missing,
    read_sfm_model,
    upright,
    vertical_report,
)
from .lines_placement import lines_placement
from .map_rows import ImagePairs, gate_map_rows, map_rows, with_facade_rows
from .map_rows import image_pairs as pairs_of_image
from .options import GeoregisterOptions
from .similarity import similarity_upright
from .uncertainty import block_uncertainty_report
from .vertical import model_vertical

logger = logging.getLogger(__name__)


def _read_map_and_priors(rec, image_path, options):
    """The priors (absolute, the map's CRS) and the map kept around them."""
    if options.priors_path is None:
        raise InputError(
            options.cadastre_path,
            "the automatic mode (a map, no control points) needs --priors_path: "
            "the images' rough positions (a COLMAP model, as register's priors)",
        )
    fp = read_footprints(options.cadastre_path, CadastreOptions(crs=options.crs))
    priors = read_priors(options.priors_path, image_path, PriorsOptions(crs=fp.crs))
    names = {rec.images[i].name for i in rec.reg_image_ids()}
    centres = np.array(
        [im.cam_from_world.center for im in priors.images.values() if im.name in names]
    )
    if len(centres) < 3:
        raise InputError(
            options.priors_path,
            f"{len(centres)} of the model's images have a prior position; "
            "at least 3 are needed",
        )
    m = CadastreOptions().area_margin_m
    lo, hi = centres[:, :2].min(0) - m, centres[:, :2].max(0) + m
    cad = build_cadastre(fp, CadastreOptions(crs=options.crs, area=(*lo, *hi)))
    return priors, cad


def georegister_automatic(
    input_path: Path, image_path: Path, options: GeoregisterOptions
) -> GeoregisterResult:
    """The block onto the map from its images' vertical segments and the
    map's corners, started from the priors' positions (no control points)."""
    rec = read_sfm_model(input_path)
    priors, cad = _read_map_and_priors(rec, Path(image_path), options)
    vertical = model_vertical(rec, Path(image_path), options.vertical, options.progress)
    if vertical is None:
        raise InputError(
            input_path,
            "the automatic mode needs the vertical: too few images with a VP",
        )
    R_up = upright(rec, vertical)
    origin = np.array([cad.origin[0], cad.origin[1], 0.0])
    by_name = {im.name: im for im in priors.shifted(origin).images.values()}
    ids = [i for i in rec.reg_image_ids() if rec.images[i].name in by_name]
    model_c = np.array([rec.images[i].projection_center() for i in ids])
    prior_c = np.array([by_name[rec.images[i].name].cam_from_world.center for i in ids])
    start = similarity_upright(
        model_c, prior_c, np.full(len(ids), 5.0), np.full(len(ids), 5.0)
    )
    method = _method(vertical, options)
    if method == "block":
        model_R = np.array(
            [rec.images[i].cam_from_world().rotation.matrix() for i in ids]
        )
        prior_R = np.array(
            [by_name[rec.images[i].name].cam_from_world.rotation for i in ids]
        )
        coarse, registered, rays, pairs, image_pairs = lines_placement(
            rec, vertical, cad, start, model_c, prior_c, model_R, prior_R, options
        )
        th = np.arctan2(coarse.rotation[1, 0], coarse.rotation[0, 0])
        loss_deg = pair_sd_deg(rays, cad, pairs, coarse.scale, th,
                               coarse.translation[:2], options.block_lines)  # fmt: skip
    else:
        coarse, registered, rays, pairs, image_pairs = _stage2_placement(
            rec, vertical, cad, start, options
        )
        loss_deg = 0.05  # fit_block's default, as before
    theta0 = np.arctan2(coarse.rotation[1, 0], coarse.rotation[0, 0])
    placement = fit_block(
        rays,
        cad.corner_xy,
        pairs,
        (coarse.scale, theta0, coarse.translation[:2]),
        loss_deg,
    )
    Rz = np.eye(3)
    Rz[:2, :2] = placement.rotation()
    tz = float(np.median(prior_c[:, 2] - placement.scale * model_c[:, 2]))
    t = np.r_[placement.translation, tz]
    rec.transform(pycolmap.Sim3d(placement.scale, pycolmap.Rotation3d(Rz), t))
    # the model is upright and on the map (a turn about z keeps down at -z),
    # in the priors' frame: their rotations choose among the VP candidates
    rotations = {n: im.cam_from_world.rotation for n, im in by_name.items()}
    block = None
    if options.block_adjustment and options.block.map_rows:
        prior_centers = {i: c for i, c in zip(ids, prior_c, strict=True)}
        adjust = options
        if method == "block" and options.block.map_sigma_px is None:
            adjust = _level_rows(rec, placement, rays, pairs, cad, options)
        block = _adjust_on_map(rec, vertical, cad, image_pairs, prior_centers, adjust)
    missing = add_missing(rec, image_path, vertical, options, rotations)
    georef = Georef(
        origin=origin,
        crs=cad.crs,
        extra={
            "vertical_datum": "the priors' camera heights (--priors_path)",
            "software": f"obliq-colmap {__version__}",
        },
    )
    names = {i: rec.images[i].name for i in rec.reg_image_ids()}
    report = {
        "input_path": str(input_path),
        "mode": "automatic (map and priors, no control points)",
        "vertical": vertical_report(vertical, R_up),
        "placement": {
            "scale": placement.scale,
            "heading_deg": float(np.degrees(placement.theta)),
            "translation": t.tolist(),
            "num_pairs": placement.num_pairs,
            "rms_deg": placement.rms_deg,
            "pairs_per_image": {
                names[i]: int(placement.pairs_per_image[k])
                for k, i in enumerate(registered)
            },
            "start_from_priors": {
                "scale": start.scale,
                "heading_deg": start.heading_deg,
            },
            "method": method,
            "stage2" if method == "per_image" else "block_lines": {
                "images_registered": len(registered)
                if method == "per_image"
                else int(np.count_nonzero(placement.pairs_per_image)),
                "scale": coarse.scale,
                "heading_deg": coarse.heading_deg,
            },
        },
        "block_adjustment": None if block is None else block.report(),
        "uncertainty": block_uncertainty_report(
            block, {i: rec.images[i].name for i in rec.reg_image_ids()}
        ),
    }
    if missing is not None:
        report["missing_images"] = missing
    return GeoregisterResult(rec, georef, report)


def _level_rows(rec, placement, rays, pairs, cad, options) -> GeoregisterOptions:
    """The map rows' sd for level cameras: the map's vertex noise at the
    pairs' median range (a street camera 15 m from a corner: 0.15 m is ~6 px,
    where an oblique image's 0.15 m is ~1 px), at least 1 px; the gate
    scaled with it."""
    c, s = np.cos(placement.theta), np.sin(placement.theta)
    origin = placement.scale * rays.origin[pairs[:, 0]] @ np.array([[c, s], [-s, c]])
    rng = np.linalg.norm(
        cad.corner_xy[pairs[:, 1]] - origin - placement.translation, axis=1
    )
    focal = np.median([rec.cameras[k].mean_focal_length() for k in rec.cameras])
    sigma = max(1.0, float(focal * options.block_lines.map_noise_m / np.median(rng)))
    logger.info("automatic (block): map rows at %.1f px (median range %.1f m)",
                sigma, float(np.median(rng)))  # fmt: skip
    block = dataclasses.replace(
        options.block, map_sigma_px=sigma, map_gate_px=options.block.map_gate_px * sigma
    )
    return dataclasses.replace(options, block=block)


def _method(vertical, options: GeoregisterOptions) -> str:
    """``options.automatic_method``, "auto" resolved by the camera kind
    the vertical came from: level cameras see too few corners per image for
    stage 2, whose search also assumes a camera high above the ground."""
    if options.automatic_method != "auto":
        return options.automatic_method
    return "block" if vertical.kind == "terrestrial" else "per_image"


def _adjust_on_map(
    rec: pycolmap.Reconstruction,
    vertical,
    cad,
    image_pairs: dict[int, ImagePairs],
    prior_centers: dict[int, np.ndarray],
    options: GeoregisterOptions,
) -> BlockAdjustmentSummary | None:
    """The block adjustment held by the map (stage 2's pairs as corner-to-line
    rows, gated against the placed block), the VPs (the tilt) and the
    priors' camera heights (the vertical datum, a weak prior)."""
    if rec.num_points3D() == 0:
        # no tracks: nothing holds the block together, each image would be
        # refitted alone on its own rows (the sample's true cameras as a
        # model: 0.5-2.0 px -> up to 4.3 px)
        logger.warning(
            "automatic mode: the model has no 3D points (tracks); the block "
            "adjustment is not run"
        )
        return None
    rows = map_rows(rec, cad.corner_xy, image_pairs)
    rows, _ = gate_map_rows(rec, rows, options.block.map_gate_px)
    if len(rows) == 0:
        logger.warning("automatic mode: no map rows near the block; not adjusted")
        return None
    if options.block.facade_rows:
        rows = with_facade_rows(rec, rows, vertical, cad, image_pairs)
    verticals = {
        im.image_id: (im.down_camera, im.sd_deg)
        for im in vertical.images
        if im.weight > 0 and im.down_camera is not None
    }
    return adjust_block(
        rec, {}, verticals, options.block, map_rows=rows, prior_centers=prior_centers
    )


def _stage2_placement(rec, vertical, cad, start, options):
    """Stage 2 on every image (its segments and VP, its pose from the start
    similarity as the prior), then the robust 4-DOF similarity from the
    model's camera centres to the registered ones: each image is an
    independent measurement of where the block lies, and the robust fit
    leaves out the ones stage 2 got wrong. Returns that similarity, the
    registered image ids, and their inlier segments as rays with their map
    corners (``pairs``: (P, 2) ray, corner) for the joint fit."""
    model_c, reg_c, reg_ids = [], [], []
    origins, bearings, ray_image, pairs = [], [], [], []
    image_pairs: dict[int, ImagePairs] = {}
    n_rays = 0
    Rz = start.rotation
    for im in vertical.images:
        if im.segments is None or len(im.segments) < 3:
            continue
        image = rec.images[im.image_id]
        pose = image.cam_from_world()
        R_m = pose.rotation.matrix()
        c_m = image.projection_center()
        R_prior = R_m @ Rz.T
        c_prior = start.apply(c_m[None])[0]
        prior = Pose.from_center(R_prior, c_prior)
        cam = image.camera
        camera = Camera(cam.model.name, cam.width, cam.height, np.asarray(cam.params))
        result = register_image(
            im.segments, im.down_camera, camera, prior, cad,
            options.registration, segments_undistorted=True,
        )  # fmt: skip
        if result.success:
            model_c.append(c_m)
            reg_c.append(result.cam_from_world.center)
            reg_ids.append(im.image_id)
            # stage 2's inlier pairs, as rays of the MODEL (its segments
            # undistorted with this camera's pinhole part, as stage 1's are)
            o, b = segment_rays(result.inlier_segments_px, im.K, R_m, c_m)
            k = len(b)
            origins.append(np.repeat(o[None], k, axis=0))
            bearings.append(b)
            ray_image.append(np.full(k, len(model_c) - 1))
            pairs.append(np.c_[n_rays + np.arange(k), result.inlier_pairs[:, 0]])
            image_pairs[im.image_id] = pairs_of_image(
                im, result, options.block.map_measured_directions
            )
            n_rays += k
    if len(model_c) < 3:
        raise InputError(
            None,
            f"the automatic mode: stage 2 registered {len(model_c)} images to "
            "the map; at least 3 are needed",
        )
    model_c, reg_c = np.array(model_c), np.array(reg_c)
    target = np.c_[reg_c[:, :2], start.apply(model_c)[:, 2]]  # heights: priors'
    n = len(model_c)
    sim = similarity_upright(model_c, target, np.full(n, 1.0), np.full(n, 5.0))
    logger.info(
        "automatic: stage 2 registered %d images, %d agree on the block",
        n, int(sim.inliers.sum()),
    )  # fmt: skip
    rays = Rays(
        np.concatenate(origins), np.concatenate(bearings), np.concatenate(ray_image)
    )
    return sim, reg_ids, rays, np.concatenate(pairs), image_pairs
