"""What both modes of :mod:`~obliq_colmap.georegister` share: reading the SfM
model, turning it upright, the result and the vertical's report."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap.colmap_io import Georef
from obliq_colmap.errors import InputError

from .relative_vp import add_missing_images
from .vertical import ModelVertical

logger = logging.getLogger(__name__)


@dataclass
class GeoregisterResult:
    """The model in the local frame of ``georef``, and the report."""

    reconstruction: pycolmap.Reconstruction
    georef: Georef
    report: dict


def read_sfm_model(path: Path) -> pycolmap.Reconstruction:
    """A COLMAP model folder (binary or text), or one clear error."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "SfM model folder not found")
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises bare errors
        raise InputError(path, f"not a readable COLMAP model: {exc}") from None
    if rec.num_reg_images() < 2:
        raise InputError(
            path, f"the model has {rec.num_reg_images()} registered images"
        )
    return rec


def upright(rec, vertical: ModelVertical | None) -> np.ndarray:
    """Rotate the model upright in place; the (3, 3) rotation applied."""
    if vertical is None:
        return np.eye(3)
    R = vertical.upright_rotation()
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), np.zeros(3)))
    return R


def add_missing(rec, image_path, vertical, options, priors=None) -> dict | None:
    """With ``options.add_missing_images``: the images under ``image_path``
    that the UPRIGHT model lacks placed from VPs and added to it
    (:mod:`.relative_vp`); their reports by name (None: not asked).
    ``priors``: name -> (3, 3) rough rotation in the model's frame."""
    if not options.add_missing_images:
        return None
    if vertical is None:
        logger.warning("missing images: not placed (the model has no vertical)")
        return {}
    return add_missing_images(
        rec,
        Path(image_path),
        np.array([0.0, 0.0, -1.0]),  # the model is upright now
        options.relative_vp,
        options.progress,
        priors,
    )


def vertical_report(vertical: ModelVertical | None, R_up: np.ndarray) -> dict:
    if vertical is None:
        return {"status": "unknown: too few vertical VPs"}
    return {
        "down_in_input_frame": vertical.down.tolist(),
        "sd_deg": vertical.sd_deg,
        "num_images": vertical.num_used,
        "images": {
            im.name: {
                "status": im.status,
                "residual_deg": None
                if not np.isfinite(im.residual_deg)
                else im.residual_deg,
                "sd_deg": None if not np.isfinite(im.sd_deg) else im.sd_deg,
            }
            for im in vertical.images
        },
        "upright_rotation": R_up.tolist(),
    }


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
