"""The 2D-3D correspondences of a missing image: pycolmap SIFT against
registered neighbours, verified pairs, the neighbours' SfM track points."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from obliq_colmap.images import IMAGE_EXTENSIONS, image_problem

from .options import ImageVPs, RelativeVPOptions
from .vps import image_vps, rotation_candidates

logger = logging.getLogger(__name__)


@dataclass
class Features:
    """pycolmap SIFT of one image: its keypoints, descriptors, and (N, 2)
    COLMAP pixel positions."""

    keypoints: pycolmap.FeatureKeypoints
    descriptors: pycolmap.FeatureDescriptors
    xy: np.ndarray

    def subset(self, index: np.ndarray) -> Features:
        """The features at the (K,) integer ``index``."""
        kp = pycolmap.FeatureKeypoints([self.keypoints[int(i)] for i in index])
        data = np.ascontiguousarray(np.asarray(self.descriptors.data)[index])
        desc = pycolmap.FeatureDescriptors(self.descriptors.type, data)
        return Features(kp, desc, self.xy[index])


def read_gray(path: Path) -> np.ndarray | None:
    """(H, W) uint8 grey image read as COLMAP reads it (pycolmap's Bitmap:
    the keypoints then equal an SfM model's from pycolmap), or None (see
    :func:`image_problem` for why)."""
    if image_problem(path) is not None:  # a truncated JPEG decodes grey
        return None
    bitmap = pycolmap.Bitmap.read(str(path), False)
    if bitmap is None:
        return None
    return np.ascontiguousarray(bitmap.to_array())


def sift(
    gray: np.ndarray, num_threads: int = 1, max_num_features: int = 8192
) -> Features:
    """pycolmap SIFT (COLMAP's defaults) on a (H, W) uint8 image. A lower
    ``max_num_features`` keeps the coarsest keypoints: a subset of the
    default's, at the same positions."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = num_threads
    opts.sift.max_num_features = max_num_features
    extractor = pycolmap.FeatureExtractor.create(opts)
    kp, desc = extractor.extract_from_uint8_array(gray)
    xy = np.array([[k.x, k.y] for k in kp], float).reshape(-1, 2)
    return Features(kp, desc, xy)


def verified_matches(
    a: Features,
    b: Features,
    camera_a: pycolmap.Camera,
    camera_b: pycolmap.Camera,
    seed: int = 0,
) -> np.ndarray:
    """(M, 2) indices (into a, into b) of pycolmap's SIFT matches that its
    two-view geometry (E / F / H, RANSAC) keeps."""
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = 1
    matcher = pycolmap.FeatureMatcher.create(opts)
    m = np.asarray(
        matcher.match(a.keypoints, a.descriptors, b.keypoints, b.descriptors)
    )
    if len(m) < 8:
        return np.zeros((0, 2), int)
    tvg = pycolmap.TwoViewGeometryOptions()
    tvg.ransac.random_seed = seed
    geom = pycolmap.estimate_two_view_geometry(
        camera_a, a.xy, camera_b, b.xy, m.astype(np.uint32), tvg
    )
    return np.asarray(geom.inlier_matches, int).reshape(-1, 2)


def track_correspondences(
    image: pycolmap.Image,
    neighbour_xy: np.ndarray,
    max_distance_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The neighbour's keypoints (K, 2) that are observations of the model's
    3D points: (K,) bool and (K,) point3D ids (-1 where not)."""
    obs = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
    ids = np.full(len(neighbour_xy), -1, np.int64)
    if not obs or len(neighbour_xy) == 0:
        return ids >= 0, ids
    xy = np.array([o[0] for o in obs])
    pid = np.array([o[1] for o in obs], np.int64)
    d, k = cKDTree(xy).query(neighbour_xy, distance_upper_bound=max_distance_px)
    hit = np.isfinite(d)
    ids[hit] = pid[k[hit]]
    return hit, ids


# --------------------------------------------------------------------------
# The stage: every missing image of a model
# --------------------------------------------------------------------------

#: file suffixes taken for images in ``--image_path``


def missing_images(rec: pycolmap.Reconstruction, image_path: Path) -> list[str]:
    """Names (relative to ``image_path``, '/'-separated, as COLMAP names
    them) of the image files that the model has no registered image of."""
    image_path = Path(image_path)
    have = {rec.images[i].name for i in rec.reg_image_ids()}
    files = (
        p.relative_to(image_path).as_posix()
        for p in image_path.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
    )
    return sorted(f for f in files if f not in have)


@dataclass
class _Neighbour:
    """A registered image's SIFT features that are observations of model
    points (only those can give 2D-3D correspondences; matching against
    them alone is 3-4x faster) and their (K,) point3D ids."""

    image_id: int
    features: Features
    point3D_ids: np.ndarray


class RegisteredImages:
    """Features and VPs of the registered images, computed when first asked."""

    def __init__(self, rec, image_path: Path, options: RelativeVPOptions) -> None:
        self.rec, self.image_path, self.options = rec, Path(image_path), options
        self._n: dict[int, _Neighbour | None] = {}
        self._vps: dict[int, ImageVPs] = {}

    def neighbour(self, image_id: int) -> _Neighbour | None:
        if image_id not in self._n:
            image = self.rec.images[image_id]
            gray = read_gray(self.image_path / image.name)
            if gray is None:
                logger.warning("%s: cannot read it; not a neighbour", image.name)
                self._n[image_id] = None
                return None
            feats = sift(gray)
            hit, pid = track_correspondences(
                image, feats.xy, self.options.max_track_distance_px
            )
            keep = np.flatnonzero(hit)
            self._n[image_id] = _Neighbour(image_id, feats.subset(keep), pid[keep])
        return self._n[image_id]

    def vps(self, image_id: int) -> ImageVPs:
        if image_id not in self._vps:
            image = self.rec.images[image_id]
            gray = read_gray(self.image_path / image.name)
            self._vps[image_id] = (
                ImageVPs("unreadable", "cannot read the image")
                if gray is None
                else image_vps(gray, image.camera, self.options)
            )
        return self._vps[image_id]

    def world_directions(self, image_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """The horizontal VPs of ``image_ids`` in the model frame (rows
        ``R^T h``): (P, 3) directions and (P,) supporting segment counts."""
        dirs, weights = [np.zeros((0, 3))], [np.zeros(0)]
        for image_id in image_ids:
            v = self.vps(image_id)
            if v.status == "ok":
                R = self.rec.images[image_id].cam_from_world().rotation.matrix()
                dirs.append(v.horizontal.directions @ R)
                weights.append(v.horizontal.num_inliers.astype(float))
        return np.concatenate(dirs), np.concatenate(weights)


def pool_directions(
    h: np.ndarray,
    pool: np.ndarray,
    weights: np.ndarray,
    down: np.ndarray,
    tolerance_deg: float,
) -> np.ndarray:
    """(J, 3) horizontal directions ``h`` each replaced by the weighted axial
    mean of the (P, 3) ``pool`` directions within ``tolerance_deg`` of it
    (sign-free), all projected on the plane perpendicular to the (3,) unit
    ``down``; a direction with no such pool member is kept."""
    e1 = np.cross(down, [1.0, 0.0, 0.0] if abs(down[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(down, e1)
    phi_h = np.arctan2(h @ e2, h @ e1)  # (J,)
    phi_p = np.arctan2(pool @ e2, pool @ e1)  # (P,)
    # axial data: angles doubled, so that h and -h are one direction
    diff = np.angle(np.exp(2j * (phi_p[None] - phi_h[:, None]))) / 2  # (J, P)
    w = np.where(np.abs(diff) < np.radians(tolerance_deg), weights[None], 0.0)
    mean = phi_h + np.angle(np.sum(w * np.exp(2j * diff), axis=1)) / 2
    return np.cos(mean)[:, None] * e1 + np.sin(mean)[:, None] * e2


def neighbour_order(rec, name: str, missing: list[str]) -> list[int]:
    """Registered image ids nearest to ``name`` in the sorted order of all
    names first (a sequence's neighbours; ties: the earlier image)."""
    ids = list(rec.reg_image_ids())
    names = sorted({rec.images[i].name for i in ids} | set(missing))
    pos = {n: k for k, n in enumerate(names)}
    return sorted(ids, key=lambda i: (abs(pos[rec.images[i].name] - pos[name]),
                                      pos[rec.images[i].name]))  # fmt: skip


@dataclass
class Correspondences:
    """An image's keypoints matched to model points through its neighbours.

    ``xy`` (N, 2) COLMAP pixels, ``rays`` (N, 3) camera-frame rays (z = 1,
    distortion removed), ``X`` (N, 3) model points, ``point3D_ids`` (N,);
    ``neighbours`` the image ids matched, most correspondences first, and
    ``num_matches`` their verified match counts.
    """

    xy: np.ndarray
    rays: np.ndarray
    X: np.ndarray
    point3D_ids: np.ndarray
    neighbours: list[int]
    num_matches: list[int]


def correspondences_2d3d(
    rec: pycolmap.Reconstruction,
    features: Features,
    camera: pycolmap.Camera,
    neighbour_ids: list[int],
    cache: RegisteredImages,
    options: RelativeVPOptions,
) -> Correspondences:
    """2D-3D correspondences of an image (its ``features``, ``camera``) by
    pycolmap SIFT matches to each neighbour's keypoints that are SfM
    observations of model points. One 3D point per keypoint and one keypoint
    per 3D point (the best neighbour's first)."""
    per_nb = []
    for image_id in neighbour_ids:
        nb = cache.neighbour(image_id)
        if nb is None:
            continue
        image = rec.images[image_id]
        m = verified_matches(nb.features, features, image.camera, camera, options.seed)
        per_nb.append((image_id, len(m), m[:, 1], nb.point3D_ids[m[:, 0]]))
    per_nb.sort(key=lambda x: -len(x[2]))
    kp = np.concatenate([p[2] for p in per_nb] + [np.zeros(0, int)])
    pid = np.concatenate([p[3] for p in per_nb] + [np.zeros(0, np.int64)])
    keep = np.sort(np.unique(kp, return_index=True)[1])  # unique keypoints
    kp, pid = kp[keep], pid[keep]
    keep = np.sort(np.unique(pid, return_index=True)[1])  # then unique points
    kp, pid = kp[keep], pid[keep]
    xy = features.xy[kp]
    rays = np.column_stack([camera.cam_from_img(xy), np.ones(len(xy))])
    X = np.array([rec.points3D[int(p)].xyz for p in pid]).reshape(-1, 3)
    return Correspondences(
        xy, rays, X, pid, [p[0] for p in per_nb], [p[1] for p in per_nb]
    )


def neighbour_candidates(
    rec: pycolmap.Reconstruction,
    vps: ImageVPs,
    neighbour_ids: list[int],
    down_world: np.ndarray,
    cache: RegisteredImages,
    pool_ids: list[int] | None = None,
) -> list[tuple[int, np.ndarray]]:
    """Per neighbour with horizontal VPs (in the given order): its id and the
    (C, 3, 3) rotation candidates of the image with ``vps``
    (:func:`rotation_candidates`, its horizontal VPs rotated into the model
    frame by its pose, each refined by :func:`pool_directions` over the
    registered images ``pool_ids``)."""
    options = cache.options
    pool, weights = cache.world_directions(pool_ids or [])
    out = []
    for image_id in neighbour_ids:
        nvps = cache.vps(image_id)
        if nvps.status != "ok":
            logger.debug("neighbour %s: %s", rec.images[image_id].name, nvps.message)
            continue
        R_nb = rec.images[image_id].cam_from_world().rotation.matrix()
        h_world = nvps.horizontal.directions @ R_nb  # rows: R^T h
        if len(pool):
            h_world = pool_directions(
                h_world, pool, weights, down_world, options.pool_tolerance_deg
            )
        out.append(
            (image_id, rotation_candidates(
                vps.down, vps.horizontal.directions, down_world, h_world
            ))
        )  # fmt: skip
    return out
