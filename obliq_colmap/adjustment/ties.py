"""Tie points of stage 3: SIFT features matched across the registered block.

Pairs are chosen from the registered poses (footprints on the ground that
overlap), not exhaustively: an oblique block of n images has O(n) useful
pairs, and matching all n^2 / 2 is most of the cost. Matches are verified
with pycolmap's calibrated two-view geometry, chained into tracks (connected
components of the match graph; tracks that see one image twice are dropped),
and triangulated from the registered poses (midpoint of the rays, batched
3x3 solves) with a reprojection check.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from shapely.geometry import Polygon

from obliq_colmap.adjustment.tie_matching import extract_features, match_pairs
from obliq_colmap.adjustment.tie_options import TiePointOptions

__all__ = [
    "TiePointOptions",
    "TiePoints",
    "chain_tie_tracks",
    "footprints",
    "select_pairs",
    "consistent_pairs",
    "reprojection_errors",
    "tie_points",
    "tie_rows",
    "triangulate_tie_tracks",
]

logger = logging.getLogger(__name__)


@dataclass
class TiePoints:
    """Triangulated tracks: T points, M observations.

    xyz: (T, 3) world points; obs_point: (M,) track of each observation;
    obs_image: (M,) index of its image (into the caller's list);
    obs_xy: (M, 2) pixel coordinates (COLMAP convention, full resolution);
    obs_feature: (M,) feature index in its image;
    obs_scale: (M,) its SIFT keypoint's scale (px, full resolution), or None
    (not known: every observation alike).
    """

    xyz: np.ndarray
    obs_point: np.ndarray
    obs_image: np.ndarray
    obs_xy: np.ndarray
    obs_feature: np.ndarray
    #: The image id of each index of ``obs_image``, where the caller set them.
    image_ids: tuple[int, ...] = ()
    obs_scale: np.ndarray | None = None

    def per_image(self, num_images: int) -> np.ndarray:
        """(num_images,) number of observations in each image."""
        return np.bincount(self.obs_image, minlength=num_images)


def footprints(
    cameras: Sequence[pycolmap.Camera],
    poses: Sequence[pycolmap.Rigid3d],
    ground_z: float,
) -> list[Polygon]:
    """Each image's footprint on the plane z = ground_z (corners' rays; a ray
    above the horizon is clipped to 20 flying heights, far enough for obliques)."""
    out = []
    for cam, pose in zip(cameras, poses, strict=True):
        w, h = cam.width, cam.height
        corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
        rays_cam = np.c_[cam.cam_from_img(corners), np.ones(4)]
        R = pose.rotation.matrix()
        c = -R.T @ pose.translation
        rays = rays_cam @ R  # (4, 3) world directions: R^T d
        height = c[2] - ground_z
        down = -rays[:, 2]
        t = np.where(down > 1e-9, height / np.maximum(down, 1e-9), np.inf)
        t = np.minimum(t, 20.0 * abs(height) / np.linalg.norm(rays, axis=1))
        out.append(Polygon(c[:2] + t[:, None] * rays[:, :2]).buffer(0))
    return out


def select_pairs(
    polys: Sequence[Polygon],
    poses: Sequence[pycolmap.Rigid3d],
    options: TiePointOptions,
) -> list[tuple[int, int]]:
    """Pairs (i < j) whose footprints overlap enough and whose views differ by
    at most ``max_view_angle_deg``, each image's best ``max_pairs_per_image``
    partners (a pair is kept if either end chose it), half of them the best
    of a similar view (``similar_view_deg``) where it has such partners."""
    n = len(polys)
    axes = np.stack([p.rotation.matrix()[2] for p in poses]).reshape(-1, 3)
    cosine = axes @ axes.T
    similar = cosine >= np.cos(np.radians(options.max_view_angle_deg))
    close = cosine >= np.cos(np.radians(options.similar_view_deg))
    share = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            if similar[i, j] and polys[i].intersects(polys[j]):
                inter = polys[i].intersection(polys[j]).area
                share[i, j] = share[j, i] = inter / max(
                    min(polys[i].area, polys[j].area), 1e-9
                )
    share[share < options.min_overlap] = 0.0
    k = options.max_pairs_per_image
    chosen = set()
    for i in range(n):
        order = np.argsort(-share[i], kind="stable")
        order = order[share[i, order] > 0]
        near = order[close[i, order]][: k // 2]
        rest = order[~np.isin(order, near)][: k - len(near)]
        chosen.update((min(i, j), max(i, j)) for j in np.concatenate([near, rest]))
    return sorted(chosen)


def chain_tie_tracks(matches: dict[tuple[int, int], np.ndarray], counts: Sequence[int]):
    """Connected components of the match graph: (M,) track, image, feature of
    each observation in tracks of >= 2 images that see each image once."""
    offset = np.concatenate([[0], np.cumsum(counts)])
    if not matches:
        return (np.zeros(0, np.int64),) * 3
    a = np.concatenate([offset[i] + m[:, 0] for (i, _), m in matches.items()])
    b = np.concatenate([offset[j] + m[:, 1] for (_, j), m in matches.items()])
    n = int(offset[-1])
    graph = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    node = np.unique(np.concatenate([a, b]))
    image = np.searchsorted(offset, node, side="right") - 1
    track = label[node]
    size = np.bincount(track)
    distinct = np.bincount(
        np.unique(np.c_[track, image], axis=0)[:, 0], minlength=len(size)
    )
    keep = (size[track] >= 2) & (distinct[track] == size[track])
    return track[keep], image[keep], node[keep] - offset[image[keep]]


def triangulate_tie_tracks(
    cameras: Sequence[pycolmap.Camera],
    poses: Sequence[pycolmap.Rigid3d],
    obs_track: np.ndarray,
    obs_image: np.ndarray,
    obs_xy: np.ndarray,
) -> np.ndarray:
    """(T, 3) midpoints of each track's rays: ``sum_k (I - d d^T) (X - c_k) = 0``,
    one batched 3x3 solve (T = obs_track.max() + 1; tracks are 0..T-1)."""
    R = np.stack([p.rotation.matrix() for p in poses])
    C = np.stack([-p.rotation.matrix().T @ p.translation for p in poses])
    d = np.empty((len(obs_xy), 3))
    for i in np.unique(obs_image):  # per image (a few dozen), not per point
        m = obs_image == i
        d[m] = np.c_[cameras[i].cam_from_img(obs_xy[m]), np.ones(m.sum())] @ R[i]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    P = np.eye(3) - d[:, :, None] * d[:, None, :]
    T = int(obs_track.max()) + 1 if len(obs_track) else 0
    A = np.zeros((T, 3, 3))
    b = np.zeros((T, 3))
    np.add.at(A, obs_track, P)
    np.add.at(b, obs_track, np.einsum("kij,kj->ki", P, C[obs_image]))
    return np.linalg.solve(A + 1e-12 * np.eye(3), b[:, :, None])[:, :, 0]


def reprojection_errors(
    cameras, poses, xyz, obs_point, obs_image, obs_xy
) -> np.ndarray:
    """(M,) pixel distance of each observation from its point's projection."""
    err = np.full(len(obs_xy), np.inf)
    for i in np.unique(obs_image):
        m = obs_image == i
        X = poses[i] * xyz[obs_point[m]]  # (m, 3) camera frame
        front = X[:, 2] > 0
        uv = cameras[i].img_from_cam(X[front])
        e = np.full(m.sum(), np.inf)
        e[front] = np.linalg.norm(np.asarray(uv) - obs_xy[m][front], axis=1)
        err[m] = e
    return err


