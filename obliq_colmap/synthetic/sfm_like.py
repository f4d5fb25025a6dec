"""An SfM-like COLMAP model of a synthetic scene, in an arbitrary similarity frame.

What a user's SfM model looks like, with the truth known: the true cameras
and poses, 3D points with tracks (building corners and window-frame corners
seen by the true cameras, depth-tested against their z-buffers, observed with
pixel noise), all moved by a seeded random similarity
``X_sfm = scale * R @ (X_abs - origin) + t``; plus the scene's control points
as an OpenSfM ``gcp_list.txt`` (observations with pixel noise, positions
with a stated accuracy) and ``sfm_frame.json`` (the similarity, to score
against).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from obliq_colmap.colmap_io import Block, ImageRecord, Point3D, to_reconstruction
from obliq_colmap.control.model import ControlObservation, ControlPoint, ControlPoints
from obliq_colmap.files import AtomicFolder
from obliq_colmap.geometry import Pose, project, rotation_from_axis_angle
from obliq_colmap.synthetic import city as C
from obliq_colmap.synthetic.cameras import stream
from obliq_colmap.synthetic.scene_io import SyntheticScene
from obliq_colmap.synthetic.street import read_gcp_list, write_gcp_list
from obliq_colmap.synthetic.truth import points_visible

#: random stream of the SfM-like model (beside the scene's own streams).
STREAM_SFM_LIKE = 11
SFM_FRAME_FILE = "sfm_frame.json"


@dataclass(frozen=True)
class SfmLikeOptions:
    """Parameters of :func:`sfm_like_model`.

    pixel_noise_px : standard deviation of the observations per axis.
    max_points : window corners kept at most (random subset); all visible
        building corners are always kept.
    min_track_length : fewest observations of a kept point.
    scale_min, scale_max : the similarity's scale, log-uniform between.
    num_control_points : oblique scenes: control points chosen (farthest
        apart); street scenes use their ~30 m spaced points.
    gcp_pixel_noise_px : noise of the written control-point observations.
    gcp_sigma_m : noise of the written control-point positions (per axis),
        the points' stated accuracy.
    principal_point_error_px, focal_error : the SfM's own lens error: each
        camera's principal point moved this far (px, a seeded random
        direction) and its focal length scaled by ``1 +- focal_error`` (a
        seeded sign), then poses and points re-fitted to the tracks with
        that lens held (pycolmap's bundle adjustment), as an SfM that
        converged on a wrong lens (Herz-Jesu-P8's: the principal point 8-9
        px off). Zero: the true lens, exact relative geometry.
    """

    pixel_noise_px: float = 0.5
    max_points: int = 4000
    min_track_length: int = 2
    scale_min: float = 0.1
    scale_max: float = 10.0
    num_control_points: int = 6
    gcp_pixel_noise_px: float = 0.5
    gcp_sigma_m: float = 0.05
    principal_point_error_px: float = 0.0
    focal_error: float = 0.0


@dataclass(frozen=True)
class Similarity:
    """``X_sfm = scale * rotation @ (X_abs - origin) + translation``."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    origin: np.ndarray  # (3,) the scene's local origin (absolute)

    def apply(self, xyz_abs: np.ndarray) -> np.ndarray:
        """(N, 3) absolute points to the SfM frame."""
        local = np.asarray(xyz_abs, float).reshape(-1, 3) - self.origin
        return self.scale * local @ self.rotation.T + self.translation

    def pose(self, pose_abs: Pose) -> Pose:
        """An absolute cam_from_world in the SfM frame (camera frame scaled).

        With ``X_abs - origin = R_s^T (X_sfm - t) / s``, ``s X_cam = R R_s^T
        X_sfm + s T - R R_s^T t`` (T the local translation): same pixels.
        """
        R = pose_abs.rotation @ self.rotation.T
        T_local = pose_abs.translation + pose_abs.rotation @ self.origin
        return Pose(R, self.scale * T_local - R @ self.translation)

    def inverse_pose(self, pose_sfm: Pose) -> Pose:
        """A cam_from_world of the SfM frame back in the ABSOLUTE frame."""
        R = pose_sfm.rotation @ self.rotation
        T_local = (pose_sfm.translation + pose_sfm.rotation @ self.translation) / (
            self.scale
        )
        return Pose(R, T_local - R @ self.origin)

    def inverse_block(self, block: Block) -> Block:
        """A block of the SfM frame in the ABSOLUTE frame (same ids and cameras)."""
        images = {
            i: ImageRecord(
                im.image_id, im.name, im.camera_id, self.inverse_pose(im.cam_from_world)
            )
            for i, im in block.images.items()
        }
        return Block(dict(block.cameras), images)

    def to_json(self) -> dict:
        return {
            "transform": "X_sfm = scale * rotation @ (X_abs - origin) + translation",
            "scale": float(self.scale),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "origin": self.origin.tolist(),
        }


def random_similarity(
    seed: int, origin: np.ndarray, options: SfmLikeOptions
) -> Similarity:
    """A seeded random similarity: any rotation, log-uniform scale, t ~ N(0, 10)."""
    rng = stream(seed, STREAM_SFM_LIKE, 1)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    angle = 2.0 * np.arccos(np.clip(abs(q[0]), -1.0, 1.0))
    axis = q[1:] / max(np.linalg.norm(q[1:]), 1e-12)
    R = rotation_from_axis_angle(angle * axis)
    scale = float(
        np.exp(rng.uniform(np.log(options.scale_min), np.log(options.scale_max)))
    )
    return Similarity(scale, R, rng.normal(0.0, 10.0, 3), np.asarray(origin, float))


def scene_points(scene: SyntheticScene) -> tuple[np.ndarray, int]:
    """(N, 3) local candidate points: building corners, then window-frame corners.

    Returns the points and the number of building corners first (whose
    visibility is the scene's ``visible_corners``, not a depth test).
    """
    corners = C.corners(scene.city)["xyz"]
    edges = scene.vertical_edges
    tex = edges["kind"] == 1
    windows = np.concatenate([edges["p0"][tex], edges["p1"][tex]])
    return np.concatenate([corners, windows]), len(corners)


def true_tracks(
    scene: SyntheticScene, options: SfmLikeOptions, seed: int
) -> list[Point3D]:
    """Points (ABSOLUTE) with noisy observations in the true images.

    Window corners are depth-tested against each image's z-buffer; building
    corners use the scene's visible corners. Points seen fewer than
    ``min_track_length`` times are dropped, and window corners beyond
    ``max_points`` (a random subset is kept).
    """
    rng = stream(seed, STREAM_SFM_LIKE, 2)
    pts, n_corners = scene_points(scene)
    visible_corners = scene.buildings["visible_corners"]
    obs: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(len(pts))]
    for im in sorted(scene.gt_local.images.values(), key=lambda i: i.image_id):
        camera = scene.gt_local.cameras[im.camera_id]
        seen, xy = points_visible(camera, im.cam_from_world, scene.depth(im.name), pts)
        seen[:n_corners] = np.isin(
            np.arange(n_corners), visible_corners.get(im.name, [])
        )
        noisy = xy + rng.normal(0.0, options.pixel_noise_px, xy.shape)
        with np.errstate(invalid="ignore"):
            inside = (
                (noisy[:, 0] >= 0)
                & (noisy[:, 0] < camera.width)
                & (noisy[:, 1] >= 0)
                & (noisy[:, 1] < camera.height)
            )
        for i in np.nonzero(seen & inside)[0]:
            obs[i].append((im.image_id, noisy[i]))
    n_obs = np.array([len(o) for o in obs])
    keep = np.nonzero(n_obs >= options.min_track_length)[0]
    windows = keep[keep >= n_corners]
    if len(windows) > options.max_points:
        windows = np.sort(rng.choice(windows, options.max_points, replace=False))
    keep = np.concatenate([keep[keep < n_corners], windows])
    return [Point3D(pts[i] + scene.origin, obs[i]) for i in keep]


