"""Score a geo-registered model of a synthetic scene against its truth (issue 27).

Beside issue 25's per-image measure (:func:`obliq_colmap.evaluate.evaluate_block`:
rotation and centre errors, the mean deviation of the visible corners in px),
the block's own errors: the rotation that takes the true world frame to the
estimated one, split into its vertical part (the tilt of the model's up
direction) and its heading (about the vertical).
"""

from __future__ import annotations

import numpy as np

from obliq_colmap.colmap_io import Block
from obliq_colmap.evaluate import EvaluateOptions, evaluate_block
from obliq_colmap.synthetic.scene_io import SyntheticScene

UP = np.array([0.0, 0.0, 1.0])


def block_rotation(est: Block, gt: Block) -> np.ndarray:
    """(3, 3) rotation W with ``X_est ~ W X_gt``, the chordal mean over the images.

    Per image ``R_est^T R_gt`` maps true world directions to estimated ones
    (both seen the same in the camera); images are matched by name.
    """
    gt_by_name = {im.name: im for im in gt.images.values()}
    M = np.zeros((3, 3))
    for im in est.images.values():
        if im.name in gt_by_name:
            R_gt = gt_by_name[im.name].cam_from_world.rotation
            M += im.cam_from_world.rotation.T @ R_gt
    if not M.any():
        raise ValueError("no image in common between the two blocks")
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def vertical_error_deg(W: np.ndarray) -> float:
    """Angle between the true up direction mapped by ``W`` and the up direction."""
    return float(np.degrees(np.arccos(np.clip(W @ UP @ UP, -1.0, 1.0))))


def heading_error_deg(W: np.ndarray) -> float:
    """Signed rotation of ``W`` about the vertical (x axis mapped, in plan), deg."""
    x = W @ np.array([1.0, 0.0, 0.0])
    return float(np.degrees(np.arctan2(x[1], x[0])))


def score_block(
    est: Block, scene: SyntheticScene, options: EvaluateOptions | None = None
) -> dict:
    """All figures of an estimated ABSOLUTE block against the scene's truth.

    Returns
    -------
    dict: ``vertical_error_deg``, ``heading_error_deg`` (the block's),
    ``rotation_error_median_deg``, ``center_error_median_m``,
    ``center_error_max_m``, ``deviation_median_px`` (median over the images
    of their mean corner deviation), ``below_2px`` (fraction of the images),
    ``num_images`` (scored), ``images`` (per image: name, rotation_error_deg,
    center_error_m, mean_deviation_px).
    """
    corners = np.asarray(scene.buildings["corners"], float)
    ev = evaluate_block(
        est, scene.gt, corners, scene.buildings["visible_corners"], options
    )
    W = block_rotation(est, scene.gt)
    rows = [
        {
            "name": e.name,
            "rotation_error_deg": e.rotation_error_deg,
            "center_error_m": e.center_error_m,
            "mean_deviation_px": e.mean_deviation_px,
        }
        for e in ev.images
    ]
    dev = np.array([r["mean_deviation_px"] for r in rows], float)
    centre = np.array([r["center_error_m"] for r in rows], float)
    measured = np.isfinite(dev)
    return {
        "vertical_error_deg": vertical_error_deg(W),
        "heading_error_deg": heading_error_deg(W),
        "rotation_error_median_deg": ev.summary.rotation_error_median_deg,
        "center_error_median_m": ev.summary.center_error_median_m,
        "center_error_max_m": float(np.nanmax(centre)) if len(centre) else np.nan,
        "deviation_median_px": ev.summary.deviation_median_all_px,
        "below_2px": float(np.mean(dev[measured] < 2.0)) if measured.any() else 0.0,
        "num_images": int(measured.sum()),
        "images": rows,
    }
