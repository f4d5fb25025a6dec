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
* With the images (:func:`eaves_with_roof`), the roof tells two more cases
  (the height at which the views agree on the footprint's interior,
  :func:`.roof.roof_height`). A building whose tracks give no such height
  (a low house's walls yield one or two tracks) takes the same rule over
  its tracks on any wall, one track enough, among those no higher than its
  roof: an eave cannot lie above the roof, and that cap is what removes the
  taller buildings' edges seen behind; nor lower below it than a pitched
  roof over the footprint could rise. A building whose roof lies higher
  above its eave than that, with its walls' tracks up to its top storey
  (or to the top of the facade search, 60 m above the ground), is a tower
  read at its podium's line (which runs round the most walls): its eave is
  its flat roof. ``eave_support`` says which rule gave the eave (2: the
  walls, 1: under the roof, 3: the roof).
  Buildings without a height get none (NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from obliq_colmap.cadastre import Cadastre

__all__ = [
    "BuildingHeights",
    "HeightOptions",
    "building_heights",
    "eave_cluster",
    "eaves_with_roof",
    "half_widths",
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
    #: the roof sweep's heights above the ground (m): up to a tower's top,
    #: in steps of about a pixel of parallax at 45 deg and 0.15 m/px.
    roof_sweep_max_m: float = 120.0
    roof_sweep_step_m: float = 0.5
    #: the steepest pitched roof: the views agree on it at most half the
    #: footprint's short side times tan(this) above its eave.
    max_roof_pitch_deg: float = 60.0
    #: a storey (m): a tower's highest facade line lies within one of its
    #: roof (the rim, the top floor), or of the top of the facade search.
    storey_m: float = 4.0
    #: the top of ``register``'s facade search above the ground (m) where
    #: the model's report does not say (``register``'s default).
    facade_top_m: float = 60.0

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


def eaves_with_roof(
    heights: BuildingHeights,
    roof_above_ground: np.ndarray,
    half_width: np.ndarray,
    facade_xyz: np.ndarray,
    facade_building: np.ndarray,
    facade_edge: np.ndarray,
    options: HeightOptions,
    facade_top_m: float | None = None,
) -> BuildingHeights:
    """``heights`` told by the roof the views agree on (``roof_above_ground``
    (B,), NaN where the sweep saw none):

    * a building without an eave takes one from its tracks at most
      ``roof_margin_m`` above its roof and no lower below it than a pitched
      roof over its footprint can rise (``half_width`` (B,), half its short
      side, times tan ``max_roof_pitch_deg``), one track on one wall enough
      (support 1): a lower line is a floor's, a shop front's;
    * a building whose roof lies higher above its eave than that rise and
      whose walls show at least ``min_tracks`` tracks above that eave within
      ``storey_m`` below the roof or below ``facade_top_m`` (the top of the
      facade search, m above the ground) is a tower read at a lower line (a
      podium, a floor): its eave is its flat roof (support 3). A chance
      agreement of the views high above a building has no facade lines up
      there. The same where the eave found is the search's last storey: its
      top cut the walls.

    Other arrays as in :func:`building_heights`."""
    B = len(heights.eave_z)
    g = heights.ground_z
    eave, count = heights.eave_z.copy(), heights.eave_tracks.copy()
    support = np.where(np.isfinite(eave), 2, 0)
    ntr, tracks = _tracks_by_building(facade_xyz, facade_building, facade_edge, B)
    seen = (ntr > 0) & np.isfinite(roof_above_ground)
    top = g + roof_above_ground + options.roof_margin_m
    rise = half_width * np.tan(np.radians(options.max_roof_pitch_deg))
    bottom = top - rise - 2 * options.roof_margin_m
    for b in np.flatnonzero(seen & ~np.isfinite(eave)):
        z, walls = tracks(b)
        under = (z <= top[b]) & (z >= bottom[b])
        if under.any():
            eave[b], count[b] = eave_cluster(
                z[under],
                options.cluster_tol_m,
                1,
                g[b] + options.min_height_m,
                walls[under],
                1,
            )
            support[b] = int(np.isfinite(eave[b]))
    searched = options.facade_top_m if facade_top_m is None else facade_top_m
    high = seen & (g + roof_above_ground - eave > rise + options.roof_margin_m)
    for b in np.flatnonzero(high & (support == 2)):
        z, _ = tracks(b)
        reach = g[b] + min(roof_above_ground[b], searched) - options.storey_m
        # the line taken for the eave may be the search's last (its top cut
        # the walls), or the tower's lines rise above it to its top storey
        # (its rim seen twice: a stray track up there is no tower)
        cut = eave[b] >= g[b] + searched - options.storey_m
        up_there = (z > eave[b] + 2 * options.cluster_tol_m) & (z >= reach)
        rises = (up_there & (z <= top[b])).sum() >= options.min_tracks
        if cut or rises:
            eave[b], count[b], support[b] = g[b] + roof_above_ground[b], 0, 3
    return BuildingHeights(g, eave, ntr, count, support)


def half_widths(polygons: list) -> np.ndarray:
    """(B,) half the short side of each footprint's minimum rotated
    rectangle (m): the run of a pitched roof from its eave to its ridge."""
    rect = shapely.minimum_rotated_rectangle(np.asarray(polygons, dtype=object))
    out = np.zeros(len(polygons))
    for b, r in enumerate(rect):
        xy = np.asarray(r.exterior.coords)[:3] if r.geom_type == "Polygon" else None
        if xy is not None:
            out[b] = 0.5 * min(np.hypot(*(xy[1] - xy[0])), np.hypot(*(xy[2] - xy[1])))
    return out


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
