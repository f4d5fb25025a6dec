"""Files: the ground truth of a scene folder in either format
(:func:`read_ground_truth`), a result model in the absolute frame
(:func:`read_absolute_block`), and :func:`evaluate_model` /
:func:`evaluate_baseline` on folders."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from obliq_colmap.colmap_io import Block, read_georef, read_model
from obliq_colmap.errors import InputError
from obliq_colmap.evaluate.block import evaluate_block
from obliq_colmap.evaluate.results import EvaluateOptions, Evaluation

logger = logging.getLogger(__name__)

GT_MODEL_DIR = "gt"
PRIORS_MODEL_DIR = "priors"
GT_BUILDINGS_FILE = "gt_buildings.json"
GT_VISIBILITY_FILE = "gt_visibility.json"  # the external format's visibility

#: The two scene formats :func:`read_ground_truth` tells apart by content.
GT_FORMAT_SYNTHETIC = "synthetic"  # obliq-colmap synth: visibility in gt_buildings
GT_FORMAT_EXTERNAL = "external"  # ../shared/data/external_oblique: gt_visibility.json


@dataclass
class GroundTruth:
    """The ground truth of a scene folder.

    Attributes
    ----------
    block : Block, the exact model, absolute frame.
    corners_world : (K, 3) array, true 3D building corners, absolute, metres.
    visible : dict image name -> (M,) int array of corner indices.
    crs : str or None.
    format : str, ``"synthetic"`` (``obliq-colmap synth``) or ``"external"``.
    """

    block: Block
    corners_world: np.ndarray
    visible: dict[str, np.ndarray]
    crs: str | None = None
    format: str = GT_FORMAT_SYNTHETIC


def _read_json_object(path: Path, expected: str) -> dict:
    """A JSON file holding an object; InputError otherwise."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read JSON: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(path, f"expected a JSON object with {expected}")
    return data


def _parse_visible(path: Path, key: str, mapping, num_corners: int) -> dict:
    """``mapping`` (image name -> corner indices) as int arrays, checked."""
    if not isinstance(mapping, dict):
        raise InputError(path, f"{key!r} must map image names to index lists")
    visible = {}
    for name, idx in mapping.items():
        try:
            arr = np.asarray(idx)
            if arr.size == 0:
                arr = arr.astype(int)
            if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
                raise ValueError("not a list of integers")
        except (TypeError, ValueError) as exc:
            raise InputError(path, f"{key}[{name!r}]: {exc}") from None
        if arr.size and (arr.min() < 0 or arr.max() >= num_corners):
            raise InputError(
                path,
                f"{key}[{name!r}]: index out of range [0, {num_corners})",
            )
        visible[name] = arr.astype(int)
    return visible


