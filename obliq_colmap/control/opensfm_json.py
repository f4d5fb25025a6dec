"""OpenSfM's ``ground_control_points.json``.

Each point has an ``id``, an optional ``position`` (``latitude``,
``longitude``, optional ``altitude``) and ``observations`` of ``shot_id``
with a ``projection`` in OpenSfM's normalised image coordinates. OpenSfM's
documentation (doc/source/geometry.rst) defines pixel = ``max(w, h) * n +
(w - 1) / 2`` with the top-left pixel's centre at 0; in COLMAP's convention
(centre at 0.5) that is ``u = max(w, h) * n_x + w / 2``, ``v = max(w, h) *
n_y + h / 2``. So the image sizes are needed: they come from the model.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from obliq_colmap.errors import InputError
from obliq_colmap.priors.crs import to_map_crs

from .model import (
    DEFAULT_SIGMA_HORIZONTAL_M,
    DEFAULT_SIGMA_VERTICAL_M,
    ControlObservation,
    ControlPoint,
    ControlPoints,
)

logger = logging.getLogger(__name__)


def _position(path: Path, point: dict) -> tuple[float, float, float] | None:
    pos = point.get("position")
    if not isinstance(pos, dict) or "latitude" not in pos or "longitude" not in pos:
        return None
    try:
        lat, lon = float(pos["latitude"]), float(pos["longitude"])
        alt = float(pos["altitude"]) if pos.get("altitude") is not None else math.nan
    except (TypeError, ValueError):
        raise InputError(
            path, f"point {point.get('id')!r}: position is not numeric"
        ) from None
    return lon, lat, alt


def _observation(path, pid, obs, image_sizes) -> ControlObservation | None:
    shot = obs.get("shot_id")
    proj = obs.get("projection")
    if not isinstance(shot, str) or not isinstance(proj, list) or len(proj) != 2:
        raise InputError(
            path, f"point {pid!r}: an observation lacks shot_id/projection"
        )
    size = image_sizes.get(shot)
    if size is None:
        return None  # not in the model: the caller warns once per image
    w, h = size
    n = np.asarray(proj, float)
    return ControlObservation(shot, n * max(w, h) + np.array([w / 2, h / 2]))


def read_opensfm_json(
    path: str | Path,
    image_sizes: dict[str, tuple[int, int]],
    crs: str | None = None,
    sigma_horizontal_m: float = DEFAULT_SIGMA_HORIZONTAL_M,
    sigma_vertical_m: float = DEFAULT_SIGMA_VERTICAL_M,
) -> ControlPoints:
    """Read the points that have a position into metric coordinates."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(path, f"cannot read the control points: {exc}") from None
    raw = doc.get("points") if isinstance(doc, dict) else None
    if not isinstance(raw, list):
        raise InputError(path, "expected an object with a 'points' list (OpenSfM)")
    kept, geo, missing = [], [], set()
    for point in raw:
        pid = str(point.get("id", len(kept)))
        where = _position(path, point)
        if where is None:
            logger.warning("%s: point %s has no position; skipped", path.name, pid)
            continue
        obs = []
        for o in point.get("observations", []):
            ob = _observation(path, pid, o, image_sizes)
            if ob is None:
                missing.add(o.get("shot_id"))
            else:
                obs.append(ob)
        kept.append((pid, obs))
        geo.append(where)
    for shot in sorted(missing):
        logger.warning("%s: image %s is not in the model; its observations skipped",
                       path.name, shot)  # fmt: skip
    if not kept:
        raise InputError(path, "no control point with a position")
    geo = np.array(geo, float)
    flat = np.where(np.isfinite(geo[:, 2]), geo[:, 2], 0.0)
    xyz, out_crs = to_map_crs(np.c_[geo[:, :2], flat], "EPSG:4326", crs, path)
    xyz[:, 2] = np.where(np.isfinite(geo[:, 2]), xyz[:, 2], np.nan)
    points = [
        ControlPoint(pid, xyz[k], obs, sigma_horizontal_m, sigma_vertical_m)
        for k, (pid, obs) in enumerate(kept)
    ]
    return ControlPoints(points, out_crs, path)
