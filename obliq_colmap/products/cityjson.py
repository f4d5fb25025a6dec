"""The LoD1 city model: every footprint with an eave height, extruded from
its ground height to its eave height (CityJSON 2.0, one Solid per footprint
polygon, LoD 1.2), integer vertices with a ``transform`` (1 mm) and the
map's CRS as ``referenceSystem``.
"""

from __future__ import annotations

import re

import numpy as np
from shapely.geometry import Polygon

__all__ = ["city_model", "reference_system"]


def reference_system(crs: str | None) -> str | None:
    """The OGC URL of an ``EPSG:N`` CRS (CityJSON's referenceSystem)."""
    m = re.fullmatch(r"EPSG:(\d+)", crs or "")
    return f"https://www.opengis.net/def/crs/EPSG/0/{m.group(1)}" if m else None


def _ring(poly_ring) -> np.ndarray:
    """(n, 2) vertices of a shapely ring without the closing repeat."""
    return np.asarray(poly_ring.coords)[:-1, :2]


def _solid(poly: Polygon, z0: float, z1: float, vertices: list) -> list:
    """Boundaries of one extruded polygon (a Solid's one shell); appends its
    vertices (absolute x, y, z) to ``vertices``. Rings: exterior CCW and
    holes CW seen from above (the building on their left), as the map's."""
    shell = []
    floor, roof = [], []
    for k, ring in enumerate([poly.exterior, *poly.interiors]):
        xy = _ring(ring)
        if (k == 0) != ring.is_ccw:  # normalise: exterior CCW, holes CW
            xy = xy[::-1]
        n = len(xy)
        base = len(vertices)
        vertices.extend([(x, y, z0) for x, y in xy])
        vertices.extend([(x, y, z1) for x, y in xy])
        bot = list(range(base, base + n))
        top = list(range(base + n, base + 2 * n))
        # outward normals: the floor faces down (reversed), the roof up.
        floor.append(bot[::-1])
        roof.append(top)
        for i in range(n):
            j = (i + 1) % n
            # building on the left of bot[i] -> bot[j]: seen from outside
            # (the right) this order runs counter-clockwise.
            shell.append([[bot[i], bot[j], top[j], top[i]]])
    return [floor, roof, *shell]


def city_model(
    polygons: list[Polygon],
    ids: list[str],
    ground_z: np.ndarray,
    eave_z: np.ndarray,
    attributes: list[dict],
    crs: str | None,
    scale: float = 0.001,
) -> dict:
    """A CityJSON 2.0 document (absolute coordinates given).

    Parameters
    ----------
    polygons : B footprints, ABSOLUTE x, y. ids : B CityObject ids (unique).
    ground_z, eave_z : (B,) absolute heights; NaN: the footprint is left out.
    attributes : B dicts of attributes.
    """
    verts: list = []
    objects = {}
    for poly, oid, z0, z1, attrs in zip(
        polygons, ids, ground_z, eave_z, attributes, strict=True
    ):
        if not (np.isfinite(z0) and np.isfinite(z1) and z1 > z0):
            continue
        objects[oid] = {
            "type": "Building",
            "attributes": attrs,
            "geometry": [
                {
                    "type": "Solid",
                    "lod": "1.2",
                    "boundaries": [_solid(poly, float(z0), float(z1), verts)],
                }
            ],
        }
    V = np.asarray(verts, float).reshape(-1, 3)
    translate = np.floor(V.min(axis=0)) if len(V) else np.zeros(3)
    Vi = np.round((V - translate) / scale).astype(np.int64)
    doc = {
        "type": "CityJSON",
        "version": "2.0",
        "transform": {"scale": [scale] * 3, "translate": translate.tolist()},
        "metadata": {"title": "LoD1 from obliq-colmap (footprints x eave heights)"},
        "CityObjects": objects,
        "vertices": Vi.tolist(),
    }
    ref = reference_system(crs)
    if ref:
        doc["metadata"]["referenceSystem"] = ref
    return doc