def scene_control_points(
    scene: SyntheticScene, options: SfmLikeOptions
) -> ControlPoints:
    """The true control points of a scene (ABSOLUTE, exact observations).

    Street scenes: their ~30 m spaced points (``gcp_list.txt``). Oblique
    scenes: ground corners of mapped buildings seen in >= 3 images,
    ``num_control_points`` of them by farthest-point sampling (a block's
    corners, as a surveyor spreads them).
    """
    corners = C.corners(scene.city)
    visible = scene.buildings["visible_corners"]
    if scene.options.scene_kind == "street":
        return read_gcp_list(scene.path / "gcp_list.txt")
    n_views = np.zeros(len(corners["xyz"]), int)
    for idx in visible.values():
        n_views[np.asarray(idx, int)] += 1
    in_map = {b.id: b.in_map for b in scene.city.buildings}
    mapped = np.array([in_map[b] for b in corners["building"]], bool)
    ground = np.asarray(corners["kind"]) == "ground"
    cand = np.nonzero(mapped & ground & (n_views >= 3))[0]
    xy = corners["xyz"][cand, :2]
    chosen = [int(np.argmax(np.linalg.norm(xy - xy.mean(0), axis=1)))]
    dist = np.linalg.norm(xy - xy[chosen[0]], axis=1)
    while len(chosen) < min(options.num_control_points, len(cand)):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(xy - xy[chosen[-1]], axis=1))
    points = []
    for k, c in enumerate(cand[chosen]):
        obs = []
        for im in scene.gt_local.images.values():
            if c in set(visible.get(im.name, ())):
                cam = scene.gt_local.cameras[im.camera_id]
                p, _ = project(cam, im.cam_from_world, corners["xyz"][c][None])
                obs.append(ControlObservation(im.name, p[0]))
        points.append(
            ControlPoint(f"gcp_{k:02d}_ground", corners["xyz"][c] + scene.origin, obs)
        )
    return ControlPoints(points, scene.crs)


