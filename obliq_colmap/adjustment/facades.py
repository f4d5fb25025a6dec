"""Horizontal facade edges of one registered image (stage 3, first step).

Habbecke & Kobbelt, section 2.3 and Fig. 6a: with the image registered to
the map, every potentially visible map edge defines a wall, the vertical
plane over the edge. Horizontal scene edges on that wall (window rows, floor
bands, roof rims) project onto lines through the wall's horizontal vanishing
point ``K R d`` (``d`` the edge's direction); they are searched in the band
of the image between the wall at ``height_range_m[0]`` and
``height_range_m[1]`` around the image's own height function (its ground
plane from stage 2).

Each detected segment is lifted onto the wall through the wall's plane
homography ``H = K R [d | e_z | p0 - c]``: wall coordinates ``s`` (metres
along the edge from its start) and ``t`` (metres above the ground plane at
that point). A segment is kept for a wall when

* its midpoint lies on the wall (``0 <= s <= length``, ``t`` in the band);
* its direction agrees with the wall's horizontal through its midpoint (the
  endpoints' distance to the line from the midpoint to the horizontal VP is
  at most ``max_endpoint_offset_px``);
* the wall is seen at a usable angle (the wall's horizontals are not nearly
  parallel to the projected vertical, where ``dist_z`` is undefined).

Lengths and offsets are in pixels of the image the segments were DETECTED in
(``Segments.pixel_scale``): the first pass runs LSD on a reduced copy of a
big image, and its endpoints' noise is about constant in those pixels.

The result is plain arrays, one row per (segment, wall) pair: a segment in
the bands of two walls (a building behind another) is kept for both; the
cross-image matching (:mod:`~obliq_colmap.adjustment.matching`) decides.

Heights ``t`` are RELATIVE to the image's ground plane: one image's absolute
heights are only as good as its height datum (stage 2 holds the prior camera
height), but its heights above its own ground agree with another image's
to a few decimetres, so matches are searched among small offsets.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from obliq_colmap.cadastre import Cadastre, visible_edge_parts
from obliq_colmap.geometry import Camera, Pose, lines_through

__all__ = ["FacadeEdges", "FacadeOptions", "facade_edges"]

_EZ = np.array([0.0, 0.0, 1.0])


@dataclass(kw_only=True)
class FacadeOptions:
    """Options of :func:`facade_edges`."""

    #: Heights above the image's ground plane (m) spanned by the search band
    #: of each wall. The paper used +-20 m around the edge; the upper bound is
    #: higher here because roof rims of tall buildings are among the best
    #: horizontal edges, and the lower bound covers ground-height errors.
    height_range_m: tuple[float, float] = (-20.0, 60.0)
    #: Shortest horizontal segment used (px of the detection image).
    min_length_px: float = 15.0
    #: A segment's endpoints may lie this far (px of the detection image)
    #: from the wall's horizontal through its midpoint (its direction must
    #: agree with the wall's).
    max_endpoint_offset_px: float = 1.5
    #: Walls seen more obliquely than this (angle between the wall's image
    #: horizontal and the projected vertical, deg) are skipped.
    min_vertical_angle_deg: float = 25.0
    #: Walls whose visible part is shorter than this (m) are skipped.
    min_wall_length_m: float = 2.0
    #: Segments must lie at least this far (m) inside the wall's ends, so that
    #: a segment on the neighbouring wall around a corner is not taken.
    end_margin_m: float = 0.3
    #: Walls (map edges) per vectorised chunk (bounds the memory:
    #: chunk x segments pairs).
    chunk_walls: int = 64

    def __post_init__(self) -> None:
        lo, hi = self.height_range_m
        if not hi > lo:
            raise ValueError(f"height_range_m must be increasing, got {lo, hi}")
        if self.min_length_px <= 0 or self.max_endpoint_offset_px <= 0:
            raise ValueError("min_length_px and max_endpoint_offset_px must be > 0")


@dataclass
class FacadeEdges:
    """Horizontal facade segments of one image, one row per (segment, wall).

    Attributes
    ----------
    edge : (K,) int array, map edge index (the wall).
    segment : (K,) int array, index into the input segments.
    endpoints : (K, 2, 2) array, the segment, UNDISTORTED pixels.
    line : (K, 3) array, its homogeneous line (unit normal), undistorted px.
    s : (K,) array, position of the midpoint along the edge (m from its start).
    height : (K,) array, height of the segment's line above the image's ground
        plane (m) on the wall's vertical through the midpoint.
    px_per_m : (K,) array, image length of one metre of that vertical (px).
    polarity : (K,) int array, +1 when the brighter side is up the wall.
    length : (K,) array, segment length (px).
    pixel_scale : (K,) array, pixels per pixel of the detection image (the
        unit of the segment's localisation noise, ``Segments.pixel_scale``).
    """

    edge: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    segment: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    endpoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    line: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    height: np.ndarray = field(default_factory=lambda: np.zeros(0))
    px_per_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    polarity: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pixel_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.edge)

    def subset(self, index: np.ndarray) -> FacadeEdges:
        return FacadeEdges(
            **{k: getattr(self, k)[index] for k in self.__dataclass_fields__}
        )

    @property
    def num_walls(self) -> int:
        return len(np.unique(self.edge))


def _wall_homographies(
    KR: np.ndarray, center: np.ndarray, p0: np.ndarray, d: np.ndarray
) -> np.ndarray:
    """(W, 3, 3) homographies from wall coordinates (s, t, 1) to pixels.

    ``X(s, t) = (p0 + s d, z0 + t)`` with ``p0`` (W, 3) the edge start at
    ground height and ``d`` (W, 3) the unit horizontal edge direction.
    """
    cols = np.stack(
        [
            d @ KR.T,
            np.broadcast_to(KR @ _EZ, d.shape),
            (p0 - center) @ KR.T,
        ],
        axis=2,
    )  # (W, 3, 3), columns
    return cols


def facade_edges(
    endpoints: np.ndarray,
    normals: np.ndarray,
    camera: Camera,
    cam_from_world: Pose,
    ground: Callable[[np.ndarray], np.ndarray],
    cadastre: Cadastre,
    options: FacadeOptions | None = None,
    pixel_scale: float = 1.0,
) -> FacadeEdges:
    """Horizontal segments on the potentially visible walls of one image.

    Parameters
    ----------
    endpoints : (N, 2, 2) array
        Line segments of the image, UNDISTORTED pixels (pinhole ``K`` of
        ``camera``), e.g. the vanishing stage's first-pass segments.
    normals : (N, 2) array
        Unit normal of each segment towards its brighter side.
    camera : Camera, the intrinsics the pose belongs to.
    cam_from_world : Pose, the registered pose, local frame.
    ground : callable (M, 2) xy -> (M,) ground heights (the image's height
        plane, same datum as the pose).
    cadastre : Cadastre
    options : FacadeOptions
    pixel_scale : float, pixels of ``endpoints`` per pixel of the image they
        were detected in (``Segments.pixel_scale``): the unit of the options'
        pixel tolerances.

    Returns
    -------
    FacadeEdges (possibly empty).
    """
    options = options or FacadeOptions()
    ends = np.asarray(endpoints, float).reshape(-1, 2, 2)
    normals = np.asarray(normals, float).reshape(-1, 2)
    seg_len = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    keep = np.flatnonzero(seg_len >= options.min_length_px * pixel_scale)
    if len(keep) == 0:
        return FacadeEdges()
    lo, hi = options.height_range_m
    walls, parts = visible_edge_parts(
        cadastre,
        camera,
        cam_from_world,
        ground,
        (lo, hi),
        use_building_heights=False,
    )
    part_len = np.linalg.norm(parts[:, 1] - parts[:, 0], axis=1)
    ok = part_len >= options.min_wall_length_m
    walls = walls[ok]
    if len(walls) == 0:
        return FacadeEdges()
    K = camera.K
    R = cam_from_world.rotation
    KR = K @ R
    center = cam_from_world.center
    e_xy = cadastre.edge_xy[walls]  # (W, 2, 2)
    length = cadastre.edge_length[walls]
    d2 = (e_xy[:, 1] - e_xy[:, 0]) / length[:, None]
    z0 = ground(e_xy[:, 0])
    z1 = ground(e_xy[:, 1])
    slope = (z1 - z0) / length  # ground rise along the edge (m/m)
    d = np.column_stack([d2, np.zeros(len(walls))])
    p0 = np.column_stack([e_xy[:, 0], z0])
    # Wall coordinates with a sloped ground: X = p0 + s d + (t + slope s) e_z,
    # i.e. the first column gets slope * e_z.
    H = _wall_homographies(KR, center, p0, d + slope[:, None] * _EZ)
    vp_h = d @ KR.T  # (W, 3) horizontal VP of each wall (homogeneous)

    S = ends[keep]
    mid = S.mean(axis=1)  # (M, 2)
    mid_h = np.column_stack([mid, np.ones(len(mid))])
    rows: list[dict[str, np.ndarray]] = []
    for w0 in range(0, len(walls), options.chunk_walls):
        sl = slice(w0, w0 + options.chunk_walls)
        r = _match_chunk(H[sl], vp_h[sl], length[sl], mid_h, S, options, pixel_scale)
        r["wall"] = r["wall"] + w0
        rows.append(r)
    wall_idx = np.concatenate([r["wall"] for r in rows])
    seg_idx = np.concatenate([r["seg"] for r in rows])
    if len(seg_idx) == 0:
        return FacadeEdges()
    s = np.concatenate([r["s"] for r in rows])
    t = np.concatenate([r["t"] for r in rows])
    ppm = np.concatenate([r["px_per_m"] for r in rows])
    up = np.concatenate([r["up"] for r in rows])  # (K, 2) image up the wall
    segs = keep[seg_idx]
    polarity = np.where(np.sum(normals[segs] * up, axis=1) > 0, 1, -1)
    E = ends[segs]
    return FacadeEdges(
        edge=walls[wall_idx].astype(np.int64),
        segment=segs.astype(np.int64),
        endpoints=E,
        line=lines_through(E[:, 0], E[:, 1]),
        s=s,
        height=t,
        px_per_m=ppm,
        polarity=polarity.astype(np.int64),
        length=seg_len[segs],
        pixel_scale=np.full(len(segs), float(pixel_scale)),
    )


def _match_chunk(
    H: np.ndarray,
    vp_h: np.ndarray,
    length: np.ndarray,
    mid_h: np.ndarray,
    S: np.ndarray,
    options: FacadeOptions,
    pixel_scale: float,
) -> dict[str, np.ndarray]:
    """Segments (M) against walls (W) of one chunk; the kept pairs' data."""
    lo, hi = options.height_range_m
    Hinv = np.linalg.inv(H)  # (W, 3, 3)
    st = np.einsum("wij,mj->wmi", Hinv, mid_h)  # (W, M, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = st[..., 0] / st[..., 2]
        t = st[..., 1] / st[..., 2]
    margin = options.end_margin_m
    inside = (
        (st[..., 2] != 0)
        & (s >= margin)
        & (s <= length[:, None] - margin)
        & (t >= lo)
        & (t <= hi)
    )
    w, m = np.nonzero(inside)
    if len(w) == 0:
        z = np.zeros(0)
        return dict(
            wall=np.zeros(0, np.int64),
            seg=np.zeros(0, np.int64),
            s=z,
            t=z,
            px_per_m=z,
            up=np.zeros((0, 2)),
        )
    # The wall's horizontal through the midpoint: the line to its VP.
    hline = np.cross(mid_h[m], vp_h[w])  # (K, 3)
    hline /= np.linalg.norm(hline[:, :2], axis=1, keepdims=True)
    ends_h = np.concatenate([S[m], np.ones((len(m), 2, 1))], axis=2)  # (K, 2, 3)
    offset = np.abs(np.einsum("kej,kj->ke", ends_h, hline)).max(axis=1)
    # Projected vertical at the midpoint (``up``: image of d/dt X(s, t),
    # px per metre, towards increasing height).
    st1 = np.column_stack([s[w, m], t[w, m], np.ones(len(m))])
    x = np.einsum("kij,kj->ki", H[w], st1)
    dt = H[w][:, :, 1]  # column for t
    # d(pixel)/dt = (dt_xy * x_z - x_xy * dt_z) / x_z^2
    up = (dt[:, :2] * x[:, 2:3] - x[:, :2] * dt[:, 2:3]) / (x[:, 2:3] ** 2)
    ppm = np.linalg.norm(up, axis=1)
    up_hat = up / np.where(ppm > 0, ppm, 1.0)[:, None]
    # Angle between the wall's horizontal (line direction) and the vertical.
    h_dir = np.column_stack([hline[:, 1], -hline[:, 0]])
    cos_hv = np.abs(np.sum(h_dir * up_hat, axis=1))
    sharp = cos_hv <= math.cos(math.radians(options.min_vertical_angle_deg))
    good = (offset <= options.max_endpoint_offset_px * pixel_scale) & sharp & (ppm > 0)
    # Height of the segment's own line on the vertical through its midpoint.
    seg_line = np.cross(ends_h[:, 0], ends_h[:, 1])
    seg_line /= np.linalg.norm(seg_line[:, :2], axis=1, keepdims=True)
    e = np.sum(seg_line * x, axis=1) / x[:, 2]  # signed distance of the wall point
    slope_px = np.sum(seg_line[:, :2] * up, axis=1)  # d distance / d t
    with np.errstate(divide="ignore", invalid="ignore"):
        t_line = t[w, m] - e / slope_px
    good &= np.isfinite(t_line)
    return dict(
        wall=w[good],
        seg=m[good],
        s=s[w, m][good],
        t=t_line[good],
        px_per_m=ppm[good],
        up=up_hat[good],
    )
