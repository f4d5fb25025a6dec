"""Buildings the images show where the map has none ("missing from the map").

Candidates come from the registration's own evidence: the bundle's tie
points written into points3D (every point that is not a map corner or a
facade track). A tie point counts as elevated when it stands at least
``min_height_m`` (the definition of a building) plus ``sigmas`` times the
measured height noise above the terrain grid: the noise of one point's
height above the grid is the ground corners' scatter about the grid and the
point's own (its reprojection error times its depth over the focal length,
the block's median). Elevated points outside every mapped footprint (grown
by ``map_margin_m``: walls, eaves and overhangs of mapped buildings) are
linked when closer than ``link_m`` and the groups with at least
``min_points`` points are the candidates.

A candidate is judged by its roof (:func:`roof_cells`): a height sweep of
a patch around its points (``patch_m``, minus the mapped footprints), cut
into cells of ``cell_m``; each cell's height is where the views agree best
on its texture (the mean NCC over view pairs). Cells count where their
agreement reaches the ``ref_quantile`` of the block's own mapped roofs'
cells swept alike (:func:`roof_reference`, :func:`reference_thresholds`).
The roof is the plane (:func:`roof_plane`; a pitched roof: one of its
planes) holding the most counted cells ``min_height_m`` above the ground
within ``plane_sigmas`` times the height noise of a mapped roof's cells
about their plane (measured there too). The patch grows while that plane
reaches its edge (``max_grow``). A candidate is reported when the plane
covers ``min_area_m2`` and ``min_plane_fraction`` of its elevated counted
cells. The size is what tells most trees apart: a crown's cells agree as
well as a roof's in the renders measured, and a crown's top or a ring of
its cells is level too, but over less than a dwelling's roof (houses-102:
where crowns touch they reach one; see the journal).

The walls (:func:`wall_evidence`, ``walls``): at each corner of a reported
roof's rectangle, in each view facing it, is a vertical edge seen along
the corner's vertical? Chance is measured on the same rectangles grown by
``wall_null_m``; ``walls_confirmed`` where a binomial tail under it is
below ``wall_alpha``. It does not decide ``reported``: where the plane is
only part of the building, its rectangle's corners miss the walls.

Each candidate becomes a GeoJSON feature (the plane cells' minimum rotated
rectangle) with its score, the roof plane's height above the ground, and
the evidence counts.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.stats import binom

from obliq_colmap.products.roof import (
    RoofView,
    patch_pixels,
    stacked_agreement,
    view_samples,
    views_seeing,
)

__all__ = [
    "MissingOptions",
    "elevated_clusters",
    "find_missing",
    "roof_cells",
    "roof_plane",
]

logger = logging.getLogger(__name__)


@dataclass
class MissingOptions:
    """Options of :func:`find_missing`."""

    #: a building stands at least this high above the ground (m).
    min_height_m: float = 2.5
    #: and its roof plane covers at least this (m^2, horizontally): a small
    #: dwelling's roof, or one half of a pitched one; garages and sheds are
    #: not reported (on the external scenes tree crowns' plane cells cover
    #: up to 34 m^2 alone, and up to 74 m^2 where crowns touch).
    min_area_m2: float = 40.0
    #: a point is elevated when this many sigmas of its height noise above
    #: ``min_height_m``.
    sigmas: float = 2.0
    #: mapped footprints grown by this (m) before points outside count.
    map_margin_m: float = 1.0
    #: elevated points closer than this (m, horizontally) are one candidate.
    link_m: float = 4.0
    #: elevated tie points a candidate needs (the points say where to look;
    #: the roof's sweep is the test: one point is enough).
    min_points: int = 1
    #: views that must see a candidate.
    min_views: int = 3
    #: the swept patch: the points' hull grown by this (m).
    patch_m: float = 4.0
    #: cell size (m) and samples per cell side.
    cell_m: float = 1.5
    cell_samples: int = 4
    #: the sweep's step (m).
    sweep_step_m: float = 0.5
    #: the share of a candidate's agreeing cells on its roof plane.
    min_plane_fraction: float = 0.4
    #: mapped roofs measured for the agreement threshold, and its quantile.
    ref_buildings: int = 40
    ref_quantile: float = 0.25
    #: a cell is on a roof plane within this many of the measured sigmas of
    #: a mapped roof's cells about their plane.
    plane_sigmas: float = 2.5
    #: the patch grows at most this many times.
    max_grow: int = 4
    #: the walls' test (:func:`wall_evidence`): heights sampled along a
    #: corner's vertical, and the search about each corner (m).
    wall_samples: int = 6
    wall_search_m: float = 1.0
    #: the chance of the walls' test is measured this far outside (m), and
    #: a candidate's walls are seen when chance explains them with less
    #: than this probability.
    wall_null_m: float = 3.0
    wall_alpha: float = 0.01
    #: run the walls' test (needs the images' files; without it, or without
    #: the files, a roof alone is reported).
    walls: bool = True

    def __post_init__(self) -> None:
        if self.cell_samples < 2 or self.cell_m <= 0 or self.sweep_step_m <= 0:
            raise ValueError("cell_samples >= 2, cell_m > 0, sweep_step_m > 0")
        if not self.min_area_m2 > 0 or self.min_points < 1:
            raise ValueError("min_area_m2 > 0, min_points >= 1")


def elevated_clusters(
    xyz: np.ndarray,
    height: np.ndarray,
    outside: np.ndarray,
    min_height: float,
    options: MissingOptions,
) -> list[np.ndarray]:
    """Groups (indices into xyz) of elevated points outside the map:
    ``height >= min_height`` and ``outside``, linked within ``link_m``,
    at least ``min_points`` each, largest first."""
    sel = np.flatnonzero(outside & (height >= min_height))
    if len(sel) == 0:
        return []
    pairs = cKDTree(xyz[sel, :2]).query_pairs(options.link_m, output_type="ndarray")
    n = len(sel)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(graph, directed=False)
    count = np.bincount(lab)
    keep = np.flatnonzero(count >= options.min_points)
    keep = keep[np.argsort(-count[keep], kind="stable")]
    return [sel[lab == k] for k in keep]


def cell_grid(patch, options: MissingOptions) -> tuple[np.ndarray, np.ndarray]:
    """Cell centres (C, 2) inside ``patch`` and each cell's samples about
    its centre (k, 2)."""
    x0, y0, x1, y1 = patch.bounds
    c = options.cell_m
    gx, gy = np.meshgrid(np.arange(x0 + c / 2, x1, c), np.arange(y0 + c / 2, y1, c))
    cen = np.column_stack([gx.ravel(), gy.ravel()])
    cen = cen[shapely.contains_xy(patch, cen[:, 0], cen[:, 1])]
    m = options.cell_samples
    t = ((np.arange(m) + 0.5) / m - 0.5) * c
    return cen, np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)


def roof_cells(
    views: list[RoofView],
    centres: np.ndarray,
    offsets: np.ndarray,
    z: np.ndarray,
    min_views: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Per cell, the swept height at which the views agree best and that
    agreement (mean NCC over pairs of views of the cell's samples).

    centres : (C, 2) cells, their samples at ``offsets`` (k, 2) about each
    (:func:`cell_grid`); z : (H,) heights (model frame).

    Returns best_z (C,) (NaN where no height has ``min_views`` views) and
    peak (C,) NCC.
    """
    C, H = len(centres), len(z)
    z = np.broadcast_to(z, (C, H))
    read = []
    for v in views:
        q, front = patch_pixels(v, centres, offsets, z)
        # a view counts for a cell at a height where all its samples are inside
        r = view_samples(v, q, np.broadcast_to(front[..., None], q.shape[:-1]), 1.0)
        if r is not None:
            read.append(r)
    if len(read) < 2:
        return np.full(C, np.nan), np.zeros(C)
    ncc, n = stacked_agreement(
        np.stack([r[0] for r in read], axis=1), np.stack([r[1] for r in read], axis=1)
    )  # (C, H)
    ncc = np.where(n >= min_views, ncc, -np.inf)
    i = ncc.argmax(axis=1)
    peak = ncc[np.arange(C), i]
    best = np.where(np.isfinite(peak), z[0, i], np.nan)
    return best, np.where(np.isfinite(peak), peak, np.nan)


