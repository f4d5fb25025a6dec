"""Building footprints: GeoJSON -> cleaned polygons, corners and edges in a local frame.

The cadastre stage (paper 000, section 2.2) turns a 2D footprint map into the
plain arrays the registration stages need:

- corners: the map vertices whose vertical edges are matched to vertical image
  lines (eq. 2), with their interior angle and outward bisector;
- edges: the facade walls whose horizontal edges are matched in section 2.3,
  with their outward normal;
- per-camera visibility queries (:func:`visible_corners`,
  :func:`visible_edges`, :func:`visible_edge_parts`) that pick the corners and
  walls a rough pose can see, all vectorised over the whole map.

Input contract (see DESIGN.md): a GeoJSON FeatureCollection of Polygon /
MultiPolygon footprints (holes allowed) in a projected metric CRS, an optional
``"crs"`` member and optional ``id`` / ``height`` properties. Longitude /
latitude input is rejected: reprojection is not supported yet.

Steps of :func:`load_cadastre`:

1. Read and check the JSON document; parse each feature into shapely
   geometries (absolute coordinates); reject degree coordinates.
2. Choose the local origin (rounded centre of the bounds) and translate; all
   arrays of a :class:`Cadastre` are in this LOCAL frame,
   ``world_abs = local + origin``.
3. Validate each feature; repair invalid ones with ``shapely.make_valid``
   (keeping the polygonal parts) or reject them; dissolve the parts of one
   feature that touch (a building stored as several ground polygons).
4. Orient every polygon (exterior counter-clockwise, holes clockwise, so the
   building is always on the LEFT of a ring), drop duplicate / near-duplicate
   vertices and vertices on straight runs, drop tiny polygons and holes.
5. Build the corner and edge arrays (holes are rings of their own: courtyard
   corners are corners too), flag party walls shared with a neighbouring
   building, and build an STRtree over the polygons.

Visibility is a purely geometric test (frustum and back-face culling); it does
NOT model occlusion by other buildings. Later stages handle occlusion through
their robust matching (RANSAC inliers, facade-edge consistency across images).
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, mapping, shape
from shapely.geometry.polygon import orient

from obliq_colmap.errors import InputError
from obliq_colmap.files import write_json_atomic
from obliq_colmap.geometry import Camera, Pose

logger = logging.getLogger(__name__)

#: A ground height: a constant in metres (local frame, the priors' vertical
#: datum), or a function of (N, 2) local xy (m) returning (N,) heights (m).
GroundHeight = float | Callable[[np.ndarray], np.ndarray]

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

#: An edge covered by neighbouring buildings over at least this fraction of its
#: length is a party wall: it is inside the block and never seen as a facade.
SHARED_WALL_FRACTION = 0.9

# Edges are clipped against the frustum in chunks of this many to bound memory
# ((chunk, 36, 9) arrays in the wall clipping).
_EDGE_CHUNK = 4096


# --------------------------------------------------------------------------
# Options and results
# --------------------------------------------------------------------------


@dataclass(kw_only=True)
class CadastreOptions:
    """How footprints are read and cleaned.

    Attributes
    ----------
    min_edge_length_m : float
        Vertices closer than this (m) to their neighbour are merged (duplicate
        and near-duplicate vertices, digitising jitter); 0 keeps all.
    collinear_tolerance_deg : float
        A vertex whose interior angle is within this many degrees of 180 lies
        on a straight run of wall and is removed; 0 removes exact ones only.
    collinear_max_offset_m : float
        ... but only if it lies within this distance (m) of the line through
        its two neighbours, so that a long, slightly bent facade keeps its
        shape (a 2 deg bend between two 30 m walls is 0.5 m); ``math.inf``
        for the angle test alone.
    min_area_m2 : float
        Polygons (and holes) smaller than this (m^2) are dropped: sheds,
        slivers left by repairs, light wells.
    repair_invalid : bool
        Repair invalid geometry (self-intersecting rings, overlapping parts of a
        MultiPolygon) with ``shapely.make_valid`` and keep its polygonal parts.
        If False, an invalid feature is an :class:`InputError`.
    dissolve_parts : bool
        Union the polygons of one feature, so that a building stored as
        several touching ground polygons becomes one footprint without
        interior walls.
    grid_size_m : float
        Precision grid (m) used when dissolving parts, so that edges that
        coincide up to rounding merge; 0 for exact arithmetic.
    shared_edge_tolerance_m : float
        An edge counts as shared with a neighbouring building where it is
        within this distance (m) of that building (party walls).
    origin_rounding_m : float
        The automatic local origin is the centre of the map's bounds rounded
        to a multiple of this (m); 0 for no rounding.
    allow_degree_range : bool
        Accept coordinates that all lie within the longitude / latitude range
        (|x| <= 180, |y| <= 90) when the ``crs`` member does not say they are
        degrees: a small map in a local metric frame near (0, 0).
    """

    min_edge_length_m: float = 0.05
    collinear_tolerance_deg: float = 3.0
    collinear_max_offset_m: float = 0.25
    min_area_m2: float = 1.0
    repair_invalid: bool = True
    dissolve_parts: bool = True
    grid_size_m: float = 0.001
    shared_edge_tolerance_m: float = 0.05
    origin_rounding_m: float = 100.0
    allow_degree_range: bool = False

    def __post_init__(self) -> None:
        for name in (
            "min_edge_length_m",
            "collinear_tolerance_deg",
            "min_area_m2",
            "collinear_max_offset_m",
            "grid_size_m",
            "shared_edge_tolerance_m",
            "origin_rounding_m",
        ):
            value = getattr(self, name)
            if not (
                value >= 0
                and (math.isfinite(value) or name == "collinear_max_offset_m")
            ):
                raise ValueError(f"CadastreOptions.{name} must be >= 0, got {value!r}")
        if self.collinear_tolerance_deg >= 90:
            raise ValueError(
                "CadastreOptions.collinear_tolerance_deg must be < 90, "
                f"got {self.collinear_tolerance_deg!r}"
            )


@dataclass
class CadastreReport:
    """Counts of one :func:`load_cadastre` run, for the run report.

    Attributes
    ----------
    num_features : int, features in the file.
    num_skipped : int, features without polygons (null / other geometry, empty).
    num_repaired : int, invalid features repaired with ``make_valid``.
    num_dropped_small : int, polygons dropped as smaller than ``min_area_m2``.
    num_vertices_in, num_vertices_removed : int, ring vertices before cleaning
        and how many cleaning removed (duplicates, short edges, collinear).
    seconds : float, wall time.
    """

    num_features: int = 0
    num_skipped: int = 0
    num_repaired: int = 0
    num_dropped_small: int = 0
    num_vertices_in: int = 0
    num_vertices_removed: int = 0
    seconds: float = 0.0


@dataclass
class Cadastre:
    """Building footprints in a local metric frame, as flat arrays.

    All coordinates are in the LOCAL frame: ``world_abs = local + origin``
    (metres, x east, y north). B buildings (one per polygon: a MultiPolygon
    feature gives several), C corners and E edges. Every ring (exterior or
    hole) is oriented with the building on its LEFT (exterior CCW, holes CW);
    its n vertices give n corners and n edges, edge k running from corner k
    to corner k + 1 of the same ring, so C == E and corner k's outgoing edge
    is edge k.

    Attributes
    ----------
    crs : str or None
        Normalised CRS name (``"EPSG:28992"``) or the string found in the file;
        None if the file has no ``crs`` member.
    origin : (3,) float array
        Absolute coordinates (m) of the local origin; z is 0 unless given.
    polygons : list of B shapely.Polygon
        Cleaned footprints, local frame, oriented as above.
    building_ids : (B,) str array
        The feature's ``id`` property (else its GeoJSON ``id``, else its index).
    feature_index : (B,) int array
        Index of the source feature in the file.
    heights : (B,) float array
        The feature's ``height`` property (m), NaN if absent.
    corner_xy : (C, 2) float array
        Corner positions (m).
    corner_building : (C,) int array
        Index into the buildings.
    corner_angle_deg : (C,) float array
        Interior angle inside the building, in (0, 360) degrees: 90 for a
        rectangle, 270 for the reflex corner of an L, and 270 for each corner
        of a rectangular courtyard.
    corner_bisector : (C, 2) float array
        Unit vector bisecting the angle OUTSIDE the building (pointing away
        from the material).
    corner_edges : (C, 2) int array
        Indices of the incoming and outgoing edges.
    corner_is_hole : (C,) bool array
        True for corners on a hole (courtyard) ring.
    edge_xy : (E, 2, 2) float array
        Start and end points (m), building on the left.
    edge_normal : (E, 2) float array
        Outward unit normal (pointing away from the building).
    edge_building : (E,) int array
        Index into the buildings.
    edge_length : (E,) float array
        Length (m).
    edge_corners : (E, 2) int array
        Start and end corner indices.
    edge_shared_fraction : (E,) float array
        Fraction in [0, 1] of the edge's length that lies on another building
        (party walls are close to 1).
    tree : shapely.STRtree
        Spatial index over ``polygons``; see :meth:`buildings_near` and
        :meth:`buildings_in_box`.
    report : CadastreReport
        Counts and timing of the load.
    """

    crs: str | None
    origin: np.ndarray
    polygons: list[Polygon]
    building_ids: np.ndarray
    feature_index: np.ndarray
    heights: np.ndarray
    corner_xy: np.ndarray
    corner_building: np.ndarray
    corner_angle_deg: np.ndarray
    corner_bisector: np.ndarray
    corner_edges: np.ndarray
    corner_is_hole: np.ndarray
    edge_xy: np.ndarray
    edge_normal: np.ndarray
    edge_building: np.ndarray
    edge_length: np.ndarray
    edge_corners: np.ndarray
    edge_shared_fraction: np.ndarray
    tree: shapely.STRtree = field(repr=False)
    report: CadastreReport = field(default_factory=CadastreReport)

    @property
    def num_buildings(self) -> int:
        """B, the number of footprint polygons."""
        return len(self.polygons)

    @property
    def num_corners(self) -> int:
        """C, the number of corners."""
        return len(self.corner_xy)

    @property
    def num_edges(self) -> int:
        """E, the number of edges."""
        return len(self.edge_xy)

    def buildings_near(
        self, xy: Sequence[float] | np.ndarray, radius_m: float = 0.0
    ) -> np.ndarray:
        """Buildings within ``radius_m`` of a point.

        Parameters
        ----------
        xy : (2,) array-like, local frame (m).
        radius_m : float, search radius (m); 0 for buildings containing or
            touching the point.

        Returns
        -------
        (K,) int array of building indices, ascending.
        """
        point = shapely.Point(float(xy[0]), float(xy[1]))
        hits = self.tree.query(point, predicate="dwithin", distance=float(radius_m))
        return np.sort(np.asarray(hits, dtype=np.int64))

    def buildings_in_box(
        self, xmin: float, ymin: float, xmax: float, ymax: float
    ) -> np.ndarray:
        """Buildings intersecting an axis-aligned box (local frame, m).

        Returns
        -------
        (K,) int array of building indices, ascending.
        """
        hits = self.tree.query(
            shapely.box(xmin, ymin, xmax, ymax), predicate="intersects"
        )
        return np.sort(np.asarray(hits, dtype=np.int64))

    def absolute_polygons(self) -> list[Polygon]:
        """The footprints in absolute map coordinates (``local + origin``)."""
        x0, y0 = float(self.origin[0]), float(self.origin[1])
        return [shapely.transform(p, lambda c: c + (x0, y0)) for p in self.polygons]


# --------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------


@dataclass
class _Feature:
    """One parsed feature: geometry in absolute coordinates and its properties."""

    index: int
    building_id: str
    height: float
    geometry: Polygon | MultiPolygon

    def label(self) -> str:
        return f"feature {self.index} (id {self.building_id!r})"


def load_cadastre(
    path: str | Path,
    options: CadastreOptions | None = None,
    origin: Sequence[float] | np.ndarray | None = None,
) -> Cadastre:
    """Read a GeoJSON footprint map into a :class:`Cadastre` in a local frame.

    Parameters
    ----------
    path : str or Path
        GeoJSON FeatureCollection of Polygon / MultiPolygon features in a
        projected metric CRS. Other geometry types and null geometries are
        skipped with a warning.
    options : CadastreOptions, optional
        Cleaning options; the defaults suit 1 cm to 10 cm cadastral maps.
    origin : (2,) or (3,) array-like, optional
        Absolute coordinates (m) of the local origin, e.g. to share a frame
        with a priors model. Default: the centre of the map's bounds rounded to
        ``options.origin_rounding_m``, with z = 0.

    Returns
    -------
    Cadastre
        Everything in the local frame, ``world_abs = local + origin``.

    Raises
    ------
    InputError
        Naming the file (and the feature's index and id where one is at fault):
        missing or unreadable file, not JSON, not a FeatureCollection, no
        polygon features, malformed coordinates, invalid geometry that cannot
        be repaired (or ``repair_invalid`` is False), coordinates in degrees.
    """
    t_start = time.perf_counter()
    options = CadastreOptions() if options is None else options
    path = Path(path)
    doc = _read_json(path)
    crs = _parse_crs(path, doc.get("crs"))
    report = CadastreReport(num_features=len(doc["features"]))

    # 1. Parse the features (absolute coordinates).
    features: list[_Feature] = []
    for index, raw in enumerate(doc["features"]):
        feature = _parse_feature(path, index, raw)
        if feature is None:
            report.num_skipped += 1
        else:
            features.append(feature)
    if not features:
        raise InputError(
            path,
            f"no Polygon or MultiPolygon features among {report.num_features} "
            "features; expected building footprints",
        )
    bounds = _check_metric(path, crs, features, options)

    # 2. Local frame.
    origin3 = _choose_origin(bounds, origin, options)
    shift = (-float(origin3[0]), -float(origin3[1]))

    # 3. + 4. Validate / repair, dissolve, orient and clean, in the local frame.
    polygons: list[Polygon] = []
    owners: list[_Feature] = []
    for feature in features:
        geometry = shapely.transform(feature.geometry, lambda c: c + shift)
        parts = _valid_parts(path, feature, geometry, options, report)
        cleaned = [
            p
            for part in parts
            if (p := _clean_polygon(part, options, report)) is not None
        ]
        if not cleaned:
            logger.warning(
                "%s: %s has no polygon of at least %g m^2 after cleaning; dropped",
                path,
                feature.label(),
                options.min_area_m2,
            )
            report.num_skipped += 1
            continue
        polygons.extend(cleaned)
        owners.extend([feature] * len(cleaned))
    if not polygons:
        raise InputError(
            path,
            "no building footprint is left after cleaning "
            f"(all smaller than {options.min_area_m2} m^2 or empty)",
        )

    # 5. Corners, edges, party walls, spatial index.
    cadastre = _assemble(crs, origin3, polygons, owners, options)
    report.seconds = time.perf_counter() - t_start
    cadastre.report = report
    logger.info(
        "cadastre %s: %d features -> %d buildings, %d corners (%d reflex), "
        "%d edges (%d party walls), %d repaired, %d skipped, %.2f s",
        path.name,
        report.num_features,
        cadastre.num_buildings,
        cadastre.num_corners,
        int(np.sum(cadastre.corner_angle_deg > 180.0)),
        cadastre.num_edges,
        int(np.sum(cadastre.edge_shared_fraction >= SHARED_WALL_FRACTION)),
        report.num_repaired,
        report.num_skipped,
        report.seconds,
    )
    return cadastre


def _read_json(path: Path) -> dict:
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


def _parse_crs(path: Path, member: Any) -> str | None:
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


def _parse_feature(path: Path, index: int, raw: Any) -> _Feature | None:
    """One feature's geometry (absolute) and properties; None to skip it."""
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
        logger.warning(
            "%s: %s has %s, not a Polygon or MultiPolygon; skipped", path, label, what
        )
        return None
    try:
        geometry = shapely.force_2d(shape(geom))
    except Exception as err:  # shapely raises many types for bad coordinates
        raise InputError(
            path, f"{label}: malformed {kind} coordinates ({err})"
        ) from None
    if geometry.is_empty:
        logger.warning("%s: %s has an empty %s; skipped", path, label, kind)
        return None
    coords = shapely.get_coordinates(geometry)
    if not np.all(np.isfinite(coords)):
        raise InputError(path, f"{label}: coordinates are not all finite numbers")
    return _Feature(index, building_id, height, geometry)


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


def _check_metric(
    path: Path, crs: str | None, features: list[_Feature], options: CadastreOptions
) -> tuple[float, float, float, float]:
    """Reject degrees; return the absolute bounds (xmin, ymin, xmax, ymax)."""
    if crs is not None and crs.upper() in GEOGRAPHIC_CRS:
        raise InputError(
            path,
            f"the map's CRS {crs} is longitude/latitude in degrees; "
            "footprints must be in a projected metric CRS (e.g. UTM): reproject "
            "the file first (e.g. ogr2ogr -t_srs EPSG:<UTM zone>); reprojection "
            "is not supported yet",
        )
    xmin, ymin, xmax, ymax = shapely.total_bounds([f.geometry for f in features])
    degree_like = max(abs(xmin), abs(xmax)) <= 180 and max(abs(ymin), abs(ymax)) <= 90
    if degree_like and not options.allow_degree_range:
        raise InputError(
            path,
            f"coordinates look like longitude/latitude in degrees (x in "
            f"[{xmin:g}, {xmax:g}], y in [{ymin:g}, {ymax:g}]); footprints must "
            "be in a projected metric CRS (e.g. UTM): reproject the file first "
            "(e.g. ogr2ogr -t_srs EPSG:<UTM zone>); reprojection is not supported "
            "yet. If these really are metres in a local frame, set "
            "CadastreOptions(allow_degree_range=True)",
        )
    return float(xmin), float(ymin), float(xmax), float(ymax)


def _choose_origin(
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


def _polygonal_parts(geometry: shapely.Geometry) -> list[Polygon]:
    """The non-empty Polygons of any geometry (GeometryCollection included)."""
    if isinstance(geometry, Polygon):
        return [] if geometry.is_empty else [geometry]
    if isinstance(geometry, MultiPolygon | shapely.GeometryCollection):
        return [p for g in geometry.geoms for p in _polygonal_parts(g)]
    return []


def _valid_parts(
    path: Path,
    feature: _Feature,
    geometry: shapely.Geometry,
    options: CadastreOptions,
    report: CadastreReport,
) -> list[Polygon]:
    """Valid polygons of one feature (local frame), repaired and dissolved."""
    if not geometry.is_valid:
        reason = shapely.is_valid_reason(geometry)
        if not options.repair_invalid:
            raise InputError(
                path,
                f"{feature.label()}: invalid geometry ({reason}); fix the "
                "footprint or enable CadastreOptions(repair_invalid=True)",
            )
        repaired = shapely.make_valid(
            geometry, method="structure", keep_collapsed=False
        )
        parts = _polygonal_parts(repaired)
        if not parts or sum(p.area for p in parts) <= 0:
            raise InputError(
                path,
                f"{feature.label()}: invalid geometry ({reason}) that cannot "
                "be repaired into a polygon with an area",
            )
        logger.debug("%s: %s repaired (%s)", path, feature.label(), reason)
        report.num_repaired += 1
    else:
        parts = _polygonal_parts(geometry)
    if options.dissolve_parts and len(parts) > 1:
        parts = _polygonal_parts(
            shapely.union_all(parts, grid_size=options.grid_size_m or None)
        )
    return parts


def _prev(xy: np.ndarray) -> np.ndarray:
    """(n, 2) previous vertices of a ring (cyclic); faster than np.roll."""
    return np.concatenate((xy[-1:], xy[:-1]))


def _next(xy: np.ndarray) -> np.ndarray:
    """(n, 2) next vertices of a ring (cyclic)."""
    return np.concatenate((xy[1:], xy[:1]))


def _turn_angles(xy: np.ndarray) -> np.ndarray:
    """(n,) signed turn angles (radians, left positive) at the vertices of a ring.

    ``xy`` is (n, 2), not closed. Interior angle = pi - turn for a ring with
    the building on its left.
    """
    d_in = xy - _prev(xy)
    d_out = _next(xy) - xy
    cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
    dot = np.sum(d_in * d_out, axis=1)
    return np.arctan2(cross, dot)


def _clean_ring(xy: np.ndarray, options: CadastreOptions) -> np.ndarray:
    """Drop near-duplicate and collinear vertices of one ring.

    Parameters
    ----------
    xy : (n, 2) array, the ring without its closing point.

    Returns
    -------
    (m, 2) array, m <= n; fewer than 3 rows means the ring collapsed.

    Works worst-first, one vertex at a time, so that a run of small bends is
    not flattened by removing all its vertices at once: removing a vertex
    makes its neighbours' turns larger.
    """
    tol_rad = math.radians(options.collinear_tolerance_deg)
    while len(xy) >= 3:
        lengths = np.linalg.norm(_next(xy) - xy, axis=1)
        k = int(np.argmin(lengths))
        if lengths[k] < max(options.min_edge_length_m, 1e-9):
            # Merge the two ends of the shortest edge into its midpoint.
            k1 = (k + 1) % len(xy)
            xy[k] = (xy[k] + xy[k1]) / 2
            xy = np.delete(xy, k1, axis=0)
            continue
        turns = np.abs(_turn_angles(xy))
        turns[_chord_offsets(xy) > options.collinear_max_offset_m] = np.inf
        k = int(np.argmin(turns))
        if turns[k] <= tol_rad:
            xy = np.delete(xy, k, axis=0)
            continue
        break
    return xy


def _chord_offsets(xy: np.ndarray) -> np.ndarray:
    """(n,) distances (m) of ring vertices from the line through their neighbours."""
    prev, nxt = _prev(xy), _next(xy)
    chord = nxt - prev
    rel = xy - prev
    cross = chord[:, 0] * rel[:, 1] - chord[:, 1] * rel[:, 0]
    norm = np.linalg.norm(chord, axis=1)
    return np.abs(cross) / np.where(norm > 0, norm, 1.0)


def _clean_polygon(
    polygon: Polygon, options: CadastreOptions, report: CadastreReport
) -> Polygon | None:
    """Oriented, cleaned polygon (building on the left of every ring), or None."""
    polygon = orient(polygon, sign=1.0)
    if polygon.area < max(options.min_area_m2, 1e-12):
        report.num_dropped_small += 1
        return None
    rings = [polygon.exterior, *polygon.interiors]
    n_in = sum(len(r.coords) - 1 for r in rings)
    cleaned = [
        _clean_ring(np.asarray(r.coords)[:-1, :2].copy(), options) for r in rings
    ]
    if len(cleaned[0]) < 3:
        report.num_dropped_small += 1
        return None
    holes = [
        h
        for h in cleaned[1:]
        if len(h) >= 3 and Polygon(h).area >= max(options.min_area_m2, 1e-12)
    ]
    result = orient(Polygon(cleaned[0], holes), sign=1.0)
    if not result.is_valid or result.area < max(options.min_area_m2, 1e-12):
        # Cleaning moved a vertex across another ring (very rare): keep the
        # oriented polygon as it was rather than invent geometry.
        logger.debug("cleaning made a polygon invalid; kept it uncleaned")
        result = polygon
    n_out = (
        len(result.exterior.coords)
        - 1
        + sum(len(r.coords) - 1 for r in result.interiors)
    )
    report.num_vertices_in += n_in
    report.num_vertices_removed += n_in - n_out
    return result


def _assemble(
    crs: str | None,
    origin: np.ndarray,
    polygons: list[Polygon],
    owners: list[_Feature],
    options: CadastreOptions,
) -> Cadastre:
    """Corner and edge arrays, party walls and the spatial index."""
    rings: list[np.ndarray] = []
    ring_building: list[int] = []
    ring_is_hole: list[bool] = []
    for b, polygon in enumerate(polygons):
        for k, ring in enumerate([polygon.exterior, *polygon.interiors]):
            rings.append(np.asarray(ring.coords)[:-1, :2])
            ring_building.append(b)
            ring_is_hole.append(k > 0)
    sizes = np.array([len(r) for r in rings], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    ring_of = np.repeat(np.arange(len(rings)), sizes)  # (C,)
    local = np.arange(int(sizes.sum())) - starts[ring_of]  # index within the ring
    nxt = starts[ring_of] + (local + 1) % sizes[ring_of]  # (C,) next corner
    prv = starts[ring_of] + (local - 1) % sizes[ring_of]  # (C,) previous corner

    xy = np.concatenate(rings, axis=0)  # (C, 2)
    edge_xy = np.stack([xy, xy[nxt]], axis=1)  # (E, 2, 2), edge k: k -> nxt[k]
    d = edge_xy[:, 1] - edge_xy[:, 0]
    length = np.linalg.norm(d, axis=1)
    direction = d / length[:, None]
    normal = np.stack([direction[:, 1], -direction[:, 0]], axis=1)  # right = out

    turn = _turn_angles_flat(direction[prv], direction)
    angle = np.pi - turn  # interior angle, radians, in (0, 2 pi)
    # The interior sweeps counter-clockwise from the outgoing direction to the
    # reversed incoming one; its bisector is the outgoing direction rotated by
    # angle / 2, and the outward bisector is its opposite.
    half = angle / 2
    c, s = np.cos(half), np.sin(half)
    inward = np.stack(
        [
            c * direction[:, 0] - s * direction[:, 1],
            s * direction[:, 0] + c * direction[:, 1],
        ],
        axis=1,
    )

    building = np.asarray(ring_building, dtype=np.int64)[ring_of]
    tree = shapely.STRtree(polygons)
    shared = _shared_fraction(
        tree, polygons, edge_xy, length, building, options.shared_edge_tolerance_m
    )
    return Cadastre(
        crs=crs,
        origin=np.asarray(origin, dtype=float),
        polygons=polygons,
        building_ids=np.array([f.building_id for f in owners], dtype=str),
        feature_index=np.array([f.index for f in owners], dtype=np.int64),
        heights=np.array([f.height for f in owners], dtype=float),
        corner_xy=xy,
        corner_building=building,
        corner_angle_deg=np.degrees(angle),
        corner_bisector=-inward,
        corner_edges=np.stack([prv, np.arange(len(xy))], axis=1),
        corner_is_hole=np.asarray(ring_is_hole, dtype=bool)[ring_of],
        edge_xy=edge_xy,
        edge_normal=normal,
        edge_building=building.copy(),
        edge_length=length,
        edge_corners=np.stack([np.arange(len(xy)), nxt], axis=1),
        edge_shared_fraction=shared,
        tree=tree,
    )


def _turn_angles_flat(d_in: np.ndarray, d_out: np.ndarray) -> np.ndarray:
    """(N,) signed turn (radians, left positive) from (N, 2) d_in to d_out."""
    cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
    return np.arctan2(cross, np.sum(d_in * d_out, axis=1))


def _shared_fraction(
    tree: shapely.STRtree,
    polygons: list[Polygon],
    edge_xy: np.ndarray,
    edge_length: np.ndarray,
    edge_building: np.ndarray,
    tolerance_m: float,
) -> np.ndarray:
    """(E,) fraction of each edge lying within ``tolerance_m`` of OTHER buildings."""
    lines = shapely.linestrings(edge_xy)  # (E,) LineStrings
    tol = max(tolerance_m, 1e-6)
    edge_idx, poly_idx = tree.query(lines, predicate="dwithin", distance=tol)
    other = edge_building[edge_idx] != poly_idx
    edge_idx, poly_idx = edge_idx[other], poly_idx[other]
    if len(edge_idx) == 0:
        return np.zeros(len(edge_xy))
    grown = shapely.buffer(
        np.asarray(polygons, dtype=object)[poly_idx],
        tol,
        quad_segs=2,
        join_style="mitre",
    )
    covered = shapely.length(shapely.intersection(lines[edge_idx], grown))
    # An edge that only ends at a neighbour (the front wall next to a party
    # wall) dips into its buffer over ~tol: that is not a shared stretch.
    covered[covered <= 2 * tol + 1e-9] = 0.0
    total = np.bincount(edge_idx, weights=covered, minlength=len(edge_xy))
    return np.clip(total / edge_length, 0.0, 1.0)


# --------------------------------------------------------------------------
# Visibility
# --------------------------------------------------------------------------


def _ground_at(ground_height: GroundHeight, xy: np.ndarray) -> np.ndarray:
    """(N,) ground heights (m) at (N, 2) local xy."""
    if callable(ground_height):
        z = np.asarray(ground_height(xy), dtype=float)
        if z.shape != (len(xy),):
            raise ValueError(
                f"ground_height({len(xy)} x 2 points) must return shape "
                f"({len(xy)},), got {z.shape}"
            )
        return z
    return np.full(len(xy), float(ground_height))


def _frustum_bounds(camera: Camera, margin_px: float) -> np.ndarray:
    """(xmin, xmax, ymin, ymax) of the image in normalised camera coordinates.

    The image spans pixels [0, width] x [0, height] (COLMAP convention), grown
    by ``margin_px``. Without distortion the bounds are exact; with distortion
    they are the bounding box of the undistorted image border (sampled), so
    the frustum test is conservative near the image corners.
    """
    m = float(margin_px)
    w, h = float(camera.width), float(camera.height)
    if not camera.has_distortion:
        K = camera.K
        return np.array(
            [
                (-m - K[0, 2]) / K[0, 0],
                (w + m - K[0, 2]) / K[0, 0],
                (-m - K[1, 2]) / K[1, 1],
                (h + m - K[1, 2]) / K[1, 1],
            ]
        )
    u = np.linspace(-m, w + m, 65)
    v = np.linspace(-m, h + m, 65)
    border = np.concatenate(
        [
            np.stack([u, np.full_like(u, -m)], 1),
            np.stack([u, np.full_like(u, h + m)], 1),
            np.stack([np.full_like(v, -m), v], 1),
            np.stack([np.full_like(v, w + m), v], 1),
        ]
    )
    uv = camera.cam_from_img(border)
    return np.array([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])


def _frustum_planes(
    camera: Camera, margin_px: float, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Half-spaces ``n . X_cam + d >= 0`` of the viewing frustum.

    Returns
    -------
    normals : (5, 3) array, camera frame.
    offsets : (5,) array, metres.
    """
    xmin, xmax, ymin, ymax = _frustum_bounds(camera, margin_px)
    normals = np.array(
        [
            [1.0, 0.0, -xmin],  # x >= xmin z
            [-1.0, 0.0, xmax],  # x <= xmax z
            [0.0, 1.0, -ymin],  # y >= ymin z
            [0.0, -1.0, ymax],  # y <= ymax z
            [0.0, 0.0, 1.0],  # z >= min_depth
        ]
    )
    offsets = np.array([0.0, 0.0, 0.0, 0.0, -float(min_depth_m)])
    return normals, offsets


def _vertical_extent(
    cadastre: Cadastre,
    buildings: np.ndarray,
    height_range_m: tuple[float, float],
    use_building_heights: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bottom and top heights above the ground (m) for each building index."""
    h_min, h_max = (float(v) for v in height_range_m)
    if not h_max >= h_min:
        raise ValueError(
            f"height_range_m must be (min, max) with min <= max, got {height_range_m!r}"
        )
    bottom = np.full(len(buildings), h_min)
    top = np.full(len(buildings), h_max)
    if use_building_heights:
        h = cadastre.heights[buildings]
        known = np.isfinite(h)
        top[known] = np.clip(h[known], h_min, h_max)
    return bottom, top


def _facing(
    cadastre: Cadastre, center_xy: np.ndarray, exclude_shared_walls: bool
) -> np.ndarray:
    """(E,) bool: the wall's outward normal points towards the camera centre."""
    to_camera = center_xy[None, :] - cadastre.edge_xy[:, 0]  # (E, 2)
    facing = np.sum(cadastre.edge_normal * to_camera, axis=1) > 0
    if exclude_shared_walls:
        facing &= cadastre.edge_shared_fraction < SHARED_WALL_FRACTION
    return facing


def visible_corners(
    cadastre: Cadastre,
    camera: Camera,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float] = (0.0, 50.0),
    margin_px: float = 0.0,
    *,
    use_building_heights: bool = True,
    exclude_shared_walls: bool = True,
    min_depth_m: float = 0.1,
) -> np.ndarray:
    """Corners whose vertical building edge a camera can potentially see.

    A corner is kept when

    1. the vertical segment from ``ground + h_min`` to ``ground + h_max`` at the
       corner lies at least partly inside the viewing frustum (in front of the
       camera by ``min_depth_m`` and inside the image grown by ``margin_px``),
       and
    2. at least one of its two walls faces the camera: the wall's outward
       normal has a positive dot product with the horizontal direction from
       the wall to the camera centre. A convex corner with both walls facing
       away is hidden by its own building; so is a reflex corner, which is
       seen only when its walls face the camera.

    There is no occlusion test against other buildings (later stages handle
    occlusion through robust matching).

    Parameters
    ----------
    cadastre : Cadastre
    camera : Camera
        Intrinsics; the image is [0, width] x [0, height] px.
    cam_from_world : Pose
        Pose in the cadastre's LOCAL frame.
    ground_height : float or callable
        Ground height (m, local frame, the priors' vertical datum), or a
        function of (N, 2) local xy returning (N,) heights, e.g. a plane.
    height_range_m : (2,) tuple of float
        (h_min, h_max), metres above the ground spanned by the corner's
        vertical segment.
    margin_px : float
        Grow the image by this many pixels on every side (uncertain poses).
    use_building_heights : bool
        Where the map gives a building's height, end its segment there
        (clipped to ``height_range_m``).
    exclude_shared_walls : bool
        Party walls (``edge_shared_fraction >= SHARED_WALL_FRACTION``) do not
        count as walls facing the camera.
    min_depth_m : float
        Near plane (m in front of the camera).

    Returns
    -------
    (K,) int array
        Indices into the cadastre's corners, ascending.

    Notes
    -----
    With lens distortion the frustum is the bounding box of the undistorted
    image border, which keeps a few corners just outside the image corners.
    """
    if cadastre.num_corners == 0:
        return np.zeros(0, dtype=np.int64)
    center = cam_from_world.center
    facing = _facing(cadastre, center[:2], exclude_shared_walls)
    candidate = (
        facing[cadastre.corner_edges[:, 0]] | facing[cadastre.corner_edges[:, 1]]
    )
    idx = np.flatnonzero(candidate)
    if len(idx) == 0:
        return idx.astype(np.int64)

    xy = cadastre.corner_xy[idx]
    ground = _ground_at(ground_height, xy)
    bottom, top = _vertical_extent(
        cadastre, cadastre.corner_building[idx], height_range_m, use_building_heights
    )
    R, t = cam_from_world.rotation, cam_from_world.translation
    start_world = np.column_stack([xy, ground + bottom])  # (K, 3)
    start_cam = start_world @ R.T + t  # (K, 3)
    up_cam = np.outer(top - bottom, R[:, 2])  # (K, 3), R @ (0, 0, dz)
    normals, offsets = _frustum_planes(camera, margin_px, min_depth_m)
    # X(t) = start + t up, t in [0, 1]; each plane: a t + c >= 0.
    a = up_cam @ normals.T  # (K, 5)
    c = start_cam @ normals.T + offsets  # (K, 5)
    inside = _interval_nonempty(a, c)
    return idx[inside].astype(np.int64)


def _interval_nonempty(a: np.ndarray, c: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(K,) bool: some t in [0, 1] has ``a t + c >= 0`` for all (K, P) rows."""
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -c / a
    lower = np.max(np.where(a > 0, root, 0.0), axis=1, initial=0.0)
    upper = np.min(np.where(a < 0, root, 1.0), axis=1, initial=1.0)
    flat_ok = np.all((a != 0) | (c >= -tol), axis=1)
    return flat_ok & (lower <= upper + tol)


def visible_edge_parts(
    cadastre: Cadastre,
    camera: Camera,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float] = (0.0, 50.0),
    margin_px: float = 0.0,
    *,
    use_building_heights: bool = True,
    exclude_shared_walls: bool = True,
    min_depth_m: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Facade walls a camera can potentially see, with their visible parts.

    A wall is the vertical quadrilateral over an edge from ``ground + h_min``
    to ``ground + h_max`` (the ground is interpolated linearly along the edge,
    exact for a planar ground). It is kept when it faces the camera (outward
    normal towards the camera centre, horizontally) and intersects the viewing
    frustum. The intersection is exact for a pinhole camera: in wall
    coordinates (s along the edge, t up the wall, both in [0, 1]) the part
    inside the frustum is a convex polygon cut out by 9 half-planes, found for
    all walls at once from the pairwise intersections of their boundary lines.
    No occlusion by other buildings is modelled.

    Parameters
    ----------
    Same as :func:`visible_corners`.

    Returns
    -------
    indices : (K,) int array
        Edge indices, ascending.
    clipped_xy : (K, 2, 2) float array
        Start and end (local frame, m) of the part of each edge over which
        some of the wall is inside the frustum, in the edge's direction.
    """
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 2, 2)))
    if cadastre.num_edges == 0:
        return empty
    center = cam_from_world.center
    idx = np.flatnonzero(_facing(cadastre, center[:2], exclude_shared_walls))
    if len(idx) == 0:
        return empty
    normals, offsets = _frustum_planes(camera, margin_px, min_depth_m)
    keep: list[np.ndarray] = []
    ranges: list[np.ndarray] = []
    for lo in range(0, len(idx), _EDGE_CHUNK):
        chunk = idx[lo : lo + _EDGE_CHUNK]
        ok, s_range = _clip_walls(
            cadastre,
            chunk,
            cam_from_world,
            ground_height,
            height_range_m,
            use_building_heights,
            normals,
            offsets,
        )
        keep.append(chunk[ok])
        ranges.append(s_range[ok])
    indices = np.concatenate(keep).astype(np.int64)
    s_range = np.concatenate(ranges, axis=0)  # (K, 2)
    p0, p1 = cadastre.edge_xy[indices, 0], cadastre.edge_xy[indices, 1]
    d = p1 - p0
    clipped = np.stack([p0 + s_range[:, :1] * d, p0 + s_range[:, 1:] * d], axis=1)
    return indices, clipped


def visible_edges(
    cadastre: Cadastre,
    camera: Camera,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float] = (0.0, 50.0),
    margin_px: float = 0.0,
    *,
    use_building_heights: bool = True,
    exclude_shared_walls: bool = True,
    min_depth_m: float = 0.1,
) -> np.ndarray:
    """Indices of the facade walls a camera can potentially see.

    See :func:`visible_edge_parts` (which also returns the visible part of
    each edge) for the test and the parameters.

    Returns
    -------
    (K,) int array
        Edge indices, ascending.
    """
    indices, _ = visible_edge_parts(
        cadastre,
        camera,
        cam_from_world,
        ground_height,
        height_range_m,
        margin_px,
        use_building_heights=use_building_heights,
        exclude_shared_walls=exclude_shared_walls,
        min_depth_m=min_depth_m,
    )
    return indices


