"""OpenSfM / ODM ``gcp_list.txt``: a projection header, then one observation per line.

Format (OpenSfM's documentation, as ODM writes it)::

    WGS84                      <- or "WGS84 UTM 32N", a "+proj=..." string, "EPSG:n"
    geo_x geo_y geo_z im_x im_y image_name [gcp_name]

With ``WGS84`` the columns are longitude, latitude, altitude. Pixel
coordinates have the top-left pixel's CENTRE at (0, 0) (OpenSfM's
convention); COLMAP's has it at (0.5, 0.5), so 0.5 is added here, once.
Observations with the same name (or, without names, the same coordinates)
are one point. An altitude of NaN makes a 2D point (plan position only).
"""

from __future__ import annotations

import logging
import math
import re
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

#: OpenSfM's pixel centre is at 0; COLMAP's at 0.5.
OPENSFM_TO_COLMAP_PX = 0.5

_UTM = re.compile(r"^WGS84\s+UTM\s+(\d{1,2})\s*([NS])$", re.IGNORECASE)


def header_crs(path: Path, line: str) -> str:
    """The CRS of a gcp_list.txt header line, as a pyproj-readable string."""
    text = line.strip()
    if text.upper() == "WGS84":
        return "EPSG:4326"
    m = _UTM.match(text)
    if m:
        zone = int(m.group(1))
        if not 1 <= zone <= 60:
            raise InputError(path, f"line 1: UTM zone {zone} is not in 1..60")
        return f"EPSG:{(32600 if m.group(2).upper() == 'N' else 32700) + zone}"
    if text.startswith("+proj") or re.match(r"^EPSG:\d+$", text, re.IGNORECASE):
        return text
    raise InputError(
        path,
        f"line 1: unknown projection {text!r}; expected WGS84, 'WGS84 UTM 32N', "
        "a '+proj=...' string or 'EPSG:n' (OpenSfM's gcp_list.txt)",
    )


def _parse_line(path: Path, number: int, line: str) -> tuple:
    parts = line.split()
    if len(parts) < 6:
        raise InputError(
            path,
            f"line {number}: expected 'geo_x geo_y geo_z im_x im_y image_name "
            f"[gcp_name]', got {line.strip()!r}",
        )
    try:
        x, y, z, u, v = (float(p) for p in parts[:5])
    except ValueError:
        raise InputError(
            path,
            f"line {number}: the first five columns must be numbers: {line.strip()!r}",
        ) from None
    if not all(math.isfinite(c) for c in (x, y, u, v)):
        raise InputError(path, f"line {number}: coordinates must be finite")
    name = " ".join(parts[6:]) if len(parts) > 6 else None
    return x, y, z, u, v, parts[5], name


def read_gcp_list(
    path: str | Path,
    crs: str | None = None,
    sigma_horizontal_m: float = DEFAULT_SIGMA_HORIZONTAL_M,
    sigma_vertical_m: float = DEFAULT_SIGMA_VERTICAL_M,
) -> ControlPoints:
    """Read a gcp_list.txt into metric coordinates (``crs``, or the file's own
    projected CRS, or the UTM zone of a geographic file)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the control points: {exc}") from None
    if not lines or not lines[0].strip():
        raise InputError(path, "empty file; expected a projection header line")
    src = header_crs(path, lines[0])
    rows = [
        _parse_line(path, k + 1, line)
        for k, line in enumerate(lines)
        if k > 0 and line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise InputError(path, "no control point observations after the header")
    keys: dict = {}
    for x, y, z, _, _, _, name in rows:
        key = name if name is not None else (x, y, z if math.isfinite(z) else None)
        keys.setdefault(key, (x, y, z))
    geo = np.array(list(keys.values()), float)
    flat = np.where(np.isfinite(geo[:, 2]), geo[:, 2], 0.0)
    xyz, out_crs = to_map_crs(np.c_[geo[:, :2], flat], src, crs, path)
    xyz[:, 2] = np.where(np.isfinite(geo[:, 2]), xyz[:, 2], np.nan)
    points = {
        key: ControlPoint(
            name=str(key) if isinstance(key, str) else f"gcp{k}",
            xyz=xyz[k],
            sigma_horizontal_m=sigma_horizontal_m,
            sigma_vertical_m=sigma_vertical_m,
        )
        for k, key in enumerate(keys)
    }
    for x, y, z, u, v, image, name in rows:
        key = name if name is not None else (x, y, z if math.isfinite(z) else None)
        xy = np.array([u, v]) + OPENSFM_TO_COLMAP_PX
        points[key].observations.append(ControlObservation(image, xy))
    logger.info(
        "%s: %d control points, %d observations (%s -> %s)",
        path.name, len(points), len(rows), src, out_crs,
    )  # fmt: skip
    return ControlPoints(list(points.values()), out_crs, path)