def roof_plane(
    xy: np.ndarray, z: np.ndarray, tol: float, rounds: int = 3
) -> np.ndarray:
    """(C,) bool: the cells on the plane that holds the most of them within
    ``tol`` (every plane through three cells of a small candidate sample,
    then refitted by least squares)."""
    C = len(z)
    if C < 3:
        return np.zeros(C, bool)
    rng = np.random.default_rng(0)
    trip = rng.integers(0, C, size=(min(200, C**3), 3))
    P = np.column_stack([xy - xy.mean(axis=0), z])
    a, b, c = P[trip[:, 0]], P[trip[:, 1]], P[trip[:, 2]]
    nrm = np.cross(b - a, c - a)
    ok = np.abs(nrm[:, 2]) > 1e-6 * np.linalg.norm(nrm, axis=1) + 1e-12
    # a roof: at most 60 deg steep
    ok &= np.abs(nrm[:, 2]) >= 0.5 * np.linalg.norm(nrm, axis=1)
    if not ok.any():
        return np.zeros(C, bool)
    nrm, a = nrm[ok], a[ok]
    # vertical distance of every cell to every plane
    dz = ((P[None, :, :2] - a[:, None, :2]) * nrm[:, None, :2]).sum(-1) / nrm[
        :, None, 2
    ]
    dz = np.abs(P[None, :, 2] - a[:, None, 2] + dz)
    inl = dz <= tol
    best = inl[inl.sum(axis=1).argmax()]
    for _ in range(rounds):
        if best.sum() < 3:
            break
        A = np.column_stack([P[best, :2], np.ones(best.sum())])
        coef, *_ = np.linalg.lstsq(A, P[best, 2], rcond=None)
        r = np.abs(np.column_stack([P[:, :2], np.ones(C)]) @ coef - P[:, 2])
        best = r <= tol
    return best


