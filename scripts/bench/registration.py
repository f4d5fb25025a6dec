"""Benchmark of the initial registration (stage 2) on synthetic scenes.

Measures how many images stage 2 registers and how well, and its time per
image: for each scene folder and each setting (the scene's own priors, or
priors and maps drawn with given errors: ``--sweep``), the images go through
the pipeline's own chain of ``register --stop_after initial``
(:func:`obliq_colmap.pipeline.initial_stage`, one process): the inputs read
as ``register`` reads them (:func:`~obliq_colmap.pipeline.load_inputs`), per
image the vertical VP with the INS prior cone of the prior rotation and focal
errors, the registration (a doubtful VP falls back to the prior's vertical
and all first-pass segments), the pass from the heads' lenses (only with
``refine_distortion``), the heads' focal lengths from all their images
(``--head_focal 3``; off by default, as in the pipeline), then the rescue of
weak images from the ground heights of the confident ones. The result of
the registered images (pose and refined focal length) is scored with
:func:`obliq_colmap.evaluate.evaluate_block` across the projected verticals
(what one image can observe); an image that failed is left out of the model,
as ``register`` leaves it out, so it counts as missing (above every
threshold), never at its prior.

Run (from the repository root)::

    OMP_NUM_THREADS=1 python scripts/bench/registration.py \\
        --scene /work/scenes/paper_s1 --sweep scene default large \\
        --output /tmp/bench_registration.json

Figures: docs/STATUS.md (stage 2: images below 2 px across the vertical,
time per image) and docs/journal/stage2-registration.md.

Data: synthetic scenes (``obliq-colmap synth --preset paper --seed N
--output_path DIR``); the drawn priors and maps are written under
``$TMPDIR/bench_registration_inputs`` (default ``/tmp``).

Printed per setting: the fraction of images with a mean deviation below 2 px
and 5 px after the first pass and after the rescue; the median inlier ratio
and RANSAC trials of the first pass; the time per image of the first-pass
registration (median / max), of the VP stage, and of stage 2 as a whole (the
first passes and the rescue, over the images); the images above 2 px, with
their inliers, how far across the image their inliers spread, and their
focal and rotation errors.

Segments (``--segments``):

- ``det``: the full vanishing stage (default; what the pipeline does);
- ``sp``: the vanishing stage's second pass run on the TRUE vertical VP; this
  isolates the registration from VP errors (the registration is then called
  directly, without the pipeline's chain, and not rescued).

Priors: the scene's own ``priors/`` model and map, or with ``--sweep`` new
priors drawn from the ground truth (position, rotation and focal errors as in
``synthetic.cameras.prior_block``: 47 m datum offset, 5 m height noise), and a
map with a given discrepancy rate (a third each of buildings shifted by 1 m,
missing from the map, and demolished, i.e. mapped but not in the scene). The
registration is told the prior errors as a user tells ``register`` (the
``--prior_*_sigma`` options, as ``bench/register.py``: the focal error in
percent / 100), all other options at their defaults.

Settings with the same prior rotations, focal lengths and VP cone (e.g. a
position or map sweep) detect the same VPs: the VP of an image is computed
once per such key (image, camera, prior, cone, options) and reused; its time
is the one measured when it was computed. For that the script replaces
``detect_vertical_vp`` in ``obliq_colmap.pipeline.workers`` (where the
pipeline's per-image stage, ``initial_image``, looks it up) and runs
``initial_stage`` in the pipeline's pool (``pipeline.worker_pool``, one
worker: in this process, so that the replacement takes effect): both follow
the pipeline's internals and must move with them.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
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
from obliq_colmap.colmap_io import Block, ImageRecord, write_absolute_model  # noqa: E402
from obliq_colmap.evaluate import EvaluateOptions, evaluate_block  # noqa: E402
from obliq_colmap.geometry import Camera, Pose, rotation_from_axis_angle  # noqa: E402
from obliq_colmap.pipeline import (  # noqa: E402
    PipelineOptions,
    image_tasks,
    initial_stage,
    load_inputs,
    worker_pool,
)
from obliq_colmap.pipeline import workers as pipeline_workers  # noqa: E402
from obliq_colmap.registration import (  # noqa: E402
    RegistrationOptions,
    RegistrationResult,
    register_image,
)
from obliq_colmap.synthetic import load_scene, true_vertical_vp  # noqa: E402
from obliq_colmap.vanishing import vertical_segments  # noqa: E402

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


# --------------------------------------------------------------------------
# Priors and maps of a setting
# --------------------------------------------------------------------------


def make_priors(gt: Block, pos_m, rot_deg, focal_pct, seed) -> Block:
    """Priors drawn from the true block (absolute frame), as ``prior_block``."""
    rng = np.random.default_rng(seed)
    out = Block()
    for cid, cam in gt.cameras.items():
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
    for iid, im in gt.images.items():
        c = im.cam_from_world.center + rng.normal(0, 1, 3) * [pos_m, pos_m, 5.0]
        c[2] += 47.0
        R = (
            rotation_from_axis_angle(rng.normal(0, np.radians(rot_deg), 3))
            @ im.cam_from_world.rotation
        )
        pose = Pose.from_center(R, c)
        out.images[iid] = ImageRecord(iid, im.name, im.camera_id, pose)
    return out


def make_map(scene, rate, seed, folder: Path) -> Path:
    """The scene's map with extra discrepancies (shifted, missing, demolished)."""
    path0 = scene.path / "cadastre.geojson"
    if rate <= 0:
        return path0
    cad = load_cadastre(path0, origin=scene.origin)
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
    path = folder / f"{scene.path.name}_map_{rate:.2f}_{seed}.geojson"
    write_geojson(path, out, crs=cad.crs)
    return path


