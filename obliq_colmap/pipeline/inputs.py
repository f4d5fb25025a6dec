"""The run's inputs: the priors, the images' presence and the map read and
checked (:func:`load_inputs`), and the per-image work (:func:`image_tasks`).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from obliq_colmap.cadastre import CadastreOptions, build_cadastre, read_footprints
from obliq_colmap.errors import InputError
from obliq_colmap.pipeline.options import PipelineOptions
from obliq_colmap.pipeline.workers import ImageTask
from obliq_colmap.priors import prior_format, read_priors
from obliq_colmap.state import Inputs

__all__ = ["image_tasks", "load_inputs"]

logger = logging.getLogger(__name__)

#: Prior formats that carry camera positions but no rotations.
POSITION_ONLY_FORMATS = ("geo", "database")


def load_inputs(
    image_path: str | Path,
    cadastre_path: str | Path,
    input_path: str | Path,
    options: PipelineOptions,
) -> Inputs:
    """Read and check the priors, the images' presence and the map.

    Raises
    ------
    InputError
        Any user mistake (missing files, unreadable map or model, degrees).
    """
    image_path, cadastre_path = Path(image_path), Path(cadastre_path)
    footprints = read_footprints(cadastre_path, options.cadastre)
    # Priors in geographic or another CRS (geo.txt, XMP, databases) go into
    # the map's CRS when the map declares one.
    prior_options = options.priors
    if prior_options.crs is None and footprints.crs is not None:
        prior_options = dataclasses.replace(prior_options, crs=footprints.crs)
    # positions only (geo.txt, database priors): a heading search, unless off
    position_only = prior_format(Path(input_path)) in POSITION_ONLY_FORMATS
    if position_only and options.heading_step_deg > 0:
        prior_options = dataclasses.replace(prior_options, require_rotation=False)
        logger.info(
            "%s: positions only: each image's heading is searched every %g deg",
            input_path, options.heading_step_deg,
        )  # fmt: skip
    priors_abs = read_priors(input_path, image_path, prior_options)
    if not priors_abs.images:
        raise InputError(input_path, "the priors model has no images")
    cadastre_options = _with_block_area(options.cadastre, priors_abs)
    cadastre = build_cadastre(footprints, cadastre_options)
    if cadastre.num_corners == 0:
        raise InputError(cadastre_path, "the map has no usable footprints")
    origin = np.array([cadastre.origin[0], cadastre.origin[1], 0.0])
    priors = priors_abs.shifted(origin)
    centres = np.array([im.cam_from_world.center for im in priors.images.values()])
    far = np.linalg.norm(centres[:, :2], axis=1).min()
    extent = np.ptp(cadastre.corner_xy, axis=0).max()
    if far > 10.0 * extent + 5_000.0:
        raise InputError(
            input_path,
            f"the prior camera centres lie {far / 1000:.1f} km from the map "
            f"{cadastre_path} (is it in another CRS?)",
        )
    cameras = {}
    for cid, cam in priors.cameras.items():
        model = options.camera_model or cam.model
        if model != cam.model:
            logger.info("camera %d: %s -> %s", cid, cam.model, model)
        cameras[cid] = cam.with_model(model)
    return Inputs(
        image_path,
        cadastre_path,
        cadastre,
        priors,
        cameras,
        Path(input_path),
        cadastre_options,
        position_only,
    )


def _with_block_area(options: CadastreOptions, priors_abs) -> CadastreOptions:
    """The map options with ``area``: the prior camera centres' bounds widened
    by ``area_margin_m`` (absolute coordinates, the map's CRS)."""
    if options.area is not None:
        return options
    centres = np.array([im.cam_from_world.center for im in priors_abs.images.values()])
    lo = centres[:, :2].min(axis=0) - options.area_margin_m
    hi = centres[:, :2].max(axis=0) + options.area_margin_m
    return dataclasses.replace(options, area=(lo[0], lo[1], hi[0], hi[1]))


def image_tasks(inputs: Inputs, options: PipelineOptions) -> list[ImageTask]:
    """The per-image work of the priors' images, in image id order."""
    return [
        ImageTask(
            image_id=im.image_id,
            name=im.name,
            path=inputs.image_path / im.name,
            # The vanishing stage undistorts with the priors' camera (a model
            # change only adds parameters that start at zero); stage 2 gets
            # it in the result model, whose radial term it may refine.
            camera=inputs.priors.cameras[im.camera_id],
            prior=im.cam_from_world,
            cone_deg=options.cone_deg,
            vanishing=options.vanishing,
            registration=options.registration,
            refine=options.refine_segments,
            model=inputs.cameras[im.camera_id].model,
            heading_step_deg=options.heading_step_deg if inputs.position_only else 0.0,
        )
        for im in sorted(inputs.priors.images.values(), key=lambda im: im.image_id)
    ]