def _mad_sd(r: np.ndarray) -> float:
    """The sd of ``r`` from its median absolute deviation (normal errors)."""
    return 1.4826 * float(np.median(np.abs(r - np.median(r))))


def _sweep_heights(lo: float, hi: float, step: float) -> np.ndarray:
    return np.arange(lo, hi + 1e-9, step)


def roof_reference(
    polygons: list,
    ground_z: np.ndarray,
    eave_z: np.ndarray,
    views: list[RoofView],
    options: MissingOptions,
) -> np.ndarray:
    """The cells of up to ``ref_buildings`` mapped roofs with an eave height
    (spread over the block) swept as a candidate's are: what a roof looks
    like in these images at these poses. A list of (centres, best heights,
    peak NCC) per roof."""
    ok = np.isfinite(eave_z) & np.isfinite(ground_z)
    ok &= np.array([p.area >= options.min_area_m2 for p in polygons], bool)
    idx = np.flatnonzero(ok)
    if len(idx) > options.ref_buildings:
        idx = idx[np.linspace(0, len(idx) - 1, options.ref_buildings).astype(int)]
    peaks = []
    for b in idx:
        inner = polygons[b].buffer(-1.0)
        if inner.is_empty:
            continue
        cen, offsets = cell_grid(inner, options)
        if len(cen) == 0:
            continue
        c = np.array(inner.centroid.coords[0])
        sees = views_seeing(views, np.r_[c, eave_z[b]][None])[:, 0]
        if sees.sum() < options.min_views:
            continue
        z = _sweep_heights(ground_z[b] - 1.0, eave_z[b] + 8.0, options.sweep_step_m)
        best, peak = roof_cells(
            [views[i] for i in np.flatnonzero(sees)], cen, offsets, z, options.min_views
        )
        peaks.append((cen, best, peak))
    return peaks


def reference_thresholds(
    roofs: list, options: MissingOptions
) -> tuple[float, float, int]:
    """From the mapped roofs' cells (:func:`roof_reference`): the agreement
    a roof cell reaches (the ``ref_quantile`` of their peak NCC) and the
    height noise of a cell about its roof's plane (the MAD of the residuals
    of the agreeing cells on each roof's plane, pooled; the plane found
    with twice the sweep's step); and the number of cells measured."""
    if not roofs:
        return 0.0, options.sweep_step_m, 0
    pk = np.concatenate([p[np.isfinite(p)] for _, _, p in roofs])
    ncc_min = float(np.quantile(pk, options.ref_quantile)) if len(pk) else 0.0
    res = []
    for cen, best, peak in roofs:
        k = np.flatnonzero(np.isfinite(best) & (peak >= ncc_min))
        if len(k) < 6:
            continue
        on = roof_plane(cen[k], best[k], 2 * options.sweep_step_m)
        if on.sum() < 6:
            continue
        A = np.column_stack([cen[k][on], np.ones(on.sum())])
        coef, *_ = np.linalg.lstsq(A, best[k][on], rcond=None)
        res.append(best[k][on] - A @ coef)
    if not res:
        return ncc_min, options.sweep_step_m, len(pk)
    return ncc_min, _mad_sd(np.concatenate(res)), len(pk)


