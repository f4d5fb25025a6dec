"""Where the accuracy goes with the image resolution: stage 2 and 3 figures.

For each synthetic scene (e.g. the same ``paper`` scene at 2004 and at 4008
px), one ``register`` run split at the end of stage 2 (its per-image
outcomes are cached on disk, keyed by the stage 1-2 options, so that stage-3
variants rerun in seconds), then:

* stage 2: per image the vertical segments, inlier corners (two vertical
  constraints each) and the across-vertical deviation of the per-image
  registration; the image scale (px per metre across the vertical at the
  inlier corners) and the residuals of the inlier pairs at the TRUE camera
  (map-corner noise + edge noise, in px and in metres on the ground);
* stage 3: the bundle's rounds (rejections, per-kind sigmas, from its log),
  the final constraints and per-kind residual spread, the same residuals at
  the true cameras, and the evaluation (full and across the vertical).

Options of stages 1-3 can be overridden by dotted paths (``--set
adjustment.bundle.loss_scale_px=2``, ``--set registration.inlier_threshold_px=4``):
a quick test of which threshold matters.

    python scripts/bench_resolution.py --scene_path /work/scenes/paper_s1 \\
        --scene_path /work/scenes/paper4k_s1 [--set PATH=VALUE ...] \\
        [--stop_after initial] [--cache_path /tmp/bench_resolution]

Scenes are made with ``obliq-colmap synth --preset paper --seed N
[--image_width 4008] --output_path DIR``.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import hashlib
import json
import logging
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

from obliq_colmap import adjustment as adj
from obliq_colmap import pipeline as pl
from obliq_colmap.bundle import residuals as res
from obliq_colmap.evaluate import EvaluateOptions, evaluate_block, read_ground_truth
from obliq_colmap.lines import RefineOptions
from obliq_colmap.matching import triangulate_tracks
from obliq_colmap.registration import RegistrationOptions


def _set(obj, path: str, value):
    """``obj`` with the dotted attribute ``path`` replaced (nested dataclasses)."""
    head, _, rest = path.partition(".")
    if not rest:
        return dataclasses.replace(obj, **{head: value})
    return dataclasses.replace(obj, **{head: _set(getattr(obj, head), rest, value)})


def _options(scene: Path, args: argparse.Namespace) -> pl.PipelineOptions:
    noise = json.loads((scene / "scene.json").read_text())["options"]
    options = pl.PipelineOptions(
        stop_after="initial",
        num_workers=args.num_workers,
        progress=False,
        registration=RegistrationOptions(
            prior_position_sigma_m=noise["prior_position_m"],
            prior_rotation_sigma_deg=noise["prior_rotation_deg"],
            prior_focal_sigma=noise["prior_focal_percent"] / 100.0,
        ),
    )
    for item in args.set or []:
        path, _, text = item.partition("=")
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text
        if path == "refine_segments" and text == "on":  # off by default
            value = RefineOptions()
        options = _set(options, path, value)
    return options


def _stage12(scene: Path, options: pl.PipelineOptions, cache: Path):
    """Inputs and the per-image outcomes (cached by the stage 1-2 options)."""
    key = repr(
        (
            str(scene.resolve()),
            options.vanishing,
            options.refine_segments,
            options.registration,
            options.cone_deg,
            options.rescue_min_inliers,
            options.head_focal_min_images,
        )
    )
    path = cache / (hashlib.sha1(key.encode()).hexdigest()[:16] + ".pkl")
    inputs = pl.load_inputs(
        scene / "images", scene / "cadastre.geojson", scene / "priors", options
    )
    if path.is_file():
        return inputs, pickle.loads(path.read_bytes()), None
    t0 = time.perf_counter()
    run = pl.run_register(
        scene / "images", scene / "cadastre.geojson", scene / "priors", options
    )
    wall = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(run.outcomes))
    return inputs, run.outcomes, wall


def _q(a: np.ndarray, qs=(50, 90, 95)) -> str:
    a = np.abs(np.asarray(a, float))
    a = a[np.isfinite(a)]
    if len(a) == 0:
        return "-"
    p = np.percentile(a, qs)
    mad = 1.4826 * np.median(a)
    return (
        "|r| "
        + " ".join(f"p{q} {v:.3f}" for q, v in zip(qs, p, strict=True))
        + f", 1.48 MAD {mad:.3f}"
    )


def _truth_local(scene: Path, inputs):
    cad = inputs.cadastre
    gt = read_ground_truth(scene)
    gtb = gt.block.shifted(np.array([cad.origin[0], cad.origin[1], 0.0]))
    by_name = {im.name: im for im in gtb.images.values()}
    return gt, gtb, by_name


def _evaluate(inputs, state: adj.BlockState, gt) -> tuple:
    cad = inputs.cadastre
    block = pl._result_block(inputs, state).shifted(
        -np.array([cad.origin[0], cad.origin[1], 0.0])
    )
    out = []
    for across, offset in ((False, "corners"), (True, "corners"), (False, "cameras")):
        ev = evaluate_block(
            block,
            gt.block,
            gt.corners_world,
            gt.visible,
            EvaluateOptions(across_vertical=across, vertical_offset=offset),
        )
        out.append(ev)
    return out


def _fmt_eval(label: str, ev) -> str:
    s = ev.summary
    return (
        f"  {label:20s} {s.num_registered}/{s.num_total} < 2 px, deviation median"
        f" {s.deviation_median_px:.3f} p95 {s.deviation_p95_px:.3f} max"
        f" {s.deviation_max_px:.3f} px; rotation {s.rotation_error_median_deg:.3f}"
        f" deg, centre {s.center_error_median_m:.2f} m"
    )


def _vertical_at_truth(cam, pose, xy: np.ndarray, h: np.ndarray, line: np.ndarray):
    """(M,) signed px distances of points (xy, h) projected to lines (M, 3)."""
    X = pose.transform(np.column_stack([xy, h]))
    px = cam.img_from_cam(X)
    return np.sum(line[:, :2] * px, axis=1) + line[:, 2]


def stage2_report(scene, inputs, outcomes, gt, gtb, by_name, per_image=False) -> None:
    reg = [o for o in outcomes.values() if o.registered]
    state = adj.BlockState.from_outcomes(reg)
    full, across, _ = _evaluate(inputs, state, gt)
    print(_fmt_eval("stage 2 full", full))
    print(_fmt_eval("stage 2 across vert.", across))
    nseg = np.array([len(o.segments) for o in outcomes.values()])
    ninl = np.array(
        [o.registration.num_inliers if o.registered else 0 for o in outcomes.values()]
    )
    print(
        f"  vertical segments per image median {np.median(nseg):.0f}"
        f" (sum {nseg.sum()}), inlier corners median {np.median(ninl):.0f}"
        f" (sum {ninl.sum()}, {2 * ninl.sum()} vertical constraints)"
    )
    # Inlier pairs at the true camera: distance of the map corner's vertical
    # to the segment (both endpoints), px and metres on the ground.
    v = adj.vertical_constraints(inputs, outcomes, state, [o.image_id for o in reg])
    r_px, r_m, ppm = [], [], []
    for k, o in enumerate(reg):
        sel = np.flatnonzero(v["image"] == k)
        if len(sel) == 0:
            continue
        t = by_name[o.name]
        cam = gtb.cameras[t.camera_id]
        pose = t.cam_from_world
        r = _vertical_at_truth(
            cam, pose, v["xy"][sel], v["height"][sel], v["line"][sel]
        )
        # px per metre across the line: move the corner 1 m along the line's
        # normal direction on the ground (the worst horizontal direction).
        best = np.zeros(len(sel))
        for ang in np.linspace(0, np.pi, 8, endpoint=False):
            d = np.array([np.cos(ang), np.sin(ang)])
            r1 = _vertical_at_truth(
                cam, pose, v["xy"][sel] + d, v["height"][sel], v["line"][sel]
            )
            best = np.maximum(best, np.abs(r1 - r))
        r_px.append(r)
        r_m.append(r / best)
        ppm.append(best)
        if per_image:
            ev = next(e for e in across.images if e.name == o.name)
            print(
                f"    {o.name:24s} segments {len(o.segments):4d} inliers"
                f" {o.registration.num_inliers:4d} px/m {np.median(best):5.2f}"
                f" truth |r| median {np.median(np.abs(r)):.2f} px, across-vertical"
                f" deviation {ev.mean_deviation_px:.2f} px"
            )
    r_px, r_m, ppm = (np.concatenate(x) for x in (r_px, r_m, ppm))
    print(
        f"  stage-2 inlier pairs at the TRUE cameras ({len(r_px)} rows): px {_q(r_px)}"
    )
    print(f"    same in metres on the ground: {_q(r_m)}")
    print(
        "    px per metre on the ground across the verticals: median"
        f" {np.median(ppm):.2f}, p10 {np.percentile(ppm, 10):.2f},"
        f" p90 {np.percentile(ppm, 90):.2f}"
    )


def stage3_report(
    scene, inputs, outcomes, options, gt, gtb, by_name, per_image=False
) -> None:
    reg = [o for o in outcomes.values() if o.registered]
    state = adj.BlockState.from_outcomes(reg)
    timings: dict[str, float] = {}
    log = _Capture()
    loggers = [
        logging.getLogger(f"obliq_colmap.{m}") for m in ("adjustment", "matching")
    ]
    for lg in loggers:
        lg.addHandler(log)
        lg.setLevel(logging.INFO)
        lg.propagate = False
    try:
        t0 = time.perf_counter()
        new, result, stage3 = adj.bundle_stage(
            inputs, outcomes, state, options.adjustment, timings
        )
        wall = time.perf_counter() - t0
    finally:
        for lg in loggers:
            lg.removeHandler(log)
            lg.propagate = True
    for line in log.lines:
        print("   ", line)
    print(
        f"  stage 3: {wall:.1f} s (facades {timings.get('facades', 0):.1f} s,"
        f" bundle {timings.get('bundle', 0):.1f} s)"
    )
    if result is None:
        print("  no bundle result")
        return
    print("  " + result.summary.brief())
    print(
        f"  final residuals: vertical ({len(result.vertical_residuals_px)})"
        f" {_q(result.vertical_residuals_px)}"
    )
    print(
        f"                   horizontal ({len(result.horizontal_residuals_px)})"
        f" {_q(result.horizontal_residuals_px)}"
    )
    full, across, cameras = _evaluate(inputs, new, gt)
    print(_fmt_eval("bundle full", full))
    print(_fmt_eval("bundle across vert.", across))
    print(_fmt_eval("bundle full, cam. dz", cameras))
    if per_image:
        acr = {e.name: e for e in across.images}
        for e in full.images:
            a = acr[e.name]
            print(
                f"    {e.name:24s} {e.status:10s} full {e.mean_deviation_px:6.2f} px,"
                f" across {a.mean_deviation_px:5.2f} px; rotation"
                f" {e.rotation_error_deg:.3f} deg, centre dz"
                f" {e.vertical_error_m:+.2f} m, dxy {e.horizontal_error_m:.2f} m"
            )
    # The bundle's first problem at the true cameras.
    stage3b = adj.Stage3(stage3.ids, stage3.facades, stage3.tracks)
    st = state.with_datum_correction(
        dict(zip(stage3.ids, stage3.tracks.datum_correction, strict=True))
    )
    problem = adj.build_bundle_problem(inputs, outcomes, st, stage3b)
    truth = [by_name[inputs.priors.images[i].name] for i in stage3.ids]
    cams = [gtb.cameras[t.camera_id] for t in truth]
    poses = [t.cam_from_world for t in truth]
    rv = np.concatenate(
        [
            _vertical_at_truth(
                cams[k],
                poses[k],
                problem.corner_xy[sel],
                problem.corner_heights[sel],
                problem.vertical_line[sel],
            )
            for k in range(len(stage3.ids))
            if len(sel := np.flatnonzero(problem.vertical_image == k))
        ]
    )
    t = stage3.tracks
    offsets = np.cumsum([0] + [len(f) for f in stage3.facades])
    ppm = np.concatenate([f.px_per_m for f in stage3.facades])[offsets[t.image] + t.row]
    normal = inputs.cadastre.edge_normal[t.edge]
    d, h = triangulate_tracks(
        t.image, t.track, stage3b.ends_raw, cams, poses, t.anchor_xy, normal, ppm, 1e6
    )
    X = np.column_stack([t.anchor_xy + d[:, None] * normal, h])[t.track]
    rh = res.horizontal_residuals_by_image(
        cams, poses, t.image, X, problem.horizontal_line
    )
    cnt = np.bincount(t.track)[t.track]
    print(f"  at the TRUE cameras: vertical ({len(rv)}) {_q(rv)}")
    print(
        f"    horizontal, tracks as free 3D lines, >= 3 obs ({(cnt >= 3).sum()})"
        f" {_q(rh[cnt >= 3])}"
    )
    lengths = np.concatenate([f.length for f in stage3.facades])
    print(
        f"    facade segment length px median {np.median(lengths):.1f};"
        f" px per m of height median {np.median(ppm):.2f}"
    )


class _Capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def scene_parser(description: str) -> argparse.ArgumentParser:
    """The options of the benchmarks built on this one's stage 1-2 cache."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--scene_path", action="append", required=True)
    parser.add_argument("--num_workers", type=int, default=2)
    parser.add_argument("--set", action="append", help="PATH=VALUE option override")
    parser.add_argument("--cache_path", default="/tmp/bench_resolution")
    return parser


