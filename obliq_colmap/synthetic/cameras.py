"""The oblique flight: a four-headed camera, its image grid, true and prior poses.

All poses here are in the LOCAL frame of the city (``world_abs = local +
origin``); :mod:`obliq_colmap.synthetic.scene_io` shifts them to absolute
coordinates when writing.

One physical camera per viewing direction (a multi-head oblique system), so
the images of one direction share a ``camera_id``. Each direction has a
``grid_rows x grid_cols`` grid of aim points centred on the scene centre,
spaced so that neighbouring footprints overlap by ``options.overlap``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from obliq_colmap.colmap_io import Block, ImageRecord
from obliq_colmap.geometry import Camera, Pose, rotation_from_axis_angle
from obliq_colmap.synthetic.options import REFERENCE_WIDTH_PX, SceneOptions

#: Viewing directions: name -> (camera_id, heading clockwise from north, deg).
DIRECTIONS: dict[str, tuple[int, float]] = {
    "N": (1, 0.0),
    "E": (2, 90.0),
    "S": (3, 180.0),
    "W": (4, 270.0),
}
#: The nadir head of a five-camera system (``SceneOptions.nadir_head``):
#: name, camera_id; its images' tops face north.
NADIR = ("D", 5)


def heads(options: SceneOptions) -> dict[str, tuple[int, float, float]]:
    """The flight's heads: name -> (camera_id, heading deg, nominal tilt deg)."""
    out = {d: (cid, h, options.tilt_deg) for d, (cid, h) in DIRECTIONS.items()}
    if options.nadir_head:
        out[NADIR[0]] = (NADIR[1], 0.0, 0.0)
    return out


# Independent random streams derived from the scene seed.
STREAM_CITY = 1
STREAM_CADASTRE = 2
STREAM_FLIGHT = 3
STREAM_PRIORS = 4
STREAM_RENDER = 5


