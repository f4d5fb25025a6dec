"""Writing footprints back as GeoJSON (atomically)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, mapping

from obliq_colmap.files import write_json_atomic


def write_geojson(
    path: str | Path,
    polygons_abs: Sequence[Polygon | MultiPolygon],
    crs: str | None = None,
    properties: Sequence[dict] | None = None,
    decimals: int = 3,
) -> Path:
    """Write footprints as a GeoJSON FeatureCollection (atomically).

    Parameters
    ----------
    path : str or Path
        Output file; written to a temporary sibling and renamed into place.
    polygons_abs : sequence of shapely Polygon or MultiPolygon
        Footprints in ABSOLUTE map coordinates (m); see
        :meth:`Cadastre.absolute_polygons`.
    crs : str, optional
        Written as a GeoJSON 2008 named CRS, ``{"type": "name", ...}``.
    properties : sequence of dict, optional
        One per polygon (JSON-serialisable), e.g. ``{"id": ..., "height": ...}``.
    decimals : int
        Coordinates are rounded to this many decimals (3: millimetres).

    Returns
    -------
    Path of the written file.
    """
    path = Path(path)
    if properties is not None and len(properties) != len(polygons_abs):
        raise ValueError(
            f"{len(properties)} properties for {len(polygons_abs)} polygons"
        )
    features = []
    for k, polygon in enumerate(polygons_abs):
        rounded = shapely.transform(polygon, lambda c: np.round(c, decimals))
        features.append(
            {
                "type": "Feature",
                "properties": dict(properties[k]) if properties is not None else {},
                "geometry": mapping(rounded),
            }
        )
    doc: dict[str, Any] = {"type": "FeatureCollection"}
    if crs is not None:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    doc["features"] = features
    write_json_atomic(path, doc, separators=(",", ":"))
    return path