# --------------------------------------------------------------------------
# The VP, once per (image, camera, prior, cone, options)
# --------------------------------------------------------------------------

_VP_CACHE: dict[tuple, object] = {}
_detect_vertical_vp = pipeline_workers.detect_vertical_vp


def _cached_detect_vertical_vp(img, options, camera, prior, rng=None):
    """``detect_vertical_vp`` memoised on all its inputs (it is deterministic
    given them: ``rng`` is the image id as the pipeline passes it)."""
    key = (
        hashlib.sha1(np.ascontiguousarray(img)).hexdigest(),
        repr(options),
        camera.model,
        camera.width,
        camera.height,
        np.asarray(camera.params, float).tobytes(),
        repr(prior),
        rng if isinstance(rng, (int, np.integer, type(None))) else id(rng),
    )
    if key not in _VP_CACHE:
        _VP_CACHE[key] = _detect_vertical_vp(img, options, camera, prior, rng)
    return copy.deepcopy(_VP_CACHE[key])


# --------------------------------------------------------------------------
# One setting
# --------------------------------------------------------------------------


def run_pipeline(
    scene, priors_dir: Path, map_path: Path, reg: RegistrationOptions, head_focal: int
):
    """The pipeline's stages 1-2 on one setting, one process
    (``head_focal``: ``PipelineOptions.head_focal_min_images``).

    Returns (inputs, tasks, outcomes, first-pass results, timings, cpu s).
    """
    options = PipelineOptions(
        stop_after="initial",
        num_workers=1,
        progress=False,
        registration=reg,
        head_focal_min_images=head_focal,
    )
    inputs = load_inputs(scene.path / "images", map_path, priors_dir, options)
    tasks = image_tasks(inputs, options)
    timings: dict[str, float] = {}
    origin3 = np.r_[inputs.cadastre.origin[:2], 0.0]
    init_args = (inputs.cadastre_path, options.cadastre, origin3)
    tc = time.process_time()
    with worker_pool(1, init_args, inputs.cadastre, False) as pool:
        outcomes, first, _ = initial_stage(pool, tasks, options, timings)
    return inputs, tasks, outcomes, first, timings, time.process_time() - tc


