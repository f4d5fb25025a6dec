"""The map's corner lines as rows of the block adjustment (issue 27 item 4:
"the cadastral corner-to-line residuals where a map is given").

Each stage-2 inlier pair of an image (a map corner, the vertical segment
that images it) becomes the rows ``register``'s stage 3 builds
(:func:`~obliq_colmap.adjustment.problem.vertical_constraints`): two points
on the corner's vertical, at the heights where the rays through the
segment's two ends pass it (from the block as it stands, then fixed),
each projected against the segment's line in RAW pixels. Two points per
segment hold its direction (its VP) as well as its position; sliding along
the vertical does not change a distance to a line through the VP, so the
fixed heights only place the points near the segment.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from obliq_colmap.adjustment.problem import heights_on_vertical
from obliq_colmap.geometry import Camera, Pose, lines_through
from obliq_colmap.registration import RegistrationOptions, register_image

from .facade_rows import FacadeRows, facade_rows

logger = logging.getLogger(__name__)


@dataclass
class MapRows:
    """(M,) corner-to-line rows, two per inlier pair, in the block's frame.

    xy : (M, 2) the map corner's position (the frame of ``rec``).
    height : (M,) the point's height on the corner's vertical, fixed.
    image_id : (M,) int, the image that sees it.
    line : (M, 3) the segment's unit line in RAW pixels of that image's camera.
    """

    xy: np.ndarray
    height: np.ndarray
    image_id: np.ndarray
    line: np.ndarray
    #: the map's facade rows from the same images (:mod:`.facade_rows`), or
    #: None
    facades: FacadeRows | None = None

    def __len__(self) -> int:
        return len(self.xy)

    def select(self, keep: np.ndarray) -> MapRows:
        """The corner rows ``keep`` selects (the facade rows unchanged)."""
        return MapRows(
            self.xy[keep],
            self.height[keep],
            self.image_id[keep],
            self.line[keep],
            self.facades,
        )


def empty_map_rows() -> MapRows:
    return MapRows(
        np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))
    )


@dataclass
class ImagePairs:
    """One image's stage-2 inliers: (K,) corner ids into the map's corners and
    (K, 2, 2) the segments, UNDISTORTED pixels of the model's camera; the
    ground plane stage 2 found (3,) ``z = a x + b y + c`` in the frame of
    the pose it registered from, or None."""

    corner: np.ndarray
    segments: np.ndarray
    height_plane: np.ndarray | None = None


def _camera(rec: pycolmap.Reconstruction, image_id: int) -> Camera:
    c = rec.images[image_id].camera
    return Camera(c.model.name, c.width, c.height, np.asarray(c.params, float))


def map_rows(
    rec: pycolmap.Reconstruction,
    corner_xy: np.ndarray,
    pairs: dict[int, ImagePairs],
) -> MapRows:
    """The rows of every image's pairs against the block ``rec`` as it
    stands (its frame: ``corner_xy`` (C, 2) must be in it)."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("xy", "h", "i", "l")}
    for image_id, p in pairs.items():
        if len(p.corner) == 0 or image_id not in rec.images:
            continue
        camera = _camera(rec, image_id)
        pose = Pose.from_rigid3d(rec.images[image_id].cam_from_world())
        raw = camera.distort_pixels(p.segments.reshape(-1, 2))  # (2K, 2)
        xy = np.repeat(corner_xy[p.corner], 2, axis=0)
        ends = raw.reshape(-1, 2, 2)
        parts["xy"].append(xy)
        parts["h"].append(heights_on_vertical(camera, pose, xy, raw))
        parts["i"].append(np.full(len(xy), image_id, np.int64))
        parts["l"].append(np.repeat(lines_through(ends[:, 0], ends[:, 1]), 2, axis=0))
    if not parts["xy"]:
        return empty_map_rows()
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    return MapRows(cat["xy"], cat["h"], cat["i"], cat["l"])


