"""Observed tie point coordinates (control points) and VP rows without a
robust loss in the bundle: what georegister's block adjustment needs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from obliq_colmap.bundle import BundleOptions
from obliq_colmap.bundle.camera_block import empty
from obliq_colmap.bundle.priors import VanishingPointObservation
from obliq_colmap.bundle.setup import Setup, State
from obliq_colmap.bundle.ties import TieRows, coordinate_prior
from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem


def _central(f, x: np.ndarray, h: float) -> np.ndarray:
    """(out_shape + x.shape) central differences of f at x."""
    out = []
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = h
        e = e.reshape(x.shape)
        out.append((f(x + e) - f(x - e)) / (2 * h))
    return np.moveaxis(np.array(out), 0, -1).reshape(np.shape(f(x)) + x.shape)


def test_coordinate_prior_gradient_and_normal_block_match_finite_differences():
    rng = np.random.default_rng(0)
    xyz, given = rng.normal(0, 5, (4, 3)), rng.normal(0, 5, (4, 3))
    weight = 1.0 / rng.uniform(0.05, 0.3, (4, 3)) ** 2
    weight[1, 2] = weight[3] = 0.0  # a 2D point's height; a free point
    H, g, cost = coordinate_prior(xyz, given, weight)
    assert cost == pytest.approx(0.5 * np.sum(weight * (xyz - given) ** 2))
    numeric_g = _central(lambda x: coordinate_prior(x, given, weight)[2], xyz, 1e-5)
    np.testing.assert_allclose(g, numeric_g, rtol=1e-7, atol=1e-6)
    # H is the derivative of g, point by point (no point couples another)
    numeric_H = _central(lambda x: coordinate_prior(x, given, weight)[1], xyz, 1e-5)
    for t in range(4):
        np.testing.assert_allclose(H[t], numeric_H[t, :, t, :], atol=1e-6)
    assert not np.any(g[3]) and not np.any(H[3])


def _with_tie_prior(sigma_z: float = 0.2):
    syn = make_synthetic_problem(seed=3, tie_points=60)
    P = syn.problem
    T = len(P.tie_xyz)
    given = syn.tie_xyz + 0.3  # 0.3 m off the truth on each axis
    sigma = np.full((T, 3), np.inf)
    sigma[:3] = [0.1, 0.1, sigma_z]
    P = dataclasses.replace(P, tie_prior_xyz=given, tie_prior_sigma=sigma)
    return P, given


def test_tie_points_blocks_hold_their_observed_coordinates():
    """The tie blocks' gradient g_p (reprojection rows and the prior) is the
    derivative of their cost in each observed point's coordinates."""
    P, given = _with_tie_prior(sigma_z=np.inf)  # the third axis free
    opts = BundleOptions()
    S = Setup(P, opts)
    st = State.start(P, S)
    ties = TieRows(P, S, opts)
    assert ties.n_prior_rows == 6
    ties.linearise(S, st, empty(S.n_red, False), np.zeros(S.n_red))
    for t in (0, 2, 5):  # two observed points and a free one

        def cost(x, t=t):
            trial = st.copy()
            trial.points[t] = x
            return ties.cost(S, trial)

        numeric = _central(cost, st.points[t].copy(), 1e-6)
        np.testing.assert_allclose(ties.g_p[t], numeric, rtol=1e-5, atol=1e-6)
    prior = ties.prior(st)
    assert prior[1][0, 2] == 0.0 and prior[1][0, 0] != 0.0


def test_tie_prior_input_is_checked():
    P, given = _with_tie_prior()
    with pytest.raises(ValueError, match="go together"):
        dataclasses.replace(P, tie_prior_sigma=None)
    with pytest.raises(ValueError, match="> 0"):
        dataclasses.replace(P, tie_prior_sigma=np.zeros_like(given))
    bad = given.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        dataclasses.replace(P, tie_prior_xyz=bad)
    # a free axis may hold NaN (a 2D control point's unknown height)
    ok = given.copy()
    ok[5, 2] = np.nan
    dataclasses.replace(P, tie_prior_xyz=ok)


def test_vp_rows_without_a_robust_loss_are_plain_least_squares():
    """``vp_loss_scale=inf``: cost 1/2 |z|^2 and J^T z its gradient."""
    from scipy.spatial.transform import Rotation

    syn = make_synthetic_problem(seed=4, buildings=(3, 3), stations=(2, 1))
    vps, covs = {}, {}
    for i in syn.problem.image_ids:
        K = syn.cameras[syn.problem.image_camera[i]].K
        u = K @ syn.poses[i].rotation @ [0.0, 0.0, -1.0]
        vps[i] = u / np.linalg.norm(u)
        covs[i] = np.diag([1e-8, 1e-8, 1e-8])
    P = dataclasses.replace(syn.problem, vertical_vps=vps, vertical_vp_covariances=covs)
    opts = BundleOptions(vp_loss_scale=np.inf)
    S = Setup(P, opts)
    st = State.start(P, S)
    obs = VanishingPointObservation.of(P, S, opts)
    z = obs.errors(st)
    assert np.abs(z).max() > 10.0  # far out, where a Cauchy loss would flatten
    assert obs.cost(st) == pytest.approx(0.5 * np.sum(z * z))
    g = np.zeros(S.n_red)
    obs.add_to(np.zeros((S.n_red, S.n_red)), g, st)
    k = int(obs.k[0])
    for c in range(3):

        def cost(w, c=c):
            trial = st.copy()
            omega = np.zeros(3)
            omega[c] = w[0]
            trial.R[k] = Rotation.from_rotvec(omega).as_matrix() @ st.R[k]
            return obs.cost(trial)

        numeric = _central(cost, np.zeros(1), 1e-7)[0]
        np.testing.assert_allclose(g[S.pose_col[k] + c], numeric, rtol=1e-5)
