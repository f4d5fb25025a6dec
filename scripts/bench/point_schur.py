"""Time of the 3x3 point elimination (bundle/schur.py) at a tie-point scale,
on a random problem of that shape: P points, 2 rows per observation, each
row touching its image's camera columns only (stored dense, as the functions
take them).

    python scripts/bench/point_schur.py --points 4177 --observations 8494 --images 36
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from obliq_colmap.bundle.schur import (
    point_back_substitution,
    point_normal_blocks,
    point_schur,
)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=4177)
    ap.add_argument("--observations", type=int, default=8494)
    ap.add_argument("--images", type=int, default=36)
    ap.add_argument("--camera_params", type=int, default=7, help="per image")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    P, M, n, k = args.points, args.observations, args.images, args.camera_params
    pidx = np.r_[np.arange(P), rng.integers(0, P, M - P)]
    image = rng.integers(0, n, M)
    rows_p, rows_i = np.repeat(pidx, 2), np.repeat(image, 2)
    N, C = len(rows_p), n * k
    Jc = np.zeros((N, C))
    cols = rows_i[:, None] * k + np.arange(k)
    Jc[np.arange(N)[:, None], cols] = rng.normal(size=(N, k))
    Jp, r, w = rng.normal(size=(N, 3)), rng.normal(size=N), np.ones(N)
    t_build, t_elim = [], []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        H_pp, g_p, W, H_cc, g_c = point_normal_blocks(Jc, Jp, r, w, rows_p, P)
        t1 = time.perf_counter()
        reduced, coupled, Hinv = point_schur(H_pp, g_p, W, 1e-3)
        A = H_cc - reduced + 1e-3 * np.diag(np.clip(np.diag(H_cc), 1e-6, 1e32))
        dc = np.linalg.solve(A, -g_c + coupled)
        point_back_substitution(Hinv, g_p, W, dc)
        t2 = time.perf_counter()
        t_build.append(t1 - t0)
        t_elim.append(t2 - t1)
    print(f"points {P}  rows {N}  camera unknowns {C}")
    print(
        f"normal blocks {np.median(t_build):.3f} s  eliminate + solve + back "
        f"{np.median(t_elim):.3f} s  (median of {args.runs})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
