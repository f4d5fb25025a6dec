"""The two vertical rows of one segment as their sum and difference
(``BundleOptions.vertical_direction_sigma_px``): the pairing, the transform,
and what it buys when the map's noise moves both ends of a segment alike."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from obliq_colmap.bundle import BundleOptions, solve_bundle
from obliq_colmap.bundle.problem import vertical_row_pairs
from obliq_colmap.bundle.setup import Setup, State, evaluate, sum_and_difference
from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem

#: Height (m) of each segment's upper end above its corner's ground.
UPPER_END_M = 6.0


def paired_problem(sb):
    """The synthetic problem with each vertical row as a segment's two ends:
    its corner's vertical at the true ground height and ``UPPER_END_M``
    above, on the same image line, heights fixed (as ``register`` builds
    them). The synthetic noise shifts each whole line across: both ends
    alike, as the map's vertex noise does."""
    P = sb.problem
    c = P.vertical_corner
    z = np.column_stack([sb.corner_heights[c], sb.corner_heights[c] + UPPER_END_M])
    return dataclasses.replace(
        P,
        corner_xy=np.repeat(P.corner_xy[c], 2, axis=0),
        corner_heights=z.ravel(),
        vertical_image=np.repeat(P.vertical_image, 2),
        vertical_corner=np.arange(2 * len(c)),
        vertical_line=np.repeat(P.vertical_line, 2, axis=0),
    )


def median_rotation_error_deg(sb, result) -> float:
    return float(
        np.median(
            [
                np.degrees(
                    np.linalg.norm(
                        Rotation.from_matrix(
                            result.poses[i].rotation @ p.rotation.T
                        ).as_rotvec()
                    )
                )
                for i, p in sb.poses.items()
            ]
        )
    )


@pytest.fixture(scope="module")
def noisy():
    sb = make_synthetic_problem(seed=3, noise_px=0.8)
    return sb, paired_problem(sb)


def test_pairs_are_consecutive_rows_of_one_line_and_corner(noisy):
    _, P = noisy
    rows = 7
    img = np.array([0, 0, 0, 0, 1, 1, 1])
    line = np.tile([1.0, 0.0, -5.0], (rows, 1))
    line[6] = [1.0, 0.0, -6.0]  # another segment
    xy = np.zeros((rows, 2))
    xy[5:] = 3.0
    Q = dataclasses.replace(
        P,
        corner_xy=xy,
        corner_heights=np.zeros(rows),
        vertical_image=img,
        vertical_corner=np.arange(rows),
        vertical_line=line,
    )
    a, b = vertical_row_pairs(Q)
    # rows 0-3: two segments' ends (0, 1), (2, 3); row 4 another corner
    # position than 5; rows 5 and 6 other lines: no pairs
    assert a.tolist() == [0, 2]
    assert b.tolist() == [1, 3]
    a, b = vertical_row_pairs(P)
    assert len(a) == len(P.vertical_image) // 2


def test_evaluation_is_the_rows_turned_pairwise(noisy):
    _, P = noisy
    base = BundleOptions(corner_heights="fixed")
    S0 = Setup(P, base)
    S1 = Setup(P, dataclasses.replace(base, vertical_direction_sigma_px=0.1))
    assert np.array_equal(S0.order, S1.order)
    assert len(S1.pair_a) == len(P.vertical_image) // 2
    st = State.start(P, S0)
    r0, J0, h0 = evaluate(S0, st, jac=True)
    r0, J0, h0 = r0.copy(), J0.copy(), h0.copy()
    r1, J1, h1 = evaluate(S1, st, jac=True)
    for x in (r0, h0):
        sum_and_difference(x, S1.pair_a, S1.pair_b)
    sum_and_difference(J0.T, S1.pair_a, S1.pair_b)
    np.testing.assert_allclose(r1, r0, atol=1e-12)
    np.testing.assert_allclose(J1, J0, atol=1e-12)
    np.testing.assert_allclose(h1, h0, atol=1e-12)
    # the difference rows carry the direction's sd, the sum rows the map's
    assert np.all(S1.weight[S1.pair_b] == 1.0 / 0.1**2)
    assert np.all(S1.weight[S1.pair_a] == S0.weight[S1.pair_a])


def test_equal_sds_are_the_unpaired_model(noisy):
    """An orthogonal transform of rows with one sd changes nothing (without
    a robust loss, which acts per row)."""
    _, P = noisy
    base = BundleOptions(corner_heights="fixed", loss="none", compute_precision=False)
    r0 = solve_bundle(P, base)
    r1 = solve_bundle(P, dataclasses.replace(base, vertical_direction_sigma_px=1.0))
    for i in r0.poses:
        np.testing.assert_allclose(
            r1.poses[i].rotation, r0.poses[i].rotation, atol=1e-9
        )
        np.testing.assert_allclose(r1.poses[i].center, r0.poses[i].center, atol=1e-6)
    # the result reports each row's own residual, not the pair's
    np.testing.assert_allclose(
        r1.vertical_residuals_px, r0.vertical_residuals_px, atol=1e-7
    )
    s, d = r1.vertical_pair_residuals_px.T
    a, b = vertical_row_pairs(P)
    np.testing.assert_allclose(
        s,
        (r1.vertical_residuals_px[a] + r1.vertical_residuals_px[b]) / np.sqrt(2),
        atol=1e-9,
    )
    np.testing.assert_allclose(
        d,
        (r1.vertical_residuals_px[a] - r1.vertical_residuals_px[b]) / np.sqrt(2),
        atol=1e-9,
    )


def test_direction_rows_hold_the_rotation_under_common_mode_noise(noisy):
    """Lines shifted across by 0.8 px (both ends alike): their direction is
    exact, and weighting the ends' difference by its own (small) sd halves
    the rotation error of the rows weighted alike."""
    sb, P = noisy
    base = BundleOptions(
        corner_heights="fixed", vertical_sigma_px=0.8, compute_precision=False
    )
    alike = median_rotation_error_deg(sb, solve_bundle(P, base))
    apart = median_rotation_error_deg(
        sb, solve_bundle(P, dataclasses.replace(base, vertical_direction_sigma_px=0.05))
    )
    assert apart < 0.6 * alike, (apart, alike)
