"""Prior formats (OPK text, geo.txt, COLMAP database) and export.

Rotations are checked against hand-computed matrices whose rows are the
COLMAP camera axes (x right, y down, z viewing) in the map frame (E, N, U).
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from obliq_colmap.cli import main
from obliq_colmap.colmap_io import Georef, read_model, write_result
from obliq_colmap.errors import InputError
from obliq_colmap.priors import (
    PriorsOptions,
    cam_from_world_from_opk,
    export_model,
    opk_from_cam_from_world,
    prior_format,
    read_priors,
)
from obliq_colmap.priors.cameras import parse_camera_params
from obliq_colmap.priors.exif import cam_from_world_from_gimbal
from obliq_colmap.priors.text import format_opk, read_geo, read_opk

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"
S = np.sqrt(0.5)

#: (omega, phi, kappa) deg -> cam_from_world worked out by hand from
#: R = Rx(omega) Ry(phi) Rz(kappa) and the camera axes it implies.
HAND = [
    # nadir, image top north: x east, y (down) south, z down
    ((0, 0, 0), [[1, 0, 0], [0, -1, 0], [0, 0, -1]]),
    # kappa 90: image right points north, image down east
    ((0, 0, 90), [[0, 1, 0], [1, 0, 0], [0, 0, -1]]),
    # phi -45: looking east and down 45 deg
    ((0, -45, 0), [[S, 0, S], [0, -1, 0], [S, 0, -S]]),
    # the README's worked example: upright, looking east and 45 deg down
    ((0, -45, -90), [[0, -1, 0], [-S, 0, -S], [S, 0, -S]]),
    # omega 45: looking north and down 45 deg
    ((45, 0, 0), [[1, 0, 0], [0, -S, -S], [0, S, -S]]),
]


@pytest.mark.parametrize(("opk", "expected"), HAND)
def test_opk_matches_hand_computed(opk, expected):
    R = cam_from_world_from_opk(np.array(opk, float))[0]
    np.testing.assert_allclose(R, expected, atol=1e-12)
    np.testing.assert_allclose(opk_from_cam_from_world(R)[0], opk, atol=1e-9)


def test_opk_round_trip_random():
    rng = np.random.default_rng(3)
    opk = np.column_stack(
        [
            rng.uniform(-180, 180, 200),
            rng.uniform(-89, 89, 200),
            rng.uniform(-180, 180, 200),
        ]
    )
    R = cam_from_world_from_opk(opk)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(
        cam_from_world_from_opk(opk_from_cam_from_world(R)), R, atol=1e-9
    )


names = st.text(alphabet="abcXYZ019_-.", min_size=1, max_size=12).filter(
    lambda s: not s.startswith("#")
)
coord = st.floats(-1e6, 1e7, allow_nan=False)
angle = st.floats(-180, 180, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(names, coord, coord, coord, angle, angle, angle),
        min_size=1,
        max_size=6,
        unique_by=lambda r: r[0],
    )
)
def test_opk_text_round_trip(rows):
    xyz = np.array([r[1:4] for r in rows])
    opk = np.array([r[4:] for r in rows])
    text = format_opk([r[0] for r in rows], xyz, opk)
    assert prior_kind(text) == "opk"
    back = read_opk(Path("x.txt"), text)
    assert back.names == [r[0] for r in rows]
    # written with 1e-4 m and 1e-8 deg
    np.testing.assert_allclose(back.xyz, xyz, atol=6e-5, rtol=0)
    np.testing.assert_allclose(back.opk_deg, opk, atol=6e-9, rtol=0)


@settings(max_examples=40, deadline=None)
@given(
    st.sampled_from(["EPSG:25832", "WGS84", "+proj=utm +zone=32 +datum=WGS84"]),
    st.lists(
        st.tuples(names, coord, coord, coord),
        min_size=1,
        max_size=6,
        unique_by=lambda r: r[0],
    ),
    st.sampled_from([" ", "\t", ","]),
)
def test_geo_text_round_trip(header, rows, sep):
    lines = [header] + [
        sep.join([r[0]] + [repr(v) for v in r[1:]] + ["0", "1", "2"]) for r in rows
    ]
    text = "\n".join(lines) + "\n"
    assert prior_kind(text) == "geo"
    back = read_geo(Path("geo.txt"), text)
    assert back.names == [r[0] for r in rows]
    np.testing.assert_array_equal(back.xyz, np.array([r[1:] for r in rows]))
    assert back.opk_deg is None
    assert back.crs == ("EPSG:4326" if header == "WGS84" else header)


def prior_kind(text: str) -> str | None:
    from obliq_colmap.priors.text import sniff_text

    return sniff_text(
        Path("x"), next(line for line in text.splitlines() if line.strip())
    )


def test_unknown_format_is_one_clear_error(tmp_path):
    bad = tmp_path / "priors.csv"
    bad.write_text("name;lat;lon\na.jpg;1;2\n")
    with pytest.raises(InputError, match="unknown prior format") as info:
        prior_format(bad)
    assert str(bad) in str(info.value)
    broken = tmp_path / "opk.txt"
    broken.write_text("imageName X Y Z Omega Phi Kappa\na.jpg 1 2 3 4 5\n")
    with pytest.raises(InputError, match="line 2"):
        read_priors(broken, None, PriorsOptions(camera_params="100,50,50"))


def test_opk_file_reproduces_the_model(tmp_path):
    """Model -> export opk -> read with the model's cameras: same poses."""
    out = tmp_path / "priors_opk.txt"
    assert (
        main(
            [
                "export",
                "--input_path",
                str(SAMPLE / "priors"),
                "--output_path",
                str(out),
                "--output_type",
                "opk",
            ]
        )
        == 0
    )
    original = read_model(SAMPLE / "priors")
    back = read_priors(
        out, SAMPLE / "images", PriorsOptions(camera_path=str(SAMPLE / "priors"))
    )
    assert len(back.images) == len(original.images) == 16
    for im in original.images.values():
        got = back.image_by_name(im.name)
        assert got.camera_id == im.camera_id
        np.testing.assert_allclose(
            got.cam_from_world.rotation, im.cam_from_world.rotation, atol=1e-9
        )
        np.testing.assert_allclose(
            got.cam_from_world.center, im.cam_from_world.center, atol=1e-4
        )


