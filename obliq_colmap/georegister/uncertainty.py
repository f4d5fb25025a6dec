"""The georegistered block's uncertainty for the user: per camera its
centre's and rotation's standard deviations from the block adjustment's
covariance (:class:`~.block.BlockUncertainty`), written into report.json's
``uncertainty`` section as ``register`` writes its own (images worst first,
the same keys, :func:`obliq_colmap.report.pose_uncertainty`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from obliq_colmap.report import components_report, pose_uncertainty

from .block import BlockAdjustmentSummary

#: How far the sds can be trusted (docs/STATUS.md, issue 27).
TRUST_NOTE = (
    "The sds come from the block adjustment's covariance (the SfM tracks at "
    "1 px, the map rows at their sd, the control points at their stated "
    "accuracy, each image's vertical VP at its sd) with a variance component "
    "per observation group (the tracks with the control points, the map "
    "rows, the VPs). They know the noise of those observations only: a wrong "
    "SfM lens held in the adjustment (the focal length by default), and the "
    "map's errors shared by every image that sees a corner, are not in them "
    "(a street block placed on a dozen corners: its centres 3.2x their sd). "
    "Measured against the truth on synthetic blocks: docs/STATUS.md "
    "(georegister)."
)

#: Why a run's report has no covariance, by cause.
NO_COVARIANCE = {
    "no_adjustment": "no block adjustment was run",
    "solver": "the covariance comes from the obliq solver only",
    "too_large": (
        "the project's bundle computes the covariance up to 3000 camera "
        "parameters (about 450 images)"
    ),
}


def _r(x: float, nd: int) -> float | None:
    return round(float(x), nd) if math.isfinite(x) else None


def block_uncertainty_report(
    block: BlockAdjustmentSummary | None, names: dict[int, str]
) -> dict[str, Any]:
    """The ``uncertainty`` section of report.json: per image (``names``:
    image_id -> name, the written images) ``position_sd_m`` (x, y, z),
    ``horizontal_ellipse_m`` (semi-major, semi-minor, angle deg
    counter-clockwise from east), ``rotation_sd_deg`` (about the camera's x,
    y, z axes), ``rotation_max_sd_deg`` and, where it has map rows,
    ``predicted_sd_px`` (else null); images worst first (the centre's 3D sd). Without a
    covariance: ``{"available": False, "reason": ...}``."""
    if block is None or block.uncertainty is None:
        if block is None:
            why = "no_adjustment"
        elif block.solver != "obliq":
            why = "solver"
        else:
            why = "too_large"
        return {"available": False, "reason": NO_COVARIANCE[why]}
    u = block.uncertainty
    ids = [i for i in u.pose_covariance if i in names]
    if not ids:
        return {"available": False, "reason": "no written image has a covariance"}
    sds = pose_uncertainty(np.array([u.pose_covariance[i] for i in ids]))
    pos3 = np.sqrt(np.sum(sds["position_sd_m"] ** 2, axis=1))
    # worst first; an undeterminable (NaN) sd is the worst of all
    order = np.argsort(-np.where(np.isfinite(pos3), pos3, np.inf), kind="stable")
    images = {}
    for k in order:
        i = ids[k]
        px = u.image_precision_px.get(i, math.nan)
        images[names[i]] = {
            "image_id": int(i),
            "predicted_sd_px": _r(px, 4),
            "position_sd_m": [_r(v, 4) for v in sds["position_sd_m"][k]],
            "horizontal_ellipse_m": [_r(v, 4) for v in sds["ellipse_m"][k]],
            "rotation_sd_deg": [_r(v, 5) for v in sds["rotation_sd_deg"][k]],
            "rotation_max_sd_deg": _r(sds["rotation_max_sd_deg"][k], 5),
        }
    return {
        "available": True,
        "variance_factor": _r(u.variance_factor, 4),
        "variance_components": components_report(u.variance_components),
        "pose_covariance": True,
        "trust": TRUST_NOTE,
        "images": images,
    }
