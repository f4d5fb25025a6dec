"""The map's corner lines in georegister's block adjustment (issue 27 item 4):
with no control point, the map rows (horizontally), the VPs (the tilt) and
the priors' camera heights (the vertical datum) hold a known block; the
map's facade edges (horizontal edges on the walls, matched across the images
into tracks of one height) as rows beside them."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pycolmap
import pytest

from obliq_colmap.cadastre import load_cadastre
from obliq_colmap.georegister.block import BlockAdjustmentOptions, adjust_block
from obliq_colmap.georegister.facade_rows import facade_rows, outlier_free
from obliq_colmap.georegister.map_rows import (
    ImagePairs,
    gate_map_rows,
    map_rows,
    row_residuals_px,
)
from obliq_colmap.lines import Segments

F, W, H = 1000.0, 1000, 700
NOISE_PX = 0.3  # tracks and segment ends, per axis
PRIOR_SD_M = 0.5  # the priors' camera centres, per axis


def _look_at(c: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _scene(rng):
    """Nine box buildings (36 corners, 8-20 m high) in a 120 m square, seen by
    8 oblique cameras (45 deg down, 110 m away, from all four sides), 400 tie
    points. Returns the reconstruction (true poses), the corners (C, 2),
    their heights (C,), the true cam_from_world per image and, per image,
    the visible corners' vertical edges as segments with noise."""
    cam = pycolmap.Camera(
        model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2]
    )
    cam.camera_id = 1
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    centres = np.array([[x, y] for x in (-40, 0, 40) for y in (-40, 0, 40)], float)
    half = rng.uniform(6, 10, (9, 2))
    box = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    corner_xy = np.concatenate(
        [c + h * box for c, h in zip(centres, half, strict=True)]
    )
    corner_h = np.repeat(rng.uniform(8, 20, 9), 4)
    poses = {}
    for k in range(8):
        a = np.pi / 4 * k
        c = np.array([110 * np.cos(a), 110 * np.sin(a), 80.0])
        target = np.array([20 * np.cos(a + 1), 20 * np.sin(a + 1), 0.0])
        R = _look_at(c, target)
        poses[k + 1] = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
        im = pycolmap.Image(name=f"im{k}.jpg", camera_id=1, image_id=k + 1)
        im.points2D = pycolmap.Point2DList()
        rec.add_image_with_trivial_frame(im, poses[k + 1])
    X = rng.uniform([-60, -60, 0], [60, 60, 20], (400, 3))
    for Xk in X:
        track = pycolmap.Track()
        for i, pose in poses.items():
            uv = cam.img_from_cam((pose * Xk)[None])[0] + rng.normal(0, NOISE_PX, 2)
            if 0 <= uv[0] < W and 0 <= uv[1] < H:
                image = rec.images[i]
                image.points2D.append(pycolmap.Point2D(uv))
                track.add_element(i, image.num_points2D() - 1)
        if track.length() >= 2:
            rec.add_point3D(Xk, track, np.zeros(3, np.uint8))
    pairs = {}
    for i, pose in poses.items():
        foot = np.c_[corner_xy, np.zeros(len(corner_xy))]
        top = np.c_[corner_xy, corner_h]
        ends = np.stack(
            [cam.img_from_cam(np.array([pose * p for p in e])) for e in (foot, top)],
            axis=1,
        )  # (C, 2, 2)
        inside = np.all((ends >= 0) & (ends < [W, H]), axis=(1, 2))
        seen = np.flatnonzero(inside)
        pairs[i] = ImagePairs(
            seen, ends[seen] + rng.normal(0, NOISE_PX, (len(seen), 2, 2))
        )
    return rec, corner_xy, poses, pairs


def _verticals(poses):
    """Each image's true down direction in its camera, exact VPs at 0.05 deg."""
    return {i: (p.rotation.matrix() @ [0.0, 0.0, -1.0], 0.05) for i, p in poses.items()}


def _centres(rec) -> np.ndarray:
    return np.array([rec.images[i].projection_center() for i in sorted(rec.images)])


def _perturbed(seed: int = 3):
    """The scene, the block moved by a similarity (1 m and 0.6 m across, 0.3
    deg about the vertical, a 0.1 deg tilt, scale 1.005) as the automatic
    mode's placement would leave it (its mean camera height the priors'),
    and the map rows built on it."""
    rng = np.random.default_rng(seed)
    rec, corner_xy, poses, pairs = _scene(rng)
    truth = _centres(rec)
    priors = {
        i: truth[k] + rng.normal(0, PRIOR_SD_M, 3)
        for k, i in enumerate(sorted(rec.images))
    }
    tilt = pycolmap.Rotation3d(np.radians([0.1, 0.0, 0.3]))
    rec.transform(pycolmap.Sim3d(1.005, tilt, [1.0, -0.6, 0.0]))
    dz = np.mean([p[2] for p in priors.values()]) - _centres(rec)[:, 2].mean()
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), [0.0, 0.0, dz]))
    rows = map_rows(rec, corner_xy, pairs)
    return rec, truth, poses, rows, priors


