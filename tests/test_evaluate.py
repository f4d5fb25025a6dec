"""Evaluation against ground truth: exact cases, known perturbations, files and CLI."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from obliq_colmap import colmap_io as io
from obliq_colmap.cli import main
from obliq_colmap.errors import InputError
from obliq_colmap.evaluate import (
    EvaluateOptions,
    evaluate_baseline,
    evaluate_block,
    evaluate_model,
    read_ground_truth,
    search_block_offset,
)
from obliq_colmap.geometry import (
    Camera,
    Pose,
    project,
    rotation_from_axis_angle,
)

ORIGIN = np.array([512300.0, 5612400.0, 130.0])  # absolute UTM, as in the scenes
CRS = "EPSG:25832"
FX = 2000.0
CAMERAS = {
    1: Camera("PINHOLE", 2000, 1500, [FX, FX, 1000.0, 750.0], camera_id=1),
    2: Camera(
        "OPENCV",
        2000,
        1500,
        [FX, 2010.0, 1003.0, 748.0, -0.06, 0.01, 5e-4, -3e-4],
        camera_id=2,
    ),
}
HEADINGS_DEG = (0.0, 90.0, 180.0, 270.0)  # N, E, S, W
DISTANCE_M, HEIGHT_M = 300.0, 300.0

# Tolerances, named with units.
EXACT_PX = 1e-6
EXACT_M = 1e-7
EXACT_DEG = 1e-9


def look_at(center, target):
    """cam_from_world of a roll-free camera at ``center`` looking at ``target``."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose.from_center(np.stack([x, y, z]), center)


def image_name(k):
    return f"cam_{k}/img_{k:03d}.jpg"


def make_gt_block():
    """Four oblique views (45 deg) of the origin, absolute frame."""
    images = {}
    for k, heading in enumerate(HEADINGS_DEG):
        a = np.radians(heading)
        # Camera south of the target for heading 0 (looking north), etc.
        c = ORIGIN + [-DISTANCE_M * np.sin(a), -DISTANCE_M * np.cos(a), HEIGHT_M]
        camera_id = 1 if k < 2 else 2
        images[k + 1] = io.ImageRecord(
            k + 1, image_name(k), camera_id, look_at(c, ORIGIN)
        )
    return io.Block({i: replace(c) for i, c in CAMERAS.items()}, images)


def make_corners():
    """(K, 3) absolute corners of a few box buildings: ground and eave."""
    xy = np.array(
        [[x, y] for x in (-60.0, -20.0, 20.0, 60.0) for y in (-50.0, 0.0, 50.0)]
    )
    ground = np.column_stack([xy, np.zeros(len(xy))])
    eave = np.column_stack([xy, np.full(len(xy), 15.0)])
    return np.vstack([ground, eave]) + ORIGIN


def visible_in(block, corners):
    """Corners projecting inside each true image (no occlusion here)."""
    out = {}
    for im in block.images.values():
        cam = block.cameras[im.camera_id]
        xy, z = project(cam, im.cam_from_world, corners)
        inside = (
            (z > 0)
            & (xy[:, 0] >= 0)
            & (xy[:, 0] < cam.width)
            & (xy[:, 1] >= 0)
            & (xy[:, 1] < cam.height)
        )
        out[im.name] = np.nonzero(inside)[0]
    return out


def copy_block(block):
    return block.shifted(np.zeros(3))


def set_center(block, image_id, center):
    im = block.images[image_id]
    im.cam_from_world = Pose.from_center(im.cam_from_world.rotation, center)


@pytest.fixture
def scene():
    gt = make_gt_block()
    corners = make_corners()
    visible = visible_in(gt, corners)
    assert all(len(v) == len(corners) for v in visible.values())  # all in view
    return gt, corners, visible


# --------------------------------------------------------------------------
# evaluate_block: exact cases and known perturbations
# --------------------------------------------------------------------------


