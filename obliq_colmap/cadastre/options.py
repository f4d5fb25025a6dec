"""Options and run counts of the cadastre stage (:func:`load_cadastre`)."""

from __future__ import annotations

import math
from dataclasses import dataclass


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
        degrees: a small map in a local metric frame near (0, 0). Otherwise
        such a map is RFC 7946 GeoJSON (WGS 84 longitude / latitude) and is
        reprojected.
    crs : str or None
        The projected CRS to bring the map into (``register --crs``, e.g.
        "EPSG:25832": the priors' CRS); None keeps a projected map's own and
        takes the UTM zone of its centre for one in longitude / latitude.
    area : (xmin, ymin, xmax, ymax) or None
        Absolute bounds (in the map's projected CRS) of the part of the map
        to keep: features whose bounding box misses it are dropped before
        cleaning, so a city-wide map costs what the block's part of it
        costs. ``register`` sets it from the prior camera centres and
        ``area_margin_m``; None keeps the whole map.
    area_margin_m : float
        ``register``: the map is kept within this distance of the prior
        camera centres. An oblique camera 1,000 m above ground at 45 deg
        with a 30 deg field of view sees ~2.4 km far; 3,000 m covers
        flights up to ~1,200 m.
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
    crs: str | None = None
    area: tuple[float, float, float, float] | None = None
    area_margin_m: float = 3000.0

    def __post_init__(self) -> None:
        for name in (
            "min_edge_length_m",
            "collinear_tolerance_deg",
            "min_area_m2",
            "collinear_max_offset_m",
            "grid_size_m",
            "shared_edge_tolerance_m",
            "origin_rounding_m",
            "area_margin_m",
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