def test_map_rows_sit_on_their_lines_in_the_true_block():
    """On the true block every row is within the segments' noise of its line
    (two rows per pair), and a pair given the wrong corner is gated out."""
    rng = np.random.default_rng(5)
    rec, corner_xy, _, pairs = _scene(rng)
    rows = map_rows(rec, corner_xy, pairs)
    assert len(rows) == 2 * sum(len(p.corner) for p in pairs.values()) > 200
    r = row_residuals_px(rec, rows)
    assert np.sqrt(np.mean(r**2)) < 2 * NOISE_PX
    wrong = {1: ImagePairs((pairs[1].corner + 1) % len(corner_xy), pairs[1].segments)}
    bad = map_rows(rec, corner_xy, wrong)
    kept, _ = gate_map_rows(rec, bad, 5.0)
    assert len(kept) < 0.3 * len(bad)


@pytest.mark.parametrize("prior_sd", [None, PRIOR_SD_M])
def test_map_rows_hold_a_block_without_control_points(prior_sd):
    """From the moved start (metres off) back to the truth: horizontally to
    what 0.3 px on ~500 rows and ~2,700 track observations leaves (0.3 px
    is 4 cm at 130 m: 5 cm is one row's noise, far above the mean of
    hundreds), in height to the mean of the 8 priors' heights (4 sd of it):
    held where the start put it (None), or the priors observed at their sd
    (the rows' fixed heights, set on the start block, pull the datum weakly
    too: the segments' noise turns their lines off the verticals' images)."""
    rec, truth, poses, rows, priors = _perturbed()
    start = _centres(rec) - truth
    assert np.abs(start[:, :2]).max() > 0.5  # the start is far off
    options = BlockAdjustmentOptions(prior_center_sigma_m=prior_sd)
    summary = adjust_block(rec, {}, _verticals(poses), options, rows, priors)
    assert summary.num_map_rows == len(rows)
    assert summary.final_cost < 0.5 * summary.initial_cost
    err = _centres(rec) - truth
    assert np.abs(err[:, :2]).max() < 0.05, err
    tol_h = 4 * PRIOR_SD_M / np.sqrt(len(truth))
    assert abs(err[:, 2].mean()) < tol_h, err
    assert np.abs(err[:, 2] - err[:, 2].mean()).max() < 0.05, err
    if prior_sd is None:  # the mean camera height held exactly
        assert err[:, 2].mean() == pytest.approx(start[:, 2].mean(), abs=1e-6)


def test_without_map_rows_the_block_stays_where_it_was_put():
    """The same problem with ``map_rows=False``: nothing holds the block
    horizontally but its start (the priors' offset is free), so it stays
    metres off: the rows are what moved it above."""
    rec, truth, poses, rows, priors = _perturbed()
    options = BlockAdjustmentOptions(map_rows=False)
    summary = adjust_block(rec, {}, _verticals(poses), options, rows, priors)
    assert summary.num_map_rows == 0
    err = _centres(rec) - truth
    assert np.abs(err[:, :2]).max() > 0.3


@pytest.mark.parametrize(
    "flag, want",
    [
        ([], (True, True)),
        (["--block_adjustment_map_rows", "0"], (False, True)),
        (["--block_adjustment_map_directions", "vp"], (True, False)),
    ],
)
def test_the_map_rows_flags_reach_the_options(tmp_path, monkeypatch, flag, want):
    """``--block_adjustment_map_rows`` (on by default) and
    ``--block_adjustment_map_directions`` (measured by default)."""
    import argparse

    from obliq_colmap.cli import georegister as cli

    seen = {}

    def fake(input_path, image_path, options):
        seen["options"] = options
        raise SystemExit(0)

    monkeypatch.setattr(cli, "georegister", fake)
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    argv = ["--input_path", str(tmp_path), "--image_path", str(tmp_path),
            "--cadastre_path", "m.geojson",
            "--output_path", str(tmp_path / "o")]  # fmt: skip
    with pytest.raises(SystemExit):
        cli.run(parser.parse_args(argv + flag))
    block = seen["options"].block
    assert (block.map_rows, block.map_measured_directions) == want


