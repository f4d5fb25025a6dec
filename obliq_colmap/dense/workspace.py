"""``export_dense``: a COLMAP dense workspace (``image_undistorter`` layout)
from a registration, in the model's local frame, written atomically.

    DENSE_DIR/images/          undistorted images (pycolmap.undistort_images)
    DENSE_DIR/sparse/          the undistorted model (cameras, images, points3D)
    DENSE_DIR/stereo/          patch-match.cfg, fusion.cfg, depth_maps/, normal_maps/
    DENSE_DIR/georef.json      the local frame: world_abs = model_xyz + origin
    DENSE_DIR/dense.json       per image: points, depth range, sources, status
    DENSE_DIR/run-colmap-geometric.sh   the dense commands (need CUDA)
"""

from __future__ import annotations

import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from obliq_colmap import __version__
from obliq_colmap.colmap_io import (
    GEOREF_FILE,
    Block,
    Georef,
    read_georef,
    read_model,
    to_reconstruction,
)
from obliq_colmap.dense.check import check_workspace
from obliq_colmap.dense.config import write_run_scripts, write_stereo_config
from obliq_colmap.dense.mvs_rules import (
    MvsModel,
    depth_ranges,
    mvs_model,
    pair_statistics,
    source_images,
)
from obliq_colmap.dense.options import DenseOptions
from obliq_colmap.dense.support import add_frustum_support, read_points
from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder

__all__ = ["DENSE_REPORT_FILE", "export_dense"]

logger = logging.getLogger(__name__)

DENSE_REPORT_FILE = "dense.json"

#: Coarsest float32 step (m) of the model's coordinates that COLMAP's MVS
#: (float32 throughout) keeps without a warning.
FLOAT32_STEP_M = 1e-3


def _check_images(block: Block, input_path: Path, image_path: Path) -> None:
    """pycolmap's undistorter only logs a missing image: refuse first."""
    if not image_path.is_dir():
        raise InputError(image_path, "image folder does not exist")
    missing = sorted(
        im.name for im in block.images.values() if not (image_path / im.name).is_file()
    )
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise InputError(
            image_path,
            f"{len(missing)} image(s) of the model {input_path} have no file "
            f"here: {shown}",
        )


def _float32_step(model: MvsModel) -> float:
    """The float32 spacing (m) at the model's largest coordinate (camera
    centres and points): what COLMAP's MVS can resolve there."""
    coords = np.concatenate([model.centers.ravel(), model.xyz.ravel()])
    return float(np.spacing(np.float32(np.abs(coords).max(initial=0.0))))


def _keep_images(
    model: MvsModel, options: DenseOptions
) -> tuple[np.ndarray, list[np.ndarray], dict[str, str]]:
    """Which images can be reference images: enough points for a depth range
    and a source image among the kept ones (repeated until stable, since
    leaving one out can take the last source of another).

    Returns keep (I,) bool, sources per image (indices), name -> reason.
    """
    _, counts = depth_ranges(model)
    shared, angle = pair_statistics(model)
    reasons = {
        model.names[k]: f"{counts[k]} point(s) in front of it, fewer than "
        f"{options.min_num_points}"
        for k in np.flatnonzero(counts < options.min_num_points)
    }
    keep = counts >= options.min_num_points
    min_angle = np.radians(options.min_triangulation_angle_deg)
    while True:
        sources = source_images(shared, angle, options.num_src_images, min_angle, keep)
        lonely = keep & np.array([len(s) == 0 for s in sources])
        if not lonely.any():
            return keep, sources, reasons
        for k in np.flatnonzero(lonely):
            reasons[model.names[k]] = (
                "no source image (no kept image shares its points at a "
                f"triangulation angle of {options.min_triangulation_angle_deg:g} deg "
                "or more)"
            )
        keep &= ~lonely


def _image_table(
    model: MvsModel,
    keep: np.ndarray,
    sources: list[np.ndarray],
    reasons: dict[str, str],
    own_counts: dict[str, int],
    added: dict[str, int],
) -> dict[str, Any]:
    ranges, counts = depth_ranges(model)
    table = {}
    for k, name in enumerate(model.names):
        table[name] = {
            "status": "kept" if keep[k] else "left_out",
            "reason": reasons.get(name) if not keep[k] else None,
            "num_points_own": own_counts[name],
            "num_points_support": added.get(name, 0),
            "num_points": int(counts[k]),
            "depth_range_m": [round(float(v), 4) for v in ranges[k]]
            if counts[k]
            else None,
            "source_images": [model.names[j] for j in sources[k]] if keep[k] else [],
        }
    return table


