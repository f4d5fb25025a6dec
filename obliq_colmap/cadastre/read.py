"""Reading the GeoJSON document: JSON checks, CRS, features, metric check, origin.

Step 1 and 2 of :func:`load_cadastre`: every function here works on the
ABSOLUTE map coordinates of the file and raises :class:`InputError` naming
the file (and the feature) at fault.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, shape

from obliq_colmap.errors import InputError

from .options import CadastreOptions

logger = logging.getLogger(__name__)

#: Coordinate reference systems in degrees (rejected: reprojection is needed).
GEOGRAPHIC_CRS = frozenset(
    {
        "EPSG:4326",
        "EPSG:4258",
        "EPSG:4269",
        "EPSG:4979",
        "EPSG:4937",
        "EPSG:4267",
        "OGC:CRS84",
        "OGC:CRS83",
        "OGC:CRS27",
    }
)


@dataclass
class Feature:
    """One parsed feature: geometry in absolute coordinates and its properties."""

    index: int
    building_id: str
    height: float
    geometry: Polygon | MultiPolygon

    def label(self) -> str:
        return f"feature {self.index} (id {self.building_id!r})"


def read_json(path: Path) -> dict:
    """The document as a dict with a ``features`` list, or an InputError."""
    if not path.exists():
        raise InputError(path, "cadastre file does not exist")
    if path.is_dir():
        raise InputError(path, "is a folder; expected a GeoJSON file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(path, f"cannot read the cadastre file: {err}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise InputError(
            path,
            f"not valid JSON (line {err.lineno}, column {err.colno}: "
            f"{err.msg}); expected a GeoJSON FeatureCollection",
        ) from None
    kind = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
    if kind != "FeatureCollection":
        raise InputError(
            path,
            f"not a GeoJSON FeatureCollection (found type {kind!r}); "
            'expected {"type": "FeatureCollection", "features": [...]}',
        )
    if not isinstance(doc.get("features"), list):
        raise InputError(path, "the FeatureCollection has no 'features' list")
    return doc


_EPSG_PATTERNS = (
    re.compile(r"^EPSG:+(\d+)$", re.IGNORECASE),
    re.compile(r"^urn:ogc:def:crs:EPSG:[\d.]*:(\d+)$", re.IGNORECASE),
    re.compile(
        r"^https?://www\.opengis\.net/def/crs/EPSG/[\d.]+/(\d+)$", re.IGNORECASE
    ),
)
_OGC_PATTERNS = (
    re.compile(r"^urn:ogc:def:crs:OGC:[\d.]*:(CRS\d+)$", re.IGNORECASE),
    re.compile(
        r"^https?://www\.opengis\.net/def/crs/OGC/[\d.]+/(CRS\d+)$", re.IGNORECASE
    ),
    re.compile(r"^(CRS\d+)$", re.IGNORECASE),
)


def normalize_crs(name: str) -> str:
    """Normalise common spellings of a CRS name.

    ``"urn:ogc:def:crs:EPSG::28992"``, ``"EPSG:28992"`` and
    ``"http://www.opengis.net/def/crs/EPSG/0/28992"`` all give
    ``"EPSG:28992"``; the OGC CRS84 spellings give ``"OGC:CRS84"``; anything
    else is returned stripped but unchanged.
    """
    name = name.strip()
    for pattern in _EPSG_PATTERNS:
        if m := pattern.match(name):
            return f"EPSG:{int(m.group(1))}"
    for pattern in _OGC_PATTERNS:
        if m := pattern.match(name):
            return f"OGC:{m.group(1).upper()}"
    return name


def parse_crs(path: Path, member: Any) -> str | None:
    """The ``crs`` member (GeoJSON 2008 named / EPSG object, or a string)."""
    if member is None:
        return None
    if isinstance(member, str):
        return normalize_crs(member)
    if isinstance(member, dict):
        props = member.get("properties")
        props = props if isinstance(props, dict) else {}
        if member.get("type") == "name" and isinstance(props.get("name"), str):
            return normalize_crs(props["name"])
        if member.get("type") == "EPSG" and "code" in props:
            return f"EPSG:{props['code']}"
    logger.warning(
        "%s: cannot interpret the 'crs' member %r; CRS left unknown", path, member
    )
    return None


def parse_feature(path: Path, index: int, raw: Any) -> Feature | str:
    """One feature's geometry (absolute) and properties, or why it is
    skipped (a short phrase that the loader counts: one line for the map,
    not one per feature)."""
    if not isinstance(raw, dict):
        raise InputError(path, f"feature {index} is not a JSON object")
    props = raw.get("properties")
    props = props if isinstance(props, dict) else {}
    raw_id = props.get("id", raw.get("id"))
    building_id = str(index) if raw_id is None else str(raw_id)
    label = f"feature {index} (id {building_id!r})"
    height = _parse_height(path, label, props.get("height"))

    geom = raw.get("geometry")
    kind = geom.get("type") if isinstance(geom, dict) else None
    if kind not in ("Polygon", "MultiPolygon"):
        what = "no geometry" if geom is None else f"geometry type {kind!r}"
        logger.debug("%s: %s has %s; skipped", path, label, what)
        return what
    try:
        geometry = shapely.force_2d(shape(geom))
    except Exception as err:  # shapely raises many types for bad coordinates
        raise InputError(
            path, f"{label}: malformed {kind} coordinates ({err})"
        ) from None
    if geometry.is_empty:
        logger.debug("%s: %s has an empty %s; skipped", path, label, kind)
        return f"an empty {kind}"
    coords = shapely.get_coordinates(geometry)
    if not np.all(np.isfinite(coords)):
        raise InputError(path, f"{label}: coordinates are not all finite numbers")
    return Feature(index, building_id, height, geometry)


def _parse_height(path: Path, label: str, value: Any) -> float:
    """The ``height`` property in metres, NaN if absent or unusable."""
    if value is None:
        return math.nan
    try:
        height = float(value)
    except (TypeError, ValueError):
        height = math.nan
    if not (math.isfinite(height) and height >= 0):
        logger.warning("%s: %s has an unusable height %r; ignored", path, label, value)
        return math.nan
    return height


def check_metric(
    path: Path, crs: str | None, features: list[Feature], options: CadastreOptions
) -> tuple[float, float, float, float]:
    """Reject degrees; return the absolute bounds (xmin, ymin, xmax, ymax)."""
    if crs is not None and crs.upper() in GEOGRAPHIC_CRS:
        raise InputError(
            path,
            f"the map's CRS {crs} is longitude/latitude in degrees; footprints"
            " must be in a projected metric CRS (e.g. UTM)",
        )
    xmin, ymin, xmax, ymax = shapely.total_bounds([f.geometry for f in features])
    degree_like = max(abs(xmin), abs(xmax)) <= 180 and max(abs(ymin), abs(ymax)) <= 90
    if degree_like and not options.allow_degree_range:
        raise InputError(
            path,
            f"coordinates look like longitude/latitude in degrees (x in "
            f"[{xmin:g}, {xmax:g}], y in [{ymin:g}, {ymax:g}]) but were not"
            " reprojected; footprints must be in a projected metric CRS (e.g."
            " UTM)",
        )
    return float(xmin), float(ymin), float(xmax), float(ymax)


def choose_origin(
    bounds: tuple[float, float, float, float],
    origin: Sequence[float] | np.ndarray | None,
    options: CadastreOptions,
) -> np.ndarray:
    """(3,) origin: the given one, or the rounded centre of the bounds."""
    if origin is not None:
        given = np.asarray(origin, dtype=float).reshape(-1)
        if given.shape not in ((2,), (3,)) or not np.all(np.isfinite(given)):
            raise ValueError(f"origin must be 2 or 3 finite numbers, got {origin!r}")
        return np.append(given, 0.0) if given.shape == (2,) else given
    centre = np.array([(bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2])
    step = options.origin_rounding_m
    if step > 0:
        centre = np.round(centre / step) * step
    return np.array([centre[0], centre[1], 0.0])
