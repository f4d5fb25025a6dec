"""Images that SfM left out, placed from vanishing points (MetropoGIS 3.2.2).

An image in ``--image_path`` that the SfM model does not hold gets its pose
from a registered neighbour:

1. **Its VP triplet.** Stage 1 (:func:`~obliq_colmap.vanishing.detect_vertical_vp`,
   a terrestrial prior) gives the vertical direction ``d`` in the camera
   frame and the image's segments. The horizontal VPs are found by RANSAC
   over the other segments (:func:`horizontal_vps`): with ``d`` known, ONE
   segment is a hypothesis (the horizontal direction in the segment's
   interpretation plane, ``h = n x d``), and the segments whose lines pass
   near the VP ``K h`` support it. ``(h, d x h, d)`` is the image's
   orthogonal triplet; more facade directions give more triplets.
2. **The rotation** (:func:`rotation_candidates`): a horizontal direction of
   the new image and one of the neighbour's (rotated into the model frame
   by the neighbour's pose), with the model's down for ``d``, give
   ``cam_from_world``; each pairing and sign is a candidate (a facade seen
   from both sides, or its perpendicular, look alike). Candidates farther
   than ``max_rotation_from_reference_deg`` from the reference (the image's
   prior rotation where given, else the neighbour's) are dropped; the
   position step decides among the rest.
3. **The position** (:func:`centre_from_rotation`): SIFT (pycolmap) against
   the neighbours, the matches verified by pycolmap's two-view geometry, the
   neighbour's keypoints looked up among its points2D with a 3D point of the
   model. With the rotation known, one 2D-3D correspondence puts the centre
   on a line (the ray through the 3D point, 2 equations), so TWO are the
   minimal sample (4 equations for 3 unknowns; a linear least-squares
   solve). MetropoGIS gets by with one POI pair because its pair has no
   scale (a base direction, 2 DOF, plus a 1-D search along the ray for
   support); against a model's metric points the scale is fixed and one
   point leaves the centre free along its ray. RANSAC over pairs, every
   hypothesis at once; the winner refined on its inliers.

It needs a building with horizontal lines that the new image and a
neighbour both see (a facade or its perpendicular), and at least a few
matches whose neighbour keypoints are SfM track observations; it refuses
(``status`` not "placed", with a message) otherwise.

References
----------
A. Klaus, J. Bauer, K. Karner, K. Schindler, "MetropoGIS: a semi-automatic
city documentation system", PCV 2002, section 3.2.2.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from obliq_colmap.geometry import Camera, rotation_angle_deg
from obliq_colmap.images import image_problem
from obliq_colmap.vanishing import VanishingOptions, VPPrior, detect_vertical_vp

logger = logging.getLogger(__name__)

#: statuses of :class:`PlacedImage`
PLACEMENT_STATUSES = (
    "placed",
    "unreadable",
    "no_vertical_vp",
    "no_horizontal_vp",
    "no_matches",
    "no_consensus",
)


@dataclass(kw_only=True)
class RelativeVPOptions:
    """How a missing image is placed from VPs and a few matches."""

    # --- horizontal VPs (step 1) ---
    #: segments shorter than this are neither hypotheses nor support, px
    min_segment_length_px: float = 20.0
    #: a segment supports a VP when both its endpoints lie this close to the
    #: line through its midpoint and the VP, px (stage 1 uses 1 px; facade
    #: lines are shorter and noisier than building corners)
    inlier_threshold_px: float = 1.5
    #: segments this close (deg) to the vertical pencil or to the horizon
    #: line say nothing about a horizontal direction: left out
    exclude_near_deg: float = 3.0
    #: RANSAC hypotheses (one segment each), evaluated at once
    num_hypotheses: int = 1024
    #: a horizontal VP needs this many supporting segments
    min_horizontal_inliers: int = 12
    #: at most this many horizontal VPs per image, each at least
    #: ``min_separation_deg`` from the others
    max_horizontal_vps: int = 3
    min_separation_deg: float = 10.0
    # --- rotation (step 2) ---
    #: candidates farther than this from the reference rotation are dropped
    max_rotation_from_reference_deg: float = 60.0
    # --- matches and position (step 3) ---
    #: a neighbour's horizontal directions are refined by the same
    #: directions (within ``pool_tolerance_deg``) of up to this many
    #: registered images nearest in name order (0: the neighbour's alone);
    #: one image's VP heading scatters by 0.1-0.3 deg (Herz-Jesu, true poses)
    pool_images: int = 8
    pool_tolerance_deg: float = 1.0
    #: registered images matched against (nearest in name order first)
    max_neighbours: int = 4
    #: a neighbour's keypoint is its SfM observation within this distance, px
    #: (0 with pycolmap's own extraction of the same file)
    max_track_distance_px: float = 1.0
    #: RANSAC inlier threshold of the position, px
    ransac_threshold_px: float = 4.0
    #: hypotheses (pairs of correspondences) for the position, at most,
    #: scored on at most ``max_score_points`` of the correspondences (the
    #: (pairs x points x 3) array stays under 50 MB; the winner's inliers
    #: are counted on all)
    max_pairs: int = 2000
    max_score_points: int = 1000
    #: the position needs this many inlier correspondences, and this share
    #: of all (COLMAP's mapper: ``abs_pose_min_inlier_ratio`` 0.25): a wrong
    #: rotation candidate still gathers a few inliers among thousands
    min_inliers: int = 6
    min_inlier_ratio: float = 0.25
    seed: int = 0


@dataclass
class HorizontalVPs:
    """An image's horizontal VPs: (K, 3) unit directions in the camera frame
    (perpendicular to the vertical), (K,) supporting segment counts and
    (K, N) inlier masks over the segments given."""

    directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    num_inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))


@dataclass
class ImageVPs:
    """One image's VP triplet(s): ``down`` (3,) the world's down in the camera
    frame (None: no vertical VP) and its horizontal VPs."""

    status: str
    message: str
    down: np.ndarray | None = None
    horizontal: HorizontalVPs = field(default_factory=HorizontalVPs)


@dataclass
class PlacedImage:
    """One missing image's fate. ``cam_from_world`` (3, 4) in the model frame
    when placed; ``points2D`` (M, 2) COLMAP pixels of its inlier keypoints and
    ``point3D_ids`` (M,) the model points they observe."""

    name: str
    status: str
    message: str
    cam_from_world: np.ndarray | None = None
    neighbour: str | None = None
    camera_id: int = -1
    num_matches: int = 0
    num_inliers: int = 0
    num_candidates: int = 0
    points2D: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def report(self) -> dict:
        return {
            "status": self.status,
            "message": self.message,
            "neighbour": self.neighbour,
            "num_matches": self.num_matches,
            "num_inliers": self.num_inliers,
            "num_rotation_candidates": self.num_candidates,
        }


# --------------------------------------------------------------------------
# Step 1: horizontal VPs
# --------------------------------------------------------------------------


def _plane_normals(endpoints: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals, camera frame, of the planes through the camera
    centre and each segment of (N, 2, 2) undistorted pixels."""
    ones = np.ones((len(endpoints), 1))
    a = np.concatenate([endpoints[:, 0], ones], 1)
    b = np.concatenate([endpoints[:, 1], ones], 1)
    n = np.cross(a, b) @ K  # the line l (N, 3); its plane's normal is K^T l
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _endpoint_distances(endpoints: np.ndarray, vps: np.ndarray) -> np.ndarray:
    """(M, N) largest distance (px) of each segment's endpoints to the line
    through its midpoint and each VP; VPs (M, 3) homogeneous (w = 0 legal)."""
    mid = np.concatenate([endpoints.mean(1), np.ones((len(endpoints), 1))], 1)
    lines = np.cross(mid[None], vps[:, None])  # (M, N, 3)
    lines /= np.maximum(np.linalg.norm(lines[..., :2], axis=2, keepdims=True), 1e-12)
    ab, c = lines[..., :2], lines[..., 2]
    d0 = np.abs(np.einsum("mnk,nk->mn", ab, endpoints[:, 0]) + c)
    d1 = np.abs(np.einsum("mnk,nk->mn", ab, endpoints[:, 1]) + c)
    return np.maximum(d0, d1)


