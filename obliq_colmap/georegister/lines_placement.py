"""The automatic mode's placement for level (terrestrial) cameras: all
images' vertical segments against the map's corners at once
(:mod:`.block_lines`), started from the priors' similarity; the result in
the form :func:`~.run_automatic.georegister_automatic` takes from stage 2's
placement (the similarity, the images, their rays, the pairs and each
image's pairs for the map rows)."""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from obliq_colmap.cadastre import Cadastre
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import Camera, Pose, rotation_z

from .automatic import Rays, fit_block, segment_rays
from .block_lines import (
    BlockLinesOptions,
    LinesFit,
    PriorSimilarity,
    best_similarities,
    candidate_pairs,
    corners_seen,
    heading_from_rotations,
    nearest_pairs,
    pair_sd_deg,
    prior_similarity,
)
from .map_rows import ImagePairs
from .options import GeoregisterOptions
from .similarity import Similarity
from .vertical import ImageVertical, ModelVertical

logger = logging.getLogger(__name__)


def _camera(rec: pycolmap.Reconstruction, image_id: int) -> Camera:
    c = rec.images[image_id].camera
    return Camera(c.model.name, c.width, c.height, np.asarray(c.params, float))


def _model_rays(
    rec: pycolmap.Reconstruction, images: list[ImageVertical]
) -> tuple[Rays, np.ndarray]:
    """All images' segments as rays of the upright model, and (R,) each
    ray's segment index in its image."""
    origins, bearings, image, segment, length = [], [], [], [], []
    for k, im in enumerate(images):
        pose = rec.images[im.image_id].cam_from_world()
        c = rec.images[im.image_id].projection_center()
        o, b = segment_rays(im.segments, im.K, pose.rotation.matrix(), c)
        origins.append(np.repeat(o[None], len(b), axis=0))
        bearings.append(b)
        image.append(np.full(len(b), k))
        segment.append(np.arange(len(b)))
        length.append(np.linalg.norm(im.segments[:, 1] - im.segments[:, 0], axis=1))
    cat = [np.concatenate(v) for v in (origins, bearings, image, segment, length)]
    return Rays(cat[0], cat[1], cat[2], cat[4]), cat[3]


def _seen(
    rec: pycolmap.Reconstruction,
    images: list[ImageVertical],
    cad: Cadastre,
    scale: float,
    theta: float,
    t: np.ndarray,
    z: float,
    margin_deg: float,
    options: BlockLinesOptions,
) -> list[np.ndarray]:
    """Per image the corners in sight of its camera placed by the similarity
    ``map_xy = scale R(theta) model_xy + t`` (heights: ``z`` + the model's
    scaled; only the camera's vertical extent matters)."""
    Rz = rotation_z(theta)
    out = []
    for im in images:
        image = rec.images[im.image_id]
        c_m = image.projection_center()
        centre = np.r_[scale * (Rz[:2, :2] @ c_m[:2]) + t, z + scale * c_m[2]]
        R = image.cam_from_world().rotation.matrix() @ Rz.T
        camera = _camera(rec, im.image_id)
        margin = camera.K[0, 0] * np.tan(np.radians(min(margin_deg, 30.0)))
        pose = Pose.from_center(R, centre)
        out.append(corners_seen(cad, camera, pose, options.max_range_m, margin))
    return out


def _image_pairs(
    images: list[ImageVertical],
    rays: Rays,
    ray_segment: np.ndarray,
    pairs: np.ndarray,
    measured_directions: bool,
) -> dict[int, ImagePairs]:
    """Each image's (corner, segment) pairs for the map rows (as
    :func:`~.map_rows.image_pairs`: the segment's own fit where asked)."""
    out = {}
    for k, im in enumerate(images):
        sel = pairs[rays.image[pairs[:, 0]] == k]
        if len(sel) == 0:
            continue
        seg = ray_segment[sel[:, 0]]
        source = im.segments
        if measured_directions and im.segments_free is not None:
            source = im.segments_free
        out[im.image_id] = ImagePairs(sel[:, 1].copy(), source[seg].copy())
    return out


