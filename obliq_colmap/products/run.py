"""``make_products``: terrain grid, building heights, LoD1 model and map
discrepancies from one registration, written atomically into one folder.

Files (absolute coordinates in the map's CRS; heights in the result model's
vertical datum, i.e. the priors', as ``georef.json`` says):

* ``terrain.asc`` + ``terrain.prj``: ESRI ASCII grid of the terrain height
  (with ``image_path``, shaped by the open ground the views agree on).
* ``buildings.geojson``: one feature per map polygon with ``ground_height``,
  ``eave_z`` (absolute), ``eave_height`` (above the ground, m) and
  ``eave_support`` (``walls``: shared by the walls; with the images,
  ``under_roof``: from the tracks under the roof the views see, ``roof``: a
  tower's flat roof; null).
* ``lod1.city.json``: CityJSON 2.0, the footprints with an eave height
  extruded from the ground to the eave.
* ``discrepancies.geojson`` (with ``image_path``): the footprints the images
  contradict, with a score (:mod:`.discrepancies`).
* ``missing.geojson`` (with ``image_path``): buildings the images show where
  the map has none, found from the tie points and told from trees by their
  roofs and walls (:mod:`.missing`).
* ``products.json``: what was made, the datum, counts and options.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from obliq_colmap.colmap_io import read_model
from obliq_colmap.files import AtomicFolder
from obliq_colmap.products.buildings import (
    BuildingHeights,
    HeightOptions,
    building_heights,
    eaves_with_roof,
    half_widths,
)
from obliq_colmap.products.cityjson import city_model
from obliq_colmap.products.constraints import ModelConstraints, load_constraints
from obliq_colmap.products.discrepancies import (
    DiscrepancyOptions,
    find_discrepancies,
    roof_views,
)
from obliq_colmap.products.esri import ascii_grid_text, esri_wkt
from obliq_colmap.products.ground import GroundOptions, ground_samples
from obliq_colmap.products.missing import MissingOptions, find_missing
from obliq_colmap.products.roof import RoofView, roof_heights
from obliq_colmap.products.terrain import TerrainOptions, estimate_terrain, terrain_grid

__all__ = ["ProductsOptions", "make_products"]

logger = logging.getLogger(__name__)


@dataclass
class ProductsOptions:
    """Options of :func:`make_products`."""

    terrain: TerrainOptions = field(default_factory=TerrainOptions)
    ground: GroundOptions = field(default_factory=GroundOptions)
    heights: HeightOptions = field(default_factory=HeightOptions)
    discrepancies: DiscrepancyOptions = field(default_factory=DiscrepancyOptions)
    missing: MissingOptions = field(default_factory=MissingOptions)
    #: search the buildings missing from the map (with the images).
    find_missing: bool = True
    #: worker processes for the discrepancy search (0: all cores).
    num_workers: int = 0


def _crs_member(crs: str | None) -> dict | None:
    return {"type": "name", "properties": {"name": crs}} if crs else None


def _num(v: float, decimals: int = 3) -> float | None:
    return round(float(v), decimals) if np.isfinite(v) else None


_SUPPORT = {0: None, 1: "under_roof", 2: "walls", 3: "roof"}


def buildings_geojson(c: ModelConstraints, h: BuildingHeights) -> dict:
    """The footprints (absolute) with their heights, one feature per polygon."""
    o = c.georef.origin
    feats = []
    for b, poly in enumerate(c.cadastre.polygons):
        geom = shapely.affinity.translate(poly, o[0], o[1])
        props = {
            "id": str(c.cadastre.building_ids[b]),
            "feature_index": int(c.cadastre.feature_index[b]),
            "ground_height": _num(h.ground_z[b] + o[2]),
            "eave_z": _num(h.eave_z[b] + o[2]),
            "eave_height": _num(h.eave_height[b]),
            "num_facade_tracks": int(h.num_tracks[b]),
            "eave_tracks": int(h.eave_tracks[b]),
            "eave_support": _SUPPORT[int(h.eave_support[b])],
        }
        feats.append(
            {
                "type": "Feature",
                "properties": props,
                "geometry": shapely.geometry.mapping(geom),
            }
        )
    doc: dict[str, Any] = {"type": "FeatureCollection"}
    if c.cadastre.crs:
        doc["crs"] = _crs_member(c.cadastre.crs)
    doc["features"] = feats
    return doc


def lod1_model(c: ModelConstraints, h: BuildingHeights) -> dict:
    o = c.georef.origin
    polys = [shapely.affinity.translate(p, o[0], o[1]) for p in c.cadastre.polygons]
    ids = [f"{bid}-{b}" for b, bid in enumerate(c.cadastre.building_ids)]
    attrs = [
        {
            "mapId": str(bid),
            "measuredHeight": _num(h.eave_height[b]),
            "eaveSupport": _SUPPORT[int(h.eave_support[b])],
        }
        for b, bid in enumerate(c.cadastre.building_ids)
    ]
    return city_model(
        polys, ids, h.ground_z + o[2], h.eave_z + o[2], attrs, c.cadastre.crs
    )


def with_roof(
    c: ModelConstraints,
    h: BuildingHeights,
    views: list[RoofView],
    options: ProductsOptions,
) -> BuildingHeights:
    """``h`` told by the roofs the views see (:func:`.buildings.
    eaves_with_roof`), swept (:func:`.roof.roof_heights`) on the buildings
    with tracks."""
    o, d = options.heights, options.discrepancies
    up = np.arange(0.0, o.roof_sweep_max_m + 1e-9, o.roof_sweep_step_m)
    roof = roof_heights(
        c.cadastre.polygons,
        h.ground_z,
        h.num_tracks > 0,
        views,
        up,
        d,
    )
    return eaves_with_roof(
        h,
        roof,
        half_widths(c.cadastre.polygons),
        c.facade_xyz,
        c.facade_building,
        c.facade_edge,
        o,
        c.facade_top_m,
    )


def measured_terrain(
    c: ModelConstraints, views: list[RoofView] | None, options: ProductsOptions
):
    """(terrain, its NODATA samples, the number of ground points from the
    images): from the map corners, then, with the images, from the open
    ground the views agree on (:func:`.ground.ground_samples`) about it."""
    terrain, samples = estimate_terrain(c.ground_xyz, c.facade_xyz, options.terrain)
    if views is None or not options.ground.enabled:
        return terrain, samples, 0
    pts = ground_samples(
        c.cadastre.polygons,
        c.ground_xyz[:, :2],
        terrain,
        views,
        options.terrain.max_distance_m,
        options.ground,
    )
    terrain, samples = estimate_terrain(
        c.ground_xyz, c.facade_xyz, options.terrain, pts
    )
    return terrain, samples, len(pts)


def make_products(
    input_path: str | Path,
    cadastre_path: str | Path,
    output_path: str | Path,
    image_path: str | Path | None = None,
    options: ProductsOptions | None = None,
) -> dict:
    """Make every product of one registration; returns the summary written
    to ``products.json``.

    Raises
    ------
    InputError
        Unreadable model or map, a map the model was not registered to, an
        output folder that exists and is not empty.
    """
    options = options or ProductsOptions()
    out = AtomicFolder(output_path)  # checks the output folder first
    c = load_constraints(input_path, cadastre_path)
    o = c.georef.origin
    block = views = None
    if image_path is not None:
        block = read_model(input_path)
        views = roof_views(block, Path(image_path), options.discrepancies)
    terrain, samples, n_ground = measured_terrain(c, views, options)
    grid = terrain_grid(terrain, samples, options.terrain)
    h = building_heights(
        c.cadastre,
        terrain,
        c.facade_xyz,
        c.facade_building,
        c.facade_edge,
        options.heights,
    )
    wkt = esri_wkt(c.cadastre.crs)
    disc = miss = None
    if views is not None:
        disc = find_discrepancies(
            input_path,
            image_path,
            c,
            h,
            options.discrepancies,
            options.num_workers,
            block,
            views,
        )
        if options.find_missing:
            miss, miss_summary = find_missing(
                c, terrain, h, views, options.missing, options.num_workers
            )
        h = with_roof(c, h, views, options)
    summary = {
        "vertical_datum": "the result model's (georef.json): the priors' heights",
        "crs": c.cadastre.crs,
        "terrain": {
            "cell_size_m": grid.cell,
            "cells": int(grid.Z.size),
            "cells_with_height": int(np.isfinite(grid.Z).sum()),
            "corner_samples": int(len(samples)),
            "ground_points_from_images": n_ground,
        },
        "buildings": {
            "mapped": len(c.cadastre.polygons),
            "with_facade_tracks": int((h.num_tracks > 0).sum()),
            "with_eave_height": int(np.isfinite(h.eave_z).sum()),
            "with_eave_under_roof": int((h.eave_support == 1).sum()),
            "with_eave_at_a_towers_roof": int((h.eave_support == 3).sum()),
        },
        "options": dataclasses.asdict(options),
    }
    if disc is not None:
        summary["discrepancies"] = {
            "flagged": sum(f["properties"]["flagged"] for f in disc["features"]),
            "scored": len(disc["features"]),
        }
    if miss is not None:
        summary["missing"] = miss_summary
    with out as tmp:
        (tmp / "terrain.asc").write_text(
            ascii_grid_text(grid.Z + o[2], grid.x0 + o[0], grid.y0 + o[1], grid.cell)
        )
        (tmp / "terrain.prj").write_text(wkt + "\n")
        (tmp / "buildings.geojson").write_text(
            json.dumps(buildings_geojson(c, h)) + "\n"
        )
        (tmp / "lod1.city.json").write_text(
            json.dumps(lod1_model(c, h), separators=(",", ":")) + "\n"
        )
        if disc is not None:
            (tmp / "discrepancies.geojson").write_text(json.dumps(disc) + "\n")
        if miss is not None:
            (tmp / "missing.geojson").write_text(json.dumps(miss) + "\n")
        (tmp / "products.json").write_text(json.dumps(summary, indent=2) + "\n")
    logger.info(
        "products: terrain %d x %d cells of %g m, %d of %d buildings with eaves",
        grid.Z.shape[1],
        grid.Z.shape[0],
        grid.cell,
        summary["buildings"]["with_eave_height"],
        summary["buildings"]["mapped"],
    )
    return summary