def noisy_control_points(
    control: ControlPoints, options: SfmLikeOptions, seed: int
) -> ControlPoints:
    """``control`` as a user measured it: positions and observations with noise."""
    rng = stream(seed, STREAM_SFM_LIKE, 3)
    points = []
    for p in control.points:
        xyz = p.xyz + rng.normal(0.0, options.gcp_sigma_m, 3)
        obs = [
            ControlObservation(
                o.image_name, o.xy + rng.normal(0.0, options.gcp_pixel_noise_px, 2)
            )
            for o in p.observations
        ]
        points.append(
            ControlPoint(p.name, xyz, obs, options.gcp_sigma_m, options.gcp_sigma_m)
        )
    return ControlPoints(points, control.crs)


def sfm_like_model(
    scene: SyntheticScene, options: SfmLikeOptions, seed: int
) -> tuple[Block, list[Point3D], Similarity]:
    """The true block and tracks moved into a random similarity frame."""
    sim = random_similarity(seed, scene.origin, options)
    points = true_tracks(scene, options, seed)
    block = Block(
        {i: c for i, c in scene.gt.cameras.items()},
        {
            i: ImageRecord(
                im.image_id, im.name, im.camera_id, sim.pose(im.cam_from_world)
            )
            for i, im in scene.gt.images.items()
        },
    )
    moved = [Point3D(sim.apply(p.xyz)[0], p.observations) for p in points]
    return block, moved, sim


def with_lens_error(rec, options: SfmLikeOptions, seed: int) -> None:
    """``rec`` (a pycolmap.Reconstruction) with its cameras' lens made wrong
    as ``options`` say and its poses and points re-fitted to its tracks with
    that lens held; in place. Each camera gets its own error."""
    import pycolmap

    rng = stream(seed, STREAM_SFM_LIKE, 2)
    for cid in sorted(rec.cameras):
        cam = rec.cameras[cid]
        params = np.array(cam.params, float)
        phi = rng.uniform(0.0, 2.0 * np.pi)
        sign = rng.choice([-1.0, 1.0])
        for k in cam.focal_length_idxs():
            params[k] *= 1.0 + sign * options.focal_error
        pp = list(cam.principal_point_idxs())
        params[pp] += options.principal_point_error_px * np.array(
            [np.cos(phi), np.sin(phi)]
        )
        cam.params = params
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = False
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.ceres.solver_options.max_num_iterations = 200
    pycolmap.bundle_adjustment(rec, ba)