def find_missing(
    c,
    terrain,
    heights,
    views: list[RoofView],
    options: MissingOptions,
    num_workers: int = 0,
) -> tuple[dict, dict]:
    """Buildings the images show where the map has none.

    Parameters
    ----------
    c : :class:`~.constraints.ModelConstraints`; terrain : (M, 2) -> (M,)
        the terrain heights (model frame); heights : the mapped buildings'
        :class:`~.buildings.BuildingHeights`; views : blurred images.

    Returns
    -------
    The GeoJSON layer (absolute coordinates) and a summary (counts, the
    measured noise and thresholds).
    """
    cad = c.cadastre
    xyz, err, mpp = c.other_xyz, c.other_error, c.other_m_per_px
    summary: dict = {"tie_points": len(xyz)}
    feats: list[dict] = []
    if len(xyz) and len(c.ground_xyz):
        h = xyz[:, 2] - terrain(xyz[:, :2])
        # the measured noise of a point's height above the grid
        rg = c.ground_xyz[:, 2] - terrain(c.ground_xyz[:, :2])
        s_grid = _mad_sd(rg)
        s_pt = float(np.median(np.maximum(err, 0.0) * mpp))
        sigma = float(np.hypot(s_grid, s_pt))
        min_h = options.min_height_m + options.sigmas * sigma
        mapped = shapely.union_all(
            shapely.buffer(np.asarray(cad.polygons, dtype=object), options.map_margin_m)
        )
        outside = ~shapely.contains_xy(mapped, xyz[:, 0], xyz[:, 1])
        groups = elevated_clusters(xyz, h, outside, min_h, options)
        ref = roof_reference(
            cad.polygons, heights.ground_z, heights.eave_z, views, options
        )
        ncc_min, s_cell, n_ref = reference_thresholds(ref, options)
        tol = max(options.plane_sigmas * s_cell, options.sweep_step_m)
        summary.update(
            height_sigma_m=round(sigma, 3),
            grid_sigma_m=round(s_grid, 3),
            point_sigma_m=round(s_pt, 3),
            min_point_height_m=round(min_h, 3),
            elevated_outside=int((outside & (h >= min_h)).sum()),
            candidates=len(groups),
            roof_cells_measured=n_ref,
            min_cell_ncc=round(ncc_min, 3),
            roof_cell_sigma_m=round(s_cell, 3),
            plane_tol_m=round(tol, 3),
        )
        feats = _judge(groups, xyz, h, terrain, mapped, views, ncc_min, tol, options)
        if options.walls and all(v.path is not None for v in views):
            _walls(feats, views, options, num_workers)
    for f in feats:
        f.pop("_walls", None)
    o = c.georef.origin
    out = []
    for f in feats:
        geom = shapely.affinity.translate(f.pop("polygon"), o[0], o[1])
        out.append(
            {
                "type": "Feature",
                "properties": f,
                "geometry": shapely.geometry.mapping(geom),
            }
        )
    summary["reported"] = sum(f["properties"]["reported"] for f in out)
    doc: dict = {"type": "FeatureCollection"}
    if cad.crs:
        doc["crs"] = {"type": "name", "properties": {"name": cad.crs}}
    doc["features"] = out
    logger.info(
        "missing from the map: %d of %d candidates reported",
        summary["reported"],
        summary.get("candidates", 0),
    )
    return doc, summary


def _cells_polygon(cen: np.ndarray, cell: float):
    sq = shapely.box(-cell / 2, -cell / 2, cell / 2, cell / 2)
    return shapely.union_all([shapely.affinity.translate(sq, x, y) for x, y in cen])


def _roof_region(patch, terrain, views, sees, top, ncc_min, tol, options):
    """Sweep the patch's cells; the roof plane's cells (a dict of arrays)."""
    cen, offsets = cell_grid(patch, options)
    if len(cen) < 3:
        return None
    gz = terrain(cen)
    z = _sweep_heights(float(gz.min()) - 1.0, top + 4.0, options.sweep_step_m)
    best, peak = roof_cells(
        [views[i] for i in np.flatnonzero(sees)], cen, offsets, z, options.min_views
    )
    agree = np.isfinite(best) & (peak >= ncc_min)
    up = agree & (best - gz >= options.min_height_m)
    k = np.flatnonzero(up)
    on = np.zeros(len(cen), bool)
    on[k] = roof_plane(cen[k], best[k], tol)
    return dict(cen=cen, gz=gz, best=best, peak=peak, agree=agree, up=up, on=on)