def test_text_priors_need_intrinsics(tmp_path):
    f = tmp_path / "opk.txt"
    f.write_text("N_00.jpg 0 0 100 0 0 0\n")
    with pytest.raises(InputError, match="no intrinsics"):
        read_priors(f, SAMPLE / "images")
    block = read_priors(
        f,
        SAMPLE / "images",
        PriorsOptions(camera_params="SIMPLE_RADIAL:900,500,333,0.01"),
    )
    cam = block.cameras[1]
    assert (cam.model, cam.width, cam.height) == ("SIMPLE_RADIAL", 1000, 667)
    assert parse_camera_params("900,500,333", 10, 10).model == "SIMPLE_PINHOLE"
    with pytest.raises(InputError, match="camera_params"):
        parse_camera_params("FISHEYE:1,2", 10, 10)


def test_position_only_and_ambiguous_cameras_refused(tmp_path):
    f = tmp_path / "geo.txt"
    f.write_text("WGS84\na.jpg 9.0 51.0 300\nb.jpg 9.0 51.001 300\n")
    with pytest.raises(InputError, match="positions only"):
        read_priors(f, None, PriorsOptions(camera_params="100,50,50"))
    opts = PriorsOptions(
        camera_path=str(SAMPLE / "priors" / "cameras.bin"), require_rotation=False
    )
    with pytest.raises(InputError, match="4 cameras"):
        read_priors(f, None, opts)


def _single_camera_text(tmp_path) -> str:
    path = tmp_path / "cameras.txt"
    path.write_text("1 PINHOLE 1000 667 1200 1200 500 333.5\n")
    return str(path)


def test_geo_txt_wgs84_goes_to_utm(tmp_path):
    """lon 9 E is zone 32's central meridian: easting exactly 500 000 m."""
    f = tmp_path / "geo.txt"
    f.write_text("WGS84\na.jpg 9.0 51.0 300\nb.jpg 9.0 51.001 300\n")
    opts = PriorsOptions(
        camera_path=_single_camera_text(tmp_path), require_rotation=False
    )
    block = read_priors(f, None, opts)
    a, b = (block.image_by_name(n).cam_from_world.center for n in ("a.jpg", "b.jpg"))
    np.testing.assert_allclose([a[0], b[0]], 500_000.0, atol=1e-6)
    # 0.001 deg of latitude is 111.2 m (x 0.9996 scale on the meridian)
    assert b[1] - a[1] == pytest.approx(111.25 * 0.9996, abs=0.2)
    assert a[2] == 300.0
    assert block.cameras[1].model == "PINHOLE"