def in_the_scene(xyz, poses, ground_z: float, options: TiePointOptions) -> np.ndarray:
    """(T,) points between the ground (less a margin) and the cameras, and
    within reach of a camera horizontally (:class:`TiePointOptions`)."""
    C = np.stack([-p.rotation.matrix().T @ p.translation for p in poses])
    height = max(float(np.median(C[:, 2])) - ground_z, 1.0)
    z = xyz[:, 2]
    ok = (z >= ground_z - options.max_below_ground_fraction * height) & (
        z <= C[:, 2].min()
    )
    d = np.linalg.norm(xyz[:, None, :2] - C[None, :, :2], axis=2).min(axis=1)
    return ok & (d <= options.max_distance_heights * height)


def tie_points(
    gray_images: Sequence[np.ndarray],
    cameras: Sequence[pycolmap.Camera],
    poses: Sequence[pycolmap.Rigid3d],
    ground_z: float,
    options: TiePointOptions | None = None,
) -> TiePoints:
    """Tie points of a registered block (images, cameras and cam_from_world
    poses in the same order)."""
    options = options or TiePointOptions()
    pairs = select_pairs(footprints(cameras, poses, ground_z), poses, options)
    features = extract_features(gray_images, options)
    matches = match_pairs(features, cameras, poses, pairs, options)
    track, image, feature = chain_tie_tracks(matches, [len(f[0]) for f in features])
    counts = np.array([len(f[0]) for f in features])
    offset = np.concatenate([[0], np.cumsum(counts)])[:-1]
    xy = np.concatenate([f[0] for f in features])[offset[image] + feature]
    size = np.concatenate([f[4] for f in features])[offset[image] + feature]
    _, track = np.unique(track, return_inverse=True)
    xyz = triangulate_tie_tracks(cameras, poses, track, image, xy)
    err = reprojection_errors(cameras, poses, xyz, track, image, xy)
    bad_track = ~in_the_scene(xyz, poses, ground_z, options)
    bad_track[track[err > options.max_reproj_error_px]] = True
    keep = ~bad_track[track]
    keep &= (
        np.bincount(track[keep], minlength=len(xyz))[track] >= options.min_track_length
    )
    kept_tracks, new_track = np.unique(track[keep], return_inverse=True)
    logger.info(
        "tie points: %d pairs, %d matched, %d points, %d observations",
        len(pairs),
        len(matches),
        len(kept_tracks),
        int(keep.sum()),
    )
    return TiePoints(
        xyz[kept_tracks],
        new_track,
        image[keep],
        xy[keep],
        feature[keep],
        obs_scale=size[keep],
    )


