"""Dense-matching export (issue 28, item 2): COLMAP's MVS rules on arrays,
the workspace on a tiny written model (five images: three that see the
points, one that sees them but has no observation, one that looks at the
sky), bad input, COLMAP's command line, and the 16-image sample."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from obliq_colmap.cli import main
from obliq_colmap.colmap_io import Block, Georef, ImageRecord, Point3D, write_result
from obliq_colmap.dense import DenseOptions, export_dense
from obliq_colmap.dense.check import check_workspace, read_patch_match_cfg
from obliq_colmap.dense.mvs_rules import (
    MvsModel,
    depth_ranges,
    pair_statistics,
    source_images,
)
from obliq_colmap.dense.support import read_points
from obliq_colmap.geometry import Camera, Pose

ORIGIN = np.array([512300.0, 5643900.0, 149.0])
W, H = 96, 72
NADIR = np.diag([1.0, -1.0, -1.0])  # camera z down, x east


def _scene() -> tuple[np.ndarray, Block]:
    """(N, 3) ground points on a 10 m grid (every other one on a 12 m roof)
    and five cameras 100 m up: 1-3 and 4 nadir (4: to be left without
    observations), 5 looking straight up."""
    g = np.arange(-60.0, 61.0, 10.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    z = np.where(np.arange(len(xy)) % 2 == 0, 0.0, 12.0)
    X = np.column_stack([xy, z])
    cams = {
        1: Camera("PINHOLE", W, H, np.array([60.0, 60.0, W / 2, H / 2]), 1),
        2: Camera("SIMPLE_RADIAL", W, H, np.array([62.0, W / 2, H / 2, 0.02]), 2),
    }
    centres = {1: (-15, 0), 2: (0, 0), 3: (15, 0), 4: (0, 15), 5: (0, 0)}
    images = {}
    for i, (cx, cy) in centres.items():
        R = np.eye(3) if i == 5 else NADIR
        C = np.array([cx, cy, 100.0])
        images[i] = ImageRecord(i, f"img_{i}.jpg", 1 + i % 2, Pose(R, -R @ C))
    return X, Block(cams, images)


def _project(block: Block, i: int, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    im = block.images[i]
    Xc = im.cam_from_world.transform(X)
    px = block.cameras[im.camera_id].img_from_cam(Xc)
    ok = (Xc[:, 2] > 0) & np.all((px >= 0) & (px <= [W, H]), axis=1)
    return np.flatnonzero(ok), px[ok]


def pycolmap_reconstruction(path: Path):
    import pycolmap

    return pycolmap.Reconstruction(str(path))


def _write_tiny(folder: Path, subfolders: bool = False) -> tuple[Path, Path]:
    """The tiny model (local frame, georef.json) and its image folder under
    ``folder``; with ``subfolders`` the images are named ``head<c>/img_<i>.jpg``."""
    X, block = _scene()
    if subfolders:
        for im in block.images.values():
            im.name = f"head{im.camera_id}/{im.name}"
    obs: list[list] = [[] for _ in X]
    for i in (1, 2, 3):
        for k, p in zip(*_project(block, i, X), strict=True):
            obs[k].append((i, p))
    points = [Point3D(x, o) for x, o in zip(X, obs, strict=True) if o]
    model = write_result(folder / "model", block, Georef(ORIGIN, "EPSG:25832"), points)
    images = folder / "images"
    # smooth texture: a warp off by 1 px changes it by ~15 grey levels
    v, u = np.mgrid[0:H, 0:W]
    for im in block.images.values():
        i = im.image_id
        rgb = [np.sin(u / 7 + i), np.cos(v / 5 + i), np.sin((u + v) / 9)]
        (images / im.name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(
            str(images / im.name), (127 + 100 * np.stack(rgb, -1)).astype(np.uint8)
        )
    return model, images


@pytest.fixture
def tiny_model(tmp_path) -> tuple[Path, Path]:
    """The tiny model and its image folder."""
    return _write_tiny(tmp_path)


def test_depth_ranges_follow_colmaps_rule():
    """Percentile indices and stretch against a plain per-image loop."""
    rng = np.random.default_rng(1)
    model = MvsModel(
        ["a", "b", "c"],
        np.stack([NADIR, NADIR, np.eye(3)]),
        np.stack([-NADIR @ [0, 0, 100.0], -NADIR @ [5, 0, 100.0], np.zeros(3)]),
        np.column_stack([rng.uniform(-50, 50, (250, 2)), rng.uniform(0, 30, 250)]),
        np.r_[np.arange(250), np.arange(0, 250, 3), np.arange(10)],
        np.r_[np.zeros(250, int), np.ones(84, int), np.full(10, 2)],
    )
    ranges, counts = depth_ranges(model)
    for k in range(3):
        pts = model.xyz[model.el_point[model.el_image == k]]
        d = np.sort(pts @ model.R[k, 2] + model.t[k, 2])
        d = d[d > 0]
        assert counts[k] == len(d)
        if len(d) == 0:  # image c looks up: every point behind it
            assert list(ranges[k]) == [-1.0, -1.0]
            continue
        lo, hi = d[int(len(d) * 0.01)], d[int(len(d) * 0.99)]
        np.testing.assert_allclose(ranges[k], [0.75 * lo, 1.25 * hi])


def test_source_images_need_the_triangulation_angle():
    """Two cameras 1 m apart at 100 m (0.6 deg) share their points but are
    not each other's source at 1 deg; a third 15 m away (8.5 deg) is."""
    X = np.column_stack([np.linspace(-10, 10, 5), np.zeros(5), np.zeros(5)])
    C = np.array([[0, 0, 100.0], [1, 0, 100.0], [15, 0, 100.0]])
    model = MvsModel(
        ["a", "b", "c"],
        np.stack([NADIR] * 3),
        -C @ NADIR.T,
        X,
        np.tile(np.arange(5), 3),
        np.repeat(np.arange(3), 5),
    )
    shared, angle = pair_statistics(model)
    assert shared[0, 1] == shared[0, 2] == 5 and shared[0, 0] == 0
    # the 75th percentile (nearest rank) of the pair's angles, from the rays
    r1, r2 = C[0] - X, C[2] - X
    a = np.arccos(
        np.sum(r1 * r2, 1) / np.linalg.norm(r1, axis=1) / np.linalg.norm(r2, axis=1)
    )
    assert angle[0, 2] == pytest.approx(np.sort(a)[3])
    src = source_images(shared, angle, 20, np.radians(1.0))
    assert [list(s) for s in src] == [[2], [2], [0, 1]]