def test_measured_directions_take_each_segments_own_fit():
    """``map_measured_directions``: a pair's segment is the free fit of the
    segment stage 2 matched (by its index), not the line through the VP."""
    from types import SimpleNamespace

    from obliq_colmap.georegister.map_rows import image_pairs

    through = np.arange(5 * 4, dtype=float).reshape(5, 2, 2)
    free = through + 100.0
    im = SimpleNamespace(segments=through, segments_free=free)
    result = SimpleNamespace(
        inlier_pairs=np.array([[7, 3], [9, 1]]),
        inlier_segments_px=through[[3, 1]],
        height_plane=np.array([0.01, 0.0, 42.0]),
    )
    vp = image_pairs(im, result, measured_directions=False)
    assert np.array_equal(vp.height_plane, [0.01, 0.0, 42.0])  # the facades' ground
    own = image_pairs(im, result, measured_directions=True)
    assert np.array_equal(vp.corner, [7, 9]) and np.array_equal(own.corner, [7, 9])
    assert np.array_equal(vp.segments, through[[3, 1]])
    assert np.array_equal(own.segments, free[[3, 1]])
    im.segments_free = None  # no free fits: the VP's lines
    assert np.array_equal(image_pairs(im, result, True).segments, through[[3, 1]])


def _with_facades(tmp_path):
    """:func:`_perturbed` with the facade rows of its floor lines (as
    ``test_facade_rows_leave_the_block_where_the_map_rows_put_it``)."""
    rec, truth, poses, rows, priors = _perturbed()
    # _perturbed's scene: the same draw, the true block
    true_rec, corners, _, _ = _scene(np.random.default_rng(3))
    cad = _map(tmp_path, corners)
    segments = _floor_lines(true_rec, corners, np.random.default_rng(11))
    rows.facades = facade_rows(rec, segments, {i: np.zeros(3) for i in segments}, cad)
    return rec, truth, poses, rows, priors


def _adjusted_both(control: bool, facades_in=None, **options):
    """The moved block adjusted by each solver on the same problem (map rows,
    VPs; with ``control`` two tie points observed at 1 cm as control
    points, else the mean camera height held; with ``facades_in`` (a
    folder for the map) the facade rows too), both to a relative cost
    change of 1e-12. Returns {solver: (rec, summary)} and the truth."""
    out = {}
    for solver in ("obliq", "ceres"):
        if facades_in is None:
            rec, truth, poses, rows, _ = _perturbed()
        else:
            rec, truth, poses, rows, _ = _with_facades(facades_in)
        ctrl = {}
        if control:
            ids = sorted(rec.point3D_ids())
            xyz = np.array([rec.points3D[p].xyz for p in ids])
            far = (ids[int(np.argmin(xyz[:, 0]))], ids[int(np.argmax(xyz[:, 0]))])
            ctrl = {p: (rec.points3D[p].xyz + 0.01, np.full(3, 0.01)) for p in far}
        opts = BlockAdjustmentOptions(
            solver=solver, function_tolerance=1e-12, **options
        )
        summary = adjust_block(rec, ctrl, _verticals(poses), opts, rows)
        out[solver] = (rec, summary)
    return out, truth


@pytest.mark.parametrize(
    "facades",
    [False, pytest.param(True, marks=pytest.mark.slow)],  # 0.8-1.6 s
)
@pytest.mark.parametrize("control, focal", [(False, True), (True, False)])
def test_ceres_with_the_map_rows_reaches_the_same_optimum(
    control, focal, facades, tmp_path
):
    """The map rows in Ceres (a pyceres cost per image, the Cauchy loss
    inside) and in the project's bundle: the same start cost (the same
    problem), the same final cost and the same cameras and lens, to far
    below what the noise moved them (the automatic mode's problem, the
    mean camera height held: a hard constraint in the bundle, a stiff row
    in Ceres, the focal refined; and with control points instead, the focal
    held: with it refined, fy and cy wander off along a weak mode of this
    8-image block and neither solver converges in 100 iterations). With
    the facade rows too (their tracks' heights unknowns, a first solve, one
    outlier round, a second solve): the same rows kept and the same
    optimum."""
    pytest.importorskip("pyceres", reason="the Ceres check needs pyceres")
    out, truth = _adjusted_both(
        control, tmp_path if facades else None, refine_focal_length=focal
    )
    (rec_o, s_o), (rec_c, s_c) = out["obliq"], out["ceres"]
    assert s_o.num_map_rows == s_c.num_map_rows > 400
    assert s_o.num_facade_rows == s_c.num_facade_rows
    assert s_o.num_facade_tracks == s_c.num_facade_tracks
    assert (s_c.num_facade_rows > 100) == facades
    assert s_o.initial_cost == pytest.approx(s_c.initial_cost, rel=1e-9)
    assert s_o.final_cost < 0.5 * s_o.initial_cost
    assert s_o.final_cost == pytest.approx(s_c.final_cost, rel=1e-8)
    c_o, c_c = _centres(rec_o), _centres(rec_c)
    tol_m = 1e-3 * float(np.median(np.linalg.norm(c_o - truth, axis=1)))
    assert tol_m > 1e-6  # the noise did move them
    assert np.linalg.norm(c_o - c_c, axis=1).max() < tol_m
    p_o, p_c = rec_o.cameras[1].params, rec_c.cameras[1].params
    assert np.abs(p_o - p_c).max() < 1e-3 * np.abs(p_o - [F, F, W / 2, H / 2]).max()


