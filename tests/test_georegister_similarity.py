"""The similarity and the vertical of georegister (issue 27), against exact truth."""

from __future__ import annotations

import numpy as np
import pytest

from obliq_colmap.errors import InputError
from obliq_colmap.geometry import rotation_aligning
from obliq_colmap.georegister.similarity import similarity_7dof, similarity_upright
from obliq_colmap.georegister.vertical import robust_mean_direction


def _truth(rng, n):
    model = rng.uniform(-50, 50, (n, 3))
    s, th, t = 2.5, np.radians(37.0), np.array([5e2, -3e2, 40.0])
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    return model, s * model @ R.T + t, (s, R, t)


@pytest.mark.parametrize("n", [2, 3, 6])
def test_upright_similarity_is_exact_without_noise(n):
    model, target, (s, R, t) = _truth(np.random.default_rng(n), n)
    sim = similarity_upright(model, target, np.full(n, 0.1), np.full(n, 0.2))
    assert sim.scale == pytest.approx(s, rel=1e-12)
    assert np.allclose(sim.rotation, R, atol=1e-12)
    assert np.allclose(sim.translation, t, atol=1e-9)
    assert sim.inliers.all()


def test_upright_similarity_with_noise_and_one_gross_outlier():
    rng = np.random.default_rng(3)
    model, target, (s, R, t) = _truth(rng, 6)
    sigma = 0.05
    target = target + rng.normal(0, sigma, target.shape)
    target[4, :2] += [8.0, -5.0]  # a mis-identified point
    sim = similarity_upright(model, target, np.full(6, sigma), np.full(6, sigma))
    assert not sim.inliers[4] and sim.inliers.sum() == 5
    # 5 points ~100 m apart with 5 cm noise: scale to ~1e-3, position ~5 cm
    assert sim.scale == pytest.approx(s, rel=2e-3)
    assert np.abs(sim.apply(model[:4]) - target[:4]).max() < 5 * sigma


def test_2d_points_give_horizontal_rows_only():
    model, target, (s, R, t) = _truth(np.random.default_rng(5), 3)
    target[1, 2] = np.nan
    target[2, 2] = np.nan
    sim = similarity_upright(model, target, np.full(3, 0.1), np.full(3, 0.2))
    assert np.allclose(sim.translation, t, atol=1e-9)
    target[0, 2] = np.nan
    with pytest.raises(InputError, match="height"):
        similarity_upright(model, target, np.full(3, 0.1), np.full(3, 0.2))


def test_7dof_umeyama_is_exact():
    rng = np.random.default_rng(7)
    model = rng.uniform(-10, 10, (5, 3))
    R = rotation_aligning(np.array([0.0, 0.3, 1.0]), np.array([1.0, 0.0, 0.2]))
    target = 0.7 * model @ R.T + [1.0, 2.0, 3.0]
    sim = similarity_7dof(model, target)
    assert sim.scale == pytest.approx(0.7, rel=1e-12)
    assert np.allclose(sim.rotation, R, atol=1e-12)


def test_robust_mean_direction_ignores_a_wrong_image():
    rng = np.random.default_rng(9)
    down = np.array([0.02, -0.01, -1.0])
    down /= np.linalg.norm(down)
    sd = np.full(9, 0.1)
    d = down + np.radians(0.1) * rng.normal(size=(9, 3))
    d[0] = rotation_aligning(down, [0.2, 0.0, -1.0]) @ down  # 11 deg off: wrong VP
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mean, ang, w, sd_mean = robust_mean_direction(d, sd, 3.0)
    err = np.degrees(np.arccos(np.clip(mean @ down, -1, 1)))
    # 8 good images of 0.1 deg: the mean within ~4 of its own sigmas
    assert err < 4 * 0.1 / np.sqrt(8) * 2
    assert w[0] == 0.0  # beyond the biweight's reach: no weight at all
    assert 0.01 < sd_mean < 0.2
