"""One whole ``register`` run of a synthetic scene, scored against the truth.

A helper module, not a script: shared by ``bench/register.py`` and
``diagnose/prior_variants.py``, which import it after putting
``scripts/bench/`` on the path (``scripts/README.md``). :func:`bench_scene`
runs ``register`` with the scene's prior noise as the prior sigmas and the
options of :func:`add_run_arguments`, writes the model to a temporary folder
and evaluates it (full deviation and across the projected vertical) beside
the priors; :func:`print_row` prints its row.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from obliq_colmap.adjustment import AdjustmentOptions
from obliq_colmap.evaluate import EvaluateOptions, evaluate_model
from obliq_colmap.geometry import SUPPORTED_MODELS
from obliq_colmap.pipeline import (
    PipelineOptions,
    default_head_focal_min_images,
    run_register,
    write_run,
)
from obliq_colmap.registration import RegistrationOptions


def _peak_rss_mib() -> tuple[float, float]:
    """Peak resident memory of this process and of its largest child, MiB."""
    me = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return me, kids


def _summary(ev) -> dict:
    s = ev.summary
    return {
        "registered": s.num_registered,
        "total": s.num_total,
        "deviation_median_px": s.deviation_median_px,
        "deviation_p95_px": s.deviation_p95_px,
        "deviation_max_px": s.deviation_max_px,
        "rotation_median_deg": s.rotation_error_median_deg,
        "center_median_m": s.center_error_median_m,
    }


def bench_scene(scene: Path, args: argparse.Namespace) -> dict:
    """One ``register`` run of ``scene`` with ``args`` (:func:`add_run_arguments`),
    its times, memory, counts and evaluation as a JSON-ready row."""
    # A user knows the accuracy of their GPS/INS: take the scene's prior noise.
    noise = json.loads((scene / "scene.json").read_text())["options"]
    adjustment = AdjustmentOptions()
    adjustment = dataclasses.replace(
        adjustment,
        bundle=dataclasses.replace(
            adjustment.bundle, refine_extra_params=bool(args.refine_extra_params)
        ),
    )
    options = PipelineOptions(
        stop_after=args.stop_after,
        num_workers=args.num_workers,
        progress=False,
        camera_model=args.camera_model,
        registration=RegistrationOptions(
            prior_position_sigma_m=noise["prior_position_m"],
            prior_rotation_sigma_deg=noise["prior_rotation_deg"],
            prior_focal_sigma=noise["prior_focal_percent"] / 100.0,
            refine_distortion=bool(args.refine_extra_params),
        ),
        adjustment=adjustment,
        reregister_failed=bool(args.reregister_failed),
        head_focal_min_images=(
            default_head_focal_min_images(args.stop_after)
            if args.head_focal_min_images is None
            else args.head_focal_min_images
        ),
    )
    t0 = time.perf_counter()
    run = run_register(
        scene / "images", scene / "cadastre.geojson", scene / "priors", options
    )
    wall = time.perf_counter() - t0
    tmp = Path(tempfile.mkdtemp(prefix="bench_register_"))
    try:
        out = write_run(tmp / "model", run)
        full = evaluate_model(out, scene, EvaluateOptions())
        across = evaluate_model(out, scene, EvaluateOptions(across_vertical=True))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = evaluate_model(None, scene, EvaluateOptions(), baseline=True)
    per_image = [
        im["time_s"].get("total", np.nan) for im in run.report["images"].values()
    ]
    row = {
        "scene": str(scene),
        "stop_after": args.stop_after,
        "camera_model": args.camera_model,
        "refine_extra_params": int(args.refine_extra_params),
        "reregister_failed": int(args.reregister_failed),
        "reregistered": run.report.get("reregistered", []),
        "num_workers": options.workers,
        "wall_s": wall,
        "time_s": run.report["time_s"],
        "per_image_s_median": float(np.nanmedian(per_image)),
        "registered_by_run": run.report["num_registered"],
        "num_points3D": len(run.points3D),
        "bundle": run.report.get("bundle"),
        "facades": {
            k: v for k, v in run.report.get("facades", {}).items() if k != "images"
        },
        "full": _summary(full),
        "across_vertical": _summary(across),
        "baseline_priors": _summary(base),
        "peak_rss_mib": dict(
            zip(("main", "largest_worker"), _peak_rss_mib(), strict=True)
        ),
    }
    return row


def print_row(row: dict) -> None:
    """The row of :func:`bench_scene`, printed."""
    f, a, b = row["full"], row["across_vertical"], row["baseline_priors"]
    print(
        f"{Path(row['scene']).name}: {row['stop_after']}, {row['num_workers']} workers,"
        f" {row['wall_s']:.1f} s (stages {row['time_s']}),"
        f" per image {row['per_image_s_median']:.2f} s median;"
        f" peak RSS {row['peak_rss_mib']}"
    )
    for label, s in (("full", f), ("across vertical", a), ("priors", b)):
        print(
            f"  {label:16s} registered {s['registered']}/{s['total']}, deviation px"
            f" median {s['deviation_median_px']:.3f} p95 {s['deviation_p95_px']:.3f}"
            f" max {s['deviation_max_px']:.3f}; rotation {s['rotation_median_deg']:.4f}"
            f" deg, centre {s['center_median_m']:.3f} m"
        )
    if row["facades"]:
        print(f"  facades: {row['facades']}")
    if row["bundle"]:
        print("  " + row["bundle"]["brief"])


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the run, as a user passes them to ``register``."""
    parser.add_argument("--stop_after", choices=("initial", "bundle"), default="bundle")
    parser.add_argument("--num_workers", type=int, default=2)
    parser.add_argument(
        "--camera_model",
        choices=sorted(SUPPORTED_MODELS),
        help="result camera model (register's --camera_model; default the priors')",
    )
    parser.add_argument(
        "--refine_extra_params",
        type=int,
        choices=(0, 1),
        default=0,
        help="refine the distortion in the bundle (register's option)",
    )
    parser.add_argument(
        "--head_focal_min_images",
        type=int,
        default=None,
        help="register's option (default as register: 3 with --stop_after "
        "initial, else 0)",
    )
    parser.add_argument(
        "--reregister_failed",
        type=int,
        choices=(0, 1),
        default=1,
        help="register failed or weak images again against the solved block "
        "(PipelineOptions.reregister_failed)",
    )