def stream(seed: int, *keys: int) -> np.random.Generator:
    """A numpy Generator for one purpose (``keys``) of the scene ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), *map(int, keys)]))


@dataclass
class FlightGeometry:
    """Derived nominal numbers of the flight (independent of the image width).

    Attributes
    ----------
    focal_ref_px : focal length at the reference width, px.
    distance_m : distance camera - aim point along the optical axis, m.
    altitude_m : nominal camera height above the local ground z = 0, m.
    spacing_along_m, spacing_across_m : aim-point grid spacings, m.
    """

    focal_ref_px: float
    distance_m: float
    altitude_m: float
    spacing_along_m: float
    spacing_across_m: float


def flight_geometry(options: SceneOptions) -> FlightGeometry:
    """Nominal distances and grid spacings from the options."""
    half_w = REFERENCE_WIDTH_PX / 2.0
    f_ref = half_w / np.tan(np.radians(options.horizontal_fov_deg) / 2.0)
    distance = options.gsd_m * f_ref
    tilt = np.radians(options.tilt_deg)
    altitude = distance * np.cos(tilt)
    half_v = np.arctan((REFERENCE_WIDTH_PX / options.image_aspect) / 2.0 / f_ref)
    near = altitude * np.tan(tilt - half_v)
    far = altitude * np.tan(tilt + half_v)
    return FlightGeometry(
        focal_ref_px=float(f_ref),
        distance_m=float(distance),
        altitude_m=float(altitude),
        spacing_along_m=float((1.0 - options.overlap) * (far - near)),
        spacing_across_m=float(
            (1.0 - options.overlap) * REFERENCE_WIDTH_PX * options.gsd_m
        ),
    )


def rotation_from_angles(
    heading_deg: float, tilt_deg: float, roll_deg: float
) -> np.ndarray:
    """``cam_from_world`` rotation of a camera with heading, tilt and roll.

    heading: clockwise from north of the horizontal viewing direction; tilt:
    angle of the optical axis from the nadir; roll: about the optical axis.
    At roll 0 the image x axis is horizontal (pointing right of the view).
    """
    h, t = np.radians(heading_deg), np.radians(tilt_deg)
    z_cam = np.array([np.sin(t) * np.sin(h), np.sin(t) * np.cos(h), -np.cos(t)])
    # Right of the heading: the same as z x up for any tilt > 0, and defined
    # at the nadir (tilt 0) and through it (a jittered nadir camera).
    x_cam = np.array([np.cos(h), -np.sin(h), 0.0])
    y_cam = np.cross(z_cam, x_cam)
    R0 = np.stack([x_cam, y_cam, z_cam])
    r = np.radians(roll_deg)
    R_roll = np.array(
        [[np.cos(r), -np.sin(r), 0.0], [np.sin(r), np.cos(r), 0.0], [0, 0, 1.0]]
    )
    return R_roll @ R0


@dataclass
class NominalImage:
    """One image of the flight plan before jitter (local frame)."""

    name: str
    direction: str
    row: int
    col: int
    heading_deg: float
    center: np.ndarray  # (3,) metres
    tilt_deg: float = 45.0


def flight_plan(options: SceneOptions) -> list[NominalImage]:
    """The nominal images: each head x rows x cols, ordered by head (the four
    oblique directions, then the nadir head where there is one)."""
    geo = flight_geometry(options)
    # The nadir footprint at the same height: square pixels of altitude / f.
    nadir_step = (1.0 - options.overlap) * REFERENCE_WIDTH_PX * geo.altitude_m
    nadir_step /= geo.focal_ref_px
    plan = []
    for d, (_, heading, tilt_deg) in heads(options).items():
        h, tilt = np.radians(heading), np.radians(tilt_deg)
        fwd = np.array([np.sin(h), np.cos(h)])
        right = np.array([np.cos(h), -np.sin(h)])
        view = np.array([np.sin(tilt) * fwd[0], np.sin(tilt) * fwd[1], -np.cos(tilt)])
        along_m, across_m = geo.spacing_along_m, geo.spacing_across_m
        distance = geo.distance_m
        if tilt_deg == 0.0:  # the image's height lies along the heading
            along_m, across_m = nadir_step / options.image_aspect, nadir_step
            distance = geo.altitude_m
        for r in range(options.grid_rows):
            for c in range(options.grid_cols):
                along = (r - (options.grid_rows - 1) / 2.0) * along_m
                across = (c - (options.grid_cols - 1) / 2.0) * across_m
                aim = np.array([*(along * fwd + across * right), 0.0])
                center = aim - distance * view
                plan.append(
                    NominalImage(f"{d}_{r}{c}.jpg", d, r, c, heading, center, tilt_deg)
                )
    return plan


def city_extent(options: SceneOptions) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) local metres that every camera footprint lies in.

    The image corners of the nominal cameras are intersected with a ground
    plane lowered by the largest terrain drop, plus jitter and margin. A
    street scene's city is a square of ``street_city_half_size_m`` instead.
    """
    if options.scene_kind == "street":
        h = float(options.street_city_half_size_m)
        return -h, -h, h, h
    geo = flight_geometry(options)
    f = geo.focal_ref_px
    w, h = REFERENCE_WIDTH_PX, REFERENCE_WIDTH_PX / options.image_aspect
    # Corner rays with 5 % slack for jitter and distortion.
    corners = np.array(
        [[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]]
    )
    rays_cam = np.hstack([1.05 * corners / f, np.ones((4, 1))])
    drop = np.tan(np.radians(options.slope_deg)) * 600.0 + options.undulation_m + 5.0
    pts = []
    for im in flight_plan(options):
        R = rotation_from_angles(im.heading_deg, im.tilt_deg, 0.0)
        rays = rays_cam @ R  # (4, 3) world directions (R^T applied)
        s = (-drop - im.center[2]) / rays[:, 2]
        pts.append(im.center[:2] + s[:, None] * rays[:, :2])
    pts = np.concatenate(pts)
    m = options.margin_m
    lo, hi = pts.min(0) - m, pts.max(0) + m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def true_cameras(options: SceneOptions, seed: int) -> dict[int, Camera]:
    """The true cameras (one per head), COLMAP model of the options."""
    rng = stream(seed, STREAM_FLIGHT, 1)
    W, H = options.image_width_px, options.image_height_px
    scale = W / REFERENCE_WIDTH_PX
    f_nom = (W / 2.0) / np.tan(np.radians(options.horizontal_fov_deg) / 2.0)
    cameras = {}
    for camera_id, _, _ in heads(options).values():
        f = f_nom * (1.0 + rng.uniform(-options.focal_spread, options.focal_spread))
        dx, dy = rng.uniform(-1.0, 1.0, 2) * options.principal_point_offset_px * scale
        cx, cy = W / 2.0 + dx, H / 2.0 + dy
        k1 = options.distortion_k1 * (1.0 + rng.uniform(-0.1, 0.1))
        k2 = options.distortion_k2
        p = options.distortion_p
        if options.distortion == "none":
            params = [f, f, cx, cy]
        elif options.distortion == "simple_radial":
            params = [f, cx, cy, k1]
        elif options.distortion == "radial":
            params = [f, cx, cy, k1, k2]
        else:
            params = [f, f, cx, cy, k1, k2, p, -0.5 * p]
        cameras[camera_id] = Camera(options.camera_model, W, H, params, camera_id)
    return cameras


