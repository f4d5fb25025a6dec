"""The model's vertical from its images' vertical vanishing points (MetropoGIS 3.2.1).

Each registered image gives, from stage 1 (:func:`detect_vertical_vp`), the
world's down direction in its camera frame with an angular sd; rotated into
the model frame (``R_i^T d_i``) these are noisy observations of ONE
direction. Their robust weighted mean on the sphere (iteratively reweighted:
weights ``1 / sd_i^2`` times a Cauchy factor of each image's angle from the
mean, scaled by the robust spread) is the model's down; the rotation that
turns it to ``-z`` makes the model upright.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from obliq_colmap.geometry import Camera, rotation_aligning
from obliq_colmap.images import read_image
from obliq_colmap.lines import Segments
from obliq_colmap.vanishing import VanishingOptions, VPPrior, detect_vertical_vp

from .options import VerticalOptions

logger = logging.getLogger(__name__)


@dataclass
class ImageVertical:
    """One image's down direction, camera and model frame, and its fate."""

    image_id: int
    name: str
    status: str  # stage 1's
    down_camera: np.ndarray | None  # (3,)
    down_model: np.ndarray | None  # (3,)
    sd_deg: float
    residual_deg: float = float("nan")
    weight: float = 0.0
    #: (N, 2, 2) stage 1's vertical segments (undistorted pixels) and the
    #: (3, 3) pinhole matrix they are in
    segments: np.ndarray | None = None
    K: np.ndarray | None = None
    #: (N, 2, 2) the same segments each fitted on its own edge points (not
    #: through the VP; the map rows' lines with
    #: ``BlockAdjustmentOptions.map_measured_directions``)
    segments_free: np.ndarray | None = None
    #: stage 1's first-pass segments (undistorted pixels of the model's
    #: camera): the facade edges' source (:mod:`.facade_rows`)
    line_segments: Segments | None = None


@dataclass
class ModelVertical:
    """The model's down direction (3,) with its sd (deg) and the per-image detail."""

    down: np.ndarray
    sd_deg: float
    images: list[ImageVertical]
    #: the VP prior whose images agreed: "terrestrial" or "oblique"
    kind: str = ""

    @property
    def num_used(self) -> int:
        return sum(1 for im in self.images if im.weight > 0)

    def upright_rotation(self) -> np.ndarray:
        """(3, 3) R with ``R @ down = (0, 0, -1)``, the smallest such rotation."""
        return rotation_aligning(self.down, np.array([0.0, 0.0, -1.0]))


def _camera(cam: pycolmap.Camera) -> Camera:
    return Camera(cam.model.name, cam.width, cam.height, np.asarray(cam.params))


def _priors(kind: str) -> list[tuple[str, VPPrior]]:
    both = [("terrestrial", VPPrior.none()), ("oblique", VPPrior.aerial())]
    return [kp for kp in both if kind in (kp[0], "auto")]


def image_vertical(
    image_path: Path,
    rec: pycolmap.Reconstruction,
    image_id: int,
    options: VerticalOptions,
    prior: VPPrior,
) -> ImageVertical:
    """Stage 1 on one registered image of the model, with one prior."""
    image = rec.images[image_id]
    gray, problem = read_image(image_path / image.name)
    if gray is None:
        logger.warning("%s: %s; no vertical from it", image.name, problem)
        return ImageVertical(image_id, image.name, "unreadable", None, None, np.inf)
    camera = _camera(image.camera)
    res = detect_vertical_vp(
        gray, VanishingOptions(seed=options.seed), camera=camera, prior=prior
    )
    if res.vertical_direction is None or res.status != "ok":
        return ImageVertical(image_id, image.name, res.status, None, None, np.inf)
    R = image.cam_from_world().rotation.matrix()
    d = np.asarray(res.vertical_direction, float)
    segs = None if res.vertical_segments is None else res.vertical_segments.endpoints
    free = res.vertical_segments_free
    return ImageVertical(
        image_id,
        image.name,
        "ok",
        d,
        R.T @ d,
        float(res.direction_std_deg),
        segments=segs,
        K=camera.K,
        segments_free=None if free is None else free.endpoints,
        line_segments=res.segments,
    )