def _judge(groups, xyz, h, terrain, mapped, views, ncc_min, tol, options) -> list[dict]:
    """One feature (dict with its ``polygon``, model frame) per candidate
    not already inside a reported one. The patch grows (by ``patch_m``)
    while the roof plane's cells reach its edge, up to ``max_grow`` times."""
    feats: list[dict] = []
    taken = shapely.Polygon()
    cell_area = options.cell_m**2
    for g in groups:
        pts = xyz[g]
        if shapely.contains_xy(taken, pts[:, 0], pts[:, 1]).mean() > 0.5:
            continue
        hull = shapely.MultiPoint(pts[:, :2]).convex_hull
        centre = np.r_[np.asarray(hull.centroid.coords[0]), np.median(pts[:, 2])]
        sees = views_seeing(views, np.asarray(centre)[None])[:, 0]
        props = {
            "score": 0.0,
            "reported": False,
            "height_above_ground_m": None,
            "tie_points": int(len(g)),
            "views": int(sees.sum()),
            "cells": 0,
            "agreeing_cells": 0,
            "roof_cells": 0,
            "roof_area_m2": 0.0,
            "roof_plane_fraction": 0.0,
            "roof_ncc": None,
            "corner_views": 0,
            "walls_seen": 0,
            "walls_chance": None,
            "walls_confirmed": False,
        }
        poly = hull.buffer(options.cell_m / 2)
        r = None
        if sees.sum() >= options.min_views:
            patch = hull.buffer(options.patch_m).difference(mapped)
            top = float(pts[:, 2].max())
            for _ in range(options.max_grow + 1):
                r = _roof_region(
                    patch, terrain, views, sees, top, ncc_min, tol, options
                )
                if r is None or not r["on"].any():
                    break
                region = _cells_polygon(r["cen"][r["on"]], options.cell_m)
                grown = region.buffer(options.patch_m).difference(mapped)
                if grown.difference(patch).area < cell_area:
                    break
                patch = patch.union(grown)
                top = max(top, float(r["best"][r["on"]].max()))
        if r is not None:
            on, up = r["on"], r["up"]
            n_on = int(on.sum())
            frac = n_on / max(int(up.sum()), 1)
            area = n_on * cell_area
            props.update(
                cells=int(len(on)),
                agreeing_cells=int(r["agree"].sum()),
                roof_cells=n_on,
                roof_area_m2=round(area, 1),
                roof_plane_fraction=round(frac, 3),
            )
            if n_on:
                gz, best = r["gz"], r["best"]
                hag = float(np.median(best[on] - gz[on]))
                props["height_above_ground_m"] = round(hag, 2)
                props["roof_ncc"] = round(float(np.median(r["peak"][on])), 3)
                poly = _cells_polygon(
                    r["cen"][on], options.cell_m
                ).minimum_rotated_rectangle
                props["score"] = round(
                    frac * min(1.0, area / (2 * options.min_area_m2)), 3
                )
            roof = area >= options.min_area_m2 and frac >= options.min_plane_fraction
            if roof:  # what the walls' test needs (:func:`_walls`)
                g0 = float(np.min(r["gz"][on]))
                g1 = g0 + float(props["height_above_ground_m"])
                props["_walls"] = (np.flatnonzero(sees), g0, g1)
            props["reported"] = bool(roof)
        if props["reported"]:
            taken = taken.union(poly)
        props["polygon"] = poly
        feats.append(props)
    return feats


def _edge_map(task: tuple) -> np.ndarray:
    """One image's distance (px) to its vertical segments, full resolution
    (:func:`.support.vertical_edge_distance`); task = (path, camera, pose)."""
    from obliq_colmap.images import read_image
    from obliq_colmap.products.discrepancy_options import DiscrepancyOptions
    from obliq_colmap.products.support import vertical_edge_distance

    path, camera, pose = task
    gray, _ = read_image(path)
    return vertical_edge_distance(gray, camera, pose, DiscrepancyOptions())


def _walls(
    feats: list[dict], views: list[RoofView], options: MissingOptions, workers: int
) -> None:
    """The walls' test of every reported roof (:func:`wall_evidence` at its
    rectangle and, for chance, at the rectangle grown by ``wall_null_m``),
    the edge maps of the views that see one made in worker processes; then
    :func:`_walls_verdict`."""
    from obliq_colmap.parallel import WorkerPool, available_cores

    todo = [f for f in feats if "_walls" in f]
    need = sorted({int(i) for f in todo for i in f["_walls"][0]})
    if not need:
        return
    tasks = [(views[i].path, views[i].camera, views[i].pose) for i in need]
    n = min(workers or available_cores(), len(tasks))
    with WorkerPool(n) as pool:
        maps = dict(zip(need, pool.map(_edge_map, tasks, "walls"), strict=True))
    for f in todo:
        vi, g0, g1 = f.pop("_walls")
        dm = [maps[int(i)] for i in vi]
        vs = [views[i] for i in vi]
        rect = f["polygon"]
        f["corner_views"], f["walls_seen"] = wall_evidence(
            rect, g0, g1, dm, vs, options
        )
        away = shapely.buffer(rect, options.wall_null_m, join_style="mitre")
        f["_null"] = wall_evidence(away, g0, g1, dm, vs, options)
    _walls_verdict(feats, options)