def run_sp(scene, priors_dir: Path, map_path: Path, reg: RegistrationOptions):
    """Registration alone on the true VP's segments (``--segments sp``)."""
    options = PipelineOptions(stop_after="initial", num_workers=1, registration=reg)
    inputs = load_inputs(scene.path / "images", map_path, priors_dir, options)
    tasks = image_tasks(inputs, options)
    results, t_reg = [], []
    tc = time.process_time()
    for t in tasks:
        gray = cv2.imread(str(t.path), cv2.IMREAD_GRAYSCALE)
        vp = true_vertical_vp(scene, t.name)
        tcam, _ = scene.camera_pose(t.name)
        seg = vertical_segments(gray, vp, camera=tcam).endpoints
        n = np.linalg.solve(t.camera.K, vp)
        t0 = time.perf_counter()
        results.append(
            register_image(
                seg,
                n / np.linalg.norm(n),
                t.result_camera,
                t.prior,
                inputs.cadastre,
                reg,
                segments_undistorted=True,
            )
        )
        t_reg.append(time.perf_counter() - t0)
    timings = {"initial": float(np.sum(t_reg)), "rescue": 0.0}
    return inputs, tasks, results, t_reg, timings, time.process_time() - tc


def evaluate_results(scene, inputs, tasks, results: list[RegistrationResult | None]):
    """Per image name: (ImageEvaluation, result); the model holds the
    successful results only (each with its own refined camera), as
    ``register`` writes it."""
    est = Block()
    for t, r in zip(tasks, results, strict=True):
        if r is None or not r.success:
            continue
        cam = r.camera if r.camera is not None else t.result_camera
        est.cameras[t.image_id] = Camera(
            cam.model, cam.width, cam.height, cam.params, t.image_id
        )
        est.images[t.image_id] = ImageRecord(
            t.image_id, t.name, t.image_id, r.cam_from_world
        )
    origin3 = np.r_[inputs.cadastre.origin[:2], 0.0]
    ev = evaluate_block(
        est.shifted(-origin3),
        scene.gt,
        np.asarray(scene.buildings["corners"], float),
        scene.buildings["visible_corners"],
        EvaluateOptions(across_vertical=True),
    )
    by_name = {t.name: r for t, r in zip(tasks, results, strict=True)}
    return {e.name: (e, by_name.get(e.name)) for e in ev.images}


def fractions(evals) -> tuple[float, float, int, np.ndarray]:
    """Fractions below 2 px and 5 px over the measurable images (a failed or
    missing image counts as above), their count, and the (N,) deviations."""
    dev = np.array(
        [
            e.mean_deviation_px if e.status not in ("missing", "behind") else np.inf
            for e, _ in evals.values()
            if e.status != "no_corners"
        ]
    )
    dev = np.where(np.isfinite(dev), dev, np.inf)
    return float(np.mean(dev < 2.0)), float(np.mean(dev < 5.0)), len(dev), dev


def inlier_spread(r: RegistrationResult | None, width: int) -> float:
    """Width of the inliers' spread across the image (10-90 % of their
    midpoints' x), as a fraction of the image width: small = one-sided."""
    if r is None or len(r.inlier_segments_px) == 0:
        return 0.0
    x = r.inlier_segments_px.mean(axis=1)[:, 0]
    return float(np.subtract(*np.percentile(x, [90, 10])) / width)


