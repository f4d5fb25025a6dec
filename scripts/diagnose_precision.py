"""Where each image's predicted precision comes from.

For the last bundle of split runs (``bench_seeds.py``'s path and cache), the
predicted sd (px) of each image's constrained points (as
``BundleResult.image_precision_px``) and the same with one block of the
image's parameters known, i.e. from the conditional covariance given its
rotation, its camera height, or its head's intrinsics. Where the sd drops
most, that block is the weak direction. Prints the medians over the images
of each run (docs/BENCHMARKS.md, issue 5, "The bundle's a-posteriori
precision per image"):

    python scripts/diagnose_precision.py --scene_path /work/scenes/paper_s1 \\
        --seeds 0 [--set PATH=VALUE ...]
"""

from __future__ import annotations

import sys

import numpy as np
from bench_resolution import scene_parser, synthetic_scenes
from bench_seeds import run_once

from obliq_colmap.bundle import solver

_ORIGINAL = solver._image_precision
#: One dict per bundle solved: image id -> {condition: variance (px^2)}.
_SOLVES: list[dict[int, dict[str, float]]] = []


def _conditional(J: np.ndarray, C: np.ndarray, known: list[int]) -> float:
    """Mean over the points of the 2D variance of their projections (J:
    (n, 2, p)) under covariance C (p, p) with the parameters ``known``."""
    if known:
        rest = [i for i in range(len(C)) if i not in known]
        C_rk = C[np.ix_(rest, known)]
        C = C[np.ix_(rest, rest)] - C_rk @ np.linalg.solve(
            C[np.ix_(known, known)], C_rk.T
        )
        J = J[:, :, rest]
    return float(np.mean(np.einsum("npi,ij,npj->n", J, C, J)))


def _recording(S, st, cov):
    """``solver._image_precision`` that also records the conditional sds
    (on the same Jacobians, :func:`solver._image_jacobians`)."""
    out = _ORIGINAL(S, st, cov)
    record = {}
    for k, J, cols in solver._image_jacobians(S, st):
        C = cov[np.ix_(cols, cols)]
        intrinsics = list(range(6, len(cols)))
        record[S.image_ids[k]] = {
            "all": _conditional(J, C, []),
            "given intrinsics": _conditional(J, C, intrinsics),
            "given camera height": _conditional(J, C, [5]),
            "given rotation": _conditional(J, C, [0, 1, 2]),
            "given height + intrinsics": _conditional(J, C, [5, *intrinsics]),
        }
    _SOLVES.append(record)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--bundle_only", action="store_true")
    args = parser.parse_args(argv)
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    args.base_set = list(args.set or [])
    solver._image_precision = _recording
    for scene in scenes:
        for seed in args.seeds:
            _SOLVES.clear()
            row = run_once(scene, seed, args)
            last = _SOLVES[-1]
            keys = list(next(iter(last.values())))
            sd = np.sqrt(np.median([[v[k] for k in keys] for v in last.values()], 0))
            parts = ", ".join(f"{k} {x:.3f}" for k, x in zip(keys, sd, strict=True))
            print(
                f"{scene.name} seed {seed}: median deviation"
                f" {row['median_px']:.3f} px; predicted sd (median over images,"
                f" px): {parts}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
