"""Each observation kind's noise in georegister's block adjustment against
its weight, and the truth's share of the per-camera errors (issue 27: why
the block's predicted sd is off where it is).

For one georegister command (its arguments after ``--``), the block
adjustment's inputs are captured (``georegister_solvers``) and the
adjustment rerun with the obliq solver; then per kind the RMS of the
whitened residuals at the optimum (1 where the kind's sd is right; the
bundle's variance factor pools them all): the SfM tracks (per axis, at
their 1 px), the map rows (at their sd), the VPs (the angle between each
camera's down and its observed VP over the VP's sd). With ``--scene`` the
per-camera errors against the truth are split into the block's common
rotation (its tilt and heading: one error shared by all cameras) and the
rest.

Run (from the repository root)::

    python scripts/bench/georegister_noise.py --scene SCENE -- \\
        --input_path MODEL --image_path SCENE/images --cadastre_path ... \\
        --priors_path ... --output_path /tmp/unused
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap.cli.georegister import add_arguments, options_from_args
from obliq_colmap.georegister.block import (
    adjust_block,
    map_row_weighting,
    vertical_rows,
)
from obliq_colmap.georegister.map_rows import row_residuals_px

sys.path.insert(0, str(Path(__file__).resolve().parent))
from georegister_solvers import capture_block_inputs  # noqa: E402 - beside this script


def _rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def track_residuals(rec: pycolmap.Reconstruction) -> np.ndarray:
    """(O, 2) reprojection residuals (px) of every track observation."""
    out = []
    for i in rec.reg_image_ids():
        image = rec.images[i]
        obs = image.get_observation_points2D()
        if not len(obs):
            continue
        X = np.array([rec.points3D[p.point3D_id].xyz for p in obs])
        uv = image.camera.img_from_cam(image.cam_from_world() * X)
        out.append(uv - np.array([p.xy for p in obs]))
    return np.concatenate(out) if out else np.zeros((0, 2))


def vp_angles_deg(rec, rows) -> dict[int, float]:
    """Per image the angle (deg) between its camera's down and the VP's
    direction through its current pinhole part."""
    from obliq_colmap.geometry import calibration_matrix

    out = {}
    for i, row in rows.items():
        image = rec.images[i]
        cam = image.camera
        K = calibration_matrix(cam.model.name, np.asarray(cam.params, float))
        m = np.linalg.solve(K, row.vp)
        m /= np.linalg.norm(m)
        d = image.cam_from_world().rotation.matrix() @ [0.0, 0.0, -1.0]
        out[i] = float(np.degrees(np.arccos(min(1.0, abs(m @ d)))))
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--")
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=None)
    ap.add_argument("--output_path", type=Path, default=None)
    args = ap.parse_args(argv[:split])
    cmd = argparse.ArgumentParser()
    add_arguments(cmd)
    gargs = cmd.parse_args(argv[split + 1 :] + ["--no_progress"])
    options = options_from_args(gargs)
    inputs = capture_block_inputs(
        Path(gargs.input_path), Path(gargs.image_path), options
    )
    rec = pycolmap.Reconstruction(inputs.rec)
    block = dataclasses.replace(inputs.block, solver="obliq")
    summary = adjust_block(rec, inputs.control, inputs.verticals, block,
                           **inputs.kwargs)  # fmt: skip
    out: dict = {"variance_factor": summary.uncertainty.variance_factor
                 if summary.uncertainty else None}  # fmt: skip
    tr = track_residuals(rec)
    out["tracks"] = {"num": len(tr), "rms_px_per_axis": _rms(tr), "sd_px": 1.0}
    rows = inputs.kwargs.get("map_rows")
    if rows is not None and len(rows):
        sigma, scale = map_row_weighting(block)
        r = row_residuals_px(rec, rows)
        out["map_rows"] = {
            "num": len(r),
            "rms_px": _rms(r),
            "rms_px_within_3_scale": _rms(r[np.abs(r) < 3 * scale]),
            "sd_px": sigma,
            "num_beyond_3_scale": int(np.sum(np.abs(r) >= 3 * scale)),
        }
    vrows = vertical_rows(rec, inputs.verticals, block.min_vertical_sd_deg)
    ang = vp_angles_deg(rec, vrows)
    sd = {i: np.degrees(r.sd_rad) for i, r in vrows.items()}
    whit = [ang[i] / sd[i] for i in ang]
    out["vps"] = {
        "num": len(ang),
        "angle_median_deg": float(np.median(list(ang.values()))),
        "sd_median_deg": float(np.median(list(sd.values()))),
        "whitened_rms_per_axis": _rms(whit) / np.sqrt(2.0),
    }
    if args.scene is not None:
        from obliq_colmap.synthetic import load_scene

        scene = load_scene(args.scene)
        truth = {im.name: im.cam_from_world for im in scene.gt_local.images.values()}
        # the model's frame: local to the origin of its georef; the truth's
        # local frame is the scene's, which may differ by a shift only
        ids = [i for i in sorted(rec.reg_image_ids()) if rec.images[i].name in truth]
        dRs = []
        for i in ids:
            R = rec.images[i].cam_from_world().rotation.matrix()
            dRs.append(R.T @ truth[rec.images[i].name].rotation)  # world frame
        # the block's common rotation (chordal mean of the world-frame errors)
        U, _, Vt = np.linalg.svd(np.sum(dRs, axis=0))
        W = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        ang_all = [pycolmap.Rotation3d(d).angle() for d in dRs]
        ang_rest = [pycolmap.Rotation3d(W.T @ d).angle() for d in dRs]
        out["rotation_errors"] = {
            "block_common_deg": float(np.degrees(pycolmap.Rotation3d(W).angle())),
            "per_camera_median_deg": float(np.degrees(np.median(np.abs(ang_all)))),
            "without_common_median_deg": float(np.degrees(np.median(np.abs(ang_rest)))),
        }
        if summary.uncertainty is not None:
            C = summary.uncertainty.pose_covariance
            sd_r = [np.degrees(np.sqrt(np.trace(C[i][:3, :3]))) for i in ids]
            out["rotation_errors"]["predicted_sd_median_deg"] = float(np.median(sd_r))
    print(json.dumps(out, indent=1))
    if args.output_path:
        args.output_path.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
