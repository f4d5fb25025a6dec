"""One missing image placed end to end, and all of them added to a model."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap.images import image_problem

from .matching import (
    Correspondences,
    RegisteredImages,
    correspondences_2d3d,
    missing_images,
    neighbour_candidates,
    neighbour_order,
    read_gray,
    sift,
)
from .options import ImageVPs, PlacedImage, RelativeVPOptions
from .position import place_with_rotations
from .vps import image_vps

logger = logging.getLogger(__name__)


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
