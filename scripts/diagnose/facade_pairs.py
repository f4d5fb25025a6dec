"""Stage 3's facade pairs against the truth: how many matched the wrong floor.

For split runs (stages 1-2 cached, ``split_runs.py``), the facade edges and
pair matching of the first block (the stage-2 poses), and per pair the true
height difference of its matched segments: each segment's midpoint cast
through the TRUE camera onto the wall plane of its map edge. A pair whose
median true difference exceeds ``--limit`` m matched edges at different
heights (a window row a floor off, or another edge); the per-image heights
it was matched in were that far off. Prints per run the pairs, the wrong
ones and their matches. With ``--oracle`` the run then goes on as
``register`` does after stage 2 (``split_runs.run_once``) with the wrong
pairs removed before the tracks are formed, every stage-3 round: what
perfect pair rejection would give.

Run (from the repository root)::

    python scripts/diagnose/facade_pairs.py --scene_path /work/scenes/hard_s1 \\
        --seeds 0 1 2 [--oracle] [--set PATH=VALUE ...]

Figures: docs/journal/stage3-bundle.md (issue 5, "Facade pairs a floor off",
2026-12-03); the live question is issue 26 (facade edges as lines, tracks
weighted by their own noise).

Data: synthetic scenes (``obliq-colmap synth``); the stage 1-2 cache under
``--cache_path`` (shared with ``bench/seeds.py``).

The wall-plane height of a segment off the wall (a roof rim's overhang, a
recessed window) differs between viewing directions by its offset times the
difference of the cotangents, a few tenths of a metre: hence the 1 m limit.

``--oracle`` replaces ``facade_stage`` in ``obliq_colmap.adjustment.rounds``
(the module of ``bundle_stage``, where it looks the name up) and rebuilds
the tracks as the matching does (``adjustment.points_along_edges``,
``datum_corrections``, ``chain_tracks``): it follows stage 3's internals and
must move with them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from obliq_colmap import adjustment as adj
from obliq_colmap.adjustment import rounds

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from split_runs import (  # noqa: E402
    run_once,
    scene_parser,
    seed_options,
    stage12,
    summary,
    synthetic_scenes,
    truth_local,
)

_FACADE_STAGE = rounds.facade_stage
#: The run's truth (block, images by name) and the wrong-pair limit (m).
_TRUTH: dict = {}


def true_heights(inputs, stage3, state, outcomes, by_name, k, rows) -> np.ndarray:
    """(R,) heights (m, local) of image slot k's facade rows on their walls,
    seen through the true camera of that image."""
    cad = inputs.cadastre
    im = by_name[outcomes[stage3.ids[k]].name]
    cam = _TRUTH["block"].cameras[im.camera_id]
    f = stage3.facades[k]
    # facade rows are undistorted with the image's stage-2 camera
    raw = state.cameras[stage3.ids[k]].distort_pixels(f.endpoints[rows].mean(axis=1))
    rays = np.column_stack([cam.cam_from_img(raw), np.ones(len(rows))])
    rays = rays @ im.cam_from_world.rotation  # world directions
    c = im.cam_from_world.center
    e, n = cad.edge_xy[f.edge[rows]], cad.edge_normal[f.edge[rows]]
    lam = np.sum((e[:, 0] - c[:2]) * n, axis=1) / np.sum(rays[:, :2] * n, axis=1)
    return c[2] + lam * rays[:, 2]


def pair_errors(inputs, stage3, state, outcomes) -> np.ndarray:
    """(P,) median true height difference (m) of each pair's matches."""
    by_name = _TRUTH["by_name"]
    out = []
    for p in stage3.tracks.pairs:
        ha = true_heights(inputs, stage3, state, outcomes, by_name, p.a, p.rows_a)
        hb = true_heights(inputs, stage3, state, outcomes, by_name, p.b, p.rows_b)
        out.append(float(np.median(ha - hb)))
    return np.array(out)


def _oracle_facade_stage(inputs, state, outcomes, options):
    """``adjustment.facade_stage`` with the truly wrong pairs removed."""
    s3 = _FACADE_STAGE(inputs, state, outcomes, options)
    err = pair_errors(inputs, s3, state, outcomes)
    keep = [
        p
        for p, e in zip(s3.tracks.pairs, err, strict=True)
        if abs(e) <= _TRUTH["limit"]
    ]
    cad = inputs.cadastre
    anchors = [
        adj.points_along_edges(cad.edge_xy[f.edge], cad.edge_length[f.edge], f.s)
        for f in s3.facades
    ]
    grounds = np.array([state.planes[i] for i in s3.ids]).reshape(-1, 3)
    correction = adj.datum_corrections(keep, len(s3.ids))
    tracks = adj.chain_tracks(
        s3.facades, anchors, grounds, correction, keep, options.matching
    )
    return adj.Stage3(s3.ids, s3.facades, tracks)


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--limit", type=float, default=1.0, help="m")
    parser.add_argument("--oracle", action="store_true")
    parser.add_argument("--bundle_only", action="store_true")
    args = parser.parse_args(argv)
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    args.base_set = list(args.set or [])
    _TRUTH["limit"] = args.limit
    rows, totals = [], np.zeros(4, int)
    for scene in scenes:
        for seed in args.seeds:
            options = seed_options(scene, seed, args)
            inputs, outcomes, _, _ = stage12(scene, options, Path(args.cache_path))
            _, gtb, by_name = truth_local(scene, inputs)
            _TRUTH.update(block=gtb, by_name=by_name)
            state = adj.BlockState.from_outcomes(
                [o for o in outcomes.values() if o.registered]
            )
            s3 = _FACADE_STAGE(inputs, state, outcomes, options.adjustment)
            err = pair_errors(inputs, s3, state, outcomes)
            n = np.array([p.num_matches for p in s3.tracks.pairs])
            wrong = np.abs(err) > args.limit
            totals += [len(n), wrong.sum(), n[wrong].sum(), n.sum()]
            line = (
                f"{scene.name} seed {seed}: {len(n)} pairs, {wrong.sum()} wrong"
                f" ({n[wrong].sum()} of {n.sum()} matches)"
            )
            if args.oracle:
                rounds.facade_stage = _oracle_facade_stage  # bundle_stage's
                try:
                    r = run_once(scene, seed, args)
                finally:
                    rounds.facade_stage = _FACADE_STAGE
                rows.append(r)
                line += (
                    f"; without them: {r['registered']}/{r['total']} < 2 px, median"
                    f" {r['median_px']:.3f} p95 {r['p95_px']:.3f} max"
                    f" {r['max_px']:.3f} px, left out {r['left_out']}, written > 5 px"
                    f" off {r['written_over_5px']}"
                )
            print(line, flush=True)
    share = 100 * totals[[1, 2]] / np.maximum(totals[[0, 3]], 1)
    print(
        f"all: {totals[0]} pairs, {totals[1]} wrong ({share[0]:.1f} %),"
        f" {totals[2]} of {totals[3]} matches ({share[1]:.1f} %)"
    )
    if rows:
        print(summary(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
