"""Benchmark of the initial registration (stage 2) on synthetic scenes.

For each scene folder (``obliq-colmap synth``) and each setting, every image
goes through the chain of ``register --stop_after initial``: the vertical VP
with the INS prior from the (rough) prior rotation (cone 3 sigma + 1 deg),
the VP-constrained vertical segments, :func:`registration.register_image`
(undistorted segments; a failed VP falls back to the prior's vertical and all
first-pass segments), then the rescue of weak images (< 20 inlier corners)
from the ground heights of the confident ones
(:func:`obliq_colmap.pipeline.rescue_heights`). The result (pose and refined
focal length) is scored with :func:`obliq_colmap.evaluate.evaluate_block`
across the projected verticals (what one image can observe). Printed per
setting: the fraction of images with a mean deviation below 2 px and 5 px
after one pass and after the rescue; the median inlier ratio, RANSAC trials,
time per image of the registration alone (median / max) and of the VP stage.

Segments (``--segments``):

- ``det``: the full vanishing stage (default; what the pipeline does);
- ``sp``: the vanishing stage's second pass run on the TRUE vertical VP; this
  isolates the registration from VP errors.

Priors: the scene's own ``priors/`` model, or with ``--sweep`` new priors drawn
from the ground truth (position, rotation and focal errors as in
``synthetic.cameras.prior_block``: 47 m datum offset, 5 m height noise), and a
map with a given discrepancy rate (a third each of buildings shifted by 1 m,
missing from the map, and demolished, i.e. mapped but not in the scene).

Example::

    OMP_NUM_THREADS=1 python scripts/bench_registration.py \\
        --scene /tmp/syn/paper /tmp/syn/paper2 --sweep scene default large
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import scipy.ndimage  # noqa: E402, F401  (imported once, as in a worker,
import scipy.optimize  # noqa: E402, F401  not timed with the first image)
from shapely import affinity  # noqa: E402

from obliq_colmap.cadastre import load_cadastre, write_geojson  # noqa: E402
from obliq_colmap.colmap_io import Block, ImageRecord  # noqa: E402
from obliq_colmap.evaluate import EvaluateOptions, evaluate_block  # noqa: E402
from obliq_colmap.geometry import Camera, Pose, rotation_from_axis_angle  # noqa: E402
from obliq_colmap.pipeline import rescue_heights  # noqa: E402
from obliq_colmap.registration import (  # noqa: E402
    RegistrationOptions,
    register_image,
)
from obliq_colmap.synthetic import load_scene, true_vertical_vp  # noqa: E402
from obliq_colmap.vanishing import (  # noqa: E402
    VanishingOptions,
    VPPrior,
    detect_vertical_vp,
    vertical_segments,
)

cv2.setNumThreads(1)

#: name -> (position sigma m, rotation sigma deg, focal error %, map discrepancy)
SETTINGS = {
    "scene": None,  # the scene's own priors and map
    "default": (8.0, 1.5, 3.0, 0.0),
    "large": (20.0, 3.0, 3.0, 0.10),
}
SWEEPS = {
    "position": [(p, 1.5, 3.0, 0.0) for p in (2.0, 8.0, 15.0, 30.0)],
    "rotation": [(8.0, r, 3.0, 0.0) for r in (0.5, 1.5, 3.0, 5.0)],
    "focal": [(8.0, 1.5, f, 0.0) for f in (0.0, 3.0, 6.0, 10.0)],
    "map": [(8.0, 1.5, 3.0, d) for d in (0.0, 0.05, 0.10, 0.20)],
}
#: One factor at a time, the default's own value left out (it is "default").
REDUCED = {
    "position": [(p, 1.5, 3.0, 0.0) for p in (2.0, 15.0, 30.0)],
    "rotation": [(8.0, r, 3.0, 0.0) for r in (0.5, 3.0, 5.0)],
    "focal": [(8.0, 1.5, f, 0.0) for f in (0.0, 6.0, 10.0)],
    "map": [(8.0, 1.5, 3.0, d) for d in (0.10, 0.20)],
}


def segments_for(scene, name, camera, prior, cone_deg, mode):
    """Undistorted vertical segments, vertical direction (None: VP failed) and
    the VP stage's time of one image."""
    gray = cv2.imread(str(scene.image_path(name)), cv2.IMREAD_GRAYSCALE)
    tcam, tpose = scene.camera_pose(name)
    t = time.perf_counter()
    if mode == "sp":
        sp = vertical_segments(gray, true_vertical_vp(scene, name), camera=tcam)
        n = np.linalg.solve(camera.K, true_vertical_vp(scene, name))
        return sp.endpoints, n / np.linalg.norm(n), time.perf_counter() - t
    vp_prior = VPPrior.from_rotation(prior.rotation, cone_deg)
    r = detect_vertical_vp(gray, VanishingOptions(), camera, vp_prior, 0)
    dt = time.perf_counter() - t
    if r.status == "ok" and r.vertical_segments is not None:
        return r.vertical_segments.endpoints, r.vertical_direction, dt
    return r.segments.endpoints, None, dt