def _db_v3(path: Path, rows: list[tuple[int, str, tuple, int]]) -> None:
    """A COLMAP 3.9-3.11 style database (pose_priors keyed by image_id)."""
    con = sqlite3.connect(path)
    con.executescript(
        "CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY, model INTEGER, "
        "width INTEGER, height INTEGER, params BLOB, prior_focal_length INTEGER);"
        "CREATE TABLE images (image_id INTEGER PRIMARY KEY, name TEXT, "
        "camera_id INTEGER);"
        "CREATE TABLE pose_priors (image_id INTEGER PRIMARY KEY NOT NULL, "
        "position BLOB, coordinate_system INTEGER NOT NULL, position_covariance BLOB);"
    )
    params = np.array([1200, 500, 333.5], "<f8").tobytes()
    con.execute("INSERT INTO cameras VALUES (1, 0, 1000, 667, ?, 1)", (params,))
    for image_id, name, xyz, system in rows:
        con.execute("INSERT INTO images VALUES (?, ?, 1)", (image_id, name))
        blob = np.array(xyz, "<f8").tobytes()
        con.execute(
            "INSERT INTO pose_priors VALUES (?, ?, ?, NULL)", (image_id, blob, system)
        )
    con.commit()
    con.close()


def test_database_v3_wgs84_is_lat_lon(tmp_path):
    db = tmp_path / "old.db"
    _db_v3(
        db, [(1, "a.jpg", (51.0, 9.0, 300.0), 0), (2, "b.jpg", (51.0, 9.0, 310.0), 0)]
    )
    assert prior_format(db) == "database"
    block = read_priors(db, None, PriorsOptions(require_rotation=False))
    a = block.image_by_name("a.jpg")
    np.testing.assert_allclose(a.cam_from_world.center[0], 500_000.0, atol=1e-6)
    assert block.image_by_name("b.jpg").cam_from_world.center[2] == 310.0
    assert block.cameras[1].model == "SIMPLE_PINHOLE"


def test_database_v4_cartesian(tmp_path):
    import pycolmap

    db_path = tmp_path / "new.db"
    db = pycolmap.Database.open(str(db_path))
    cam = pycolmap.Camera(
        model="PINHOLE", width=1000, height=667, params=[1200, 1200, 500, 333.5]
    )
    cid = db.write_camera(cam)
    expected = {}
    for k, name in enumerate(["a.jpg", "b.jpg", "c.jpg"]):
        iid = db.write_image(pycolmap.Image(name=name, camera_id=cid))
        xyz = np.array([512_000.0 + k, 5_643_000.0 - k, 400.0 + 2 * k])
        prior = pycolmap.PosePrior(
            corr_data_id=pycolmap.data_t(
                sensor_id=pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cid),
                id=iid,
            ),
            position=xyz,
            coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
        )
        db.write_pose_prior(prior)
        expected[name] = xyz
    db.close()
    block = read_priors(db_path, None, PriorsOptions(require_rotation=False))
    assert sorted(im.name for im in block.images.values()) == sorted(expected)
    for name, xyz in expected.items():
        np.testing.assert_allclose(
            block.image_by_name(name).cam_from_world.center, xyz, atol=1e-6
        )
    assert block.cameras[cid].model == "PINHOLE"


def test_export_absolute_and_text(tmp_path, caplog):
    """A local model + georef.json exported absolute gives back the map frame."""
    absolute = read_model(SAMPLE / "priors")
    origin = np.array([512_340.0, 5_643_870.0, 100.0])
    local = tmp_path / "local"
    write_result(local, absolute.shifted(origin), Georef(origin, "EPSG:25832"))
    out = tmp_path / "abs"
    export_model(local, out, "absolute")
    assert "float32" in caplog.text  # float32 steps 0.5 m at 5.6e6 m
    back = read_model(out)
    for im in absolute.images.values():
        got = back.image_by_name(im.name).cam_from_world
        np.testing.assert_allclose(got.center, im.cam_from_world.center, atol=1e-6)
    georef = json.loads((out / "georef.json").read_text())
    assert georef["origin"] == [0.0, 0.0, 0.0] and georef["crs"] == "EPSG:25832"
    text = tmp_path / "text"
    export_model(local, text, "text")
    assert (text / "images.txt").is_file() and (text / "georef.json").is_file()
    opk = tmp_path / "abs.txt"
    export_model(local, opk, "opk")  # absolute centres, as from the absolute model
    rows = read_opk(opk, opk.read_text())
    got = dict(zip(rows.names, rows.xyz, strict=True))
    for im in absolute.images.values():
        np.testing.assert_allclose(got[im.name], im.cam_from_world.center, atol=1e-4)


def test_cli_errors_exit_2(tmp_path, capsys):
    out = tmp_path / "out"
    (out).mkdir()
    (out / "keep").write_text("x")
    argv = ["export", "--input_path", str(SAMPLE / "priors"), "--output_path"]
    assert main([*argv, str(out), "--output_type", "text"]) == 2
    assert "not empty" in capsys.readouterr().err
    geo = tmp_path / "geo.txt"
    geo.write_text("EPSG:25832\nN_00.jpg 512000 5643000 400\n")
    reg = [
        "register",
        "--image_path", str(SAMPLE / "images"),
        "--cadastre_path", str(SAMPLE / "cadastre.geojson"),
        "--input_path", str(geo),
        "--camera_params", "1200,500,333.5",
        "--output_path", str(tmp_path / "result"),
        "--heading_step", "0",  # no heading search: positions only refused
    ]  # fmt: skip
    assert main(reg) == 2
    err = capsys.readouterr().err
    assert "positions only" in err and str(geo) in err
    assert not (tmp_path / "result").exists()