def _workspace_model(
    rec, block: Block, input_path: Path, tmpdir: Path, options: DenseOptions
) -> tuple[Path, MvsModel, dict[str, int], dict[str, int], int]:
    """The model the workspace is made from: ``input_path`` itself, or a copy
    in ``tmpdir`` without the points of tracks shorter than
    ``min_track_length`` and, for images left with fewer than
    ``min_num_points`` points, with the block's points in their frustum
    added (:mod:`.support`).

    Returns (model folder, its MvsModel, image name -> own points in front
    of it, image name -> points added, number of points dropped).
    """
    import pycolmap

    model = mvs_model(rec)
    length = np.bincount(model.el_point, minlength=len(model.xyz))
    long_enough = length >= options.min_track_length
    el = long_enough[model.el_point]
    kept = MvsModel(
        model.names, model.R, model.t, model.xyz, model.el_point[el], model.el_image[el]
    )
    counts = depth_ranges(kept)[1]
    own = dict(zip(model.names, counts.tolist(), strict=True))
    weak = [
        block.image_by_name(n).image_id
        for n, c in own.items()
        if c < options.min_num_points
    ]
    dropped = int(np.sum(~long_enough))
    if not weak and not dropped:
        return input_path, model, own, {}, 0
    points = [p for p, ok in zip(read_points(rec), long_enough, strict=True) if ok]
    added = {
        block.images[i].name: n
        for i, n in add_frustum_support(block, points, weak).items()
    }
    to_reconstruction(block, points).write_binary(str(tmpdir))
    if dropped:
        logger.info(
            "%d point(s) seen in fewer than %d images left out of the workspace",
            dropped,
            options.min_track_length,
        )
    if added:
        logger.info(
            "depth-range support: %s", ", ".join(f"{n} +{a}" for n, a in added.items())
        )
    model = mvs_model(pycolmap.Reconstruction(str(tmpdir)))
    return tmpdir, model, own, added, dropped


def _write_workspace(
    tmp: Path,
    source_model: Path,
    image_path: Path,
    model: MvsModel,
    keep: np.ndarray,
    sources: list[np.ndarray],
    georef: Georef,
    options: DenseOptions,
) -> None:
    """Undistort into ``tmp`` and write the configuration, scripts and
    georef.json; then check the result with COLMAP's rules."""
    import pycolmap

    pycolmap.undistort_images(
        tmp,
        source_model,
        image_path,
        num_patch_match_src_images=options.num_src_images,
        undistort_options=pycolmap.UndistortCameraOptions(
            max_image_size=options.max_image_size
        ),
    )
    write_stereo_config(
        tmp / "stereo",
        [
            (model.names[k], [model.names[j] for j in sources[k]])
            for k in np.flatnonzero(keep)
        ],
        options.num_src_images if keep.all() else None,
    )
    write_run_scripts(tmp)
    (tmp / GEOREF_FILE).write_text(json.dumps(georef.to_json(), indent=2) + "\n")
    check = check_workspace(tmp, options.min_triangulation_angle_deg)
    if not check.ok:  # a bug here, not a user mistake
        raise RuntimeError("dense workspace invalid: " + "; ".join(check.problems))


def export_dense(
    input_path: str | Path,
    image_path: str | Path,
    output_path: str | Path,
    options: DenseOptions | None = None,
) -> dict[str, Any]:
    """Write the dense workspace of the model at ``input_path`` into
    ``output_path`` (new or empty folder); returns what ``dense.json`` says.

    Raises
    ------
    InputError
        Bad model, missing image folder or files, output folder not empty,
        no image left with a depth range and a source image.
    """
    import pycolmap

    options = options or DenseOptions()
    input_path, image_path = Path(input_path), Path(image_path)
    folder = AtomicFolder(output_path)  # checks the output before any work
    block = read_model(input_path)
    georef = read_georef(input_path)
    _check_images(block, input_path, image_path)
    rec = pycolmap.Reconstruction(str(input_path))
    with tempfile.TemporaryDirectory(prefix="obliq-dense-") as tmpdir:
        source_model, model, own, added, dropped = _workspace_model(
            rec, block, input_path, Path(tmpdir), options
        )
        keep, sources, reasons = _keep_images(model, options)
        for name, why in reasons.items():
            logger.warning("%s: left out of the dense workspace: %s", name, why)
        if not keep.any():
            raise InputError(
                input_path,
                "no image has a depth range and a source image; nothing written",
            )
        summary = _summary(input_path, image_path, georef, options, keep)
        summary["num_points_dropped"] = dropped
        summary["float32_step_m"] = step = _float32_step(model)
        if step > FLOAT32_STEP_M:
            logger.warning(
                "%s: coordinates this far from the origin keep %.3g m in COLMAP's "
                "float32 MVS; register writes a local frame (georef.json) for this",
                input_path,
                step,
            )
        summary["images"] = _image_table(model, keep, sources, reasons, own, added)
        with folder as tmp:
            _write_workspace(
                tmp, source_model, image_path, model, keep, sources, georef, options
            )
            (tmp / DENSE_REPORT_FILE).write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _summary(
    input_path: Path,
    image_path: Path,
    georef: Georef,
    options: DenseOptions,
    keep: np.ndarray,
) -> dict[str, Any]:
    """dense.json without its per-image table."""
    return {
        "software": f"obliq-colmap {__version__}",
        "input_path": str(input_path),
        "image_path": str(image_path),
        "georef": georef.to_json(),
        "frame": "local: world_abs = xyz + georef origin (also fused.ply)",
        "options": {
            "max_image_size": options.max_image_size,
            "min_num_points": options.min_num_points,
            "min_track_length": options.min_track_length,
            "num_src_images": options.num_src_images,
            "min_triangulation_angle_deg": options.min_triangulation_angle_deg,
        },
        "num_images": int(len(keep)),
        "num_kept": int(keep.sum()),
        "dense_commands": "sh run-colmap-geometric.sh (COLMAP with CUDA)",
    }
