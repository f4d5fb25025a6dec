"""Control points in the formats users have, triangulated in a model (issue 27)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from obliq_colmap.cli import main
from obliq_colmap.control.read import read_control_points
from obliq_colmap.control.triangulate import triangulate_control_points
from obliq_colmap.errors import InputError

BERLIN = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "opensfm_berlin_facade"
)
pytest.importorskip("pyproj", reason="control point CRSs need pyproj (extra gis)")


@pytest.mark.skipif(not BERLIN.is_dir(), reason="shared Berlin data not present")
def test_berlin_gcp_list_and_json():
    c = read_control_points(BERLIN / "gcp_list.txt")
    assert c.crs == "EPSG:32633"  # Berlin, 13.4 E: UTM zone 33
    assert len(c) == 10 and sum(len(p.observations) for p in c.points) == 26
    first = c.points[0].observations[0]  # "... 2639.18148357 938.06742366 02.jpg"
    assert first.image_name == "02.jpg"
    assert np.allclose(first.xy, [2639.68148357, 938.56742366])  # + 0.5: COLMAP's
    sizes = {n: (3264, 2448) for n in ("01.jpg", "02.jpg", "03.jpg")}
    j = read_control_points(BERLIN / "ground_control_points.json", sizes)
    usable = [p for p in j.points if len(p.observations) >= 2]
    assert len(usable) == 1
    # OpenSfM normalised (-0.015689, -0.0625362) in a 3264 x 2448 image
    xy = usable[0].observations[0].xy
    assert np.allclose(xy, [-0.015689 * 3264 + 1632, -0.0625362 * 3264 + 1224])


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "gcp_list.txt"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "header, crs",
    [
        ("WGS84 UTM 32N", "EPSG:32632"),
        ("EPSG:25832", "EPSG:25832"),
        ("+proj=utm +zone=32 +ellps=GRS80 +units=m +no_defs", None),
    ],
)
def test_header_kinds(tmp_path, header, crs):
    path = _write(
        tmp_path,
        f"{header}\n500000 5400000 100 10 20 a.jpg p1\n"
        "500030 5400000 nan 30 40 a.jpg p2\n500030 5400000 nan 31 41 b.jpg p2\n",
    )
    c = read_control_points(path)
    assert crs is None or c.crs == crs
    assert c.names() == ["p1", "p2"]
    assert c.points[0].has_height and not c.points[1].has_height  # NaN: 2D
    assert np.allclose(c.points[1].xyz[:2], [500030, 5400000], atol=1e-6)
    assert len(c.points[1].observations) == 2


@pytest.mark.parametrize(
    "text, problem",
    [
        ("WGS 1984\n1 2 3 4 5 a.jpg\n", "unknown projection"),
        ("WGS84\n13.4 52.5 10 4 a.jpg\n", "line 2"),
        ("WGS84\n13.4 52.5 ten 4 5 a.jpg\n", "line 2"),
        ("WGS84\n", "no control point"),
        ("", "empty"),
    ],
)
def test_bad_files_name_the_problem(tmp_path, text, problem):
    with pytest.raises(InputError, match=problem):
        read_control_points(_write(tmp_path, text))


def _synthetic_model(seed=0):
    """Five cameras around a 40 m block, looking at its centre; known points."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="SIMPLE_RADIAL", width=1200, height=800, params=[1000, 600, 400, -0.02]
    )
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for i in range(5):
        a = np.radians(-40 + 20 * i)
        c = np.array([60 * np.sin(a), -60 * np.cos(a), 10.0])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        im = pycolmap.Image(name=f"im{i}.jpg", camera_id=1, image_id=i + 1)
        im.points2D = pycolmap.Point2DList()
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
        rec.add_image_with_trivial_frame(im, pose)
    points = rng.uniform([-15, -15, -5], [15, 15, 15], (6, 3))
    return rec, cam, points