def test_the_map_line_cost_jacobians_match_finite_differences():
    """:class:`MapLineRows`' Jacobians (pose block along the quaternion's
    tangent and the translation; the camera's parameters) against central
    differences of its own residuals, rows well inside and far out on the
    Cauchy loss."""
    pytest.importorskip("pyceres", reason="the Ceres check needs pyceres")
    from obliq_colmap.georegister.block_ceres import MapLineRows

    rec, _, _, rows, _ = _perturbed()
    image = rec.images[1]
    sel = rows.image_id == 1
    X = np.c_[rows.xy[sel], rows.height[sel]]
    line = rows.line[sel].copy()
    line[::7, 2] += 6.0  # some rows 6 px off: on the loss's flat part
    cost = MapLineRows(X, line, image.camera, 1.5, 2.0)
    pose = np.array(rec.frame(image.frame_id).rig_from_world.params, float)
    params = np.array(image.camera.params, float)
    n = cost.num_residuals()

    def evaluate(pose, params, jac=False):
        r = np.empty(n)
        J = [np.empty(n * 7), np.empty(n * 4)] if jac else None
        assert cost.Evaluate([pose, params], r, J)
        return (r, [J[0].reshape(n, 7), J[1].reshape(n, 4)]) if jac else r

    r0, (J_pose, J_par) = evaluate(pose, params, jac=True)
    # the tangent of the unit quaternion: q <- q + eps (0, e / 2) * q
    q = pycolmap.Rotation3d(pose[:4])
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        dq = []
        for s in (1, -1):
            p = pose.copy()
            p[:4] = (pycolmap.Rotation3d(s * e) * q).quat
            dq.append(p)
        num = (evaluate(dq[0], params) - evaluate(dq[1], params)) / 2e-6
        ana = J_pose[:, :4] @ ((dq[0] - dq[1])[:4] / 2e-6)
        assert np.allclose(ana, num, rtol=1e-5, atol=1e-6 * np.abs(num).max())
    for k in range(3):  # translation
        p1, p2 = pose.copy(), pose.copy()
        p1[4 + k] += 1e-5
        p2[4 + k] -= 1e-5
        num = (evaluate(p1, params) - evaluate(p2, params)) / 2e-5
        assert np.allclose(J_pose[:, 4 + k], num, rtol=1e-5, atol=1e-8)
    for k in range(4):
        h = 1e-5 * max(1.0, abs(params[k]))
        a, b = params.copy(), params.copy()
        a[k] += h
        b[k] -= h
        num = (evaluate(pose, a) - evaluate(pose, b)) / (2 * h)
        assert np.allclose(J_par[:, k], num, rtol=1e-4, atol=1e-8)
    # the cost is the bundle's: 1/2 rho(r^2) / sigma^2 with Cauchy at 2 px
    raw = cost.raw_residuals(pose, params)
    assert np.allclose(r0**2, 4.0 * np.log1p(raw**2 / 4.0) / 1.5**2)


def _tangent_steps(pose: np.ndarray, eps: float) -> list[tuple[np.ndarray, ...]]:
    """Per rotation axis the pose block turned by +-eps about it (the unit
    quaternion's tangent: ``q <- Exp(+-eps e_k) q``)."""
    q = pycolmap.Rotation3d(pose[:4])
    out = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        pair = []
        for s in (1, -1):
            p = pose.copy()
            p[:4] = (pycolmap.Rotation3d(s * e) * q).quat
            pair.append(p)
        out.append(tuple(pair))
    return out


