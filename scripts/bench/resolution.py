"""Where the accuracy goes with the image resolution: stage 2 and 3 figures.

Per synthetic scene (e.g. the same ``paper`` scene at 2004 and at 4008 px),
one ``register`` run split at the end of stage 2 (stages 1-2 cached by
their options, ``split_runs.py``), then for stage 2: per image the vertical
segments, the inlier corners (two vertical constraints each) and the
across-vertical deviation of the per-image registration; the image scale (px
per metre across the vertical at the inlier corners) and the residuals of
the inlier pairs at the TRUE cameras (map-corner noise + edge noise, in px
and in metres on the ground); for stage 3: the bundle's rounds (rejections,
per-kind sigmas, from its log), the final constraints and per-kind residual
spread, the same residuals at the true cameras, and the evaluation (full,
across the vertical, and with the camera-height offset).

Run (from the repository root)::

    python scripts/bench/resolution.py --scene_path /work/scenes/paper_s1 \\
        --scene_path /work/scenes/paper4k_s1 [--set PATH=VALUE ...] \\
        [--stop_after initial] [--per_image] [--cache_path /tmp/bench_resolution]

Figures: docs/journal/stage3-bundle.md (the stage-2 part also in
docs/journal/stage2-registration.md); a diagnosis, not a figure of
docs/STATUS.md.

Data: synthetic scenes, made with ``obliq-colmap synth --preset paper --seed N
[--image_width 4008] --output_path DIR``; the stage 1-2 cache under
``--cache_path`` (shared with the other split-run scripts).

Options of stages 1-3 can be overridden by dotted paths (``--set
adjustment.bundle.loss_scale_px=2``, ``--set registration.inlier_threshold_px=4``):
a quick test of which threshold matters.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from obliq_colmap import adjustment as adj
from obliq_colmap.adjustment import triangulate_tracks
from obliq_colmap.bundle import residuals as res

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from split_runs import (  # noqa: E402
    evaluate_state,
    format_evaluation,
    run_options,
    scene_parser,
    stage12,
    synthetic_scenes,
    truth_local,
)


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


def _vertical_at_truth(cam, pose, xy: np.ndarray, h: np.ndarray, line: np.ndarray):
    """(M,) signed px distances of points (xy, h) projected to lines (M, 3)."""
    X = pose.transform(np.column_stack([xy, h]))
    px = cam.img_from_cam(X)
    return np.sum(line[:, :2] * px, axis=1) + line[:, 2]


def stage2_report(scene, inputs, outcomes, gt, gtb, by_name, per_image=False) -> None:
    reg = [o for o in outcomes.values() if o.registered]
    state = adj.BlockState.from_outcomes(reg)
    full, across, _ = evaluate_state(inputs, state, gt)
    print(format_evaluation("stage 2 full", full))
    print(format_evaluation("stage 2 across vert.", across))
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
    # Stage 3's log: its modules' loggers (obliq_colmap.adjustment.matching,
    # .problem, .rounds ...) pass their records up to the package's.
    loggers = [logging.getLogger("obliq_colmap.adjustment")]
    for lg in loggers:
        lg.addHandler(log)
        lg.setLevel(logging.INFO)
        lg.propagate = False
    try:
        t0 = time.perf_counter()
        adjusted = adj.bundle_stage(
            inputs, outcomes, state, options.adjustment, timings
        )
        new, result, stage3 = adjusted.state, adjusted.bundle, adjusted.stage3
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
    full, across, cameras = evaluate_state(inputs, new, gt)
    print(format_evaluation("bundle full", full))
    print(format_evaluation("bundle across vert.", across))
    print(format_evaluation("bundle full, cam. dz", cameras))
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


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--stop_after", choices=("initial", "bundle"), default="bundle")
    parser.add_argument("--per_image", action="store_true")
    args = parser.parse_args(argv)
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    for scene in scenes:
        options = run_options(scene, args)
        inputs, outcomes, _, wall = stage12(scene, options, Path(args.cache_path))
        cam = next(iter(inputs.priors.cameras.values()))
        print(
            f"{scene.name} ({cam.width}x{cam.height}): stages 1-2"
            + (f" {wall:.0f} s" if wall is not None else " cached")
            + (f"; overrides {args.set}" if args.set else "")
        )
        gt, gtb, by_name = truth_local(scene, inputs)
        stage2_report(scene, inputs, outcomes, gt, gtb, by_name, args.per_image)
        if args.stop_after == "bundle":
            stage3_report(
                scene, inputs, outcomes, options, gt, gtb, by_name, args.per_image
            )
    print(f"load average {os.getloadavg()}, {time.strftime('%Y-%m-%d %H:%M')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