def read_ground_truth(scene_path: str | Path) -> GroundTruth:
    """Read the ground truth of a scene folder, in either format.

    The format is told by content: a ``gt_buildings.json`` with
    ``visible_corners`` is a scene of ``obliq-colmap synth`` (CRS in its
    ``crs``); one without, beside a ``gt_visibility.json`` (``images``: image
    name -> corner indices), is the external format (CRS in ``frame.crs``).
    Both have ``gt/`` and the absolute ``corners`` [x, y, z].

    Raises
    ------
    InputError
        Missing folder, model or file; malformed JSON.
    """
    scene_path = Path(scene_path)
    if not scene_path.is_dir():
        raise InputError(scene_path, "ground-truth scene folder does not exist")
    block = read_model(scene_path / GT_MODEL_DIR)
    path = scene_path / GT_BUILDINGS_FILE
    if not path.is_file():
        raise InputError(path, "missing: the scene has no true building corners")
    data = _read_json_object(path, "'corners' and 'visible_corners'")
    vis_path = scene_path / GT_VISIBILITY_FILE
    external = "visible_corners" not in data and vis_path.is_file()
    keys = ("corners",) if external else ("corners", "visible_corners")
    for key in keys:
        if key not in data:
            raise InputError(
                path,
                f"missing key {key!r}"
                + ("" if key == "corners" else f" (and no {GT_VISIBILITY_FILE})"),
            )
    try:
        corners = np.asarray(data["corners"], dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"'corners' is not a list of [x, y, z]: {exc}") from None
    if corners.size == 0:
        corners = corners.reshape(0, 3)
    if corners.ndim != 2 or corners.shape[1] != 3:
        raise InputError(
            path, f"'corners' must be a list of [x, y, z], got shape {corners.shape}"
        )
    if not np.isfinite(corners).all():
        raise InputError(path, "'corners' contains non-finite values")
    if external:
        vis_data = _read_json_object(vis_path, "'images'")
        if "images" not in vis_data:
            raise InputError(vis_path, "missing key 'images'")
        visible = _parse_visible(vis_path, "images", vis_data["images"], len(corners))
        frame = data.get("frame")
        crs = frame.get("crs") if isinstance(frame, dict) else None
        unknown_path = vis_path
    else:
        visible = _parse_visible(
            path, "visible_corners", data["visible_corners"], len(corners)
        )
        crs = data.get("crs")
        unknown_path = path
    gt_names = {im.name for im in block.images.values()}
    unknown = sorted(set(visible) - gt_names)
    if unknown:
        logger.warning(
            "%s: %d image(s) not in %s, ignored: %s",
            unknown_path,
            len(unknown),
            GT_MODEL_DIR,
            ", ".join(unknown[:5]),
        )
    fmt = GT_FORMAT_EXTERNAL if external else GT_FORMAT_SYNTHETIC
    return GroundTruth(block, corners, visible, crs, fmt)


def read_absolute_block(model_path: str | Path) -> tuple[Block, str | None]:
    """Read a model and convert it to the absolute frame with its ``georef.json``.

    Returns
    -------
    block : Block, absolute frame (``X_abs = X_model + origin``).
    crs : str or None, from ``georef.json``.
    """
    block = read_model(model_path)
    georef = read_georef(model_path)
    # Block.shifted(s) re-expresses in X_new = X_old - s; X_abs = X_local + origin.
    return block.shifted(-np.asarray(georef.origin, float)), georef.crs


def evaluate_model(
    result_path: str | Path | None,
    gt_path: str | Path,
    options: EvaluateOptions | None = None,
    *,
    baseline: bool = False,
) -> Evaluation:
    """Evaluate a result model folder against a scene folder (either format).

    Parameters
    ----------
    result_path : the result model (with ``georef.json`` if local; absolute
        without); ignored (may be None) with ``baseline``.
    gt_path : the scene folder (``gt/``, ``gt_buildings.json``, ``priors/``;
        ``gt_visibility.json`` in the external format, see
        :func:`read_ground_truth`).
    options : EvaluateOptions, defaults if None.
    baseline : evaluate ``gt_path/priors`` instead of ``result_path``.

    Returns
    -------
    Evaluation

    Raises
    ------
    InputError
        Missing or unreadable folders and files, different CRS, no image in
        common.
    """
    options = options or EvaluateOptions()
    truth = read_ground_truth(gt_path)
    if baseline:
        result_path = Path(gt_path) / PRIORS_MODEL_DIR
    elif result_path is None:
        raise InputError(None, "a result model path is needed unless baseline=True")
    result_path = Path(result_path)
    est, crs = read_absolute_block(result_path)
    if crs and truth.crs and crs != truth.crs:
        raise InputError(
            result_path,
            f"georef.json has CRS {crs}, the ground truth {truth.crs}; reproject first",
        )
    gt_names = {im.name for im in truth.block.images.values()}
    if not gt_names & {im.name for im in est.images.values()}:
        raise InputError(
            result_path,
            "no image name in common with the ground truth "
            f"{Path(gt_path) / GT_MODEL_DIR}",
        )
    evaluation = evaluate_block(
        est, truth.block, truth.corners_world, truth.visible, options
    )
    evaluation.result_path = str(result_path)
    evaluation.gt_path = str(gt_path)
    evaluation.gt_format = truth.format
    return evaluation


def evaluate_baseline(
    gt_path: str | Path, options: EvaluateOptions | None = None
) -> Evaluation:
    """Evaluate the scene's rough priors (``gt_path/priors``) the same way."""
    return evaluate_model(None, gt_path, options, baseline=True)
