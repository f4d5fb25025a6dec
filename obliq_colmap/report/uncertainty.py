"""Per-camera uncertainty for the user: position and rotation standard
deviations and the predicted deviation in pixels, from the bundle's
a-posteriori covariance.

The bundle computes the cofactor matrix of its camera block
(:func:`obliq_colmap.bundle.covariance.camera_covariance`) and hands it,
scaled by the variance factor, to ``covariance.image_precision``; it keeps
only the per-image pixel figure. :func:`record_pose_covariance` wraps that
call (the module calls through its attribute so that it can be wrapped) to
keep each image's 6 x 6 pose block as well; :func:`uncertainty_report`
picks the recorded call that produced the final bundle's figures.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from obliq_colmap.bundle import BundleResult, covariance

__all__ = [
    "PoseCovarianceRecord",
    "TRUST_NOTE",
    "horizontal_ellipse",
    "pose_uncertainty",
    "record_pose_covariance",
    "uncertainty_report",
]

#: How far the predicted sd can be trusted (docs/STATUS.md, issue 26).
TRUST_NOTE = (
    "The sds come from the last bundle's covariance scaled by its variance "
    "factor and are not yet calibrated (issue 26). Pixel sd: measured / "
    "predicted deviation median 0.71 on the synthetic 'paper' scenes, 0.79 on "
    "'hard', about 0.3 on the external urban-101 scene (~3x pessimistic "
    "there). Position sd: on the 16-image sample the horizontal centres are "
    "off by 2.1x the predicted sd (RMS), systematically per head along its "
    "viewing direction (1-2 m against 0.5 m predicted); on synthetic bundles "
    "with image noise only, measured and predicted agree (0.92-1.17). The "
    "covariance knows only the image noise: the map's errors and the block's "
    "weak modes beyond it are not in it. Read the sds as a ranking of the "
    "images and an order of magnitude, not as confidence intervals. Datum: "
    "the bundle's gauge (the mean camera height per component, or the GNSS "
    "centres where given)."
)


@dataclass
class PoseCovarianceRecord:
    """One call of ``covariance.image_precision``.

    Attributes
    ----------
    precision_px : dict image_id -> predicted deviation (px), as returned.
    pose_cov : dict image_id -> (6, 6) covariance of (rotation increment
        omega (rad, camera frame, ``R <- Exp(omega) R``), centre (m, local
        frame)).
    """

    precision_px: dict[int, float] = field(default_factory=dict)
    pose_cov: dict[int, np.ndarray] = field(default_factory=dict)


@contextmanager
def record_pose_covariance() -> Iterator[list[PoseCovarianceRecord]]:
    """Record every bundle precision computation inside the ``with`` block.

    Yields the list the records are appended to (one per bundle solve that
    computed its precision); the bundle's results are unchanged.
    """
    records: list[PoseCovarianceRecord] = []
    original = covariance.image_precision

    def recording(S, st, cov):
        out = original(S, st, cov)
        rec = PoseCovarianceRecord()
        for k, value in out.items():
            iid = int(S.image_ids[k])
            cols = S.pose_col[k] + np.arange(6)
            rec.precision_px[iid] = value
            rec.pose_cov[iid] = cov[np.ix_(cols, cols)].copy()
        records.append(rec)
        return out

    covariance.image_precision = recording
    try:
        yield records
    finally:
        covariance.image_precision = original


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


def _matching(
    bundle: BundleResult, records: list[PoseCovarianceRecord]
) -> PoseCovarianceRecord | None:
    """The last record whose figures are the final bundle's (the rounds
    solve several times; only one solve's covariance belongs to the poses
    written)."""
    want = {i: v for i, v in bundle.image_precision_px.items() if math.isfinite(v)}
    for rec in reversed(records):
        got = {i: v for i, v in rec.precision_px.items() if math.isfinite(v)}
        if want and got == want:
            return rec
    return None


def _r(x: float, nd: int) -> float | None:
    return round(float(x), nd) if math.isfinite(x) else None


def uncertainty_report(
    bundle: BundleResult,
    names: dict[int, str],
    records: list[PoseCovarianceRecord] | None = None,
) -> dict[str, Any]:
    """The ``uncertainty`` section of report.json, images worst first.

    Only the images in ``names`` (``register`` passes the written ones; the
    last bundle may still have held images that its verdicts then left out,
    and their sds are in their messages).

    Per image: ``predicted_sd_px`` (RMS over its constrained points of their
    projections' sd), and where the pose covariance was recorded
    (``records`` from :func:`record_pose_covariance`) ``position_sd_m``
    (x, y, z), ``horizontal_ellipse_m`` (semi-major, semi-minor, angle deg
    counter-clockwise from east) and ``rotation_sd_deg`` (camera x, y, z
    axes) with ``rotation_max_sd_deg``.
    """
    rec = _matching(bundle, records or [])
    ids = [i for i in bundle.image_precision_px if i in names]
    px = {i: bundle.image_precision_px[i] for i in ids}
    with_cov = [i for i in ids if rec is not None and i in rec.pose_cov]
    sds = (
        pose_uncertainty(np.array([rec.pose_cov[i] for i in with_cov]))
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
        "pose_covariance": rec is not None,
        "trust": TRUST_NOTE,
        "images": images,
    }
