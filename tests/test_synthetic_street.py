"""Street scenes, near-plane clipping, SfM-like models and the georegister score.

Ground truth is analytic (a camera above a plane), the scene's own (its true
cameras and corners) or a known similarity; tolerances are float precision
or derived from the injected noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from obliq_colmap.colmap_io import Block, ImageRecord, read_model
from obliq_colmap.control.model import ControlObservation, ControlPoint, ControlPoints
from obliq_colmap.geometry import (
    Camera,
    Pose,
    project,
    rotation_from_axis_angle,
)
from obliq_colmap.synthetic import build_city, generate_scene, load_scene, preset
from obliq_colmap.synthetic.cameras import rotation_from_angles
from obliq_colmap.synthetic.city import toy_city
from obliq_colmap.synthetic.georef_score import (
    block_rotation,
    heading_error_deg,
    score_block,
    vertical_error_deg,
)
from obliq_colmap.synthetic.render import render_depth
from obliq_colmap.synthetic.sfm_like import (
    SfmLikeOptions,
    random_similarity,
    read_similarity,
    write_sfm_like,
)
from obliq_colmap.synthetic.street import (
    choose_street,
    read_gcp_list,
    street_block,
    write_gcp_list,
)

FLOAT_TOL = 1e-9


def random_block(n: int, seed: int) -> Block:
    rng = np.random.default_rng(seed)
    cam = Camera("SIMPLE_RADIAL", 400, 300, [300.0, 200.0, 150.0, -0.02], 1)
    block = Block({1: cam})
    for i in range(1, n + 1):
        R = rotation_from_angles(rng.uniform(0, 360), rng.uniform(60, 100), 0.0)
        block.images[i] = ImageRecord(
            i, f"im{i}.jpg", 1, Pose.from_center(R, rng.normal(0, 30, 3))
        )
    return block


# --------------------------------------------------------------------------
# renderer: a camera inside the city
# --------------------------------------------------------------------------


def test_ground_under_a_street_camera_is_rendered_exactly():
    """Big ground triangles reaching behind the camera are clipped, not dropped.

    Every pixel whose ray points down sees the plane z = 0 at the analytic
    depth (before clipping, the triangles crossing the near plane left the
    ground near the camera empty).
    """
    big = 500.0
    tris = np.array(
        [
            [[-big, -big, 0], [big, -big, 0], [big, big, 0]],
            [[-big, -big, 0], [big, big, 0], [-big, big, 0]],
        ]
    )
    city = toy_city(tris, np.full((2, 3), 0.5), preset("street"))
    cam = Camera("PINHOLE", 160, 120, [100.0, 100.0, 80.0, 60.0], 1)
    h = 1.6
    pose = Pose.from_center(rotation_from_angles(30.0, 80.0, 3.0), [2.0, 5.0, h])
    depth, _ = render_depth(city, cam, pose)
    jj, ii = np.meshgrid(np.arange(160) + 0.5, np.arange(120) + 0.5)
    rays = np.stack([(jj - 80.0) / 100.0, (ii - 60.0) / 100.0, np.ones_like(jj)], -1)
    down = -(rays @ pose.rotation)[..., 2]  # world z of each ray, negated
    t = np.where(down > 1e-3, h / np.maximum(down, 1e-3), np.inf)
    hit = pose.center + t[..., None] * (rays @ pose.rotation)
    below = (down > 1e-3) & (np.abs(hit[..., :2]).max(-1) < big - 1.0)
    assert below.sum() > 0.3 * below.size
    expected = t[below]
    np.testing.assert_allclose(depth[below], expected, rtol=1e-4)
    assert np.isinf(depth[down < -1e-3]).all()  # sky above the horizon


# --------------------------------------------------------------------------
# the walk
# --------------------------------------------------------------------------


def test_street_walk_is_a_phone_on_the_sidewalk():
    options = preset("street", street_num_images=12)
    city = build_city(options, 1)
    block = street_block(city, options, 1)
    walk = choose_street(city)
    centres = np.array(
        [block.images[i].cam_from_world.center for i in sorted(block.images)]
    )
    ground = city.terrain.height(centres[:, 0], centres[:, 1])
    jitter = 4 * options.street_jitter_m  # 4 sigma
    assert np.all(np.abs(centres[:, 2] - ground - 1.6) < jitter / 2 + 1e-9)
    steps = np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1)
    assert np.all(np.abs(steps - options.street_step_m) < 2 * jitter)
    # facades across the street 10-20 m away: street width minus half a sidewalk
    assert 10.0 <= walk.street_width_m - 1.375 <= 21.0
    # sideways and slightly forward, pitched up
    for im in block.images.values():
        axis = im.cam_from_world.rotation[2]
        fwd = np.degrees(
            np.arctan2(axis[:2] @ walk.direction, axis[:2] @ walk.facade_normal)
        )
        pitch = np.degrees(np.arcsin(axis[2]))
        assert abs(fwd - options.street_forward_deg) < 4 * options.street_jitter_deg + 1
        assert abs(pitch - options.street_pitch_deg) < 4 * options.street_jitter_deg + 1
    assert block.cameras[1].model == "SIMPLE_RADIAL"


def test_gcp_list_round_trip_and_pixel_convention(tmp_path):
    obs = [ControlObservation("a.jpg", np.array([10.5, 20.5]))]
    cp = ControlPoints(
        [ControlPoint("p1", np.array([512000.25, 5643000.5, 101.0]), obs)], "EPSG:25832"
    )
    path = tmp_path / "gcp_list.txt"
    assert write_gcp_list(path, cp) == 1
    lines = path.read_text().splitlines()
    assert lines[0] == "EPSG:25832"
    # OpenSfM: the top-left pixel's centre at (0, 0), COLMAP's minus 0.5
    assert lines[1].split()[3:7] == ["10.000", "20.000", "a.jpg", "p1"]
    back = read_gcp_list(path)
    assert back.crs == "EPSG:25832" and back.names() == ["p1"]
    np.testing.assert_allclose(back.points[0].xyz, cp.points[0].xyz)
    np.testing.assert_allclose(back.points[0].observations[0].xy, [10.5, 20.5])


# --------------------------------------------------------------------------
# similarity and score
# --------------------------------------------------------------------------


def test_similarity_keeps_every_pixel_and_inverts():
    block = random_block(5, 3)
    origin = np.array([512340.0, 5643870.0, 100.0])
    sim = random_similarity(4, origin, SfmLikeOptions())
    X = origin + np.random.default_rng(5).normal(0, 20, (50, 3))
    cam = block.cameras[1]
    for im in block.images.values():
        pose = im.cam_from_world
        P_abs = Pose(pose.rotation, pose.translation - pose.rotation @ origin)
        xy0, z0 = project(cam, P_abs, X)
        xy1, z1 = project(cam, sim.pose(P_abs), sim.apply(X))
        front = z0 > 0
        np.testing.assert_allclose(xy1[front], xy0[front], atol=1e-6)
        back = sim.inverse_pose(sim.pose(P_abs))
        np.testing.assert_allclose(back.matrix(), P_abs.matrix(), atol=1e-6)


@pytest.mark.parametrize("tilt_deg", [0.03, 0.5])
def test_block_vertical_and_heading_errors(tilt_deg):
    gt = random_block(8, 1)
    heading = 2.0
    W = rotation_from_axis_angle(
        [np.radians(tilt_deg), 0, 0]
    ) @ rotation_from_axis_angle([0, 0, np.radians(heading)])
    est = Block(
        gt.cameras,
        {
            i: ImageRecord(
                im.image_id,
                im.name,
                1,
                Pose(im.cam_from_world.rotation @ W.T, im.cam_from_world.translation),
            )
            for i, im in gt.images.items()
        },
    )
    Wb = block_rotation(est, gt)
    np.testing.assert_allclose(Wb, W, atol=FLOAT_TOL)
    assert vertical_error_deg(Wb) == pytest.approx(tilt_deg, abs=1e-9)
    assert heading_error_deg(Wb) == pytest.approx(heading, abs=1e-3)


# --------------------------------------------------------------------------
# a whole street scene and its SfM-like model
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def street_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("street") / "scene"
    options = preset("street", street_num_images=30, image_width_px=240)
    generate_scene(path, options, seed=1, show_progress=False, num_workers=1)
    return load_scene(path)


@pytest.mark.slow
def test_street_scene_control_points_and_buildings(street_scene):
    """gcp_list.txt: >= 3 points ~30 m apart, observations = true projections."""
    control = read_gcp_list(street_scene.path / "gcp_list.txt")
    assert control.crs == street_scene.crs
    assert len(control) >= 3
    xyz = control.xyz()
    along = (xyz[:, :2] - street_scene.origin[:2]) @ choose_street(
        street_scene.city
    ).direction
    assert np.all(np.diff(np.sort(along)) > 20.0)
    for p in control.points:
        assert len(p.observations) >= 3
        for ob in p.observations:
            cam, pose = street_scene.camera_pose(ob.image_name)
            xy, z = project(cam, pose, p.xyz[None] - street_scene.origin)
            assert z[0] > 0
            np.testing.assert_allclose(ob.xy, xy[0], atol=1e-3)  # file: 3 decimals
    # >= 6 mapped buildings in view along the street
    b = street_scene.buildings
    mapped = {x["id"] for x in b["buildings"] if x["in_map"]}
    seen = {b["corner_building"][i] for v in b["visible_corners"].values() for i in v}
    assert len(seen & mapped) >= 6


@pytest.mark.slow
def test_sfm_like_model_reprojects_at_its_noise_and_scores_zero(street_scene, tmp_path):
    options = SfmLikeOptions(pixel_noise_px=0.5)
    out = write_sfm_like(tmp_path / "sfm", street_scene, options, seed=2)
    import pycolmap

    rec = pycolmap.Reconstruction(str(out))
    n = rec.compute_num_observations()
    assert rec.num_points3D() > 100
    # mean of |2D Gaussian| = sigma sqrt(pi / 2); 4 standard errors
    mean = options.pixel_noise_px * np.sqrt(np.pi / 2)
    sd = options.pixel_noise_px * np.sqrt(2 - np.pi / 2)
    assert abs(rec.compute_mean_reprojection_error() - mean) < 4 * sd / np.sqrt(n)
    sim = read_similarity(out)
    assert sim.scale != pytest.approx(1.0, abs=1e-3)
    score = score_block(sim.inverse_block(read_model(out)), street_scene)
    assert score["vertical_error_deg"] < 1e-6
    assert score["center_error_max_m"] < 1e-6
    assert score["deviation_median_px"] < 1e-6
    assert score["below_2px"] == 1.0
