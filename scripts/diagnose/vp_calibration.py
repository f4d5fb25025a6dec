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

Environment: ``CONE`` (deg, default 5.681...: ``PipelineOptions().cone_deg``),
``VPOPTS`` (JSON of VanishingOptions fields).
"""

import argparse
import collections
import json
import os

import cv2
import numpy as np
import pycolmap

from obliq_colmap.geometry import Camera
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


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--json")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args()
    S = a.scene
    vo = json.loads(os.environ.get("VPOPTS", "{}"))
    opts = VanishingOptions(**vo)
    cone = float(os.environ.get("CONE", "5.681017059859261"))
    gt = pycolmap.Reconstruction(S + "/gt")
    pr = pycolmap.Reconstruction(S + "/priors")
    pri = {i.name: i for i in pr.images.values()}
    rows = []
    for im in sorted(gt.images.values(), key=lambda i: i.name):
        p = pri[im.name]
        pc = pr.cameras[p.camera_id]
        cam = Camera(pc.model.name, pc.width, pc.height, np.asarray(pc.params))
        R = im.cam_from_world().rotation.matrix()
        K = gt.cameras[im.camera_id].calibration_matrix()
        img = cv2.imread(S + "/images/" + im.name, cv2.IMREAD_GRAYSCALE)
        prior = VPPrior.from_rotation(p.cam_from_world().rotation.matrix(), cone)
        res = detect_vertical_vp(img, opts, camera=cam, prior=prior)
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
