"""How far the bundle's result is from what its observations allow.

One ``register`` run of a synthetic scene, split after stage 2 (stages 1-2
cached, ``split_runs.py``), then the bundle as the pipeline solves it. Its
FINAL problem (constraints, weights, loss) is then solved again with some of
its image observations replaced by exact ones, from the TRUE cameras, each
variant scored with ``evaluate``'s full and across-vertical deviation: what
limits the full deviation, the lines' noise, the map or the tracks.

Run (from the repository root)::

    python scripts/diagnose/bundle_limit.py --scene_path /work/scenes/paper_s1 \\
        [--seeds 2] [--set PATH=VALUE ...]

Figures: docs/journal/stage3-bundle.md (issue 5, "What limits the full
deviation", 2026-12-02, and the limit analysis in the scene-datum measure);
the live question is issue 26 (what the bundle's constraint model leaves
unused).

Data: synthetic scenes (``obliq-colmap synth``); the stage 1-2 cache under
``--cache_path`` (shared with ``bench/seeds.py``).

The exact observations:

* a vertical constraint's line becomes the true camera's image of the
  vertical through the TRUE building corner nearest to its map corner (the
  map corner, with the map's own errors, stays in the problem);
* a facade row's line becomes the true image of its track's line, the track
  triangulated at the true cameras as a free 3D horizontal line (offset from
  the wall and height), and that line's offset is the row's anchor.

Both are the tangents of those (distorted) images at the points the
residuals project, so exact rows have zero residual at the truth. The true
cameras are moved into the problem's vertical datum (the median camera
height difference; ``evaluate`` removes one vertical offset anyway).

Gaussian noise (``--vertical_noise_px``, ``--horizontal_noise_px``) is added
across the exact lines. Variants (each solved from the true cameras unless
said otherwise):

* ``exact``: both kinds exact, the real map: the limit of this constraint
  set with perfect line detection;
* ``exact, true map``: also the map corners at the true corners;
* ``real V``: the real vertical lines, exact facade lines;
* ``real H``: exact vertical lines, the real facade lines (true anchors);
* ``real V+H, true tracks``: the real lines of both kinds with the track
  geometry (anchors, heights) triangulated at the true cameras;
* ``real, from truth``: the final problem as it is, started at the true
  cameras.

The bundle's last problem is caught by replacing ``solve_bundle`` in
``obliq_colmap.adjustment.rounds`` (the module of ``bundle_stage``, where it
looks the name up) with a spy: it follows stage 3's internals and must move
with them.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from obliq_colmap import adjustment as adj
from obliq_colmap.adjustment import rounds, triangulate_tracks
from obliq_colmap.bundle import BundleProblem, solve_bundle
from obliq_colmap.geometry import Pose, lines_through

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import split_runs as sr  # noqa: E402


def _final_problem(inputs, outcomes, options):
    """The bundle as the pipeline runs it, and its last (problem, options)."""
    calls = []

    def spy(problem, opts):
        result = solve_bundle(problem, opts)
        calls.append((problem, opts, result))
        return result

    saved = rounds.solve_bundle
    rounds.solve_bundle = spy  # where bundle_stage looks it up
    try:
        state = adj.BlockState.from_outcomes(
            [o for o in outcomes.values() if o.registered]
        )
        adjusted = adj.bundle_stage(inputs, outcomes, state, options.adjustment, {})
    finally:
        rounds.solve_bundle = saved
    if not calls:
        raise SystemExit("error: the bundle did not run (no facade constraints)")
    return state, adjusted.state, adjusted.stage3, calls[-1]


def _exact_lines(problem: BundleProblem, inputs, stage3, gt, gtb, by_name):
    """Exact vertical lines (M, 3), facade lines (H, 3), their anchors (H, 2),
    the true track heights (J,) and the true cameras and poses."""
    P, cad = problem, inputs.cadastre
    ids = P.image_ids
    truth = [by_name[inputs.priors.images[i].name] for i in ids]
    cams = [gtb.cameras[t.camera_id] for t in truth]
    # The truth in the problem's vertical datum (the priors' heights, a
    # datum offset away): under a lens the image of a vertical is curved,
    # so a point slid along it by the datum offset leaves the segment.
    dz = np.median(
        [
            P.poses[i].center[2] - t.cam_from_world.center[2]
            for i, t in zip(ids, truth, strict=True)
        ]
    )
    poses = [
        Pose.from_center(
            t.cam_from_world.rotation, t.cam_from_world.center + [0, 0, dz]
        )
        for t in truth
    ]
    corners = gt.corners_world - np.array([cad.origin[0], cad.origin[1], 0.0])
    _, nearest = cKDTree(corners[:, :2]).query(P.corner_xy[P.vertical_corner])
    xy_true = corners[nearest, :2]

    def image_lines(k, a_world, b_world):
        project = lambda X: cams[k].img_from_cam(poses[k].transform(X))  # noqa: E731
        return lines_through(project(a_world), project(b_world))

    # Lines tangent to the (distorted) images of the true lines at the
    # points the residuals project: exact for every camera model.
    zv = P.corner_heights[P.vertical_corner][:, None]
    vl = np.zeros((len(P.vertical_image), 3))
    for k in range(len(ids)):
        m = P.vertical_image == k
        if m.any():
            vl[m] = image_lines(
                k,
                np.hstack([xy_true[m], zv[m] - 0.5]),
                np.hstack([xy_true[m], zv[m] + 0.5]),
            )
    t = stage3.tracks
    offsets = np.cumsum([0] + [len(f) for f in stage3.facades])
    ppm = np.concatenate([f.px_per_m for f in stage3.facades])[offsets[t.image] + t.row]
    normal = cad.edge_normal[t.edge]
    d, h = triangulate_tracks(
        t.image, t.track, stage3.ends_raw, cams, poses, t.anchor_xy, normal, ppm, 1e6
    )
    d, h = np.nan_to_num(d), np.where(np.isfinite(h), h, t.height)
    along = np.column_stack([-normal[:, 1], normal[:, 0]])
    j = P.horizontal_height
    anchor = t.anchor_xy[j] + d[j, None] * normal[j]
    hl = np.zeros((len(j), 3))
    for k in range(len(ids)):
        m = P.horizontal_image == k
        if m.any():
            z = h[j[m], None]
            hl[m] = image_lines(
                k,
                np.hstack([anchor[m] - 0.5 * along[j[m]], z]),
                np.hstack([anchor[m] + 0.5 * along[j[m]], z]),
            )
    true_cams = {c: gtb.cameras[c] for c in P.cameras}
    true_poses = dict(zip(ids, poses, strict=True))
    return vl, xy_true, hl, anchor, h, true_cams, true_poses


def run_scene(scene: Path, args: argparse.Namespace) -> None:
    """All variants of one scene, printed."""
    options = sr.run_options(scene, args)
    inputs, outcomes, _, _ = sr.stage12(scene, options, Path(args.cache_path))
    gt, gtb, by_name = sr.truth_local(scene, inputs)
    state, new, stage3, (P, opts, _) = _final_problem(inputs, outcomes, options)
    print(f"{scene.name}" + (f"; overrides {args.set}" if args.set else ""))

    def report(label: str, problem: BundleProblem) -> None:
        result = solve_bundle(problem, opts)
        full, across, _ = sr.evaluate_state(
            inputs, state.with_bundle(result, P.image_camera), gt
        )
        print(sr.format_evaluation(f"{label}, full", full).replace("  ", " ", 1))
        print(sr.format_evaluation(f"{label}, across", across).replace("  ", " ", 1))
        print(f"      cost {result.summary.final_cost:.1f}")

    full, across, _ = sr.evaluate_state(inputs, new, gt)
    print(sr.format_evaluation("pipeline's bundle, full", full))
    print(sr.format_evaluation("pipeline's bundle, across", across))
    vl, xy_true, hl, anchor, h, cams, poses = _exact_lines(
        P, inputs, stage3, gt, gtb, by_name
    )
    heights = P.facade_heights.copy()
    heights[: len(h)] = h
    start = dict(cameras=cams, poses=poses)
    tracks = dict(horizontal_anchor_xy=anchor, facade_heights=heights)
    report("real, from truth", dataclasses.replace(P, **start))
    report("real V+H, true tracks", dataclasses.replace(P, **start, **tracks))
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        v = vl.copy()
        v[:, 2] += args.vertical_noise_px * rng.standard_normal(len(v))
        hh = hl.copy()
        hh[:, 2] += args.horizontal_noise_px * rng.standard_normal(len(hh))
        true_map = P.corner_xy.copy()
        true_map[P.vertical_corner] = xy_true
        for label, change in (
            ("exact", dict(vertical_line=v, horizontal_line=hh)),
            (
                "exact, true map",
                dict(vertical_line=v, horizontal_line=hh, corner_xy=true_map),
            ),
            ("real V", dict(horizontal_line=hh)),
            ("real H", dict(vertical_line=v)),
        ):
            report(
                f"{label} (seed {seed})",
                dataclasses.replace(P, **start, **tracks, **change),
            )


def main(argv: list[str] | None = None) -> int:
    parser = sr.scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--vertical_noise_px", type=float, default=0.3)
    parser.add_argument("--horizontal_noise_px", type=float, default=0.1)
    parser.add_argument("--seeds", type=int, default=2)
    args = parser.parse_args(argv)
    scenes = sr.synthetic_scenes(args)
    if scenes is None:
        return 2
    for scene in scenes:
        run_scene(scene, args)
    print(f"load average {os.getloadavg()}, {time.strftime('%Y-%m-%d %H:%M')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
