"""Reprojection of prior positions with pyproj (optional extra ``gis``)."""

from __future__ import annotations

import logging

import numpy as np

from obliq_colmap.errors import InputError

logger = logging.getLogger(__name__)


def _pyproj(source: object):
    try:
        import pyproj
    except ModuleNotFoundError:
        raise InputError(
            None,
            f"{source}: priors in another CRS need pyproj: "
            "pip install 'obliq-colmap[gis]'",
        ) from None
    return pyproj


def utm_crs(lon_deg: float, lat_deg: float) -> str:
    """The WGS84 UTM zone of a point, as ``EPSG:326zz`` (north) or ``EPSG:327zz``."""
    zone = int(np.floor((lon_deg + 180.0) / 6.0)) % 60 + 1
    return f"EPSG:{32600 + zone if lat_deg >= 0 else 32700 + zone}"


def to_map_crs(
    xyz: np.ndarray, src_crs: str, dst_crs: str | None, source: object
) -> tuple[np.ndarray, str]:
    """Reproject (N, 3) positions (x = easting/longitude first) into ``dst_crs``.

    ``dst_crs`` None keeps a projected ``src_crs`` and sends a geographic one
    to the UTM zone of the mean position. Heights pass through unchanged
    (no vertical datum change). Returns the (N, 3) positions and the CRS.
    """
    pyproj = _pyproj(source)
    try:
        src = pyproj.CRS.from_user_input(src_crs)
        dst = None if dst_crs is None else pyproj.CRS.from_user_input(dst_crs)
    except pyproj.exceptions.CRSError as exc:
        raise InputError(None, f"{source}: unknown CRS: {exc}") from None
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    if dst is None:
        if not src.is_geographic:
            return xyz, src_crs
        lon, lat = xyz[:, 0].mean(), xyz[:, 1].mean()
        dst = pyproj.CRS.from_user_input(utm_crs(lon, lat))
        logger.info("%s: geographic priors projected to %s", source, dst.to_string())
    if src == dst:
        return xyz, dst.to_string()
    transformer = pyproj.Transformer.from_crs(src, dst, always_xy=True)
    x, y = transformer.transform(xyz[:, 0], xyz[:, 1])
    out = np.column_stack([x, y, xyz[:, 2]])
    if not np.all(np.isfinite(out)):
        raise InputError(None, f"{source}: positions fall outside {dst.to_string()}")
    return out, dst.to_string()
