"""Time stage 2 (:func:`registration.register_image`) alone, one core.

Measures what the pipeline spends on stage 2 per image: every image of a
synthetic scene registered as the pipeline's initial pass does, and the weak
images (< ``rescue_min_inliers``) again from each of the block's ground
heights (the pipeline's rescue, :func:`pipeline.rescue_heights`), without
``refine_distortion`` (whose head pass would add one more call per image).
With ``--reference TREE`` that tree's ``register_image`` runs on the same
inputs alternately with this one, in the same process: the time ratio new /
reference, and the largest differences of the results (rotation, centre,
focal, inlier count), which must be nil for a pure speed change.

Run (from the repository root)::

    python scripts/bench/register_speed.py --scene_path /work/scenes/paper_s1 \\
        --reference /tmp/ref [--prior_position_sigma 20 --prior_rotation_sigma 3]

Figures: docs/STATUS.md (stage 2: time per image) and
docs/journal/stage2-registration.md.

Data: a synthetic scene (``obliq-colmap synth --preset paper --seed N
--output_path DIR``); ``--reference`` a source tree (another checkout, or
``git archive REV obliq_colmap | tar -x -C TREE``).

Stage 1 runs once per image as the pipeline runs it (the vertical VP with
the INS prior, the VP-constrained segments, or all first-pass segments and
the fallback options when the VP fails) and its output is cached in a pickle
(``--cache_dir``, default ``/tmp/bench_register_speed``), so that a second
run times stage 2 only. One thread (OMP_NUM_THREADS=1, threadpoolctl,
cv2.setNumThreads(1)). Options: the scene's prior noise (as
``bench/register.py``), or ``--prior_position_sigma`` /
``--prior_rotation_sigma`` to time a wider search (the target is stated at
20 m / 3 deg).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pickle
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import scipy.ndimage  # noqa: E402, F401  (imported once, not timed
import scipy.optimize  # noqa: E402, F401  with the first image)
from threadpoolctl import threadpool_limits  # noqa: E402

from obliq_colmap import pipeline  # noqa: E402
from obliq_colmap.registration import RegistrationOptions, register_image  # noqa: E402
from obliq_colmap.vanishing import VPPrior, detect_vertical_vp  # noqa: E402

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from reference import load_reference  # noqa: E402


@dataclasses.dataclass
class Stage1:
    """Stage 1's output of one image, as stage 2 gets it."""

    name: str
    segments: np.ndarray  # (N, 2, 2) undistorted px
    vertical: np.ndarray | None  # (3,) or None (VP failed)
    vp_status: str


def stage1(task) -> Stage1:
    """What the pipeline's per-image stage 1 hands to stage 2."""
    img = cv2.imread(str(task.path), cv2.IMREAD_GRAYSCALE)
    prior = VPPrior.from_rotation(task.prior.rotation, task.cone_deg)
    vp = detect_vertical_vp(img, task.vanishing, task.camera, prior, task.image_id)
    if vp.status == "ok" and vp.vertical_segments is not None:
        return Stage1(
            task.name, vp.vertical_segments.endpoints, vp.vertical_direction, vp.status
        )
    return Stage1(task.name, vp.segments.endpoints, None, vp.status)


def cached_stage1(scene: Path, tasks, cache_dir: Path) -> dict[str, Stage1]:
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = cache_dir / f"{scene.resolve().as_posix().strip('/').replace('/', '_')}.pkl"
    if path.exists():
        # Plain dicts in the pickle: readable from any importing script.
        return {n: Stage1(**d) for n, d in pickle.loads(path.read_bytes()).items()}
    out = {}
    for k, task in enumerate(tasks):
        out[task.name] = stage1(task)
        print(f"  stage 1 {k + 1}/{len(tasks)} {task.name}", flush=True)
    path.write_bytes(pickle.dumps({n: dataclasses.asdict(s) for n, s in out.items()}))
    return out


