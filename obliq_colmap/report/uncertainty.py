"""Per-camera uncertainty for the user: position and rotation standard
deviations and the predicted deviation in pixels, from the bundle's
a-posteriori covariance (:attr:`BundleResult.pose_covariance` and
:attr:`BundleResult.image_precision_px`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from obliq_colmap.bundle import BundleResult

__all__ = [
    "TRUST_NOTE",
    "components_report",
    "horizontal_ellipse",
    "pose_uncertainty",
    "uncertainty_report",
]

#: How far the predicted sd can be trusted (docs/STATUS.md, issue 26).
TRUST_NOTE = (
    "The sds come from the last bundle's covariance with a variance "
    "component per observation group (map corners, segment directions, "
    "facade rows, tie points, VPs), each group's noise as its own residuals "
    "show it, and the map's vertex error shared by every view of a corner. "
    "Measured against the truth (issue 26, docs/STATUS.md, 2026-12-08): the "
    "RMS of deviation / predicted sd per run is 0.68-2.36 over eleven runs "
    "(two external scenes, five districts of our generator, our paper "
    "preset; about 0.85 for an honest sd): pessimistic by up to 1.3x "
    "(urban-101 and high-rise blocks, whose good images are predicted near "
    "1 px), optimistic by up to 2.8x on low-rise houses, where a head's "
    "camera height, distance and focal slide together and no observation "
    "sees it. Position sd: on the 16-image "
    "sample the horizontal "
    "centres were off by 2.1x the predicted sd (RMS), systematically per head "
    "along its viewing direction. The covariance knows the observations' "
    "noise and the map's vertex error only: buildings the map has shifted "
    "and the block's weak modes beyond them are not in it. Read the sds as a "
    "ranking of the images and an order of magnitude, not as confidence "
    "intervals. Datum: the bundle's gauge (the mean camera height per "
    "component, or the GNSS centres where given)."
)


def horizontal_ellipse(cov_xy: np.ndarray) -> np.ndarray:
    """(K, 3) standard ellipse of (K, 2, 2) horizontal covariances: semi-major
    and semi-minor axes (m, 1 sd) and the major axis' direction (deg,
    counter-clockwise from east, in [0, 180))."""
    vals, vecs = np.linalg.eigh(cov_xy)  # ascending eigenvalues
    axes = np.sqrt(np.clip(vals[:, ::-1], 0.0, None))
    major = vecs[:, :, 1]
    angle = np.degrees(np.arctan2(major[:, 1], major[:, 0])) % 180.0
    return np.column_stack([axes, angle])


def pose_uncertainty(pose_cov: np.ndarray) -> dict[str, np.ndarray]:
    """Standard deviations of (K, 6, 6) pose covariances (omega rad, centre m).

    Returns
    -------
    position_sd_m : (K, 3) sd of the centre along x (east), y (north), z.
    ellipse_m : (K, 3) horizontal ellipse (:func:`horizontal_ellipse`).
    rotation_sd_deg : (K, 3) sd of the rotation about the camera's x, y and
        z (optical) axes.
    rotation_max_sd_deg : (K,) sd along the worst rotation axis.
    """
    cov = np.asarray(pose_cov, float)
    var = np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None)
    rot = cov[:, :3, :3]
    return {
        "position_sd_m": np.sqrt(var[:, 3:]),
        "ellipse_m": horizontal_ellipse(cov[:, 3:5, 3:5]),
        "rotation_sd_deg": np.degrees(np.sqrt(var[:, :3])),
        "rotation_max_sd_deg": np.degrees(
            np.sqrt(np.clip(np.linalg.eigvalsh(rot)[:, -1], 0.0, None))
        ),
    }


def _r(x: float, nd: int) -> float | None:
    return round(float(x), nd) if math.isfinite(x) else None


def components_report(components: dict[str, tuple[float, float]]) -> dict[str, Any]:
    """Per observation group its variance component (the factor on its
    stated variance) and redundancy, as report.json writes them."""
    return {
        name: {"factor": _r(v, 4), "redundancy": _r(red, 1)}
        for name, (v, red) in components.items()
    }


def uncertainty_report(
    bundle: BundleResult,
    names: dict[int, str],
) -> dict[str, Any]:
    """The ``uncertainty`` section of report.json, images worst first.

    Only the images in ``names`` (``register`` passes the written ones; the
    last bundle may still have held images that its verdicts then left out,
    and their sds are in their messages).

    Per image: ``predicted_sd_px`` (RMS over its constrained points of their
    projections' sd), and where the bundle computed the pose covariance
    ``position_sd_m``
    (x, y, z), ``horizontal_ellipse_m`` (semi-major, semi-minor, angle deg
    counter-clockwise from east) and ``rotation_sd_deg`` (camera x, y, z
    axes) with ``rotation_max_sd_deg``.
    """
    ids = [i for i in bundle.image_precision_px if i in names]
    px = {i: bundle.image_precision_px[i] for i in ids}
    with_cov = [i for i in ids if i in bundle.pose_covariance]
    sds = (
        pose_uncertainty(np.array([bundle.pose_covariance[i] for i in with_cov]))
        if with_cov
        else {}
    )
    row = {i: k for k, i in enumerate(with_cov)}
    images = {}
    # worst first; an undeterminable (NaN) precision is the worst of all
    for i in sorted(ids, key=lambda i: -px[i] if math.isfinite(px[i]) else -math.inf):
        entry: dict[str, Any] = {"image_id": i, "predicted_sd_px": _r(px[i], 4)}
        if i in row:
            k = row[i]
            entry["position_sd_m"] = [_r(v, 4) for v in sds["position_sd_m"][k]]
            entry["horizontal_ellipse_m"] = [_r(v, 4) for v in sds["ellipse_m"][k]]
            entry["rotation_sd_deg"] = [_r(v, 5) for v in sds["rotation_sd_deg"][k]]
            entry["rotation_max_sd_deg"] = _r(sds["rotation_max_sd_deg"][k], 5)
        images[names[i]] = entry
    return {
        "variance_factor": _r(bundle.variance_factor, 4),
        "variance_components": components_report(bundle.variance_components),
        "pose_covariance": bool(with_cov),
        "trust": TRUST_NOTE,
        "images": images,
    }
