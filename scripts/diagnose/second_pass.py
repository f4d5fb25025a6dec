#!/usr/bin/env python
"""Why the second pass misses true corner edges, and what its "false" detections are.

On a synthetic scene (true intrinsics, aerial prior, default options, as in
``bench/vanishing.py --sections synthetic``), every pixel-sample of every
visible true building-corner edge > 20 px that the final detections do not
cover (within 1 px) is traced back through the stages of the second pass,
and every final detection that the bench counts as false is classified;
also the signed offset of detections from the true corner edges they match.

Run (from the repository root)::

    python scripts/diagnose/second_pass.py --scene /work/scenes/paper_s1 \\
        [--every 3] [--output diag.json] [--set second_pass.high=5]

Figures: docs/journal/stage1-vanishing.md (the second pass's misses,
classified, 2026-12-02); the live question is issue 25 (``no_vp`` and weak
VPs on scenes we did not make).

Data: a synthetic scene (``obliq-colmap synth``); the scoring is
``vanishing_scoring.py``'s, shared with the bench.

Recall side, per 1-px sample of a target edge (first matching cause):

- ``no contrast``: the step across the edge |I(+2 px) - I(-2 px)| (mean of
  3 samples along it) is below the bench's visible-contrast bound;
- ``final within 2 px``: a final detection covers it within 2 px, not 1;
- ``final rule``: covered by the second pass at the final VP with default
  filters (``vanishing.vertical_segments``), but removed by the stage's
  competing-VP rule (its refinement on chains);
- ``chain filters: length / density / RMS``: covered with that filter of
  the second pass off (``min_length_px`` 0, ``min_density`` 0,
  ``max_rms_px`` 1.5), ``several``: only with all three off;
- ``chain lost``: an edge point of a chain that passed the hysteresis lies
  there, but no chain through the VP keeps it (dropped > 1.5 px from its
  chain's line, or a fragment of < 3 points);
- ``hysteresis``: an edge point with |D| >= low exists, but its chain never
  reaches ``high``;
- ``D < low`` / ``gradient angle``: no edge point; the largest |D| across
  the edge (+-1.5 px) is below ``low``, or the gradient leaves the normal by
  more than ``max_gradient_angle_deg``; ``NMS``: neither (a stronger
  neighbour response within a pixel takes the maximum).

Each missed edge gets the cause of most of its uncovered samples, or
``gt: no-contrast part`` when the detections cover >= 80 % of its samples
with visible contrast (the edge as listed cannot reach 80 % coverage by any
method), and flags: another listed vertical edge within 3 px, the image
border within 5 px.

Precision side, per final detection not on listed edges (1 px, >= 80 %):
``listed within 2 px``, ``partly listed`` (20-80 % on listed edges: ends
running on beyond a true edge), ``3D vertical, unlisted`` (the bench's
depth-buffer test), else the materials of the face buffer 2.5 px either
side (wall|ground, roof|roof, tree|...).

Also the signed offset of detections from the true corner edges they match
within 3 px (positive towards the brighter side).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from obliq_colmap.lines import bilinear, edge_points, gradients
from obliq_colmap.synthetic import load_scene
from obliq_colmap.synthetic.city import MATERIAL_NAMES
from obliq_colmap.synthetic.render import render_depth
from obliq_colmap.synthetic.truth import vertical_edge_segments
from obliq_colmap.vanishing import (
    VanishingOptions,
    VPPrior,
    detect_vertical_vp,
    vertical_segments,
)

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from vanishing_scoring import (  # noqa: E402
    edge_contrast,
    on_line,
    step_contrast,
    union_coverage,
    vertical_in_3d,
    with_overrides,
)

CAUSES = (
    "no contrast",
    "final within 2 px",
    "final rule",
    "chain filters: length",
    "chain filters: density",
    "chain filters: RMS",
    "chain filters: several",
    "chain lost",
    "hysteresis",
    "D < low",
    "gradient angle",
    "NMS",
)


def vp_normal_field(vp: np.ndarray):
    """``normal_at`` of :func:`edge_points`: unit normal of the line to ``vp``."""
    vx, vy, vw = (float(c) for c in vp / np.abs(vp).max())

    def field(x, y, gx_, gy_):
        ux, uy = vx - x * vw, vy - y * vw
        n = np.maximum(np.sqrt(ux * ux + uy * uy), 1e-30)
        return (-uy / n).astype(np.float32), (ux / n).astype(np.float32)

    return field


def sample_edges(segs: np.ndarray, step: float = 1.0):
    """1-px samples of (M, 2, 2) segments.

    Returns
    -------
    P (K, 2) points, edge (K,) segment index, s (K,) position along it (px),
    t, n (M, 2) unit tangent and normal of each segment.
    """
    d = segs[:, 1] - segs[:, 0]
    L = np.linalg.norm(d, axis=1)
    t = d / np.maximum(L, 1e-9)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    cnt = np.maximum(np.floor(L / step).astype(int), 1)
    edge = np.repeat(np.arange(len(segs)), cnt)
    k = np.arange(len(edge)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    s = (k + 0.5) * (L / cnt)[edge]
    P = segs[edge, 0] + s[:, None] * t[edge]
    return P, edge, s, t, n


def covered_by_segments(segs, edge, s, det, tol):
    """(K,) bool: sample (edge, s) lies in the extent of a detection within tol."""
    if len(det) == 0 or len(segs) == 0:
        return np.zeros(len(edge), bool)
    _, lo, hi, close = on_line(segs, det, tol)
    ok = close & (hi > lo)
    cov = np.zeros(len(edge), bool)
    for m in np.unique(edge):
        j = np.flatnonzero(ok[m])
        if len(j) == 0:
            continue
        k = np.flatnonzero(edge == m)
        sk = s[k][:, None]
        cov[k] = np.any((sk >= lo[m, j] - 0.5) & (sk <= hi[m, j] + 0.5), axis=1)
    return cov


def near_points(P, edge, t, n, pts, across=1.0, along=0.75):
    """(K,) bool: an edge point lies within ``across`` / ``along`` of a sample."""
    if len(pts) == 0:
        return np.zeros(len(P), bool)
    tree = cKDTree(pts)
    hits = tree.query_ball_point(P, np.hypot(across, along))
    lens = np.array([len(h) for h in hits])
    if lens.sum() == 0:
        return np.zeros(len(P), bool)
    k = np.repeat(np.arange(len(P)), lens)
    q = pts[np.concatenate([h for h in hits if h])]
    r = q - P[k]
    ok = (np.abs(np.sum(r * n[edge[k]], axis=1)) <= across) & (
        np.abs(np.sum(r * t[edge[k]], axis=1)) <= along
    )
    out = np.zeros(len(P), bool)
    out[k[ok]] = True
    return out


def peak_derivative(gx, gy, field_vp, P, n_edge):
    """(K,) largest |D| within +-1.5 px across, and the gradient angle there (deg)."""
    offs = np.linspace(-1.5, 1.5, 13)
    Q = P[:, None] + offs[None, :, None] * n_edge[:, None]
    flat = Q.reshape(-1, 2)
    bx = bilinear(gx, flat).reshape(Q.shape[:2])
    by = bilinear(gy, flat).reshape(Q.shape[:2])
    nx, ny = field_vp(flat[:, 0], flat[:, 1], None, None)
    nx, ny = nx.reshape(Q.shape[:2]), ny.reshape(Q.shape[:2])
    D = np.abs(bx * nx + by * ny)
    i = np.argmax(D, axis=1)
    r = np.arange(len(P))
    mag = np.hypot(bx[r, i], by[r, i])
    ang = np.degrees(np.arccos(np.clip(D[r, i] / np.maximum(mag, 1e-9), 0, 1)))
    return D[r, i], ang


def side_materials(face_id, material_of_face, P, n_dir, offset=2.5):
    """(K,) material index on the + and - side (-1: nothing)."""
    H, W = face_id.shape
    out = []
    for sgn in (1.0, -1.0):
        Q = P + sgn * offset * n_dir
        col = np.clip(np.floor(Q[:, 0]).astype(int), 0, W - 1)
        row = np.clip(np.floor(Q[:, 1]).astype(int), 0, H - 1)
        f = face_id[row, col]
        out.append(np.where(f >= 0, material_of_face[np.maximum(f, 0)], -1))
    return out


def mat_name(m: int) -> str:
    return "none" if m < 0 else MATERIAL_NAMES[m]


def diagnose_image(scene, name, options, min_contrast, acc):
    im = next(i for i in scene.gt.images.values() if i.name == name)
    cam = scene.gt.cameras[im.camera_id]
    img = cv2.imread(str(scene.image_path(name)), cv2.IMREAD_GRAYSCALE)
    gray = img.astype(float)
    H, W = img.shape
    cam_l, pose_l = scene.camera_pose(name)
    depth, face_id = render_depth(scene.city, cam_l, pose_l)
    mat_face = scene.city.face_material

    r = detect_vertical_vp(img, options, camera=cam, prior=VPPrior.aerial())
    if r.vp is None:
        return
    F = r.vertical_segments.endpoints
    sp = options.second_pass
    # The second pass alone at the final VP (no competing-VP rule).
    B = vertical_segments(img, r.vp, sp, cam).endpoints
    relax = {"min_length_px": 0.0, "min_density": 0.0, "max_rms_px": 1.5}
    R = vertical_segments(img, r.vp, dataclasses.replace(sp, **relax), cam)
    R = R.endpoints
    # One filter off at a time.
    R1 = {
        k: vertical_segments(
            img, r.vp, dataclasses.replace(sp, **{k: v}), cam
        ).endpoints
        for k, v in relax.items()
    }
    gx, gy = gradients(img, sp.sigma_px)
    field = vp_normal_field(r.vp)
    p_low = edge_points(gx, gy, field, sp.low, sp.low, sp.max_gradient_angle_deg).xy
    eph = edge_points(gx, gy, field, sp.low, sp.high, sp.max_gradient_angle_deg)
    p_high = eph.xy

    # As synthetic.true_vertical_edges, on the depth buffer rendered above.
    edges = vertical_edge_segments(scene.vertical_edges, cam_l, pose_l, depth)
    segs, kind = edges["segments_undistorted"], np.asarray(edges["kind"])
    L = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
    target = (kind == "corner") & (L > 20)
    contrast = edge_contrast(img, edges["segments"])
    visible = target & (contrast >= min_contrast)
    tsegs = segs[visible]
    tid = np.flatnonzero(visible)
    acc["images"] += 1
    acc["targets"] += int(visible.sum())
    if len(tsegs) == 0:
        return

    # --- recall: edge level (the bench's criterion) ------------------------
    def edge_cov(det, tol):
        if len(det) == 0:
            return np.zeros(len(tsegs))
        _, lo, hi, close = on_line(tsegs, det, tol)
        return union_coverage(lo, hi, close, L[visible])

    cov1, cov2 = edge_cov(F, 1.0), edge_cov(F, 2.0)
    hit = cov1 >= 0.8
    acc["detected"] += int(hit.sum())

    # --- recall: samples ---------------------------------------------------
    P, e, s, t, n = sample_edges(tsegs)
    step = step_contrast(gray, P, t[e], n[e])
    has_contrast = step >= min_contrast
    cF1 = covered_by_segments(tsegs, e, s, F, 1.0)
    cF2 = covered_by_segments(tsegs, e, s, F, 2.0)
    cB = covered_by_segments(tsegs, e, s, B, 1.0)
    cR = covered_by_segments(tsegs, e, s, R, 1.0)
    cR1 = {k: covered_by_segments(tsegs, e, s, v, 1.0) for k, v in R1.items()}
    eh = near_points(P, e, t, n, p_high)
    el = near_points(P, e, t, n, p_low)
    pos_pts = near_points(P, e, t, n, p_high[eph.derivative > 0])
    neg_pts = near_points(P, e, t, n, p_high[eph.derivative < 0])
    dpk, ang = peak_derivative(gx, gy, field, P, n[e])
    cause = np.full(len(P), "", object)
    rules = [
        (~has_contrast, "no contrast"),
        (cF2, "final within 2 px"),
        (cB, "final rule"),
        (cR1["min_length_px"], "chain filters: length"),
        (cR1["min_density"], "chain filters: density"),
        (cR1["max_rms_px"], "chain filters: RMS"),
        (cR, "chain filters: several"),
        (eh, "chain lost"),
        (el, "hysteresis"),
        (dpk < sp.low, "D < low"),
        (ang > sp.max_gradient_angle_deg, "gradient angle"),
        (np.ones(len(P), bool), "NMS"),
    ]
    for mask, label in reversed(rules):
        cause[mask] = label
    cause[cF1] = "covered"

    # Neighbours: samples of the other listed vertical edges within 3 px.
    Pall, eall, _, _, _ = sample_edges(segs)
    tree = cKDTree(Pall)
    dist, j = tree.query(P, k=8, distance_upper_bound=3.0)
    other = np.isfinite(dist) & (eall[np.minimum(j, len(eall) - 1)] != tid[e][:, None])
    neighbour = other.any(axis=1)
    border = np.minimum.reduce([P[:, 0], W - P[:, 0], P[:, 1], H - P[:, 1]]) < 5.0

    m_plus, m_minus = side_materials(face_id, mat_face, P, n[e])
    for k in np.flatnonzero(~cF1 & ~hit[e]):
        acc["miss_px"][cause[k]] += 1
    for k in np.flatnonzero(~cF1 & hit[e]):
        acc["hit_uncovered_px"][cause[k]] += 1
    acc["target_px"] += len(P)
    acc["no_contrast_px"] += int((~has_contrast).sum())
    acc["no_contrast_px_on_missed"] += int((~has_contrast & ~hit[e]).sum())
    # The hysteresis / threshold margin of all visible-contrast samples.
    for lo_, hi_ in ((0, 2), (2, 4), (4, 6), (6, 8), (8, 1e9)):
        sel = has_contrast & (dpk >= lo_) & (dpk < hi_)
        acc["dpk_bins"][f"{lo_}-{hi_:g}"] = acc["dpk_bins"].get(
            f"{lo_}-{hi_:g}", [0, 0]
        )
        acc["dpk_bins"][f"{lo_}-{hi_:g}"][0] += int(sel.sum())
        acc["dpk_bins"][f"{lo_}-{hi_:g}"][1] += int((sel & cF1).sum())

    for m in np.flatnonzero(~hit):
        k = np.flatnonzero(e == m)
        unc = k[~cF1[k]]
        vis_k = k[has_contrast[k]]
        frac_vis_cov = cF1[vis_k].mean() if len(vis_k) else 0.0
        if cov2[m] >= 0.8:
            label = "final within 2 px"
        elif len(vis_k) and frac_vis_cov >= 0.8:
            label = "gt: no-contrast part"
        else:
            causes = [c for c in cause[unc] if c != "no contrast"] or ["no contrast"]
            label = Counter(causes).most_common(1)[0][0]
        extent = "none (< 20 % covered)" if cov1[m] < 0.2 else "partial"
        nb = bool(neighbour[unc].mean() > 0.5) if len(unc) else False
        acc["records"].append(
            {
                "image": name,
                "edge": int(tid[m]),
                "segment": tsegs[m].round(1).tolist(),
                "length_px": float(L[visible][m]),
                "coverage": float(cov1[m]),
                "coverage_2px": float(cov2[m]),
                "contrast": float(contrast[tid[m]]),
                "cause": label,
                "neighbour": nb,
                "uncovered_causes": dict(Counter(cause[unc])),
            }
        )
        acc["miss_cross"][f"{label} / {'neighbour' if nb else 'alone'}"] += 1
        # The polarity flips along the edge: strong points of both signs.
        if min(pos_pts[k].sum(), neg_pts[k].sum()) >= 3:
            acc["miss_flip"][label] += 1
        acc["miss_edges"][label][extent] = acc["miss_edges"][label].get(extent, 0) + 1
        if nb:
            acc["miss_flags"]["neighbour edge within 3 px"] += 1
        if border[k].any():
            acc["miss_flags"]["image border within 5 px"] += 1
        # Where the uncovered samples are: the ends or the middle.
        pos = s[unc] / L[visible][m]
        acc["miss_where"]["end 15 %"] += int(((pos < 0.15) | (pos > 0.85)).sum())
        acc["miss_where"]["middle"] += int(((pos >= 0.15) & (pos <= 0.85)).sum())
        # Materials either side of the uncovered samples.
        for kk in unc:
            pair = "|".join(sorted((mat_name(m_plus[kk]), mat_name(m_minus[kk]))))
            acc["miss_materials"][pair] += 1

    # --- localisation: signed offsets of detections near target edges -------
    if len(F):
        _, lo, hi, close3 = on_line(tsegs, F, 3.0)
        mm, jj = np.nonzero(close3 & (hi - lo > 5))
        mid = F[jj].mean(axis=1)
        off = np.sum((mid - tsegs[mm, 0]) * n[mm], axis=1)
        # Positive: the detection lies on the brighter side of the true edge.
        bright = np.sign(np.sum(r.vertical_segments.normal[jj] * n[mm], axis=1))
        so = off * bright
        acc["offsets"].extend(so.tolist())
        acc["offset_contrast"].extend(contrast[tid[mm]].tolist())

    # --- precision ------------------------------------------------------------
    if len(F) == 0:
        return
    Ld = np.linalg.norm(F[:, 1] - F[:, 0], axis=1)
    _, lo, hi, close = on_line(F, segs, 1.0)
    pc1 = union_coverage(lo, hi, close, Ld)
    _, lo, hi, close = on_line(F, segs, 2.0)
    pc2 = union_coverage(lo, hi, close, Ld)
    v3d = vertical_in_3d(F, cam_l, pose_l, depth)
    mid = F.mean(axis=1)
    dn = F[:, 1] - F[:, 0]
    nn = np.stack([-dn[:, 1], dn[:, 0]], axis=1) / np.maximum(Ld, 1e-9)[:, None]
    mp, mn = side_materials(face_id, mat_face, mid, nn)
    Pd = F[:, 0][:, None] + np.linspace(0.1, 0.9, 9)[None, :, None] * dn[:, None]
    step_d = step_contrast(
        gray, Pd.reshape(-1, 2), np.repeat(dn / Ld[:, None], 9, 0), np.repeat(nn, 9, 0)
    ).reshape(-1, 9)
    real = np.median(step_d, axis=1) >= min_contrast
    acc["det"] += len(F)
    acc["det_tp"] += int((pc1 >= 0.8).sum())
    acc["det_3d"] += int(v3d.sum())
    partial_overhang(F, segs, kind, pc1, face_id, mat_face, acc)
    tp = pc1 >= 0.8
    acc["det_class_3d"]["on listed edges / 3D"] += int((tp & v3d).sum())
    acc["det_class_3d"]["on listed edges / not 3D"] += int((tp & ~v3d).sum())
    for i in np.flatnonzero(pc1 < 0.8):
        if pc2[i] >= 0.8:
            label = "listed within 2 px"
        elif pc1[i] >= 0.2:
            label = "partly listed (20-80 %)"
        elif v3d[i]:
            label = "3D vertical, unlisted"
        else:
            label = "not vertical: " + "|".join(
                sorted((mat_name(mp[i]), mat_name(mn[i])))
            )
        acc["false"][label] += 1
        acc["det_class_3d"][
            label.split(":")[0] + (" / 3D" if v3d[i] else " / not 3D")
        ] += 1
        acc["false_real_edge"][label] += int(real[i])
        acc["false_len"].setdefault(label, []).append(float(Ld[i]))


def partial_overhang(F, segs, kind, pc1, face_id, mat_face, acc) -> None:
    """Where the detections 20-80 % on listed edges leave them.

    Per 1-px sample of such a detection: on a listed edge (1 px) or not; the
    uncovered samples are counted by place (the run touching the end nearer
    the image bottom, i.e. the wall's foot in these views, the top end, or
    inside) and by the materials 2.5 px either side.
    """
    part = np.flatnonzero((pc1 >= 0.2) & (pc1 < 0.8))
    if len(part) == 0:
        return
    D = F[part]
    P, e, s, t, n = sample_edges(D)
    cov = covered_by_segments(D, e, s, segs, 1.0)
    cov2 = covered_by_segments(D, e, s, segs, 2.0)
    bottom_first = D[:, 0, 1] > D[:, 1, 1]  # (n,) endpoint 0 is the image-bottom one
    mp, mn = side_materials(face_id, mat_face, P, n[e])
    kinds_on = Counter()
    _, lo, hi, close = on_line(D, segs, 1.0)
    for m in range(len(D)):
        j = np.flatnonzero(close[m] & (hi[m] > lo[m]))
        kinds_on[",".join(sorted(set(kind[j].tolist())))] += 1
        k = np.flatnonzero(e == m)
        c = cov[k]
        # Runs of uncovered samples touching either end.
        first_cov = np.argmax(c) if c.any() else len(c)
        last_cov = len(c) - 1 - np.argmax(c[::-1]) if c.any() else -1
        at0 = np.zeros(len(c), bool)
        at0[:first_cov] = True
        at1 = np.zeros(len(c), bool)
        at1[last_cov + 1 :] = True
        bot, top = (at0, at1) if bottom_first[m] else (at1, at0)
        inner = ~c & ~bot & ~top
        acc["partial_px"]["bottom end"] += int(bot.sum())
        acc["partial_px"]["top end"] += int(top.sum())
        acc["partial_px"]["inside (gap between listed pieces)"] += int(inner.sum())
        acc["partial_px"]["on listed edge"] += int(c.sum())
        acc["partial_px"]["uncovered but within 2 px"] += int((~c & cov2[k]).sum())
        acc["partial_overhang_px"].append(
            [float(bot.sum()), float(top.sum()), float(inner.sum()), float(len(c))]
        )
        for kk in k[~c]:
            pair = "|".join(sorted((mat_name(mp[kk]), mat_name(mn[kk]))))
            acc["partial_materials"][pair] += 1
    acc["partial_kinds"].update(kinds_on)


def new_acc() -> dict:
    return {
        "images": 0,
        "targets": 0,
        "detected": 0,
        "target_px": 0,
        "no_contrast_px": 0,
        "no_contrast_px_on_missed": 0,
        "miss_px": Counter(),
        "hit_uncovered_px": Counter(),
        "miss_edges": {c: {} for c in ("gt: no-contrast part",) + CAUSES},
        "miss_flags": Counter(),
        "miss_cross": Counter(),
        "miss_flip": Counter(),
        "det_class_3d": Counter(),
        "records": [],
        "miss_where": Counter(),
        "miss_materials": Counter(),
        "dpk_bins": {},
        "offsets": [],
        "offset_contrast": [],
        "det": 0,
        "det_tp": 0,
        "det_3d": 0,
        "false": Counter(),
        "false_real_edge": Counter(),
        "false_len": {},
        "partial_px": Counter(),
        "partial_overhang_px": [],
        "partial_materials": Counter(),
        "partial_kinds": Counter(),
    }


def report(acc: dict) -> dict:
    n_t, n_d = acc["targets"], acc["det"]
    miss = n_t - acc["detected"]
    out = {
        "images": acc["images"],
        "recall": acc["detected"] / max(n_t, 1),
        "targets": n_t,
        "missed": miss,
        "missed_edges_by_cause": {
            k: {
                "n": sum(v.values()),
                "share_of_targets": sum(v.values()) / max(n_t, 1),
                **v,
            }
            for k, v in acc["miss_edges"].items()
            if v
        },
        "missed_flags": dict(acc["miss_flags"]),
        "missed_by_cause_and_neighbour": dict(sorted(acc["miss_cross"].items())),
        "missed_with_polarity_flip": dict(acc["miss_flip"].most_common()),
        "detections_3d_vertical_by_class": dict(acc["det_class_3d"]),
        "uncovered_px_of_missed_edges": dict(acc["miss_px"].most_common()),
        "uncovered_px_of_detected_edges": dict(acc["hit_uncovered_px"].most_common()),
        "uncovered_px_where": dict(acc["miss_where"]),
        "uncovered_px_materials": dict(acc["miss_materials"].most_common(12)),
        "target_px": acc["target_px"],
        "no_contrast_share_of_target_px": acc["no_contrast_px"]
        / max(acc["target_px"], 1),
        "visible_px_by_peak_D": {
            k: {"px": v[0], "covered": v[1] / max(v[0], 1)}
            for k, v in acc["dpk_bins"].items()
        },
        "precision": acc["det_tp"] / max(n_d, 1),
        "precision_3d": acc["det_3d"] / max(n_d, 1),
        "detections": n_d,
        "false_by_class": {
            k: {
                "n": v,
                "share_of_detections": v / max(n_d, 1),
                "real_edge": acc["false_real_edge"][k] / v,
                "median_length_px": float(np.median(acc["false_len"][k])),
            }
            for k, v in acc["false"].most_common()
        },
    }
    ov = np.asarray(acc["partial_overhang_px"]).reshape(-1, 4)
    if len(ov):
        out["partly_listed"] = {
            "px": dict(acc["partial_px"]),
            "median_bottom_top_inside_length_px": np.median(ov, axis=0).tolist(),
            "share_with_bottom_overhang_gt_20pc": float(
                np.mean(ov[:, 0] > 0.2 * ov[:, 3])
            ),
            "share_with_top_overhang_gt_20pc": float(
                np.mean(ov[:, 1] > 0.2 * ov[:, 3])
            ),
            "share_with_inside_gap_gt_20pc": float(np.mean(ov[:, 2] > 0.2 * ov[:, 3])),
            "uncovered_materials": dict(acc["partial_materials"].most_common(10)),
            "listed_kinds_touched": dict(acc["partial_kinds"].most_common()),
        }
    o = np.asarray(acc["offsets"])
    c = np.asarray(acc["offset_contrast"])
    if len(o):
        rows = {}
        for name, sel in (
            ("all", np.ones(len(o), bool)),
            ("contrast < 30", c < 30),
            ("contrast 30-60", (c >= 30) & (c < 60)),
            ("contrast >= 60", c >= 60),
        ):
            x = o[sel]
            if len(x):
                rows[name] = {
                    "n": int(len(x)),
                    "p10_p50_p90_px": np.percentile(x, [10, 50, 90]).round(3).tolist(),
                    "share_1_to_3_px": float(np.mean(np.abs(x) > 1)),
                }
        out["offsets_towards_bright_side"] = rows
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", required=True)
    parser.add_argument("--every", type=int, default=1, help="every k-th image")
    parser.add_argument("--images", default=None, help="comma-separated names")
    parser.add_argument("--output", default=None)
    parser.add_argument("--set", action="append", default=[], metavar="PATH=VALUE")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    options = with_overrides(VanishingOptions(), args.set)
    scene = load_scene(args.scene)
    names = sorted(i.name for i in scene.gt.images.values())
    if args.images:
        names = args.images.split(",")
    names = names[:: args.every]
    min_contrast = 5.0 * np.sqrt(2.0) * max(scene.options.noise_sigma, 1.0)
    acc = new_acc()
    with threadpool_limits(1):
        for name in names:
            diagnose_image(scene, name, options, min_contrast, acc)
            print(name, "done", flush=True, file=sys.stderr)
    out = report(acc)
    print(json.dumps(out, indent=1))
    if args.output:
        out["missed_edges"] = acc["records"]
        Path(args.output).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
