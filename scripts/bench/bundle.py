"""Benchmark the global bundle at the paper's scale against Ceres, same process.

Measures the time and the accuracy of :func:`obliq_colmap.bundle.solve_bundle`
on a synthetic bundle problem of the paper's scale, against Ceres (pyceres
on pycolmap's own bundle problem) solving the same constraints, each route
timed as the median of ``--runs`` solves (BLAS pinned to one thread, Ceres
``num_threads=1``); with ``--reference TREE`` instead, that tree's
``solve_bundle`` timed alternately with ours on the same problem.

Run (from the repository root)::

    python scripts/bench/bundle.py [--runs 5] [--ceres-runs 3] [--no-ceres]
    python scripts/bench/bundle.py --reference /tmp/ref

Figures: docs/STATUS.md (stage 3: the global solve's time and its ratio to
Ceres) and docs/journal/stage3-bundle.md.

Data: none (the problem is generated); the Ceres route needs ``pyceres`` and
``pycolmap``; ``--reference`` a source tree (``git archive REV obliq_colmap
| tar -x -C TREE``).

Problem: 36 images (9 stations x 4 oblique heads, one COLMAP camera per head,
SIMPLE_RADIAL 4008 x 2672), ~2.7k map corners and ~15k facade heights,
~48k horizontal + ~11k vertical line constraints, 0.5 px noise; start 0.5 deg /
5 m / 2 % focal off the truth (``make_synthetic_problem``).

Routes:

* ours: :func:`obliq_colmap.bundle.solve_bundle` with default options
  (Huber 2 px, free corner heights with a 5 m prior, f / cx / cy refined);
* ceres: pyceres on pycolmap's own bundle problem (one 7-vector pose block per
  frame with pycolmap's manifold, C++ ``ReprojErrorCost``) with the line
  constraints as point residuals whose covariance is flat along the line
  (L = 1e6 px); the horizontal ones scaled by the start's ``1 / |n . d_hat|``
  (a FROZEN denominator, so its optimum is near, not at, ours); the same Huber
  loss, the corner-height prior as Python costs; no gauge (damping only), so
  its vertical datum is removed before comparing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from obliq_colmap.bundle import BundleOptions, solve_bundle
from obliq_colmap.bundle import residuals as res
from obliq_colmap.geometry import Pose, project
from obliq_colmap.synthetic.bundle_problem import PAPER_FLIGHT, make_synthetic_problem

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from reference import load_reference  # noqa: E402

PAPER = dict(buildings=(26, 26), stations=(3, 3), **PAPER_FLIGHT)


def pose_errors(poses, cameras, syn):
    """Rotation (deg) and centre (m, after the mean vertical offset) errors,
    and the mean pixel deviation of true building points per image."""
    P = syn.problem
    ids = P.image_ids
    dz = np.mean([poses[i].center[2] - syn.poses[i].center[2] for i in ids])
    rot = np.array(
        [
            np.degrees(
                np.linalg.norm(_log(poses[i].rotation @ syn.poses[i].rotation.T))
            )
            for i in ids
        ]
    )
    ctr = np.array(
        [
            np.linalg.norm(poses[i].center - syn.poses[i].center - [0, 0, dz])
            for i in ids
        ]
    )
    pts = np.concatenate(
        [np.column_stack([P.corner_xy, syn.corner_heights + z]) for z in (0.0, 10.0)]
    )
    dev = []
    for i in ids:
        cid = P.image_camera[i]
        a, _ = project(syn.cameras[cid], syn.poses[i], pts)
        b, _ = project(
            cameras[cid],
            Pose.from_center(poses[i].rotation, poses[i].center - [0, 0, dz]),
            pts,
        )
        cam = syn.cameras[cid]
        ok = (
            (a[:, 0] > 0)
            & (a[:, 0] < cam.width)
            & (a[:, 1] > 0)
            & (a[:, 1] < cam.height)
        )
        dev.append(np.linalg.norm(a[ok] - b[ok], axis=1).mean())
    return rot, ctr, np.array(dev)


def _log(R):
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    s, c = np.linalg.norm(w), (np.trace(R) - 1) / 2
    return w if s < 1e-12 else w / s * np.arctan2(s, c)


def ceres_route(P, options: BundleOptions, max_iterations=100):
    """Solve with pyceres on pycolmap's BA problem; returns poses, cameras,
    heights, build time, solve time, summary."""
    import pyceres
    import pycolmap
    import pycolmap.cost_functions  # noqa: F401  (submodule must be imported)

    t0 = time.perf_counter()
    rec = pycolmap.Reconstruction()
    for cam in P.cameras.values():
        rec.add_camera_with_trivial_rig(cam.to_pycolmap())
    config = pycolmap.BundleAdjustmentConfig()
    # One dummy point seen by every image makes pycolmap create each pose
    # block with its manifold; its loss scale (below) makes it weightless.
    X = np.r_[P.corner_xy.mean(0), P.corner_heights.mean()]
    track = pycolmap.Track()
    for iid in P.image_ids:
        pose = P.poses[iid]
        cid = P.image_camera[iid]
        xy = P.cameras[cid].img_from_cam(pose.transform(X[None]))
        im = pycolmap.Image(
            name=f"{iid}.jpg", keypoints=xy, camera_id=cid, image_id=iid
        )
        rec.add_image_with_trivial_frame(im, pose.to_rigid3d())
        track.add_element(iid, 0)
        config.add_image(iid)
    pid = rec.add_point3D(X, track)
    config.add_constant_point(pid)
    ba_opts = pycolmap.BundleAdjustmentOptions()
    ba_opts.refine_focal_length = options.refine_focal_length
    ba_opts.refine_principal_point = options.refine_principal_point
    ba_opts.refine_extra_params = options.refine_extra_params
    ba_opts.min_track_length = 1
    ba_opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba_opts.ceres.loss_function_scale = 1e-12
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba_opts, config, rec)
    problem = adjuster.problem
    pose_block = {i: rec.frame(i).rig_from_world.params for i in P.image_ids}
    cam_block = {c: rec.camera(c).params for c in P.cameras}
    for i in P.image_ids:
        assert problem.has_parameter_block(pose_block[i])
    len(P.facade_heights)
    free = options.corner_heights == "free"
    first = np.unique(P.horizontal_height, return_index=True)[1]  # every j occurs
    pts = [
        np.array([*xy, h])
        for xy, h in zip(P.horizontal_anchor_xy[first], P.facade_heights, strict=True)
    ]
    corner_pts = [
        np.array([*xy, h]) for xy, h in zip(P.corner_xy, P.corner_heights, strict=True)
    ]
    loss = (
        pyceres.HuberLoss(options.loss_scale_px)
        if options.loss == "huber"
        else (
            pyceres.CauchyLoss(options.loss_scale_px)
            if options.loss == "cauchy"
            else None
        )
    )
    L2 = 1e12  # (1e6 px)^2 along the line
    model_ids = {
        c: getattr(pycolmap.CameraModelId, cam.model) for c, cam in P.cameras.items()
    }
    keep = []  # hold Python objects alive for as long as the problem exists

    def covariances(kind, imgs, X, lines):
        """Foot points on the lines and flat-along-the-line covariances (vectorised)."""
        n = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
        c = lines[:, 2] / np.linalg.norm(lines[:, :2], axis=1)
        t = np.column_stack([-n[:, 1], n[:, 0]])
        p0, s2 = np.zeros((len(X), 2)), np.ones(len(X))
        for k in np.unique(imgs):
            m = imgs == k
            iid = P.image_ids[k]
            cam, pose = P.cameras[P.image_camera[iid]], P.poses[iid]
            xy, J, _ = res.project_with_jacobian(
                cam.model, cam.params, pose.transform(X[m])
            )
            p0[m] = xy - ((n[m] * xy).sum(1) + c[m])[:, None] * n[m]
            if kind == 1:  # frozen 1 / |n . d_hat| of dist_z at the start
                d = J @ pose.rotation[:, 2]
                s2[m] = ((n[m] * d).sum(1) / np.linalg.norm(d, axis=1)) ** 2
        cov = (
            s2[:, None, None] * n[:, :, None] * n[:, None, :]
            + L2 * t[:, :, None] * t[:, None, :]
        )
        return p0, cov

    for kind, imgs, idx, blocks, lines in (
        (1, P.horizontal_image, P.horizontal_height, pts, P.horizontal_line),
        (0, P.vertical_image, P.vertical_corner, corner_pts, P.vertical_line),
    ):
        X = np.array([blocks[j] for j in idx])
        p0, cov = covariances(kind, imgs, X, lines)
        for k, j, p, C in zip(imgs, idx, p0, cov, strict=True):
            iid = P.image_ids[k]
            cid = P.image_camera[iid]
            cost = pycolmap.cost_functions.ReprojErrorCost(model_ids[cid], C, p)
            problem.add_residual_block(
                cost, loss, [blocks[j], pose_block[iid], cam_block[cid]]
            )
    # Tie points: free 3D blocks, the same rows (identity covariance scaled
    # by the tie sigma) and the tie loss on the 2D error.
    tie_pts = [x.copy() for x in P.tie_xyz]
    tie_loss = {"huber": pyceres.HuberLoss, "cauchy": pyceres.CauchyLoss}.get(
        options.loss, lambda s: None
    )(options.tie_loss_scale_px / options.tie_sigma_px)
    tie_cov = np.eye(2) * options.tie_sigma_px**2
    for k, t, xy in zip(P.tie_image, P.tie_point, P.tie_xy, strict=True):
        iid = P.image_ids[k]
        cid = P.image_camera[iid]
        cost = pycolmap.cost_functions.ReprojErrorCost(model_ids[cid], tie_cov, xy)
        problem.add_residual_block(
            cost, tie_loss, [tie_pts[t], pose_block[iid], cam_block[cid]]
        )
    for X in pts + corner_pts:
        if problem.has_parameter_block(X):
            problem.set_manifold(X, pyceres.SubsetManifold(3, [0, 1]))
    if free and options.corner_height_prior_m:

        class Prior(pyceres.CostFunction):
            def __init__(self, h0, sigma):
                super().__init__()
                self.set_num_residuals(1)
                self.set_parameter_block_sizes([3])
                self.h0, self.inv = h0, 1.0 / sigma

            def Evaluate(self, parameters, residuals, jacobians):
                residuals[0] = (parameters[0][2] - self.h0) * self.inv
                if jacobians is not None and jacobians[0] is not None:
                    jacobians[0][:] = [0.0, 0.0, self.inv]
                return True

        for X in corner_pts:
            if problem.has_parameter_block(X):
                cost = Prior(X[2], options.corner_height_prior_m)
                keep.append(cost)
                problem.add_residual_block(cost, None, [X])
    else:
        for X in corner_pts:
            if problem.has_parameter_block(X):
                problem.set_parameter_block_constant(X)
    t_build = time.perf_counter() - t0
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = pyceres.LinearSolverType.DENSE_SCHUR
    opts.num_threads = 1
    opts.max_num_iterations = max_iterations
    opts.function_tolerance = options.function_tolerance
    opts.parameter_tolerance = options.parameter_tolerance
    opts.gradient_tolerance = 1e-10
    summary = pyceres.SolverSummary()
    t1 = time.perf_counter()
    pyceres.solve(opts, problem, summary)
    t_solve = time.perf_counter() - t1
    poses = {i: Pose.from_rigid3d(rec.image(i).cam_from_world()) for i in P.image_ids}
    from obliq_colmap.geometry import Camera

    cameras = {c: Camera.from_pycolmap(rec.camera(c)) for c in P.cameras}
    heights = np.array([X[2] for X in pts] + [X[2] for X in corner_pts])
    del adjuster, problem, keep
    return poses, cameras, heights, t_build, t_solve, summary, rec


def reference_timing(P, tree: Path, runs: int) -> None:
    """Ours and the reference tree's solver alternately on ``P`` (defaults)."""
    (ref,) = load_reference(tree, ("bundle",))
    times = {"ours": [], "reference": []}
    for _ in range(runs):
        t = time.perf_counter()
        new = solve_bundle(P, BundleOptions())
        times["ours"].append(time.perf_counter() - t)
        t = time.perf_counter()
        old = ref.solve_bundle(P, ref.BundleOptions())
        times["reference"].append(time.perf_counter() - t)
    dc = max(
        np.abs(new.poses[i].center - old.poses[i].center).max() for i in P.image_ids
    )
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(
        f"ours {med['ours']:.3f} s, reference {med['reference']:.3f} s (medians of"
        f" {runs}, alternating): ratio {med['ours'] / med['reference']:.3f};"
        f" iterations {new.summary.num_iterations} / {old.summary.num_iterations},"
        f" largest centre difference {dc:.2e} m; load {os.getloadavg()}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--ceres-runs", type=int, default=3)
    ap.add_argument("--no-ceres", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--tie_points",
        type=int,
        default=0,
        help="so many tie points on the terrain (make_synthetic_problem), in "
        "both routes",
    )
    ap.add_argument(
        "--reference",
        help="source tree (git archive REV obliq_colmap | tar -x -C TREE): its "
        "solve_bundle timed alternately with ours on the same problem, then exit",
    )
    args = ap.parse_args()

    syn = make_synthetic_problem(seed=args.seed, tie_points=args.tie_points, **PAPER)
    P = syn.problem
    print(
        f"problem: {len(P.image_ids)} images, {len(P.cameras)} cameras, "
        f"{len(P.facade_heights)} facade + {len(P.corner_xy)} corner heights, "
        f"{len(P.horizontal_image)} horizontal + "
        f"{len(P.vertical_image)} vertical constraints, {len(P.tie_xyz)} tie "
        f"points with {len(P.tie_image)} observations"
    )

    if args.reference:
        reference_timing(P, Path(args.reference), args.runs)
        return

    rows = []
    for name, opts in [
        ("ours (defaults, ftol 1e-8)", BundleOptions()),
        # What the per-image precision (one more linearisation and one
        # dense inverse) adds to the defaults.
        ("ours (defaults, no precision)", BundleOptions(compute_precision=False)),
        (
            "ours (ftol 1e-10)",
            BundleOptions(function_tolerance=1e-10, parameter_tolerance=1e-10),
        ),
        ("ours (fixed corner heights)", BundleOptions(corner_heights="fixed")),
    ]:
        times, out = [], None
        for _ in range(args.runs):
            out = solve_bundle(P, opts)
            times.append(out.summary.time_s)
        s = out.summary
        rot, ctr, dev = pose_errors(out.poses, out.cameras, syn)
        rows.append(
            (
                name,
                np.median(times),
                s.num_iterations,
                s.final_rmse_vertical_px,
                s.final_rmse_horizontal_px,
                rot,
                ctr,
                dev,
                s.termination,
            )
        )
        if name == "ours (defaults, ftol 1e-8)":
            ours = out
    if not args.no_ceres:
        times_b, times_s = [], []
        with threadpool_limits(limits=1, user_api="blas"):
            for _ in range(args.ceres_runs):
                poses, cams, heights, tb, ts, summ, rec = ceres_route(
                    P, BundleOptions()
                )
                times_b.append(tb)
                times_s.append(ts)
        r = solve_bundle(  # residuals of the Ceres optimum in our exact objective
            _with(P, poses, cams, heights),
            BundleOptions(max_iterations=0, height_initialisation_steps=0),
        )
        rot, ctr, dev = pose_errors(poses, cams, syn)
        rows.append(
            (
                f"ceres (build {np.median(times_b):.2f} s + solve)",
                np.median(times_s),
                summ.num_successful_steps + summ.num_unsuccessful_steps,
                r.summary.initial_rmse_vertical_px,
                r.summary.initial_rmse_horizontal_px,
                rot,
                ctr,
                dev,
                str(summ.termination_type).split(".")[-1],
            )
        )
        dz = np.mean(
            [poses[i].center[2] - ours.poses[i].center[2] for i in P.image_ids]
        )
        d_rot = max(
            np.degrees(
                np.linalg.norm(_log(poses[i].rotation @ ours.poses[i].rotation.T))
            )
            for i in P.image_ids
        )
        d_ctr = max(
            np.linalg.norm(poses[i].center - ours.poses[i].center - [0, 0, dz])
            for i in P.image_ids
        )
        print(
            f"ceres optimum vs ours: max rotation {d_rot:.2e} deg, "
            f"max centre {d_ctr:.3f} m (after {dz:+.3f} m datum); "
            f"Ceres {summ.BriefReport()}"
        )

    print(
        "\n| route | median solve s | iterations | RMSE vert px | RMSE horiz px "
        "| rot err deg median / max | centre err m median / max "
        "| true-point dev px median / max | termination |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    for name, t, it, rv, rh, rot, ctr, dev, term in rows:
        print(
            f"| {name} | {t:.3f} | {it} | {rv:.4f} | {rh:.4f} | {np.median(rot):.4f} / "
            f"{rot.max():.4f} | {np.median(ctr):.3f} / {ctr.max():.3f} | "
            f"{np.median(dev):.2f} / {dev.max():.2f} | {term} |"
        )
    print(
        "\nratio ours (defaults) / ours (no precision): "
        f"{rows[0][1] / rows[1][1]:.3f}; median predicted precision "
        f"{np.nanmedian(list(ours.image_precision_px.values())):.2f} px"
    )
    if not args.no_ceres:
        print(
            f"\nratio ceres solve / ours (defaults): {rows[-1][1] / rows[0][1]:.2f}; "
            "(build + solve) / ours: "
            f"{(rows[-1][1] + np.median(times_b)) / rows[0][1]:.2f}"
        )


def _with(P, poses, cameras, heights):
    import dataclasses

    nJ = len(P.facade_heights)
    return dataclasses.replace(
        P,
        poses=poses,
        cameras=cameras,
        facade_heights=heights[:nJ],
        corner_heights=heights[nJ:],
    )


if __name__ == "__main__":
    main()