def make_priors(gt_local: Block, pos_m, rot_deg, focal_pct, seed) -> Block:
    rng = np.random.default_rng(seed)
    out = Block()
    for cid, cam in gt_local.cameras.items():
        p = focal_pct / 100.0
        rel = rng.uniform(0.5 * p, p) * rng.choice([-1.0, 1.0]) if p > 0 else 0.0
        f = cam.K[0, 0] * (1.0 + rel)
        out.cameras[cid] = Camera(
            "PINHOLE",
            cam.width,
            cam.height,
            [f, f, cam.width / 2.0, cam.height / 2.0],
            cid,
        )
    for iid, im in gt_local.images.items():
        c = im.cam_from_world.center + rng.normal(0, 1, 3) * [pos_m, pos_m, 5.0]
        c[2] += 47.0
        R = (
            rotation_from_axis_angle(rng.normal(0, np.radians(rot_deg), 3))
            @ im.cam_from_world.rotation
        )
        pose = Pose.from_center(R, c)
        out.images[iid] = ImageRecord(iid, im.name, im.camera_id, pose)
    return out


def make_map(scene, rate, seed, folder: Path):
    """The scene's map with extra discrepancies (shifted, missing, demolished)."""
    cad = load_cadastre(scene.path / "cadastre.geojson", origin=scene.origin)
    if rate <= 0:
        return cad
    rng = np.random.default_rng(seed)
    polys = cad.absolute_polygons()
    n = len(polys)
    k = int(round(rate * n / 3))
    pick = rng.permutation(n)
    shifted, missing, demolished = pick[:k], pick[k : 2 * k], pick[2 * k : 3 * k]
    out = []
    for i, p in enumerate(polys):
        if i in set(missing.tolist()):
            continue
        if i in set(shifted.tolist()):
            a = rng.uniform(0, 2 * np.pi)
            p = affinity.translate(p, np.cos(a), np.sin(a))
        out.append(p)
    for i in demolished:  # a mapped building that is not there: a copy elsewhere
        out.append(affinity.translate(polys[i], *rng.uniform(-40, 40, 2)))
    path = folder / f"map_{rate:.2f}_{seed}.geojson"
    write_geojson(path, out, crs=cad.crs)
    return load_cadastre(path, origin=scene.origin)


def fallback(opts: RegistrationOptions) -> RegistrationOptions:
    """Options when the vertical comes from the prior (as the pipeline)."""
    tol = max(opts.vp_tolerance_deg, 2.0 * opts.prior_rotation_sigma_deg)
    return dataclasses.replace(opts, vp_tolerance_deg=tol)


def run_setting(scene, priors_local, cad, opts, mode, min_inliers=20):
    cone = 3.0 * opts.prior_rotation_sigma_deg + 1.0
    results, times, cpu, vp_times, inputs = {}, [], [], [], {}
    for im in sorted(priors_local.images.values(), key=lambda i: i.name):
        cam = priors_local.cameras[im.camera_id]
        seg, n, dt = segments_for(scene, im.name, cam, im.cam_from_world, cone, mode)
        vp_times.append(dt)
        o = opts if n is not None else fallback(opts)
        inputs[im.name] = (seg, n, o)
        t, tc = time.perf_counter(), time.process_time()
        r = register_image(
            seg, n, cam, im.cam_from_world, cad, o, segments_undistorted=True
        )
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - tc)
        results[im.name] = r
    # Rescue (as the pipeline): weak images from each confident ground height.
    heights = rescue_heights(
        list(results.values()), min_inliers, opts.coarse_height_step_m
    )
    results2 = dict(results)
    rerun = 0
    for im in priors_local.images.values():
        r = results[im.name]
        seg, n, o = inputs[im.name]
        if r.num_inliers >= min_inliers or len(heights) == 0:
            continue
        rerun += 1
        for h in heights:
            r2 = register_image(
                seg,
                n,
                priors_local.cameras[im.camera_id],
                im.cam_from_world,
                cad,
                dataclasses.replace(o, ground_height=float(h)),
                segments_undistorted=True,
            )
            if r2.success and r2.num_inliers > results2[im.name].num_inliers:
                results2[im.name] = r2
    return results, results2, times, cpu, vp_times, rerun


