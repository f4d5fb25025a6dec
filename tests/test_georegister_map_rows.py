"""The map's corner lines in georegister's block adjustment (issue 27 item 4):
with no control point, the map rows (horizontally), the VPs (the tilt) and
the priors' camera heights (the vertical datum) hold a known block."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from obliq_colmap.georegister.block import BlockAdjustmentOptions, adjust_block
from obliq_colmap.georegister.map_rows import (
    ImagePairs,
    gate_map_rows,
    map_rows,
    row_residuals_px,
)

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
        inlier_pairs=np.array([[7, 3], [9, 1]]), inlier_segments_px=through[[3, 1]]
    )
    vp = image_pairs(im, result, measured_directions=False)
    own = image_pairs(im, result, measured_directions=True)
    assert np.array_equal(vp.corner, [7, 9]) and np.array_equal(own.corner, [7, 9])
    assert np.array_equal(vp.segments, through[[3, 1]])
    assert np.array_equal(own.segments, free[[3, 1]])
    im.segments_free = None  # no free fits: the VP's lines
    assert np.array_equal(image_pairs(im, result, True).segments, through[[3, 1]])
