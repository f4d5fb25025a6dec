"""Benchmark of the standard COLMAP route (SfM + GPS alignment) on synthetic scenes.

Measures what a COLMAP user gets today with oblique images and rough GPS/INS
priors, scored exactly like ``obliq-colmap register``: SIFT, exhaustive
matching, incremental mapping and a 7-DoF alignment to the prior centres,
evaluated with ``obliq_colmap.evaluate.evaluate_model`` beside the priors
(baseline) and beside the route's ceiling (a perfect SfM aligned the same
way); per scene also the verified image pairs within and across the cardinal
directions and how many of them agree with the true epipolar geometry (why
the mapper fails where it fails).

Run (from the repository root)::

    python scripts/bench/sfm_baseline.py \\
        --scene_path data_samples/oblique_small --scene_path /work/scenes/paper_s1 \\
        [--num_threads 2] [--max_image_size 2004] [--output_path bench_sfm.json] \\
        [--workspace_path /tmp/bench_sfm [--reuse_database matches]]

This is a benchmark, not a test: it takes minutes per scene.

Figures: docs/STATUS.md (the COLMAP baseline beside ``register``) and
docs/journal/sfm-baseline.md.

Data: synthetic scenes (``obliq-colmap synth --preset paper --seed N
--output_path DIR``, or ``data_samples/oblique_small``); ``pycolmap``.

The route:

1. SIFT feature extraction on the CPU, one camera per cardinal direction with
   the priors' intrinsics (``priors/`` shares one camera_id per direction);
2. exhaustive matching with geometric verification;
3. incremental mapping (``pycolmap.incremental_mapping``; the bundle refines
   the focal length, as by default), keep the largest reconstruction;
4. georegistration: a 7-DoF similarity to the prior camera centres,
   ``pycolmap.align_reconstruction_to_locations`` (LO-RANSAC, inlier
   threshold 3 sigma of the scene's prior position noise by default);
5. the aligned model is written as an obliq-colmap result (LOCAL frame,
   ``world_abs = model_xyz + georef.origin``) and scored by
   ``obliq_colmap.evaluate.evaluate_model``, beside the priors (baseline);
6. the ceiling of the route: the TRUE cameras, moved by an arbitrary
   similarity and aligned to the priors the same way (a perfect SfM).

COLMAP's advice for few matches / large viewpoint changes (FAQ) is
``--estimate_affine_shape 1 --domain_size_pooling 1 --guided_matching 1``,
and lower mapper thresholds (``--init_min_num_inliers``,
``--abs_pose_min_num_inliers``); CPU guided matching is slow (seconds per pair).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

import obliq_colmap
from obliq_colmap.colmap_io import (
    Block,
    Georef,
    ImageRecord,
    Point3D,
    read_model,
    read_priors,
    write_result,
)
from obliq_colmap.evaluate import (
    EvaluateOptions,
    Evaluation,
    evaluate_baseline,
    evaluate_model,
)
from obliq_colmap.geometry import Camera, Pose

logger = logging.getLogger("bench_sfm_baseline")

#: Cardinal direction of an image: the prefix of its name (``N_00.jpg``).
DIRECTIONS = ("N", "E", "S", "W")


# --------------------------------------------------------------------------
# Options and inputs
# --------------------------------------------------------------------------


@dataclass
class SfmOptions:
    """Options of the COLMAP route, with the names of COLMAP's command line.

    Attributes
    ----------
    num_threads : int, threads of extraction, matching and mapping.
    max_image_size : int, SiftExtraction / FeatureExtraction max_image_size
        (px, longest side); images larger than this are downscaled.
    max_num_features : int, SIFT features per image.
    first_octave, estimate_affine_shape, domain_size_pooling : SiftExtraction
        options (COLMAP's defaults -1, False, False; affine shape and DSP are
        COLMAP's advice for large viewpoint changes).
    guided_matching, max_ratio : FeatureMatching / SiftMatching options.
    init_min_num_inliers, abs_pose_min_num_inliers : Mapper options (the
        inliers of the initial pair and of each image registration).
    ba_refine_focal_length : bool, Mapper.ba_refine_focal_length.
    ba_refine_principal_point : bool, Mapper.ba_refine_principal_point.
    alignment_max_error : float or None, inlier threshold of the similarity
        to the prior centres (m); None = 3 sigma of the scene's prior noise.
    min_common_images : int, min images common to model and priors to align.
    random_seed : int, for the mapper and the RANSACs (reproducible runs).
    """

    num_threads: int = 2
    max_image_size: int = 2004
    max_num_features: int = 8192
    first_octave: int = -1
    estimate_affine_shape: bool = False
    domain_size_pooling: bool = False
    guided_matching: bool = False
    max_ratio: float = 0.8
    init_min_num_inliers: int = 100
    abs_pose_min_num_inliers: int = 30
    ba_refine_focal_length: bool = True
    ba_refine_principal_point: bool = False
    alignment_max_error: float | None = None
    min_common_images: int = 3
    random_seed: int = 1


@dataclass
class Scene:
    """The inputs a user has: images and rough priors (plus their noise level).

    Attributes
    ----------
    path : the scene folder.
    image_path : its ``images/`` folder.
    priors : Block, the rough poses and intrinsics, absolute frame.
    crs : str or None.
    prior_sigma_m : (3,) array, prior centre noise (x, y, z), metres.
    """

    path: Path
    image_path: Path
    priors: Block
    crs: str | None
    prior_sigma_m: np.ndarray


def read_scene(scene_path: Path) -> Scene:
    """Read the priors and the prior noise of a synthetic scene folder."""
    meta = json.loads((scene_path / "scene.json").read_text())
    noise = meta["options"]
    sigma = np.array(
        [noise["prior_position_m"], noise["prior_position_m"], noise["prior_height_m"]]
    )
    priors = read_priors(scene_path / "priors", scene_path / "images")
    return Scene(scene_path, scene_path / "images", priors, meta.get("crs"), sigma)


def default_alignment_max_error(sigma_m: np.ndarray) -> float:
    """3 sigma of the prior centre noise: 3 x the largest per-axis sigma (m)."""
    return 3.0 * float(np.max(sigma_m))


def direction_of(name: str) -> str:
    """Cardinal direction of an image from its name prefix, '?' if none."""
    head = name.split("_", 1)[0]
    return head if head in DIRECTIONS else "?"


# --------------------------------------------------------------------------
# The COLMAP steps
# --------------------------------------------------------------------------


def extract_features(
    database_path: Path, scene: Scene, options: SfmOptions
) -> dict[int, list[str]]:
    """SIFT on the CPU; one shared camera per prior camera (cardinal direction).

    As a user would on the command line: one ``feature_extractor`` call per
    camera with ``--ImageReader.single_camera 1 --ImageReader.camera_model
    PINHOLE --ImageReader.camera_params fx,fy,cx,cy`` and the image list.

    Returns
    -------
    dict prior camera_id -> image names of that camera.
    """
    groups: dict[int, list[str]] = {}
    for im in sorted(scene.priors.images.values(), key=lambda im: im.name):
        groups.setdefault(im.camera_id, []).append(im.name)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.max_image_size = options.max_image_size
    extraction.use_gpu = False
    extraction.sift.max_num_features = options.max_num_features
    extraction.sift.first_octave = options.first_octave
    extraction.sift.estimate_affine_shape = options.estimate_affine_shape
    extraction.sift.domain_size_pooling = options.domain_size_pooling
    for camera_id, names in sorted(groups.items()):
        camera = scene.priors.cameras[camera_id]
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera.model
        reader.camera_params = ",".join(f"{v:.6f}" for v in camera.params)
        pycolmap.extract_features(
            database_path,
            scene.image_path,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    return groups


def match_exhaustive(database_path: Path, options: SfmOptions) -> None:
    """Exhaustive SIFT matching on the CPU with geometric verification."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    matching.use_gpu = False
    matching.guided_matching = options.guided_matching
    matching.sift.max_ratio = options.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.random_seed
    pycolmap.match_exhaustive(
        database_path,
        matching_options=matching,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )


def clear_matches(database_path: Path) -> None:
    """Remove the matches and two-view geometries of a database, keep features."""
    db = pycolmap.Database.open(database_path)
    try:
        db.clear_matches()
        db.clear_two_view_geometries()
    finally:
        db.close()


@dataclass
class MatchStats:
    """Verified image pairs of the database, by the directions of the images.

    Attributes
    ----------
    num_keypoints_median : median SIFT keypoints per image.
    pairs : dict relation -> [verified, true, all]: image pairs with at least
        ``min_inliers`` verified inlier matches; of those, the pairs whose
        inliers agree with the TRUE epipolar geometry (median distance to the
        true epipolar lines below ``true_max_error_px``); all image pairs.
        Relation ``same`` (same direction), ``adjacent`` (90 deg apart),
        ``opposite`` (180 deg apart).
    inliers_median : dict relation -> median inlier matches of its verified pairs.
    true_inliers_median : dict relation -> median, over its true pairs, of the
        inliers within ``true_max_error_px`` of the true epipolar lines.
    """

    num_keypoints_median: float
    pairs: dict[str, list[int]] = field(default_factory=dict)
    inliers_median: dict[str, float] = field(default_factory=dict)
    true_inliers_median: dict[str, float] = field(default_factory=dict)


def _relation(a: str, b: str) -> str:
    da, db = direction_of(a), direction_of(b)
    if "?" in (da, db):
        return "unknown"
    steps = abs(DIRECTIONS.index(da) - DIRECTIONS.index(db)) % 4
    return {0: "same", 1: "adjacent", 2: "opposite", 3: "adjacent"}[steps]


def epipolar_errors_px(
    gt: Block, name1: str, name2: str, xy1: np.ndarray, xy2: np.ndarray
) -> np.ndarray:
    """Distance (px) of matches to the TRUE epipolar lines, the larger of both images.

    Computed in normalised (undistorted) coordinates with the true essential
    matrix and converted to pixels with each image's focal length.
    """
    im1, im2 = gt.image_by_name(name1), gt.image_by_name(name2)
    cam1, cam2 = gt.cameras[im1.camera_id], gt.cameras[im2.camera_id]
    R1, t1 = im1.cam_from_world.rotation, im1.cam_from_world.translation
    R2, t2 = im2.cam_from_world.rotation, im2.cam_from_world.translation
    R = R2 @ R1.T
    t = t2 - R @ t1
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ R
    u1 = np.column_stack([cam1.cam_from_img(xy1), np.ones(len(xy1))])
    u2 = np.column_stack([cam2.cam_from_img(xy2), np.ones(len(xy2))])
    l2 = u1 @ E.T  # lines in image 2
    l1 = u2 @ E  # lines in image 1
    num = np.abs(np.sum(u2 * l2, axis=1))
    d2 = num / np.linalg.norm(l2[:, :2], axis=1) * cam2.K[0, 0]
    d1 = num / np.linalg.norm(l1[:, :2], axis=1) * cam1.K[0, 0]
    return np.maximum(d1, d2)


def match_stats(
    database_path: Path,
    gt: Block,
    min_inliers: int = 15,
    true_max_error_px: float = 3.0,
) -> MatchStats:
    """Count verified pairs within and across cardinal directions, and the true ones."""
    db = pycolmap.Database.open(database_path)
    try:
        images = {im.image_id: im.name for im in db.read_all_images()}
        keypoints = {i: db.read_keypoints(i)[:, :2] for i in images}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    names = sorted(images.values())
    total: dict[str, int] = {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            total[_relation(a, b)] = total.get(_relation(a, b), 0) + 1
    inliers: dict[str, list[int]] = {rel: [] for rel in total}
    true_inliers: dict[str, list[int]] = {rel: [] for rel in total}
    for pair_id, geometry in zip(pair_ids, geometries, strict=True):
        id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
        matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
        if len(matches) < min_inliers:
            continue
        rel = _relation(images[id1], images[id2])
        inliers[rel].append(len(matches))
        err = epipolar_errors_px(
            gt,
            images[id1],
            images[id2],
            keypoints[id1][matches[:, 0]],
            keypoints[id2][matches[:, 1]],
        )
        if np.median(err) < true_max_error_px:
            true_inliers[rel].append(int(np.sum(err < true_max_error_px)))

    def median(v: list[int]) -> float:
        return float(np.median(v)) if v else math.nan

    return MatchStats(
        float(np.median([len(k) for k in keypoints.values()])),
        {rel: [len(inliers[rel]), len(true_inliers[rel]), total[rel]] for rel in total},
        {rel: median(v) for rel, v in inliers.items()},
        {rel: median(v) for rel, v in true_inliers.items()},
    )


def run_mapping(
    database_path: Path, image_path: Path, sparse_path: Path, options: SfmOptions
) -> dict[int, pycolmap.Reconstruction]:
    """``pycolmap.incremental_mapping`` with the default options of a user."""
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.random_seed
    mapping.ba_refine_focal_length = options.ba_refine_focal_length
    mapping.ba_refine_principal_point = options.ba_refine_principal_point
    mapping.ba_use_gpu = False
    mapping.mapper.init_min_num_inliers = options.init_min_num_inliers
    mapping.mapper.abs_pose_min_num_inliers = options.abs_pose_min_num_inliers
    sparse_path.mkdir(parents=True, exist_ok=True)
    return pycolmap.incremental_mapping(
        database_path, image_path, sparse_path, options=mapping
    )


def largest(
    reconstructions: dict[int, pycolmap.Reconstruction],
) -> pycolmap.Reconstruction | None:
    """The reconstruction with the most registered images (None if none)."""
    if not reconstructions:
        return None
    return max(reconstructions.values(), key=lambda r: r.num_reg_images())


@dataclass
class Alignment:
    """The similarity from the SfM frame to the LOCAL frame of the priors.

    Attributes
    ----------
    success : bool.
    scale : float, metres per SfM unit.
    num_common : int, registered images with a prior.
    num_inliers : int, of those within the max error after alignment.
    max_error_m : float, RANSAC inlier threshold used.
    residual_rms_m, residual_max_m : float, aligned minus prior centres, all
        common images.
    """

    success: bool
    scale: float = math.nan
    num_common: int = 0
    num_inliers: int = 0
    max_error_m: float = math.nan
    residual_rms_m: float = math.nan
    residual_max_m: float = math.nan


def align_to_priors(
    rec: pycolmap.Reconstruction,
    priors: Block,
    origin: np.ndarray,
    max_error_m: float,
    options: SfmOptions,
) -> Alignment:
    """Align ``rec`` in place to the prior centres expressed as ``X - origin``.

    The priors are absolute (UTM-like, ~5e6 m); the target is shifted by
    ``origin`` first so that the model ends in the result's LOCAL frame.
    """
    prior_centres = {
        im.name: im.cam_from_world.center - origin for im in priors.images.values()
    }
    names = [
        rec.image(i).name
        for i in rec.reg_image_ids()
        if rec.image(i).name in prior_centres
    ]
    alignment = Alignment(False, num_common=len(names), max_error_m=max_error_m)
    if len(names) < options.min_common_images:
        logger.warning("only %d images in common with the priors", len(names))
        return alignment
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = max_error_m
    ransac.random_seed = options.random_seed
    locations = np.array([prior_centres[n] for n in names])
    sim3 = pycolmap.align_reconstruction_to_locations(
        rec, names, locations, options.min_common_images, ransac
    )
    if sim3 is None:
        logger.warning("align_reconstruction_to_locations failed")
        return alignment
    rec.transform(sim3)
    by_name = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    residuals = np.linalg.norm(
        np.array([by_name[n].projection_center() for n in names]) - locations, axis=1
    )
    alignment.success = True
    alignment.scale = float(sim3.scale)
    alignment.num_inliers = int(np.sum(residuals <= max_error_m))
    alignment.residual_rms_m = float(np.sqrt(np.mean(residuals**2)))
    alignment.residual_max_m = float(residuals.max())
    return alignment


def to_result_block(
    rec: pycolmap.Reconstruction, priors: Block
) -> tuple[Block, list[Point3D]]:
    """The registered images, cameras and points of ``rec`` as a Block.

    Image ids and camera ids are those of the priors (matched by name), so the
    result reads like our own output; the frame is that of ``rec``.
    """
    prior_by_name = {im.name: im for im in priors.images.values()}
    block = Block()
    image_id_map: dict[int, int] = {}
    for sfm_id in rec.reg_image_ids():
        image = rec.image(sfm_id)
        prior = prior_by_name[image.name]
        camera = Camera.from_pycolmap(rec.cameras[image.camera_id])
        camera.camera_id = prior.camera_id
        block.cameras.setdefault(prior.camera_id, camera)
        block.images[prior.image_id] = ImageRecord(
            prior.image_id,
            image.name,
            prior.camera_id,
            Pose.from_rigid3d(image.cam_from_world()),
        )
        image_id_map[sfm_id] = prior.image_id
    points: list[Point3D] = []
    for point in rec.points3D.values():
        observations = [
            (
                image_id_map[el.image_id],
                np.asarray(rec.image(el.image_id).points2D[el.point2D_idx].xy),
            )
            for el in point.track.elements
            if el.image_id in image_id_map
        ]
        if len(observations) >= 2:
            points.append(Point3D(np.asarray(point.xyz, float), observations))
    return block, points


def focal_errors_percent(block: Block, gt: Block) -> dict[str, float]:
    """Relative focal error (fx) per camera of ``block`` against the truth, %.

    Keyed by the direction of the camera's first image.
    """
    gt_by_name = {im.name: im for im in gt.images.values()}
    out: dict[str, float] = {}
    for camera_id, camera in sorted(block.cameras.items()):
        names = sorted(
            im.name for im in block.images.values() if im.camera_id == camera_id
        )
        if not names:
            continue
        true = gt.cameras[gt_by_name[names[0]].camera_id]
        out[direction_of(names[0])] = float(
            100.0 * (camera.params[0] - true.params[0]) / true.params[0]
        )
    return out


# --------------------------------------------------------------------------
# One scene
# --------------------------------------------------------------------------


def summarize(ev: Evaluation) -> dict:
    """The block figures of an evaluation, as a JSON-ready dict."""
    s = ev.summary
    return {
        "registered": s.num_registered,
        "total": s.num_total,
        "missing": s.num_missing,
        "deviation_median_px": s.deviation_median_px,
        "deviation_p95_px": s.deviation_p95_px,
        "deviation_max_px": s.deviation_max_px,
        "rotation_median_deg": s.rotation_error_median_deg,
        "center_median_m": s.center_error_median_m,
        "horizontal_median_m": s.horizontal_error_median_m,
        "vertical_median_m": s.vertical_error_median_m,
        "vertical_offset_m": s.vertical_offset_m,
    }


def bench_scene(
    scene_path: Path, workspace: Path, options: SfmOptions, reuse: str = "none"
) -> dict:
    """Run the COLMAP route on one scene and evaluate it; returns one row.

    ``reuse``: ``none`` runs every step; ``features`` keeps the database's
    features and re-matches; ``matches`` keeps the matches too and only maps
    (to vary the mapper options; those steps then have no time).
    """
    scene = read_scene(scene_path)
    workspace.mkdir(parents=True, exist_ok=True)
    database_path = workspace / "database.db"
    if reuse == "none" and database_path.exists():
        database_path.unlink()
    elif reuse != "none" and not database_path.is_file():
        raise FileNotFoundError(f"--reuse_database {reuse}: no {database_path}")
    times: dict[str, float] = {}
    row: dict = {
        "scene": str(scene_path),
        "num_images": len(scene.priors.images),
        "reused": reuse,
    }

    if reuse == "none":
        t = time.perf_counter()
        extract_features(database_path, scene, options)
        times["extraction"] = time.perf_counter() - t
    if reuse in ("none", "features"):
        if reuse == "features":
            clear_matches(database_path)
        t = time.perf_counter()
        match_exhaustive(database_path, options)
        times["matching"] = time.perf_counter() - t
    gt = read_model(scene_path / "gt")
    row["matches"] = asdict(match_stats(database_path, gt))

    t = time.perf_counter()
    sparse_path = workspace / "sparse"
    shutil.rmtree(sparse_path, ignore_errors=True)
    reconstructions = run_mapping(database_path, scene.image_path, sparse_path, options)
    rec = largest(reconstructions)
    times["mapping"] = time.perf_counter() - t
    row["reconstructions"] = sorted(
        (r.num_reg_images() for r in reconstructions.values()), reverse=True
    )
    row["time_s"] = times
    if rec is None:
        logger.error("%s: the mapper made no reconstruction", scene_path)
        times["total"] = sum(times.values())
        row.update(sfm_registered=0, aligned=False)
        return row
    row["sfm_registered"] = rec.num_reg_images()
    row["sfm_unregistered"] = sorted(
        {im.name for im in scene.priors.images.values()}
        - {rec.image(i).name for i in rec.reg_image_ids()}
    )
    row["num_points3D"] = rec.num_points3D()
    row["mean_reprojection_error_px"] = rec.compute_mean_reprojection_error()

    t = time.perf_counter()
    origin = local_origin(scene.priors)
    max_error = options.alignment_max_error or default_alignment_max_error(
        scene.prior_sigma_m
    )
    alignment = align_to_priors(rec, scene.priors, origin, max_error, options)
    times["alignment"] = time.perf_counter() - t
    times["total"] = sum(times.values())
    row["alignment"] = asdict(alignment)
    row["aligned"] = alignment.success
    row["prior_focal_error_percent"] = focal_errors_percent(scene.priors, gt)
    if alignment.success:
        block = write_and_evaluate(
            rec,
            scene,
            origin,
            workspace / "model",
            "pycolmap SfM + align_reconstruction_to_locations to the priors",
            row,
        )
        row["focal_error_percent"] = focal_errors_percent(block, gt)
    return row


def local_origin(priors: Block) -> np.ndarray:
    """The origin of the result's LOCAL frame: the rounded mean prior centre."""
    return np.round(
        np.mean([im.cam_from_world.center for im in priors.images.values()], axis=0)
    )


def write_and_evaluate(
    rec: pycolmap.Reconstruction,
    scene: Scene,
    origin: np.ndarray,
    model_path: Path,
    method: str,
    row: dict,
    prefix: str = "result",
) -> Block:
    """Write ``rec`` (LOCAL frame of ``origin``) as a result; evaluate it into ``row``.

    Sets ``row[prefix]`` (full deviation) and ``row[prefix + "_across_vertical"]``.
    """
    block, points = to_result_block(rec, scene.priors)
    shutil.rmtree(model_path, ignore_errors=True)
    model_path.parent.mkdir(parents=True, exist_ok=True)
    georef = Georef(
        origin, scene.crs, {"method": method, "pycolmap": pycolmap.__version__}
    )
    write_result(model_path, block, georef, points)
    row[prefix] = summarize(evaluate_model(model_path, scene.path, EvaluateOptions()))
    row[prefix + "_across_vertical"] = summarize(
        evaluate_model(model_path, scene.path, EvaluateOptions(across_vertical=True))
    )
    return block


def bench_ceiling(
    scene_path: Path, workspace: Path, options: SfmOptions, row: dict
) -> None:
    """The ceiling of the route: a PERFECT SfM aligned to the priors the same way.

    The true cameras (exact relative geometry and intrinsics) are moved by an
    arbitrary similarity (as SfM leaves them), then aligned to the prior
    centres with the same threshold. Sets ``row["ceiling"]`` and
    ``row["ceiling_alignment"]``.
    """
    scene = read_scene(scene_path)
    rec = pycolmap.Reconstruction(str(scene_path / "gt"))
    rng = np.random.default_rng(options.random_seed)
    rec.transform(
        pycolmap.Sim3d(
            0.0137, pycolmap.Rotation3d(rng.normal(size=3)), rng.normal(size=3) * 50.0
        )
    )
    origin = local_origin(scene.priors)
    max_error = options.alignment_max_error or default_alignment_max_error(
        scene.prior_sigma_m
    )
    alignment = align_to_priors(rec, scene.priors, origin, max_error, options)
    row["ceiling_alignment"] = asdict(alignment)
    if alignment.success:
        write_and_evaluate(
            rec,
            scene,
            origin,
            workspace / "ceiling_model",
            "true cameras moved by a similarity, aligned to the priors",
            row,
            prefix="ceiling",
        )


# --------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------


def machine_info() -> dict:
    """CPU model and core count (lscpu), load, versions, date."""
    info = {
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "cpus": os.cpu_count(),
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "python": platform.python_version(),
        "pycolmap": pycolmap.__version__,
        "obliq_colmap": obliq_colmap.__version__,
        "numpy": np.__version__,
    }
    try:
        lscpu = subprocess.run(
            ["lscpu"], capture_output=True, text=True, check=True
        ).stdout
        for line in lscpu.splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("Model name", "CPU(s)", "CPU family", "Model"):
                info[
                    "lscpu_" + key.strip().lower().replace(" ", "_").replace("(s)", "s")
                ] = value.strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return info


def _fmt(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def format_rows(rows: list[dict]) -> str:
    """The figures table (one line per scene and model) and the timings."""
    header = (
        "| scene | model | SfM registered | registered (< 2 px) | deviation median /"
        " p95 / max px | rotation median deg | centre median m |"
    )
    lines = [header, "|" + "---|" * 7]
    timing = [
        "| scene | extraction s | matching s | mapping s | alignment s | total s |",
        "|" + "---|" * 6,
    ]
    for row in rows:
        name = Path(row["scene"]).name
        n = row["num_images"]
        for label, key in (
            ("SfM + alignment", "result"),
            ("SfM + alignment, across vertical", "result_across_vertical"),
            ("perfect SfM + alignment (ceiling)", "ceiling"),
            ("ceiling, across vertical", "ceiling_across_vertical"),
            ("priors", "baseline_priors"),
            ("priors, across vertical", "baseline_priors_across_vertical"),
        ):
            s = row.get(key)
            sfm = f"{row.get('sfm_registered', 0)} / {n}" if key == "result" else ""
            if s is None:
                lines.append(f"| {name} | {label} | {sfm} | failed | - | - | - |")
                continue
            deviation = " / ".join(
                _fmt(s[k])
                for k in ("deviation_median_px", "deviation_p95_px", "deviation_max_px")
            )
            lines.append(
                f"| {name} | {label} | {sfm} | {s['registered']} / {s['total']} | "
                f"{deviation} | {_fmt(s['rotation_median_deg'], 3)} | "
                f"{_fmt(s['center_median_m'])} |"
            )
        t = row.get("time_s", {})
        timing.append(
            f"| {name} | "
            + " | ".join(
                _fmt(t.get(k), 1)
                for k in ("extraction", "matching", "mapping", "alignment", "total")
            )
            + " |"
        )
    return "\n".join(lines + [""] + timing)


def format_details(row: dict) -> str:
    """Matching, mapping and alignment details of one scene."""
    m = row.get("matches", {})
    pairs = "; ".join(
        f"{rel} {v[0]} of {v[2]} (median {_fmt(m['inliers_median'].get(rel), 0)}"
        f" inliers), {v[1]} true (median "
        f"{_fmt(m['true_inliers_median'].get(rel), 0)} true inliers)"
        for rel, v in sorted(m.get("pairs", {}).items())
    )
    a = row.get("alignment", {})
    c = row.get("ceiling_alignment", {})
    lines = [
        f"{Path(row['scene']).name}: keypoints/image median "
        f"{_fmt(m.get('num_keypoints_median'), 0)}; verified pairs {pairs}",
        f"  reconstructions (images): {row.get('reconstructions')}; largest: "
        f"{row.get('sfm_registered')} images, {row.get('num_points3D')} points, "
        f"mean reprojection error {_fmt(row.get('mean_reprojection_error_px'), 3)} px;"
        f" unregistered: {row.get('sfm_unregistered')}",
        f"  alignment: success {a.get('success')}, scale {_fmt(a.get('scale'), 4)},"
        f" {a.get('num_inliers')}/{a.get('num_common')} within "
        f"{_fmt(a.get('max_error_m'), 1)} m, residual rms "
        f"{_fmt(a.get('residual_rms_m'))} m, max {_fmt(a.get('residual_max_m'))} m",
        f"  ceiling alignment: {c.get('num_inliers')}/{c.get('num_common')} within "
        f"{_fmt(c.get('max_error_m'), 1)} m, residual rms "
        f"{_fmt(c.get('residual_rms_m'))} m, max {_fmt(c.get('residual_max_m'))} m",
        f"  focal error %: SfM {row.get('focal_error_percent')}, priors "
        f"{row.get('prior_focal_error_percent')}",
    ]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--scene_path",
        action="append",
        required=True,
        help="synthetic scene folder (images/, priors/, gt/, scene.json); repeatable",
    )
    parser.add_argument("--output_path", help="write all rows as JSON here")
    parser.add_argument(
        "--workspace_path",
        help="keep the database, sparse/ and the result model/ under "
        "WORKSPACE/SCENE_NAME (default: a temporary folder, removed)",
    )
    parser.add_argument(
        "--reuse_database",
        choices=("none", "features", "matches"),
        default="none",
        help="with --workspace_path: keep the features (re-match) or the matches "
        "(map only) of a previous run",
    )
    parser.add_argument("--num_threads", type=int, default=2)
    parser.add_argument(
        "--max_image_size", type=int, default=2004, help="SIFT max image size, px"
    )
    parser.add_argument("--max_num_features", type=int, default=8192)
    parser.add_argument("--first_octave", type=int, default=-1)
    parser.add_argument("--estimate_affine_shape", type=int, choices=(0, 1), default=0)
    parser.add_argument("--domain_size_pooling", type=int, choices=(0, 1), default=0)
    parser.add_argument("--guided_matching", type=int, choices=(0, 1), default=0)
    parser.add_argument("--max_ratio", type=float, default=0.8)
    parser.add_argument("--init_min_num_inliers", type=int, default=100)
    parser.add_argument("--abs_pose_min_num_inliers", type=int, default=30)
    parser.add_argument("--ba_refine_focal_length", type=int, choices=(0, 1), default=1)
    parser.add_argument(
        "--ba_refine_principal_point", type=int, choices=(0, 1), default=0
    )
    parser.add_argument(
        "--alignment_max_error",
        type=float,
        help="inlier threshold (m) of the alignment to the prior centres; "
        "default 3 x the scene's largest prior position sigma",
    )
    parser.add_argument("--min_common_images", type=int, default=3)
    parser.add_argument("--random_seed", type=int, default=1)
    parser.add_argument(
        "--log_level", default="INFO", choices=("DEBUG", "INFO", "WARNING")
    )
    parser.add_argument(
        "--colmap_log", action="store_true", help="show COLMAP's own (glog) log"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    os.environ.setdefault("OMP_NUM_THREADS", str(args.num_threads))
    if not args.colmap_log:
        pycolmap.logging.minloglevel = 1  # warnings and errors only
    options = SfmOptions(
        num_threads=args.num_threads,
        max_image_size=args.max_image_size,
        max_num_features=args.max_num_features,
        first_octave=args.first_octave,
        estimate_affine_shape=bool(args.estimate_affine_shape),
        domain_size_pooling=bool(args.domain_size_pooling),
        guided_matching=bool(args.guided_matching),
        max_ratio=args.max_ratio,
        init_min_num_inliers=args.init_min_num_inliers,
        abs_pose_min_num_inliers=args.abs_pose_min_num_inliers,
        ba_refine_focal_length=bool(args.ba_refine_focal_length),
        ba_refine_principal_point=bool(args.ba_refine_principal_point),
        alignment_max_error=args.alignment_max_error,
        min_common_images=args.min_common_images,
        random_seed=args.random_seed,
    )
    pycolmap.set_random_seed(args.random_seed)
    scenes = [Path(s) for s in args.scene_path]
    for scene in scenes:
        if not (scene / "gt").is_dir() or not (scene / "scene.json").is_file():
            print(f"error: {scene} is not a synthetic scene", file=sys.stderr)
            return 2
    if args.reuse_database != "none" and not args.workspace_path:
        print("error: --reuse_database needs --workspace_path", file=sys.stderr)
        return 2
    meta = machine_info()
    meta["options"] = asdict(options)
    logger.info("machine: %s", meta)
    tmp = None
    if args.workspace_path:
        root = Path(args.workspace_path)
    else:
        tmp = Path(tempfile.mkdtemp(prefix="bench_sfm_"))
        root = tmp
    rows = []
    try:
        for scene in scenes:
            logger.info("scene %s", scene)
            t = time.perf_counter()
            row = bench_scene(scene, root / scene.name, options, args.reuse_database)
            row["wall_s"] = time.perf_counter() - t
            bench_ceiling(scene, root / scene.name, options, row)
            row["baseline_priors"] = summarize(evaluate_baseline(scene))
            row["baseline_priors_across_vertical"] = summarize(
                evaluate_baseline(scene, EvaluateOptions(across_vertical=True))
            )
            rows.append(row)
            print(format_details(row), flush=True)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    print()
    print(format_rows(rows))
    meta["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    print(f"\nmachine: {meta}")
    if args.output_path:
        Path(args.output_path).write_text(
            json.dumps(json_safe({"meta": meta, "rows": rows}), indent=2) + "\n"
        )
    return 0


def json_safe(obj):
    """Numpy scalars to Python numbers, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


if __name__ == "__main__":
    sys.exit(main())