def _difference(a, b) -> dict:
    """Largest-difference terms of two RegistrationResults."""
    if a.success != b.success:
        return dict(success=math.inf)
    # The angle from ||Ra - Rb||_F = 2 sqrt(2) sin(angle / 2): 0 for equal
    # matrices (acos of the trace has a floor of ~1e-6 deg from rounding).
    dR = np.linalg.norm(a.cam_from_world.rotation - b.cam_from_world.rotation)
    ang = math.degrees(2.0 * math.asin(min(1.0, dR / math.sqrt(8.0))))
    dc = float(np.linalg.norm(a.cam_from_world.center - b.cam_from_world.center))
    df = 0.0
    if a.camera is not None and b.camera is not None:
        df = float(np.max(np.abs(np.asarray(a.camera.params) - b.camera.params)))
    return dict(
        rotation_deg=ang,
        center_m=dc,
        params=df,
        inliers=abs(a.num_inliers - b.num_inliers),
        trials=abs(a.num_trials - b.num_trials),
    )


def bench(args) -> dict:
    scene = Path(args.scene_path)
    noise = json.loads((scene / "scene.json").read_text())["options"]
    reg = RegistrationOptions(
        prior_position_sigma_m=args.prior_position_sigma or noise["prior_position_m"],
        prior_rotation_sigma_deg=args.prior_rotation_sigma
        or noise["prior_rotation_deg"],
        prior_focal_sigma=noise["prior_focal_percent"] / 100.0,
    )
    popts = pipeline.PipelineOptions(
        stop_after="initial", num_workers=1, progress=False, registration=reg
    )
    inputs = pipeline.load_inputs(
        scene / "images", scene / "cadastre.geojson", scene / "priors", popts
    )
    tasks = pipeline.image_tasks(inputs, popts)
    s1 = cached_stage1(scene, tasks, Path(args.cache_dir))

    versions = {"new": (register_image, RegistrationOptions)}
    if args.reference:
        (ref_reg,) = load_reference(Path(args.reference), ("registration",))
        versions["ref"] = (ref_reg.register_image, ref_reg.RegistrationOptions)

    def options_for(tag, s: Stage1, **changes):
        cls = versions[tag][1]
        o = cls(**{f.name: getattr(reg, f.name) for f in dataclasses.fields(reg)})
        if s.vertical is None:
            tol = max(o.vp_tolerance_deg, 2.0 * o.prior_rotation_sigma_deg)
            changes["vp_tolerance_deg"] = tol
        return dataclasses.replace(o, **changes)

    def run(tag, task, s: Stage1, **changes):
        fn = versions[tag][0]
        o = options_for(tag, s, **changes)
        t, c = time.perf_counter(), time.process_time()
        r = fn(
            s.segments,
            s.vertical,
            task.result_camera,
            task.prior,
            inputs.cadastre,
            o,
            segments_undistorted=True,
        )
        return r, time.perf_counter() - t, time.process_time() - c

    # (pass, image) -> tag -> list of times; results of the last repeat.
    times: dict = {}
    cpu: dict = {}
    results: dict = {}
    diffs: list[dict] = []

    def timed(key, task, s, **changes):
        for _ in range(args.repeats):
            for tag in versions:
                r, dt, dc = run(tag, task, s, **changes)
                times.setdefault(key, {}).setdefault(tag, []).append(dt)
                cpu.setdefault(key, {}).setdefault(tag, []).append(dc)
                results.setdefault(key, {})[tag] = r
        if "ref" in versions:
            d = _difference(results[key]["new"], results[key]["ref"])
            diffs.append(dict(key=list(key), **d))

    load0 = os.getloadavg()
    names = args.images or [t.name for t in tasks][: args.max_images or None]
    for task in tasks:
        if task.name not in names:
            continue
        timed(("initial", task.name), task, s1[task.name])
        r = results[("initial", task.name)]["new"]
        print(
            f"  {task.name}: {len(s1[task.name].segments)} segments, "
            f"{r.num_inliers} inliers, "
            + ", ".join(
                f"{tag} {min(times[('initial', task.name)][tag]):.2f} s"
                for tag in versions
            ),
            flush=True,
        )
    rescue = 0
    if args.rescue:
        initial = [results[("initial", n)]["new"] for n in names]
        heights = pipeline.rescue_heights(
            initial, popts.rescue_min_inliers, reg.coarse_height_step_m
        )
        for task in tasks:
            if task.name not in names:
                continue
            r = results[("initial", task.name)]["new"]
            s = s1[task.name]
            weak = r.num_inliers < popts.rescue_min_inliers
            if not weak or len(s.segments) < reg.min_segments:
                continue
            for h in heights:
                rescue += 1
                timed(("rescue", task.name, float(h)), task, s, ground_height=float(h))

    def best(key, tag):
        return min(times[key][tag])

    out: dict = {
        "scene": str(scene),
        "image_size": [tasks[0].camera.width, tasks[0].camera.height],
        "prior_sigmas": [reg.prior_position_sigma_m, reg.prior_rotation_sigma_deg],
        "images": len(names),
        "rescue_calls": rescue,
        "repeats": args.repeats,
        "load_average_start": load0,
    }
    for tag in versions:
        ini = np.array([best(k, tag) for k in times if k[0] == "initial"])
        per_image = {n: 0.0 for n in names}
        for k in times:
            per_image[k[1]] += best(k, tag)
        tot = np.array(list(per_image.values()))
        parts: dict = {}
        for k in results:
            if k[0] == "initial":
                for p, v in results[k][tag].timings.items():
                    parts.setdefault(p, []).append(v)
        ini_cpu = np.array([min(cpu[k][tag]) for k in cpu if k[0] == "initial"])
        out[tag] = {
            "initial_cpu_s_median": float(np.median(ini_cpu)),
            "initial_cpu_s_max": float(np.max(ini_cpu)),
            "initial_s_median": float(np.median(ini)),
            "initial_s_max": float(np.max(ini)),
            "pipeline_stage2_per_image_s_median": float(np.median(tot)),
            "pipeline_stage2_per_image_s_mean": float(np.mean(tot)),
            "pipeline_stage2_per_image_s_max": float(np.max(tot)),
            "initial_parts_s_median": {
                p: float(np.median(v)) for p, v in parts.items()
            },
        }
    if "ref" in versions:
        keys = list(times)
        a = np.array([best(k, "new") for k in keys])
        b = np.array([best(k, "ref") for k in keys])
        ac = np.array([min(cpu[k]["new"]) for k in keys])
        bc = np.array([min(cpu[k]["ref"]) for k in keys])
        out["ratio_new_over_ref"] = {
            "of_sums": float(a.sum() / b.sum()),
            "median_per_call": float(np.median(a / b)),
            "cpu_of_sums": float(ac.sum() / bc.sum()),
        }
        out["max_difference"] = {
            f: float(max(d.get(f, 0.0) for d in diffs))
            for f in ("success", "rotation_deg", "center_m", "params", "inliers")
        }
        out["max_difference"]["trials"] = float(max(d.get("trials", 0) for d in diffs))
        out["differing_calls"] = [
            d
            for d in diffs
            if d.get("success") or d["rotation_deg"] > 1e-6 or d["center_m"] > 1e-6
        ]
    out["load_average_end"] = os.getloadavg()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene_path", required=True)
    ap.add_argument("--reference", help="source tree timed alternately with this one")
    ap.add_argument("--prior_position_sigma", type=float, default=None)
    ap.add_argument("--prior_rotation_sigma", type=float, default=None)
    ap.add_argument("--repeats", type=int, default=1, help="runs per call (best)")
    ap.add_argument("--rescue", type=int, default=1, help="time the rescue pass too")
    ap.add_argument("--max_images", type=int, default=0, help="0: all")
    ap.add_argument("--images", nargs="+", help="only these images (names)")
    ap.add_argument("--cache_dir", default="/tmp/bench_register_speed")
    ap.add_argument("--output", help="JSON file for the figures")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    with threadpool_limits(1):
        out = bench(args)
    out.update(
        machine=platform.processor() or platform.machine(),
        date=time.strftime("%Y-%m-%d %H:%M"),
    )
    print(json.dumps(out, indent=1))
    if args.output:
        Path(args.output).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
