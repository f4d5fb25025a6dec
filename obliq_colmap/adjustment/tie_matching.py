"""SIFT features of the tie points and their matches (pycolmap), for
:mod:`obliq_colmap.adjustment.ties`."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from obliq_colmap.parallel import WorkerPool

if TYPE_CHECKING:
    from obliq_colmap.adjustment.tie_options import TiePointOptions

__all__ = ["extract_features", "match_pairs"]


_EXTRACTOR: dict[tuple[int, int], object] = {}


def _sift_arrays(args: tuple[np.ndarray | Path, int, int, int, int]):
    """SIFT of one image (an (H, W) uint8 array, or a path read here as
    stored, in grey), down-sampled to ``max_image_size``, from SIFT's
    ``first_octave``, as plain arrays (pycolmap's keypoints do not pickle):
    (K, 6) keypoints (x, y, a11, a12, a21, a22) in the down-sampled image,
    the (K, 128) uint8 descriptors, their type and the (2,) scales
    (down-sampled / full size, x and y: the rounded sizes make them differ,
    0.05 % at 2004 x 1336 -> 1000 x 667, 0.7 px at the bottom row). One
    extractor per process and setting."""
    img, max_image_size, max_num_features, first_octave, threads = args
    if not isinstance(img, np.ndarray):
        img = cv2.imread(str(img), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    scale = np.ones(2)
    s = min(1.0, max_image_size / max(img.shape))
    if s < 1.0:
        height, width = img.shape
        size = (round(width * s), round(height * s))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        scale = np.array([size[0] / width, size[1] / height])
    key = (max_num_features, first_octave)
    if key not in _EXTRACTOR:
        eo = pycolmap.FeatureExtractionOptions()
        eo.num_threads = threads
        eo.sift.max_num_features = max_num_features
        eo.sift.first_octave = first_octave
        _EXTRACTOR[key] = pycolmap.FeatureExtractor.create(eo, pycolmap.Device.cpu)
    kps, desc = _EXTRACTOR[key].extract_from_uint8_array(np.ascontiguousarray(img))
    k = np.array([(p.x, p.y, p.a11, p.a12, p.a21, p.a22) for p in kps], float)
    return k.reshape(-1, 6), np.asarray(desc.data, np.uint8), desc.type, scale


def _keypoints(k: np.ndarray) -> pycolmap.FeatureKeypoints:
    names = ("x", "y", "a11", "a12", "a21", "a22")
    return pycolmap.FeatureKeypoints(
        [
            pycolmap.FeatureKeypoint(**dict(zip(names, map(float, row), strict=True)))
            for row in k
        ]
    )


def extract_features(
    gray_images: Sequence[np.ndarray | Path], options: TiePointOptions
):
    """SIFT on each (H, W) uint8 image (or image file, read in the worker),
    down-sampled to ``max_image_size``
    (pycolmap's array entry point does not down-sample): a list of ((K, 2)
    full-resolution pixel coordinates, pycolmap keypoints in the down-sampled
    image, pycolmap descriptors, (2,) scales = down-sampled / full size, (K,)
    keypoint scales in full-resolution pixels: the square root of the
    determinant of SIFT's affine shape).

    With ``options.num_workers`` > 1 the images are shared out over so many
    processes (pycolmap's SIFT holds the GIL: threads do not help; measured
    on urban-101, 8 images: 4.3 s serial, 5.1 s in 2 threads)."""
    jobs = [
        (
            img,
            options.max_image_size,
            options.max_num_features,
            options.first_octave,
            options.num_threads,
        )
        for img in gray_images
    ]
    workers = options.num_workers if len(jobs) > 1 else 1
    with WorkerPool(workers, progress=None) as pool:
        found = pool.map(_sift_arrays, jobs, desc="tie points: SIFT")
    out = []
    for k, d, kind, scale in found:
        # COLMAP's pixel convention (corner at 0): scaling is a plain division
        size = np.sqrt(np.abs(k[:, 2] * k[:, 5] - k[:, 3] * k[:, 4]))
        out.append(
            (
                k[:, :2] / scale,
                _keypoints(k),
                pycolmap.FeatureDescriptors(kind, d),
                scale,
                size / float(np.mean(scale)),
            )
        )
    return out


def mutual_ratio_matches(
    a: np.ndarray, b: np.ndarray, max_ratio: float, max_angle: float = 0.7
) -> np.ndarray:
    """(m, 2) indices of the SIFT descriptors (rows of a and b, (n, 128))
    that are each other's nearest neighbour, each passing the ratio test
    (angle to the nearest < ``max_ratio`` x angle to the second) and at most
    ``max_angle`` (rad) apart: COLMAP's CPU matcher's rules (cross check,
    max_ratio, max_distance), one matrix product (5x faster than pycolmap's
    CPU matcher on urban-101, >= 95 % of its matches)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    A = a.astype(np.float32)
    B = b.astype(np.float32)
    A /= np.maximum(np.linalg.norm(A, axis=1, keepdims=True), 1e-12)
    B /= np.maximum(np.linalg.norm(B, axis=1, keepdims=True), 1e-12)
    cos = A @ B.T
    fwd = _ratio_best(cos, 1, max_ratio, max_angle)
    bwd = _ratio_best(cos, 0, max_ratio, max_angle)
    i = np.flatnonzero(fwd >= 0)
    mutual = bwd[fwd[i]] == i
    return np.column_stack([i[mutual], fwd[i][mutual]]).astype(np.int64)


def _ratio_best(
    S: np.ndarray, axis: int, max_ratio: float, max_angle: float
) -> np.ndarray:
    """Per row (``axis`` 1) or column (0) of the cosines ``S`` its best
    partner, or -1 where the ratio test (angles) or ``max_angle`` fails.

    The two largest by two max passes, the first one masked in place and
    put back: an argpartition per row cost 43 ms on ~2000 x 2000, these
    reductions 2 ms along the rows. Down the columns numpy's argmax walks
    the array column by column (34 ms on 2500 x 2500, 8x its max): there
    the best is the first row equal to its column's max."""
    top = np.argmax(S, axis=1) if axis == 1 else _first_argmax_down(S)
    k = np.arange(len(top))
    at = (k, top) if axis == 1 else (top, k)
    v1 = S[at].copy()
    S[at] = -np.inf
    v2 = np.max(S, axis=axis)
    S[at] = v1
    a1 = np.arccos(np.clip(v1, -1.0, 1.0))
    a2 = np.arccos(np.clip(v2, -1.0, 1.0))
    return np.where((a1 < max_ratio * a2) & (a1 <= max_angle), top, -1)


def _first_argmax_down(S: np.ndarray) -> np.ndarray:
    """``np.argmax(S, axis=0)`` of an (n, m) array without NaN: per column
    the first row that equals the column's max."""
    hit = np.flatnonzero(np.equal(S, S.max(axis=0)))  # row-major: rows ascending
    cols, first = np.unique(hit % S.shape[1], return_index=True)
    top = np.empty(S.shape[1], np.intp)
    top[cols] = hit[first] // S.shape[1]
    return top


def _scaled(camera: pycolmap.Camera, scale: np.ndarray | float) -> pycolmap.Camera:
    """A copy of ``camera`` for the image down-sampled by ``scale`` ((2,) x
    and y, or one for both)."""
    cam = pycolmap.Camera(
        model=camera.model,
        width=camera.width,
        height=camera.height,
        params=camera.params,
    )
    sx, sy = np.broadcast_to(np.asarray(scale, float), (2,))
    if sx != 1.0 or sy != 1.0:
        cam.rescale(round(camera.width * sx), round(camera.height * sy))
    return cam


def _pose_geometry(cam_i, cam_j, pose_i, pose_j) -> pycolmap.TwoViewGeometry:
    """The two-view geometry the registered poses imply (E, F, relative pose)."""
    rel = pose_j * pose_i.inverse()  # cam_j_from_cam_i
    t = rel.translation
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ rel.rotation.matrix()
    Ki, Kj = cam_i.calibration_matrix(), cam_j.calibration_matrix()
    geom = pycolmap.TwoViewGeometry()
    geom.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    geom.E = E
    geom.F = np.linalg.inv(Kj).T @ E @ np.linalg.inv(Ki)
    geom.cam2_from_cam1 = rel
    return geom


def match_pairs(
    features,
    cameras: Sequence[pycolmap.Camera],
    poses: Sequence[pycolmap.Rigid3d],
    pairs: Sequence[tuple[int, int]],
    options: TiePointOptions,
) -> dict[tuple[int, int], np.ndarray]:
    """Verified matches per pair: (m, 2) feature indices.

    Default: the mutual ratio-test matches (:func:`mutual_ratio_matches`),
    then the inliers of pycolmap's estimated two-view geometry
    (uncalibrated: the cameras' focal lengths not trusted), the pairs
    shared over ``options.num_threads`` threads. ``guided_matching``:
    pycolmap's guided matching under the two-view geometry of the
    registered poses (SIFT's ratio test alone keeps ~20 true matches per
    pair of the synthetic renders; within the epipolar band, ~140).
    """
    mo = pycolmap.FeatureMatchingOptions()
    mo.use_gpu = False
    mo.num_threads = options.num_threads
    mo.sift.max_ratio = options.max_ratio
    matcher = pycolmap.FeatureMatcher.create(mo, pycolmap.Device.cpu)
    small = [_scaled(c, f[3]) for c, f in zip(cameras, features, strict=True)]
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.max_num_trials = options.max_num_trials
    verify.ransac.random_seed = options.random_seed
    # Verified without the focal lengths (a fundamental matrix, as COLMAP
    # does for a camera without a prior focal length): the per-image poses'
    # cameras may be several per cent off and lack the lens' distortion,
    # which a calibrated (essential) model does not absorb (houses-102:
    # 518 points against 6,124 with the true cameras).
    free = []
    for c in small:
        c = _scaled(c, 1.0)
        c.has_prior_focal_length = False
        free.append(c)
    # the keypoints' positions in the down-sampled images, once per image
    small_xy = [f[0] * f[3] for f in features]

    def verified(pair: tuple[int, int]) -> np.ndarray | None:
        i, j = pair
        ki, di = features[i][1:3]
        kj, dj = features[j][1:3]
        if options.guided_matching:
            geom = _pose_geometry(small[i], small[j], poses[i], poses[j])
            err = options.max_epipolar_error_px
            matcher.match_guided(err, ki, di, small[i], kj, dj, small[j], geom)
        else:
            m = mutual_ratio_matches(di.data, dj.data, options.max_ratio)
            if len(m) < 16:
                return None
            geom = pycolmap.estimate_two_view_geometry(
                free[i], small_xy[i], free[j], small_xy[j], m.astype(np.uint32), verify
            )
        inl = np.asarray(geom.inlier_matches).reshape(-1, 2)
        return inl.astype(np.int64) if len(inl) >= 16 else None

    # pycolmap's two-view estimation releases the GIL: threads share the
    # pairs (the guided matcher is one object: one thread).
    threads = 1 if options.guided_matching else max(1, options.num_threads)
    with ThreadPoolExecutor(threads) as pool:
        found = list(
            tqdm(
                pool.map(verified, pairs),
                total=len(pairs),
                desc="tie points: matching",
                disable=None,
            )
        )
    return {
        pair: inl for pair, inl in zip(pairs, found, strict=True) if inl is not None
    }
