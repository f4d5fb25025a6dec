"""The block adjustment in the project's bundle (``BlockAdjustmentOptions.
solver="obliq"``, the default): the SfM model as a
:class:`~obliq_colmap.bundle.BundleProblem` and back.

- cameras: the model's, intrinsics refined as the options say (the focal
  held by default; fx and fy refined independently when refined, as
  COLMAP's adjuster does);
- images: every registered image's ``cam_from_world``;
- the SfM tracks: tie points (3D unknowns eliminated by their 3x3 blocks),
  two reprojection rows per observation, Cauchy loss on the observation's
  2D error at ``loss_scale_px`` (Ceres' loss on pycolmap's 2-row cost);
- control points: tie points whose coordinates are observed
  (``BundleProblem.tie_prior_xyz`` at their stated sigmas, a 2D point's
  height free);
- VPs: each image's vertical VP (``BundleProblem.vertical_vps``) with an
  isotropic covariance of its angular sd, no robust loss (the vertical's
  robust mean already dropped the images that disagree).

- the map (where given and ``BlockAdjustmentOptions.map_rows``): the
  corner-to-line rows of stage 2's inlier pairs (:mod:`.map_rows`), points
  at fixed heights on the corners' verticals as in ``register``'s stage 3
  (``corner_heights="fixed"``), at ``map_sigma_px`` with the Cauchy loss at
  ``loss_scale_px``; and (``facade_rows``) the facade tracks' rows
  (:mod:`.facade_rows`), their heights unknowns, at 1 px with the same loss;
- the vertical datum without control points (the automatic mode): the
  block's mean camera height held where the placement put it (the
  priors' heights; the bundle's gauge row, ``component_mean_camera_height``:
  the tracks link the block into one component), or, with
  ``prior_center_sigma_m``, the priors' centres observed at that sd with
  one horizontal offset estimated (``BundleOptions.position_prior_sigma_m``,
  ``estimate_prior_offset``).

No height unknowns but the facade tracks'; with control points no gauge rows
(they hold the datum), as in the Ceres problem.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pycolmap

from obliq_colmap.bundle import BundleOptions, BundleProblem, solve_bundle
from obliq_colmap.geometry import Camera, Pose, calibration_matrix

from .block import (
    BlockAdjustmentOptions,
    BlockAdjustmentSummary,
    BlockUncertainty,
    VerticalRow,
    facade_outlier_round,
    facade_row_weighting,
    map_row_weighting,
)
from .facade_rows import empty_facade_rows
from .map_rows import MapRows, empty_map_rows

logger = logging.getLogger(__name__)

#: Gauss-Newton steps on the facade tracks' heights alone (the cameras
#: held) before the joint solve (``BundleOptions.height_initialisation_steps``)
FACADE_HEIGHT_STEPS = 3


def bundle_options(
    options: BlockAdjustmentOptions,
    prior_centers: bool = False,
    hold_mean_height: bool = False,
) -> BundleOptions:
    """The bundle's options for the block's problem (the same cost as the
    Ceres problem's: unit weights, Cauchy on the tracks, plain VP rows; the
    map rows where given; the priors' centres or the mean camera height as
    the vertical datum where asked)."""
    map_sigma, map_scale = map_row_weighting(options)
    facade_sigma, _ = facade_row_weighting(options)  # at the map rows' scale
    return BundleOptions(
        loss="cauchy",
        loss_scale_px=map_scale,  # the map rows' (the tracks have their own)
        tie_sigma_px=1.0,
        tie_loss_scale_px=options.loss_scale_px,
        refine_focal_length=options.refine_focal_length,
        refine_aspect_ratio=True,  # as COLMAP's adjuster
        refine_principal_point=options.refine_principal_point,
        refine_extra_params=options.refine_extra_params,
        gauge="component_mean_camera_height" if hold_mean_height else "none",
        corner_heights="fixed",
        vertical_sigma_px=map_sigma,
        horizontal_sigma_px=facade_sigma,
        position_prior_sigma_m=(
            options.prior_center_sigma_m if prior_centers else None
        ),
        estimate_prior_offset=True,
        height_initialisation_steps=0,
        vp_observations=True,
        vp_loss_scale=np.inf,
        max_iterations=options.max_num_iterations,
        function_tolerance=options.function_tolerance,
        compute_precision=options.covariance,
        map_corner_sigma_m=options.map_vertex_sigma_m,
    )


def vp_covariance(row: VerticalRow, K: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of the unit homogeneous VP ``v`` whose direction
    ``K^-1 v`` has the isotropic angular sd ``row.sd_rad``:
    ``sd^2 |K^-1 v|^2 K K^T`` (through the bundle's propagation it gives
    ``sd^2`` on both tangent axes)."""
    nu = np.linalg.norm(np.linalg.solve(K, row.vp))
    return row.sd_rad**2 * nu**2 * (K @ K.T)