def test_export_dense_layout_depth_ranges_and_georef(tiny_model, tmp_path, caplog):
    model, images = tiny_model
    out = tmp_path / "dense"
    summary = export_dense(model, images, out, DenseOptions(min_num_points=10))
    for rel in (
        "sparse/cameras.bin",
        "sparse/images.bin",
        "sparse/points3D.bin",
        "stereo/patch-match.cfg",
        "stereo/fusion.cfg",
        "stereo/depth_maps",
        "run-colmap-geometric.sh",
    ):
        assert (out / rel).exists(), rel
    assert sorted(p.name for p in (out / "images").iterdir()) == [
        f"img_{i}.jpg" for i in range(1, 6)
    ]
    script = out / "run-colmap-geometric.sh"
    assert subprocess.run(["sh", "-n", str(script)]).returncode == 0
    commands = [
        ln for ln in script.read_text().splitlines() if ln.startswith('"$COLMAP"')
    ]
    assert len(commands) == 2  # patch_match_stereo, stereo_fusion: not joined
    georef = json.loads((out / "georef.json").read_text())
    np.testing.assert_array_equal(georef["origin"], ORIGIN)
    assert georef["crs"] == "EPSG:25832"
    table = json.loads((out / "dense.json").read_text())["images"]
    assert table == summary["images"]
    # image 4 sees the points but had no observation: supported, kept
    assert table["img_4.jpg"]["num_points_own"] == 0
    assert table["img_4.jpg"]["num_points_support"] >= 10
    assert table["img_4.jpg"]["status"] == "kept"
    # image 5 looks at the sky: left out, by name, of both configurations
    assert table["img_5.jpg"]["status"] == "left_out"
    assert "img_5.jpg" in caplog.text
    config = read_patch_match_cfg(out / "stereo/patch-match.cfg")
    assert [ref for ref, _ in config] == [f"img_{i}.jpg" for i in range(1, 5)]
    assert all("img_5.jpg" not in src for _, src in config)
    fused = (out / "stereo/fusion.cfg").read_text().split()
    assert fused == [f"img_{i}.jpg" for i in range(1, 5)]
    check = check_workspace(out)
    assert check.ok, check.problems
    # every kept image's range holds the true depths of the points it sees
    # (fewer than 100 each: the percentiles are the extremes)
    X, block = _scene()
    for i in range(1, 5):
        keep, _ = _project(block, i, X)
        depth = block.images[i].cam_from_world.transform(X[keep])[:, 2]
        lo, hi = check.depth_range[f"img_{i}.jpg"]
        assert lo == pytest.approx(0.75 * depth.min(), rel=1e-6)
        assert hi == pytest.approx(1.25 * depth.max(), rel=1e-6)


