"""How well the report's per-camera sds (``report.json`` "uncertainty")
predict the real deviation of the solved poses.

Two measurements:

* ``synthetic`` (default): Monte Carlo over the bundle alone on
  ``make_synthetic_problem`` (16 images, 0.5 px noise, loss off), the pose
  blocks of ``BundleResult.pose_covariance``;
  prints per axis sqrt(mean deviation^2 / mean sd^2) for the horizontal
  centre (m) and the rotation about the camera's axes (deg).
* ``--model OUT --gt GT``: one ``register`` output against the scene's true
  model (absolute COLMAP model, e.g. ``data_samples/oblique_small/gt``):
  the same ratio for the horizontal centres (the vertical one carries the
  datum) over the images written, and the median of error / sd.

Run (from the repository root)::

    python scripts/bench/pose_sd.py [--trials 40] [--noise 0.5]
    python scripts/bench/pose_sd.py --model OUT --gt data_samples/oblique_small/gt

Figures: docs/STATUS.md ("Products (issue 28)"), docs/journal/report.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from obliq_colmap.bundle import BundleOptions, solve_bundle
from obliq_colmap.colmap_io import read_georef, read_model
from obliq_colmap.geometry import axis_angle_from_rotation
from obliq_colmap.report import uncertainty_report
from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem


def synthetic(trials: int, noise: float) -> None:
    opts = BundleOptions(
        loss="none", function_tolerance=1e-14, parameter_tolerance=1e-14
    )
    dxy, sxy, drot, srot = [], [], [], []
    for seed in range(trials):
        syn = make_synthetic_problem(
            seed=seed, buildings=(5, 5), stations=(2, 2), noise_px=noise
        )
        out = solve_bundle(syn.problem, opts)
        names = {i: str(i) for i in syn.problem.image_ids}
        unc = uncertainty_report(out, names)
        for i in syn.problem.image_ids:
            e = unc["images"][names[i]]
            dxy.append(out.poses[i].center[:2] - syn.poses[i].center[:2])
            sxy.append(e["position_sd_m"][:2])
            w = axis_angle_from_rotation(
                out.poses[i].rotation @ syn.poses[i].rotation.T
            )
            drot.append(np.degrees(w))
            srot.append(e["rotation_sd_deg"])
    dxy, sxy, drot, srot = map(np.array, (dxy, sxy, drot, srot))
    ratio = lambda d, s: np.sqrt(np.mean(d**2, axis=0) / np.mean(s**2, axis=0))  # noqa: E731
    print(f"synthetic bundle, {trials} trials x 16 images, noise {noise} px")
    print("  measured / predicted, centre x, y:", np.round(ratio(dxy, sxy), 3))
    print(
        "  measured / predicted, rotation about camera x, y, z:",
        np.round(ratio(drot, srot), 3),
    )
    print(
        "  median predicted sd: centre x, y (m)",
        np.round(np.median(sxy, axis=0), 3),
        " rotation (deg)",
        np.round(np.median(srot, axis=0), 4),
    )


def against_truth(model: Path, gt: Path) -> None:
    unc = json.loads((model / "report.json").read_text())["uncertainty"]["images"]
    block, truth = read_model(model), read_model(gt)
    origin = read_georef(model).origin
    true_c = {im.name: im.cam_from_world.center for im in truth.images.values()}
    err, sd = [], []
    for im in block.images.values():
        e = unc.get(im.name, {})
        if "position_sd_m" not in e or im.name not in true_c:
            continue
        err.append(im.cam_from_world.center[:2] + origin[:2] - true_c[im.name][:2])
        sd.append(e["position_sd_m"][:2])
    err, sd = np.array(err), np.array(sd)
    print(f"{model} against {gt}: {len(err)} images")
    print(
        "  horizontal error (m) median |dx|, |dy|:",
        np.round(np.median(np.abs(err), axis=0), 3),
    )
    print("  predicted sd (m) median x, y:", np.round(np.median(sd, axis=0), 3))
    print(
        "  measured / predicted RMS x, y:",
        np.round(np.sqrt(np.mean(err**2, axis=0) / np.mean(sd**2, axis=0)), 3),
    )
    print("  median |error| / sd:", np.round(np.median(np.abs(err) / sd), 3))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=40)
    p.add_argument("--noise", type=float, default=0.5)
    p.add_argument("--model", type=Path)
    p.add_argument("--gt", type=Path)
    a = p.parse_args()
    if a.model is not None:
        against_truth(a.model, a.gt)
    else:
        synthetic(a.trials, a.noise)


if __name__ == "__main__":
    main()