def score(scene, priors_local, results):
    # One camera per image: the registration refines the focal length.
    est = Block()
    for im in priors_local.images.values():
        r = results[im.name]
        cam = r.camera if r.camera is not None else priors_local.cameras[im.camera_id]
        est.cameras[im.image_id] = dataclasses.replace(cam, camera_id=im.image_id)
        est.images[im.image_id] = ImageRecord(
            im.image_id, im.name, im.image_id, r.cam_from_world
        )
    est_abs = est.shifted(-scene.origin)
    truth_corners = np.asarray(scene.buildings["corners"], float)
    ev = evaluate_block(
        est_abs,
        scene.gt,
        truth_corners,
        scene.buildings["visible_corners"],
        EvaluateOptions(across_vertical=True),
    )
    dev = np.array([e.mean_deviation_px for e in ev.images if e.status != "no_corners"])
    dev = np.where(np.isfinite(dev), dev, np.inf)
    return float(np.mean(dev < 2.0)), float(np.mean(dev < 5.0)), len(dev)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", nargs="+", required=True, help="synthetic scene folders")
    ap.add_argument("--segments", choices=["sp", "det"], default="det")
    ap.add_argument(
        "--sweep",
        nargs="+",
        default=["scene"],
        help=f"settings: {', '.join(SETTINGS)}; sweeps: {', '.join(SWEEPS)} "
        "(4 values each) or reduced_<name> (the values other than the default)",
    )
    ap.add_argument("--prior_seed", type=int, default=0)
    ap.add_argument("--output", help="JSON file for the rows")
    args = ap.parse_args(argv)
    rows = []
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / "bench_registration_maps"
    tmp.mkdir(parents=True, exist_ok=True)
    for path in args.scene:
        scene = load_scene(path)
        gt_local = scene.gt.shifted(scene.origin)
        scene_priors = scene.priors.shifted(scene.origin)
        settings = []
        for name in args.sweep:
            if name in SETTINGS:
                settings.append((name, SETTINGS[name]))
            elif name.startswith("reduced_"):
                settings += [(name, v) for v in REDUCED[name[len("reduced_") :]]]
            else:
                settings += [(name, v) for v in SWEEPS[name]]
        for name, setting in settings:
            if setting is None:
                priors_local = scene_priors
                cad = load_cadastre(
                    scene.path / "cadastre.geojson", origin=scene.origin
                )
                noise = json.loads((scene.path / "scene.json").read_text())["options"]
                opts = RegistrationOptions(
                    prior_position_sigma_m=noise["prior_position_m"],
                    prior_rotation_sigma_deg=noise["prior_rotation_deg"],
                    prior_focal_sigma=noise["prior_focal_percent"] / 200.0,
                )
                label = "scene priors"
            else:
                pos, rot, foc, rate = setting
                priors_local = make_priors(gt_local, pos, rot, foc, args.prior_seed)
                cad = make_map(scene, rate, args.prior_seed, tmp)
                big = pos > 10 or rot > 2
                opts = RegistrationOptions(
                    prior_position_sigma_m=max(pos, 2.0),
                    prior_rotation_sigma_deg=max(rot, 0.5),
                    prior_focal_sigma=max(foc, 1.0) / 200.0,
                    num_candidates_verified=16 if big else 12,
                )
                label = (
                    f"pos {pos:g} m, rot {rot:g} deg, focal {foc:g} %, map {rate:.0%}"
                )
            r1, r2, times, cpu, vp_times, rerun = run_setting(
                scene, priors_local, cad, opts, args.segments
            )
            f2_1, f5_1, n = score(scene, priors_local, r1)
            f2_2, f5_2, _ = score(scene, priors_local, r2)
            ok = [r for r in r2.values() if r.success]
            row = dict(
                scene=str(path),
                setting=name,
                label=label,
                images=n,
                below2_pass1=f2_1,
                below5_pass1=f5_1,
                below2=f2_2,
                below5=f5_2,
                rerun=rerun,
                inlier_ratio_median=float(np.median([r.inlier_ratio for r in ok]))
                if ok
                else float("nan"),
                trials_median=float(np.median([r.num_trials for r in ok])) if ok else 0,
                time_median_s=float(np.median(times)),
                time_max_s=float(np.max(times)),
                time_p90_s=float(np.percentile(times, 90)),
                cpu_median_s=float(np.median(cpu)),
                cpu_max_s=float(np.max(cpu)),
                vp_time_median_s=float(np.median(vp_times)),
                load=os.getloadavg()[0],
            )
            rows.append(row)
            print(
                f"{Path(path).name:10s} {label:45s} <2px {f2_1:.3f} -> {f2_2:.3f}  "
                f"<5px {f5_2:.3f}  inl {row['inlier_ratio_median']:.2f}  "
                f"trials {row['trials_median']:.0f}  t {row['time_median_s']:.2f}/"
                f"{row['time_max_s']:.2f} s  cpu {row['cpu_median_s']:.2f}/"
                f"{row['cpu_max_s']:.2f} s  vp {row['vp_time_median_s']:.2f} s  "
                f"(rerun {rerun}, load {row['load']:.1f})",
                flush=True,
            )
    meta = dict(
        machine=platform.processor() or platform.machine(),
        python=sys.version.split()[0],
        cpus=os.cpu_count(),
        date=time.strftime("%Y-%m-%d"),
        segments=args.segments,
    )
    if args.output:
        Path(args.output).write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