@pytest.mark.parametrize(
    ("ypr", "expected"),
    [
        # looking east, 45 deg down: right = south, down = west-and-down
        ((90, -45, 0), [[0, -1, 0], [-S, 0, -S], [S, 0, -S]]),
        # looking north, horizontal, rolled 90 deg: right points down
        ((0, 0, 90), [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]),
    ],
)
def test_gimbal_matches_hand_computed(ypr, expected):
    R = cam_from_world_from_gimbal(np.array(ypr, float))[0]
    np.testing.assert_allclose(R, expected, atol=1e-12)


def test_nadir_gimbal_yaw_is_minus_kappa():
    yaw = np.array([-102.3, 0.0, 37.0, 170.0])
    R = cam_from_world_from_gimbal(np.column_stack([yaw, -90 + 0 * yaw, 0 * yaw]))
    np.testing.assert_allclose(opk_from_cam_from_world(R)[:, 2], -yaw, atol=1e-9)


def _jpeg_with_xmp(path: Path, tags: dict[str, str]) -> None:
    """A tiny JPEG with a DJI-style XMP packet in an APP1 segment."""
    import cv2

    ok, jpeg = cv2.imencode(".jpg", np.zeros((8, 12), np.uint8))
    attrs = " ".join(f'drone-dji:{k}="{v}"' for k, v in tags.items())
    xmp = (
        b"http://ns.adobe.com/xap/1.0/\x00<x:xmpmeta><rdf:Description "
        + attrs.encode()
        + b"/></x:xmpmeta>"
    )
    segment = b"\xff\xe1" + (len(xmp) + 2).to_bytes(2, "big") + xmp
    path.write_bytes(jpeg[:2].tobytes() + segment + jpeg[2:].tobytes())


def test_xmp_folder(tmp_path):
    for k, yaw in enumerate([0.0, 90.0]):
        tags = {
            "GpsLatitude": f"+{51 + k * 0.001}",
            "GpsLongitude": "+9.0",
            "AbsoluteAltitude": "+350.5",
            "GimbalYawDegree": f"{yaw}",
            "GimbalPitchDegree": "-45.0",
            "GimbalRollDegree": "0.0",
        }
        _jpeg_with_xmp(tmp_path / f"DJI_{k}.JPG", tags)
    assert prior_format(tmp_path) == "xmp"
    block = read_priors(tmp_path, tmp_path, PriorsOptions(camera_params="10,6,4"))
    a, b = (block.image_by_name(f"DJI_{k}.JPG").cam_from_world for k in (0, 1))
    np.testing.assert_allclose(a.center[0], 500_000.0, atol=1e-6)
    # The height passes through pyproj's 3D transform: exact to ~1e-10 m.
    np.testing.assert_allclose(a.center[2], 350.5, atol=1e-6)
    np.testing.assert_allclose(b.rotation, HAND_GIMBAL_EAST, atol=1e-12)
    assert (block.cameras[1].width, block.cameras[1].height) == (12, 8)
    (tmp_path / "plain.jpg").write_bytes((tmp_path / "DJI_0.JPG").read_bytes()[:2])
    with pytest.raises(InputError, match="plain.jpg"):
        read_priors(tmp_path, tmp_path, PriorsOptions(camera_params="10,6,4"))


HAND_GIMBAL_EAST = [[0, -1, 0], [-S, 0, -S], [S, 0, -S]]


def test_geo_txt_into_a_declared_crs_keeps_x_east(tmp_path):
    """EPSG:31468 declares northing first; positions still come out x = east.

    Gauss-Krueger zone 4 has its central meridian at 12 E with a false
    easting of 4 500 000 m; the DHDN datum shift is ~100 m.
    """
    f = tmp_path / "geo.txt"
    f.write_text("EPSG:4326\na.jpg 12.0 51.0 300\n")
    opts = PriorsOptions(
        camera_path=_single_camera_text(tmp_path),
        require_rotation=False,
        crs="EPSG:31468",
    )
    centre = read_priors(f, None, opts).image_by_name("a.jpg").cam_from_world.center
    assert abs(centre[0] - 4_500_000.0) < 300.0
    assert abs(centre[1] - 5_651_000.0) < 3_000.0
