"""Control and check point residuals of a georegistered model, in metres and pixels."""

from __future__ import annotations

import numpy as np
import pycolmap

from .model import ControlPoints
from .triangulate import ControlTriangulation


def point_residuals(
    rec: pycolmap.Reconstruction,
    control: ControlPoints,
    tri: ControlTriangulation,
    given_local: np.ndarray,
    triangulated_local: np.ndarray,
    roles: dict[str, str],
) -> list[dict]:
    """Per usable point: the triangulated-minus-given offset (m: horizontal,
    vertical) and the reprojection of the GIVEN position into the images
    that observe it, minus the measurement (px). ``roles``: name -> "control"
    or "check". Frames: ``rec``, ``given_local`` and ``triangulated_local``
    all in the output's local frame."""
    out = []
    for k, point in enumerate(control.points):
        if not tri.usable[k]:
            continue
        d = triangulated_local[k] - given_local[k]
        px = []
        for image_id, xy in zip(tri.image_ids[k], tri.observations_px[k], strict=True):
            image = rec.images[int(image_id)]
            Xc = image.cam_from_world() * given_local[k]
            if not np.all(np.isfinite(Xc)) or Xc[2] <= 0:
                px.append(np.inf)
                continue
            uv = image.camera.img_from_cam(np.nan_to_num(Xc)[None])[0]
            px.append(float(np.linalg.norm(uv - xy)))
        out.append(
            {
                "name": point.name,
                "role": roles.get(point.name, "control"),
                "num_observations": int(tri.n_observations[k]),
                "horizontal_m": float(np.hypot(d[0], d[1])),
                "vertical_m": float(d[2]) if np.isfinite(d[2]) else None,
                "reprojection_px": [round(v, 3) for v in px],
                "mean_reprojection_px": float(np.mean(px)) if px else None,
            }
        )
    return out


def summarise(rows: list[dict], role: str) -> dict:
    """Median and RMS of the rows of one role."""
    sel = [r for r in rows if r["role"] == role]
    if not sel:
        return {"num_points": 0}
    h = np.array([r["horizontal_m"] for r in sel])
    v = np.array([r["vertical_m"] for r in sel if r["vertical_m"] is not None])
    px = np.concatenate([r["reprojection_px"] for r in sel])
    return {
        "num_points": len(sel),
        "horizontal_m_median": float(np.median(h)),
        "horizontal_m_rms": float(np.sqrt(np.mean(h**2))),
        "vertical_m_median": float(np.median(np.abs(v))) if len(v) else None,
        "vertical_m_rms": float(np.sqrt(np.mean(v**2))) if len(v) else None,
        "reprojection_px_median": float(np.median(px)) if len(px) else None,
        "reprojection_px_rms": float(np.sqrt(np.mean(px**2))) if len(px) else None,
    }