def write_sfm_like(
    output_path: str | Path,
    scene: SyntheticScene,
    options: SfmLikeOptions | None = None,
    *,
    seed: int = 0,
) -> Path:
    """Write an SfM-like model folder atomically.

    Layout: ``cameras.bin images.bin points3D.bin`` (the model),
    ``gcp_list.txt`` (noisy control points, the scene's CRS),
    ``gcp_true.txt`` (the same points exact) and ``sfm_frame.json`` (the
    similarity and the options).
    """
    options = options or SfmLikeOptions()
    block, points, sim = sfm_like_model(scene, options, seed)
    control = scene_control_points(scene, options)
    rec = to_reconstruction(block, points)
    if options.principal_point_error_px or options.focal_error:
        with_lens_error(rec, options, seed)
    with AtomicFolder(Path(output_path)) as tmp:
        rec.write_binary(str(tmp))
        write_gcp_list(
            tmp / "gcp_list.txt", noisy_control_points(control, options, seed)
        )
        write_gcp_list(tmp / "gcp_true.txt", control)
        doc = {
            **sim.to_json(),
            "scene": str(scene.path),
            "seed": int(seed),
            "options": asdict(options),
            "num_points3D": len(points),
            "control_points": control.names(),
        }
        (tmp / SFM_FRAME_FILE).write_text(json.dumps(doc, indent=2) + "\n")
    return Path(output_path)


def read_similarity(model_path: str | Path) -> Similarity:
    """The similarity of an SfM-like model folder (its ``sfm_frame.json``)."""
    doc = json.loads((Path(model_path) / SFM_FRAME_FILE).read_text())
    return Similarity(
        float(doc["scale"]),
        np.asarray(doc["rotation"], float),
        np.asarray(doc["translation"], float),
        np.asarray(doc["origin"], float),
    )


def write_pycolmap_sfm(
    output_path: str | Path,
    scene: SyntheticScene,
    options: SfmLikeOptions | None = None,
    *,
    seed: int = 0,
    overlap: int = 10,
    num_threads: int = 2,
) -> Path:
    """A real SfM model of the scene's images by pycolmap, as a user makes one.

    SIFT on the CPU (one shared SIMPLE_RADIAL camera, intrinsics unknown),
    sequential matching over ``overlap`` neighbours in walking order (street
    scenes; exhaustive otherwise), incremental mapping; the largest
    reconstruction is written with the same ``gcp_list.txt`` /
    ``gcp_true.txt`` as :func:`write_sfm_like`.

    Raises
    ------
    RuntimeError
        pycolmap reconstructed nothing.
    """
    import pycolmap

    options = options or SfmLikeOptions()
    control = scene_control_points(scene, options)
    with AtomicFolder(Path(output_path)) as tmp:
        work = tmp / "work"
        work.mkdir()
        database = work / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.use_gpu = False
        pycolmap.extract_features(
            database,
            scene.path / "images",
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        matching.use_gpu = False
        if scene.options.scene_kind == "street":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = overlap
            pycolmap.match_sequential(
                database,
                matching_options=matching,
                pairing_options=pairing,
                device=pycolmap.Device.cpu,
            )
        else:  # a flight's file order is no sequence
            pycolmap.match_exhaustive(
                database, matching_options=matching, device=pycolmap.Device.cpu
            )
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.num_threads = num_threads
        mapping.random_seed = seed
        recs = pycolmap.incremental_mapping(
            database, scene.path / "images", work / "sparse", options=mapping
        )
        if not recs:
            raise RuntimeError(f"pycolmap reconstructed nothing from {scene.path}")
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        rec.write_binary(str(tmp))
        write_gcp_list(
            tmp / "gcp_list.txt", noisy_control_points(control, options, seed)
        )
        write_gcp_list(tmp / "gcp_true.txt", control)
        for f in sorted(work.rglob("*"), reverse=True):
            f.unlink() if f.is_file() else f.rmdir()
        work.rmdir()
    return Path(output_path)