def tie_rows(
    ties: TiePoints,
    ids: Sequence[int],
    cameras: Sequence[pycolmap.Camera],
    poses: Sequence[pycolmap.Rigid3d],
    ground_z: float,
    options: TiePointOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tie points as the bundle's rows over the images ``ids`` (with
    their cameras and poses, in that order): (T, 3) start points
    triangulated from these poses, (O,) image index into ``ids``, (O,) point
    index, (O, 2) raw pixels, (O,) relative standard deviation.

    A SIFT keypoint is located to a share of its scale: at the true cameras
    of urban-101 the tie residuals' median grows from 0.23 px at scales of
    3-4 px to 0.69 px above 10 px, 0.04-0.05 of the scale throughout. So
    each observation's sd is its keypoint's scale over the median scale of
    the kept observations (1 where the scale is not known); the bundle
    estimates the sd at the median scale (``BundleOptions.tie_sigma_px``).

    Kept: the observations of images in ``ids`` in front of their camera, of
    points in the scene (:func:`in_the_scene`) seen at least
    ``min_track_length`` times. No reprojection test here: the poses are the
    ones the bundle is about to correct (the robust loss and its rounds judge
    the matches).
    """
    pos = {int(i): k for k, i in enumerate(ids)}
    img = np.array([pos.get(int(ties.image_ids[j]), -1) for j in ties.obs_image])
    img = img.reshape(-1).astype(np.int64)
    keep = img >= 0
    track, img, xy = ties.obs_point[keep], img[keep], ties.obs_xy[keep]
    size = ties.obs_scale[keep] if ties.obs_scale is not None else np.ones(len(track))
    R = np.stack([p.rotation.matrix() for p in poses]).reshape(-1, 3, 3)
    t = np.stack([p.translation for p in poses]).reshape(-1, 3)
    while True:
        many = np.bincount(track)[track] >= options.min_track_length
        track, img, xy, size = track[many], img[many], xy[many], size[many]
        if len(track) == 0:
            return np.zeros((0, 3)), img, track, xy, size
        _, track = np.unique(track, return_inverse=True)
        xyz = triangulate_tie_tracks(cameras, poses, track, img, xy)
        depth = np.einsum("kj,kj->k", R[img][:, 2], xyz[track]) + t[img][:, 2]
        ok = (depth > 0) & in_the_scene(xyz, poses, ground_z, options)[track]
        if ok.all():
            return xyz, img, track, xy, size / np.median(size)
        track, img, xy, size = track[ok], img[ok], xy[ok], size[ok]


def consistent_pairs(
    err: np.ndarray,
    image: np.ndarray,
    point: np.ndarray,
    factor: float,
    floor_px: float,
) -> np.ndarray:
    """(T,) the tracks all of whose image pairs agree with the block.

    ``err``: (O,) each observation's reprojection error (px) at the solved
    block, ``image``, ``point``: (O,) its image and track. Two-view
    verification can accept a whole pair of images on a wrong geometry
    (repeated texture: the matches shifted by one period, mutually
    consistent); a block solved without the tie points shows such a pair as
    many matches several pixels off together. A pair of images whose median
    error (over the tracks both see; a track's error in the pair is the
    larger of its two) exceeds ``factor`` times the median over the pairs
    and ``floor_px`` is rejected, with every track that sees it.
    """
    T = int(point.max()) + 1 if len(point) else 0
    order = np.argsort(point, kind="stable")
    p, im, e = point[order], image[order], err[order]
    start = np.searchsorted(p, np.arange(T + 1))
    n = np.diff(start)
    # every ordered pair (a, b), a < b, of observations of one track
    first = np.repeat(start[:-1], n * n)
    k = np.arange(len(first)) - np.repeat(np.cumsum(n * n) - n * n, n * n)
    a = first + k // np.repeat(n, n * n)
    b = first + k % np.repeat(n, n * n)
    ok = a < b
    a, b = a[ok], b[ok]
    if len(a) == 0:
        return np.ones(T, bool)
    i, j = np.minimum(im[a], im[b]), np.maximum(im[a], im[b])
    key = i * (int(im.max()) + 1) + j
    pair_err = np.maximum(e[a], e[b])
    keys, inv = np.unique(key, return_inverse=True)
    srt = np.lexsort((pair_err, inv))
    cnt = np.bincount(inv)
    lo = np.cumsum(cnt) - cnt
    pe = pair_err[srt]
    med = 0.5 * (pe[lo + (cnt - 1) // 2] + pe[lo + cnt // 2])
    bad_pair = med > max(factor * float(np.median(med)), floor_px)
    good = np.ones(T, bool)
    good[p[a[bad_pair[inv]]]] = False
    return good