def true_block(options: SceneOptions, seed: int) -> Block:
    """True cameras and poses (local frame) of all images, with flight jitter."""
    rng = stream(seed, STREAM_FLIGHT, 2)
    block = Block(cameras=true_cameras(options, seed))
    for image_id, im in enumerate(flight_plan(options), start=1):
        heading = im.heading_deg + rng.normal(0.0, options.jitter_heading_deg)
        tilt = im.tilt_deg + rng.normal(0.0, options.jitter_tilt_deg)
        roll = rng.normal(0.0, options.jitter_roll_deg)
        center = im.center + np.array(
            [
                rng.normal(0.0, options.jitter_position_m),
                rng.normal(0.0, options.jitter_position_m),
                rng.normal(0.0, options.jitter_altitude_m),
            ]
        )
        R = rotation_from_angles(heading, tilt, roll)
        camera_id = heads(options)[im.direction][0]
        block.images[image_id] = ImageRecord(
            image_id, im.name, camera_id, Pose.from_center(R, center)
        )
    return block


def prior_block(options: SceneOptions, seed: int, gt: Block) -> Block:
    """Rough priors from the true block (same frame, ids, names and models).

    Position noise per axis (horizontal / vertical standard deviations), a
    rotation error with normally distributed axis-angle components, a focal
    error per camera of magnitude uniform in [p/2, p] percent with a random
    sign, the principal point at the exact image centre, no distortion, and
    every camera z raised by the vertical datum offset.
    """
    rng = stream(seed, STREAM_PRIORS)
    block = Block()
    for camera_id in sorted(gt.cameras):
        cam = gt.cameras[camera_id]
        p = options.prior_focal_percent / 100.0
        rel = rng.uniform(0.5 * p, p) * rng.choice([-1.0, 1.0])
        params = np.zeros_like(cam.params)
        f = cam.K[0, 0] * (1.0 + rel)
        cx, cy = cam.width / 2.0, cam.height / 2.0
        if cam.model in ("PINHOLE", "OPENCV"):
            params[:4] = [f, f, cx, cy]
        else:  # SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL: f, cx, cy, ...
            params[:3] = [f, cx, cy]
        block.cameras[camera_id] = Camera(
            cam.model, cam.width, cam.height, params, camera_id
        )
    sigma = np.array(
        [options.prior_position_m, options.prior_position_m, options.prior_height_m]
    )
    offset = np.array([0.0, 0.0, options.prior_vertical_datum_offset_m])
    for image_id in sorted(gt.images):
        im = gt.images[image_id]
        center = im.cam_from_world.center + rng.normal(0.0, 1.0, 3) * sigma + offset
        omega = rng.normal(0.0, np.radians(options.prior_rotation_deg), 3)
        R = rotation_from_axis_angle(omega) @ im.cam_from_world.rotation
        block.images[image_id] = ImageRecord(
            image_id, im.name, im.camera_id, Pose.from_center(R, center)
        )
    return block
