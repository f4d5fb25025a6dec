"""The automatic mode of georegister (issue 27 item 3) against exact truth."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from obliq_colmap.cli import main
from obliq_colmap.evaluate import EvaluateOptions, evaluate_model
from obliq_colmap.geometry import rotation_from_axis_angle
from obliq_colmap.georegister.automatic import Rays, fit_block

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


def test_fit_block_recovers_the_similarity_from_rays():
    """Rays from model cameras through map corners, the block displaced: the
    joint fit finds scale, heading and translation (noise-free: exactly)."""
    rng = np.random.default_rng(0)
    s, th, t = 27.0, np.radians(-63.0), np.array([120.0, -40.0])
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    cams = rng.uniform(-10, 10, (8, 2))  # model frame
    corners = rng.uniform(-400, 400, (200, 2))  # map frame
    cams_map = s * cams @ R.T + t
    image = np.repeat(np.arange(8), 25)
    corner = rng.integers(0, 200, len(image))
    d = corners[corner] - cams_map[image]
    bearing_model = (d / np.linalg.norm(d, axis=1, keepdims=True)) @ R  # R^T d
    rays = Rays(cams[image], bearing_model, image)
    pairs = np.c_[np.arange(len(image)), corner]
    start = (s * 1.01, th + np.radians(0.5), t + [5.0, -3.0])
    fit = fit_block(rays, corners, pairs, start)
    assert fit.scale == pytest.approx(s, rel=1e-9)
    assert fit.theta == pytest.approx(th, abs=1e-9)
    assert np.allclose(fit.translation, t, atol=1e-6)
    assert fit.rms_deg < 1e-6


@pytest.mark.slow
def test_automatic_mode_on_the_sample(tmp_path):
    """The sample's true cameras as an SfM model in an arbitrary similarity
    frame, placed on its map from its images and the priors' positions: every
    image within 2 px (the sample's own `register` gives ~0.3-0.5 px)."""
    gt = pycolmap.Reconstruction(str(SAMPLE / "gt"))
    c = np.mean([gt.images[i].projection_center() for i in gt.reg_image_ids()], 0)
    gt.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -c))
    R = rotation_from_axis_angle(np.array([0.3, -0.2, 1.1]))
    gt.transform(
        pycolmap.Sim3d(0.037, pycolmap.Rotation3d(R), np.array([3.0, -1, 0.5]))
    )
    sfm = tmp_path / "sfm"
    sfm.mkdir()
    gt.write_binary(str(sfm))
    out = tmp_path / "out"
    rc = main(
        ["georegister", "--input_path", str(sfm), "--image_path",
         str(SAMPLE / "images"), "--cadastre_path", str(SAMPLE / "cadastre.geojson"),
         "--priors_path", str(SAMPLE / "priors"), "--output_path", str(out),
         "--camera_kind", "oblique", "--no_progress"]
    )  # fmt: skip
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert report["placement"]["stage2"]["images_registered"] >= 12
    result = evaluate_model(out, SAMPLE, EvaluateOptions(vertical_offset="search"))
    means = np.array([im.mean_deviation_px for im in result.images])
    assert np.all(means < 2.0), means
    shutil.rmtree(out)


def test_automatic_mode_needs_priors(tmp_path, capsys):
    gt = pycolmap.Reconstruction(str(SAMPLE / "gt"))
    sfm = tmp_path / "sfm"
    sfm.mkdir()
    gt.write_binary(str(sfm))
    rc = main(
        ["georegister", "--input_path", str(sfm), "--image_path",
         str(SAMPLE / "images"), "--cadastre_path", str(SAMPLE / "cadastre.geojson"),
         "--output_path", str(tmp_path / "out")]
    )  # fmt: skip
    assert rc == 2 and "--priors_path" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
@pytest.mark.parametrize("with_map", [False, True])
def test_control_point_mode_on_the_sample(tmp_path, with_map):
    """An SfM-like model of the sample (true cameras, 0.5 px corner tracks, a
    random similarity frame) and its noisy control points: every image within
    2 px of the truth, with the block adjustment (the default); with the
    map too, its corner lines are rows of the adjustment."""
    from obliq_colmap.synthetic import load_scene
    from obliq_colmap.synthetic.sfm_like import write_sfm_like

    sfm = write_sfm_like(tmp_path / "sfm", load_scene(SAMPLE), seed=3)
    out = tmp_path / "out"
    rc = main(
        ["georegister", "--input_path", str(sfm), "--image_path",
         str(SAMPLE / "images"), "--control_points_path", str(sfm / "gcp_list.txt"),
         "--output_path", str(out), "--no_progress"]
        + (["--cadastre_path", str(SAMPLE / "cadastre.geojson")] if with_map else [])
    )  # fmt: skip
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert (report["block_adjustment"]["num_map_rows"] > 100) is with_map
    assert (
        report["block_adjustment"]["final_cost"]
        <= report["block_adjustment"]["initial_cost"]
    )
    result = evaluate_model(out, SAMPLE, EvaluateOptions(vertical_offset="search"))
    means = np.array([im.mean_deviation_px for im in result.images])
    assert np.all(means < 2.0), means
