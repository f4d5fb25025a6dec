"""The synthetic city: geometry against its own images, noise against its options.

Tolerances are named with units; statistical bounds are derived from the
injected noise and the sample size (about 4 standard errors).
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from obliq_colmap import colmap_io as io
from obliq_colmap.cli import main
from obliq_colmap.geometry import Camera, Pose, rotation_angle_deg
from obliq_colmap.synthetic import (
    PRESETS,
    build_city,
    preset,
    render_image,
    true_vertical_edges,
    true_vertical_vp,
)
from obliq_colmap.synthetic import city as C
from obliq_colmap.synthetic.cameras import (
    STREAM_RENDER,
    prior_block,
    stream,
    true_block,
)
from obliq_colmap.synthetic.render import render_depth
from obliq_colmap.synthetic.truth import vertical_edge_segments

EDGE_PEAK_TOL_PX = 0.2  # sub-pixel location of the gradient peak on true edges
NAMES = ["N_00.jpg", "E_01.jpg", "S_00.jpg", "W_01.jpg"]


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def gradient_profile(
    image: np.ndarray, segments: np.ndarray, offsets: np.ndarray
) -> np.ndarray:
    """Mean |gradient . normal| along (M, 2, 2) segments at normal offsets (px)."""
    grey = image.astype(np.float32).mean(2)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    pts, normals = [], []
    for p0, p1 in segments:
        d = p1 - p0
        length = np.linalg.norm(d)
        t = np.linspace(0.15, 0.85, max(2, int(0.7 * length)))
        pts.append(p0 + t[:, None] * d)
        normals.append(np.repeat([[-d[1] / length, d[0] / length]], len(t), 0))
    pts, normals = np.concatenate(pts), np.concatenate(normals)
    prof = []
    for off in offsets:
        q = pts + off * normals - 0.5  # COLMAP pixel -> array index of the centre
        mx, my = q[:, 0].astype(np.float32)[None], q[:, 1].astype(np.float32)[None]
        sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR)[0]
        sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR)[0]
        prof.append(np.mean(np.abs(sx * normals[:, 0] + sy * normals[:, 1])))
    return np.asarray(prof)


def peak_offset(offsets: np.ndarray, prof: np.ndarray) -> float:
    """Sub-sample peak of a profile by a parabola through the top three samples."""
    k = int(np.argmax(prof))
    assert 0 < k < len(prof) - 1, f"profile peaks at its border: {prof}"
    a, b, c = prof[k - 1 : k + 2]
    step = offsets[1] - offsets[0]
    return float(offsets[k] + 0.5 * step * (a - c) / (a - 2 * b + c))


def read_rgb(path) -> np.ndarray:
    return cv2.imread(str(path))[..., ::-1]


# --------------------------------------------------------------------------
# options, determinism, files
# --------------------------------------------------------------------------


def test_options_presets_and_validation():
    assert PRESETS["small"].grid_rows * PRESETS["small"].grid_cols * 4 == 8
    assert PRESETS["paper"].grid_rows * PRESETS["paper"].grid_cols * 4 == 36
    assert PRESETS["hard"].distortion == "radial"
    assert preset("paper", image_width_px=4008).image_height_px == 2672
    assert preset("paper", image_width_px=1002).image_height_px == 668
    with pytest.raises(ValueError, match="allowed"):
        preset("nope")
    with pytest.raises(ValueError, match="allowed"):
        preset("paper", distortion="fisheye")
    o = PRESETS["paper"]
    assert C.SceneOptions.from_json(json.loads(json.dumps(o.to_json()))) == o


def test_field_of_view_is_kept_when_the_width_changes():
    a = true_block(preset("paper", image_width_px=2004), 3)
    b = true_block(preset("paper", image_width_px=1002), 3)
    for cid in a.cameras:
        ka, kb = a.cameras[cid].K, b.cameras[cid].K
        assert ka[0, 0] == pytest.approx(2 * kb[0, 0], rel=1e-12)
        # Principal point offsets scale too: same normalised geometry.
        assert (ka[0, 2] - 1002) == pytest.approx(2 * (kb[0, 2] - 501), abs=1e-9)
    for i in a.images:  # the flight does not depend on the image size
        assert np.allclose(
            a.images[i].cam_from_world.matrix(), b.images[i].cam_from_world.matrix()
        )


def test_gsd_at_image_centre():
    o = preset("paper")
    block = true_block(
        dataclasses.replace(
            o,
            jitter_tilt_deg=0,
            jitter_heading_deg=0,
            jitter_roll_deg=0,
            jitter_position_m=0,
            jitter_altitude_m=0,
            focal_spread=0,
        ),
        1,
    )
    im = block.images[1]
    cam = block.cameras[im.camera_id]
    z_cam = im.cam_from_world.rotation[2]
    c = im.cam_from_world.center
    dist = -c[2] / z_cam[2]  # optical axis meets the local ground z = 0
    assert dist / cam.K[0, 0] == pytest.approx(o.gsd_m, rel=1e-9)
    assert np.degrees(np.arccos(-z_cam[2])) == pytest.approx(o.tilt_deg, abs=1e-9)


def test_scene_is_rebuilt_identically(small_scene):
    """load_scene rebuilds the city: its corners equal those written at generation."""
    corners = C.corners(small_scene.city)
    written = np.asarray(small_scene.buildings["corners"])
    assert written.shape == corners["xyz"].shape
    assert np.allclose(written, corners["xyz"] + small_scene.origin, atol=1e-3)
    assert small_scene.buildings["corner_kind"] == corners["kind"]


def test_rendering_is_deterministic(small_scene, small_options):
    """Re-rendering image 1 with its noise stream gives the same JPEG bytes."""
    name = "N_00.jpg"
    camera, pose = small_scene.camera_pose(name)
    image_id = small_scene.gt.image_by_name(name).image_id
    img, _, _ = render_image(
        small_scene.city,
        camera,
        pose,
        small_options,
        stream(small_scene.seed, STREAM_RENDER, image_id),
    )
    ok, data = cv2.imencode(
        ".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, small_options.jpeg_quality]
    )
    assert ok
    assert data.tobytes() == small_scene.image_path(name).read_bytes()


def test_different_seeds_differ():
    a = true_block(PRESETS["small"], 1)
    b = true_block(PRESETS["small"], 2)
    assert not np.allclose(
        a.images[1].cam_from_world.matrix(), b.images[1].cam_from_world.matrix()
    )


def test_scene_folder_and_models(small_scene_path, small_options):
    p = small_scene_path
    for name in (
        "images",
        "priors",
        "gt",
        "cadastre.geojson",
        "gt_buildings.json",
        "scene.json",
    ):
        assert (p / name).exists(), name
    gt, priors = io.read_model(p / "gt"), io.read_model(p / "priors")
    assert len(gt.images) == 8 and len(gt.cameras) == 4
    assert {i: (im.name, im.camera_id) for i, im in gt.images.items()} == {
        i: (im.name, im.camera_id) for i, im in priors.images.items()
    }
    for cam in gt.cameras.values():
        assert cam.model == "PINHOLE"
        assert (cam.width, cam.height) == (600, 400)
    # One physical camera per direction.
    for im in gt.images.values():
        assert im.camera_id == {"N": 1, "E": 2, "S": 3, "W": 4}[im.name[0]]
        assert (p / "images" / im.name).is_file()
        c = im.cam_from_world.center
        assert 5.0e5 < c[0] < 5.3e5 and 5.6e6 < c[1] < 5.7e6  # absolute coordinates
        assert 200 < c[2] - small_options.ground_height_m < 400
        R = im.cam_from_world.rotation
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
    scene = json.loads((p / "scene.json").read_text())
    assert scene["seed"] == 7 and scene["preset"] == "small"
    assert scene["options"]["image_width_px"] == 600


def test_generate_refuses_non_empty_output(tmp_path, small_options):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "file").write_text("")
    from obliq_colmap.errors import InputError
    from obliq_colmap.synthetic import generate_scene

    with pytest.raises(InputError, match="not empty"):
        generate_scene(tmp_path / "x", small_options, seed=1, show_progress=False)


# --------------------------------------------------------------------------
# image formation
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "model,params",
    [
        ("PINHOLE", [100.0, 100.0, 32.0, 24.0]),
        ("RADIAL", [100.0, 32.0, 24.0, -0.08, 0.02]),
    ],
)
def test_half_pixel_convention(model, params):
    """A plate edge projected onto a pixel's centre line covers half of that pixel."""
    o = dataclasses.replace(
        PRESETS["small"], blur_sigma_px=0, noise_sigma=0, vignetting=0
    )
    cam = Camera(model, 64, 48, params)
    pose = Pose.from_center(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 100.0])  # nadir
    # World x of the plate edge whose image passes through x = 40.5 on row 24.
    x_edge = float(cam.cam_from_img(np.array([[40.5, 24.0]]))[0, 0]) * 100.0
    big = 50.0
    plate = [
        [[x_edge, -big, 0], [big, -big, 0], [big, big, 0]],
        [[x_edge, -big, 0], [big, big, 0], [x_edge, big, 0]],
    ]
    floor = [
        [[-200, -200, -1], [200, -200, -1], [200, 200, -1]],
        [[-200, -200, -1], [200, 200, -1], [-200, 200, -1]],
    ]
    city = C.toy_city(
        np.array(plate + floor), np.array([[0.4] * 3] * 2 + [[0.0] * 3] * 2), o
    )
    img, depth, buf = render_image(city, cam, pose, o)
    row = img[24, :, 0].astype(float)
    full = row[44]
    assert full > 50
    assert row[39] == 0
    assert row[41] == pytest.approx(full, abs=1)
    assert row[40] == pytest.approx(full / 2, abs=1.5)  # 2 of 4 sub-samples
    # Depth buffer: exact camera z of the plate / floor at pixel centres.
    assert depth[24, 44] == pytest.approx(100.0, abs=1e-4)
    assert depth[24, 30] == pytest.approx(101.0, abs=1e-4)
    assert buf["face_id"][24, 44] in (0, 1) and buf["face_id"][24, 30] in (2, 3)


