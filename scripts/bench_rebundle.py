"""Is stage 3 stable when it runs again from its own solved block?

``register`` solves the bundle a second time when an image registered again
against the solved block joins it. This script runs ``bundle_stage`` on the
cached stage 1-2 outcomes of a scene (``bench_resolution.py``'s cache: the
scene's prior noise as the registration's sigmas), then ``--rounds`` more
times, each from the state the previous one returned, and prints the full
deviation of each round and the datum corrections the facade matches asked
for (near zero on a solved block)::

    python scripts/bench_rebundle.py --scene_path /work/scenes/paper_s1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_resolution as brz  # noqa: E402

from obliq_colmap import adjustment as adj  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene_path", required=True, type=Path)
    ap.add_argument("--rounds", type=int, default=2, help="rounds after the first")
    ap.add_argument("--cache_path", default="/tmp/bench_resolution", type=Path)
    a = ap.parse_args()
    options = brz._options(a.scene_path, argparse.Namespace(num_workers=2, set=None))
    inputs, outcomes, _ = brz._stage12(a.scene_path, options, a.cache_path)
    gt, _, _ = brz._truth_local(a.scene_path, inputs)
    registered = [o for o in outcomes.values() if o.registered]
    state = adj.BlockState.from_outcomes(registered)
    for k in range(a.rounds + 1):
        state, result, stage3 = adj.bundle_stage(
            inputs, outcomes, state, options.adjustment, {}
        )
        full, _, _ = brz._evaluate(inputs, state, gt)
        dc = np.abs(np.asarray(stage3.tracks.datum_correction))
        dc = dc[np.isfinite(dc)]
        worst = [
            f"{e.name} {e.mean_deviation_px:.1f}"
            for e in full.images
            if e.mean_deviation_px is not None and e.mean_deviation_px >= 2.0
        ]
        print(brz._fmt_eval(f"round {k}", full))
        print(
            f"    {stage3.tracks.num_tracks} tracks, {stage3.tracks.num_observations}"
            f" observations; datum corrections asked |e| median / p90 / max "
            f"{np.median(dc):.2f} / {np.percentile(dc, 90):.2f} / {dc.max():.2f} m;"
            f" >= 2 px: {', '.join(worst) or 'none'}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