@pytest.mark.parametrize("across_vertical", [False, True])
def test_gt_against_itself_is_exactly_zero(scene, across_vertical):
    gt, corners, visible = scene
    ev = evaluate_block(
        copy_block(gt),
        gt,
        corners,
        visible,
        EvaluateOptions(across_vertical=across_vertical),
    )
    assert ev.summary.num_registered == ev.summary.num_total == 4
    assert ev.summary.vertical_offset_m == 0.0
    for im in ev.images:
        assert im.status == "registered"
        assert im.num_corners == len(corners) and im.num_behind == 0
        assert im.rotation_error_deg == 0.0
        assert im.center_error_m == 0.0
        assert im.mean_deviation_px == 0.0 and im.max_deviation_px == 0.0
    assert ev.summary.deviation_max_px == 0.0


def test_rotation_about_optical_axis(scene):
    gt, corners, visible = scene
    est = copy_block(gt)
    angle_deg = 0.05
    im = est.images[2]
    c = im.cam_from_world.center
    R = (
        rotation_from_axis_angle([0.0, 0.0, np.radians(angle_deg)])
        @ im.cam_from_world.rotation
    )
    im.cam_from_world = Pose.from_center(R, c)
    ev = evaluate_block(est, gt, corners, visible)
    r = ev.image(image_name(1))
    assert r.rotation_error_deg == pytest.approx(angle_deg, abs=EXACT_DEG)
    assert r.center_error_m < EXACT_M
    # A roll of theta moves a pixel at distance rho from the principal point
    # by theta * rho: between 0 and theta * half diagonal.
    assert 0 < r.mean_deviation_px < np.radians(angle_deg) * 1250.0
    assert ev.image(image_name(0)).rotation_error_deg == 0.0
    assert ev.summary.rotation_error_median_deg == 0.0


def test_constant_vertical_shift_is_removed(scene):
    gt, corners, visible = scene
    est = copy_block(gt)
    for i, im in est.images.items():
        set_center(est, i, im.cam_from_world.center + [0.0, 0.0, 37.5])
    ev = evaluate_block(est, gt, corners, visible)
    assert ev.summary.vertical_offset_m == pytest.approx(37.5, abs=1e-9)
    assert ev.summary.num_registered == 4
    for r in ev.images:
        assert r.center_error_m < EXACT_M and abs(r.vertical_error_m) < EXACT_M
        assert r.max_deviation_px < EXACT_PX
    # Without removing it, it is an error of 37.5 m and every image fails.
    ev = evaluate_block(
        est, gt, corners, visible, EvaluateOptions(remove_vertical_offset=False)
    )
    assert ev.summary.vertical_offset_m == 0.0
    assert ev.summary.num_registered == 0
    for r in ev.images:
        assert r.center_error_m == pytest.approx(37.5, abs=1e-6)
        assert r.vertical_error_m == pytest.approx(37.5, abs=1e-6)


def test_vertical_offset_is_the_scene_datum_not_the_camera_heights(scene):
    """A camera raised and re-aimed at the same target (its height traded for
    pitch, the bundle's weak mode) still images the scene nearly right: the
    removed offset is the one its projections ask for. The median of the
    camera-height errors (``vertical_offset="cameras"``) takes the raised
    cameras' height for the datum and shifts every image's corners by ~5 px."""
    gt, corners, visible = scene
    datum, raised = 20.0, 3.0
    est = copy_block(gt)
    for i, im in est.images.items():
        c = im.cam_from_world.center + [0.0, 0.0, datum + (raised if i <= 2 else 0.0)]
        im.cam_from_world = look_at(c, ORIGIN + [0.0, 0.0, datum])
    ev = evaluate_block(est, gt, corners, visible)
    assert ev.summary.vertical_offset_m == pytest.approx(datum, abs=0.2)
    assert ev.summary.num_registered == 4
    assert ev.summary.deviation_max_px < 1.5  # the trade is exact at one depth
    old = evaluate_block(
        est, gt, corners, visible, EvaluateOptions(vertical_offset="cameras")
    )
    assert old.summary.vertical_offset_m == pytest.approx(datum + raised / 2)
    assert old.summary.num_registered == 0


