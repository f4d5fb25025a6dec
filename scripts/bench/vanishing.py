#!/usr/bin/env python
"""Benchmarks of the vertical vanishing point stage (stage 1, obliq_colmap.vanishing).

Measures the vertical VP's accuracy and speed: the angular error of the
vertical direction on YorkUrbanDB (known K) and on Eurasian Cities (K
unknown), against the peer lu-vp-detect on the same images and machine; the
time per image at 640x480, 2004x1336 and 4008x2672 (optionally against
another source tree in the same process); and on a synthetic scene the
direction error and the second pass's recall and precision on the true
vertical edges. One thread everywhere (cv2.setNumThreads(1), BLAS via
threadpoolctl).

Run (from the repository root)::

    python scripts/bench/vanishing.py --sections yud,peer --split train
    python scripts/bench/vanishing.py --sections yud --set second_pass.weak_high=4
    python scripts/bench/vanishing.py --sections timing --reference /tmp/ref
    python scripts/bench/vanishing.py --sections synthetic \\
        --scene /work/scenes/paper_s1 [--synthetic_prior ins]

Figures: docs/STATUS.md (stage 1: error and time per image) and
docs/journal/stage1-vanishing.md.

Data: under ``/work/shared/data/``: ``yorkurbandb/`` (``yud_gt.json`` and the
images), ``eurasian_cities/`` (``ecd_gt.json`` and the images),
``rennes_oblique_aerial/images/`` (timing); the ``peer`` section needs the
``lu-vp-detect`` package (PyPI); ``synthetic`` a scene from ``obliq-colmap
synth``; ``--reference`` a source tree (``git archive REV obliq_colmap | tar
-x -C TREE``).

Sections (``--sections``, comma separated):

- ``yud``: YorkUrbanDB, known K: angular error of the vertical direction
  against the ground truth (median, mean, AUC at 1/2/5 deg) on ``--split``.
  Note: the GT ``vps_camera`` of yud_gt.json are in a y-up frame relative to
  the images (the labelled segments converge at K (x, -y, z)); they are the
  algebraic fit (smallest eigenvector of sum n n^T over the unit normals of
  the labelled segments' interpretation planes), verified here to 0.00 deg
  median. We also report the error against the maximum-likelihood VP of the
  same labelled segments ("ML-GT").
- ``peer``: lu-vp-detect (PyPI) on the same images, same machine (OpenCV 5
  adapter: its LSD returns (N, 4) where the package expects (N, 1, 4)).
- ``ecd``: Eurasian Cities, K unknown: mean angle between the labelled
  vertical segments and the lines from their midpoints to the estimated VP
  (parameter-free), with the dataset's own zenith as reference.
- ``timing``: time per image, both passes, at 640x480, 2004x1336 and
  4008x2672 (Rennes oblique aerial photos resampled), aerial prior, and on
  the 51 YorkUrbanDB training images (640x480); with ``--reference TREE`` (a
  copy of another revision, ``git archive REV | tar -x -C TREE``) that code
  runs alternately in the same process and the ratios are reported.
- ``synthetic``: a scene of ``obliq_colmap.synthetic`` (``--scene``): vertical
  direction error with the TRUE intrinsics and with the priors' focal;
  second-pass recall on visible building-corner edges longer than 20 px and
  precision against all true vertical edges (within 1 px, overlap >= 80%);
  also the recall with each corner cut to its extent with visible contrast
  (``contrast_extent``: ends where both sides have the same grey cannot be
  located by any method) and the precision counting a detection on listed
  edges or on unlisted vertical 3D structure (``vertical_in_3d``). The
  prior is the paper's aerial one, or with ``--synthetic_prior ins`` the
  INS prior ``register`` uses: each image's prior rotation with the cone
  ``PipelineOptions.cone_deg`` gives for the scene's prior noise. The
  scoring is in ``vanishing_scoring.py``.

``--set PATH=VALUE`` (repeatable) overrides one field of ``VanishingOptions``
(dotted path into the nested options, VALUE a Python literal) for ablations.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from obliq_colmap.geometry import Camera
from obliq_colmap.vanishing import (
    VanishingOptions,
    VPPrior,
    detect_vertical_vp,
    refine_vp,
)

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from reference import load_reference  # noqa: E402
from vanishing_scoring import (  # noqa: E402
    edge_contrast,
    on_line,
    step_contrast,
    union_coverage,
    vertical_in_3d,
    with_overrides,
)

DATA = Path("/work/shared/data")


def angle_deg(a, b) -> float:
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))


def auc(errors, threshold_deg) -> float:
    """Area under the recall-vs-error curve up to the threshold, normalised."""
    e = np.sort(np.asarray(errors, float))
    xs = np.linspace(0, threshold_deg, 2001)
    ys = np.searchsorted(e, xs, side="right") / len(e)
    return float(np.trapezoid(ys, xs) / threshold_deg)


def summary(errors, times=None) -> dict:
    e = np.asarray(errors, float)
    out = {
        "n": int(len(e)),
        "median_deg": float(np.median(e)),
        "mean_deg": float(e.mean()),
        "p95_deg": float(np.percentile(e, 95)),
        "auc1": auc(e, 1),
        "auc2": auc(e, 2),
        "auc5": auc(e, 5),
    }
    if times is not None:
        out["time_ms_median"] = 1000 * float(np.median(times))
    return out


# --------------------------------------------------------------------------
# YorkUrbanDB
# --------------------------------------------------------------------------


def yud_gt(split: str) -> tuple[np.ndarray, list[dict]]:
    """YUD's K (3, 3) and the ``yud_gt.json`` entries of one split."""
    gt = json.loads((DATA / "yorkurbandb" / "yud_gt.json").read_text())
    return np.array(gt["K"]), [im for im in gt["images"] if im["split"] == split]


