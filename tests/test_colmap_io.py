"""COLMAP model I/O: round trips, atomic writes, errors, and COLMAP 3.8 as reader."""

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from obliq_colmap import colmap_io as io
from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder
from obliq_colmap.geometry import Camera, Pose, rotation_from_axis_angle

ORIGIN = np.array([512300.0, 5612400.0, 130.0])


def make_block(model="PINHOLE", params=(1500.0, 1500.0, 1000.0, 670.0)):
    cam = Camera(model, 2000, 1340, np.array(params), camera_id=3)
    images = {}
    for k in range(3):
        R = rotation_from_axis_angle([np.radians(135.0), 0.01 * k, 0.02 * k])
        images[k + 1] = io.ImageRecord(
            k + 1, f"dir/img_{k}.jpg", 3, Pose.from_center(R, [20.0 * k, -300.0, 350.0])
        )
    return io.Block({3: cam}, images)


def make_points(block):
    pts = []
    for k in range(5):
        X = np.array([5.0 * k, 10.0, 2.0])
        obs = [(i, np.array([100.0 + k, 200.0 + i])) for i in block.images]
        pts.append(io.Point3D(X, obs))
    return pts


def test_write_read_round_trip(tmp_path):
    block = make_block()
    out = tmp_path / "model"
    io.write_result(out, block, io.Georef(ORIGIN, "EPSG:25832"), make_points(block))
    back = io.read_model(out)
    assert {im.name for im in back.images.values()} == {
        im.name for im in block.images.values()
    }
    for i, im in block.images.items():
        np.testing.assert_allclose(
            back.images[i].cam_from_world.rotation,
            im.cam_from_world.rotation,
            atol=1e-12,
        )
        np.testing.assert_allclose(
            back.images[i].cam_from_world.translation,
            im.cam_from_world.translation,
            atol=1e-9,
        )
    np.testing.assert_array_equal(back.cameras[3].params, block.cameras[3].params)
    georef = json.loads((out / "georef.json").read_text())
    assert georef["crs"] == "EPSG:25832"
    assert georef["origin"] == [float(v) for v in ORIGIN]
    assert all(isinstance(v, float) for v in georef["origin"])
    # Tracks: every point seen in the 3 images, observations in points2D.
    rec = pycolmap.Reconstruction(str(out))
    assert rec.num_points3D() == 5
    for point in rec.points3D.values():
        assert point.track.length() == 3
    for image in rec.images.values():
        assert image.num_points3D == 5
    assert not list(tmp_path.glob(".model.tmp-*"))


def test_text_model_is_read(tmp_path):
    block = make_block("SIMPLE_RADIAL", (1500.0, 1000.0, 670.0, -0.01))
    rec = io.to_reconstruction(block)
    (tmp_path / "txt").mkdir()
    rec.write_text(str(tmp_path / "txt"))
    back = io.read_model(tmp_path / "txt")
    assert back.cameras[3].model == "SIMPLE_RADIAL"
    assert len(back.images) == 3


def test_shifted_keeps_projections():
    block = make_block()
    local = block.shifted(ORIGIN)
    X_abs = np.array([[10.0, 20.0, 5.0]]) + ORIGIN
    for i in block.images:
        a = block.images[i].cam_from_world.transform(X_abs)
        b = local.images[i].cam_from_world.transform(X_abs - ORIGIN)
        np.testing.assert_allclose(a, b, atol=1e-6)
    back = local.shifted(-ORIGIN)
    np.testing.assert_allclose(
        back.images[1].cam_from_world.translation,
        block.images[1].cam_from_world.translation,
        atol=1e-6,
    )