def test_horizontal_shift_at_known_depth():
    """1 m sideways with all corners at depth d: deviation = f * 1 m / d."""
    gt = make_gt_block()
    depth_m = 400.0
    im = gt.images[1]  # PINHOLE
    pose = im.cam_from_world
    uv = np.array([[x, y] for x in (-0.4, 0.0, 0.3) for y in (-0.3, 0.1, 0.35)])
    corners = (
        np.column_stack([uv, np.ones(len(uv))]) * depth_m
    ) @ pose.rotation + pose.center
    visible = {im.name: np.arange(len(corners))}
    est = copy_block(gt)
    x_cam_world = pose.rotation[0]  # camera x axis: horizontal (roll-free)
    assert abs(x_cam_world[2]) < 1e-12
    set_center(est, 1, pose.center + 1.0 * x_cam_world)
    ev = evaluate_block(est, gt, corners, visible)
    r = ev.image(im.name)
    assert ev.summary.vertical_offset_m == pytest.approx(0.0, abs=1e-9)
    assert r.center_error_m == pytest.approx(1.0, abs=1e-9)
    assert r.horizontal_error_m == pytest.approx(1.0, abs=1e-9)
    assert abs(r.vertical_error_m) < 1e-9
    assert r.mean_deviation_px == pytest.approx(FX / depth_m, abs=EXACT_PX)
    assert r.max_deviation_px == pytest.approx(FX / depth_m, abs=EXACT_PX)
    assert r.status == "failed"  # 5 px >= 2 px
    # The other images have no visible corners: listed, not in the total.
    assert ev.summary.num_total == 1 and ev.summary.num_no_corners == 3
    assert ev.image(image_name(1)).status == "no_corners"
    assert ev.image(image_name(1)).rotation_error_deg == 0.0


@pytest.mark.parametrize("image_id", [1, 3])  # PINHOLE, OPENCV
def test_across_vertical_ignores_vertical_shift_only(scene, image_id):
    gt, corners, visible = scene
    name = gt.images[image_id].name
    c = gt.images[image_id].cam_from_world.center
    full, across = EvaluateOptions(), EvaluateOptions(across_vertical=True)

    up = copy_block(gt)
    set_center(up, image_id, c + [0.0, 0.0, 5.0])  # one of four: median offset 0
    r_full = evaluate_block(up, gt, corners, visible, full).image(name)
    r_across = evaluate_block(up, gt, corners, visible, across).image(name)
    assert r_full.mean_deviation_px > 10.0 and r_full.status == "failed"
    assert r_across.status == "registered"
    # Exact for a pinhole; the distorted image of a vertical is slightly curved.
    tol = (
        EXACT_PX
        if gt.cameras[gt.images[image_id].camera_id].model == "PINHOLE"
        else 0.05
    )
    assert r_across.max_deviation_px < tol

    side = copy_block(gt)
    x_cam_world = gt.images[image_id].cam_from_world.rotation[0]
    set_center(side, image_id, c + 2.0 * x_cam_world)
    r_full = evaluate_block(side, gt, corners, visible, full).image(name)
    r_across = evaluate_block(side, gt, corners, visible, across).image(name)
    assert r_across.mean_deviation_px > 0.8 * r_full.mean_deviation_px > 4.0
    assert r_across.mean_deviation_px <= r_full.mean_deviation_px + 1e-12
    assert r_across.status == "failed"


def test_missing_and_extra_images(scene):
    gt, corners, visible = scene
    est = copy_block(gt)
    del est.images[3]
    est.images[9] = io.ImageRecord(9, "not_in_gt.jpg", 1, est.images[1].cam_from_world)
    ev = evaluate_block(est, gt, corners, visible)
    assert ev.image(image_name(2)).status == "missing"
    assert np.isnan(ev.image(image_name(2)).mean_deviation_px)
    s = ev.summary
    assert (s.num_total, s.num_registered, s.num_missing, s.num_extra) == (4, 3, 1, 1)
    assert ev.extra_images == ["not_in_gt.jpg"]
    assert s.registered_fraction == 0.75
    assert s.deviation_max_px == 0.0  # over the measured images only