def yud_images(split: str):
    root = DATA / "yorkurbandb"
    K, entries = yud_gt(split)
    for im in entries:
        img = cv2.imread(
            str(root / im["name"] / f"{im['name']}.jpg"), cv2.IMREAD_GRAYSCALE
        )
        # The GT frame has y up relative to the image (see the docstring).
        g = np.array(im["vps_camera"][im["vertical_index"]]) * [1, -1, 1]
        lines = np.array(im["lines"])
        vert = lines[lines[:, 4] == im["vertical_index"] + 1, :4].reshape(-1, 2, 2)
        yield im["name"], img, K, g, vert


def _normaliser(width: int, height: int) -> np.ndarray:
    """T mapping pixels to centred coordinates scaled by half the longer
    side: the normalisation the vanishing stage fits VPs in."""
    s = max(width, height) / 2.0
    return np.array(
        [[1 / s, 0, -width / 2 / s], [0, 1 / s, -height / 2 / s], [0, 0, 1.0]]
    )


def ml_gt(vert_px, K, g):
    """ML VP of the labelled vertical segments, as a direction (camera frame)."""
    from obliq_colmap.lines import scatter_matrices

    T = _normaliser(640, 480)
    en = vert_px @ T[:2, :2].T + T[:2, 2]
    S = scatter_matrices(en.reshape(-1, 2), np.repeat(np.arange(len(en)), 2), len(en))
    v0 = T @ (K @ g)
    v, *_ = refine_vp(S, v0 / np.linalg.norm(v0))
    d = np.linalg.solve(K, np.linalg.inv(T) @ v)
    return d / np.linalg.norm(d)


def orthogonal_gt_vs_gt(split: str) -> list[float]:
    """Angle (deg) between each GT vertical and the GT's orthogonalised triplet.

    The GT VPs are fitted one by one and are not orthogonal; a Manhattan-frame
    estimate disagrees with the GT vertical by about this much by construction.
    """
    return [
        min(
            angle_deg(im["vps_camera"][im["vertical_index"]], o)
            for o in im["vps_orthogonal_camera"]
        )
        for im in yud_gt(split)[1]
    ]


