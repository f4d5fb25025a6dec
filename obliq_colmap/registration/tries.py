"""Steps 3-4 from one coarse peak (one candidate ground height): the fine
pose vote and a short RANSAC (:func:`try_start`), resumed to the full RANSAC
for the winner (:func:`finish_try`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from obliq_colmap.geometry import Camera
from obliq_colmap.registration.hough import HoughGrid, HoughPeak, hough
from obliq_colmap.registration.options import RegistrationOptions, at_image_scale
from obliq_colmap.registration.ransac import (
    Candidates,
    RansacState,
    candidates,
    run_ransac,
)
from obliq_colmap.registration.segments import Segments, pairs_near
from obliq_colmap.registration.view import View

#: Upper bound on the cells of the fine pose vote (step 3); the window is
#: about (2 * 1.5 * coarse / fine)^3 ~ 30 x 13 x 13 cells at the true height.
_FINE_MAX_CELLS = 20_000


@dataclass
class Try:
    """One candidate ground height carried through steps 3 and 4."""

    start: HoughPeak
    grid: HoughGrid
    h0: float
    vis: np.ndarray
    corner_rel: np.ndarray
    depth_m: float
    cand: Candidates
    alpha: float
    c_xy: np.ndarray
    plane: np.ndarray
    count: int
    cost: float
    trials: int
    #: The RANSAC's search centre (alpha, c_xy) and half-widths, and where it
    #: stopped (to resume it).
    center: tuple[float, np.ndarray]
    windows: tuple[float, float]
    state: RansacState


def try_start(
    view: View,
    segs: Segments,
    cadastre,
    camera: Camera,
    start: HoughPeak,
    h0: float,
    coarse: HoughGrid,
    radius: float,
    alpha_half: float,
    c_half: float,
    options: RegistrationOptions,
    rng: np.random.Generator,
) -> Try | None:
    """Steps 3 and 4 from one coarse peak, with the short RANSAC
    (``options.verify_trials``; :func:`finish_try` resumes it); None when
    nothing matches."""
    from obliq_colmap.cadastre import visible_corners

    vis = visible_corners(
        cadastre,
        camera,
        view.pose(start.alpha, start.c_xy),
        ground_height=h0,
        height_range_m=options.height_range_m,
        margin_px=radius,
    )
    if len(vis) < 3:
        return None
    corner_rel = cadastre.corner_xy[vis] - view.c0[:2]
    _, depth0 = view.project(
        np.array([start.alpha]), start.c_xy[None], corner_rel, np.full(len(vis), h0)
    )
    front = depth0[0][depth0[0] > 0]
    if len(front) < 3:
        return None
    depth_m = float(np.median(front))
    options = at_image_scale(options, view.focal, depth_m)
    # 3. Fine pose vote within two coarse cells, pairs near the ground height.
    band_px = (
        2.0 * coarse.d_c * view.focal / depth_m + 2.0 * coarse.d_alpha * view.focal
    )
    ii, jj = pairs_near(
        view,
        segs,
        corner_rel,
        start.alpha,
        start.c_xy,
        band_px,
        ground=h0,
        height_tol_m=options.candidate_height_tolerance_m + 2.0 * coarse.d_c,
    )
    if len(ii) < 3:
        return None
    fine = hough(
        view,
        segs,
        corner_rel,
        ii,
        jj,
        start.alpha,
        1.5 * coarse.d_alpha,
        start.c_xy,
        1.5 * coarse.d_c,
        (options.hough_cell_px,) * 3,
        depth_m,
        # The window is 3 coarse cells wide; at a spurious ground height
        # near the camera the viewing distance, hence the cell in metres,
        # is tiny and the window would need 10^5-10^6 cells: cap it (the
        # cells grow instead; a wrong height fails the RANSAC anyway).
        min(options.hough_max_cells, _FINE_MAX_CELLS),
    ).peak()
    # 4. RANSAC in a small radius around it.
    cand = candidates(
        view,
        segs,
        corner_rel,
        fine.alpha,
        fine.c_xy,
        h0,
        options.ransac_radius_px,
        options.candidate_height_tolerance_m,
    )
    if len(cand.corner) < 3:
        return None
    windows = (
        alpha_half + 4.0 * options.ransac_radius_px / view.focal,
        c_half + 4.0 * options.ransac_radius_px * depth_m / view.focal,
    )
    state = RansacState(rng)
    alpha, c_xy, plane, count, cost, trials = run_ransac(
        view,
        segs,
        corner_rel,
        cand,
        fine.alpha,
        fine.c_xy,
        *windows,
        options,
        state,
        max_trials=options.verify_trials,
    )
    return Try(
        start,
        coarse,
        h0,
        vis,
        corner_rel,
        depth_m,
        cand,
        alpha,
        c_xy,
        plane,
        count,
        cost,
        trials,
        (fine.alpha, fine.c_xy),
        windows,
        state,
    )


def finish_try(view: View, segs: Segments, t: Try, options: RegistrationOptions) -> Try:
    """The full RANSAC of a verified try: its short run resumed, which draws
    and scores the samples a fresh full run with the same seed would (the
    steps before it are deterministic, so they are not recomputed)."""
    options = at_image_scale(options, view.focal, t.depth_m)
    alpha, c_xy, plane, count, cost, trials = run_ransac(
        view, segs, t.corner_rel, t.cand, *t.center, *t.windows, options, t.state
    )
    return replace(
        t, alpha=alpha, c_xy=c_xy, plane=plane, count=count, cost=cost, trials=trials
    )