def test_corners_behind_the_estimated_camera_fail(scene):
    gt, corners, visible = scene
    est = copy_block(gt)
    im = est.images[4]
    turn = rotation_from_axis_angle([0.0, np.pi, 0.0])  # looks away
    im.cam_from_world = Pose.from_center(
        turn @ im.cam_from_world.rotation, im.cam_from_world.center
    )
    ev = evaluate_block(est, gt, corners, visible)
    r = ev.image(image_name(3))
    assert r.status == "behind" and r.num_behind == len(corners)
    assert np.isnan(r.mean_deviation_px)
    assert ev.summary.num_registered == 3 and ev.summary.num_behind == 1


def test_bad_arguments(scene):
    gt, corners, visible = scene
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        evaluate_block(gt, gt, corners[:, :2], visible)
    with pytest.raises(ValueError, match="indices"):
        evaluate_block(gt, gt, corners, {image_name(0): [0, len(corners)]})
    other = copy_block(gt)
    for im in other.images.values():
        im.name = "x_" + im.name
    with pytest.raises(ValueError, match="no image name in common"):
        evaluate_block(other, gt, corners, visible)
    with pytest.raises(ValueError, match="registered_threshold_px"):
        EvaluateOptions(registered_threshold_px=0.0)


# --------------------------------------------------------------------------
# Files: local result with georef.json, scene folder, CLI
# --------------------------------------------------------------------------


def write_scene(folder, gt, corners, visible, priors_dz=45.0):
    folder.mkdir()
    io.write_absolute_model(folder / "gt", gt)
    priors = copy_block(gt)
    rng = np.random.default_rng(0)
    for i, im in priors.images.items():  # another vertical datum + rough poses
        set_center(
            priors, i, im.cam_from_world.center + [*rng.normal(0, 2.0, 2), priors_dz]
        )
    io.write_absolute_model(folder / "priors", priors)
    (folder / "gt_buildings.json").write_text(
        json.dumps(
            {
                "crs": CRS,
                "corners": corners.tolist(),
                "corner_building": [0] * len(corners),
                "corner_kind": ["ground"] * len(corners),
                "buildings": [{"id": 0, "in_scene": True, "in_map": True}],
                "visible_corners": {k: v.tolist() for k, v in visible.items()},
            }
        )
    )
    return folder


@pytest.fixture
def files(tmp_path, scene):
    gt, corners, visible = scene
    scene_path = write_scene(tmp_path / "scene", gt, corners, visible)
    est = copy_block(gt)
    set_center(est, 2, est.images[2].cam_from_world.center + [0.0, 0.0, 5.0])
    local_origin = ORIGIN + [3.0, -7.0, 20.0]
    local = est.shifted(local_origin)  # X_local = X_abs - origin
    result = io.write_result(tmp_path / "result", local, io.Georef(local_origin, CRS))
    return scene_path, result


def test_evaluate_model_local_result(files):
    scene_path, result = files
    ev = evaluate_model(result, scene_path)
    assert ev.summary.vertical_offset_m == pytest.approx(0.0, abs=1e-6)
    assert ev.image(image_name(0)).max_deviation_px < EXACT_PX
    assert ev.image(image_name(0)).center_error_m < EXACT_M
    assert ev.image(image_name(0)).rotation_error_deg < 1e-6
    assert ev.image(image_name(1)).vertical_error_m == pytest.approx(5.0, abs=1e-6)
    assert ev.image(image_name(1)).status == "failed"
    assert ev.summary.num_registered == 3
    ev = evaluate_model(result, scene_path, EvaluateOptions(across_vertical=True))
    assert ev.summary.num_registered == 4
    data = ev.to_json()
    json.dumps(data, allow_nan=False)
    assert data["summary"]["num_registered"] == 4 and data["options"]["across_vertical"]


