"""The block adjustment of georegister (issue 27 item 4) against exact truth."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from obliq_colmap.geometry import calibration_matrix
from obliq_colmap.georegister.block import BlockAdjustmentOptions, adjust_block

TRUE_PARAMS = (1380.0, 760.0, 503.0, 0.0)


def _block(rng, n_images=6, n_points=300, noise_px=0.3):
    """Cameras walking 15 m in front of a 30 m facade (points in a slab)."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="SIMPLE_RADIAL", width=1536, height=1024, params=list(TRUE_PARAMS)
    )
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    X = rng.uniform([-15, 14, -1], [15, 18, 12], (n_points, 3))  # facade at y ~ 15
    poses = {}
    for i in range(n_images):
        # a walk along the facade, each photo aimed at its middle (as
        # Herz-Jesu-P8: converging views, not a parallel strip, in which the
        # principal point and the headings are not separable)
        c = np.array([-12 + 4.8 * i, rng.uniform(-2, 2), 1.6])
        z = np.array([0.0, 16.0, 5.0]) - c
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        poses[i + 1] = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
        im = pycolmap.Image(name=f"im{i}.jpg", camera_id=1, image_id=i + 1)
        im.points2D = pycolmap.Point2DList()
        rec.add_image_with_trivial_frame(im, poses[i + 1])
    for Xk in X:
        track = pycolmap.Track()
        for i, pose in poses.items():
            uv = cam.img_from_cam((pose * Xk)[None])[0] + rng.normal(0, noise_px, 2)
            if not (0 <= uv[0] < 1536 and 0 <= uv[1] < 1024):
                continue
            image = rec.images[i]
            image.points2D.append(pycolmap.Point2D(uv))
            track.add_element(i, image.num_points2D() - 1)
        if track.length() >= 2:
            rec.add_point3D(Xk, track, np.zeros(3, np.uint8))
    return rec, X, poses


def _verticals(truth, start_params, sd_deg=0.05):
    """Each image's true vertical VP (the true lens's pixels) as stage 1
    reports it: its direction through the SfM model's (start) pinhole."""
    K_true = calibration_matrix("SIMPLE_RADIAL", np.array(TRUE_PARAMS))
    K_start = calibration_matrix("SIMPLE_RADIAL", np.asarray(start_params))
    out = {}
    for i, pose in truth.items():
        d = np.linalg.solve(K_start, K_true @ pose.rotation.matrix() @ [0, 0, -1.0])
        out[i] = (d / np.linalg.norm(d), sd_deg)
    return out


def _adjusted(noise_px: float, seed: int = 4, **options):
    """The block from a 10 px principal point error and 2 cm point noise,
    adjusted; its summary and each camera's centre error (m)."""
    rng = np.random.default_rng(seed)
    rec, X, truth = _block(rng, noise_px=noise_px)
    ids = list(rec.point3D_ids())
    true_xyz = {pid: rec.points3D[pid].xyz.copy() for pid in ids}
    # the SfM model's lens: principal point at the image centre, 10 px off
    rec.cameras[1].params = np.array([1375.0, 768.0, 512.0, 0.0])
    # start: every point moved by a small error, as after a similarity
    for pid in ids:
        rec.points3D[pid].xyz = rec.points3D[pid].xyz + rng.normal(0, 0.02, 3)
    far = sorted(ids, key=lambda p: true_xyz[p][0])
    control = {
        pid: (true_xyz[pid], np.array([0.01, 0.01, 0.01])) for pid in (far[0], far[-1])
    }
    verticals = _verticals(truth, rec.cameras[1].params)
    options = {"refine_focal_length": True, **options}
    summary = adjust_block(rec, control, verticals, BlockAdjustmentOptions(**options))
    errors = []
    for i, pose in truth.items():
        c = -pose.rotation.matrix().T @ pose.translation
        errors.append(np.linalg.norm(rec.images[i].projection_center() - c))
    return rec, summary, np.array(errors)


