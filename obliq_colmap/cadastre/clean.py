"""Cleaning footprints and building the corner / edge arrays.

Steps 3 to 5 of :func:`load_cadastre`, in the LOCAL frame: repair and
dissolve each feature's polygons, orient and clean every ring (building on
the LEFT), then assemble corners, edges, party walls and the spatial index
into a :class:`Cadastre`.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.polygon import orient

from obliq_colmap.errors import InputError

from .model import Cadastre
from .options import CadastreOptions, CadastreReport
from .read import Feature

logger = logging.getLogger(__name__)


def _polygonal_parts(geometry: shapely.Geometry) -> list[Polygon]:
    """The non-empty Polygons of any geometry (GeometryCollection included)."""
    if isinstance(geometry, Polygon):
        return [] if geometry.is_empty else [geometry]
    if isinstance(geometry, MultiPolygon | shapely.GeometryCollection):
        return [p for g in geometry.geoms for p in _polygonal_parts(g)]
    return []


def valid_parts(
    path: Path,
    feature: Feature,
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


def clean_polygon(
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


def assemble(
    crs: str | None,
    origin: np.ndarray,
    polygons: list[Polygon],
    owners: list[Feature],
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