def test_evaluate_baseline(files):
    scene_path, _ = files
    ev = evaluate_baseline(scene_path)
    assert ev.result_path.endswith("priors")
    assert ev.summary.vertical_offset_m == pytest.approx(45.0, abs=4.0)
    assert ev.summary.num_total == 4
    assert ev.summary.horizontal_error_median_m > 0.5


def test_evaluate_model_bad_inputs(tmp_path, files, scene):
    scene_path, result = files
    with pytest.raises(InputError, match="does not exist"):
        evaluate_model(result, tmp_path / "nope")
    bad = tmp_path / "bad_scene"
    gt, corners, visible = scene
    write_scene(bad, gt, corners, visible)
    (bad / "gt_buildings.json").write_text(
        '{"corners": [[1, 2]], "visible_corners": {}}'
    )
    with pytest.raises(InputError, match="corners"):
        evaluate_model(result, bad)
    (bad / "gt_buildings.json").write_text("{not json")
    with pytest.raises(InputError, match="JSON"):
        evaluate_model(result, bad)
    (bad / "gt_buildings.json").unlink()
    with pytest.raises(InputError, match="gt_buildings.json"):
        evaluate_model(result, bad)
    other = copy_block(gt)
    for im in other.images.values():
        im.name = "x_" + im.name
    io.write_absolute_model(tmp_path / "other", other)
    with pytest.raises(InputError, match="no image name in common"):
        evaluate_model(tmp_path / "other", scene_path)


def _evaluate_cli(*args) -> int:
    return main(["evaluate", *map(str, args)])


def test_cli(files, tmp_path, capsys):
    scene_path, result = files
    report = tmp_path / "report.json"
    common = ("--input_path", result, "--gt_path", scene_path)
    assert _evaluate_cli(*common, "--output_path", report) == 0
    out = capsys.readouterr().out
    assert image_name(1) in out and "registered 3 / 4 images" in out
    data = json.loads(report.read_text())
    assert data["summary"]["num_registered"] == 3 and len(data["images"]) == 4

    rc = _evaluate_cli(
        "--gt_path",
        scene_path,
        "--baseline",
        "--across_vertical",
        "--registered_threshold_px",
        1.5,
    )
    assert rc == 0
    assert "baseline" in capsys.readouterr().out

    assert _evaluate_cli(*common, "--baseline", "--output_path", report) == 0
    data = json.loads(report.read_text())
    assert data["result_path"] == str(result) and data["baseline"]["result_path"]

    rc = _evaluate_cli(*common, "--vertical_offset", "cameras", "--output_path", report)
    assert rc == 0
    data = json.loads(report.read_text())
    assert data["options"]["vertical_offset"] == "cameras"
    assert data["summary"]["num_registered"] == 3


def test_unknown_vertical_offset_is_refused():
    with pytest.raises(ValueError, match="vertical_offset"):
        EvaluateOptions(vertical_offset="median")


def test_cli_errors(files, tmp_path, capsys):
    scene_path, result = files
    missing = tmp_path / "no_scene"
    rc = main(["evaluate", "--input_path", str(result), "--gt_path", str(missing)])
    assert rc == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "does not exist" in err and "Traceback" not in err
    rc = main(["evaluate", "--gt_path", str(scene_path)])
    assert rc == 2 and "--input_path is required" in capsys.readouterr().err
    rc = main(
        [
            "evaluate",
            "--input_path",
            str(result),
            "--gt_path",
            str(scene_path),
            "--output_path",
            str(tmp_path / "no_dir" / "r.json"),
        ]
    )
    assert rc == 2 and "no_dir" in capsys.readouterr().err


# --------------------------------------------------------------------------
# The external format (../shared/data/external_oblique) and the searched offset
# --------------------------------------------------------------------------