def test_occlusion_nearest_surface_wins():
    o = dataclasses.replace(
        PRESETS["small"], blur_sigma_px=0, noise_sigma=0, vignetting=0, supersample=1
    )
    cam = Camera("PINHOLE", 40, 40, [100.0, 100.0, 20.0, 20.0])
    pose = Pose.from_center(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 100.0])
    quad = np.array(
        [
            [[-50, -50, 0], [50, -50, 0], [50, 50, 0]],
            [[-50, -50, 0], [50, 50, 0], [-50, 50, 0]],
        ],
        float,
    )
    tris = np.concatenate([quad, quad + [0, 0, 10.0]])  # drawn first far, then near
    cols = np.array([[0.2] * 3] * 2 + [[0.4] * 3] * 2)
    for order in (slice(None), slice(None, None, -1)):
        city = C.toy_city(tris[order], cols[order], o)
        img, depth, _ = render_image(city, cam, pose, o)
        assert np.allclose(depth, 90.0, atol=1e-4)
        assert img[..., 0].min() == img[..., 0].max()


def test_true_corner_edges_lie_on_image_edges(small_scene):
    """Gradient across projected true vertical corner edges peaks exactly on them."""
    offsets = np.arange(-3.0, 3.01, 0.25)
    profiles = []
    for name in NAMES:
        e = true_vertical_edges(small_scene, name, min_length_px=8.0)
        seg = e["segments"][e["kind"] == "corner"]
        assert len(seg) > 20
        profiles.append(
            gradient_profile(read_rgb(small_scene.image_path(name)), seg, offsets)
        )
    prof = np.mean(profiles, 0)
    mid = len(offsets) // 2
    assert prof[mid] > 1.5 * max(prof[0], prof[-1])
    assert abs(peak_offset(offsets, prof)) < EDGE_PEAK_TOL_PX