def block_problem(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, VerticalRow],
    map_rows: MapRows | None = None,
    prior_centers: dict[int, np.ndarray] | None = None,
) -> tuple[BundleProblem, np.ndarray]:
    """The model as a bundle problem, and the (T,) point3D ids of its tie
    points in order. An image without a prior centre is observed where it
    stands (the priors leave it out; its tracks place it)."""
    image_ids = sorted(rec.reg_image_ids())
    index = {iid: k for k, iid in enumerate(image_ids)}
    cameras = {
        cid: Camera(c.model.name, c.width, c.height, np.array(c.params), cid)
        for cid, c in rec.cameras.items()
    }
    poses = {i: Pose.from_rigid3d(rec.images[i].cam_from_world()) for i in image_ids}
    point_ids = np.array(sorted(rec.point3D_ids()), np.int64)
    slot = {int(p): t for t, p in enumerate(point_ids)}
    img, pt, xy = [], [], []
    for i in image_ids:
        for p2 in rec.images[i].get_observation_points2D():
            img.append(index[i])
            pt.append(slot[p2.point3D_id])
            xy.append(p2.xy)
    tie_xyz = np.array([rec.points3D[int(p)].xyz for p in point_ids]).reshape(-1, 3)
    prior_xyz = np.zeros_like(tie_xyz)
    prior_sigma = np.full_like(tie_xyz, np.inf)
    for pid, (given, sigma) in control_point_ids.items():
        if pid in slot:
            sig = np.where(np.isfinite(given), sigma, np.inf)
            prior_sigma[slot[pid]] = sig
            prior_xyz[slot[pid]] = np.where(np.isfinite(sig), given, 0.0)
    vps, covs = {}, {}
    for i, row in verticals.items():
        if i in index:
            cam = cameras[rec.images[i].camera_id]
            vps[i] = row.vp
            covs[i] = vp_covariance(row, calibration_matrix(cam.model, cam.params))
    rows = map_rows if map_rows is not None else empty_map_rows()
    rows = rows.select(np.isin(rows.image_id, image_ids))
    fac = rows.facades.select(image_ids) if rows.facades is not None else None
    if fac is None or len(fac) == 0:
        fac = empty_facade_rows()
    centers = None
    if prior_centers:  # every image observed (the bundle wants all or none)
        centers = {
            i: np.asarray(prior_centers.get(i, poses[i].center), float)
            for i in image_ids
        }
    problem = BundleProblem(
        cameras=cameras,
        poses=poses,
        image_camera={i: rec.images[i].camera_id for i in image_ids},
        image_ids=tuple(image_ids),
        corner_xy=rows.xy,
        corner_heights=rows.height,
        vertical_image=np.array([index[int(i)] for i in rows.image_id], np.int64),
        vertical_corner=np.arange(len(rows)),
        vertical_line=rows.line,
        facade_heights=fac.height.copy(),
        horizontal_image=np.array([index[int(i)] for i in fac.image_id], np.int64),
        horizontal_height=fac.track,
        horizontal_anchor_xy=fac.anchor_xy[fac.track],
        horizontal_line=fac.line,
        # the facade rows' anchors carry the map's noise across their
        # edge: an unknown to the precision (the solve keeps them fixed)
        horizontal_offset_normal=fac.normal[fac.track] if len(fac) else None,
        prior_centers=centers,
        vertical_vps=vps or None,
        vertical_vp_covariances=covs or None,
        tie_xyz=tie_xyz,
        tie_image=np.array(img, np.int64),
        tie_point=np.array(pt, np.int64),
        tie_xy=np.array(xy, float).reshape(-1, 2),
        tie_prior_xyz=prior_xyz,
        tie_prior_sigma=prior_sigma,
    )
    return problem, point_ids


