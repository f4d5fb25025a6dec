"""The automatic mode for level cameras (issue 27 item 3 on a street): the
whole upright block onto the map from all images' vertical segments at once
(:mod:`obliq_colmap.georegister.block_lines`), on a synthetic street whose
images show a few building corners among many window edges."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest

from obliq_colmap.cadastre import load_cadastre
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import rotation_z
from obliq_colmap.georegister.block_lines import (
    heading_from_rotations,
    prior_similarity,
)
from obliq_colmap.georegister.lines_placement import lines_placement
from obliq_colmap.georegister.options import GeoregisterOptions
from obliq_colmap.georegister.run_automatic import _method
from obliq_colmap.georegister.similarity import similarity_upright
from obliq_colmap.georegister.vertical import ImageVertical, ModelVertical

F, W, H = 600.0, 800, 600
X0, Y0 = 500_000.0, 5_600_000.0
FACADE_Y = 12.0  # the terraces' street front; the walk is along y = 0
MAP_NOISE_M = 0.05  # the map's joins, per axis
SEGMENT_NOISE_PX = 0.3  # segment ends, per axis
PRIOR_POS_M, PRIOR_HEADING_DEG = 3.0, 4.0  # a phone's GPS and compass
PRIOR_BIAS_M = np.array([1.2, -0.8])  # the GPS in a street canyon


def _look(direction: np.ndarray) -> np.ndarray:
    z = direction / np.linalg.norm(direction)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _terraces(rng) -> np.ndarray:
    """(B + 1,) x of the joins of a row of terraces 6-10 m wide."""
    xs = [-70.0]
    while xs[-1] < 70.0:
        xs.append(xs[-1] + rng.uniform(6.0, 10.0))
    return np.array(xs)


def _write_map(path, joins: np.ndarray, rng) -> np.ndarray:
    """The terraces (10 m deep) as GeoJSON; the joins' map positions (noisy,
    shared by the two buildings at each) as (B + 1,) x offsets."""
    noisy = rng.normal(0.0, MAP_NOISE_M, (len(joins), 2))
    feats = []
    for k in range(len(joins) - 1):
        a = (joins[k] + noisy[k, 0], FACADE_Y + noisy[k, 1])
        b = (joins[k + 1] + noisy[k + 1, 0], FACADE_Y + noisy[k + 1, 1])
        ring = [a, b, (b[0], FACADE_Y + 10), (a[0], FACADE_Y + 10), a]
        ring = [[X0 + x, Y0 + y] for x, y in ring]
        feats.append(
            {
                "type": "Feature",
                "properties": {"id": str(k)},
                "geometry": {"type": "Polygon", "coordinates": [ring]},
            }
        )
    crs = {"type": "name", "properties": {"name": "EPSG:25832"}}
    doc = {"type": "FeatureCollection", "crs": crs, "features": feats}
    path.write_text(json.dumps(doc))
    return noisy


def _project(R, c, X):
    x = (X - c) @ R.T
    return F * x[:, :2] / x[:, 2:] + [W / 2, H / 2], x[:, 2]


def _segments(R, c, xs, z0, z1, rng) -> np.ndarray:
    """(N, 2, 2) images of the verticals at (xs, FACADE_Y) from z0 to z1,
    clipped to the image, with noise; those out of view dropped."""
    n = len(xs)
    lo = np.c_[xs, np.full(n, FACADE_Y), np.full(n, z0)]
    hi = np.c_[xs, np.full(n, FACADE_Y), np.full(n, z1)]
    (a, da), (b, db) = _project(R, c, lo), _project(R, c, hi)
    ok = (da > 1) & (db > 1) & (a[:, 0] > 5) & (a[:, 0] < W - 5)
    a, b = a[ok], b[ok]
    # clipped to the image rows along the (slanted) image of the vertical
    t = np.clip((np.array([0.0, H])[:, None] - a[:, 1]) / (b[:, 1] - a[:, 1]), 0, 1)
    t0, t1 = t.min(axis=0), t.max(axis=0)
    seg = np.stack([a + t0[:, None] * (b - a), a + t1[:, None] * (b - a)], axis=1)
    seg = seg[np.abs(seg[:, 0, 1] - seg[:, 1, 1]) > 10]
    return seg + rng.normal(0.0, SEGMENT_NOISE_PX, seg.shape)


def _street_block(tmp_path, seed: int):
    """20 level cameras 1.6 m up walking x = -19..19 along y = 0, looking
    across at the terraces 25 deg forward and 12 deg up; per image the
    joins' full-height edges and four window columns per house at three
    floors (short edges), as stage 1 would give them. The model: the true
    block moved by a similarity about the vertical."""
    rng = np.random.default_rng(seed)
    joins = _terraces(rng)
    path = tmp_path / "street.geojson"
    _write_map(path, joins, rng)
    cad = load_cadastre(path, origin=(X0, Y0))
    windows = np.concatenate(
        [
            a + rng.uniform(1.0, b - a - 1.0, 4)
            for a, b in zip(joins[:-1], joins[1:], strict=True)
        ]
    )
    d = np.array([np.sin(np.radians(25)), np.cos(np.radians(25)), 0.0])
    d[2] = np.tan(np.radians(12))
    R = _look(d)
    cam = pycolmap.Camera(model="PINHOLE", width=W, height=H,
                          params=[F, F, W / 2, H / 2])  # fmt: skip
    cam.camera_id = 1
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    images, centres = [], []
    for k, x in enumerate(np.arange(-19.0, 20.0, 2.0)):
        c = np.array([x, rng.normal(0, 0.1), 1.6])
        centres.append(c)
        im = pycolmap.Image(name=f"s{k:02d}.jpg", camera_id=1, image_id=k + 1)
        im.points2D = pycolmap.Point2DList()
        rec.add_image_with_trivial_frame(
            im, pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
        )
        segs = [_segments(R, c, joins, 0.3, 14.0, rng)]
        for z in (2.0, 5.0, 8.0):
            segs.append(_segments(R, c, windows, z, z + 1.5, rng))
        seg = np.concatenate(segs)
        down = R @ np.array([0.0, 0.0, -1.0])
        images.append(
            ImageVertical(
                k + 1,
                im.name,
                "ok",
                down,
                None,
                0.01,
                segments=seg,
                K=cam.calibration_matrix(),
                segments_free=seg,
            )  # fmt: skip
        )
    # the model: scale 0.37, turned 70 deg about the vertical, moved
    s_m, th_m, t_m = 0.37, np.radians(70.0), np.array([3.0, -2.0, 0.4])
    rec.transform(pycolmap.Sim3d(s_m, pycolmap.Rotation3d(rotation_z(th_m)), t_m))
    for im in images:
        im.down_model = np.array([0.0, 0.0, -1.0])
    vertical = ModelVertical(np.array([0.0, 0.0, -1.0]), 0.01, images, "terrestrial")
    return rec, vertical, cad, np.array(centres), R, rng


def test_the_street_block_is_placed_from_its_segments(tmp_path):
    """The rough priors (3 m and a 1.4 m bias, 4 deg) leave the block over a
    metre off; the block
    placement finds the similarity within what the map's noise allows (0.05
    m on ~10 joins in view: centres within 0.1 m median, 0.2 m max, i.e. 2
    and 4 sd of one join)."""
    rec, vertical, cad, true_c, R, rng = _street_block(tmp_path, seed=3)
    ids = sorted(rec.reg_image_ids())
    model_c = np.array([rec.images[i].projection_center() for i in ids])
    noise = rng.normal(0, PRIOR_POS_M, (len(ids), 2)) + PRIOR_BIAS_M
    prior_c = true_c + np.c_[noise, np.zeros(len(ids))]
    model_R = np.array([rec.images[i].cam_from_world().rotation.matrix() for i in ids])
    prior_R = np.array(
        [R @ rotation_z(np.radians(rng.normal(0, PRIOR_HEADING_DEG))) for _ in ids]
    )
    start = similarity_upright(model_c, prior_c, np.full(len(ids), 5.0),
                               np.full(len(ids), 5.0))  # fmt: skip
    start_err = np.linalg.norm(start.apply(model_c)[:, :2] - true_c[:, :2], axis=1)
    sim, _, _, pairs, per_image = lines_placement(
        rec, vertical, cad, start, model_c, prior_c, model_R, prior_R,
        GeoregisterOptions(),
    )  # fmt: skip
    err = np.linalg.norm(sim.apply(model_c)[:, :2] - true_c[:, :2], axis=1)
    assert np.median(err) < 2 * MAP_NOISE_M, err
    assert err.max() < 4 * MAP_NOISE_M, err
    assert start_err.min() > 1.0  # the priors alone
    # the pairs are the joins' long edges, several per image
    assert len(per_image) >= 15 and len(pairs) >= 40


def test_heading_prior_from_rotations():
    rng = np.random.default_rng(1)
    R_model = np.array([rotation_z(a) for a in rng.uniform(-3, 3, 50)])
    theta = np.radians(33.0)
    noise = np.radians(rng.normal(0, 5.0, 50))
    # R_model = R_prior R_z(theta) with the prior's heading noisy
    R_prior = np.array(
        [Rm @ rotation_z(-theta - e) for Rm, e in zip(R_model, noise, strict=True)]
    )
    th, sd = heading_from_rotations(R_model, R_prior)
    assert abs(np.degrees(th) - 33.0) < 4 * np.degrees(sd)
    assert 0.3 < np.degrees(sd) < 1.5  # 5 deg / sqrt(50) = 0.7


def test_prior_heading_combined_and_widened_when_they_disagree():
    rng = np.random.default_rng(2)
    model = np.c_[np.linspace(-30, 30, 30), rng.normal(0, 0.2, 30)]
    truth = 2.0 * model @ rotation_z(0.5)[:2, :2].T + [10.0, 5.0]
    prior = truth + rng.normal(0, 3.0, truth.shape)
    alone = prior_similarity(model, prior, 1.0)
    agree = prior_similarity(model, prior, 1.0, (0.5, np.radians(0.5)))
    apart = prior_similarity(model, prior, 1.0, (0.5 + np.radians(20), 0.01))
    assert agree.sd_theta < alone.sd_theta
    assert abs(agree.theta - 0.5) < abs(alone.theta - 0.5) + 1e-3
    assert apart.sd_theta > np.radians(5)  # 20 deg apart: the window widens


@pytest.mark.parametrize(
    ("kind", "asked", "method"),
    [
        ("terrestrial", "auto", "block"),
        ("oblique", "auto", "per_image"),
        ("oblique", "block", "block"),
        ("terrestrial", "per_image", "per_image"),
    ],
)
def test_the_method_follows_the_camera_kind(kind, asked, method):
    vertical = ModelVertical(np.array([0.0, 0.0, -1.0]), 0.1, [], kind)
    assert _method(vertical, GeoregisterOptions(automatic_method=asked)) == method


def test_no_corner_in_sight_is_one_clear_error(tmp_path):
    """Priors 300 m off the street (no mapped corner where they put the
    cameras): an InputError (exit 2), not a guess."""
    rec, vertical, cad, true_c, R, rng = _street_block(tmp_path, seed=4)
    ids = sorted(rec.reg_image_ids())
    model_c = np.array([rec.images[i].projection_center() for i in ids])
    prior_c = true_c + np.array([300.0, 300.0, 0.0])
    model_R = np.array([rec.images[i].cam_from_world().rotation.matrix() for i in ids])
    prior_R = np.array([R for _ in ids])
    start = similarity_upright(model_c, prior_c, np.full(len(ids), 5.0),
                               np.full(len(ids), 5.0))  # fmt: skip
    with pytest.raises(InputError, match="level cameras"):
        lines_placement(
            rec, vertical, cad, start, model_c, prior_c, model_R, prior_R,
            GeoregisterOptions(),
        )  # fmt: skip