def robust_mean_direction(
    d: np.ndarray, sd_deg: np.ndarray, outlier_sigmas: float, iterations: int = 20
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Robust weighted mean of (N, 3) unit vectors (all oriented one way).

    Returns the unit mean (3,), (N,) angles from it (deg), (N,) final weights
    and the mean's sd (deg). Weights: ``1 / sd_i^2`` (the floor of 0.01 deg
    keeps one over-confident image from dominating) times a robust factor of
    the image's angle from the mean: Cauchy first (it converges from the
    plain mean), then Tukey's biweight, which gives an image beyond
    ``outlier_sigmas`` robust spreads no weight at all (a Cauchy weight of
    0.5 % on a VP 11 deg off still moved the mean by 0.05 deg).
    """
    base = 1.0 / np.maximum(sd_deg, 0.01) ** 2
    mean = d.sum(0)
    mean /= np.linalg.norm(mean)
    w = base
    for it in range(2 * iterations):
        ang = np.degrees(np.arccos(np.clip(d @ mean, -1.0, 1.0)))
        spread = max(1.4826 * float(np.median(ang)), float(np.median(sd_deg)), 1e-3)
        u = ang / (outlier_sigmas * spread)
        if it < iterations:
            w = base / (1.0 + u**2)
        else:
            w = base * np.where(u < 1.0, (1.0 - u**2) ** 2, 0.0)
        new = (w[:, None] * d).sum(0)
        new /= np.linalg.norm(new)
        done = np.degrees(np.arccos(np.clip(new @ mean, -1.0, 1.0))) < 1e-7
        mean = new
        if done and it >= iterations:
            break
    ang = np.degrees(np.arccos(np.clip(d @ mean, -1.0, 1.0)))
    # sd of the weighted mean: each image's own sd or the spread, whichever
    # is larger (their errors are not independent of the model's own)
    eff = np.maximum(sd_deg, np.median(ang))
    sd_mean = float(1.0 / np.sqrt(np.sum((w / base) / eff**2)))
    return mean, ang, w, sd_mean


def _combine(images: list[ImageVertical], options: VerticalOptions):
    """The robust mean of the images' downs (None: too few); sets each
    image's residual and weight. Returns (mean, sd, median residual)."""
    ok = [im for im in images if im.down_model is not None]
    if len(ok) < options.min_images:
        return None
    d = np.array([im.down_model for im in ok])
    # orient every image's "down" like the majority (stage 1 orients by the
    # image's y axis, which a camera held upside down would flip)
    d *= np.sign(d @ d.sum(0))[:, None]
    mean, ang, w, sd = robust_mean_direction(
        d, np.array([im.sd_deg for im in ok]), options.outlier_sigmas
    )
    for im, a, wk in zip(ok, ang, w, strict=True):
        im.residual_deg, im.weight = float(a), float(wk)
    return mean, sd, float(np.median(ang))


def model_vertical(
    rec: pycolmap.Reconstruction,
    image_path: Path,
    options: VerticalOptions,
    progress: bool = True,
) -> ModelVertical | None:
    """The model's down direction from all its registered images (None: too few VPs).

    With ``camera_kind`` "auto" both priors run on every image and the kind
    whose images agree is kept: the smallest median residual among the
    kinds with at least half the most images. A per-image choice (the more significant
    VP) picked a facade's horizontal pencil on oblique images of a model in
    a random frame and put the vertical 45-90 deg off.
    """
    ids = sorted(rec.reg_image_ids())
    found = []  # (images used, median residual, ModelVertical) per kind
    for kind, prior in _priors(options.camera_kind):
        bar = tqdm(ids, desc=f"vertical VPs ({kind})", disable=not progress or None)
        images = [image_vertical(image_path, rec, i, options, prior) for i in bar]
        got = _combine(images, options)
        if got is None:
            continue
        used = sum(1 for im in images if im.weight > 0)
        logger.info(
            "vertical (%s prior) from %d of %d images: sd %.3f deg, median "
            "residual %.3f deg", kind, used, len(images), got[1], got[2],
        )  # fmt: skip
        found.append((used, got[2], ModelVertical(got[0], got[1], images, kind)))
    if not found:
        return None
    # the images of the right kind agree (residuals of their VPs' sd); a
    # wrong kind's VPs scatter by tens of degrees, however many it finds
    most = max(f[0] for f in found)
    return min((f for f in found if f[0] >= 0.5 * most), key=lambda f: f[1])[2]
