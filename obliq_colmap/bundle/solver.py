"""The solve: :func:`solve_bundle`, the robust loss and the Levenberg-Marquardt loop.

Robust loss by IRLS weights ``rho'(r^2)`` (Huber or Cauchy, scale in pixels);
the cost is ``1/2 sum rho(r^2)`` (plus the optional corner-height prior and
the observed camera parameters of :mod:`.priors`: attitude, centres,
principal points, vertical VPs), the same as Ceres' with the same loss.

Algorithm (Levenberg-Marquardt with the heights eliminated):

1. Evaluate residuals and analytic Jacobians, vectorised per camera model.
2. Normal equations in the camera block C (6 per image + refined intrinsics
   per camera: dense for a few hundred unknowns, gathered sparse for large
   blocks, :mod:`.camera_block`) and the height block h, which is DIAGONAL
   because every residual touches at most one height.
3. Marquardt damping ``H + lambda * clip(diag H, 1e-6, 1e32)`` on both blocks.
4. Schur complement ``S = H_CC - E^T D_h^-1 E`` (E: sparse height-camera
   coupling), solve of S with the gauge constraints (below) as a KKT system
   (dense LU, or sparse for large blocks: :mod:`.linear`), back-substitution
   of the heights.
5. Accept the step if the robust cost decreases (gain ratio > 1e-3);
   Nielsen's update of lambda.

Gauge: the map fixes x, y, heading and scale; only the vertical datum is
free (all heights and the camera centres of a group of linked images shift
together). Images are linked when they share a height unknown (union-find
via connected components of the image-height graph). For each component one
hard linear constraint keeps the mean camera-centre height of its images at
its initial value (``gauge="component_mean_camera_height"``). Components are
reported in the summary.

Free corner heights are almost unobservable (the whole vertical edge
projects onto the same line at the true pose), so an optional weak prior
``(h_i - h_i0) / sigma`` keeps them at their initial value unless the data
say otherwise; at the true pose it costs nothing.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from ..geometry import Camera, Pose, rotation_exp
from . import camera_block, covariance
from .blocks import EliminatedBlocks
from .components import Group, component_factors, sandwich_covariance, shared_meat
from .facade_lines import FacadeLineRows
from .loss import robust_loss
from .priors import (
    AttitudePrior,
    CentrePrior,
    PosePrior,
    PrincipalPointPrior,
    VanishingPointObservation,
)
from .problem import BundleOptions, BundleProblem, BundleResult, BundleSummary
from .schur import Schur, damped_step, normal_equations
from .setup import Setup, State, evaluate, sum_and_difference
from .ties import TieRows

__all__ = ["solve_bundle"]

logger = logging.getLogger(__name__)


def solve_bundle(
    problem: BundleProblem, options: BundleOptions | None = None
) -> BundleResult:
    """Refine all extrinsics, intrinsics and heights of eq. 3.

    Parameters
    ----------
    problem : BundleProblem
    options : BundleOptions, optional

    Returns
    -------
    BundleResult
        Refined copies; the problem is not modified.

    Raises
    ------
    ValueError
        If a constrained point is behind its camera at the start.
    """
    options = options or BundleOptions()
    if options.blas_threads is None:
        return _solve(problem, options)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=options.blas_threads, user_api="blas"):
        return _solve(problem, options)


def _solve(problem: BundleProblem, opts: BundleOptions) -> BundleResult:
    t0 = time.perf_counter()
    P = problem
    S = Setup(P, opts)
    free = opts.corner_heights == "free"
    nJ = S.n_facade_heights
    st = State.start(P, S)
    ties = TieRows(P, S, opts) if len(P.tie_image) else None
    lines = FacadeLineRows(P, S, opts, st) if S.facade_lines else None
    # The unknowns eliminated by their 3x3 blocks.
    blocks = [b for b in (ties, lines) if b is not None]
    heights0 = st.heights.copy()
    prior_w = (
        1.0 / opts.corner_height_prior_m**2
        if free and opts.corner_height_prior_m is not None
        else 0.0
    )
    prior_mask = np.zeros(S.n_heights, bool)
    prior_mask[nJ:] = prior_w > 0

    # Observed poses (INS attitude, GNSS centres): 3 rows per active image;
    # the uncalibrated cameras' principal points: 2 rows per camera; stage
    # 1's vertical VPs: 2 rows per observed image.
    vp_obs = VanishingPointObservation.of(P, S, opts)
    pose_priors = [
        p
        for p in (
            AttitudePrior.of(P, S, opts),
            CentrePrior.of(P, S, opts),
            PrincipalPointPrior.of(P, S, opts),
            vp_obs if opts.vp_in_fit else None,
        )
        if p is not None
    ]

    def cost_of(r: np.ndarray, st: State) -> float:
        rho, _ = robust_loss(opts.loss, S.loss_scale, r * r)
        c = 0.5 * float(np.sum(S.weight * rho))
        if prior_w:
            dh = (st.heights - heights0)[prior_mask]
            c += 0.5 * prior_w * float(dh @ dh)
        c += sum(p.cost(st) for p in pose_priors)
        c += sum(b.cost(S, st) for b in blocks)
        return c if np.isfinite(c) else np.inf

    def rmse(r: np.ndarray, st: State) -> tuple[float, float]:
        v, h = r[S.kind == 0], r[S.kind == 1]
        if lines is not None:
            h = lines.evaluate(S, st, jac=False)[0].ravel()
        f = lambda a: float(np.sqrt(np.mean(a * a))) if len(a) else float("nan")  # noqa: E731
        return f(v), f(h)

    r, Jc, Jh = evaluate(S, st, jac=True)
    if not np.all(np.isfinite(r)):
        bad = np.flatnonzero(~np.isfinite(r))
        raise ValueError(
            f"{len(bad)} constrained points are behind their camera (or project to "
            f"infinity) at the start, e.g. in image {P.image_ids[S.img[bad[0]]]}"
        )
    for b, what in ((ties, "tie point"), (lines, "facade line")):
        if b is None:
            continue
        r_b = b.evaluate(S, st, jac=False)[0]
        if not np.all(np.isfinite(r_b)):
            bad = np.flatnonzero(~np.all(np.isfinite(r_b), axis=1))
            raise ValueError(
                f"{len(bad)} {what} observations are behind their camera at"
                f" the start, e.g. in image {P.image_ids[b.img[bad[0]]]}"
            )
    cost = cost_of(r, st)
    initial_cost, initial_rmse = cost, rmse(r, st)

    # Height-only Gauss-Newton steps (cameras fixed): cheap, diagonal.
    for _ in range(opts.height_initialisation_steps):
        if not S.n_heights:
            break
        _, w = robust_loss(opts.loss, S.loss_scale, r * r)
        w = w * S.weight
        Hh = np.bincount(S.hidx[S.has_h], (w * Jh * Jh)[S.has_h], S.n_heights)
        gh = np.bincount(S.hidx[S.has_h], (w * Jh * r)[S.has_h], S.n_heights)
        Hh = Hh + prior_w * prior_mask
        gh = gh + prior_w * prior_mask * (st.heights - heights0)
        trial = st.copy()
        trial.heights = st.heights - gh / np.maximum(Hh, 1e-12)
        r_t, _, _ = evaluate(S, trial, jac=False)
        c_t = cost_of(r_t, trial)
        if not c_t < cost:
            break
        st, cost = trial, c_t
        r, Jc, Jh = evaluate(S, st, jac=True)

    # The same on the facade lines (their 3x3 blocks, cameras fixed).
    for _ in range(opts.height_initialisation_steps if lines is not None else 0):
        scratch = camera_block.empty(S.n_red, S.sparse_camera)
        lines.linearise(S, st, scratch, np.zeros(S.n_red))
        trial = st.copy()
        trial.lines = st.lines + lines.step(np.zeros(S.n_red), 0.0)
        r_t, _, _ = evaluate(S, trial, jac=False)
        c_t = cost_of(r_t, trial)
        if not c_t < cost:
            break
        st, cost = trial, c_t

    it = n_ok = 0
    for _ in range(1 + _REANCHOR_PASSES):
        st, cost, r, it_, n_ok_, termination, converged = _levenberg_marquardt(
            S,
            opts,
            st,
            r,
            Jc,
            Jh,
            cost,
            cost_of,
            pose_priors,
            prior_w,
            prior_mask,
            heights0,
            blocks,
        )
        it, n_ok = it + it_, n_ok + n_ok_
        # The facade lines' end positions were fixed at the start; where the
        # solve moved them (a distorted image of a line is no chord), solve
        # again from where the ends' rays now meet the lines.
        if lines is None or not lines.reanchor(P, S, st):
            break
        r, Jc, Jh = evaluate(S, st, jac=True)
        cost = cost_of(r, st)

    final_rmse = rmse(r, st)
    precision, variance_factor = {}, float("nan")
    components: dict[str, tuple[float, float]] = {}
    pose_cov: dict[int, np.ndarray] = {}
    vp_stats = None
    # The cofactor matrix serves the precision and the VP rows' redundancy
    # numbers and tests (which the rounds read between solves). Any rows
    # will do: a block of tie points and control points alone (georegister
    # without a map) has pose covariances too, though no map point to
    # predict pixels at.
    rows = len(r) + sum(len(b.img) for b in blocks)
    want = (opts.compute_precision or vp_obs is not None) and rows > 0
    if want and S.n_red > opts.precision_max_camera_params:
        logger.info(
            "bundle: no precision for %d camera parameters (more than %d)",
            S.n_red,
            opts.precision_max_camera_params,
        )
    elif want:
        r, groups = _observation_groups(
            S, opts, st, pose_priors, prior_w, prior_mask, heights0, blocks
        )
        cov = covariance.gauge_cofactor(S, sum(g.normal for g in groups))
        if opts.compute_precision:
            precision, variance_factor, components, C = _precision(
                S, st, opts, groups, cov
            )
            if C is not None:
                pose_cov = covariance.pose_covariances(S, C)
        if vp_obs is not None:
            vp_stats = vp_obs.statistics(st, cov)
    r_rows = r
    if len(S.pair_a):  # each row's own residual again (the transform's inverse)
        r_rows = r.copy()
        sum_and_difference(r_rows, S.pair_a, S.pair_b)
    r_problem = np.empty_like(r)
    r_problem[S.order] = r_rows
    r_horizontal = r_problem[S.nv :]
    if lines is not None:
        r_horizontal = lines.observation_residuals(S, st)
    cameras = {}
    for s, cid in enumerate(S.camera_ids):
        c0 = P.cameras[cid]
        cameras[cid] = Camera(c0.model, c0.width, c0.height, st.params[s], c0.camera_id)
    for cid, cam in P.cameras.items():
        cameras.setdefault(
            cid, Camera(cam.model, cam.width, cam.height, cam.params, cam.camera_id)
        )
    poses = {
        iid: Pose.from_center(st.R[k], st.c[k]) for k, iid in enumerate(P.image_ids)
    }
    vp_angle, vp_chi2, vp_omega, vp_red, vp_test = {}, {}, {}, {}, {}
    vp_loo = {}
    if vp_obs is not None:
        e, _ = vp_obs.angles(st)
        ang = np.degrees(np.arcsin(np.clip(np.linalg.norm(e, axis=1), 0.0, 1.0)))
        chi2 = vp_obs.chi2_stated(st)
        for j, k in enumerate(vp_obs.k):
            vp_angle[P.image_ids[k]] = float(ang[j])
            vp_chi2[P.image_ids[k]] = float(chi2[j])
            if vp_stats is not None:
                i, sc = P.image_ids[k], opts.vp_sigma_scale
                vp_omega[i] = float(vp_stats["omega"][j])
                vp_red[i] = float(vp_stats["redundancy"][j])
                vp_test[i] = float(vp_stats["test"][j])
                # in stage 1's stated units (scale 1)
                vp_loo[i] = (
                    vp_stats["loo_residual"][j] * sc,
                    vp_stats["loo_cofactor"][j] * sc * sc,
                )
        logger.info(
            "bundle: %d VP observations (sd x %.2f): angle median %.3f deg, max"
            " %.3f deg",
            len(vp_obs.k),
            opts.vp_sigma_scale,
            float(np.median(ang)),
            float(np.max(ang)),
        )
    if vp_stats is not None:
        # stage 1's stated sd of each VP and the sd at which the rest of the
        # block predicts its direction (deg; the mean over the 2 axes)
        Ce = np.linalg.inv(np.einsum("kji,kjl->kil", vp_obs.L, vp_obs.L))
        sd = np.degrees(np.sqrt(np.trace(Ce, axis1=1, axis2=2) / 2.0))
        sd /= opts.vp_sigma_scale
        A = vp_stats["loo_cofactor"]
        rest = sd * opts.vp_sigma_scale * np.sqrt(np.trace(A, axis1=1, axis2=2) / 2)
        logger.info(
            "bundle: VP sd stated median %.3f deg; the rest of the block predicts"
            " them to %.3f deg (median; per camera %s)",
            float(np.median(sd)),
            float(np.nanmedian(rest)),
            ", ".join(
                f"{S.camera_ids[int(c)]}: {np.nanmedian(rest[vp_obs.slot == c]):.3f}"
                f" / {np.median(sd[vp_obs.slot == c]):.3f}"
                for c in np.unique(vp_obs.slot)
            ),
        )
    tie_r = tie_scaled = np.zeros((0, 2))
    if ties is not None:
        white = np.empty((len(ties.img), 2))
        white[ties.order] = ties.evaluate(S, st, jac=False)[0]
        tie_r = white if P.tie_sd is None else white * P.tie_sd[:, None]
        n = np.bincount(P.tie_point, minlength=len(P.tie_xyz))[P.tie_point]
        tie_scaled = white * np.sqrt(2 * n / np.maximum(2 * n - 3, 1))[:, None]
        e = np.linalg.norm(tie_r, axis=1)
        logger.info(
            "bundle: %d tie points, %d observations: error median %.3f px, p95 %.3f px",
            ties.n_points,
            len(e),
            float(np.median(e)),
            float(np.percentile(e, 95)),
        )
    summary = BundleSummary(
        initial_cost=initial_cost,
        final_cost=cost,
        initial_rmse_vertical_px=initial_rmse[0],
        final_rmse_vertical_px=final_rmse[0],
        initial_rmse_horizontal_px=initial_rmse[1],
        final_rmse_horizontal_px=final_rmse[1],
        num_iterations=it,
        num_successful_steps=n_ok,
        time_s=time.perf_counter() - t0,
        termination=termination,
        converged=converged,
        components=S.components,
        num_vertical=S.nv,
        num_horizontal=len(P.horizontal_image),
        num_heights=S.n_heights,
        num_camera_params=S.n_red,
    )
    logger.info(summary.brief())
    if S.shift_col >= 0:
        logger.info(
            "bundle: the priors' centres sit %.3f m east, %.3f m north of the map's"
            " frame",
            -st.shift[0],
            -st.shift[1],
        )
    return BundleResult(
        cameras=cameras,
        poses=poses,
        facade_heights=(
            st.lines[:, 0].copy() if lines is not None else st.heights[:nJ].copy()
        ),
        corner_heights=st.heights[nJ:].copy() if free else P.corner_heights.copy(),
        vertical_residuals_px=r_problem[: S.nv],
        vertical_pair_residuals_px=np.column_stack([r[S.pair_a], r[S.pair_b]]),
        horizontal_residuals_px=r_horizontal,
        summary=summary,
        image_precision_px={
            iid: precision.get(k, float("nan")) for k, iid in enumerate(P.image_ids)
        },
        pose_covariance={
            iid: pose_cov[k] for k, iid in enumerate(P.image_ids) if k in pose_cov
        },
        variance_factor=variance_factor,
        variance_components=components,
        prior_offset_m=-st.shift.copy() if S.shift_col >= 0 else None,
        vp_angle_deg=vp_angle,
        vp_chi2=vp_chi2,
        vp_omega=vp_omega,
        vp_redundancy=vp_red,
        vp_test=vp_test,
        vp_loo=vp_loo,
        tie_xyz=st.points.copy(),
        tie_residuals_px=tie_r,
        tie_residuals_scaled_px=tie_scaled,
        facade_offsets=st.lines[:, 1].copy(),
        facade_angles=st.lines[:, 2].copy(),
    )


#: Solves again with the facade lines' end positions moved to where the
#: solved rays meet them (:meth:`FacadeLineRows.reanchor`).
_REANCHOR_PASSES = 2


def _levenberg_marquardt(
    S: Setup,
    opts: BundleOptions,
    st: State,
    r: np.ndarray,
    Jc: np.ndarray,
    Jh: np.ndarray,
    cost: float,
    cost_of: Callable[[np.ndarray, State], float],
    pose_priors: list[PosePrior],
    prior_w: float,
    prior_mask: np.ndarray,
    heights0: np.ndarray,
    blocks: list[EliminatedBlocks] = (),
):
    """The LM iterations from ``st`` (its residuals ``r``, Jacobians ``Jc``,
    ``Jh`` and robust cost ``cost``; ``cost_of(r, st)`` the cost of a trial).

    Returns
    -------
    st, cost, r : the last accepted state, its cost and residuals.
    it, n_ok : iterations and accepted steps.
    termination : str, converged : bool.
    """
    lam, nu = opts.initial_damping, 2.0
    it = n_ok = 0
    termination = "max_iterations"
    converged = False
    need_build = True
    while it < opts.max_iterations:
        it += 1
        if need_build:
            _, w = robust_loss(opts.loss, S.loss_scale, r * r)
            w = w * S.weight
            H_cc, g_c, H_hh, g_h, F = normal_equations(S, Jc, Jh, r, w)
            for p in pose_priors:
                p.add_to(H_cc, g_c, st)
            for b in blocks:
                b.linearise(S, st, H_cc, g_c)
            H_cc = camera_block.finish(H_cc)
            H_hh = H_hh + prior_w * prior_mask
            g_h = g_h + prior_w * prior_mask * (st.heights - heights0)
            schur = Schur(S.coupling, H_hh, g_h, F)
            need_build = False
        dc, dh, dp, D_c, D_h = damped_step(
            S, H_cc, g_c, H_hh, g_h, F, lam, schur, blocks
        )
        predicted = 0.5 * (
            lam * (dc @ (D_c * dc) + dh @ (D_h * dh)) - (g_c @ dc + g_h @ dh)
        )
        predicted += sum(b.predicted(d, lam) for b, d in zip(blocks, dp, strict=True))
        trial = _apply(S, st, dc, dh, blocks, dp)
        r_t, _, _ = evaluate(S, trial, jac=False)
        c_t = cost_of(r_t, trial)
        x_norm = np.sqrt(
            np.sum(st.c[S.active_images] ** 2)
            + sum(float(p @ p) for p in st.params)
            + float(st.heights @ st.heights)
            + sum(float(np.sum(b.unknowns(st) ** 2)) for b in blocks)
        )
        step_norm = np.sqrt(dc @ dc + dh @ dh + sum(float(np.sum(d * d)) for d in dp))
        small_step = step_norm <= opts.parameter_tolerance * (
            x_norm + opts.parameter_tolerance
        )
        logger.debug(
            "  try lam %.3g pred %.6g cost %.9g trial %.9g", lam, predicted, cost, c_t
        )
        if predicted <= max(opts.function_tolerance * cost, 1e-30 * len(r)):
            termination, converged = "function_tolerance (predicted decrease)", True
            break
        rho = (cost - c_t) / predicted if np.isfinite(c_t) else -np.inf
        if rho > 1e-3:
            decrease = cost - c_t
            st, cost, r = trial, c_t, r_t
            n_ok += 1
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            lam = max(lam, 1e-16)
            nu = 2.0
            logger.debug("it %d cost %.9g lambda %.2g", it, cost, lam)
            if decrease <= opts.function_tolerance * (cost + decrease):
                termination, converged = "function_tolerance", True
                break
            if small_step:
                termination, converged = "parameter_tolerance", True
                break
            r, Jc, Jh = evaluate(S, st, jac=True)
            need_build = True
        else:
            if small_step:
                termination, converged = "parameter_tolerance", True
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                termination = "no further decrease (damping > 1e16)"
                break

    return st, cost, r, it, n_ok, termination, converged


def _observation_groups(
    S: Setup,
    opts: BundleOptions,
    st: State,
    pose_priors: list[PosePrior],
    prior_w: float,
    prior_mask: np.ndarray,
    heights0: np.ndarray,
    blocks: list[EliminatedBlocks] = (),
) -> tuple[np.ndarray, list[Group]]:
    """The residuals ``r`` (N,) at ``st`` and the observation groups
    (:class:`~.components.Group`): each with its normal matrix on the camera
    block (its own unknowns eliminated: heights and anchor offsets, tie
    points, facade lines), its weighted sum of squares and rows."""
    n = S.n_red
    r, Jc, Jh = evaluate(S, st, jac=True)
    _, w = robust_loss(opts.loss, S.loss_scale, r * r)
    w = w * S.weight
    offset_w = 1.0 / opts.horizontal_offset_sigma_m**2
    difference = np.zeros(len(r), bool)
    difference[S.pair_b] = True
    if np.any(S.has_h & (S.kind == 0)):
        # free corner heights: both kinds observe them, one group
        masks = {"map rows": np.ones(len(r), bool)}
    else:
        masks = {
            "map corners": (S.kind == 0) & ~difference,
            "segment directions": difference,
            "facade rows": S.kind == 1,
        }
    groups = []
    for name, m in masks.items():
        if not m.any():
            continue
        wm = np.where(m, w, 0.0)
        H = camera_block.finish(normal_equations(S, Jc, Jh, r, wm)[0])
        heights = m & S.has_h
        with_prior = prior_w * prior_mask if heights.any() else np.zeros(S.n_heights)
        normal = covariance.eliminate_heights(
            S, camera_block.to_dense(H)[:n, :n], Jc, Jh, wm, with_prior, offset_w
        )
        private = covariance.private_share(S, Jc, Jh, wm, with_prior, offset_w)
        wss, rows = float(np.sum(wm * r * r)), int(m.sum())
        shared = None
        if name == "map corners" and opts.map_corner_sigma_m is not None:
            shared = covariance.corner_offset_meat(S, Jc, wm, opts.map_corner_sigma_m)
        dh = np.where(prior_mask, st.heights - heights0, 0.0) if prior_w else 0.0
        if heights.any() and prior_w:  # the corner heights' prior rows
            wss += prior_w * float(np.sum(dh * dh))
            rows += int(prior_mask.sum())
        # the squares at the optimum of the heights and offsets counted in
        # ``private`` (the solve holds the offsets)
        wss -= covariance.private_refit(S, Jc, Jh, r, wm, with_prior, dh, offset_w)
        groups.append(Group(name, normal, wss, rows, private, shared))
    for p in pose_priors:
        normal = _dense_terms(S, lambda H, p=p: p.add_to(H, np.zeros(n + 1), st))
        groups.append(
            Group(p.group_name, normal, p.weighted_sum_of_squares(st), p.n_rows)
        )
    for b in blocks:
        normal = _dense_terms(S, lambda H, b=b: b.linearise(S, st, H, np.zeros(n + 1)))
        normal = normal - camera_block.to_dense(b.reduced)
        private = 3 * b.n_points
        groups.append(
            Group(
                b.group_name,
                normal,
                b.weighted_sum_of_squares(S, st),
                b.redundancy + private,
                private,
            )
        )
    return r, groups


def _dense_terms(
    S: Setup, fill: Callable[[camera_block.CameraBlock], None]
) -> np.ndarray:
    """(n_red, n_red) the camera-block terms ``fill`` adds to an empty block."""
    H = camera_block.empty(S.n_red, S.sparse_camera)
    fill(H)
    return camera_block.to_dense(camera_block.finish(H))[: S.n_red, : S.n_red]


def _precision(
    S: Setup,
    st: State,
    opts: BundleOptions,
    groups: list[Group],
    cofactor: np.ndarray,
) -> tuple[dict[int, float], float, dict[str, tuple[float, float]], np.ndarray | None]:
    """Each active image's a-posteriori precision (px) at ``st`` from the
    observation groups and the cofactor matrix of their sum.

    Returns
    -------
    precision : dict image slot -> px (empty where the redundancy is not
        positive).
    variance_factor : float, the pooled one (all groups' ``r^T W r`` over the
        redundancy), NaN where the redundancy is not positive.
    components : dict group name -> (variance component, redundancy), where
        the covariance uses them (``BundleOptions.variance_components``).
    covariance : (n_red, n_red) the camera block's, or None.
    """
    redundancy = sum(g.redundancy(cofactor) for g in groups)
    if not redundancy > 0 or not np.all(np.isfinite(cofactor)):
        return {}, float("nan"), {}, None
    variance_factor = sum(g.wss for g in groups) / redundancy
    if opts.variance_components:
        components = component_factors(groups, cofactor, opts.component_min_redundancy)
        C = sandwich_covariance(groups, cofactor, components)
        logger.info(
            "bundle: variance components (factor, redundancy): %s",
            ", ".join(f"{k} {v:.3g} ({r:.0f})" for k, (v, r) in components.items()),
        )
    else:
        components = {}
        C = variance_factor * cofactor
        shared = shared_meat(groups)
        if shared is not None:
            C = C + cofactor @ shared @ cofactor
    return covariance.image_precision(S, st, C), variance_factor, components, C


def _apply(
    S: Setup,
    st: State,
    dc: np.ndarray,
    dh: np.ndarray,
    blocks: list[EliminatedBlocks] = (),
    dp: list[np.ndarray] = (),
) -> State:
    """New state: R <- Exp(omega) R, c <- c + dc, params += d, heights += dh,
    each block's unknowns (tie points, facade lines) += its step in dp."""
    new = st.copy()
    k = S.active_images
    pose = dc[S.pose_col[k][:, None] + np.arange(6)]  # (K_active, 6)
    new.R[k] = rotation_exp(pose[:, :3]) @ st.R[k]
    new.c[k] = st.c[k] + pose[:, 3:]
    for s, basis in enumerate(S.refined):
        if basis.shape[1]:
            new.params[s] += basis @ dc[S.intr_col[s] + np.arange(basis.shape[1])]
    new.heights = st.heights + dh
    for b, d in zip(blocks, dp, strict=True):
        setattr(new, b.state_attr, b.unknowns(st) + d)
    if S.shift_col >= 0:
        new.shift = st.shift + dc[S.shift_col : S.shift_col + 2]
    return new