def synthetic_scenes(args: argparse.Namespace) -> list[Path] | None:
    """``--scene_path`` as paths; None (after one error line) when one is
    not a synthetic scene folder. Sets up the warnings-only logging."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    scenes = [Path(p) for p in args.scene_path]
    for scene in scenes:
        if not (scene / "gt").is_dir():
            print(f"error: {scene} is not a synthetic scene (no gt/)", file=sys.stderr)
            return None
    return scenes


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--stop_after", choices=("initial", "bundle"), default="bundle")
    parser.add_argument("--per_image", action="store_true")
    args = parser.parse_args(argv)
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    for scene in scenes:
        options = _options(scene, args)
        inputs, outcomes, wall = _stage12(scene, options, Path(args.cache_path))
        cam = next(iter(inputs.priors.cameras.values()))
        print(
            f"{scene.name} ({cam.width}x{cam.height}): stages 1-2"
            + (f" {wall:.0f} s" if wall is not None else " cached")
            + (f"; overrides {args.set}" if args.set else "")
        )
        gt, gtb, by_name = _truth_local(scene, inputs)
        stage2_report(scene, inputs, outcomes, gt, gtb, by_name, args.per_image)
        if args.stop_after == "bundle":
            stage3_report(
                scene, inputs, outcomes, options, gt, gtb, by_name, args.per_image
            )
    print(f"load average {os.getloadavg()}, {time.strftime('%Y-%m-%d %H:%M')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