def test_export_dense_all_kept_uses_colmaps_auto_selection(tiny_model, tmp_path):
    model, images = tiny_model
    out = tmp_path / "dense"
    # without image 5 nothing is left out: COLMAP's own source selection
    (images / "img_5.jpg").unlink()
    block_without_5 = tmp_path / "model5"
    X, block = _scene()
    del block.images[5]
    write_result(
        block_without_5,
        block,
        Georef(ORIGIN),
        [
            Point3D(
                x,
                [
                    (i, p)
                    for i in (1, 2, 3, 4)
                    for _, p in zip(*_project(block, i, x[None]), strict=True)
                ],
            )
            for x in X
        ],
    )
    export_dense(block_without_5, images, out, DenseOptions(num_src_images=7))
    config = read_patch_match_cfg(out / "stereo/patch-match.cfg")
    assert len(config) == 4 and all(src == ["__auto__", "7"] for _, src in config)
    assert check_workspace(out).ok


def test_two_view_points_are_left_out_by_default(tmp_path):
    """Wrong matches seen in two images (5, more than COLMAP's 1 %),
    triangulated 3 km below the ground, stretch those images' depth range
    to 1.25 x their depth; with the default minimum track length (3) they
    are left out and the range is the scene's (depths 88-100 m)."""
    import pycolmap

    model, images = _write_tiny(tmp_path)
    _, block = _scene()
    bad = np.column_stack([np.linspace(-2, 2, 5), np.zeros(5), np.full(5, -3000.0)])
    wrong = [
        Point3D(x, [(i, _project(block, i, x[None])[1][0]) for i in (1, 2)])
        for x in bad
    ]
    points = read_points(pycolmap.Reconstruction(str(model)))
    bad_model = write_result(tmp_path / "bad", block, Georef(ORIGIN), points + wrong)
    far = {}
    for n in (2, 3):
        options = DenseOptions(min_num_points=10, min_track_length=n)
        table = export_dense(bad_model, images, tmp_path / f"d{n}", options)["images"]
        far[n] = {
            k: r["depth_range_m"][1] for k, r in table.items() if r["depth_range_m"]
        }
    assert far[2]["img_1.jpg"] == pytest.approx(1.25 * 3100, rel=1e-3)
    assert far[3]["img_1.jpg"] == pytest.approx(1.25 * 100, rel=1e-3)
    assert far[2]["img_3.jpg"] == far[3]["img_3.jpg"] == pytest.approx(125, rel=1e-3)


def test_an_absolute_model_is_warned_about_float32(tmp_path, caplog):
    """The same scene in absolute UTM coordinates: COLMAP's MVS (float32)
    keeps 0.5 m at 5.6e6 m; the export says so (and still writes it)."""
    model, images = _write_tiny(tmp_path)
    _, block = _scene()
    points = read_points(pycolmap_reconstruction(model))
    for p in points:
        p.xyz = p.xyz + ORIGIN
    absolute = write_result(
        tmp_path / "abs", block.shifted(-ORIGIN), Georef(np.zeros(3)), points
    )
    local = export_dense(
        model, images, tmp_path / "d1", DenseOptions(min_num_points=10)
    )
    assert local["float32_step_m"] < 1e-5
    assert "float32" not in caplog.text
    summary = export_dense(
        absolute, images, tmp_path / "d2", DenseOptions(min_num_points=10)
    )
    assert summary["float32_step_m"] == 0.5
    assert "float32" in caplog.text


