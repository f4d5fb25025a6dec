#!/usr/bin/env python
"""Is stage 1's stated covariance realistic? Per image of a scene with the truth.

Runs ``detect_vertical_vp`` as ``register`` does (INS prior from the priors'
rotation, cone ``CONE`` deg, the priors' camera) on every image of a scene in
the external format (``images/``, ``gt/`` and ``priors/`` COLMAP models: the
external scenes and ``obliq-colmap synth`` scenes), and scores the vertical
direction with the TRUE K against the true vertical. Per image: status,
error (deg), the claimed sd (``direction_std_deg``), their ratio, and the
Mahalanobis distance of the error under the stated covariance (propagated
to the direction with the true K; a realistic covariance gives ~ chi with
2 dof: median 1.18, > 3 in 1 % of the images). Summaries over the images with
status ok / any VP.

Run (from the repository root)::

    python scripts/diagnose/vp_calibration.py SCENE [--json out.json]
        [--prior aerial] [--overlay_path DIR [--names N_00.jpg ...]]

Each image is seeded from its name as ``register`` seeds it
(:func:`obliq_colmap.parallel.image_seed`). ``--prior aerial``: the aerial
prior with the priors' camera (``obliq-colmap vanishing --input_path priors
--vp_prior aerial``), i.e. stage 1 without the INS prior. ``--overlay_path``:
the images drawn (first-pass inliers blue, second-pass segments red, the
projected true wall corners green, lines to the true VP thin green and to
the found VP thin yellow).

Environment: ``CONE`` (deg, default 5.681...: ``PipelineOptions().cone_deg``),
``VPOPTS`` (JSON of VanishingOptions fields).
"""

import argparse
import collections
import dataclasses
import json
import os

import cv2
import numpy as np
import pycolmap

from obliq_colmap.geometry import Camera
from obliq_colmap.parallel import image_seed
from obliq_colmap.vanishing import VanishingOptions, VPPrior, detect_vertical_vp


def mahalanobis(vp, cov, K, d_true):
    Kinv = np.linalg.inv(K)
    m = Kinv @ vp
    nm = np.linalg.norm(m)
    J = (np.eye(3) - np.outer(m, m) / nm**2) / nm @ Kinv
    C = J @ cov @ J.T
    d = m / nm
    if d @ d_true < 0:
        d = -d
    e = d_true - d
    # tangent basis at d
    B = np.linalg.svd(np.eye(3) - np.outer(d, d))[0][:, :2]
    C2 = B.T @ C @ B
    e2 = B.T @ e
    try:
        return float(np.sqrt(e2 @ np.linalg.solve(C2, e2)))
    except np.linalg.LinAlgError:
        return np.nan