def bench_yud(split: str, options: VanishingOptions) -> dict:
    errs, errs_ml, times, status = [], [], [], {}
    for _, img, K, g, vert in yud_images(split):
        # YUD's MATLAB pixels (1-based) to COLMAP's: subtract 0.5.
        cam = Camera(
            "PINHOLE", 640, 480, [K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5]
        )
        t = time.perf_counter()
        r = detect_vertical_vp(img, options, camera=cam)
        times.append(time.perf_counter() - t)
        status[r.status] = status.get(r.status, 0) + 1
        n = r.vertical_direction
        errs.append(90.0 if n is None else angle_deg(n, g))
        errs_ml.append(90.0 if n is None else angle_deg(n, ml_gt(vert, K, g)))
    return {
        "vs_gt": summary(errs, times),
        "vs_ml_gt": summary(errs_ml),
        "status": status,
        "gt_self_check_orthogonal_gt_vs_gt": summary(orthogonal_gt_vs_gt(split)),
        "gt_self_check_ml_gt_vs_gt": summary(
            [angle_deg(ml_gt(v, K, g), g) for _, _, K, g, v in yud_images(split)]
        ),
    }


class _Cv2Lsd4to1:
    """cv2 proxy whose LSD returns (N, 1, 4) as lu-vp-detect expects (OpenCV 5)."""

    def __getattr__(self, name):
        return getattr(cv2, name)

    @staticmethod
    def createLineSegmentDetector(*args):
        lsd = cv2.createLineSegmentDetector(*args)

        class Wrapped:
            def detect(self, img):
                out = list(lsd.detect(img))
                out[0] = (
                    np.zeros((0, 1, 4), np.float32)
                    if out[0] is None
                    else out[0].reshape(-1, 1, 4)
                )
                return tuple(out)

        return Wrapped()


def lu_vertical(img, f, pp):
    """Vertical VP of lu-vp-detect as a pixel-homogeneous point, or None."""
    import lu_vp_detect.vp_detection as lu

    lu.cv2 = _Cv2Lsd4to1()
    det = lu.VPDetection(length_thresh=30, principal_point=pp, focal_length=f, seed=0)
    vps = det.find_vps(img)  # (3, 3) unit directions, vertical last
    if vps is None or not np.all(np.isfinite(vps)):
        return None
    # Their frame: pixel = f (x, -y)/z + pp? Use their 2D VPs to stay neutral.
    v2 = np.asarray(det.vps_2D, float)
    K = np.array([[f, 0, pp[0]], [0, f, pp[1]], [0, 0, 1.0]])
    dirs = np.linalg.solve(K, np.hstack([v2, np.ones((3, 1))]).T).T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    k = int(np.argmax(np.abs(dirs[:, 1])))  # the most vertical of the three
    return np.append(v2[k], 1.0)


def bench_peer_yud(split: str) -> dict:
    errs, times = [], []
    for _, img, K, g, _ in yud_images(split):
        t = time.perf_counter()
        v = lu_vertical(img, K[0, 0], (K[0, 2], K[1, 2]))
        times.append(time.perf_counter() - t)
        errs.append(90.0 if v is None else angle_deg(np.linalg.solve(K, v), g))
    return summary(errs, times)


# --------------------------------------------------------------------------
# Eurasian Cities
# --------------------------------------------------------------------------


def ecd_error(vp, segs) -> float:
    """Mean angle (deg) between segments and the lines midpoint -> VP."""
    vp = np.asarray(vp, float)
    mid = segs.mean(axis=1)
    d = segs[:, 1] - segs[:, 0]
    u = vp[:2][None] - mid * vp[2]
    cross = d[:, 0] * u[:, 1] - d[:, 1] * u[:, 0]
    dot = np.sum(d * u, axis=1)
    ang = np.degrees(np.abs(np.arctan2(cross, dot)))
    return float(np.mean(np.minimum(ang, 180 - ang)))