@pytest.mark.parametrize("solver", ["obliq", "ceres"])
def test_block_adjustment_is_exact_without_noise(solver):
    """Two control points and the verticals fix the block; the tracks fix the
    lens: from a 10 px principal point error back to the truth."""
    rec, summary, errors = _adjusted(noise_px=0.0, solver=solver)
    assert summary.num_control_rows == 2 and summary.num_vertical_rows == 6
    assert summary.final_cost < 1e-8 * summary.initial_cost
    assert np.allclose(rec.cameras[1].params[:3], [1380, 760, 503], atol=1e-3)
    assert errors.max() < 1e-4


@pytest.mark.parametrize("solver", ["obliq", "ceres"])
def test_block_adjustment_with_noise(solver):
    """0.3 px on 300 points: the principal point within ~1 px, cameras within
    a few cm (Herz-Jesu-P8, real: 3 cm)."""
    rec, summary, errors = _adjusted(noise_px=0.3, solver=solver)
    assert summary.final_cost < summary.initial_cost
    assert np.allclose(rec.cameras[1].params[1:3], [760, 503], atol=3.0)
    assert errors.max() < 0.1, errors


def test_the_project_solver_and_ceres_reach_the_same_optimum():
    """The same problem (0.3 px noise, the default options: focal held) in
    the project's bundle and in Ceres: the same start cost, the same final
    cost and the same cameras, to far below what the noise leaves in them
    (both converged to a relative cost change of 1e-12)."""
    out = {
        solver: _adjusted(noise_px=0.3, solver=solver, refine_focal_length=False,
                          function_tolerance=1e-12)
        for solver in ("obliq", "ceres")
    }  # fmt: skip
    (rec_o, sum_o, err_o), (rec_c, sum_c, _) = out["obliq"], out["ceres"]
    assert sum_o.solver == "obliq" and sum_c.solver == "ceres"
    assert sum_o.initial_cost == pytest.approx(sum_c.initial_cost, rel=1e-9)
    assert sum_o.final_cost < 0.1 * sum_o.initial_cost
    assert sum_o.final_cost == pytest.approx(sum_c.final_cost, rel=1e-8)
    # the noise moves the cameras by cm from the truth; the two optima must
    # agree to a thousandth of that, the principal points likewise
    tol_m = 1e-3 * float(np.median(err_o))
    assert tol_m > 1e-6  # the noise did move them
    for i in rec_o.reg_image_ids():
        d = rec_o.images[i].projection_center() - rec_c.images[i].projection_center()
        assert np.linalg.norm(d) < tol_m, (i, d)
    pp_o, pp_c = rec_o.cameras[1].params, rec_c.cameras[1].params
    assert np.abs(pp_o - pp_c)[1:3].max() < 1e-3 * np.abs(pp_o[1:3] - [760, 503]).max()
    assert pp_o[0] == pp_c[0] == 1375.0  # the focal held in both
    # the points too (the tie points' 3x3 blocks against Ceres' Schur)
    for pid in list(rec_o.point3D_ids())[:50]:
        d = rec_o.points3D[pid].xyz - rec_c.points3D[pid].xyz
        assert np.linalg.norm(d) < tol_m


def test_an_unknown_solver_is_refused():
    with pytest.raises(ValueError, match="solver"):
        BlockAdjustmentOptions(solver="lm")


@pytest.mark.parametrize("flag, solver", [([], "obliq"), (["ceres"], "ceres")])
def test_the_solver_flag_reaches_the_options(tmp_path, monkeypatch, flag, solver):
    """``--block_adjustment_solver``: obliq by default, ceres when asked."""
    import argparse

    from obliq_colmap.cli import georegister as cli

    seen = {}

    def fake(input_path, image_path, options):
        seen["options"] = options
        raise SystemExit(0)  # stop before anything is read or written

    monkeypatch.setattr(cli, "georegister", fake)
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    argv = [
        "--input_path",
        str(tmp_path),
        "--image_path",
        str(tmp_path),
        "--control_points_path",
        "x.txt",
        "--output_path",
        str(tmp_path / "o"),
    ]
    argv += ["--block_adjustment_solver", *flag] if flag else []  # fmt: skip
    with pytest.raises(SystemExit):
        cli.run(parser.parse_args(argv))
    assert seen["options"].block.solver == solver