def draw_overlay(out_dir, im, gt, img, res, edges) -> None:
    """The image with stage 1's segments, the true wall corners and the VPs."""
    pose = im.cam_from_world()
    R, t = pose.rotation.matrix(), pose.translation
    K = gt.cameras[im.camera_id].calibration_matrix()
    H, W = img.shape
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)

    def line(p, q, color, thick=1):
        p, q = np.round(np.asarray(p) - 0.5), np.round(np.asarray(q) - 0.5)
        cv2.line(out, tuple(map(int, p)), tuple(map(int, q)), color, thick, cv2.LINE_AA)

    vt = K @ R[:, 2]
    for vp, color in ((vt, (0, 160, 0)), (res.vp, (0, 220, 220))):
        if vp is None:
            continue
        for x in np.linspace(0.05, 0.95, 7) * W:
            # from the image's top edge towards the VP, to the bottom edge
            p = np.array([x, 0.0])
            d = vp[:2] - p * vp[2]
            if abs(d[1]) < 1e-9:
                continue
            line(p, p + d * (H / d[1]), color)
    Xc = edges.reshape(-1, 3) @ R.T + t
    ok = (Xc[:, 2] > 0).reshape(-1, 2).all(1)
    px = Xc @ K.T
    px = (px[:, :2] / px[:, 2:]).reshape(-1, 2, 2)
    for e in px[ok]:
        line(e[0], e[1], (0, 255, 0), 3)
    for e in res.segments.endpoints[res.inliers]:
        line(e[0], e[1], (255, 128, 0), 2)
    if res.vertical_segments is not None:
        for e in res.vertical_segments.endpoints:
            line(e[0], e[1], (0, 0, 255), 2)
    cv2.putText(
        out,
        f"{im.name} {res.status}",
        (20, 40),
        cv2.FONT_HERSHEY_SIMPLEX,
        1.2,
        (0, 0, 255),
        2,
    )
    cv2.imwrite(os.path.join(out_dir, im.name.rsplit(".", 1)[0] + ".png"), out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--json")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--prior", choices=("ins", "aerial"), default="ins")
    ap.add_argument("--overlay_path")
    ap.add_argument("--names", nargs="*")
    a = ap.parse_args()
    S = a.scene
    vo = json.loads(os.environ.get("VPOPTS", "{}"))
    opts = VanishingOptions(**vo)
    cone = float(os.environ.get("CONE", "5.681017059859261"))
    gt = pycolmap.Reconstruction(S + "/gt")
    pr = pycolmap.Reconstruction(S + "/priors")
    pri = {i.name: i for i in pr.images.values()}
    rows = []
    edges = None
    if a.overlay_path:
        import sys
        from pathlib import Path

        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from vp_edge_oracle import wall_corners

        edges = wall_corners(Path(S) / "gt_buildings.json")
        os.makedirs(a.overlay_path, exist_ok=True)
    for im in sorted(gt.images.values(), key=lambda i: i.name):
        if a.names and im.name not in a.names:
            continue
        p = pri[im.name]
        pc = pr.cameras[p.camera_id]
        cam = Camera(pc.model.name, pc.width, pc.height, np.asarray(pc.params))
        R = im.cam_from_world().rotation.matrix()
        K = gt.cameras[im.camera_id].calibration_matrix()
        img = cv2.imread(S + "/images/" + im.name, cv2.IMREAD_GRAYSCALE)
        if a.prior == "ins":
            prior = VPPrior.from_rotation(p.cam_from_world().rotation.matrix(), cone)
        else:
            prior = VPPrior.aerial()
        seeded = dataclasses.replace(opts, seed=image_seed(im.name, opts.seed))
        res = detect_vertical_vp(img, seeded, camera=cam, prior=prior)
        if edges is not None:
            draw_overlay(a.overlay_path, im, gt, img, res, edges)
        row = dict(
            name=im.name,
            status=res.status,
            err=np.nan,
            sd=res.direction_std_deg,
            maha=np.nan,
            t=res.time_s.get("total", np.nan),
        )
        if res.vp is not None:
            dt = R @ [0, 0, -1.0]
            d = np.linalg.solve(K, res.vp)
            d /= np.linalg.norm(d)
            row["err"] = float(np.degrees(np.arccos(min(1, abs(d @ dt)))))
            # Signed: the small rotation taking the true vertical to the found
            # one, about the camera's x axis (tilt: the pitch that trades with
            # focal and camera height) and about the axis across it (roll).
            d = d if d @ dt > 0 else -d
            w = np.cross(dt, d)
            across = np.cross(dt, [1.0, 0, 0])
            row["tilt"] = float(np.degrees(w[0]))
            row["roll"] = float(np.degrees(w @ across / np.linalg.norm(across)))
            row["maha"] = mahalanobis(res.vp, res.covariance, K, dt)
        row["ratio"] = row["err"] / row["sd"] if row["sd"] > 0 else np.nan
        rows.append(row)
        if a.verbose:
            print(row, flush=True)
    heads = collections.defaultdict(list)
    for r in rows:
        heads[r["name"][0]].append(r["status"] == "ok" and r["err"] <= 0.5)
    ok = [r for r in rows if r["status"] == "ok"]
    anyvp = [r for r in rows if np.isfinite(r["err"])]

    def q(vals):
        v = np.array(vals, float)
        v = v[np.isfinite(v)]
        if not len(v):
            return "-"
        return (
            f"med {np.median(v):.2f} p90 {np.quantile(v, 0.9):.2f} max {v.max():.2f} "
            f">3: {int((v > 3).sum())}/{len(v)}"
        )

    name = os.path.basename(S.rstrip("/"))
    print(
        f"{name}: ok<=0.5deg {sum(sum(v) for v in heads.values())}/{len(rows)} "
        + " ".join(f"{h}:{sum(v)}/{len(v)}" for h, v in sorted(heads.items()))
        + f"; status ok {len(ok)}, ok but >0.5deg {sum(r['err'] > 0.5 for r in ok)}"
        + f"; median err(ok) {np.median([r['err'] for r in ok]) if ok else np.nan:.3f}"
        + f"; median t {np.median([r['t'] for r in rows]):.2f}s"
    )
    print(f"   ratio err/sd (ok): {q([r['ratio'] for r in ok])}")
    print(f"   mahalanobis  (ok): {q([r['maha'] for r in ok])}")
    print(f"   mahalanobis (any): {q([r['maha'] for r in anyvp])}")
    print(f"   sd (ok): med {np.median([r['sd'] for r in ok]) if ok else np.nan:.3f}")
    print(
        "   not ok<=0.5:",
        "; ".join(
            f"{r['name']} {r['status']} {r['err']:.2f} sd {r['sd']:.2f}"
            for r in rows
            if not (r["status"] == "ok" and r["err"] <= 0.5)
        ),
    )
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=0)


if __name__ == "__main__":
    main()
