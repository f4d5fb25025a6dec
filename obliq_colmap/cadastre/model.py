"""The :class:`Cadastre`: cleaned footprints, corners and edges as flat arrays."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import Polygon

from .options import CadastreReport

#: An edge covered by neighbouring buildings over at least this fraction of its
#: length is a party wall: it is inside the block and never seen as a facade.
SHARED_WALL_FRACTION = 0.9


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