FRAME = {"x0": 512300.0, "y0": 5612400.0, "z0": 100.0, "crs": CRS}
KNOWN_OFFSET_M = 12.3  # the datum of the estimated model above the truth's
HEIGHT_NOISE_M = (0.04, -0.03, 0.02, 0.0)  # per image, on top of the offset
SIDE_SHIFT_M = 1.5  # image 4 moved sideways: fails at every offset


def write_external_scene(folder, gt, corners, visible):
    """A scene folder in the external format: gt/, gt_buildings.json without
    visibility (corner_info, corner_kinds, frame), gt_visibility.json."""
    folder.mkdir()
    io.write_absolute_model(folder / "gt", gt)
    (folder / "gt_buildings.json").write_text(
        json.dumps(
            {
                "frame": FRAME,
                "buildings": [],
                "map_only": [],
                "corners": corners.tolist(),
                "corner_info": [
                    [0, 0 if z < ORIGIN[2] + 1 else 1] for z in corners[:, 2]
                ],
                "corner_kinds": {"0": "ground", "1": "eave", "2": "ridge"},
                "trees": [],
            }
        )
    )
    (folder / "gt_visibility.json").write_text(
        json.dumps(
            {
                "tolerance": "all corners in the image (no occlusion)",
                "images": {k: v.tolist() for k, v in visible.items()},
            }
        )
    )
    return folder


def make_estimate(gt):
    """The truth raised by KNOWN_OFFSET_M, each image by HEIGHT_NOISE_M more,
    the last one also moved SIDE_SHIFT_M sideways."""
    est = copy_block(gt)
    for i, im in est.images.items():
        c = im.cam_from_world.center + [
            0.0,
            0.0,
            KNOWN_OFFSET_M + HEIGHT_NOISE_M[i - 1],
        ]
        set_center(est, i, c)
    x_cam_world = est.images[4].cam_from_world.rotation[0]
    set_center(est, 4, est.images[4].cam_from_world.center + SIDE_SHIFT_M * x_cam_world)
    return est


def independent_means(est, gt, corners, visible, offset):
    """Per image, the mean distance between the projections of its visible
    corners by the estimated camera lowered by ``offset`` and by the true one
    (geometry.project, no code of evaluate)."""
    out = {}
    for i, im in gt.images.items():
        idx = visible[im.name]
        e = est.images[i]
        lowered = Pose.from_center(
            e.cam_from_world.rotation, e.cam_from_world.center - [0.0, 0.0, offset]
        )
        xy_est, _ = project(est.cameras[e.camera_id], lowered, corners[idx])
        xy_true, _ = project(gt.cameras[im.camera_id], im.cam_from_world, corners[idx])
        out[im.name] = float(np.linalg.norm(xy_est - xy_true, axis=1).mean())
    return out