def initial_facade_heights(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, VerticalRow],
    options: BlockAdjustmentOptions,
    map_rows: MapRows,
) -> MapRows:
    """``map_rows`` with its facade rows those of rec's registered images
    (``FacadeRows.select``) and their tracks' heights fitted to the block
    with the cameras held: the start of the obliq solver's first solve
    (its ``FACADE_HEIGHT_STEPS`` height steps, the bundle's own, run with
    no joint iteration), for the Ceres solver to start from the same
    heights. The Cauchy loss makes the start matter: from the images' own
    grounds Ceres' joint steps left tracks matched a floor off in another
    minimum (paper block, automatic: 7987.6 against 7975.8)."""
    problem, _ = block_problem(rec, control_point_ids, verticals, map_rows)
    bopts = dataclasses.replace(
        bundle_options(options),
        height_initialisation_steps=FACADE_HEIGHT_STEPS,
        max_iterations=0,
        compute_precision=False,
    )
    result = solve_bundle(problem, bopts)
    facades = map_rows.facades.select(problem.image_ids)
    facades.height = np.array(result.facade_heights, float)
    return dataclasses.replace(map_rows, facades=facades)


def adjust_block_bundle(
    rec: pycolmap.Reconstruction,
    control_point_ids: dict[int, tuple[np.ndarray, np.ndarray]],
    verticals: dict[int, VerticalRow],
    options: BlockAdjustmentOptions,
    map_rows: MapRows | None = None,
    prior_centers: dict[int, np.ndarray] | None = None,
) -> BlockAdjustmentSummary:
    """:func:`~obliq_colmap.georegister.block.adjust_block` in the project's
    bundle; the solved cameras, poses and points written back into ``rec``."""
    use_priors = bool(prior_centers) and options.prior_center_sigma_m is not None
    problem, point_ids = block_problem(
        rec,
        control_point_ids,
        verticals,
        map_rows,
        prior_centers if use_priors else None,
    )
    # without control points (the automatic mode) nothing else holds the
    # height: the mean camera height stays where the placement put it
    hold = not control_point_ids and not use_priors
    bopts = bundle_options(options, use_priors, hold)
    if len(problem.facade_heights):
        # the tracks' heights come from the images' own grounds: fitted to
        # the block with the cameras held before the joint solve
        bopts = dataclasses.replace(
            bopts, height_initialisation_steps=FACADE_HEIGHT_STEPS
        )
    result = solve_bundle(problem, bopts)
    _write_back(rec, result, point_ids)
    initial_cost, iterations = result.summary.initial_cost, 0
    if len(problem.facade_heights):
        # one outlier round on the facade rows (register's rounds, once),
        # then the adjustment again from the solved block
        kept = facade_outlier_round(
            map_rows,
            problem.image_ids,
            result.horizontal_residuals_px,
            result.facade_heights,
        )
        problem, point_ids = block_problem(
            rec,
            control_point_ids,
            verticals,
            kept,
            prior_centers if use_priors else None,
        )
        iterations = result.summary.num_iterations
        result = solve_bundle(problem, bopts)
        _write_back(rec, result, point_ids)
    s = result.summary
    iterations += s.num_iterations  # both solves, from the first's start
    n_ctrl = int(np.sum(np.any(np.isfinite(problem.tie_prior_sigma), axis=1)))
    logger.info(
        "block adjustment (obliq): cost %.6g -> %.6g in %d iterations (%d "
        "control points, %d verticals, %d map rows, %d facade rows), %s",
        initial_cost, s.final_cost, iterations, n_ctrl,
        len(result.vp_angle_deg), len(problem.corner_xy),
        len(problem.horizontal_image), s.termination,
    )  # fmt: skip
    uncertainty = None
    if result.pose_covariance:
        uncertainty = BlockUncertainty(
            pose_covariance=dict(result.pose_covariance),
            image_precision_px=dict(result.image_precision_px),
            variance_factor=float(result.variance_factor),
            variance_components=dict(result.variance_components),
        )
    return BlockAdjustmentSummary(
        uncertainty=uncertainty,
        initial_cost=float(initial_cost),
        final_cost=float(s.final_cost),
        iterations=int(iterations),
        num_control_rows=n_ctrl,
        num_vertical_rows=len(result.vp_angle_deg),
        termination=s.termination,
        solver="obliq",
        num_map_rows=len(problem.corner_xy),
        num_facade_rows=len(problem.horizontal_image),
        num_facade_tracks=len(problem.facade_heights),
    )


def _write_back(rec: pycolmap.Reconstruction, result, point_ids) -> None:
    """The solved cameras, poses and tie points into ``rec``."""
    for cid, cam in result.cameras.items():
        rec.cameras[cid].params = cam.params
    for iid, pose in result.poses.items():
        rec.frame(rec.images[iid].frame_id).rig_from_world = pose.to_rigid3d()
    for t, pid in enumerate(point_ids):
        rec.points3D[int(pid)].xyz = result.tie_xyz[t]