@pytest.mark.parametrize("model", ["PINHOLE", "OPENCV"])
def test_the_facade_cost_jacobians_match_finite_differences(tmp_path, model):
    """:class:`FacadeRowsCost`' Jacobians (pose block along the quaternion's
    tangent and the translation, the camera's parameters, each track's
    height) against central differences of its own residuals, rows well
    inside and far out on the Cauchy loss, a pinhole camera and one with
    radial and tangential distortion (the rows' lines the pinhole's:
    residuals of some px); its raw rows are the bundle's
    ``dist_z`` (:func:`~obliq_colmap.bundle.residuals.horizontal_residuals`)
    and its cost the bundle's."""
    pytest.importorskip("pyceres", reason="the Ceres check needs pyceres")
    from obliq_colmap.bundle.residuals import horizontal_residuals
    from obliq_colmap.georegister.block_ceres import FacadeRowsCost

    rec, _, _, rows, _ = _with_facades(tmp_path)
    fac = rows.facades
    image = rec.images[int(fac.image_id[0])]
    sel = np.flatnonzero(fac.image_id == image.image_id)
    tracks, local = np.unique(fac.track[sel], return_inverse=True)
    assert len(sel) > 10 and len(tracks) > 3
    line = fac.line[sel].copy()
    line[::5, 2] += 6.0 * np.hypot(line[::5, 0], line[::5, 1])  # 6 px off
    params = np.array(image.camera.params, float)
    if model == "OPENCV":
        params = np.r_[params, 0.03, -0.01, 1e-3, -5e-4]
    P = len(params)
    cost = FacadeRowsCost(
        fac.anchor_xy[fac.track[sel]], local, line, model, P, 1.5, 2.0
    )
    pose = np.array(rec.frame(image.frame_id).rig_from_world.params, float)
    heights = fac.height[tracks] + 0.3  # off the start too
    n, T = cost.num_residuals(), len(tracks)

    def evaluate(pose, params, heights, jac=False):
        r = np.empty(n)
        J = None
        if jac:
            J = [np.empty(n * 7), np.empty(n * P)] + [np.empty(n) for _ in range(T)]
        blocks = [pose, params] + [np.array([h]) for h in heights]
        assert cost.Evaluate(blocks, r, J)
        if not jac:
            return r
        return r, J[0].reshape(n, 7), J[1].reshape(n, P), np.stack(J[2:], axis=1)

    r0, J_pose, J_par, J_h = evaluate(pose, params, heights, jac=True)
    for p1, p2 in _tangent_steps(pose, 1e-6):
        num = (evaluate(p1, params, heights) - evaluate(p2, params, heights)) / 2e-6
        ana = J_pose[:, :4] @ ((p1 - p2)[:4] / 2e-6)
        assert np.allclose(ana, num, rtol=1e-5, atol=1e-6 * np.abs(num).max())
    for k in range(3):  # translation
        p1, p2 = pose.copy(), pose.copy()
        p1[4 + k] += 1e-5
        p2[4 + k] -= 1e-5
        num = (evaluate(p1, params, heights) - evaluate(p2, params, heights)) / 2e-5
        assert np.allclose(J_pose[:, 4 + k], num, rtol=1e-5, atol=1e-8)
    for k in range(P):
        h = 1e-5 * max(1.0, abs(params[k])) if k < 4 else 1e-7
        a, b = params.copy(), params.copy()
        a[k] += h
        b[k] -= h
        num = (evaluate(pose, a, heights) - evaluate(pose, b, heights)) / (2 * h)
        assert np.allclose(J_par[:, k], num, rtol=1e-4, atol=1e-6 * np.abs(num).max())
    for k in range(T):
        a, b = heights.copy(), heights.copy()
        a[k] += 1e-6
        b[k] -= 1e-6
        num = (evaluate(pose, params, a) - evaluate(pose, params, b)) / 2e-6
        assert np.allclose(J_h[:, k], num, rtol=1e-5, atol=1e-8)
        assert np.all(J_h[local != k, k] == 0) and np.any(J_h[local == k, k] != 0)
    # its rows are the bundle's, its cost 1/2 rho(r^2) / sigma^2 with Cauchy
    # at 2 px
    raw = cost.raw_residuals(pose, params, heights)
    R = pycolmap.Rotation3d(pose[:4]).matrix()
    X = np.c_[fac.anchor_xy[fac.track[sel]], heights[local]]
    bundle = horizontal_residuals(
        model, params, np.repeat(R[None], n, 0),
        np.repeat((-R.T @ pose[4:])[None], n, 0), X, line, jacobians=False,
    ).residuals  # fmt: skip
    assert np.allclose(raw, bundle, rtol=0, atol=1e-9) and np.abs(raw).max() > 5.0
    assert np.allclose(r0**2, 4.0 * np.log1p(raw**2 / 4.0) / 1.5**2)


