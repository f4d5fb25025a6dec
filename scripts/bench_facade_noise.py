"""Facade observation noise at the TRUE cameras: LSD's endpoints vs the refit.

For each synthetic scene, one ``register`` run split at the end of stage 2
with the refit OFF (its default, ``refine_segments=None``; stages 1-2 cached as in
``bench_resolution.py``), its facade tracks formed as the pipeline forms
them, and each track triangulated at the true cameras as a horizontal line
parallel to its map edge (:func:`matching.triangulate_tracks`, offset and
height). The noise of an observation is the distance (px) from its segment's
line to the projection of the track's anchor point on that line, over the
tracks with at least ``--min_views`` views, scaled by sqrt(n / (n - 2)) for
the two unknowns per track. The same observations are then measured with
their segments refitted on the image (:func:`lines.refine_segments`, the
default ``RefineOptions``): the matching is not rerun, so both columns
measure the same rows.

    python scripts/bench_facade_noise.py --scene_path /work/scenes/paper_s1 \\
        [--scene_path ...] [--set registration.refine_distortion=True]
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import cv2
import numpy as np
from bench_resolution import (
    _options,
    _stage12,
    _truth_local,
    scene_parser,
    synthetic_scenes,
)

from obliq_colmap import adjustment as adj
from obliq_colmap.lines import RefineOptions, Segments, refine_segments
from obliq_colmap.matching import triangulate_tracks


def observation_noise(stage3, inputs, cameras, poses, ends) -> np.ndarray:
    """(H,) px: each observation's line to its track's anchor, at ``cameras``."""
    t = stage3.tracks
    offsets = np.cumsum([0] + [len(f) for f in stage3.facades])
    ppm = np.concatenate([f.px_per_m for f in stage3.facades])[offsets[t.image] + t.row]
    normal = inputs.cadastre.edge_normal[t.edge]
    d, h = triangulate_tracks(
        t.image, t.track, ends, cameras, poses, t.anchor_xy, normal, ppm, 1e3
    )
    r = np.full(len(t.image), np.nan)
    for k in np.unique(t.image):
        sel = np.flatnonzero(t.image == k)
        j = t.track[sel]
        point = np.column_stack([t.anchor_xy[j] + d[j, None] * normal[j], h[j]])
        px = cameras[k].img_from_cam(poses[k].transform(point))
        a = np.column_stack([ends[sel, 0], np.ones(len(sel))])
        b = np.column_stack([ends[sel, 1], np.ones(len(sel))])
        line = np.cross(a, b)
        line /= np.linalg.norm(line[:, :2], axis=1, keepdims=True)
        r[sel] = np.abs(np.sum(line[:, :2] * px, axis=1) + line[:, 2])
    return r


def run_scene(scene: Path, args) -> None:
    args.set = ["refine_segments=None", *(args.set or [])]
    options = _options(scene, args)
    inputs, outcomes, _ = _stage12(scene, options, Path(args.cache_path))
    _, gtb, by_name = _truth_local(scene, inputs)
    registered = [o for o in outcomes.values() if o.registered]
    state = adj.BlockState.from_outcomes(registered)
    stage3 = adj.facade_stage(inputs, state, outcomes, options.adjustment)
    adj.build_bundle_problem(inputs, outcomes, state, stage3)
    ids, t = stage3.ids, stage3.tracks
    truth = [by_name[inputs.priors.images[i].name] for i in ids]
    cameras = [gtb.cameras[x.camera_id] for x in truth]
    poses = [x.cam_from_world for x in truth]
    ends = stage3.ends_raw
    refitted = ends.copy()
    for k, i in enumerate(ids):
        sel = np.flatnonzero(t.image == k)
        image = inputs.priors.images[i]
        gray = cv2.imread(str(scene / "images" / image.name), cv2.IMREAD_GRAYSCALE)
        rows = stage3.facades[k].segment[t.row[sel]]
        first = outcomes[i].line_segments
        segs = Segments(
            ends[sel], first.normal[rows], first.strength[rows], first.pixel_scale
        )
        # raw pixels in and out: the priors' camera is what the pipeline uses
        camera = inputs.priors.cameras[image.camera_id]
        und = segs.undistorted(camera)
        out = refine_segments(gray, und, camera, RefineOptions())
        refitted[sel] = camera.distort_pixels(out.endpoints.reshape(-1, 2)).reshape(
            -1, 2, 2
        )
    n = np.bincount(t.track, minlength=t.num_tracks)[t.track]
    keep = n >= args.min_views
    for label, e in (("LSD", ends), ("refitted", refitted)):
        r = observation_noise(stage3, inputs, cameras, poses, e)[keep]
        r = r * np.sqrt(n[keep] / (n[keep] - 2.0))
        r = r[np.isfinite(r)]
        print(
            f"{scene.name:16s} {label:9s} {len(r)} observations: |r| p50 "
            f"{np.median(r):.3f} p90 {np.percentile(r, 90):.3f} px, "
            f"< 1 px {100 * np.mean(r < 1):.1f} %",
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--min_views", type=int, default=4)
    args = parser.parse_args(argv)
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    logging.getLogger("obliq_colmap").setLevel(logging.WARNING)
    base = list(args.set or [])
    for scene in scenes:
        args.set = list(base)
        run_scene(scene, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