def _walls_verdict(feats: list[dict], options: MissingOptions) -> None:
    """Are a reported roof's walls seen more often than chance? The chance
    of a corner view being seen is measured on the same candidates'
    rectangles grown by ``wall_null_m`` (corners on the ground around them,
    where no wall stands), pooled over the block; a roof whose count has a
    binomial tail below ``wall_alpha`` under that rate has its walls
    confirmed. The score: half for the roof, half for the walls (one minus
    that tail)."""
    nulls = [f.pop("_null") for f in feats if "_null" in f]
    n0 = sum(n for n, _ in nulls)
    k0 = sum(k for _, k in nulls)
    p0 = (k0 + 1) / (n0 + 2)  # never 0 with few measurements
    for f in feats:
        if not f["reported"]:
            continue
        n, k = f["corner_views"], f["walls_seen"]
        tail = float(binom.sf(k - 1, n, p0)) if n else 1.0
        f["walls_chance"] = round(tail, 4)
        f["walls_confirmed"] = tail < options.wall_alpha
        f["score"] = round(f["score"] * (1.0 - 0.5 * tail), 3)


def wall_evidence(
    rect,
    ground_z: float,
    roof_z: float,
    dmaps: list[np.ndarray],
    views: list[RoofView],
    options: MissingOptions,
    support_px: float = 1.5,
) -> tuple[int, int]:
    """The candidate's walls in the images: per view that sees a corner of
    ``rect`` (one of its walls facing the camera), is a vertical edge seen
    along the corner's vertical (half of ``wall_samples`` heights between
    1 m above the ground and 0.5 m below the roof within ``support_px`` of
    a segment through the vertical VP) at its best place within
    ``wall_search_m`` (the rectangle is known to about a cell)?

    Returns (corner views, corner views seen).
    """
    xy = np.asarray(rect.exterior.coords)[:-1]
    if len(xy) < 3 or roof_z - ground_z < 2.0:
        return 0, 0
    if not shapely.Polygon(xy).exterior.is_ccw:
        xy = xy[::-1]
    e = np.roll(xy, -1, axis=0) - xy  # edge k from corner k to k + 1
    nrm = np.column_stack([e[:, 1], -e[:, 0]])  # outward for a ccw ring
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-12
    walls = np.stack([nrm, np.roll(nrm, 1, axis=0)], axis=1)  # (C, 2, 2)
    m = options.wall_samples
    z = ground_z + 1.0 + (np.arange(m) + 0.5) / m * (roof_z - 0.5 - ground_z - 1.0)
    k = np.arange(-options.wall_search_m, options.wall_search_m + 1e-9, 0.25)
    S = np.stack(np.meshgrid(k, k), -1).reshape(-1, 2)
    C = len(xy)
    P = np.empty((C, len(S), m, 3))
    P[..., :2] = xy[:, None, None] + S[None, :, None]
    P[..., 2] = z[None, None]
    total = seen = 0
    for v, dmap in zip(views, dmaps, strict=True):
        c = v.pose.center
        facing = ((c[None, None, :2] - xy[:, None]) * walls).sum(-1).max(axis=1) > 0
        Xc = v.pose.transform(P.reshape(-1, 3))
        q = v.camera.img_from_cam(Xc)
        H, W = dmap.shape
        col = np.floor(q[:, 0]).astype(int)
        row = np.floor(q[:, 1]).astype(int)
        ok = (Xc[:, 2] > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        d = np.full(len(q), np.inf, np.float32)
        d[ok] = dmap[row[ok], col[ok]]
        inside = ok.reshape(C, len(S), m).all(axis=2)[:, len(S) // 2]
        sup = (d <= support_px).reshape(C, len(S), m).mean(axis=2).max(axis=1)
        use = facing & inside
        total += int(use.sum())
        seen += int((use & (sup >= 0.5)).sum())
    return total, seen
