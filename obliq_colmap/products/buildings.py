"""Ground and eave height per mapped footprint.

* Ground height: the lowest terrain height (:mod:`.terrain`) at the
  footprint's vertices, as a building's base is where it meets the ground
  on its downhill side.
* Eave height: the height where the building's walls meet its roof (a flat
  roof's rim, a pitched roof's eave). It runs round the building, so it is
  the height that the most walls share: of the heights that at least
  ``min_tracks`` of the building's tracks share within ``cluster_tol_m``, on
  at least ``min_walls`` walls and ``min_height_m`` above the ground (lower
  ones are the wall's foot), those on the most walls, and of them the
  highest (floor lines run round a building too, below its eave). Edges of
  a taller building seen behind show on the walls facing it only; in dense
  blocks they outnumber the eave's tracks there and lie far above it.
* With the images (:func:`eaves_under_roof`): a building whose tracks give
  no such height (a low house's walls yield one or two tracks) takes the
  same rule over its tracks on any wall, one track enough, among those no
  higher than its roof (the height at which the views agree on its
  interior, :func:`.roof.roof_height`): an eave cannot lie above the roof,
  and that cap is what removes the taller buildings' edges seen behind.
  Its ``eave_support`` says so (1 instead of 2).
  Buildings without a height get none (NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from obliq_colmap.cadastre import Cadastre

__all__ = [
    "BuildingHeights",
    "HeightOptions",
    "building_heights",
    "eave_cluster",
    "eaves_under_roof",
]


@dataclass
class HeightOptions:
    """Options of :func:`building_heights`."""

    #: tracks within this height of each other count as one edge (m): twice
    #: the track heights' spread across a building's walls (~0.2 m).
    cluster_tol_m: float = 0.5
    #: tracks a height needs to be an eave (2: one wall seen from two sides
    #: or two walls; a single track may be another building's edge).
    min_tracks: int = 2
    #: walls (map edges) among those tracks: a building's eave runs round
    #: it, while a taller building seen behind one wall shows on that wall
    #: (and the eave is taken from the heights on the most walls).
    min_walls: int = 2
    #: an eave lower than this above the ground is a wall's foot (m).
    min_height_m: float = 2.0
    #: :func:`eaves_under_roof`: a track counts up to this above the roof
    #: the sweep sees (m): a flat roof's parapet (up to ~1 m) rises above
    #: the roof surface the views agree on.
    roof_margin_m: float = 1.0
    #: the roof sweep's heights above the ground (m): up to a tower's top.
    roof_sweep_max_m: float = 80.0
    roof_sweep_step_m: float = 0.25

    def __post_init__(self) -> None:
        if self.cluster_tol_m <= 0 or self.min_tracks < 1 or self.min_height_m < 0:
            raise ValueError("cluster_tol_m > 0, min_tracks >= 1, min_height_m >= 0")


@dataclass
class BuildingHeights:
    """Per cadastre building (polygon) b, LOCAL heights (m).

    ground_z, eave_z : (B,) NaN where unknown. num_tracks : (B,) int, the
    building's facade tracks. eave_tracks : (B,) int, those at its eave.
    eave_support : (B,) int, the rule that gave the eave: 2 shared by the
    walls, 1 under the roof (:func:`eaves_under_roof`), 0 none.
    """

    ground_z: np.ndarray
    eave_z: np.ndarray
    num_tracks: np.ndarray
    eave_tracks: np.ndarray
    eave_support: np.ndarray

    @property
    def eave_height(self) -> np.ndarray:
        """(B,) eave height above the ground (m)."""
        return self.eave_z - self.ground_z


def eave_cluster(
    z: np.ndarray,
    tol: float,
    min_count: int,
    floor: float,
    walls: np.ndarray | None = None,
    min_walls: int = 1,
):
    """The eave among the track heights ``z`` (N,) on ``walls`` (N,): of the
    values above ``floor`` that at least ``min_count`` values on at least
    ``min_walls`` distinct walls share within ``tol``, the highest of those
    on the most walls. Returns (height, count): the median of the values
    within ``tol`` of it and their number, or (NaN, 0)."""
    walls = np.zeros(len(z), int) if walls is None else np.asarray(walls)
    keep = z >= floor
    z, walls = z[keep], walls[keep]
    if len(z) == 0:
        return np.nan, 0
    near = np.abs(z[:, None] - z[None, :]) <= tol  # (N, N): a few tracks each
    # distinct walls among the values within tol of each: (N, W) counts > 0
    _, w = np.unique(walls, return_inverse=True)
    n_walls = ((near.astype(int) @ np.eye(w.max() + 1, dtype=int)[w]) > 0).sum(1)
    ok = (near.sum(axis=1) >= min_count) & (n_walls >= min_walls)
    if not ok.any():
        return np.nan, 0
    cand = np.flatnonzero(ok & (n_walls == n_walls[ok].max()))
    i = cand[np.argmax(z[cand])]
    return float(np.median(z[near[i]])), int(near[i].sum())


def building_heights(
    cadastre: Cadastre,
    terrain,
    facade_xyz: np.ndarray,
    facade_building: np.ndarray,
    facade_edge: np.ndarray,
    options: HeightOptions,
) -> BuildingHeights:
    """Ground and eave height of every building of the map.

    Parameters
    ----------
    terrain : function (M, 2) -> (M,) local heights (:func:`estimate_terrain`).
    facade_xyz : (F, 3) facade track points; facade_building : (P, 2)
        (facade point, building) pairs; facade_edge : (P,) their walls.
    """
    B = len(cadastre.polygons)
    zc = terrain(cadastre.corner_xy)
    ground = np.full(B, np.inf)
    np.minimum.at(ground, cadastre.corner_building, zc)
    ground[~np.isfinite(ground)] = np.nan
    eave = np.full(B, np.nan)
    count = np.zeros(B, int)
    ntr, tracks = _tracks_by_building(facade_xyz, facade_building, facade_edge, B)
    for b in np.flatnonzero(ntr):  # per building: a handful of tracks each
        z, walls = tracks(b)
        eave[b], count[b] = eave_cluster(
            z,
            options.cluster_tol_m,
            options.min_tracks,
            ground[b] + options.min_height_m,
            walls,
            options.min_walls,
        )
    support = np.where(np.isfinite(eave), 2, 0)
    return BuildingHeights(ground, eave, ntr, count, support)


def eaves_under_roof(
    heights: BuildingHeights,
    roof_above_ground: np.ndarray,
    facade_xyz: np.ndarray,
    facade_building: np.ndarray,
    facade_edge: np.ndarray,
    options: HeightOptions,
) -> BuildingHeights:
    """``heights`` with an eave for the buildings that had none, from their
    tracks at most ``roof_margin_m`` above their roof (``roof_above_ground``
    (B,), NaN where the sweep saw none), one track on one wall enough.
    Arrays as in :func:`building_heights`."""
    B = len(heights.eave_z)
    eave, count = heights.eave_z.copy(), heights.eave_tracks.copy()
    ntr, tracks = _tracks_by_building(facade_xyz, facade_building, facade_edge, B)
    ask = (ntr > 0) & ~np.isfinite(eave) & np.isfinite(roof_above_ground)
    for b in np.flatnonzero(ask):
        z, walls = tracks(b)
        top = heights.ground_z[b] + roof_above_ground[b] + options.roof_margin_m
        under = z <= top
        if under.any():
            eave[b], count[b] = eave_cluster(
                z[under],
                options.cluster_tol_m,
                1,
                heights.ground_z[b] + options.min_height_m,
                walls[under],
                1,
            )
    support = np.where(
        np.isfinite(heights.eave_z), 2, np.where(np.isfinite(eave), 1, 0)
    )
    return BuildingHeights(heights.ground_z, eave, ntr, count, support)


def _tracks_by_building(
    facade_xyz: np.ndarray,
    facade_building: np.ndarray,
    facade_edge: np.ndarray,
    B: int,
):
    """((B,) int tracks per building, b -> (heights (n,), walls (n,)))."""
    ntr = (
        np.bincount(facade_building[:, 1], minlength=B)
        if len(facade_building)
        else np.zeros(B, int)
    )
    order = np.argsort(facade_building[:, 1], kind="stable")
    fb, fe = facade_building[order], facade_edge[order]
    starts = np.searchsorted(fb[:, 1], np.arange(B + 1))

    def tracks(b: int) -> tuple[np.ndarray, np.ndarray]:
        rows = slice(starts[b], starts[b + 1])
        return facade_xyz[fb[rows, 0], 2], fe[rows]

    return ntr, tracks
