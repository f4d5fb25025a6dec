"""Export a result model: absolute coordinates, OPK text or COLMAP text.

Result models are written in a local frame (``world_abs = model_xyz +
origin``, see ``georef.json``). ``absolute`` undoes the shift; ``opk``
writes each image's absolute centre and omega, phi, kappa (the file
:func:`obliq_colmap.priors.read_priors` reads); ``text`` writes the same
local model as COLMAP text files. ``georef.json`` goes beside the model.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from obliq_colmap.colmap_io import GEOREF_FILE, Georef, read_georef, read_model
from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder, check_output_path, write_text_atomic
from obliq_colmap.priors.opk import opk_from_cam_from_world
from obliq_colmap.priors.text import format_opk

logger = logging.getLogger(__name__)

OUTPUT_TYPES = ("absolute", "opk", "text")

#: float32 spacing above which we warn that absolute coordinates lose detail.
FLOAT32_WARN_M = 0.01


def _reconstruction(path: Path):
    import pycolmap

    read_model(path)  # the model checks and their messages
    return pycolmap.Reconstruction(str(path))


def _warn_float32(origin: np.ndarray, path: Path) -> None:
    spacing = float(np.spacing(np.float32(np.abs(origin).max())))
    if spacing > FLOAT32_WARN_M:
        logger.warning(
            "%s: absolute coordinates near %.0f m keep only %.3f m in float32; "
            "GPU/MVS tools reading float32 lose precision (the local model "
            "with georef.json does not)",
            path,
            np.abs(origin).max(),
            spacing,
        )


def export_absolute(input_path: Path, output_path: Path) -> Path:
    """The model with ``origin`` added to every point and camera centre."""
    import pycolmap

    georef = read_georef(input_path)
    rec = _reconstruction(input_path)
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), georef.origin))
    absolute = Georef(np.zeros(3), georef.crs, dict(georef.extra))
    absolute.extra["exported_from"] = str(input_path)
    with AtomicFolder(output_path) as tmp:
        rec.write_binary(str(tmp))
        (tmp / GEOREF_FILE).write_text(json.dumps(absolute.to_json(), indent=2) + "\n")
    _warn_float32(georef.origin, output_path)
    return output_path


def export_text(input_path: Path, output_path: Path) -> Path:
    """The same local model as COLMAP text files, georef.json copied."""
    rec = _reconstruction(input_path)
    georef = read_georef(input_path)
    with AtomicFolder(output_path) as tmp:
        rec.write_text(str(tmp))
        (tmp / GEOREF_FILE).write_text(json.dumps(georef.to_json(), indent=2) + "\n")
    return output_path


def export_opk(input_path: Path, output_path: Path) -> Path:
    """``imageName X Y Z Omega Phi Kappa``: absolute centres, degrees."""
    block = read_model(input_path)
    georef = read_georef(input_path)
    # Image id order, so that reading the file back gives the same order.
    images = sorted(block.images.values(), key=lambda im: im.image_id)
    centres = np.array([im.cam_from_world.center for im in images]) + georef.origin
    rotations = np.array([im.cam_from_world.rotation for im in images])
    text = format_opk(
        [im.name for im in images], centres, opk_from_cam_from_world(rotations)
    )
    if output_path.is_dir():
        raise InputError(output_path, "opk output is a file, not a folder")
    if not output_path.parent.is_dir():
        raise InputError(
            output_path.parent, "parent folder of --output_path does not exist"
        )
    if output_path.exists():
        raise InputError(output_path, "output file exists; refusing to overwrite")
    write_text_atomic(output_path, text)
    if georef.crs:
        logger.info("%s: coordinates in %s", output_path, georef.crs)
    return output_path


def export_model(
    input_path: str | Path, output_path: str | Path, output_type: str
) -> Path:
    """Write ``input_path`` (a result model) as ``output_type`` at ``output_path``."""
    input_path, output_path = Path(input_path), Path(output_path)
    if output_type not in OUTPUT_TYPES:
        raise InputError(None, f"--output_type must be one of {OUTPUT_TYPES}")
    if output_type == "opk":
        return export_opk(input_path, output_path)
    check_output_path(output_path)
    if output_type == "absolute":
        return export_absolute(input_path, output_path)
    return export_text(input_path, output_path)