def misses(scene, evals, outcomes_by_name) -> list[dict]:
    """The images at or above 2 px after the rescue, with why-hints."""
    out = []
    for name, (e, r) in sorted(evals.items()):
        if e.status == "no_corners" or (
            e.status not in ("missing", "behind") and e.mean_deviation_px < 2.0
        ):
            continue
        tcam, _ = scene.camera_pose(name)
        o = outcomes_by_name.get(name)
        focal = (
            r.camera.K[0, 0] / tcam.K[0, 0] - 1.0
            if r is not None and r.success and r.camera is not None
            else float("nan")
        )
        out.append(
            dict(
                name=name,
                status=e.status,
                deviation_px=e.mean_deviation_px,
                success=bool(r is not None and r.success),
                message=r.message if r is not None else "",
                inliers=r.num_inliers if r is not None else 0,
                inlier_spread=inlier_spread(r, tcam.width),
                focal_error=focal,
                rotation_error_deg=e.rotation_error_deg,
                horizontal_error_m=e.horizontal_error_m,
                vertical_source=r.vertical_source if r is not None else "",
                vp_status=o.vp_status if o is not None else "",
                rescued=bool(o.rescued) if o is not None else False,
            )
        )
    return out


def setting_inputs(scene, name, setting, seed, tmp: Path):
    """(priors folder, map path, RegistrationOptions, label) of one setting."""
    if setting is None:
        noise = json.loads((scene.path / "scene.json").read_text())["options"]
        reg = RegistrationOptions(
            prior_position_sigma_m=noise["prior_position_m"],
            prior_rotation_sigma_deg=noise["prior_rotation_deg"],
            prior_focal_sigma=noise["prior_focal_percent"] / 100.0,
        )
        label = "scene priors"
        return scene.path / "priors", scene.path / "cadastre.geojson", reg, label
    pos, rot, foc, rate = setting
    priors_dir = tmp / f"{scene.path.name}_priors_{pos:g}_{rot:g}_{foc:g}_{seed}"
    if not priors_dir.is_dir():
        write_absolute_model(priors_dir, make_priors(scene.gt, pos, rot, foc, seed))
    # As a user would state them: a 0 % focal error is never known exactly.
    reg = RegistrationOptions(
        prior_position_sigma_m=max(pos, 2.0),
        prior_rotation_sigma_deg=max(rot, 0.5),
        prior_focal_sigma=max(foc, 1.0) / 100.0,
    )
    label = f"pos {pos:g} m, rot {rot:g} deg, focal {foc:g} %, map {rate:.0%}"
    return priors_dir, make_map(scene, rate, seed, tmp), reg, label


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
    ap.add_argument(
        "--head_focal",
        type=int,
        default=PipelineOptions().head_focal_min_images,
        help="PipelineOptions.head_focal_min_images (the heads' focal lengths "
        "from all their images; 0: off)",
    )
    ap.add_argument("--output", help="JSON file for the rows (rewritten per row)")
    args = ap.parse_args(argv)
    # where initial_image looks it up (one worker: in this process)
    pipeline_workers.detect_vertical_vp = _cached_detect_vertical_vp
    rows = []
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / "bench_registration_inputs"
    tmp.mkdir(parents=True, exist_ok=True)
    meta = dict(
        machine=platform.processor() or platform.machine(),
        python=sys.version.split()[0],
        cpus=os.cpu_count(),
        date=time.strftime("%Y-%m-%d"),
        segments=args.segments,
        argv=sys.argv[1:] if argv is None else list(argv),
    )
    for path in args.scene:
        scene = load_scene(path)
        settings = []
        for name in args.sweep:
            if name in SETTINGS:
                settings.append((name, SETTINGS[name]))
            elif name.startswith("reduced_"):
                settings += [(name, v) for v in REDUCED[name[len("reduced_") :]]]
            else:
                settings += [(name, v) for v in SWEEPS[name]]
        for name, setting in settings:
            priors_dir, map_path, reg, label = setting_inputs(
                scene, name, setting, args.prior_seed, tmp
            )
            t_wall = time.perf_counter()
            if args.segments == "sp":
                inputs, tasks, final, t_reg, timings, cpu = run_sp(
                    scene, priors_dir, map_path, reg
                )
                first, outcomes, t_vp = final, [], [np.nan]
            else:
                inputs, tasks, outcomes, first, timings, cpu = run_pipeline(
                    scene, priors_dir, map_path, reg, args.head_focal
                )
                final = [o.registration for o in outcomes]
                t_reg = [o.time_s.get("registration", np.nan) for o in outcomes]
                t_vp = [o.time_s.get("vanishing", np.nan) for o in outcomes]
            wall = time.perf_counter() - t_wall
            ev1 = evaluate_results(scene, inputs, tasks, first)
            ev2 = evaluate_results(scene, inputs, tasks, final)
            f2_1, f5_1, n, _ = fractions(ev1)
            f2_2, f5_2, _, dev = fractions(ev2)
            ok1 = [r for r in first if r is not None and r.success]
            n_img = len(tasks)
            stage2 = timings["initial"] - np.nansum(t_vp) + timings["rescue"]
            stage2 += timings.get("head_pass", 0.0) + timings.get("head_focal", 0.0)
            row = dict(
                scene=str(path),
                setting=name,
                label=label,
                images=n,
                registered_pass1=len(ok1),
                registered=sum(r is not None and r.success for r in final),
                below2_pass1=f2_1,
                below5_pass1=f5_1,
                below2=f2_2,
                below5=f5_2,
                deviation_median_px=float(np.median(dev)),
                deviation_max_px=float(np.max(dev)),
                rescued=sum(bool(o.rescued) for o in outcomes),
                vp_ok=sum(o.vp_status == "ok" for o in outcomes),
                inlier_ratio_median=float(np.median([r.inlier_ratio for r in ok1]))
                if ok1
                else float("nan"),
                trials_median=float(np.median([r.num_trials for r in ok1]))
                if ok1
                else 0.0,
                time_median_s=float(np.nanmedian(t_reg)),
                time_max_s=float(np.nanmax(t_reg)),
                vp_time_median_s=float(np.nanmedian(t_vp)),
                stage2_per_image_s=float(stage2 / n_img),
                head_focal_s=float(timings.get("head_focal", 0.0)),
                rescue_s=float(timings["rescue"]),
                wall_s=wall,
                cpu_s=cpu,
                load=os.getloadavg(),
                misses=misses(scene, ev2, {o.name: o for o in outcomes}),
            )
            rows.append(row)
            print(
                f"{Path(path).name:10s} {label:45s} <2px {f2_1:.3f} -> {f2_2:.3f}  "
                f"<5px {f5_1:.3f} -> {f5_2:.3f}  inl {row['inlier_ratio_median']:.2f}  "
                f"trials {row['trials_median']:.0f}  reg {row['time_median_s']:.2f}/"
                f"{row['time_max_s']:.2f} s  vp {row['vp_time_median_s']:.2f} s  "
                f"stage2 {row['stage2_per_image_s']:.2f} s/img "
                f"(heads' focal {row['head_focal_s'] / n_img:.2f})  "
                f"(rescued {row['rescued']}, vp ok {row['vp_ok']}/{n_img}, "
                f"wall {wall:.0f} s, load {row['load'][0]:.1f})",
                flush=True,
            )
            for m in row["misses"]:
                print(
                    f"    miss {m['name']}: {m['status']} {m['deviation_px']:.2f} px, "
                    f"{m['inliers']} inl, spread {m['inlier_spread']:.2f}, "
                    f"focal {m['focal_error']:+.3f}, rot {m['rotation_error_deg']:.2f} "
                    f"deg, xy {m['horizontal_error_m']:.1f} m, vp {m['vp_status']}, "
                    f"vertical {m['vertical_source']}, rescued {m['rescued']}"
                    + (f" ({m['message']})" if not m["success"] else ""),
                    flush=True,
                )
            if args.output:
                Path(args.output).write_text(
                    json.dumps(dict(meta=meta, rows=rows), indent=1, default=float)
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