def bench_ecd(options: VanishingOptions, peer: bool) -> dict:
    root = DATA / "eurasian_cities"
    gt = json.loads((root / "ecd_gt.json").read_text())
    ours, ref, lu_errs, times = [], [], [], []
    status = {}
    for im in gt["images"]:
        img = cv2.imread(str(root / im["name"]), cv2.IMREAD_GRAYSCALE)
        lines = np.array(im["lines"])
        segs = lines[lines[:, 4] == 1, :4].reshape(-1, 2, 2) - 0.5  # MATLAB -> COLMAP
        ref.append(ecd_error(np.append(np.array(im["zenith"]) - 0.5, 1.0), segs))
        t = time.perf_counter()
        r = detect_vertical_vp(img, options)  # K unknown, prior "none"
        times.append(time.perf_counter() - t)
        status[r.status] = status.get(r.status, 0) + 1
        ours.append(90.0 if r.vp is None else ecd_error(r.vp, segs))
        if peer:
            h, w = img.shape
            v = lu_vertical(img, 1.2 * max(w, h), (w / 2, h / 2))  # focal guessed
            lu_errs.append(90.0 if v is None else ecd_error(v + [0.5, 0.5, 0], segs))
    out = {
        "ours": {
            "n": len(ours),
            "median_deg": float(np.median(ours)),
            "mean_deg": float(np.mean(ours)),
            "time_ms_median": 1000 * float(np.median(times)),
            "status": status,
        },
        "dataset_zenith": {
            "median_deg": float(np.median(ref)),
            "mean_deg": float(np.mean(ref)),
        },
    }
    if peer:
        out["lu_vp_detect"] = {
            "median_deg": float(np.median(lu_errs)),
            "mean_deg": float(np.mean(lu_errs)),
        }
    return out


# --------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------


def _timing_jobs():
    """(set name, image, camera parameters or None, prior kind) to time."""
    files = sorted((DATA / "rennes_oblique_aerial" / "images").glob("*.jpg"))
    for size in [(640, 480), (2004, 1336), (4008, 2672)]:
        for f in files:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            interp = cv2.INTER_AREA if size[0] < img.shape[1] else cv2.INTER_CUBIC
            yield (
                f"{size[0]}x{size[1]}",
                f.name,
                cv2.resize(img, size, interpolation=interp),
                None,
                "aerial",
            )
    for name, img, K, _, _ in yud_images("train"):
        params = [K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5]
        yield "yud_train_640x480", name, img, params, "none"


def bench_timing(
    options: VanishingOptions, repeats: int = 3, reference: Path | None = None
) -> dict:
    """Time per image, both passes: the best of ``repeats`` runs per image.

    Sets: the Rennes oblique photos resampled to 640x480, 2004x1336 and
    4008x2672 (aerial prior) and the 51 YorkUrbanDB training images (640x480,
    known K, no prior). With ``reference`` (a source tree) its code runs
    alternately with this one on each image, and the ratios are reported.
    """
    versions = [("ours", detect_vertical_vp, VPPrior, Camera, options)]
    if reference is not None:
        ref_v, ref_g = load_reference(reference, ("vanishing", "geometry"))
        versions.append(
            (
                "reference",
                ref_v.detect_vertical_vp,
                ref_v.VPPrior,
                ref_g.Camera,
                ref_v.VanishingOptions(),
            )
        )
    best: dict = {}
    parts: dict = {}
    out: dict = {"status": {}}
    for set_name, name, img, params, prior_kind in _timing_jobs():
        H, W = img.shape
        for _ in range(repeats):
            for tag, detect, prior_cls, cam_cls, opts in versions:
                cam = None if params is None else cam_cls("PINHOLE", W, H, params)
                prior = prior_cls.aerial() if prior_kind == "aerial" else None
                t = time.perf_counter()
                r = detect(img, opts, camera=cam, prior=prior)
                dt = time.perf_counter() - t
                key = (set_name, name, tag)
                best[key] = min(best.get(key, np.inf), dt)
                for k, v in r.time_s.items():
                    parts.setdefault((set_name, tag), {}).setdefault(k, []).append(v)
                if tag == "ours" and not set_name.startswith("yud"):
                    n_sp = (
                        0 if r.vertical_segments is None else len(r.vertical_segments)
                    )
                    out["status"][f"{name}@{W}"] = (
                        f"{r.status}, {r.n_inliers} inliers, {n_sp} segments"
                    )
    for set_name in dict.fromkeys(k[0] for k in best):
        row = {}
        for tag, *_ in versions:
            t = np.array(
                [v for k, v in best.items() if k[0] == set_name and k[2] == tag]
            )
            row[tag] = {
                "time_s_median_of_best": float(np.median(t)),
                "parts_s_median": {
                    k: float(np.median(v)) for k, v in parts[(set_name, tag)].items()
                },
            }
        if reference is not None:
            a = np.array(
                [v for k, v in best.items() if k[0] == set_name and k[2] == "ours"]
            )
            b = np.array(
                [v for k, v in best.items() if k[0] == set_name and k[2] == "reference"]
            )
            row["ratio_ours_over_reference"] = {
                "of_sums": float(a.sum() / b.sum()),
                "median_per_image": float(np.median(a / b)),
            }
        out[set_name] = row
    out["load_average_after"] = os.getloadavg()
    return out


