"""Diagnostics of the cadastral-line bundle on a synthetic scene with truth.

Two measurements behind the bundle stage's design (issue 5), on the stage-2
result of ``register`` for one scene:

1. Facade tracks at the TRUE cameras: the dist_z residuals of every track
   observation when the track is a point on its map edge (the paper's
   ``x_j + h_j z``), and when it is a free 3D horizontal line parallel to
   the edge (``matching.triangulate_tracks``). Far smaller residuals for the
   line mean that the tracks sit off their walls (roof rims overhang).
2. The conditioning of the solved problem: the smallest eigenvalues of the
   Jacobi-scaled reduced camera system (heights eliminated) at the bundle's
   solution, and which parameters make up their modes (pose rotation w0..w2
   about the camera axes, centre c0..c2, camera parameters p0.. in the
   refined basis: for PINHOLE f, cx, cy).

    python scripts/bench_bundle_diagnostics.py --scene_path SCENE [--num_workers 2]

Scenes are made with ``obliq-colmap synth --preset paper --seed N --output_path DIR``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from obliq_colmap import adjustment as adj
from obliq_colmap import pipeline as pl
from obliq_colmap.bundle import residuals as res
from obliq_colmap.bundle import solver as sv
from obliq_colmap.evaluate import read_ground_truth
from obliq_colmap.matching import triangulate_tracks
from obliq_colmap.registration import RegistrationOptions


def _stage2(scene: Path, workers: int) -> tuple[pl.Inputs, dict, pl.PipelineOptions]:
    noise = json.loads((scene / "scene.json").read_text())["options"]
    options = pl.PipelineOptions(
        stop_after="initial",
        num_workers=workers,
        progress=False,
        registration=RegistrationOptions(
            prior_position_sigma_m=noise["prior_position_m"],
            prior_rotation_sigma_deg=noise["prior_rotation_deg"],
            prior_focal_sigma=noise["prior_focal_percent"] / 100.0,
        ),
    )
    run = pl.run_register(
        scene / "images", scene / "cadastre.geojson", scene / "priors", options
    )
    inputs = pl.load_inputs(
        scene / "images", scene / "cadastre.geojson", scene / "priors", options
    )
    return inputs, run.outcomes, options


def _percentiles(a: np.ndarray) -> str:
    a = np.abs(a[np.isfinite(a)])
    q = np.percentile(a, [50, 75, 90, 95])
    return (
        f"|r| median {q[0]:.3f} p75 {q[1]:.3f} p90 {q[2]:.3f} p95 {q[3]:.3f} px,"
        f" > 1 px {np.mean(a > 1):.3f}"
    )


def track_residuals_at_truth(scene: Path, inputs, stage3, problem) -> None:
    """Measurement 1."""
    cad = inputs.cadastre
    gt = read_ground_truth(scene)
    gtb = gt.block.shifted(np.array([cad.origin[0], cad.origin[1], 0.0]))
    by_name = {im.name: im for im in gtb.images.values()}
    truth = [by_name[inputs.priors.images[i].name] for i in stage3.ids]
    cams = [gtb.cameras[t.camera_id] for t in truth]
    poses = [t.cam_from_world for t in truth]
    t = stage3.tracks
    offsets = np.cumsum([0] + [len(f) for f in stage3.facades])
    ppm = np.concatenate([f.px_per_m for f in stage3.facades])[offsets[t.image] + t.row]
    normal = cad.edge_normal[t.edge]
    for label, sigma in (("point on the map edge", 1e-6), ("free 3D line", 1e6)):
        d, h = triangulate_tracks(
            t.image,
            t.track,
            stage3.ends_raw,
            cams,
            poses,
            t.anchor_xy,
            normal,
            ppm,
            sigma,
        )
        X = np.column_stack([t.anchor_xy + d[:, None] * normal, h])[t.track]
        r = res.horizontal_residuals_by_image(
            cams, poses, t.image, X, problem.horizontal_line
        )
        print(f"  tracks as a {label}: {_percentiles(r)}")


def conditioning(problem, options: sv.BundleOptions) -> None:
    """Measurement 2."""
    result = sv.solve_bundle(problem, options)
    P = dataclasses.replace(
        problem,
        poses=result.poses,
        cameras=result.cameras,
        facade_heights=result.facade_heights,
    )
    S = sv._Setup(P, options)
    st = sv._State(
        np.stack([P.poses[i].rotation for i in P.image_ids]),
        np.stack([P.poses[i].center for i in P.image_ids]),
        [P.cameras[c].params.copy() for c in S.camera_ids],
        P.facade_heights.copy(),
    )
    r, Jc, Jh = sv._evaluate(S, st, jac=True)
    _, w = sv._loss(options.loss, options.loss_scale_px, r * r)
    H_cc, _, H_hh, _, F = sv._normal_equations(S, Jc, Jh, r, w * S.weight)
    E = S.coupling.matrix(F)
    Es = sp.diags(np.sqrt(1.0 / np.maximum(H_hh, 1e-12))) @ E
    A = H_cc - (Es.T @ Es).toarray()
    d = np.sqrt(np.maximum(np.diag(A), 1e-12))
    ev, V = np.linalg.eigh(A / np.outer(d, d))
    labels = [
        f"{k}" for _ in S.active_images for k in (["w0", "w1", "w2", "c0", "c1", "c2"])
    ]
    for basis in S.refined:
        labels += [f"p{q}" for q in range(basis.shape[1])]
    labels = np.array(labels)
    print(f"  {result.summary.brief()}")
    print(
        "  smallest eigenvalues (Jacobi-scaled; the first is the vertical datum):",
        " ".join(f"{e:.1e}" for e in ev[:10]),
    )
    print(f"  median eigenvalue {np.median(ev):.2e}")
    for m in range(1, 8):
        share = {k: float(np.sum(V[labels == k, m] ** 2)) for k in np.unique(labels)}
        top = sorted(share.items(), key=lambda kv: -kv[1])[:4]
        print(
            f"  mode {m}: eigenvalue {ev[m]:.1e}, "
            + ", ".join(f"{k} {v:.2f}" for k, v in top)
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene_path", required=True, help="synthetic scene folder")
    parser.add_argument("--num_workers", type=int, default=2)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    scene = Path(args.scene_path)
    if not (scene / "gt").is_dir():
        print(f"error: {scene} is not a synthetic scene (no gt/)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    inputs, outcomes, options = _stage2(scene, args.num_workers)
    reg = [o for o in outcomes.values() if o.registered]
    state = adj.BlockState.from_outcomes(reg)
    stage3 = adj.facade_stage(inputs, state, outcomes, options.adjustment)
    state = state.with_datum_correction(
        dict(zip(stage3.ids, stage3.tracks.datum_correction, strict=True))
    )
    problem = adj.build_bundle_problem(inputs, outcomes, state, stage3)
    print(f"{scene.name}: {len(reg)} images, {stage3.tracks.num_tracks} tracks")
    track_residuals_at_truth(scene, inputs, stage3, problem)
    bundle = dataclasses.replace(options.adjustment.bundle, corner_heights="fixed")
    conditioning(problem, bundle)
    print(f"  ({time.perf_counter() - t0:.0f} s, {time.strftime('%Y-%m-%d')})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
