"""Maps as users have them: GeoJSON (RFC 7946 longitude / latitude or a
projected ``crs`` member), Shapefile and GeoPackage (through pyogrio), brought
into one projected metric CRS (through pyproj, x = easting first).

* :func:`read_document`: any of these as a GeoJSON-like document
  ``{"crs": str | None, "features": [...]}``.
* :func:`to_projected`: the features in the target CRS: ``CadastreOptions.crs``
  (``register --crs``) when given, else the map's own projected CRS, else (a
  map in longitude / latitude) the UTM zone of its centre.

pyproj and pyogrio are the optional extra ``gis``; without them a map that
needs them is one clear error naming the extra.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import mapping

from obliq_colmap.errors import InputError

from .read import GEOGRAPHIC_CRS, Feature, normalize_crs, read_json

__all__ = ["OGR_SUFFIXES", "read_document", "to_projected"]

logger = logging.getLogger(__name__)

#: Files read through OGR (pyogrio) instead of as GeoJSON text.
OGR_SUFFIXES = frozenset({".shp", ".gpkg", ".fgb", ".gml", ".kml", ".sqlite"})


def _need(module: str, path: Path, why: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ModuleNotFoundError:
        raise InputError(
            path, f"{why} needs {module}: pip install 'obliq-colmap[gis]'"
        ) from None


def read_document(path: Path) -> dict:
    """The map at ``path`` as ``{"crs": ..., "features": [GeoJSON features]}``."""
    if path.suffix.lower() not in OGR_SUFFIXES:
        return read_json(path)
    if not path.exists():
        raise InputError(path, "cadastre file does not exist")
    pyogrio = _need("pyogrio", path, f"reading a {path.suffix} map")
    try:
        meta, _, wkb, fields = pyogrio.raw.read(path)
    except Exception as err:  # pyogrio raises its own and GDAL's error types
        raise InputError(path, f"cannot read the map ({err})") from None
    names = [str(n) for n in meta.get("fields", [])]
    columns = {n.lower(): fields[k] for k, n in enumerate(names)}
    features = []
    for i, geom in enumerate(shapely.from_wkb(wkb)):
        props = {
            key: _plain(columns[key][i]) for key in ("id", "height") if key in columns
        }
        features.append(
            {
                "type": "Feature",
                "properties": props,
                "geometry": None if geom is None else mapping(geom),
            }
        )
    crs = meta.get("crs")
    return {"type": "FeatureCollection", "crs": crs, "features": features}


def _plain(value: Any) -> Any:
    """A numpy scalar as a Python one (JSON-like properties)."""
    return value.item() if isinstance(value, np.generic) else value


def _degree_like(bounds: tuple[float, float, float, float]) -> bool:
    xmin, ymin, xmax, ymax = bounds
    return max(abs(xmin), abs(xmax)) <= 180 and max(abs(ymin), abs(ymax)) <= 90


def _refuse_degrees_in_projected_crs(
    path: Path, crs: str, bounds: tuple[float, float, float, float]
) -> None:
    """One clear error for a map whose ``crs`` member names a projected CRS
    while its coordinates look like longitude / latitude (a map reprojected
    without updating the member, or the member copied from another file).

    Small coordinates alone prove nothing (a local engineering frame has
    them), so the map is refused only where pyproj places them outside the
    CRS's area of use; without pyproj it is read as stated.
    """
    try:
        import pyproj
    except ModuleNotFoundError:
        return
    try:
        source = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError:
        return  # an unknown CRS is reported where it is used
    area = source.area_of_use
    if area is None:
        return
    to_lonlat = pyproj.Transformer.from_crs(source, "EPSG:4326", always_xy=True)
    lon, lat = to_lonlat.transform(
        0.5 * (bounds[0] + bounds[2]), 0.5 * (bounds[1] + bounds[3])
    )
    west, south, east, north = area.bounds
    margin = 1.0  # degrees: maps at a zone's edge are still used in it
    inside = (
        np.isfinite(lon)
        and np.isfinite(lat)
        and south - margin <= lat <= north + margin
        and (west - margin <= lon <= east + margin or west > east)
    )
    if not inside:
        raise InputError(
            path,
            f"the map's 'crs' is {crs} (projected, metres) but its coordinates"
            f" look like longitude/latitude (x in [{bounds[0]:g}, {bounds[2]:g}],"
            f" y in [{bounds[1]:g}, {bounds[3]:g}]) and lie outside {crs}'s area"
            f" of use ({area.name}): drop the 'crs' member for RFC 7946"
            " longitude/latitude, or give the map in that CRS",
        )


def utm_zone_crs(lon: float, lat: float) -> str:
    """The WGS 84 / UTM zone of a longitude / latitude, as ``EPSG:326zz`` (north)
    or ``EPSG:327zz`` (south)."""
    zone = min(60, int(math.floor((lon + 180.0) / 6.0)) + 1)
    return f"EPSG:{(32600 if lat >= 0 else 32700) + zone}"


def to_projected(
    path: Path,
    crs: str | None,
    features: list[Feature],
    target: str | None,
    allow_degree_range: bool,
) -> tuple[list[Feature], str | None]:
    """The features in a projected metric CRS, and that CRS.

    ``crs`` is the map's own (None: not stated; RFC 7946 GeoJSON is then
    longitude / latitude when its coordinates lie in that range), ``target``
    the one asked for (None: keep a projected map as it is). Reprojection
    always takes x = easting / longitude first (some CRSs, e.g. EPSG:31468,
    declare northing first).
    """
    bounds = tuple(shapely.total_bounds([f.geometry for f in features]))
    geographic = (crs is not None and crs.upper() in GEOGRAPHIC_CRS) or (
        crs is None and _degree_like(bounds) and not allow_degree_range
    )
    if crs is not None and not geographic and _degree_like(bounds):
        _refuse_degrees_in_projected_crs(path, crs, bounds)
    source = (crs or "EPSG:4326") if geographic else crs
    if target is None and not geographic:
        return features, crs
    if (
        target is not None
        and source is not None
        and normalize_crs(target).upper() == normalize_crs(source).upper()
    ):
        return features, crs
    if geographic and not _degree_like(bounds):
        raise InputError(
            path,
            f"the map's CRS {source} is longitude/latitude but its coordinates"
            f" are not (x in [{bounds[0]:g}, {bounds[2]:g}], y in [{bounds[1]:g},"
            f" {bounds[3]:g}]): state its projected CRS in the 'crs' member",
        )
    if source is None:
        raise InputError(
            path,
            f"the map states no CRS, so it cannot be reprojected to {target}; add"
            " a 'crs' member (or give the map in that CRS)",
        )
    pyproj = _need("pyproj", path, "reprojecting the map")
    if target is None:
        centre = shapely.box(*bounds).centroid
        to_lonlat = pyproj.Transformer.from_crs(source, "EPSG:4326", always_xy=True)
        lon, lat = to_lonlat.transform(centre.x, centre.y)
        target = utm_zone_crs(lon, lat)
    try:
        transformer = pyproj.Transformer.from_crs(source, target, always_xy=True)
    except pyproj.exceptions.CRSError as err:
        raise InputError(
            path, f"cannot reproject {source} to {target} ({err})"
        ) from None
    if pyproj.CRS.from_user_input(target).is_geographic:
        raise InputError(
            path, f"--crs {target} is longitude / latitude; give a projected CRS"
        )

    def forward(xy: np.ndarray) -> np.ndarray:
        x, y = transformer.transform(xy[:, 0], xy[:, 1])
        return np.column_stack([x, y])

    out = [
        Feature(
            f.index, f.building_id, f.height, shapely.transform(f.geometry, forward)
        )
        for f in features
    ]
    logger.info("%s: reprojected from %s to %s", path, source, target)
    return out, target