def _error_ratios(rec, truth, poses, u) -> tuple[list, list]:
    """Per camera of ``rec`` (adjusted; ``truth`` its true centres in image
    order, ``poses`` its true cam_from_world) the horizontal centre error
    and the rotation error over their sd from ``u``'s pose covariance,
    which must be finite and positive definite for every camera."""
    assert u is not None and set(u.pose_covariance) == set(rec.reg_image_ids())
    centre, rotation = [], []
    for k, i in enumerate(sorted(rec.images)):
        C = u.pose_covariance[i]
        assert np.all(np.isfinite(C)) and np.all(np.linalg.eigvalsh(C) > 0)
        e = rec.images[i].projection_center() - truth[k]
        # horizontal: where the mean height is the datum (held), its error
        # is no noise
        centre.append(np.linalg.norm(e[:2]) / np.sqrt(np.trace(C[3:5, 3:5])))
        R = rec.images[i].cam_from_world().rotation.matrix()
        dR = pycolmap.Rotation3d(R @ poses[i].rotation.matrix().T)
        rotation.append(abs(dR.angle()) / np.sqrt(np.trace(C[:3, :3])))
    return centre, rotation


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def test_the_block_covariance_predicts_the_errors():
    """The obliq solver's covariance (map rows in the problem): every
    camera has a finite pose covariance, and over 6 noise draws the centre
    and rotation errors against the truth sit at 0.5-2 times their
    predicted sd (RMS over cameras and draws): the tracks, segment ends and
    VPs carry exactly the noise they are weighted by here, up to the
    variance factor, which the covariance includes, and the map's corners
    their stated vertex error (0.98 / 0.82; with the corners as unknowns of
    the precision, 1.72 / 1.44)."""
    c_ratio, r_ratio = [], []
    options = BlockAdjustmentOptions()
    for seed in range(6):
        rec, truth, poses, rows, _ = _perturbed(10 + seed)
        # the map's vertex error at its stated sd, shared by a corner's rows
        _, corner = np.unique(np.round(rows.xy, 6), axis=0, return_inverse=True)
        corner = corner.ravel()
        rng = np.random.default_rng(40 + seed)
        offset = rng.normal(0.0, options.map_vertex_sigma_m, (corner.max() + 1, 2))
        rows = dataclasses.replace(rows, xy=rows.xy + offset[corner])
        summary = adjust_block(rec, {}, _verticals(poses), options, rows)
        c, r = _error_ratios(rec, truth, poses, summary.uncertainty)
        c_ratio += c
        r_ratio += r
    assert 0.5 < _rms(c_ratio) < 2.0, _rms(c_ratio)
    assert 0.5 < _rms(r_ratio) < 2.0, _rms(r_ratio)


def test_control_points_alone_give_a_block_covariance():
    """No map: the tracks, the VPs and three control points (0.05 m). The
    project's bundle computed its cofactor only where a problem had map
    rows; every camera now has a finite, positive definite pose covariance.
    Not yet calibrated here: over these 6 draws the horizontal centre errors
    are 2.65 times their sd (RMS; journal georegister.md, 2026-12-06), so
    the bound checks the order of magnitude only."""
    ratio = []
    for seed in range(6):
        rng = np.random.default_rng(20 + seed)
        rec, _, poses, _ = _scene(rng)
        truth = _centres(rec)
        ids = sorted(rec.points3D)[:: len(rec.points3D) // 3][:3]
        sd = np.full(3, 0.05)
        control = {p: (rec.points3D[p].xyz + rng.normal(0.0, 0.05, 3), sd) for p in ids}
        tilt = pycolmap.Rotation3d(np.radians([0.05, 0.0, 0.2]))
        rec.transform(pycolmap.Sim3d(1.002, tilt, [0.5, -0.3, 0.2]))
        options = BlockAdjustmentOptions()
        u = adjust_block(rec, control, _verticals(poses), options).uncertainty
        ratio += _error_ratios(rec, truth, poses, u)[0]
    assert 0.5 < _rms(ratio) < 4.0, _rms(ratio)


def test_the_block_covariance_is_ceres_covariance_without_a_robust_loss(monkeypatch):
    """The obliq solver's cofactor (its covariance over the variance factor)
    with map rows, VPs and the gauge against pycolmap's covariance of the
    Ceres problem at its optimum, both plain least squares (the robust
    losses' linearisations differ: 3 % in sd on the paper block): the same
    to 1e-4. Ceres' rotation tangent is half the rotation vector. Ours with
    one pooled variance factor, which the cofactor is the covariance over
    (with a component per observation group the covariance is a sandwich
    of the same cofactor)."""
    pytest.importorskip("pyceres", reason="the Ceres check needs pyceres")
    import functools

    import pyceres

    import obliq_colmap.georegister.block_bundle as block_bundle
    import obliq_colmap.georegister.block_ceres as block_ceres
    from obliq_colmap.bundle import BundleOptions
    from obliq_colmap.geometry import skew

    pooled = functools.partial(BundleOptions, variance_components=False)
    monkeypatch.setattr(block_bundle, "BundleOptions", pooled)

    # Ceres' problem holds the corners exactly: so does our precision here
    options = BlockAdjustmentOptions(
        loss_scale_px=1e6, function_tolerance=1e-12, map_vertex_sigma_m=None
    )
    rec, _, poses, rows, _ = _perturbed()
    ours = adjust_block(rec, {}, _verticals(poses), options, rows).uncertainty
    rec_c, _, _, rows, _ = _perturbed()
    got, solve = {}, pyceres.solve

    def solve_then_covariance(opts, problem, summary):
        solve(opts, problem, summary)
        got["ba"] = pycolmap.estimate_ba_covariance_from_problem(
            pycolmap.BACovarianceOptions(), rec_c, problem
        )

    monkeypatch.setattr(block_ceres.pyceres, "solve", solve_then_covariance)
    ceres = dataclasses.replace(options, solver="ceres")
    adjust_block(rec_c, {}, _verticals(poses), ceres, rows)
    for i in rec_c.reg_image_ids():
        T = rec_c.images[i].cam_from_world()
        R, t = T.rotation.matrix(), T.translation
        J = np.zeros((6, 6))
        J[:3, :3], J[3:, :3], J[3:, 3:] = 2 * np.eye(3), -2 * R.T @ skew(t), -R.T
        C_c = J @ got["ba"].get_cam_cov_from_world(i) @ J.T
        C_o = ours.pose_covariance[i] / ours.variance_factor
        assert np.allclose(C_o, C_c, rtol=1e-4, atol=1e-4 * np.abs(C_c).max())


def test_the_uncertainty_section_lists_the_cameras_worst_first():
    """report.json's ``uncertainty``: register's keys per written image,
    sorted by the centre's 3D sd; without a covariance, why."""
    from obliq_colmap.georegister.block import BlockAdjustmentSummary, BlockUncertainty
    from obliq_colmap.georegister.uncertainty import block_uncertainty_report

    cov = {i: np.diag([1e-8] * 3 + [s**2] * 3) for i, s in ((1, 0.01), (2, 0.05))}
    u = BlockUncertainty(cov, {1: 0.2, 2: float("nan")}, 0.5)
    summary = BlockAdjustmentSummary(1.0, 0.5, 3, 0, 2, "done", uncertainty=u)
    rep = block_uncertainty_report(summary, {1: "a.jpg", 2: "b.jpg", 3: "new.jpg"})
    assert rep["available"] and list(rep["images"]) == ["b.jpg", "a.jpg"]
    b = rep["images"]["b.jpg"]
    assert b["position_sd_m"] == [0.05, 0.05, 0.05] and b["predicted_sd_px"] is None
    assert set(b) >= {"horizontal_ellipse_m", "rotation_sd_deg", "rotation_max_sd_deg"}
    assert "uncertainty" not in summary.report()
    assert not block_uncertainty_report(None, {})["available"]
    summary.uncertainty = None
    assert "3000 camera" in block_uncertainty_report(summary, {1: "a.jpg"})["reason"]


ORIGIN = (500_000.0, 5_600_000.0)
FLOORS_M = (3.0, 6.0)  # the heights of the horizontal edges on every wall


def _map(tmp_path, corner_xy: np.ndarray):
    """The scene's nine boxes as a GeoJSON cadastre (EPSG:25832), read back
    in the scene's frame."""
    rings = corner_xy.reshape(-1, 4, 2) + ORIGIN
    features = [
        {
            "type": "Feature",
            "properties": {"id": f"b{k}"},
            "geometry": {
                "type": "Polygon",
                "coordinates": [[*r.tolist(), r[0].tolist()]],
            },
        }
        for k, r in enumerate(rings)
    ]
    doc = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "EPSG:25832"}},
        "features": features,
    }
    path = tmp_path / "map.geojson"
    path.write_text(json.dumps(doc))
    return load_cadastre(path, origin=ORIGIN)


