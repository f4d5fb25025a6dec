"""Facade tracks: horizontal facade edges matched across images (stage 3).

:class:`PairMatch` holds the matches of one image pair and
:class:`FacadeTracks` what :func:`~obliq_colmap.adjustment.match_facade_edges`
returns: the pairs' matches chained into tracks, one per 3D horizontal edge,
with its observations (image, row of that image's
:class:`~obliq_colmap.adjustment.FacadeEdges`), its anchor on the map edge
and its initial height. :func:`triangulate_tracks` fits each track as a
horizontal 3D line near its wall with the solved cameras (the bundle's
rounds).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = ["FacadeTracks", "PairMatch", "triangulate_tracks"]


@dataclass
class PairMatch:
    """The matches of one image pair.

    Attributes
    ----------
    a, b : int, indices of the two images (into the input sequence).
    rows_a, rows_b : (M,) int arrays, matched rows of the two FacadeEdges.
    model : (4,) array, the relative height offset ``t_a - t_b = m0 x + m1 y
        + m2 + m3 t`` (m; x, y about the candidates' centroid, t the height
        above ground).
    datum_offset : float, ``e_a - e_b`` (m) at the matches' centroid.
    num_candidates, num_trials : int.
    """

    a: int
    b: int
    rows_a: np.ndarray
    rows_b: np.ndarray
    model: np.ndarray
    datum_offset: float
    num_candidates: int
    num_trials: int

    @property
    def num_matches(self) -> int:
        return len(self.rows_a)


@dataclass
class FacadeTracks:
    """Horizontal facade edges matched across images.

    Attributes
    ----------
    image : (H,) int array, image index (into the input sequence) per
        observation.
    row : (H,) int array, row of that image's FacadeEdges.
    track : (H,) int array, track index in [0, J).
    anchor_xy : (J, 2) array, a point of the track's map edge (m, local):
        at the mean position along the edge of its observations.
    edge : (J,) int array, map edge of each track.
    height : (J,) array, initial absolute height of each track (m, the
        corrected datum: see ``datum_correction``).
    datum_correction : (I,) array, ``e_k`` per image (m): subtract from the
        camera height and the image's ground plane; NaN for images without
        matches.
    pairs : list of PairMatch.
    """

    image: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    row: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    anchor_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    edge: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    height: np.ndarray = field(default_factory=lambda: np.zeros(0))
    datum_correction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pairs: list[PairMatch] = field(default_factory=list)

    @property
    def num_tracks(self) -> int:
        return len(self.edge)

    @property
    def num_observations(self) -> int:
        return len(self.image)


def triangulate_tracks(
    image: np.ndarray,
    track: np.ndarray,
    ends_raw: np.ndarray,
    cameras: Sequence,
    poses: Sequence,
    base_xy: np.ndarray,
    normal_xy: np.ndarray,
    px_per_m: np.ndarray,
    offset_sigma_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Each track as a horizontal 3D line parallel to its map edge.

    A horizontal edge on or near a wall (a roof rim overhangs by tens of
    centimetres, a parapet or a ridge stands back) is the line
    ``base + d n + h z + s u`` (``u`` the edge direction, ``n`` its outward
    normal): two unknowns ``(d, h)`` per track. Each observation's
    back-projected plane (normal ``pi``, through the camera centre ``C``)
    contains it: ``pi . n d + pi . z h = pi . (C - base)``, linear; scaled to
    metres of height and weighted by ``px_per_m`` it is in pixels. A weak
    prior ``d ~ N(0, offset_sigma_m)`` keeps tracks seen from one direction
    (parallax too small to separate d from h) on the wall.

    Parameters
    ----------
    image, track : (H,) int arrays, image index and track of each observation.
    ends_raw : (H, 2, 2) array, the observed segments, raw pixels.
    cameras, poses : per image index its Camera and Pose.
    base_xy, normal_xy : (J, 2) arrays, track anchor on the map edge and the
        edge's outward normal.
    px_per_m : (H,) array, image scale of one metre of height (weights).

    Returns
    -------
    d, h : (J,) arrays, metres (offset along the normal, height).
    """
    J = len(base_xy)
    pi = np.zeros((len(image), 3))
    centers = np.zeros((len(image), 3))
    for k in np.unique(image):
        sel = np.flatnonzero(image == k)
        cam, pose = cameras[k], poses[k]
        uv = cam.cam_from_img(ends_raw[sel].reshape(-1, 2)).reshape(-1, 2, 2)
        a = np.concatenate([uv[:, 0], np.ones((len(sel), 1))], axis=1)
        b = np.concatenate([uv[:, 1], np.ones((len(sel), 1))], axis=1)
        pi[sel] = np.cross(a, b) @ pose.rotation  # plane normal, world frame
        centers[sel] = pose.center
    with np.errstate(divide="ignore", invalid="ignore"):
        pi = pi / pi[:, 2:3]  # per metre of height
    n3 = np.column_stack([normal_xy, np.zeros(J)])[track]
    x3 = np.column_stack([base_xy, np.zeros(J)])[track]
    a1 = np.sum(pi * n3, axis=1)
    rhs = np.sum(pi * (centers - x3), axis=1)
    w = px_per_m**2
    good = np.isfinite(a1) & np.isfinite(rhs)
    w, a1, rhs, tr = w[good], a1[good], rhs[good], track[good]
    s11 = np.bincount(tr, w * a1 * a1, J)
    s12 = np.bincount(tr, w * a1, J)
    s22 = np.bincount(tr, w, J)
    b1 = np.bincount(tr, w * a1 * rhs, J)
    b2 = np.bincount(tr, w * rhs, J)
    # prior on d in pixels: the track's mean scale over sigma
    mean_w = s22 / np.maximum(np.bincount(tr, None, J), 1)
    s11 = s11 + mean_w / offset_sigma_m**2
    det = s11 * s22 - s12 * s12
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (s22 * b1 - s12 * b2) / det
        h = (s11 * b2 - s12 * b1) / det
    bad = ~(np.isfinite(d) & np.isfinite(h))
    return np.where(bad, 0.0, d), np.where(bad, np.nan, h)
