#!/usr/bin/env python
"""Is the vertical VP what limits a scene? ``register`` with stage 1's VP
replaced by the TRUE one (issue 25: "the method cannot" or "the information
is not there").

For a scene in the external format (``images/``, ``priors/``, ``gt/``,
``cadastre.geojson``: the external scenes and ``obliq-colmap synth``
scenes), runs ``obliq-colmap register`` in this process (``--num_workers 1``,
so that the replacement reaches the per-image stage) with
``detect_vertical_vp`` wrapped: the real detection runs (its first-pass
segments stay, for the facade stage), then the VP is set to where the true
camera sees the world's vertical (``K_true R_true e_z``, the pixel a perfect
detector would find), its vertical segments are the second pass through
that VP, its status is ``ok`` and its covariance is ``--sigma_deg`` in
direction. Everything after stage 1 is the project's own code and options.
Then ``obliq-colmap evaluate --vertical_offset search`` (the judging
measure) on the result.

Run (from the repository root)::

    python scripts/diagnose/vp_oracle.py SCENE OUT [--sigma_deg 0.02]
        [--noise_deg 0] [--tilt_bias_deg 0]
        [--register_args "--camera_model SIMPLE_RADIAL --bundle_vp_observations 1"]

``--noise_deg`` / ``--tilt_bias_deg``: how good must stage 1 be? The true
direction is turned by a random angle (isotropic, ``noise_deg`` per axis,
seeded from the image's name) and by ``tilt_bias_deg`` about the camera's
x axis (the VP moved along the image's vertical axis, as stage 1's
systematic errors on low-rise districts move it), before it is projected;
the stated covariance stays ``--sigma_deg``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

import obliq_colmap.pipeline.workers as workers
from obliq_colmap.cli import main as cli_main
from obliq_colmap.lines import gradients
from obliq_colmap.parallel import image_seed
from obliq_colmap.vanishing.pencil import canonical_sign, normaliser, vertical_direction
from obliq_colmap.vanishing.second_pass import run_second_pass


def true_vps(
    gt_path: Path, noise_deg: float = 0.0, tilt_bias_deg: float = 0.0
) -> dict[str, np.ndarray]:
    """image name -> (3,) unit homogeneous pixel of the true vertical VP,
    optionally turned (module docstring)."""
    rec = pycolmap.Reconstruction(str(gt_path))
    out = {}
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        R = im.cam_from_world().rotation.matrix()
        rng = np.random.default_rng(image_seed(im.name, 0))
        w = np.radians(np.r_[rng.normal(0.0, noise_deg, 2), 0.0])
        w[0] += np.radians(tilt_bias_deg)
        v = cam.calibration_matrix() @ Rotation.from_rotvec(w).as_matrix() @ R[:, 2]
        out[im.name] = canonical_sign(v / np.linalg.norm(v))
    return out


def direction_covariance(vp: np.ndarray, K: np.ndarray, sigma_deg: float) -> np.ndarray:
    """(3, 3) covariance of the unit homogeneous VP for an isotropic
    direction error of ``sigma_deg``."""
    d = np.linalg.solve(K, vp)
    d /= np.linalg.norm(d)
    cov_d = np.radians(sigma_deg) ** 2 * (np.eye(3) - np.outer(d, d))
    Kd = K @ d
    n = np.linalg.norm(Kd)
    u = Kd / n
    J = (np.eye(3) - np.outer(u, u)) / n @ K
    return J @ cov_d @ J.T


def install_oracle(
    vps: dict[str, np.ndarray], downs: dict[str, np.ndarray], sigma_deg: float
):
    """Wrap the stage-1 call; the image is the one whose priors' "down"
    direction is the INS prior's (the call carries no name)."""
    real = workers.detect_vertical_vp
    names = list(downs)
    D = np.array([downs[n] for n in names])  # (I, 3)

    def oracle(img, options, camera, prior, rng=None):
        res = real(img, options, camera, prior, rng)
        vp = vps[names[int(np.argmax(D @ prior.down_cam))]]
        H, W = img.shape[:2]
        T, _ = normaliser(W, H)
        grads = gradients(img, options.second_pass.sigma_px)
        sp = run_second_pass(img, vp, options.second_pass, camera, T, grads)
        res.vp = vp
        res.covariance = direction_covariance(vp, camera.K, sigma_deg)
        res.direction_std_deg = sigma_deg
        res.vertical_direction = vertical_direction(
            vp, camera.K, prior.down_cam if prior.kind == "ins" else None
        )
        res.vertical_segments = sp.through(vp, T)
        res.vertical_segments_free = sp.free(T)
        res.status, res.message = "ok", "oracle: the true VP"
        return res

    workers.detect_vertical_vp = oracle


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("output_path", type=Path)
    ap.add_argument("--sigma_deg", type=float, default=0.02)
    ap.add_argument("--noise_deg", type=float, default=0.0)
    ap.add_argument("--tilt_bias_deg", type=float, default=0.0)
    ap.add_argument("--register_args", default="")
    args = ap.parse_args()
    scene = args.scene
    priors = pycolmap.Reconstruction(str(scene / "priors"))
    down = np.array([0.0, 0.0, -1.0])
    downs = {
        im.name: im.cam_from_world().rotation.matrix() @ down
        for im in priors.images.values()
    }
    install_oracle(
        true_vps(scene / "gt", args.noise_deg, args.tilt_bias_deg),
        downs,
        args.sigma_deg,
    )
    out = args.output_path
    shutil.rmtree(out, ignore_errors=True)
    argv = [
        "register",
        "--image_path", str(scene / "images"),
        "--cadastre_path", str(scene / "cadastre.geojson"),
        "--input_path", str(scene / "priors"),
        "--output_path", str(out),
        "--num_workers", "1",
        "--no_progress",
        *shlex.split(args.register_args),
    ]  # fmt: skip
    cli_main(argv)
    ev = out.with_suffix(".eval.json")
    cli_main(
        [
            "evaluate",
            "--input_path", str(out),
            "--gt_path", str(scene),
            "--vertical_offset", "search",
            "--output_path", str(ev),
        ]
    )  # fmt: skip
    res = json.loads(ev.read_text())
    # a missing image counts as infinitely far off, as in the judging measure
    px = [im["mean_deviation_px"] for im in res["images"]]
    px = np.array([np.inf if p is None else p for p in px])
    print(
        f"oracle VPs at {args.sigma_deg} deg: {int((px < 2).sum())}/{len(px)}"
        f" < 2 px, median {np.median(px):.2f} px"
    )


if __name__ == "__main__":
    main()
