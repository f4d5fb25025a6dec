"""The report package: uncertainty from the bundle's covariance (against
Monte Carlo truth), the map's projection, and the report folder (built from
a small model made of the sample's priors, and opened in a real browser)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from obliq_colmap.bundle import BundleOptions, solve_bundle
from obliq_colmap.cadastre import load_cadastre
from obliq_colmap.cli import main
from obliq_colmap.colmap_io import Block, Georef, read_priors, write_result
from obliq_colmap.geometry import Camera, Pose, axis_angle_from_rotation
from obliq_colmap.report import (
    horizontal_ellipse,
    pose_uncertainty,
    uncertainty_report,
)
from obliq_colmap.report.build import ReportOptions, build_report
from obliq_colmap.report.overlays import project_edges
from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"
CHROMIUM = shutil.which("chromium")


def test_pose_uncertainty_recovers_a_known_covariance():
    """A covariance built from known axes and angles gives them back."""
    a, b, theta = 0.8, 0.3, np.radians(30.0)
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s], [s, c]])
    cov = np.zeros((1, 6, 6))
    cov[0, :3, :3] = np.diag(np.radians([0.1, 0.05, 0.02]) ** 2)
    cov[0, 3:5, 3:5] = R @ np.diag([a * a, b * b]) @ R.T
    cov[0, 5, 5] = 0.4**2
    out = pose_uncertainty(cov)
    np.testing.assert_allclose(out["ellipse_m"][0], [a, b, 30.0], atol=1e-9)
    np.testing.assert_allclose(out["rotation_sd_deg"][0], [0.1, 0.05, 0.02])
    np.testing.assert_allclose(out["rotation_max_sd_deg"], [0.1])
    sd_xy = np.sqrt(np.diag(cov[0, 3:5, 3:5]))
    np.testing.assert_allclose(out["position_sd_m"][0], [*sd_xy, 0.4])
    # an axis has no sign: an ellipse along -30 deg reads 150 deg
    Rm = np.array([[c, s], [-s, c]])
    flipped = Rm @ np.diag([a * a, b * b]) @ Rm.T
    np.testing.assert_allclose(horizontal_ellipse(flipped[None])[0], [a, b, 150.0])


@pytest.mark.slow
def test_pose_sd_predicts_the_deviation_from_the_truth():
    """Monte Carlo over noise: the recorded pose blocks' sds are the RMS
    deviation of the solved centres (horizontal, where the map fixes the
    datum) and rotations from the truth.

    20 trials of 16 images; the deviations are dominated by modes shared by
    the images of a trial (~20 independent samples), so an RMS ratio is
    known to about 1 / sqrt(2 * 20) = 16 %: bounds at 3 sigma.
    """
    opts = BundleOptions(
        loss="none", function_tolerance=1e-14, parameter_tolerance=1e-14
    )
    dxy, sxy, drot, srot = [], [], [], []
    for seed in range(20):
        syn = make_synthetic_problem(
            seed=seed, buildings=(5, 5), stations=(2, 2), noise_px=0.5
        )
        out = solve_bundle(syn.problem, opts)
        names = {i: f"im{i}" for i in syn.problem.image_ids}
        unc = uncertainty_report(out, names)
        assert unc["pose_covariance"]
        for i in syn.problem.image_ids:
            e = unc["images"][names[i]]
            assert e["predicted_sd_px"] == pytest.approx(
                out.image_precision_px[i], abs=1e-4
            )
            true, solved = syn.poses[i], out.poses[i]
            dxy.append(solved.center[:2] - true.center[:2])
            sxy.append(e["position_sd_m"][:2])
            # solved R = Exp(omega) R_true: omega about the camera's axes
            omega = axis_angle_from_rotation(solved.rotation @ true.rotation.T)
            drot.append(np.degrees(omega))
            srot.append(e["rotation_sd_deg"])
    dxy, sxy, drot, srot = map(np.array, (dxy, sxy, drot, srot))
    pos = np.sqrt(np.mean(dxy**2, axis=0) / np.mean(sxy**2, axis=0))
    rot = np.sqrt(np.mean(drot**2, axis=0) / np.mean(srot**2, axis=0))
    assert np.all((pos > 0.53) & (pos < 1.47)), pos
    assert np.all((rot > 0.53) & (rot < 1.47)), rot


def test_uncertainty_report_lists_the_worst_first_with_the_final_pose_blocks():
    syn = make_synthetic_problem(seed=1, buildings=(3, 3), stations=(2, 1))
    out = solve_bundle(syn.problem, BundleOptions())
    names = {i: f"im{i}" for i in syn.problem.image_ids}
    unc = uncertainty_report(out, names)
    px = [e["predicted_sd_px"] for e in unc["images"].values()]
    assert px == sorted(px, reverse=True) and len(px) == len(names)
    # the position sd is the final covariance's own block
    i = syn.problem.image_ids[0]
    sd = np.sqrt(np.diag(out.pose_covariance[i])[3:])
    np.testing.assert_allclose(unc["images"][names[i]]["position_sd_m"], sd, atol=1e-4)
    # each observation group's factor and redundancy, as the bundle gave them
    groups = unc["variance_components"]
    assert set(groups) == set(out.variance_components) and "map rows" in groups
    v, red = out.variance_components["map rows"]
    assert groups["map rows"] == {"factor": round(v, 4), "redundancy": round(red, 1)}


def test_project_edges_through_a_known_camera():
    """A pinhole looking down +z: an edge at depth 10 lands where f X / Z says;
    an edge behind the camera is NaN."""
    cam = Camera("PINHOLE", 100, 100, np.array([100.0, 100.0, 50.0, 50.0]))
    edges = np.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 1.0], [0.0, 2.0]]])
    px = project_edges(edges, cam, Pose(np.eye(3), np.zeros(3)), 10.0)
    np.testing.assert_allclose(px, [[[50, 50], [60, 50]], [[50, 60], [50, 70]]])
    behind = project_edges(edges, cam, Pose(np.eye(3), np.zeros(3)), -10.0)
    assert np.all(np.isnan(behind))


def _small_model(folder: Path, names: tuple[str, ...]) -> Path:
    """A 'register' output made of the sample's priors (two images) with a
    minimal report.json; the poses are the priors' (before == after)."""
    priors = read_priors(SAMPLE / "priors")
    cad = load_cadastre(SAMPLE / "cadastre.geojson")
    origin = np.array([cad.origin[0], cad.origin[1], 148.0])
    keep = {i: im for i, im in priors.images.items() if im.name in names}
    used = {im.camera_id for im in keep.values()}
    block = Block({c: priors.cameras[c] for c in used}, keep).shifted(origin)
    images = {
        im.name: {
            "image_id": i,
            "status": "registered",
            "message": "",
            "vp_status": "ok",
            "num_segments": 10,
            "num_inlier_corners": 5,
            "residual_rms_px": 0.5,
            "ground_height_m": 147.0,
        }
        for i, im in keep.items()
    }
    report = {"software": "test", "num_images": 2, "num_registered": 2}
    report["images"] = images
    out = folder / "model"
    write_result(
        out, block, Georef(origin, cad.crs), [], {"report.json": json.dumps(report)}
    )
    return out