def lines_placement(
    rec: pycolmap.Reconstruction,
    vertical: ModelVertical,
    cad: Cadastre,
    start: Similarity,
    model_c: np.ndarray,
    prior_c: np.ndarray,
    model_R: np.ndarray,
    prior_R: np.ndarray,
    options: GeoregisterOptions,
) -> tuple[Similarity, list[int], Rays, np.ndarray, dict[int, ImagePairs]]:
    """The upright block's similarity onto the map from all images' segment
    rays (``start``: the priors' similarity of the camera centres
    ``model_c`` (N, 3) onto ``prior_c`` (N, 3); its inliers and the
    upright model's and the priors' rotations ``model_R``, ``prior_R``
    (N, 3, 3 cam_from_world) give the candidate windows). Returns the
    similarity, the image ids in ray order, the rays, the (P, 2) (ray,
    corner) pairs and each image's pairs; exit 2 (InputError) when the
    block finds no consensus."""
    lo: BlockLinesOptions = options.block_lines
    images = [
        im
        for im in vertical.images
        if im.segments is not None and len(im.segments) and im.down_camera is not None
    ]
    if len(images) < 2:
        raise InputError(None, "the automatic mode: fewer than 2 images with a VP")
    rays, ray_segment = _model_rays(rec, images)
    used = start.inliers
    prior = prior_similarity(
        model_c[used, :2],
        prior_c[used, :2],
        lo.min_prior_position_sigma_m,
        heading_from_rotations(model_R, prior_R),
    )
    _log_prior(prior)
    z0 = float(start.translation[2])
    window = np.degrees(lo.window_sigmas * prior.sd_theta) + 5.0
    seen = _seen(rec, images, cad, prior.scale, prior.theta, prior.translation,
                 z0, window, lo)  # fmt: skip
    cand = candidate_pairs(rays, seen, cad, prior, lo)
    fits = best_similarities(rays, cand, cad, prior, lo)
    if not fits:
        raise InputError(
            None,
            "the automatic mode (level cameras): no map corner is seen from two "
            "images near where the priors put it",
        )
    refined = [_guided(rec, images, cad, rays, fit, z0, lo) for fit in fits]
    k = int(np.argmax([r[0] for r in refined]))
    score, (scale, theta, t), pairs, placed = refined[k]
    if placed is None or len(pairs) < lo.min_inliers:
        raise InputError(
            None,
            "the automatic mode (level cameras): no consensus of the images' "
            f"vertical segments with the map ({len(pairs)} pairs, "
            f"{lo.min_inliers} needed)",
        )
    logger.info(
        "block lines: %d hypotheses, the best %d refined: scores %s px; kept "
        "#%d: %d pairs, rms %.3f deg, scale %.5g, heading %.3f deg",
        fits[0].num_hypotheses, len(fits), [round(r[0]) for r in refined], k,
        len(pairs), placed.rms_deg, scale, np.degrees(theta),
    )  # fmt: skip
    sim = Similarity(
        scale,
        rotation_z(theta),
        np.r_[t, z0],
        start.inliers,
        start.residuals_m,
    )
    ids = [im.image_id for im in images]
    measured = options.block.map_measured_directions
    per_image = _image_pairs(images, rays, ray_segment, pairs, measured)
    return sim, ids, rays, pairs, per_image


def _guided(rec, images, cad, rays, fit: LinesFit, z0, lo: BlockLinesOptions):
    """Guided matching from one hypothesis, ``guided_rounds`` times: each
    ray's corner in sight under the current similarity, then the 4-DOF
    refit on those pairs (each weighted by its sd). Returns (score: the
    last pairs' segment lengths, px; (scale, theta, t) fitted to them; the
    (P, 2) pairs; the fit)."""
    scale, theta, t = fit.model_to_map()
    pairs, placed = np.zeros((0, 2), int), None
    for _ in range(lo.guided_rounds):
        seen = _seen(rec, images, cad, scale, theta, t, z0, 2.0, lo)
        pairs = nearest_pairs(rays, seen, cad, scale, theta, t, lo)
        if len(pairs) < 2:
            return 0.0, (scale, theta, t), pairs, placed
        sd_deg = pair_sd_deg(rays, cad, pairs, scale, theta, t, lo)
        placed = fit_block(rays, cad.corner_xy, pairs, (scale, theta, t), sd_deg)
        scale, theta, t = placed.scale, placed.theta, placed.translation
    return float(rays.length[pairs[:, 0]].sum()), (scale, theta, t), pairs, placed


def _log_prior(prior: PriorSimilarity) -> None:
    logger.info(
        "block lines: prior similarity scale %.5g, heading %.2f deg (sd %.2f deg)",
        prior.scale, np.degrees(prior.theta), np.degrees(prior.sd_theta),
    )  # fmt: skip
