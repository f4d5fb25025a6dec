"""The facade tracks as 3D horizontal lines in the bundle
(``BundleOptions.facade_lines``): Jacobians, exact recovery, the redundancy."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from obliq_colmap.bundle import BundleOptions, solve_bundle
from obliq_colmap.bundle.facade_lines import FacadeLineRows
from obliq_colmap.bundle.setup import Setup, State
from obliq_colmap.geometry import rotation_exp
from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem

LINES = BundleOptions(facade_lines=True, refine_extra_params=True)


def _perturbed_lines(st: State, seed: int = 0) -> None:
    """Offsets of ~0.5 m and angles of ~3 deg on the start lines (in place)."""
    rng = np.random.default_rng(seed)
    st.lines[:, 1] = rng.normal(0.0, 0.5, len(st.lines))
    st.lines[:, 2] = rng.normal(0.0, np.radians(3.0), len(st.lines))


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "SIMPLE_RADIAL", "OPENCV"])
def test_facade_line_jacobians_match_finite_differences(model):
    syn = make_synthetic_problem(
        seed=5, buildings=(3, 3), stations=(2, 2), models=(model,) * 4
    )
    P = syn.problem
    S = Setup(P, LINES)
    st = State.start(P, S)
    _perturbed_lines(st)
    rows = FacadeLineRows(P, S, LINES, st)
    _, Jc, Jp = rows.evaluate(S, st, jac=True)

    def residuals(state: State) -> np.ndarray:
        return rows.evaluate(S, state, jac=False)[0]

    eps = 1e-6
    for a in range(3):  # height, offset, angle
        up, down = st.copy(), st.copy()
        up.lines[:, a] += eps
        down.lines[:, a] -= eps
        num = (residuals(up) - residuals(down)) / (2 * eps)
        np.testing.assert_allclose(Jp[:, :, a], num, rtol=0, atol=1e-5)
    for col in range(S.L):  # every image's column `col` moved at once
        up, down = st.copy(), st.copy()
        for state, sign in ((up, eps), (down, -eps)):
            if col < 3:
                w = np.zeros(3)
                w[col] = sign
                state.R = rotation_exp(np.tile(w, (len(st.R), 1))) @ st.R
            elif col < 6:
                state.c[:, col - 3] += sign
            else:
                for s, basis in enumerate(S.refined):
                    state.params[s] = st.params[s] + sign * basis[:, col - 6]
        num = (residuals(up) - residuals(down)) / (2 * eps)
        scale = np.abs(Jc[:, :, col]).max() + 1.0
        np.testing.assert_allclose(Jc[:, :, col], num, rtol=0, atol=1e-6 * scale)


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE"])
def test_noise_free_facade_lines_recover_the_truth(model):
    """Without distortion the image of a line is a line: the truth is the
    exact optimum, offsets and angles back to 0 from 0.5 m and 3 deg."""
    syn = make_synthetic_problem(
        seed=5, buildings=(5, 5), stations=(2, 2), models=(model,) * 4
    )
    rng = np.random.default_rng(1)
    J = len(syn.problem.facade_heights)
    P = dataclasses.replace(
        syn.problem,
        facade_offsets=rng.normal(0.0, 0.5, J),
        facade_angles=rng.normal(0.0, np.radians(3.0), J),
    )
    opts = BundleOptions(
        facade_lines=True, function_tolerance=1e-14, parameter_tolerance=1e-14
    )
    out = solve_bundle(P, opts)
    assert out.summary.converged, out.summary.termination
    assert out.summary.num_horizontal == len(P.horizontal_image)
    for i in P.image_ids:
        dR = out.poses[i].rotation @ syn.poses[i].rotation.T
        assert np.linalg.norm(rotation_exp(np.zeros((1, 3)))[0] - dR) < 1e-8
        np.testing.assert_allclose(out.poses[i].center, syn.poses[i].center, atol=1e-6)
    np.testing.assert_allclose(out.facade_heights, syn.facade_heights, atol=1e-6)
    np.testing.assert_allclose(out.facade_offsets, 0.0, atol=1e-6)
    np.testing.assert_allclose(out.facade_angles, 0.0, atol=1e-8)
    assert np.abs(out.horizontal_residuals_px).max() < 1e-6


def test_facade_lines_count_their_unknowns_and_priors_in_the_variance_factor():
    """Map rows and segment ends with the same 0.3 px noise and sigma 1 px:
    the variance factor is 0.09 only if each line's 3 unknowns and 2 prior
    rows enter the redundancy (counted as 1 unknown per observation instead,
    as the scalar rows, it comes out 0.15). The ends' noise is across the
    line, the rows measure along the projected vertical (a few % longer)."""
    syn = make_synthetic_problem(
        seed=2, buildings=(5, 5), stations=(2, 2), noise_px=0.3, end_noise_px=0.3
    )
    out = solve_bundle(syn.problem, BundleOptions(facade_lines=True, loss="none"))
    assert out.summary.converged
    assert out.variance_factor == pytest.approx(0.09, rel=0.1)


def test_a_track_seen_once_is_held_by_its_priors():
    """One observation (two rows) of a line's three unknowns: the priors on
    offset and angle define it; the solve stays finite and near the truth."""
    syn = make_synthetic_problem(seed=4, buildings=(3, 3), stations=(2, 2))
    P = syn.problem
    first = np.unique(P.horizontal_height, return_index=True)[1]
    keep = np.ones(len(P.horizontal_image), bool)
    keep[np.setdiff1d(np.flatnonzero(P.horizontal_height == 0), first[:1])] = False
    P = dataclasses.replace(
        P,
        horizontal_image=P.horizontal_image[keep],
        horizontal_height=P.horizontal_height[keep],
        horizontal_anchor_xy=P.horizontal_anchor_xy[keep],
        horizontal_line=P.horizontal_line[keep],
        horizontal_ends=P.horizontal_ends[keep],
    )
    assert np.sum(P.horizontal_height == 0) == 1
    out = solve_bundle(P, BundleOptions(facade_lines=True))
    assert out.summary.converged
    assert abs(out.facade_heights[0] - syn.facade_heights[0]) < 0.05
    assert abs(out.facade_offsets[0]) < 0.05


def test_tracks_that_are_not_level_are_the_scalar_rows():
    """A track near the ground (not level: it may follow the terrain) keeps
    one row per observation at its anchor, offset and angle held: with no
    level track the lines' solve is the scalar model's."""
    syn = make_synthetic_problem(
        seed=3, buildings=(4, 4), stations=(2, 2), noise_px=0.3
    )
    J = len(syn.problem.facade_heights)
    P = dataclasses.replace(syn.problem, facade_level=np.zeros(J, bool))
    scalar = solve_bundle(P, BundleOptions())
    held = solve_bundle(P, BundleOptions(facade_lines=True))
    assert held.summary.converged and scalar.summary.converged
    for i in P.image_ids:
        np.testing.assert_allclose(
            held.poses[i].center, scalar.poses[i].center, atol=1e-5
        )
    # (both solves stop within their tolerances of one optimum: 0.1 mm)
    np.testing.assert_allclose(held.facade_heights, scalar.facade_heights, atol=1e-4)
    np.testing.assert_allclose(
        held.horizontal_residuals_px, scalar.horizontal_residuals_px, atol=1e-4
    )
    assert held.variance_factor == pytest.approx(scalar.variance_factor, rel=1e-4)
    np.testing.assert_allclose(held.facade_offsets, 0.0, atol=1e-6)