def _refine_horizontal(
    normals: np.ndarray, weight: np.ndarray, basis: np.ndarray
) -> np.ndarray:
    """(3,) unit h in span(basis (3, 2)) minimising sum w (n . h)^2 over the
    (S, 3) plane normals: the smallest eigenvector of a 2 x 2 matrix."""
    a = normals @ basis  # (S, 2)
    M = (a * weight[:, None]).T @ a
    _, vec = np.linalg.eigh(M)
    h = basis @ vec[:, 0]
    return h / np.linalg.norm(h)


def horizontal_vps(
    endpoints: np.ndarray,
    K: np.ndarray,
    down: np.ndarray,
    options: RelativeVPOptions,
    exclude: np.ndarray | None = None,
    rng: np.random.Generator | int | None = None,
) -> HorizontalVPs:
    """Horizontal VPs of an image whose vertical is known.

    Parameters
    ----------
    endpoints : (N, 2, 2) segment endpoints, undistorted COLMAP pixels.
    K : (3, 3) pinhole matrix of those pixels.
    down : (3,) unit world down in the camera frame (stage 1).
    exclude : (N,) bool, segments already explained (the vertical pencil).
    rng : Generator or seed (default ``options.seed``).

    Returns
    -------
    HorizontalVPs, strongest first; empty when no direction has
    ``min_horizontal_inliers`` segments.
    """
    rng = np.random.default_rng(options.seed if rng is None else rng)
    endpoints = np.asarray(endpoints, float).reshape(-1, 2, 2)
    n_all = len(endpoints)
    out = HorizontalVPs(inliers=np.zeros((0, n_all), bool))
    down = np.asarray(down, float) / np.linalg.norm(down)
    lengths = np.linalg.norm(endpoints[:, 1] - endpoints[:, 0], axis=1)
    normals = _plane_normals(endpoints, K)
    nd = np.abs(normals @ down)
    near = np.sin(np.radians(options.exclude_near_deg))
    # |n.d| ~ 0: the plane holds the vertical (a vertical segment, any h
    # fits it); |n.d| ~ 1: the segment lies on the horizon line, through
    # every horizontal VP. Neither can choose a horizontal direction.
    usable = (lengths >= options.min_segment_length_px) & (nd > near)
    usable &= nd < np.cos(np.radians(options.exclude_near_deg))
    if exclude is not None:
        usable &= ~np.asarray(exclude, bool)
    # an orthonormal basis of the plane perpendicular to down
    e1 = np.cross(down, [1.0, 0.0, 0.0] if abs(down[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(down, e1)], 1)  # (3, 2)
    found, counts, masks = [], [], []
    free = usable.copy()
    thr = options.inlier_threshold_px
    for _ in range(options.max_horizontal_vps):
        idx = np.flatnonzero(free)
        if len(idx) < options.min_horizontal_inliers:
            break
        # hypotheses: one segment each, drawn by length (long ones first)
        m = min(options.num_hypotheses, len(idx))
        p = lengths[idx] / lengths[idx].sum()
        hyp = rng.choice(idx, size=m, replace=False, p=p)
        h = np.cross(normals[hyp], down)  # (M, 3), perpendicular to down
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        dist = _endpoint_distances(endpoints[idx], h @ K.T)  # (M, S)
        # truncated quadratic (MSAC), weighted by length
        score = (np.clip(1.0 - (dist / thr) ** 2, 0.0, None) * lengths[idx]).sum(1)
        best = h[int(np.argmax(score))]
        for _ in range(3):  # refit on the inliers, re-score
            inl = idx[_endpoint_distances(endpoints[idx], (K @ best)[None])[0] < thr]
            if len(inl) < 2:
                break
            best = _refine_horizontal(normals[inl], lengths[inl] ** 2, basis)
        inl = idx[_endpoint_distances(endpoints[idx], (K @ best)[None])[0] < thr]
        if len(inl) < options.min_horizontal_inliers:
            break
        free[inl] = False
        # a pencil close to one already found is its spill-over, not a facade
        if found:
            cos = np.abs(np.array(found) @ best).max()
            if np.degrees(np.arccos(min(cos, 1.0))) < options.min_separation_deg:
                continue
        mask = np.zeros(n_all, bool)
        mask[inl] = True
        found.append(best)
        counts.append(len(inl))
        masks.append(mask)
    if found:
        out = HorizontalVPs(np.array(found), np.array(counts), np.array(masks))
    return out


def image_vps(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    options: RelativeVPOptions,
    vanishing: VanishingOptions | None = None,
) -> ImageVPs:
    """Stage 1 (terrestrial prior) and :func:`horizontal_vps` on one image.

    gray : (H, W) uint8 image; camera : its intrinsics (distortion removed
    from the segments by stage 1).
    """
    cam = Camera(
        camera.model.name, camera.width, camera.height, np.asarray(camera.params)
    )
    res = detect_vertical_vp(
        gray,
        vanishing or VanishingOptions(seed=options.seed),
        camera=cam,
        prior=VPPrior.none(),
    )
    if res.status != "ok" or res.vertical_direction is None:
        return ImageVPs("no_vertical_vp", f"no vertical VP ({res.message})")
    down = np.asarray(res.vertical_direction, float)
    hv = horizontal_vps(
        res.segments.endpoints, cam.K, down, options, exclude=res.inliers
    )
    if len(hv.directions) == 0:
        return ImageVPs(
            "no_horizontal_vp",
            f"no horizontal VP with >= {options.min_horizontal_inliers} segments",
            down,
        )
    return ImageVPs("ok", f"{len(hv.directions)} horizontal VP(s)", down, hv)


# --------------------------------------------------------------------------
# Step 2: the rotation
# --------------------------------------------------------------------------


def _triads(down: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(K, 3, 3) right-handed frames with columns (h, down x h, down) for
    (K, 3) directions h perpendicular to the unit (3,) down."""
    h = h - (h @ down)[:, None] * down
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    return np.stack([h, np.cross(down, h), np.broadcast_to(down, h.shape)], 2)


def rotation_candidates(
    down_cam: np.ndarray,
    h_cam: np.ndarray,
    down_world: np.ndarray,
    h_world: np.ndarray,
) -> np.ndarray:
    """All ``cam_from_world`` rotations that take the world's down to
    ``down_cam`` and one of the world's horizontal directions to one of the
    camera's, either sign.

    down_cam (3,), h_cam (I, 3): the new image's vertical and horizontal
    directions (camera frame); down_world (3,), h_world (J, 3): the same in
    the model frame (from the neighbour). Returns (2 I J, 3, 3).
    """
    h_cam = np.concatenate([h_cam, -h_cam])  # a VP's direction has no sign
    C = _triads(down_cam / np.linalg.norm(down_cam), h_cam)  # (2I, 3, 3)
    W = _triads(down_world / np.linalg.norm(down_world), h_world)  # (J, 3, 3)
    # R W_j = C_i: the world frame's axes onto the camera's
    R = np.einsum("iab,jcb->ijac", C, W)
    return R.reshape(-1, 3, 3)


# --------------------------------------------------------------------------
# Step 3: the position
# --------------------------------------------------------------------------


def _centres(P: np.ndarray, X: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Least-squares points nearest to lines: (H, S, 3, 3) projectors
    ``I - w w^T`` across each line, (H, S, 3) points on them, (H, S)
    weights; (H, 3) centres (NaN where the lines are parallel)."""
    A = np.einsum("hs,hsab->hab", weight, P)
    b = np.einsum("hs,hsab,hsb->ha", weight, P, X)
    ok = np.abs(np.linalg.det(A)) > 1e-12 * np.einsum("hii->h", A) ** 3
    c = np.full(b.shape, np.nan)
    if ok.any():
        c[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return c


def _reprojection_px(
    R: np.ndarray, centre: np.ndarray, rays: np.ndarray, X: np.ndarray, f: float
) -> np.ndarray:
    """(H, N) errors (px, focal ``f``) of (N, 3) points X seen along the
    (N, 3) camera rays (z = 1) from (H, 3) centres; inf behind the camera."""
    Xc = (X[None] - centre[:, None]) @ R.T  # (H, N, 3)
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = f * np.linalg.norm(Xc[..., :2] / z[..., None] - rays[None, :, :2], axis=2)
    return np.where(z > 0, err, np.inf)


def centre_from_rotation(
    R: np.ndarray,
    rays: np.ndarray,
    X: np.ndarray,
    focal_px: float,
    options: RelativeVPOptions,
    rng: np.random.Generator | int | None = None,
) -> tuple[np.ndarray | None, np.ndarray]:
    """The camera centre with ``cam_from_world`` rotation R known.

    Parameters
    ----------
    R : (3, 3) cam_from_world rotation.
    rays : (N, 3) camera-frame rays (normalised coordinates, z = 1) of the
        image's keypoints.
    X : (N, 3) the model points they observe.
    focal_px : pixels per unit of normalised coordinates (for the threshold).

    Returns
    -------
    centre (3,) in the model frame (None: fewer than ``min_inliers`` or
    than ``min_inlier_ratio`` of N) and the (N,) inlier mask.

    Each correspondence holds the centre on the line through X_j along the
    world ray ``R^T rays_j``; two such lines (4 equations) give the centre
    as their least-squares meeting point. All pairs at once (at most
    ``max_pairs``), scored by inliers; the winner refit on its inliers with
    weights ``1 / range^2`` (distance to a line over the range is the
    angular, i.e. pixel, error), three times.
    """
    rng = np.random.default_rng(options.seed if rng is None else rng)
    n = len(X)
    inl = np.zeros(n, bool)
    if n < max(2, options.min_inliers):
        return None, inl
    w = rays @ R  # world directions (rows: R^T r)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    P = np.eye(3)[None] - w[:, :, None] * w[:, None, :]  # (N, 3, 3)
    i, j = np.triu_indices(n, 1)
    if len(i) > options.max_pairs:
        pick = rng.choice(len(i), options.max_pairs, replace=False)
        i, j = i[pick], j[pick]
    pairs = np.stack([i, j], 1)  # (H, 2)
    c = _centres(P[pairs], X[pairs], np.ones(pairs.shape))
    good = np.isfinite(c).all(1)
    if not good.any():
        return None, inl
    sub = np.arange(n)
    if n > options.max_score_points:
        sub = rng.choice(n, options.max_score_points, replace=False)
    err = _reprojection_px(R, c[good], rays[sub], X[sub], focal_px)
    ninl = (err < options.ransac_threshold_px).sum(1)
    best = c[good][int(np.argmax(ninl))]
    for _ in range(3):
        inl = _reprojection_px(R, best[None], rays, X, focal_px)[0]
        inl = inl < options.ransac_threshold_px
        if inl.sum() < 2:
            break
        rng_sq = np.sum((X[inl] - best) ** 2, axis=1)
        refit = _centres(P[inl][None], X[inl][None], (1.0 / rng_sq)[None])[0]
        if not np.isfinite(refit).all():
            break
        best = refit
    inl = _reprojection_px(R, best[None], rays, X, focal_px)[0] < (
        options.ransac_threshold_px
    )
    if inl.sum() < max(options.min_inliers, options.min_inlier_ratio * n):
        return None, inl
    return best, inl


def place_with_rotations(
    candidates: np.ndarray,
    reference: np.ndarray,
    rays: np.ndarray,
    X: np.ndarray,
    focal_px: float,
    options: RelativeVPOptions,
) -> tuple[int, np.ndarray | None, np.ndarray, int]:
    """Among (C, 3, 3) rotation candidates within
    ``max_rotation_from_reference_deg`` of the (3, 3) reference, the one
    whose position has the most inliers.

    Returns (candidate index or -1, centre (3,) or None, (N,) inlier mask,
    number of candidates tried).
    """
    ang = np.atleast_1d(rotation_angle_deg(candidates, reference[None]))
    near = np.flatnonzero(ang <= options.max_rotation_from_reference_deg)
    best = (-1, None, np.zeros(len(X), bool))
    for k in near[np.argsort(ang[near])]:  # at most a few (2-8) candidates
        c, inl = centre_from_rotation(candidates[k], rays, X, focal_px, options)
        if c is not None and inl.sum() > best[2].sum():
            best = (int(k), c, inl)
    return (*best, len(near))


# --------------------------------------------------------------------------
# Matches against the model (pycolmap SIFT)
# --------------------------------------------------------------------------


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


def sift(gray: np.ndarray, num_threads: int = 1) -> Features:
    """pycolmap SIFT (COLMAP's defaults) on a (H, W) uint8 image."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = num_threads
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
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"})


def missing_images(rec: pycolmap.Reconstruction, image_path: Path) -> list[str]:
    """Names (relative to ``image_path``, '/'-separated, as COLMAP names
    them) of the image files that the model has no registered image of."""
    image_path = Path(image_path)
    have = {rec.images[i].name for i in rec.reg_image_ids()}
    files = (
        p.relative_to(image_path).as_posix()
        for p in image_path.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
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


@dataclass
class MissingImage:
    """What placing an image needs: its camera (the model's camera of its
    size), its VPs and its 2D-3D correspondences."""

    name: str
    camera: pycolmap.Camera
    vps: ImageVPs
    correspondences: Correspondences
    #: registered images whose VPs refine the neighbours' directions
    pool_ids: list[int] = field(default_factory=list)


def prepare_image(
    rec: pycolmap.Reconstruction,
    image_path: Path,
    name: str,
    options: RelativeVPOptions,
    missing: list[str] | None = None,
    cache: RegisteredImages | None = None,
) -> MissingImage | PlacedImage:
    """The VPs and correspondences of image ``name`` (under ``image_path``),
    or a refusal (a :class:`PlacedImage` with its status and message).
    ``missing``: all names being added (the sequence order of the
    neighbours counts them too)."""
    cache = cache or RegisteredImages(rec, image_path, options)
    gray = read_gray(Path(image_path) / name)
    if gray is None:
        why = image_problem(Path(image_path) / name) or "cannot decode it"
        return PlacedImage(name, "unreadable", why)
    h, w = gray.shape
    cams = [c for c in rec.cameras.values() if (c.width, c.height) == (w, h)]
    if not cams:
        return PlacedImage(
            name, "unreadable", f"no camera of the model is {w} x {h} px"
        )
    camera = cams[0]
    vps = image_vps(gray, camera, options)
    if vps.status != "ok":
        return PlacedImage(name, vps.status, vps.message)
    order = neighbour_order(rec, name, missing or [name])
    corr = correspondences_2d3d(
        rec, sift(gray), camera, order[: options.max_neighbours], cache, options
    )
    if not corr.neighbours:
        return PlacedImage(name, "no_matches", "no readable neighbour")
    return MissingImage(name, camera, vps, corr, order[: options.pool_images])


def place_prepared(
    rec: pycolmap.Reconstruction,
    image: MissingImage,
    down_world: np.ndarray,
    options: RelativeVPOptions,
    cache: RegisteredImages,
    prior_cam_from_world: np.ndarray | None = None,
) -> PlacedImage:
    """Steps 2-3 of the module docstring for a prepared image.

    down_world : (3,) unit down direction in the model frame (the model's
        vertical from its images' VPs).
    prior_cam_from_world : (3, 3) the image's rough rotation in the model
        frame, if known: the reference that candidates are chosen near
        (else each neighbour's rotation).
    """
    name, corr = image.name, image.correspondences
    num_matches = int(sum(corr.num_matches))
    best_nb = rec.images[corr.neighbours[0]].name
    if len(corr.X) < options.min_inliers:
        return PlacedImage(
            name,
            "no_matches",
            f"{len(corr.X)} matches to model points through "
            f"{len(corr.neighbours)} neighbours (need {options.min_inliers})",
            neighbour=best_nb,
            num_matches=num_matches,
        )
    xy, rays, X, pid = corr.xy, corr.rays, corr.X, corr.point3D_ids
    focal = float(image.camera.mean_focal_length())
    found = neighbour_candidates(
        rec, image.vps, corr.neighbours, down_world, cache, image.pool_ids
    )
    if not found:
        return PlacedImage(
            name, "no_horizontal_vp", "no matched neighbour has a horizontal VP",
            neighbour=best_nb, num_matches=num_matches,
        )  # fmt: skip
    fail = None
    for image_id, cands in found:  # the best-matched neighbour first
        R_nb = rec.images[image_id].cam_from_world().rotation.matrix()
        ref = R_nb if prior_cam_from_world is None else prior_cam_from_world
        k, centre, inl, tried = place_with_rotations(
            cands, ref, rays, X, focal, options
        )
        if k < 0:
            fail = fail or PlacedImage(
                name,
                "no_consensus",
                f"no rotation of {tried} candidates (neighbour "
                f"{rec.images[image_id].name}) has {options.min_inliers} inliers "
                f"among {len(X)} matches to model points",
                neighbour=best_nb,
                num_matches=num_matches,
            )
            continue
        R = cands[k]
        return PlacedImage(
            name,
            "placed",
            f"{int(inl.sum())} / {len(X)} inliers, neighbour "
            f"{rec.images[image_id].name}, {tried} rotation candidates",
            cam_from_world=np.column_stack([R, -R @ centre]),
            neighbour=rec.images[image_id].name,
            camera_id=int(image.camera.camera_id),
            num_matches=num_matches,
            num_inliers=int(inl.sum()),
            num_candidates=tried,
            points2D=xy[inl],
            point3D_ids=pid[inl],
        )
    return fail


def place_image(
    rec: pycolmap.Reconstruction,
    image_path: Path,
    name: str,
    down_world: np.ndarray,
    options: RelativeVPOptions,
    prior_cam_from_world: np.ndarray | None = None,
    missing: list[str] | None = None,
    cache: RegisteredImages | None = None,
) -> PlacedImage:
    """The pose of one image that the model lacks (see the module docstring):
    :func:`prepare_image` then :func:`place_prepared`. ``rec`` is not
    changed (:func:`write_placed` adds the result)."""
    cache = cache or RegisteredImages(rec, image_path, options)
    prepared = prepare_image(rec, image_path, name, options, missing, cache)
    if isinstance(prepared, PlacedImage):
        return prepared
    return place_prepared(
        rec, prepared, down_world, options, cache, prior_cam_from_world
    )


def write_placed(rec: pycolmap.Reconstruction, placed: PlacedImage) -> int:
    """Add a placed image to ``rec`` (registered, its inlier keypoints as
    observations of their model points); its new image_id."""
    camera_id = placed.camera_id
    image_id = max(rec.images) + 1 if rec.images else 1
    image = pycolmap.Image(name=placed.name, camera_id=camera_id, image_id=image_id)
    image.points2D = pycolmap.Point2DList(
        [pycolmap.Point2D(np.asarray(xy, float)) for xy in placed.points2D]
    )
    R, t = placed.cam_from_world[:, :3], placed.cam_from_world[:, 3]
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
    rec.add_image_with_trivial_frame(image, pose)
    for k, pid in enumerate(placed.point3D_ids):
        rec.add_observation(int(pid), pycolmap.TrackElement(image_id, k))
    return image_id


def add_missing_images(
    rec: pycolmap.Reconstruction,
    image_path: Path,
    down_world: np.ndarray,
    options: RelativeVPOptions,
    progress: bool = True,
    priors: dict[str, np.ndarray] | None = None,
) -> dict[str, dict]:
    """Place every image under ``image_path`` that ``rec`` lacks and add
    those placed to ``rec`` (in place). Returns each image's report (its
    status and message); an image that cannot be placed is named in a
    warning with the reason and left out.

    down_world : (3,) unit down direction in ``rec``'s frame.
    priors : name -> (3, 3) rough cam_from_world rotation in ``rec``'s
        frame (INS); the rotation candidates are chosen near it instead of
        near the neighbour's.
    """
    from tqdm import tqdm

    missing = missing_images(rec, image_path)
    if not missing:
        logger.info("missing images: none (every image is in the model)")
        return {}
    cache = RegisteredImages(rec, image_path, options)
    placed_all = []
    bar = tqdm(missing, desc="missing images", disable=not progress or None)
    for name in bar:
        prior = None if priors is None else priors.get(name)
        placed = place_image(
            rec, image_path, name, down_world, options, prior, missing, cache
        )
        placed_all.append(placed)
        if placed.status == "placed":
            logger.info("%s: placed from VPs (%s)", name, placed.message)
        else:
            logger.warning("%s: not placed (%s): %s", name, placed.status,
                           placed.message)  # fmt: skip
    # added after all are placed: a placed image is no neighbour of another
    # (its pose rests on a few matches and one VP pair)
    for placed in placed_all:
        if placed.status == "placed":
            write_placed(rec, placed)
    n = sum(p.status == "placed" for p in placed_all)
    logger.info("missing images: %d of %d placed from VPs", n, len(missing))
    return {p.name: p.report() for p in placed_all}