def _clip_walls(
    cadastre: Cadastre,
    edges: np.ndarray,
    cam_from_world: Pose,
    ground_height: GroundHeight,
    height_range_m: tuple[float, float],
    use_building_heights: bool,
    normals: np.ndarray,
    offsets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Clip N walls against the frustum.

    Returns
    -------
    ok : (N,) bool, the wall intersects the frustum.
    s_range : (N, 2) array, [s_min, s_max] along the edge of the visible part
        (meaningless where not ok).
    """
    xy = cadastre.edge_xy[edges]  # (N, 2, 2)
    n = len(edges)
    ground = _ground_at(ground_height, xy.reshape(-1, 2)).reshape(n, 2)
    bottom, top = _vertical_extent(
        cadastre, cadastre.edge_building[edges], height_range_m, use_building_heights
    )
    R, t = cam_from_world.rotation, cam_from_world.translation
    b0 = np.column_stack([xy[:, 0], ground[:, 0] + bottom])  # (N, 3)
    b1 = np.column_stack([xy[:, 1], ground[:, 1] + bottom])  # (N, 3)
    # X(s, t) = b0 + s (b1 - b0) + t (0, 0, top - bottom), camera frame:
    base = b0 @ R.T + t
    along = (b1 - b0) @ R.T
    up = np.outer(top - bottom, R[:, 2])
    # Half-planes a s + b t + c >= 0: 5 frustum planes, then the unit square.
    a = np.concatenate([along @ normals.T, np.tile([1.0, -1.0, 0.0, 0.0], (n, 1))], 1)
    b = np.concatenate([up @ normals.T, np.tile([0.0, 0.0, 1.0, -1.0], (n, 1))], 1)
    c = np.concatenate(
        [base @ normals.T + offsets, np.tile([0.0, 1.0, 0.0, 1.0], (n, 1))], 1
    )  # (N, 9)
    scale = np.hypot(a, b)
    degenerate = scale < 1e-12  # a constant constraint: c >= 0 or never
    scale = np.where(degenerate, 1.0, scale)
    a, b, c = a / scale, b / scale, c / scale
    tol = 1e-9
    always_violated = np.any(degenerate & (c < -tol), axis=1)

    # Candidate vertices: intersections of every pair of boundary lines.
    i, j = np.triu_indices(a.shape[1], k=1)  # 36 pairs
    det = a[:, i] * b[:, j] - a[:, j] * b[:, i]  # (N, 36)
    good = np.abs(det) > 1e-12
    det = np.where(good, det, 1.0)
    s = (-c[:, i] * b[:, j] + b[:, i] * c[:, j]) / det
    tt = (-a[:, i] * c[:, j] + a[:, j] * c[:, i]) / det
    # Feasible: every half-plane holds, (N, 36, 9).
    slack = a[:, None, :] * s[..., None] + b[:, None, :] * tt[..., None] + c[:, None, :]
    feasible = good & np.all(slack >= -tol, axis=2)
    ok = feasible.any(axis=1) & ~always_violated
    s_min = np.min(np.where(feasible, s, np.inf), axis=1)
    s_max = np.max(np.where(feasible, s, -np.inf), axis=1)
    s_range = np.clip(np.stack([s_min, s_max], axis=1), 0.0, 1.0)
    return ok, s_range


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------


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