# --------------------------------------------------------------------------
# Synthetic scene
# --------------------------------------------------------------------------


def contrast_extent(img, segs, segs_undistorted, min_contrast):
    """(M, 2, 2) the part of each segment between its first and last pixel
    with visible contrast (``step_contrast`` >= min_contrast), undistorted.

    An edge's ends where both sides have the same grey (a wall's top against
    pavement of its own brightness) cannot be located by any method; gaps
    inside the extent still count (a line detector can bridge them). Rows
    without any such pixel are NaN. Samples every pixel of the rendered
    (distorted) segment; the extent is mapped to the undistorted one by the
    same fractions.
    """
    out = np.full(segs.shape, np.nan)
    d = segs[:, 1] - segs[:, 0]
    L = np.linalg.norm(d, axis=1)
    cnt = np.maximum(np.floor(L).astype(int), 1)
    edge = np.repeat(np.arange(len(segs)), cnt)
    k = np.arange(len(edge)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    f = (k + 0.5) / cnt[edge]
    t = d / np.maximum(L, 1e-9)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    P = segs[edge, 0] + f[:, None] * d[edge]
    ok = step_contrast(img.astype(float), P, t[edge], n[edge]) >= min_contrast
    if not ok.any():
        return out
    f_lo = np.full(len(segs), np.inf)
    f_hi = np.full(len(segs), -np.inf)
    np.minimum.at(f_lo, edge[ok], f[ok] - 0.5 / cnt[edge[ok]])
    np.maximum.at(f_hi, edge[ok], f[ok] + 0.5 / cnt[edge[ok]])
    has = np.isfinite(f_lo)
    du = segs_undistorted[:, 1] - segs_undistorted[:, 0]
    out[has, 0] = segs_undistorted[has, 0] + f_lo[has, None] * du[has]
    out[has, 1] = segs_undistorted[has, 0] + f_hi[has, None] * du[has]
    return out


def _ins_cone_deg(scene) -> float:
    """The VP cone ``register`` uses for the scene's prior noise."""
    from obliq_colmap.pipeline import PipelineOptions
    from obliq_colmap.registration import RegistrationOptions

    o = scene.options
    return PipelineOptions(
        registration=RegistrationOptions(
            prior_rotation_sigma_deg=o.prior_rotation_deg,
            prior_focal_sigma=o.prior_focal_percent / 100.0,
        )
    ).cone_deg


def bench_synthetic(
    scene_path: str, options: VanishingOptions, prior_kind: str = "aerial"
) -> dict:
    from obliq_colmap.synthetic import load_scene, true_vertical_edges, true_vertical_vp

    scene = load_scene(scene_path)
    cone = _ins_cone_deg(scene)
    errs_true, errs_prior, recalls, precisions, times, n_sp, n_in = (
        [],
        [],
        [],
        [],
        [],
        [],
        [],
    )
    recalls_vis, recalls_ext, precisions_3d, precisions_any, per_image = (
        [],
        [],
        [],
        [],
        {},
    )
    # Visible contrast: the median step across a true edge (2 px either side)
    # exceeds 5 standard deviations of the difference of two noisy pixels.
    min_contrast = 5.0 * np.sqrt(2.0) * max(scene.options.noise_sigma, 1.0)
    prior_by_name = {im.name: im for im in scene.priors.images.values()}
    for im in scene.gt.images.values():
        name = im.name
        cam_true = scene.gt.cameras[im.camera_id]
        pim = prior_by_name[name]
        cam_prior = scene.priors.cameras[pim.camera_id]
        img = cv2.imread(str(scene.image_path(name)), cv2.IMREAD_GRAYSCALE)
        vp_true = true_vertical_vp(scene, name)
        n_true = np.linalg.solve(cam_true.K, vp_true)
        t = time.perf_counter()
        prior = (
            VPPrior.from_rotation(pim.cam_from_world.rotation, cone)
            if prior_kind == "ins"
            else VPPrior.aerial()
        )
        r = detect_vertical_vp(img, options, camera=cam_true, prior=prior)
        times.append(time.perf_counter() - t)
        errs_true.append(
            90.0
            if r.vp is None
            else angle_deg(np.linalg.solve(cam_true.K, r.vp), n_true)
        )
        if r.vp is not None:
            # The same VP read with the priors' (slightly wrong) intrinsics.
            errs_prior.append(angle_deg(np.linalg.solve(cam_prior.K, r.vp), n_true))
        n_in.append(r.n_inliers)
        edges = true_vertical_edges(scene, name)
        segs = edges["segments_undistorted"]
        kind = np.asarray(edges["kind"])
        det = (
            r.vertical_segments.endpoints
            if r.vertical_segments is not None
            else np.zeros((0, 2, 2))
        )
        n_sp.append(len(det))
        L = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
        target = (kind == "corner") & (L > 20)
        contrast = edge_contrast(img, edges["segments"])  # as rendered
        visible = target & (contrast >= min_contrast)
        for mask, out in ((target, recalls), (visible, recalls_vis)):
            if mask.any() and len(det):
                _, lo, hi, close = on_line(segs[mask], det)
                out.append(
                    float(np.mean(union_coverage(lo, hi, close, L[mask]) >= 0.8))
                )
            elif mask.any():
                out.append(0.0)
        # The same corners, each cut to its extent with visible contrast
        # (still > 20 px): the coverage asked of the detector is only where
        # the edge can be seen at all.
        ext = contrast_extent(img, edges["segments"], segs, min_contrast)
        Le = np.linalg.norm(ext[:, 1] - ext[:, 0], axis=1)
        ext_t = visible & np.isfinite(Le) & (Le > 20)
        if ext_t.any():
            cov = np.zeros(int(ext_t.sum()))
            if len(det):
                _, lo, hi, close = on_line(ext[ext_t], det)
                cov = union_coverage(lo, hi, close, Le[ext_t])
            recalls_ext.append(float(np.mean(cov >= 0.8)))
        on_listed = np.zeros(len(det), bool)
        if len(det) and len(segs):
            # Precision: a detection counts when >= 80% of it lies within 1 px
            # of true vertical edges (any kind).
            _, lo, hi, close = on_line(det, segs)
            Ld = np.linalg.norm(det[:, 1] - det[:, 0], axis=1)
            on_listed = union_coverage(lo, hi, close, Ld) >= 0.8
            precisions.append(float(np.mean(on_listed)))
        if len(det):
            cam_l, pose_l = scene.camera_pose(name)
            v3d = vertical_in_3d(det, cam_l, pose_l, scene.depth(name))
            precisions_3d.append(float(np.mean(v3d)))
            # On listed edges or on unlisted vertical 3D structure.
            precisions_any.append(float(np.mean(v3d | on_listed)))
        per_image[name] = {
            "error_deg": errs_true[-1],
            "recall_visible": recalls_vis[-1] if visible.any() else None,
            "precision": precisions[-1] if len(det) and len(segs) else None,
        }
    e = np.asarray(errs_true)
    return {
        "n_images": len(e),
        "prior": prior_kind if prior_kind == "aerial" else f"ins, cone {cone:.2f} deg",
        "direction_true_K": {
            "median_deg": float(np.median(e)),
            "p95_deg": float(np.percentile(e, 95)),
            "max_deg": float(e.max()),
        },
        "direction_prior_K": {
            "median_deg": float(np.median(errs_prior)),
            "p95_deg": float(np.percentile(errs_prior, 95)),
        },
        "second_pass_recall_corners_gt20px": float(np.mean(recalls))
        if recalls
        else None,
        "second_pass_recall_visible_corners_gt20px": float(np.mean(recalls_vis))
        if recalls_vis
        else None,
        "second_pass_recall_visible_extent_gt20px": float(np.mean(recalls_ext))
        if recalls_ext
        else None,
        "visible_contrast_min": min_contrast,
        "second_pass_precision": float(np.mean(precisions)) if precisions else None,
        "second_pass_precision_3d_vertical": float(np.mean(precisions_3d))
        if precisions_3d
        else None,
        "second_pass_precision_listed_or_3d": float(np.mean(precisions_any))
        if precisions_any
        else None,
        "per_image": per_image,
        "first_pass_inliers_median": float(np.median(n_in)),
        "second_pass_segments_median": float(np.median(n_sp)),
        "time_s_median": float(np.median(times)),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sections", default="yud,peer,ecd,timing")
    parser.add_argument("--split", default="train", choices=["train", "test"])
    parser.add_argument("--scene", default=None, help="synthetic scene folder")
    parser.add_argument(
        "--synthetic_prior",
        default="aerial",
        choices=["aerial", "ins"],
        help="synthetic: the paper's aerial prior, or register's INS prior",
    )
    parser.add_argument("--output", default=None, help="write the figures as JSON")
    parser.add_argument(
        "--reference",
        default=None,
        help="timing: a source tree (git archive) timed alternately with this code",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timing: runs per image")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="override an option, e.g. second_pass.weak_high=4 (repeatable)",
    )
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    options = with_overrides(VanishingOptions(), args.set)
    sections = args.sections.split(",")
    results = {
        "machine": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "split": args.split,
        "overrides": args.set,
        "load_average_start": os.getloadavg(),
    }
    with threadpool_limits(1):
        if "yud" in sections:
            results["yud"] = bench_yud(args.split, options)
            print("YUD", args.split, json.dumps(results["yud"], indent=1), flush=True)
        if "peer" in sections:
            results["yud_lu_vp_detect"] = bench_peer_yud(args.split)
            print(
                "lu-vp-detect",
                json.dumps(results["yud_lu_vp_detect"], indent=1),
                flush=True,
            )
            if "yud" in results:
                a, b = results["yud"]["vs_gt"], results["yud_lu_vp_detect"]
                results["yud_ratio_ours_over_lu"] = {
                    "median_error": a["median_deg"] / b["median_deg"],
                    "mean_error": a["mean_deg"] / b["mean_deg"],
                    "time": a["time_ms_median"] / b["time_ms_median"],
                }
                print("ratios", results["yud_ratio_ours_over_lu"], flush=True)
        if "ecd" in sections:
            results["ecd"] = bench_ecd(options, peer="peer" in sections)
            print("ECD", json.dumps(results["ecd"], indent=1), flush=True)
        if "timing" in sections:
            results["timing"] = bench_timing(
                options, args.repeats, Path(args.reference) if args.reference else None
            )
            print("timing", json.dumps(results["timing"], indent=1), flush=True)
        if "synthetic" in sections:
            if not args.scene:
                parser.error("the synthetic section needs --scene")
            results["synthetic"] = bench_synthetic(
                args.scene, options, args.synthetic_prior
            )
            print("synthetic", json.dumps(results["synthetic"], indent=1), flush=True)
    if args.output:
        Path(args.output).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