def row_residuals_px(rec: pycolmap.Reconstruction, rows: MapRows) -> np.ndarray:
    """(M,) signed distance (px) of each row's point, projected through its
    image's camera, from its line."""
    out = np.empty(len(rows))
    for image_id in np.unique(rows.image_id):
        sel = np.flatnonzero(rows.image_id == image_id)
        image = rec.images[int(image_id)]
        X = np.c_[rows.xy[sel], rows.height[sel]]
        uv = image.camera.img_from_cam(image.cam_from_world() * X)
        line = rows.line[sel]
        out[sel] = (np.sum(line[:, :2] * uv, axis=1) + line[:, 2]) / np.linalg.norm(
            line[:, :2], axis=1
        )
    return out


def gate_map_rows(
    rec: pycolmap.Reconstruction, rows: MapRows, gate_px: float
) -> tuple[MapRows, np.ndarray]:
    """The rows within ``gate_px`` of their lines as the block stands, both
    rows of a pair together (a pair stage 2 got wrong for an image that the
    block's similarity then placed elsewhere sits pixels off; the bundle's
    Cauchy loss would still feel it). Also returns the (M,) residuals."""
    r = row_residuals_px(rec, rows)
    pair_ok = np.all(np.abs(r).reshape(-1, 2) <= gate_px, axis=1)
    keep = np.repeat(pair_ok, 2)
    logger.info(
        "map rows: %d of %d pairs within %.1f px (median |r| %.2f px)",
        int(pair_ok.sum()), len(pair_ok), gate_px,
        float(np.median(np.abs(r))) if len(r) else float("nan"),
    )  # fmt: skip
    return rows.select(keep), r


def image_pairs(im, result, measured_directions: bool) -> ImagePairs:
    """One image's stage-2 inliers (``im``: its
    :class:`~.vertical.ImageVertical`, ``result``: its RegistrationResult).
    With ``measured_directions`` each segment's own fit on its edge points
    (as ``register``'s ``measured_vertical_directions``) instead of the
    line through the image's VP that stage 2 matched: through the VP, all
    of an image's rows repeat its VP's direction (and its error, ~0.4 deg
    on the paper block) at many times the VP row's weight."""
    corner = result.inlier_pairs[:, 0].copy()
    plane = np.asarray(result.height_plane, float).copy()
    if measured_directions and im.segments_free is not None:
        free = im.segments_free[result.inlier_pairs[:, 1]].copy()
        return ImagePairs(corner, free, plane)
    return ImagePairs(corner, result.inlier_segments_px.copy(), plane)


def pairs_on_map(
    rec: pycolmap.Reconstruction,
    vertical,
    cad,
    options: RegistrationOptions,
    measured_directions: bool = False,
) -> dict[int, ImagePairs]:
    """Stage 2 on every image with a VP and 3 or more vertical segments
    (``vertical``: :class:`~.vertical.ModelVertical`), its pose in ``rec``
    (already in ``cad``'s frame, e.g. placed by control points) as the
    prior; each registered image's inlier pairs."""
    out = {}
    for im in vertical.images:
        if im.segments is None or len(im.segments) < 3 or im.down_camera is None:
            continue
        if im.image_id not in rec.images or not rec.images[im.image_id].has_pose:
            continue
        prior = Pose.from_rigid3d(rec.images[im.image_id].cam_from_world())
        result = register_image(
            im.segments, im.down_camera, _camera(rec, im.image_id), prior, cad,
            options, segments_undistorted=True,
        )  # fmt: skip
        if result.success and len(result.inlier_pairs):
            out[im.image_id] = image_pairs(im, result, measured_directions)
    logger.info(
        "map rows: stage 2 registered %d of %d images from their placed poses",
        len(out), len(vertical.images),
    )  # fmt: skip
    return out


def with_facade_rows(
    rec: pycolmap.Reconstruction,
    rows: MapRows,
    vertical,
    cad,
    pairs: dict[int, ImagePairs],
) -> MapRows:
    """``rows`` with the map's facade rows (:func:`.facade_rows.facade_rows`)
    from the images that stage 2 registered (``pairs``, their ground
    planes) and whose first-pass segments stage 1 kept (``vertical``)."""
    segments = {
        im.image_id: im.line_segments
        for im in vertical.images
        if im.line_segments is not None and len(im.line_segments)
    }
    planes = {i: p.height_plane for i, p in pairs.items() if p.height_plane is not None}
    rows.facades = facade_rows(rec, segments, planes, cad)
    return rows
