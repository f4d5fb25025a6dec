"""The map's facade edges as rows of the block adjustment (issue 27 item 4:
"the cadastral corner-to-line and facade residuals where a map is given").

``register``'s stage 3 on the georegistered block: in every image that stage
2 registered on the map (:func:`~.map_rows.pairs_on_map`), stage 1's
first-pass segments that lie on the walls it should see become facade edges
(:func:`~obliq_colmap.adjustment.facade_edges`, the image's ground the plane
stage 2 found), matched across the images into tracks of one height each
(:func:`~obliq_colmap.adjustment.match_facade_edges`). Each observation is
one row of the bundle, the point at the track's height over its anchor on
the map edge against the segment's line in RAW pixels (``register``'s rows
with ``BundleOptions.facade_lines`` off); the heights are unknowns of the
adjustment, initialised with the cameras held.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from obliq_colmap.adjustment import (
    FacadeOptions,
    MatchingOptions,
    facade_edges,
    match_facade_edges,
    raw_lines,
    within_robust_bound,
)
from obliq_colmap.geometry import Camera, Pose

logger = logging.getLogger(__name__)


@dataclass
class FacadeRows:
    """(H,) facade observations of (J,) tracks, in the block's frame.

    image_id : (H,) int, the image that sees it.
    track : (H,) int in [0, J), its track.
    line : (H, 3) the segment's unit line in RAW pixels of that image.
    anchor_xy : (J, 2) each track's point on its map edge (m).
    height : (J,) each track's initial height (m; the adjustment refines it).
    normal : (J, 2) the outward unit normal of each track's map edge: the
        anchor's position across the edge is the map's (its vertex noise,
        shared by every row of the edge), which the adjustment's precision
        counts as an unknown (``BundleProblem.horizontal_offset_normal``).
    """

    image_id: np.ndarray
    track: np.ndarray
    line: np.ndarray
    anchor_xy: np.ndarray
    height: np.ndarray
    normal: np.ndarray

    def __len__(self) -> int:
        return len(self.image_id)

    @property
    def num_tracks(self) -> int:
        return len(self.height)

    def select(self, image_ids) -> FacadeRows:
        """The observations of ``image_ids`` (tracks renumbered; a track
        left with fewer than two observations dropped)."""
        return self.subset(
            np.isin(self.image_id, np.asarray(list(image_ids), np.int64))
        )

    def subset(self, keep: np.ndarray, heights: np.ndarray | None = None) -> FacadeRows:
        """The observations ``keep`` (H,) bool selects; a track left with
        fewer than two dropped, the rest renumbered, their heights
        ``heights`` (J,) where given (e.g. a solve's)."""
        h = self.height if heights is None else np.asarray(heights, float)
        count = np.bincount(self.track[keep], minlength=self.num_tracks)
        keep = keep & (count[self.track] >= 2)
        used = np.flatnonzero(np.bincount(self.track[keep], minlength=self.num_tracks))
        new = np.full(self.num_tracks, -1, np.int64)
        new[used] = np.arange(len(used))
        return FacadeRows(
            self.image_id[keep],
            new[self.track[keep]],
            self.line[keep],
            self.anchor_xy[used],
            h[used],
            self.normal[used],
        )


def outlier_free(
    rows: FacadeRows,
    residuals_px: np.ndarray,
    heights: np.ndarray,
    factor: float = 3.0,
    floor_px: float = 1.0,
) -> FacadeRows:
    """``rows`` without the observations whose residual (px, (H,), in the
    rows' order) exceeds ``factor`` robust sds of all of them (and
    ``floor_px``): ``register``'s outlier test
    (:func:`~obliq_colmap.adjustment.within_robust_bound`) once; wrong
    matches of one facade's repeated floor lines sit a floor off. The
    tracks' ``heights`` (J,) e.g. the solve's."""
    keep = within_robust_bound(np.asarray(residuals_px, float), factor, floor_px)
    return rows.subset(keep, heights)


def empty_facade_rows() -> FacadeRows:
    return FacadeRows(
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 3)),
        np.zeros((0, 2)),
        np.zeros(0),
        np.zeros((0, 2)),
    )


def facade_rows(
    rec: pycolmap.Reconstruction,
    segments: dict[int, object],
    planes: dict[int, np.ndarray],
    cad,
    facades: FacadeOptions | None = None,
    matching: MatchingOptions | None = None,
) -> FacadeRows:
    """Facade tracks over the images of ``rec`` that have both first-pass
    ``segments`` (image id -> :class:`~obliq_colmap.lines.Segments`,
    undistorted pixels of the model's camera) and a ground plane (image id
    -> (3,) ``z = a x + b y + c`` in ``rec``'s frame, e.g. stage 2's
    ``height_plane``), against the map ``cad`` (in ``rec``'s frame)."""
    ids = sorted(
        i
        for i in segments
        if i in planes
        and np.all(np.isfinite(planes[i]))
        and i in rec.images
        and rec.images[i].has_pose
    )
    if len(ids) < 2:
        return empty_facade_rows()
    edges, cams = [], []
    for i in ids:
        image = rec.images[i]
        c = image.camera
        camera = Camera(c.model.name, c.width, c.height, np.asarray(c.params, float))
        pose = Pose.from_rigid3d(image.cam_from_world())
        seg = segments[i]
        p = np.asarray(planes[i], float)
        edges.append(
            facade_edges(
                seg.endpoints,
                seg.normal,
                camera,
                pose,
                lambda xy, p=p: xy @ p[:2] + p[2],
                cad,
                facades,
                seg.pixel_scale,
            )
        )
        cams.append(camera)
    grounds = np.array([planes[i] for i in ids], float)
    tracks = match_facade_edges(edges, grounds, cad, matching)
    if tracks.num_observations == 0:
        return empty_facade_rows()
    lines = np.zeros((tracks.num_observations, 3))
    for k, camera in enumerate(cams):
        sel = np.flatnonzero(tracks.image == k)
        if len(sel) == 0:
            continue
        lines[sel] = raw_lines(camera, edges[k].endpoints[tracks.row[sel]])
    rows = FacadeRows(
        np.asarray(ids, np.int64)[tracks.image],
        tracks.track.astype(np.int64),
        lines,
        tracks.anchor_xy,
        tracks.height,
        np.asarray(cad.edge_normal, float)[tracks.edge],
    )
    logger.info(
        "facade rows: %d observations of %d tracks in %d images",
        len(rows), rows.num_tracks, len(np.unique(rows.image_id)),
    )  # fmt: skip
    return rows