def _floor_lines(rec, corner_xy, rng) -> dict[int, Segments]:
    """Per image the horizontal edges at ``FLOORS_M`` on the walls facing it
    (20-80 % of each wall's length), with the segments' noise."""
    rings = corner_xy.reshape(-1, 4, 2)
    out = {}
    for i in sorted(rec.images):
        image = rec.images[i]
        cam, pose = image.camera, image.cam_from_world()
        centre = image.projection_center()
        ends = []
        for ring in rings:
            middle = ring.mean(axis=0)
            for a, b in zip(ring, np.roll(ring, -1, axis=0), strict=True):
                out_dir = (a + b) / 2 - middle
                if out_dir @ (centre[:2] - (a + b) / 2) <= 0:
                    continue  # the wall faces away
                for z in FLOORS_M:
                    p = [np.r_[a + t * (b - a), z] for t in (0.2, 0.8)]
                    uv = cam.img_from_cam(np.array([pose * q for q in p]))
                    if np.all((uv >= 0) & (uv < [cam.width, cam.height])):
                        ends.append(uv + rng.normal(0, NOISE_PX, (2, 2)))
        ends = np.array(ends).reshape(-1, 2, 2)
        d = ends[:, 1] - ends[:, 0]
        normal = np.c_[d[:, 1], -d[:, 0]] / np.linalg.norm(d, axis=1)[:, None]
        out[i] = Segments(ends, normal, np.full(len(ends), 10.0))
    return out


def test_facade_rows_match_the_floor_lines_across_images(tmp_path):
    """On the true block every track is one floor line of one wall: its
    height one of ``FLOORS_M``, seen by two images or more."""
    rng = np.random.default_rng(5)
    rec, corner_xy, _, _ = _scene(rng)
    cad = _map(tmp_path, corner_xy)
    segments = _floor_lines(rec, corner_xy, rng)
    planes = {i: np.zeros(3) for i in segments}
    rows = facade_rows(rec, segments, planes, cad)
    assert rows.num_tracks > 20
    assert len(rows) >= 2 * rows.num_tracks
    assert np.bincount(rows.track).min() >= 2
    off = np.abs(rows.height[:, None] - np.array(FLOORS_M)[None]).min(axis=1)
    assert np.median(off) < 0.1 and np.mean(off < 0.5) > 0.9, rows.height
    kept = outlier_free(rows, np.r_[np.zeros(len(rows) - 1), 50.0], rows.height)
    assert len(kept) < len(rows)  # the one far row is gone