def test_true_ground_footprint_edges_lie_on_image_edges(small_scene):
    """Footprint edges between two visible ground corners sit on image edges."""
    gb = small_scene.buildings
    xyz = np.asarray(gb["corners"]) - small_scene.origin
    kinds = np.asarray(gb["corner_kind"])
    bids = np.asarray(gb["corner_building"])
    offsets = np.arange(-3.0, 3.01, 0.25)
    rand_rng = np.random.default_rng(0)
    on, off = [], []
    for name in NAMES:
        camera, pose = small_scene.camera_pose(name)
        vis = set(gb["visible_corners"][name])
        segs3d = []
        for i in range(len(xyz) - 1):
            j = i + 1
            if (
                kinds[i] == kinds[j] == "ground"
                and bids[i] == bids[j]
                and i in vis
                and j in vis
            ):
                segs3d.append((xyz[i], xyz[j]))
        P = np.array(segs3d).reshape(-1, 3)
        px = (
            small_scene.camera_pose(name)[0]
            .img_from_cam(pose.transform(P))
            .reshape(-1, 2, 2)
        )
        px = px[np.linalg.norm(px[:, 1] - px[:, 0], axis=1) > 8]
        assert len(px) > 10
        img = read_rgb(small_scene.image_path(name))
        on.append(gradient_profile(img, px, offsets))
        rnd = rand_rng.uniform(
            [20, 20], [camera.width - 20, camera.height - 20], (200, 1, 2)
        )
        rnd = np.concatenate([rnd, rnd + rand_rng.normal(0, 15, (200, 1, 2))], 1)
        off.append(gradient_profile(img, rnd, offsets[[len(offsets) // 2]]))
    prof = np.mean(on, 0)
    assert prof[len(offsets) // 2] > 2.0 * np.mean(off)
    assert abs(peak_offset(offsets, prof)) < 2 * EDGE_PEAK_TOL_PX


def test_radial_distortion_matches_colmap_projection(small_scene, small_options):
    """With RADIAL distortion, projected true edges still sit on rendered edges."""
    name = "E_01.jpg"
    cam0, pose = small_scene.camera_pose(name)
    f, cx, cy = cam0.K[0, 0], cam0.K[0, 2], cam0.K[1, 2]
    cam = Camera("RADIAL", cam0.width, cam0.height, [f, cx, cy, -0.12, 0.03])
    o = dataclasses.replace(small_options, noise_sigma=0)
    img, depth, _ = render_image(small_scene.city, cam, pose, o)
    e = vertical_edge_segments(
        small_scene.vertical_edges, cam, pose, depth, min_length_px=8
    )
    seg = e["segments"][e["kind"] == "corner"]
    # Only edges far from the centre, where distortion moves them by pixels.
    r = np.linalg.norm(seg.mean(1) - [cx, cy], axis=1)
    seg = seg[r > 0.6 * cam.width / 2]
    assert len(seg) > 10
    offsets = np.arange(-3.0, 3.01, 0.25)
    prof = gradient_profile(img, seg, offsets)
    assert abs(peak_offset(offsets, prof)) < EDGE_PEAK_TOL_PX
    # The depth-only z-buffer agrees with the rendered one.
    d2, _ = render_depth(small_scene.city, cam, pose)
    ok = np.isfinite(depth) & np.isfinite(d2)
    assert np.median(np.abs(depth[ok] - d2[ok])) < 0.05


def test_vertical_segments_converge_at_true_vp(small_scene):
    for name in NAMES:
        vp = true_vertical_vp(small_scene, name)
        e = true_vertical_edges(small_scene, name)
        assert {"corner", "texture"} <= set(e["kind"])
        seg = e["segments_undistorted"]
        mid = seg.mean(1)
        d = seg[:, 1] - seg[:, 0]
        to_vp = vp[:2] - mid * vp[2]  # direction to the (possibly far) VP
        cos = np.abs(np.sum(d * to_vp, 1)) / (
            np.linalg.norm(d, axis=1) * np.linalg.norm(to_vp, axis=1)
        )
        angle = np.degrees(np.arccos(np.clip(cos, 0, 1)))
        assert np.max(angle) < 0.01
        # Oblique views: the nadir VP lies below the image.
        assert vp[1] / vp[2] > 1.5 * small_scene.options.image_height_px


def test_visible_corners(small_scene):
    gb = small_scene.buildings
    xyz = np.asarray(gb["corners"]) - small_scene.origin
    for name in NAMES:
        camera, pose = small_scene.camera_pose(name)
        vis = np.asarray(gb["visible_corners"][name])
        px, z = camera.img_from_cam(pose.transform(xyz)), pose.transform(xyz)[:, 2]
        inside = (
            (px[:, 0] >= 0)
            & (px[:, 0] < camera.width)
            & (px[:, 1] >= 0)
            & (px[:, 1] < camera.height)
        )
        assert inside[vis].all()
        frac = len(vis) / inside.sum()
        assert 0.25 < frac < 0.9, frac  # occlusion removes some, not all
        # Visible corners are near the first surface along their pixel ray.
        depth = small_scene.depth(name)
        col, row = np.floor(px[vis]).astype(int).T
        assert np.median(np.abs(depth[row, col] - z[vis])) < 1.0


# --------------------------------------------------------------------------
# priors and cadastre
# --------------------------------------------------------------------------


def test_priors_match_configured_noise():
    o = preset("paper", grid_rows=10, grid_cols=10)  # 400 images, no rendering
    gt = true_block(o, 5)
    pr = prior_block(o, 5, gt)
    n = len(gt.images)
    dc = np.array(
        [
            pr.images[i].cam_from_world.center - gt.images[i].cam_from_world.center
            for i in gt.images
        ]
    )
    # ~4 standard errors of a standard deviation estimated from m samples.
    assert np.std(dc[:, :2]) == pytest.approx(
        o.prior_position_m, rel=4.0 / np.sqrt(2 * 2 * n)
    )
    assert np.mean(dc[:, 2]) == pytest.approx(
        o.prior_vertical_datum_offset_m, abs=4 * o.prior_height_m / np.sqrt(n)
    )
    assert np.std(dc[:, 2]) == pytest.approx(o.prior_height_m, rel=4.0 / np.sqrt(2 * n))
    ang = np.array(
        [
            rotation_angle_deg(
                pr.images[i].cam_from_world.rotation,
                gt.images[i].cam_from_world.rotation,
            )
            for i in gt.images
        ]
    )
    # |omega|^2 is sigma^2 chi^2(3): RMS angle = sqrt(3) sigma, relative standard
    # error of the RMS sqrt(6) / 3 / 2 / sqrt(n) ~ 0.41 / sqrt(n).
    assert np.sqrt(np.mean(ang**2)) == pytest.approx(
        np.sqrt(3) * o.prior_rotation_deg, rel=4 * 0.41 / np.sqrt(n)
    )
    for cid, cam in pr.cameras.items():
        true = gt.cameras[cid]
        rel = abs(cam.K[0, 0] / true.K[0, 0] - 1) * 100
        assert o.prior_focal_percent / 2 - 1e-9 <= rel <= o.prior_focal_percent + 1e-9
        assert cam.model == true.model and not cam.has_distortion
        assert (cam.K[0, 2], cam.K[1, 2]) == (cam.width / 2, cam.height / 2)
        assert (true.K[0, 2], true.K[1, 2]) != (true.width / 2, true.height / 2)


def test_hard_preset_cameras_are_radial_and_priors_drop_distortion():
    o = PRESETS["hard"]
    gt = true_block(o, 1)
    pr = prior_block(o, 1, gt)
    for cid in gt.cameras:
        assert gt.cameras[cid].model == "RADIAL" and gt.cameras[cid].has_distortion
        assert pr.cameras[cid].model == "RADIAL" and not pr.cameras[cid].has_distortion


def test_cadastre_has_realistic_discrepancies(small_scene, small_scene_path):
    doc = json.loads((small_scene_path / "cadastre.geojson").read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["crs"] == {"type": "name", "properties": {"name": "EPSG:25832"}}
    types = {f["geometry"]["type"] for f in doc["features"]}
    assert types == {"Polygon", "MultiPolygon"}
    assert any(
        len(f["geometry"]["coordinates"]) > 1
        for f in doc["features"]
        if f["geometry"]["type"] == "Polygon"
    )  # courtyards
    with_height = sum("height" in f["properties"] for f in doc["features"])
    assert 0 < with_height < len(doc["features"])
    table = {b["id"]: b for b in small_scene.buildings["buildings"]}
    ids = [f["properties"]["id"] for f in doc["features"]]
    assert len(ids) == len(set(ids)) and all(table[i]["in_map"] for i in ids)
    n = len(table)
    missing = sum(b["in_scene"] and not b["in_map"] for b in table.values())
    demolished = sum(b["in_map"] and not b["in_scene"] for b in table.values())
    shifted = [b for b in table.values() if any(b["shift_m"])]
    assert 0.015 * n < missing < 0.05 * n and 0.015 * n < demolished < 0.05 * n
    assert len(shifted) >= 3
    assert all(0.7 < np.hypot(*b["shift_m"]) < 1.3 for b in shifted)
    # Vertex noise: map minus truth, for unshifted single-part buildings.
    city = small_scene.city
    origin = small_scene.origin[:2]
    diffs = []
    for f in doc["features"]:
        b = city.building_by_id(f["properties"]["id"])
        if any(b.shift_m) or f["geometry"]["type"] != "Polygon":
            continue
        true_ext = C._rings(b.footprint)[0] + origin
        diffs.append(np.asarray(f["geometry"]["coordinates"][0])[:-1] - true_ext)
    d = np.concatenate(diffs)
    assert np.abs(np.mean(d, 0)).max() < 0.02
    # Shared vertices share their noise, so the effective count is smaller.
    assert np.std(d) == pytest.approx(
        small_scene.options.cadastre_vertex_noise_m, rel=0.1
    )


def test_buildings_table_and_terrain(small_scene):
    gb = small_scene.buildings
    assert gb["crs"] == "EPSG:25832"
    assert len(gb["corners"]) == len(gb["corner_building"]) == len(gb["corner_kind"])
    assert set(gb["corner_kind"]) == {"ground", "eave", "ridge"}
    roofs = {b["roof"] for b in gb["buildings"]}
    assert roofs == {"flat", "gabled", "hipped"}
    heights = np.array([b["height_m"] for b in gb["buildings"]])
    assert heights.min() >= 6.0 and heights.max() <= 45.0
    city = small_scene.city
    for b in city.buildings[:200]:
        fp = b.footprint
        x, y = np.asarray(
            fp.exterior.coords
            if fp.geom_type == "Polygon"
            else fp.geoms[0].exterior.coords
        ).T
        z = city.terrain.height(x, y)
        assert z.min() >= b.base_z - 1e-9  # walls reach into the terrain: no gaps
        assert z.max() - b.base_z < 3.0
    # Ground corners lie on the terrain, eave corners at base + height.
    xyz = np.asarray(gb["corners"]) - small_scene.origin
    k = np.asarray(gb["corner_kind"])
    g = xyz[k == "ground"]
    assert np.allclose(city.terrain.height(g[:, 0], g[:, 1]), g[:, 2], atol=1e-3)


@pytest.mark.slow  # 3.6 s: the whole generator through the CLI
def test_cli_synth(tmp_path):
    out = tmp_path / "scene"
    code = main(
        [
            "synth",
            "--preset",
            "small",
            "--seed",
            "3",
            "--output_path",
            str(out),
            "--image_width",
            "96",
            "--num_workers",
            "1",
            "--no_progress",
            "--prior_position_m",
            "2.5",
        ]
    )
    assert code == 0
    assert len(list((out / "images").glob("*.jpg"))) == 8
    scene = json.loads((out / "scene.json").read_text())
    assert scene["options"]["prior_position_m"] == 2.5
    assert scene["image_size"] == [96, 64]
    assert main(["synth", "--preset", "small", "--output_path", str(out)]) == 2


def test_city_is_deterministic_for_a_seed():
    o = preset("small", margin_m=-150.0)  # a smaller city, faster
    a, b = build_city(o, 11), build_city(o, 11)
    assert np.array_equal(a.vertices, b.vertices)
    assert [x.id for x in a.buildings] == [x.id for x in b.buildings]
    c = build_city(o, 12)
    assert len(c.vertices) != len(a.vertices) or not np.array_equal(
        c.vertices, a.vertices
    )


def test_render_refuses_absolute_poses(small_scene, small_options):
    im = small_scene.gt.image_by_name("N_00.jpg")
    with pytest.raises(ValueError, match="LOCAL"):
        render_image(
            small_scene.city,
            small_scene.gt.cameras[im.camera_id],
            im.cam_from_world,
            small_options,
        )


def test_a_nadir_head_looks_down_and_leaves_the_oblique_flight_as_it_was():
    """``nadir_head``: a fifth camera (id 5) with grid_rows x grid_cols images
    D_rc.jpg whose optical axes are within the tilt jitter of the nadir, at
    the obliques' flying height; the four oblique heads' true cameras and
    poses are those of the flight without it."""
    import dataclasses

    import numpy as np

    from obliq_colmap.synthetic import preset
    from obliq_colmap.synthetic.cameras import (
        flight_geometry,
        rotation_from_angles,
        true_block,
    )

    base = preset("small", image_width_px=600)
    with_nadir = dataclasses.replace(base, nadir_head=True)
    a, b = true_block(base, 3), true_block(with_nadir, 3)
    assert set(b.cameras) == set(a.cameras) | {5}
    for i, rec in a.images.items():
        assert b.images[i].name == rec.name
        np.testing.assert_array_equal(
            b.images[i].cam_from_world.rotation, rec.cam_from_world.rotation
        )
    nadir = [r for r in b.images.values() if r.name.startswith("D_")]
    assert len(nadir) == base.grid_rows * base.grid_cols
    assert all(r.camera_id == 5 for r in nadir)
    jitter = 4 * np.hypot(base.jitter_tilt_deg, base.jitter_roll_deg)
    altitude = flight_geometry(base).altitude_m
    for r in nadir:
        axis = r.cam_from_world.rotation[2]  # the optical axis in the world
        assert np.degrees(np.arccos(-axis[2])) < jitter
        assert abs(r.cam_from_world.center[2] - altitude) < 5 * base.jitter_altitude_m
    # the rotation at and through the nadir is a rotation, and the image's x
    # axis stays to the right of the heading (no flip at negative tilt)
    for tilt in (0.0, -2.0, 2.0, 45.0):
        R = rotation_from_angles(30.0, tilt, 1.0)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
        assert R[0] @ [np.cos(np.radians(30.0)), -np.sin(np.radians(30.0)), 0] > 0.99