def _build(tmp_path: Path) -> Path:
    model = _small_model(tmp_path, ("N_00.jpg", "S_11.jpg"))
    return build_report(
        ReportOptions(
            model,
            SAMPLE / "images",
            SAMPLE / "cadastre.geojson",
            tmp_path / "report",
            SAMPLE / "priors",
        )
    )


def test_report_folder_links_every_overlay(tmp_path):
    page = _build(tmp_path)
    html = page.read_text()
    links = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert len(links) == 2 * 2 * 2  # two images, before / after, thumb + full
    assert all((page.parent / link).is_file() for link in links)
    assert "N_00.jpg" in html and "S_11.jpg" in html
    # nothing from the network: every link relative, no stylesheet or script
    assert not any("://" in link for link in links)
    assert "<link" not in html and "<script src" not in html
    assert json.loads((page.parent / "report.json").read_text())["images"]


def test_report_cli_names_a_model_without_report_json(tmp_path, capsys):
    (tmp_path / "m").mkdir()
    code = main(
        [
            "report",
            "--input_path",
            str(tmp_path / "m"),
            "--image_path",
            str(SAMPLE / "images"),
            "--cadastre_path",
            str(SAMPLE / "cadastre.geojson"),
            "--output_path",
            str(tmp_path / "r"),
        ]
    )
    assert code == 2
    assert "report.json" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium (Debian package) not found")
def test_report_renders_in_headless_chromium_with_every_overlay(tmp_path):
    page = _build(tmp_path)
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'chromium'}",
        "--virtual-time-budget=5000",
        "--dump-dom",
        page.as_uri(),
    ]
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120).stdout
    m = re.search(r'id="image-check" data-loaded="(\d+)" data-total="(\d+)"', dom)
    assert m, "the page's image check did not run"
    assert int(m.group(2)) == 4 and m.group(1) == m.group(2)
    assert dom.count("<svg") == 6  # four histograms, two plan views