def test_external_scene_searched_offset(tmp_path, scene):
    gt, corners, visible = scene
    scene_path = write_external_scene(tmp_path / "ext", gt, corners, visible)
    est = make_estimate(gt)
    origin = ORIGIN + [10.0, -20.0, 30.0]
    result = io.write_result(
        tmp_path / "result", est.shifted(origin), io.Georef(origin, CRS)
    )

    ev = evaluate_model(result, scene_path, EvaluateOptions(vertical_offset="search"))
    assert ev.gt_format == "external"
    s = ev.summary
    # Images 1-3 fit exactly at KNOWN_OFFSET_M + their own height noise, and
    # every one's deviation grows away from it; image 4 is the largest
    # everywhere near: the median (of 4: the mean of the 2nd and 3rd) is least
    # within the spread of the three images' own offsets.
    noise = np.asarray(HEIGHT_NOISE_M[:3])
    assert KNOWN_OFFSET_M + noise.min() - 1e-6 <= s.vertical_offset_m
    assert s.vertical_offset_m <= KNOWN_OFFSET_M + noise.max() + 1e-6
    assert s.camera_offset_m == pytest.approx(
        KNOWN_OFFSET_M + np.median(HEIGHT_NOISE_M)
    )

    # The deviations are those of an independent projection at that offset.
    want = independent_means(est, gt, corners, visible, s.vertical_offset_m)
    for name, mean in want.items():
        assert ev.image(name).mean_deviation_px == pytest.approx(mean, abs=1e-6)
    # ... and no other offset gives a lower median (a dense brute-force scan).
    scan = np.linspace(KNOWN_OFFSET_M - 1.0, KNOWN_OFFSET_M + 1.0, 2001)
    medians = [
        np.median(list(independent_means(est, gt, corners, visible, d).values()))
        for d in scan
    ]
    assert s.deviation_median_all_px <= min(medians) + 1e-6
    # 1.5 m sideways at ~420 m: ~7 px; the others: cm of height, < 1 px.
    assert ev.image(image_name(3)).status == "failed"
    assert s.num_registered == 3 and s.deviation_median_all_px < 1.0

    # The other offsets read the same format; "cameras" takes the heights'
    # median, off the best fit by the spread of the height noise.
    cams = evaluate_model(
        result, scene_path, EvaluateOptions(vertical_offset="cameras")
    )
    assert cams.summary.vertical_offset_m == pytest.approx(s.camera_offset_m)
    assert cams.summary.deviation_median_px >= s.deviation_median_px - 1e-9


def test_external_scene_missing_images_count_as_infinite(tmp_path, scene):
    gt, corners, visible = scene
    scene_path = write_external_scene(tmp_path / "ext", gt, corners, visible)
    est = copy_block(gt)
    for i, im in est.images.items():
        set_center(est, i, im.cam_from_world.center + [0.0, 0.0, KNOWN_OFFSET_M])
    del est.images[1], est.images[2]
    io.write_absolute_model(tmp_path / "half", est)
    ev = evaluate_model(
        tmp_path / "half", scene_path, EvaluateOptions(vertical_offset="search")
    )
    s = ev.summary
    # Half missing: the median over the 4 is infinite at every offset; the
    # offset comes from the images present.
    assert s.vertical_offset_m == pytest.approx(KNOWN_OFFSET_M, abs=1e-9)
    assert s.num_registered == 2 and s.num_missing == 2
    assert s.deviation_median_all_px == np.inf and s.deviation_p95_all_px == np.inf
    assert s.deviation_median_px < EXACT_PX  # over the measured images only
    assert ev.to_json()["summary"]["deviation_median_all_px"] is None
    del est.images[3]
    io.write_absolute_model(tmp_path / "one", est)
    s = evaluate_model(
        tmp_path / "one", scene_path, EvaluateOptions(vertical_offset="search")
    ).summary
    assert s.deviation_median_all_px == np.inf
    assert s.deviation_p95_all_px == np.inf


def test_search_finds_the_global_minimum_of_a_non_convex_median():
    """Per-image V-shapes in two clusters: the median has a local minimum at
    the camera-height offset (the centre) and its global one 9 m away."""
    lows = [0.0, 0.1, 9.0, 9.05, 9.1]
    slopes = [5.0, 4.0, 6.0, 3.0, 5.0]
    profiles = [
        (lambda d, a=a, s=s: s * np.abs(np.asarray(d) - a))
        for a, s in zip(lows, slopes, strict=True)
    ]
    offset, median = search_block_offset(profiles, 0, center=0.05, half_range=20.0)
    scan = np.linspace(-19.95, 20.05, 400001)
    brute = np.median(np.column_stack([f(scan) for f in profiles]), axis=1)
    assert median <= brute.min() + 1e-9
    assert offset == pytest.approx(scan[np.argmin(brute)], abs=1e-4)
    assert 9.0 <= offset <= 9.1
    # Within +-5 m of the centre: the least median of that range, between the
    # clusters (3rd smallest of five: one of the pair, or of the three).
    offset, median = search_block_offset(profiles, 0, center=0.05, half_range=5.0)
    near = np.abs(scan - 0.05) <= 5.0
    assert median <= brute[near].min() + 1e-9
    assert offset == pytest.approx(scan[near][np.argmin(brute[near])], abs=1e-4)
    # A missing image (infinite) makes the median of 6 the mean of the 3rd
    # and 4th: the global minimum stays in the cluster of three.
    offset, median = search_block_offset(profiles, 1, center=0.05, half_range=20.0)
    assert 9.0 <= offset <= 9.1 and np.isfinite(median)


