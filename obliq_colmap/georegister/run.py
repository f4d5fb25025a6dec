"""The second workflow end to end: :func:`georegister` (nothing written yet).

1. Read the SfM model and the control points (in the map's CRS where a map
   is given, else the points' own projected CRS or their UTM zone).
2. The model's vertical from its images' VPs; the model rotated upright.
3. Control points triangulated in the upright model; the 4-DOF similarity
   (closed form with two, robust least squares with more; 7-DOF without a
   vertical). Check points (``check_points``) are triangulated and scored
   but not used.
4. The model moved into a local frame of the map (``georef.json``:
   ``world_abs = model_xyz + origin``), the control points added to
   points3D with their tracks at their GIVEN coordinates.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap import __version__
from obliq_colmap.colmap_io import Georef
from obliq_colmap.control import ControlPoints
from obliq_colmap.control.read import read_control_points
from obliq_colmap.control.residuals import point_residuals, summarise
from obliq_colmap.control.triangulate import require_usable, triangulate_control_points
from obliq_colmap.errors import InputError

from .block import BlockAdjustmentSummary, adjust_block
from .common import (
    GeoregisterResult,
    add_missing,
    read_sfm_model,
    upright,
    vertical_report,
)
from .map_rows import (
    MapRows,
    gate_map_rows,
    map_rows,
    pairs_on_map,
    with_facade_rows,
)
from .options import GeoregisterOptions
from .similarity import Similarity, similarity_7dof, similarity_upright
from .uncertainty import block_uncertainty_report
from .vertical import model_vertical

logger = logging.getLogger(__name__)


def _map_crs(options: GeoregisterOptions) -> str | None:
    if options.crs is not None or options.cadastre_path is None:
        return options.crs
    from obliq_colmap.cadastre import load_cadastre

    return load_cadastre(options.cadastre_path).crs


def _read_control(rec, options: GeoregisterOptions) -> ControlPoints:
    sizes = {
        rec.images[i].name: (rec.images[i].camera.width, rec.images[i].camera.height)
        for i in rec.reg_image_ids()
    }
    control = read_control_points(
        options.control_points_path,
        sizes,
        _map_crs(options),
        options.sigma_horizontal_m,
        options.sigma_vertical_m,
    )
    unknown = sorted(set(options.check_points) - set(control.names()))
    if unknown:
        raise InputError(
            options.control_points_path,
            f"--check_points names {', '.join(unknown)}, not in the file "
            f"(its points: {', '.join(control.names())})",
        )
    return control


def _fit(tri, control, use, vertical) -> Similarity:
    given = control.xyz()[use]
    sh = np.array([p.sigma_horizontal_m for p in control.points])[use]
    sv = np.array([p.sigma_vertical_m for p in control.points])[use]
    if vertical is not None:
        return similarity_upright(tri.xyz[use], given, sh, sv)
    return similarity_7dof(tri.xyz[use], given)


def _origin(control: ControlPoints, use: np.ndarray) -> np.ndarray:
    xyz = control.xyz()[use]
    z = xyz[np.isfinite(xyz[:, 2]), 2]
    return np.array(
        [
            np.round(xyz[:, 0].mean()),
            np.round(xyz[:, 1].mean()),
            np.round(z.mean()) if len(z) else 0.0,
        ]
    )


def _add_control_points(rec, control, tri, given_local, tri_local) -> dict[str, int]:
    """Control points into points3D at their given position (a 2D point at its
    triangulated height), with their tracks: name -> point3D_id."""
    added = {}
    for k in range(len(control)):
        if not tri.usable[k]:
            continue
        where = np.where(np.isfinite(given_local[k]), given_local[k], tri_local[k])
        track = pycolmap.Track()
        for image_id, xy in zip(tri.image_ids[k], tri.observations_px[k], strict=True):
            image = rec.images[int(image_id)]
            image.points2D.append(pycolmap.Point2D(np.asarray(xy, float)))
            track.add_element(int(image_id), image.num_points2D() - 1)
        pid = rec.add_point3D(where, track, np.array([255, 0, 255], np.uint8))
        added[control.points[k].name] = int(pid)
    return added


def georegister(
    input_path: Path, image_path: Path, options: GeoregisterOptions
) -> GeoregisterResult:
    """Bring an SfM model onto the map (see the module docstring)."""
    if options.control_points_path is None and options.cadastre_path is None:
        raise InputError(None, "give --control_points_path, --cadastre_path or both")
    if options.control_points_path is None:
        from .run_automatic import georegister_automatic

        return georegister_automatic(input_path, image_path, options)
    rec = read_sfm_model(input_path)
    control = _read_control(rec, options)
    # usable points first: a file that cannot work fails before stage 1 runs
    tri = triangulate_control_points(rec, control)
    check = np.array([p.name in options.check_points for p in control.points])
    use = tri.usable & ~check
    require_usable(dataclasses.replace(tri, usable=use), 2, options.control_points_path)
    vertical = model_vertical(rec, Path(image_path), options.vertical, options.progress)
    if vertical is None:
        logger.warning("fewer than %d images with a vertical VP: 7-DOF similarity",
                       options.vertical.min_images)  # fmt: skip
        require_usable(
            dataclasses.replace(tri, usable=use & np.isfinite(control.xyz()[:, 2])),
            3,
            options.control_points_path,
            "3D control points (no vertical from the images)",
        )
    R_up = upright(rec, vertical)
    missing = add_missing(rec, image_path, vertical, options)
    tri.xyz = tri.xyz @ R_up.T
    sim = _fit(tri, control, use, vertical)
    origin = _origin(control, use)
    to_local = pycolmap.Sim3d(
        sim.scale, pycolmap.Rotation3d(sim.rotation), sim.translation - origin
    )
    rec.transform(to_local)
    given_local = control.xyz() - origin
    tri_local = sim.apply(tri.xyz) - origin
    roles = {
        p.name: ("check" if c else "control")
        for p, c in zip(control.points, check, strict=True)
    }
    added = _add_control_points(rec, control, tri, given_local, tri_local)
    block = None
    if options.block_adjustment:
        # the similarity's inliers only: a point it rejected would pull the block
        inlier = np.zeros(len(use), bool)
        inlier[np.flatnonzero(use)] = sim.inliers
        on_map = _map_rows(rec, vertical, control, options, origin)
        block = _adjust(rec, control, added, inlier, vertical, options, origin, on_map)
        tri = triangulate_control_points(rec, control)
        tri_local = tri.xyz
    rows = point_residuals(rec, control, tri, given_local, tri_local, roles)
    georef = Georef(
        origin=origin,
        crs=control.crs,
        extra={
            "vertical_datum": "the control points' heights, unchanged",
            "software": f"obliq-colmap {__version__}",
        },
    )
    report = {
        "input_path": str(input_path),
        "control_points_path": str(options.control_points_path),
        "vertical": vertical_report(vertical, R_up),
        "similarity": _similarity_report(sim, control.names(), use),
        "control_points": summarise(rows, "control"),
        "check_points": summarise(rows, "check"),
        "points": rows,
        "num_control_points_written": len(added),
        "block_adjustment": None if block is None else block.report(),
        "uncertainty": block_uncertainty_report(
            block, {i: rec.images[i].name for i in rec.reg_image_ids()}
        ),
    }
    if missing is not None:
        report["missing_images"] = missing
    return GeoregisterResult(rec, georef, report)


def _map_rows(
    rec: pycolmap.Reconstruction,
    vertical,
    control: ControlPoints,
    options: GeoregisterOptions,
    origin: np.ndarray,
) -> MapRows | None:
    """With a map (and ``options.block.map_rows``): the
    map's corner lines as rows of the block adjustment, from stage 2 on
    every image started from its pose as the control points placed it
    (the map read in their CRS and frame, kept around the cameras), gated
    against that pose."""
    if options.cadastre_path is None or vertical is None or not options.block.map_rows:
        return None
    from obliq_colmap.cadastre import CadastreOptions, build_cadastre, read_footprints

    fp = read_footprints(options.cadastre_path, CadastreOptions(crs=control.crs))
    centres = np.array([rec.images[i].projection_center() for i in rec.reg_image_ids()])
    m = CadastreOptions().area_margin_m
    lo = centres[:, :2].min(0) - m + origin[:2]
    hi = centres[:, :2].max(0) + m + origin[:2]
    cad = build_cadastre(
        fp, CadastreOptions(crs=control.crs, area=(*lo, *hi)), origin=origin
    )
    pairs = pairs_on_map(
        rec, vertical, cad, options.registration, options.block.map_measured_directions
    )
    rows, _ = gate_map_rows(
        rec, map_rows(rec, cad.corner_xy, pairs), options.block.map_gate_px
    )
    if options.block.facade_rows:
        rows = with_facade_rows(rec, rows, vertical, cad, pairs)
    return rows


def _adjust(
    rec, control, added, use, vertical, options, origin, rows=None
) -> BlockAdjustmentSummary:
    """The block adjustment with the used control points' priors, every
    image's VP that the vertical kept (weight > 0) and the map's rows where
    given."""
    priors = {}
    for k, point in enumerate(control.points):
        if use[k] and point.name in added:
            sig = np.array([point.sigma_horizontal_m] * 2 + [point.sigma_vertical_m])
            given = point.xyz - origin
            sig[2] = sig[2] if np.isfinite(given[2]) else np.inf
            priors[added[point.name]] = (given, sig)
    verticals = {}
    if vertical is not None:
        for im in vertical.images:
            if im.weight > 0 and im.down_camera is not None:
                verticals[im.image_id] = (im.down_camera, im.sd_deg)
    return adjust_block(rec, priors, verticals, options.block, map_rows=rows)


def _similarity_report(sim: Similarity, names: list[str], use: np.ndarray) -> dict:
    inlier = np.zeros(len(use), bool)
    inlier[np.flatnonzero(use)] = sim.inliers
    return {
        "scale": sim.scale,
        "heading_deg": sim.heading_deg,
        "translation": sim.translation.tolist(),
        "points_used": [n for n, i in zip(names, inlier, strict=True) if i],
        "points_rejected": [
            n for n, u, i in zip(names, use, inlier, strict=True) if u and not i
        ],
    }