def test_triangulation_recovers_points_and_skips_unknown_images(tmp_path, caplog):
    rec, cam, points = _synthetic_model()
    sigma = 0.5
    rng = np.random.default_rng(1)
    lines = ["EPSG:32632"]
    for k, X in enumerate(points):
        for i in rec.reg_image_ids():
            uv = cam.img_from_cam((rec.images[i].cam_from_world() * X)[None])[0]
            uv = uv + rng.normal(0, sigma, 2) - 0.5  # OpenSfM pixels
            lines.append(f"{X[0]} {X[1]} {X[2]} {uv[0]} {uv[1]} im{i - 1}.jpg g{k}")
    lines.append(f"{points[0][0]} {points[0][1]} {points[0][2]} 5 5 other.jpg g0")
    c = read_control_points(_write(tmp_path, "\n".join(lines) + "\n"))
    with caplog.at_level(logging.WARNING):
        tri = triangulate_control_points(rec, c)
    assert "other.jpg" in caplog.text
    assert tri.usable.all() and (tri.n_observations == 5).all()
    # the position sd of a 5-ray intersection at ~60 m with f = 1000 px:
    # sigma * depth / f per ray, / sqrt(5): ~1.3 cm; 5 sigma
    err = np.linalg.norm(tri.xyz - points, axis=1)
    assert err.max() < 5 * sigma * 60 / 1000 / np.sqrt(5) * 2, err
    med = np.median(np.concatenate(tri.reprojection_px))
    assert med < 2 * sigma


def test_georegister_with_a_bad_gcp_file_exits_2(tmp_path, capsys):
    rec, _, _ = _synthetic_model()
    model = tmp_path / "model"
    model.mkdir()
    rec.write_binary(str(model))
    gcp = _write(tmp_path, "NAD27 somewhere\n1 2 3 4 5 im0.jpg\n")
    out = tmp_path / "out"
    rc = main(
        ["georegister", "--input_path", str(model), "--image_path", str(tmp_path),
         "--control_points_path", str(gcp), "--output_path", str(out)]
    )  # fmt: skip
    assert rc == 2 and not out.exists()
    assert "unknown projection" in capsys.readouterr().err


def test_evaluate_with_control_points_scores_any_model(tmp_path, capsys):
    """Check points in a model that is already in the points' frame."""
    rec, cam, points = _synthetic_model(seed=2)
    model = tmp_path / "model"
    model.mkdir()
    rec.write_binary(str(model))
    lines = ["EPSG:32632"]
    truth = points + np.array([0.0, 0.0, 0.0])
    for k, X in enumerate(truth):
        for i in rec.reg_image_ids():
            uv = cam.img_from_cam((rec.images[i].cam_from_world() * X)[None])[0] - 0.5
            lines.append(f"{X[0]} {X[1]} {X[2] + (0.3 if k == 0 else 0)} "
                         f"{uv[0]} {uv[1]} im{i - 1}.jpg g{k}")  # fmt: skip
    gcp = _write(tmp_path, "\n".join(lines) + "\n")
    out = tmp_path / "r.json"
    rc = main(["evaluate", "--input_path", str(model), "--control_points_path",
               str(gcp), "--output_path", str(out)])  # fmt: skip
    assert rc == 0
    report = json.loads(out.read_text())
    rows = {r["name"]: r for r in report["points"]}
    # g0's given height is 0.3 m too high: the triangulation says so
    assert rows["g0"]["vertical_m"] == pytest.approx(-0.3, abs=1e-6)
    assert all(rows[f"g{k}"]["horizontal_m"] < 1e-6 for k in range(6))
    assert max(rows["g1"]["reprojection_px"]) < 1e-6
    assert report["check_points"]["num_points"] == 6
    assert "g0" in capsys.readouterr().out


def test_georegister_with_fewer_than_two_usable_points_exits_2(tmp_path, capsys):
    """One point seen twice, one seen once, one in an image the model lacks."""
    rec, cam, points = _synthetic_model(seed=3)
    model = tmp_path / "model"
    model.mkdir()
    rec.write_binary(str(model))
    lines = ["EPSG:32632"]
    for k, X in enumerate(points[:2]):
        for i in list(rec.reg_image_ids())[: 2 - k]:
            uv = cam.img_from_cam((rec.images[i].cam_from_world() * X)[None])[0]
            lines.append(f"{X[0]} {X[1]} {X[2]} {uv[0]} {uv[1]} im{i - 1}.jpg g{k}")
    lines.append("1 2 3 10 10 elsewhere.jpg g9")
    gcp = _write(tmp_path, "\n".join(lines) + "\n")
    out = tmp_path / "out"
    argv = ["georegister", "--input_path", str(model), "--image_path", str(tmp_path),
            "--control_points_path", str(gcp), "--output_path", str(out)]  # fmt: skip
    assert main(argv) == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "1 usable control points" in err and str(gcp) in err
    assert main([*argv, "--check_points", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
