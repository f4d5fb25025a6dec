"""Do the ends of the stage-2 inlier vertical segments mark one 3D point per
map corner? Measured at the TRUE cameras of a synthetic scene.

For every map corner that is an inlier of two or more images, the heights at
which the rays through its segments' top and bottom endpoints meet the
corner's vertical (``adjustment._heights_on_vertical``, the true camera and
pose): the spread within the corner (MAD), and for corners seen by several
heads the range of the per-head medians. A consistent top (or bottom) would
tie the heads' heights in the bundle; the answer decides whether to build
such constraints.

Stage 1-2 outcomes come from ``bench_resolution.py``'s cache (the scene's
prior noise as the registration's sigmas), computed on first use::

    python scripts/bench_corner_ends.py --scene_path /work/scenes/paper_s1
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_resolution as brz  # noqa: E402

from obliq_colmap import adjustment as adj  # noqa: E402
from obliq_colmap.synthetic import load_scene  # noqa: E402


def end_heights(
    scene_path: Path, cache: Path
) -> dict[int, list[tuple[str, float, float]]]:
    """Per map corner: (head letter, top height, bottom height) per inlier."""
    args = argparse.Namespace(num_workers=2, set=None)
    options = brz._options(scene_path, args)
    inputs, outcomes, _ = brz._stage12(scene_path, options, cache)
    scene = load_scene(scene_path)
    cad = inputs.cadastre
    shift = cad.origin[:2] - scene.origin[:2]  # map frame -> scene frame
    out: dict[int, list] = collections.defaultdict(list)
    items = outcomes.values() if isinstance(outcomes, dict) else outcomes
    for o in items:
        r = o.registration
        if r is None or not r.success:
            continue
        cam, pose = scene.camera_pose(o.name)
        c = r.inlier_pairs[:, 0]
        ends = r.inlier_segments_px
        xy = cad.corner_xy[c] + shift
        h0 = adj._heights_on_vertical(cam, pose, xy, ends[:, 0])
        h1 = adj._heights_on_vertical(cam, pose, xy, ends[:, 1])
        for k, corner in enumerate(c.tolist()):
            out[corner].append((o.name[0], max(h0[k], h1[k]), min(h0[k], h1[k])))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene_path", required=True, type=Path)
    ap.add_argument("--cache_path", default="/tmp/bench_resolution", type=Path)
    a = ap.parse_args()
    per_corner = end_heights(a.scene_path, a.cache_path)
    for k, label in ((1, "top"), (2, "bottom")):
        mad, cross = [], []
        for obs in per_corner.values():
            if len(obs) < 2:
                continue
            h = np.array([x[k] for x in obs])
            mad.append(np.median(np.abs(h - np.median(h))))
            heads = {x[0] for x in obs}
            if len(heads) > 1:
                med = [np.median([x[k] for x in obs if x[0] == d]) for d in heads]
                cross.append(max(med) - min(med))
        mad, cross = np.array(mad), np.array(cross)
        q = [np.percentile(mad, p) for p in (50, 75, 90)]
        qc = [np.percentile(cross, p) for p in (50, 75, 90)]
        print(
            f"{label:6s}: {len(mad)} corners in 2+ images, MAD median / p75 / p90 "
            f"{q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f} m; {len(cross)} in 2+ heads, "
            f"range of the head medians {qc[0]:.3f} / {qc[1]:.3f} / {qc[2]:.3f} m"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
