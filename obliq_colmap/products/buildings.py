"""Ground and eave height per mapped footprint.

* Ground height: the lowest terrain height (:mod:`.terrain`) at the
  footprint's vertices, as a building's base is where it meets the ground
  on its downhill side.
* Eave height: the height of the highest facade constraint below the roof
  rim. The highest horizontal edge a wall shows is where it meets its roof
  (a flat roof's rim, a pitched roof's eave); tracks above it on the same
  wall are edges of other buildings seen behind it, matched across images
  but single (no other track of the building at that height), so the eave
  is the highest height that at least ``min_tracks`` of the building's
  tracks share within ``cluster_tol_m``, at least ``min_height_m`` above
  the ground (lower clusters are the wall's foot). Buildings without such a
  cluster get no eave height (NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from obliq_colmap.cadastre import Cadastre

__all__ = ["BuildingHeights", "HeightOptions", "building_heights", "highest_cluster"]


@dataclass
class HeightOptions:
    """Options of :func:`building_heights`."""

    #: tracks within this height of each other count as one edge (m): twice
    #: the track heights' spread across a building's walls (~0.2 m).
    cluster_tol_m: float = 0.5
    #: tracks a height needs to be an eave (2: one wall seen from two sides
    #: or two walls; a single track may be another building's edge).
    min_tracks: int = 2
    #: an eave lower than this above the ground is a wall's foot (m).
    min_height_m: float = 2.0

    def __post_init__(self) -> None:
        if self.cluster_tol_m <= 0 or self.min_tracks < 1 or self.min_height_m < 0:
            raise ValueError("cluster_tol_m > 0, min_tracks >= 1, min_height_m >= 0")


@dataclass
class BuildingHeights:
    """Per cadastre building (polygon) b, LOCAL heights (m).

    ground_z, eave_z : (B,) NaN where unknown. num_tracks : (B,) int, the
    building's facade tracks. eave_tracks : (B,) int, those at its eave.
    """

    ground_z: np.ndarray
    eave_z: np.ndarray
    num_tracks: np.ndarray
    eave_tracks: np.ndarray

    @property
    def eave_height(self) -> np.ndarray:
        """(B,) eave height above the ground (m)."""
        return self.eave_z - self.ground_z


def highest_cluster(z: np.ndarray, tol: float, min_count: int, floor: float):
    """The highest value of ``z`` (N,) above ``floor`` that at least
    ``min_count`` values share within ``tol``: (height, count), or (NaN, 0).
    The height is the median of those values."""
    z = np.sort(z[z >= floor])
    if len(z) == 0:
        return np.nan, 0
    n = (np.abs(z[:, None] - z[None, :]) <= tol).sum(axis=1)
    ok = np.flatnonzero(n >= min_count)
    if len(ok) == 0:
        return np.nan, 0
    top = z[ok[-1]]
    members = z[np.abs(z - top) <= tol]
    return float(np.median(members)), int(len(members))


def building_heights(
    cadastre: Cadastre,
    terrain,
    facade_xyz: np.ndarray,
    facade_building: np.ndarray,
    options: HeightOptions,
) -> BuildingHeights:
    """Ground and eave height of every building of the map.

    Parameters
    ----------
    terrain : function (M, 2) -> (M,) local heights (:func:`estimate_terrain`).
    facade_xyz : (F, 3) facade track points; facade_building : (P, 2)
        (facade point, building) pairs.
    """
    B = len(cadastre.polygons)
    zc = terrain(cadastre.corner_xy)
    ground = np.full(B, np.inf)
    np.minimum.at(ground, cadastre.corner_building, zc)
    ground[~np.isfinite(ground)] = np.nan
    eave = np.full(B, np.nan)
    count = np.zeros(B, int)
    ntr = (
        np.bincount(facade_building[:, 1], minlength=B)
        if len(facade_building)
        else np.zeros(B, int)
    )
    order = np.argsort(facade_building[:, 1], kind="stable")
    fb = facade_building[order]
    starts = np.searchsorted(fb[:, 1], np.arange(B + 1))
    for b in np.flatnonzero(ntr):  # per building: a handful of tracks each
        z = facade_xyz[fb[starts[b] : starts[b + 1], 0], 2]
        eave[b], count[b] = highest_cluster(
            z,
            options.cluster_tol_m,
            options.min_tracks,
            ground[b] + options.min_height_m,
        )
    return BuildingHeights(ground, eave, ntr, count)
