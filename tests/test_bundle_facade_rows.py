"""Each scalar facade row weighted by its segment's line fit where the row
reads it (``BundleOptions.facade_row_extrapolation``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from obliq_colmap.bundle import BundleOptions, solve_bundle
from obliq_colmap.bundle.setup import facade_row_sd
from obliq_colmap.geometry import lines_through
from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem


def _segments(problem, far: np.ndarray, noise_px: float, seed: int):
    """The problem with each row's segment on its exact line: centred on the
    anchor's projection (t in [-1, 1] of the line's 3 m step) or, where
    ``far``, at t in [3, 5] (s / L = 2); each end moved across by Gaussian
    noise, the row's line through the noisy ends."""
    p1, p2 = problem.horizontal_ends[:, 0], problem.horizontal_ends[:, 1]
    step = p2 - p1
    a = np.where(far, 3.0, -1.0)[:, None]
    b = np.where(far, 5.0, 1.0)[:, None]
    ea, eb = p1 + a * step, p1 + b * step
    n = np.column_stack([-step[:, 1], step[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    ea = ea + rng.normal(0.0, noise_px, len(ea))[:, None] * n
    eb = eb + rng.normal(0.0, noise_px, len(eb))[:, None] * n
    return dataclasses.replace(
        problem,
        horizontal_ends=np.stack([ea, eb], axis=1),
        horizontal_line=lines_through(ea, eb),
    )


def test_facade_row_sd_is_the_line_fit_read_at_the_anchor():
    """Centred segments (s = 0) and segments 2 lengths away (s / L = 2):
    their sds are 1 and sqrt(1 + 12 * 4), over the median."""
    syn = make_synthetic_problem(seed=3, buildings=(3, 3), stations=(2, 2))
    far = np.arange(len(syn.problem.horizontal_image)) % 3 == 0
    P = _segments(syn.problem, far, 0.0, 0)
    # read at the true cameras, where the anchors project onto p1 exactly
    P = dataclasses.replace(
        P, poses=syn.poses, cameras=syn.cameras, facade_heights=syn.facade_heights
    )
    sd = facade_row_sd(P)
    np.testing.assert_allclose(sd[~far], sd[~far][0], rtol=1e-6)
    np.testing.assert_allclose(sd[far], np.sqrt(49.0) * sd[~far][0], rtol=1e-6)
    assert np.median(sd) == 1.0


def test_rows_read_far_from_their_segment_lose_weight_and_the_poses_gain():
    """Half the segments 2 lengths away from the anchor, each end with
    0.3 px: their rows' noise is 17x the variance of the centred ones (two
    ends; the fit's factor says 49x). Weighted by it, the centres' RMS
    error (the block's mean shift removed: the datum) over 3 noise draws
    must drop: measured 1.64 m against 2.15 m with equal weights (0.76);
    the bound 0.85 leaves the draws' spread (~1 / sqrt(3 x 16 images))."""
    syn = make_synthetic_problem(seed=3, buildings=(4, 4), stations=(2, 2))
    far = np.arange(len(syn.problem.horizontal_image)) % 2 == 0
    err = {False: [], True: []}
    for seed in range(3):
        P = _segments(syn.problem, far, 0.3, seed)
        for on in (False, True):
            out = solve_bundle(
                P,
                BundleOptions(
                    loss="none",
                    horizontal_sigma_px=0.3,
                    compute_precision=False,
                    facade_row_extrapolation=on,
                ),
            )
            assert out.summary.converged
            dc = np.array(
                [out.poses[i].center - syn.poses[i].center for i in P.image_ids]
            )
            err[on] += list(np.linalg.norm(dc - dc.mean(axis=0), axis=1))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}
    assert rms[True] < 0.85 * rms[False], rms
