"""What COLMAP's ``patch_match_stereo`` derives from a workspace's sparse
model, re-implemented on arrays (COLMAP 3.8, ``mvs/model.cc`` and
``mvs/patch_match.cc``), so that a workspace can be checked where COLMAP's
dense stage cannot run (it needs CUDA):

* each reference image's depth range: the 1st and 99th percentile of the
  depths of its own track points (those in front of it), widened by 25 %;
  an image without such points stops the whole run (a CHECK failure);
* ``__auto__`` source images: the images sharing points with the reference
  image whose triangulation angle (75th percentile over the shared points)
  reaches ``min_triangulation_angle``, most shared points first; a reference
  image without any is skipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "MvsModel",
    "depth_ranges",
    "mvs_model",
    "pair_statistics",
    "source_images",
]

#: COLMAP's percentiles and stretch of the depth range (mvs/model.cc).
MIN_PERCENTILE, MAX_PERCENTILE, STRETCH = 0.01, 0.99, 0.25
#: percentile of a pair's triangulation angles (mvs/patch_match.cc).
ANGLE_PERCENTILE = 75.0


@dataclass
class MvsModel:
    """The part of a sparse model that COLMAP's MVS reads.

    Attributes
    ----------
    names : (I,) image names; index = image index below.
    R : (I, 3, 3) cam_from_world rotations; t : (I, 3) translations.
    xyz : (P, 3) points, model frame.
    el_point : (E,) point index of each track element.
    el_image : (E,) image index of each track element.
    """

    names: list[str]
    R: np.ndarray
    t: np.ndarray
    xyz: np.ndarray
    el_point: np.ndarray
    el_image: np.ndarray

    @property
    def centers(self) -> np.ndarray:
        """(I, 3) projection centres, -R^T t."""
        return -np.einsum("ikj,ik->ij", self.R, self.t)


def mvs_model(rec) -> MvsModel:
    """The :class:`MvsModel` of a ``pycolmap.Reconstruction`` (posed images)."""
    ids = sorted(i for i, im in rec.images.items() if im.has_pose)
    index = {image_id: k for k, image_id in enumerate(ids)}
    poses = [rec.images[i].cam_from_world() for i in ids]
    R = np.array([p.rotation.matrix() for p in poses]).reshape(-1, 3, 3)
    t = np.array([p.translation for p in poses]).reshape(-1, 3)
    xyz, el_point, el_image = [], [], []
    for k, point in enumerate(rec.points3D.values()):
        xyz.append(point.xyz)
        for el in point.track.elements:
            if el.image_id in index:
                el_point.append(k)
                el_image.append(index[el.image_id])
    return MvsModel(
        [rec.images[i].name for i in ids],
        R,
        t,
        np.array(xyz, float).reshape(-1, 3),
        np.array(el_point, int),
        np.array(el_image, int),
    )


def depth_ranges(model: MvsModel) -> tuple[np.ndarray, np.ndarray]:
    """Each image's depth range as COLMAP's MVS computes it.

    Returns
    -------
    ranges : (I, 2) [min, max] depth, m; -1 where the image has no point
        in front of it (COLMAP's value, which stops patch_match_stereo).
    counts : (I,) number of its track points in front of it.
    """
    num = len(model.names)
    img = model.el_image
    X = model.xyz[model.el_point]
    depth = np.einsum("ej,ej->e", model.R[img, 2], X) + model.t[img, 2]
    front = depth > 0
    img, depth = img[front], depth[front]
    order = np.lexsort((depth, img))
    depth = depth[order]
    counts = np.bincount(img, minlength=num)
    start = np.cumsum(counts) - counts
    ranges = np.full((num, 2), -1.0)
    has = counts > 0
    # C++ size_t(n * p): truncation towards zero
    lo = start[has] + np.floor(counts[has] * MIN_PERCENTILE).astype(int)
    hi = start[has] + np.floor(counts[has] * MAX_PERCENTILE).astype(int)
    ranges[has, 0] = depth[lo] * (1.0 - STRETCH)
    ranges[has, 1] = depth[hi] * (1.0 + STRETCH)
    return ranges, counts


def _element_pairs(model: MvsModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All pairs of track elements of one point in two different images:
    (image a, image b, point), each (K,)."""
    order = np.argsort(model.el_point, kind="stable")
    point, image = model.el_point[order], model.el_image[order]
    longest = int(np.bincount(point).max()) if len(point) else 0
    pa, pb, pp = [], [], []
    # one pass per offset inside a track (tracks are short), vectorised
    for k in range(1, longest):
        same = (point[:-k] == point[k:]) & (image[:-k] != image[k:])
        pa.append(image[:-k][same])
        pb.append(image[k:][same])
        pp.append(point[:-k][same])
    if not pa:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0, int)
    return np.concatenate(pa), np.concatenate(pb), np.concatenate(pp)


def _triangulation_angle(C1: np.ndarray, C2: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(K,) angle (rad) at points X (K, 3) between the rays to C1 and C2
    (K, 3), the smaller of it and its supplement, as COLMAP's."""
    b2 = np.sum((C1 - C2) ** 2, axis=1)
    r1 = np.sum((X - C1) ** 2, axis=1)
    r2 = np.sum((X - C2) ** 2, axis=1)
    den = 2.0 * np.sqrt(r1 * r2)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.where(den > 0, (r1 + r2 - b2) / den, 1.0)
    angle = np.abs(np.arccos(np.clip(cos, -1.0, 1.0)))
    return np.minimum(angle, np.pi - angle)


def pair_statistics(model: MvsModel) -> tuple[np.ndarray, np.ndarray]:
    """Shared points and triangulation angle of every image pair.

    Returns
    -------
    shared : (I, I) int, points seen by both images.
    angle : (I, I) float, rad, the 75th percentile of the pair's
        triangulation angles (COLMAP's nearest-rank percentile); NaN where
        the pair shares no point.
    """
    num = len(model.names)
    a, b, p = _element_pairs(model)
    shared = np.zeros((num, num), int)
    np.add.at(shared, (a, b), 1)
    np.add.at(shared, (b, a), 1)
    angle = np.full((num, num), np.nan)
    if len(a) == 0:
        return shared, angle
    C = model.centers
    ang = _triangulation_angle(C[a], C[b], model.xyz[p])
    key = np.minimum(a, b) * num + np.maximum(a, b)
    order = np.lexsort((ang, key))
    key, ang = key[order], ang[order]
    keys, start, n = np.unique(key, return_index=True, return_counts=True)
    # std::round: halves away from zero
    pick = start + np.floor(ANGLE_PERCENTILE / 100.0 * (n - 1) + 0.5).astype(int)
    i, j = keys // num, keys % num
    angle[i, j] = angle[j, i] = ang[pick]
    return shared, angle


def source_images(
    shared: np.ndarray,
    angle: np.ndarray,
    max_num: int,
    min_angle_rad: float,
    keep: np.ndarray | None = None,
) -> list[np.ndarray]:
    """``__auto__`` source images of every image: those sharing points with
    it under at least ``min_angle_rad``, most shared points first, at most
    ``max_num``; only images with ``keep`` (I,) bool as candidates."""
    num = len(shared)
    keep = np.ones(num, bool) if keep is None else keep
    with np.errstate(invalid="ignore"):
        ok = (shared > 0) & (np.nan_to_num(angle, nan=-1.0) >= min_angle_rad)
    ok &= keep[None, :]
    np.fill_diagonal(ok, False)
    out = []
    for i in range(num):
        cand = np.flatnonzero(ok[i])
        cand = cand[np.argsort(-shared[i, cand], kind="stable")]
        out.append(cand[:max_num])
    return out
