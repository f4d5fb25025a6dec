"""georegister's block covariance (the project's bundle) against Ceres' on
the same problem (pycolmap's ``estimate_ba_covariance_from_problem`` on the
Ceres block adjustment, :mod:`obliq_colmap.georegister.block_ceres`).

For one georegister command (its arguments after ``--``) the block
adjustment's inputs are captured (``georegister_solvers``), the block is
adjusted with each solver (to ``--tolerance``), and per camera the ratio of
our centre and rotation sds (the cofactor, i.e. the covariance over the
variance factor) to Ceres' is reported. Ceres' pose covariance is in its
quaternion manifold's tangent, ``q <- [cos |d|, sin |d| d / |d|] q``: half
the rotation vector, so it is converted to ours (``R <- Exp(omega) R``,
omega = 2 d; the centre ``c = -R^T t``). ``--loss_scale_px`` (e.g. 1e6)
makes both problems plain least squares, where the two must agree exactly;
with the Cauchy loss they differ by how each linearises it (ours: the
IRLS weight ``rho'``; Ceres: its corrected Jacobian, and the map rows' loss
inside their residual).

Run (from the repository root)::

    python scripts/bench/georegister_covariance.py [--loss_scale_px 1e6] -- \\
        GEOREGISTER_ARGUMENTS
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pyceres
import pycolmap

import obliq_colmap.georegister.block_ceres as block_ceres
from obliq_colmap.cli.georegister import add_arguments, options_from_args
from obliq_colmap.geometry import skew
from obliq_colmap.georegister.block import adjust_block

sys.path.insert(0, str(Path(__file__).resolve().parent))
from georegister_solvers import capture_block_inputs  # noqa: E402 - beside this script


def ceres_pose_covariance(
    ba: pycolmap.BACovariance, rec: pycolmap.Reconstruction, image_id: int
) -> np.ndarray | None:
    """(6, 6) covariance of (omega, rad; centre, m) from Ceres' covariance of
    ``cam_from_world`` in its tangent (half rotation vector, translation)."""
    C = ba.get_cam_cov_from_world(image_id)
    if C is None or C.shape != (6, 6):
        return None
    T = rec.images[image_id].cam_from_world()
    R, t = T.rotation.matrix(), T.translation
    J = np.zeros((6, 6))
    J[:3, :3] = 2.0 * np.eye(3)  # omega = 2 d
    # c = -R^T t with R <- Exp(omega) R, t <- t + dt:
    # dc = -R^T dt - R^T skew(t) omega (to first order)
    J[3:, :3] = -2.0 * R.T @ skew(t)
    J[3:, 3:] = -R.T
    return J @ C @ J.T


def adjust_both(inputs, block) -> tuple[dict, dict, float]:
    """Our covariance over its variance factor (the cofactor) and Ceres'
    covariance at its optimum, per image; and our variance factor."""
    rec_o = pycolmap.Reconstruction(inputs.rec)
    ours = adjust_block(rec_o, inputs.control, inputs.verticals, block,
                        **inputs.kwargs)  # fmt: skip
    u = ours.uncertainty
    if u is None:
        raise RuntimeError("no covariance from the obliq solver (no map rows?)")
    rec_c = pycolmap.Reconstruction(inputs.rec)
    got = {}
    solve = pyceres.solve

    def solve_then_covariance(options, problem, summary):
        solve(options, problem, summary)
        got["ba"] = pycolmap.estimate_ba_covariance_from_problem(
            pycolmap.BACovarianceOptions(), rec_c, problem
        )

    block_ceres.pyceres.solve = solve_then_covariance  # the bench's hook only
    try:
        adjust_block(rec_c, inputs.control, inputs.verticals,
                     dataclasses.replace(block, solver="ceres"),
                     **inputs.kwargs)  # fmt: skip
    finally:
        block_ceres.pyceres.solve = solve
    theirs = {}
    for i in rec_c.reg_image_ids():
        C = ceres_pose_covariance(got["ba"], rec_c, i)
        if C is not None:
            theirs[i] = C
    ours_cof = {i: C / u.variance_factor for i, C in u.pose_covariance.items()}
    return ours_cof, theirs, u.variance_factor


def sd_ratios(ours: dict, theirs: dict) -> dict:
    """Per image sqrt(trace) ratios ours / Ceres' of the centre and rotation
    blocks: median, min, max."""
    ids = sorted(set(ours) & set(theirs))
    c = [np.sqrt(np.trace(ours[i][3:, 3:]) / np.trace(theirs[i][3:, 3:])) for i in ids]
    r = [np.sqrt(np.trace(ours[i][:3, :3]) / np.trace(theirs[i][:3, :3])) for i in ids]
    f = lambda a: {"median": float(np.median(a)), "min": float(np.min(a)),  # noqa: E731
                   "max": float(np.max(a))}  # fmt: skip
    return {"num_images": len(ids), "centre": f(c), "rotation": f(r)}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--")
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--loss_scale_px", type=float, default=None)
    ap.add_argument("--tolerance", type=float, default=1e-10)
    ap.add_argument("--output_path", type=Path, default=None)
    args = ap.parse_args(argv[:split])
    cmd = argparse.ArgumentParser()
    add_arguments(cmd)
    gargs = cmd.parse_args(argv[split + 1 :] + ["--no_progress"])
    inputs = capture_block_inputs(
        Path(gargs.input_path), Path(gargs.image_path), options_from_args(gargs)
    )
    block = dataclasses.replace(inputs.block, function_tolerance=args.tolerance)
    if args.loss_scale_px is not None:
        block = dataclasses.replace(block, loss_scale_px=args.loss_scale_px)
    ours, theirs, vf = adjust_both(inputs, block)
    out = {"loss_scale_px": block.loss_scale_px, "variance_factor": vf,
           **sd_ratios(ours, theirs)}  # fmt: skip
    print(json.dumps(out, indent=1))
    if args.output_path:
        args.output_path.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