def test_output_may_exist_if_empty(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    io.write_result(out, make_block(), io.Georef(ORIGIN))
    assert (out / "images.bin").is_file() and (out / "georef.json").is_file()


def test_refuses_non_empty_output(tmp_path):
    out = tmp_path / "full"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    with pytest.raises(InputError, match="not empty"):
        io.write_result(out, make_block(), io.Georef(ORIGIN))
    assert (out / "keep.txt").read_text() == "precious"


def test_failed_write_leaves_nothing(tmp_path):
    out = tmp_path / "model"
    with pytest.raises(RuntimeError), AtomicFolder(out) as tmp:
        (tmp / "cameras.bin").write_bytes(b"partial")
        raise RuntimeError("crash in the middle")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_output_location_is_refused_before_any_work(
    tmp_path, monkeypatch
):
    # (as root a read-only mode does not stop writing: the refusal is
    # simulated where the probe writes)
    from obliq_colmap import files

    def refuse(*args, **kwargs):
        raise PermissionError(30, "Read-only file system")

    monkeypatch.setattr(files.tempfile, "mkdtemp", refuse)
    with pytest.raises(InputError, match="cannot write there") as exc:
        files.check_output_path(tmp_path / "model")
    assert str(tmp_path) in str(exc.value)
    assert list(tmp_path.iterdir()) == []


def test_an_output_folder_that_is_a_mount_point_is_filled_in_place(
    tmp_path, monkeypatch
):
    """A mount point cannot be renamed onto (EBUSY): the model is staged
    inside it and its files renamed into place; nothing else is left."""
    out = tmp_path / "mounted"
    out.mkdir()
    real = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == out or real(p))
    replace = os.replace

    def busy(src, dst):  # what rename(2) onto a mount point does
        if Path(dst) == out:
            raise OSError(16, "Device or resource busy", str(dst))
        replace(src, dst)

    monkeypatch.setattr(os, "replace", busy)
    io.write_result(out, make_block(), io.Georef(ORIGIN))
    plain = tmp_path / "plain"
    io.write_result(plain, make_block(), io.Georef(ORIGIN))
    assert sorted(p.name for p in out.iterdir()) == sorted(
        p.name for p in plain.iterdir()
    )
    shutil.rmtree(plain)
    assert [p.name for p in tmp_path.iterdir()] == ["mounted"]


def test_read_errors_name_the_path(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        io.read_model(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a COLMAP model") as exc:
        io.read_model(tmp_path / "empty")
    assert str(tmp_path / "empty") in str(exc.value)
    bad = tmp_path / "bad"
    bad.mkdir()
    for name in io.MODEL_FILES:
        (bad / f"{name}.bin").write_bytes(b"\x01\x02")
    with pytest.raises(InputError, match="cannot read"):
        io.read_model(bad)


def test_non_perspective_camera_rejected(tmp_path):
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="OPENCV_FISHEYE",
        width=100,
        height=100,
        params=[50, 50, 50, 50, 0, 0, 0, 0],
        camera_id=1,
    )
    rec.add_camera_with_trivial_rig(cam)
    im = pycolmap.Image(name="a.jpg", camera_id=1, image_id=1)
    rec.add_image_with_trivial_frame(im, Pose().to_rigid3d())
    rec.write_binary(str(tmp_path))
    with pytest.raises(InputError, match="OPENCV_FISHEYE"):
        io.read_model(tmp_path)


def test_priors_need_image_files(tmp_path):
    block = make_block()
    model = tmp_path / "priors"
    io.write_absolute_model(model, block)
    images = tmp_path / "images"
    (images / "dir").mkdir(parents=True)
    (images / "dir" / "img_0.jpg").write_bytes(b"")
    with pytest.raises(InputError, match="2 image"):
        io.read_priors(model, images)
    for k in (1, 2):
        (images / "dir" / f"img_{k}.jpg").write_bytes(b"")
    assert len(io.read_priors(model, images).images) == 3


@pytest.mark.colmap
@pytest.mark.skipif(
    shutil.which("colmap") is None,
    reason="COLMAP's command line (Debian package colmap) is not installed",
)
def test_colmap_reads_the_output(tmp_path):
    block = make_block("OPENCV", (1500, 1500, 1000, 670, -0.01, 0.001, 0.0, 0.0))
    out = tmp_path / "model"
    io.write_result(
        out.resolve(), block.shifted(ORIGIN), io.Georef(ORIGIN), make_points(block)
    )
    res = subprocess.run(
        ["colmap", "model_analyzer", "--path", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    text = res.stdout + res.stderr
    assert "Registered images: 3" in text
    assert "Points: 5" in text
    conv = tmp_path / "txt"
    conv.mkdir()
    res = subprocess.run(
        [
            "colmap",
            "model_converter",
            "--input_path",
            str(out),
            "--output_path",
            str(conv),
            "--output_type",
            "TXT",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    assert "dir/img_0.jpg" in (conv / "images.txt").read_text()