def test_facade_rows_leave_the_block_where_the_map_rows_put_it(tmp_path):
    """The moved block of the map rows' test (which the map rows alone bring
    back within 5 cm: ``test_map_rows_hold_a_block_without_control_points``),
    adjusted with the facade rows too, their track heights free: it comes
    back as closely, so the rows are consistent with the block they were
    matched on (a wrong anchor, height datum or raw line would pull it)."""
    rec, truth, poses, rows, priors = _perturbed()
    # _perturbed's scene: the same draw, the true block (the images, and
    # so their floor lines, do not move with the block)
    true_rec, corners, _, _ = _scene(np.random.default_rng(3))
    cad = _map(tmp_path, corners)
    segments = _floor_lines(true_rec, corners, np.random.default_rng(11))
    rows.facades = facade_rows(rec, segments, {i: np.zeros(3) for i in segments}, cad)
    assert len(rows.facades) > 100
    summary = adjust_block(rec, {}, _verticals(poses), BlockAdjustmentOptions(
        prior_center_sigma_m=PRIOR_SD_M), rows, priors)  # fmt: skip
    assert summary.num_facade_rows > 100
    err = _centres(rec) - truth
    assert np.abs(err[:, :2]).max() < 0.05, err
    assert np.abs(err[:, 2] - err[:, 2].mean()).max() < 0.05, err


def test_the_maps_vertex_error_is_shared_by_its_corners_rows():
    """The map's vertex sd in the block's precision (each corner's offset two
    unknowns that all its rows share): the cameras' sds grow with it, the
    solve does not change, and a vertex sd far below the rows' noise gives
    the corners-known precision back."""

    def adjusted(sigma):
        rec, _, poses, rows, priors = _perturbed()
        options = BlockAdjustmentOptions(
            prior_center_sigma_m=PRIOR_SD_M, map_vertex_sigma_m=sigma
        )
        s = adjust_block(rec, {}, _verticals(poses), options, rows, priors)
        sd = {i: np.sqrt(np.diag(c)[3:5].sum()) for i, c in
              s.uncertainty.pose_covariance.items()}  # fmt: skip
        return _centres(rec), sd

    known_c, known = adjusted(None)
    tiny_c, tiny = adjusted(1e-6)
    map_c, shared = adjusted(0.15)
    assert np.allclose(known_c, map_c) and np.allclose(known_c, tiny_c)
    for i in known:
        assert tiny[i] == pytest.approx(known[i], rel=1e-3)
        assert shared[i] > 1.2 * known[i]


@pytest.mark.slow
def test_the_precision_predicts_the_spread_the_maps_vertex_error_causes():
    """Against a Monte Carlo of the solve itself: the map's corners redrawn
    with their stated vertex sd (each corner's error shared by all its rows),
    the block solved again each time; the cameras' horizontal centres
    scatter as the precision predicts: measured / predicted variance in
    [0.3, 1.7]. Above: 1.7 is 1 + 2.4 sampling sds of a variance from 24
    draws (0.29). Below: room for pessimism, since the map rows' variance
    component carries part of the vertex error too. Counting the corners as
    unknowns of the precision instead (the estimator that would solve for
    them) gave 5.0 here."""
    sigma, draws = 0.3, 24
    options = BlockAdjustmentOptions(prior_center_sigma_m=PRIOR_SD_M,
                                     map_vertex_sigma_m=sigma)  # fmt: skip
    rec, _, poses, rows, priors = _perturbed()
    s = adjust_block(rec, {}, _verticals(poses), options, rows, priors)
    predicted = np.array([np.diag(c)[3:5].sum() for _, c in
                          sorted(s.uncertainty.pose_covariance.items())])  # fmt: skip
    _, corner = np.unique(np.round(rows.xy, 6), axis=0, return_inverse=True)
    corner = corner.ravel()
    rng = np.random.default_rng(17)
    centres = []
    for _ in range(draws):
        rec, _, poses, rows, priors = _perturbed()
        offset = rng.normal(0.0, sigma, (corner.max() + 1, 2))
        drawn = dataclasses.replace(rows, xy=rows.xy + offset[corner])
        adjust_block(rec, {}, _verticals(poses), options, drawn, priors)
        centres.append(_centres(rec)[:, :2])
    measured = np.var(np.array(centres), axis=0, ddof=1).sum(axis=1)
    ratio = float(np.mean(measured) / np.mean(predicted))
    assert 0.3 < ratio < 1.7, ratio