def test_format_is_told_by_content(tmp_path, scene):
    gt, corners, visible = scene
    ext = write_external_scene(tmp_path / "ext", gt, corners, visible)
    truth = read_ground_truth(ext)
    assert truth.format == "external" and truth.crs == CRS
    assert set(truth.visible) == {im.name for im in gt.images.values()}
    syn = write_scene(tmp_path / "syn", gt, corners, visible)
    assert read_ground_truth(syn).format == "synthetic"
    # A synthetic file's visible_corners win over a stray gt_visibility.json.
    (syn / "gt_visibility.json").write_text('{"images": {}}')
    assert read_ground_truth(syn).format == "synthetic"
    # Neither: named as missing.
    (ext / "gt_visibility.json").unlink()
    with pytest.raises(InputError, match="visible_corners.*gt_visibility.json"):
        read_ground_truth(ext)
    (ext / "gt_visibility.json").write_text(
        '{"images": {"cam_0/img_000.jpg": [0, 999]}}'
    )
    with pytest.raises(InputError, match="out of range"):
        read_ground_truth(ext)
    (ext / "gt_visibility.json").write_text('{"imgs": {}}')
    with pytest.raises(InputError, match="'images'"):
        read_ground_truth(ext)


def test_cli_search(tmp_path, scene, capsys):
    gt, corners, visible = scene
    scene_path = write_external_scene(tmp_path / "ext", gt, corners, visible)
    io.write_absolute_model(tmp_path / "est", make_estimate(gt))
    report = tmp_path / "r.json"
    rc = _evaluate_cli(
        "--input_path",
        tmp_path / "est",
        "--gt_path",
        scene_path,
        "--vertical_offset",
        "search",
        "--output_path",
        report,
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "registered 3 / 4 images" in out and "vertical offset: search" in out
    data = json.loads(report.read_text())
    assert data["options"]["vertical_offset"] == "search"
    assert data["gt_format"] == "external"
    assert data["summary"]["vertical_offset_m"] == pytest.approx(
        KNOWN_OFFSET_M, abs=0.05
    )
    rc = _evaluate_cli(
        "--input_path",
        tmp_path / "est",
        "--gt_path",
        scene_path,
        "--vertical_offset",
        "search",
        "--search_range_m",
        5,
    )
    assert rc == 0  # the camera-height offset is 12.3 m: within +-5 m
    assert "+-5 m" in capsys.readouterr().out


def _external_scene(name):
    """``<repo>/../shared/data/external_oblique/<name>``, looked for from the
    repository up (worktrees sit deeper than the main checkout)."""
    here = Path(__file__).resolve().parent
    for parent in here.parents:
        path = parent / "shared" / "data" / "external_oblique" / name
        if path.is_dir():
            return path
    pytest.skip(
        f"external scene {name} not found in any ../shared/data/external_oblique"
    )


def test_real_external_truth_against_itself():
    scene_path = _external_scene("urban-101")
    ev = evaluate_model(
        scene_path / "gt", scene_path, EvaluateOptions(vertical_offset="search")
    )
    s = ev.summary
    assert ev.gt_format == "external"
    assert (s.num_registered, s.num_total) == (36, 36)
    assert s.vertical_offset_m == 0.0 and s.camera_offset_m == 0.0
    assert s.deviation_max_px == 0.0 and s.deviation_median_all_px == 0.0