def test_image_names_with_folders(tmp_path):
    """Image names with a folder (one per head, as COLMAP allows): the
    workspace mirrors the folders, also where COLMAP writes depth maps."""
    model, images = _write_tiny(tmp_path, subfolders=True)
    ws = tmp_path / "dense"
    summary = export_dense(model, images, ws, DenseOptions(min_num_points=10))
    assert summary["num_kept"] == 4
    assert (ws / "images/head2/img_1.jpg").is_file()
    assert check_workspace(ws).ok


def test_max_image_size_scales_the_undistorted_images(tiny_model, tmp_path):
    model, images = tiny_model
    out = tmp_path / "dense"
    main(
        [
            "export_dense",
            "--input_path",
            str(model),
            "--image_path",
            str(images),
            "--output_path",
            str(out),
            "--max_image_size",
            "48",
            "--min_num_points",
            "10",
        ]
    )
    sizes = {cv2.imread(str(p)).shape[:2] for p in (out / "images").iterdir()}
    assert max(max(s) for s in sizes) <= 48


@pytest.mark.parametrize(
    "problem", ["missing image", "output not empty", "bad option", "not a model"]
)
def test_bad_input_exits_2_naming_the_problem(tiny_model, tmp_path, capsys, problem):
    model, images = tiny_model
    out = tmp_path / "dense"
    extra: list[str] = []
    expected = ""
    if problem == "missing image":
        (images / "img_3.jpg").unlink()
        expected = "img_3.jpg"
    elif problem == "output not empty":
        out.mkdir()
        (out / "x").write_text("x")
        expected = "not empty"
    elif problem == "bad option":
        extra = ["--min_num_points", "0"]
        expected = "min_num_points"
    else:
        model = images
        expected = "not a COLMAP model"
    code = main(
        [
            "export_dense",
            "--input_path",
            str(model),
            "--image_path",
            str(images),
            "--output_path",
            str(out),
            *extra,
        ]
    )
    assert code == 2
    assert expected in capsys.readouterr().err
    assert problem == "output not empty" or not out.exists()


def _colmap(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["colmap", *args], capture_output=True, text=True, timeout=120
    )


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP CLI not installed")
def test_colmap_model_analyzer_reads_the_workspace_model(tiny_model, tmp_path):
    model, images = tiny_model
    export_dense(model, images, tmp_path / "dense", DenseOptions(min_num_points=10))
    res = _colmap("model_analyzer", "--path", str(tmp_path / "dense/sparse"))
    assert res.returncode == 0, res.stderr
    text = res.stdout + res.stderr
    assert "Registered images: 5" in text


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP CLI not installed")
def test_undistortion_matches_colmaps_image_undistorter(tiny_model, tmp_path):
    """Same cameras as COLMAP 3.8's image_undistorter (one head has radial
    distortion) and the same pixels up to JPEG re-encoding (quality 90:
    ~1-2 grey levels; a 0.2 px warp error would add ~3 on this texture)."""
    import pycolmap

    model, images = tiny_model
    ws, ref = tmp_path / "dense", tmp_path / "colmap"
    export_dense(model, images, ws, DenseOptions(min_num_points=10))
    ref.mkdir()
    res = _colmap(
        "image_undistorter",
        "--image_path",
        str(images),
        "--input_path",
        str(model),
        "--output_path",
        str(ref),
    )
    assert res.returncode == 0, res.stderr[-2000:]
    ours = pycolmap.Reconstruction(str(ws / "sparse")).cameras
    theirs = pycolmap.Reconstruction(str(ref / "sparse")).cameras
    assert {c.model.name for c in ours.values()} == {"PINHOLE"}
    for cid, cam in ours.items():
        assert (cam.width, cam.height) == (theirs[cid].width, theirs[cid].height)
        np.testing.assert_allclose(cam.params, theirs[cid].params, rtol=1e-9)
    for name in ("img_1.jpg", "img_2.jpg"):  # distorted, pinhole
        a = cv2.imread(str(ws / "images" / name)).astype(float)
        b = cv2.imread(str(ref / "images" / name)).astype(float)
        assert np.abs(a - b).mean() < 3.0


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP CLI not installed")
def test_colmap_patch_match_stereo_runs_where_cuda_is(tiny_model, tmp_path):
    model, images = tiny_model
    ws = tmp_path / "dense"
    export_dense(model, images, ws, DenseOptions(min_num_points=10))
    res = _colmap(
        "patch_match_stereo",
        "--workspace_path",
        str(ws),
        "--PatchMatchStereo.geom_consistency",
        "true",
    )
    if "requires CUDA" in res.stdout + res.stderr:
        pytest.skip("COLMAP here is built without CUDA: " + res.stderr.strip())
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    maps = {p.name for p in (ws / "stereo/depth_maps").iterdir()}
    assert {f"img_{i}.jpg.geometric.bin" for i in range(1, 5)} <= maps


SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


@pytest.fixture(scope="module")
def sample_model(tmp_path_factory) -> Path:
    """``register`` on the 16-image sample, once."""
    out = tmp_path_factory.mktemp("sample") / "model"
    code = main(
        [
            "register",
            "--image_path",
            str(SAMPLE / "images"),
            "--cadastre_path",
            str(SAMPLE / "cadastre.geojson"),
            "--input_path",
            str(SAMPLE / "priors"),
            "--output_path",
            str(out),
        ]
    )
    assert code == 0
    return out


@pytest.mark.slow
def test_sample_every_registered_image_gets_a_depth_range(sample_model, tmp_path):
    """On register's output every image has its own points (no support
    needed) and COLMAP's rules give it a depth range and source images."""
    ws = tmp_path / "dense"
    summary = export_dense(sample_model, SAMPLE / "images", ws)
    assert summary["num_kept"] == summary["num_images"] == 16
    for row in summary["images"].values():
        assert row["num_points_support"] == 0
        assert row["num_points_own"] >= DenseOptions.min_num_points
        assert row["source_images"]
    assert check_workspace(ws).ok


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP CLI not installed")
def test_sample_workspace_matches_colmaps_image_undistorter(sample_model, tmp_path):
    """COLMAP 3.8's own image_undistorter on the same model writes the same
    stereo configuration and cameras as the export."""
    import pycolmap

    ws, ref = tmp_path / "dense", tmp_path / "colmap"
    # every point kept, as image_undistorter does
    export_dense(sample_model, SAMPLE / "images", ws, DenseOptions(min_track_length=2))
    ref.mkdir()
    res = _colmap(
        "image_undistorter",
        "--image_path",
        str(SAMPLE / "images"),
        "--input_path",
        str(sample_model),
        "--output_path",
        str(ref),
    )
    assert res.returncode == 0, res.stderr[-2000:]
    for cfg in ("patch-match.cfg", "fusion.cfg"):
        assert (ws / "stereo" / cfg).read_text().split() == (
            ref / "stereo" / cfg
        ).read_text().split()
    ours = pycolmap.Reconstruction(str(ws / "sparse"))
    theirs = pycolmap.Reconstruction(str(ref / "sparse"))
    assert sorted(ours.cameras) == sorted(theirs.cameras)
    for cid, cam in ours.cameras.items():
        assert cam.model == theirs.cameras[cid].model
        assert (cam.width, cam.height) == (
            theirs.cameras[cid].width,
            theirs.cameras[cid].height,
        )
        np.testing.assert_allclose(cam.params, theirs.cameras[cid].params, rtol=1e-9)
    assert ours.num_points3D() == theirs.num_points3D()
    res = _colmap("model_analyzer", "--path", str(ws / "sparse"))
    assert res.returncode == 0 and "Registered images: 16" in res.stdout + res.stderr
