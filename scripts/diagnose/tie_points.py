"""What point tie observations would add to each image's precision (a what-if).

The bundle's constraints (map corners on vertical lines, facade edges with
free heights) leave each image's vertical direction traded against its
centre as the weak direction (``diagnose/precision.py``). Image-to-image tie
points (e.g. SIFT matches of a COLMAP database: ground, roofs, facades) tie
the neighbouring images' relative orientation. This script takes the last
bundle of split runs (stages 1-2 cached, ``split_runs.py``) at its optimum
and adds, to the information of the camera block, that of hypothetical tie
points: ``--points_per_image`` random 3D points per image footprint between
the ground and ``--max_height_m`` above it, each observed
(``--tie_sigma_px``) in every image of the same head (``--cross_head``: of
any head) in which it projects inside the frame (occlusions ignored: an
upper bound for those points), each point's three coordinates free
(eliminated, Schur complement). Prints the median over the images of the
predicted sd (px, as ``BundleResult.image_precision_px``) without and with
them.

Run (from the repository root)::

    python scripts/diagnose/tie_points.py --scene_path /work/scenes/paper_s1 \\
        --seeds 0 --bundle_only [--points_per_image 50 300] [--cross_head]

Figures: docs/journal/stage3-bundle.md (issue 5, "What more information
would give", 2026-12-03); the live question is issue 26 (tie points in the
bundle).

Data: synthetic scenes (``obliq-colmap synth``); the stage 1-2 cache under
``--cache_path`` (shared with ``bench/seeds.py``).

It replaces ``obliq_colmap.bundle.covariance.image_precision`` by a
recording wrapper and reads the solver's setup and state (their columns,
Jacobians, camera sizes): it follows the solver's layout and must move with
it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from obliq_colmap.bundle import covariance
from obliq_colmap.bundle import residuals as res
from obliq_colmap.geometry import skew

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from split_runs import observed, run_all, scene_parser, synthetic_scenes  # noqa: E402

_ORIGINAL = covariance.image_precision
_CTX: dict = {}
#: One dict per bundle solved: image id -> {variant: variance (px^2)}.
_SOLVES: list[dict[int, dict[str, float]]] = []


def _points(S, st, n_per_image: int, max_height: float, rng) -> np.ndarray:
    """(M, 3) random points over the block's constrained area (world)."""
    h_all = st.heights[np.maximum(S.hidx, 0)] if S.n_heights else S.zfix
    z = np.where(S.has_h, h_all, S.zfix)
    ground = float(np.percentile(z, 5))
    lo, hi = S.xy.min(axis=0), S.xy.max(axis=0)
    M = n_per_image * len(S.active_images)
    xy = lo + rng.random((M, 2)) * (hi - lo)
    return np.column_stack([xy, ground + max_height * rng.random(M)])


def _columns(S, k: int) -> np.ndarray:
    """Camera-block columns of image slot k: its pose, its head's intrinsics."""
    slot = int(S.img_cam[k])
    q = S.refined[slot].shape[1]
    return np.r_[S.pose_col[k] + np.arange(6), S.intr_col[slot] + np.arange(q)]


def _tie_information(S, st, X: np.ndarray, sigma: float, cross: bool) -> np.ndarray:
    """(n_red, n_red) camera-block information of tie points X (M, 3), their
    coordinates eliminated."""
    n, M = S.n_red, len(X)
    H = np.zeros((n, n))
    B = np.zeros((M, n, 3))  # per point: sum of J_c^T J_X (global columns)
    U = np.zeros((M, 3, 3))  # per point: sum of J_X^T J_X
    seen, head = {}, {}
    for k in S.active_images:
        slot = int(S.img_cam[k])
        Xc = (X - st.c[k]) @ st.R[k].T
        W, Hh = S.camera_size[slot]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = res.project_with_jacobian(S.camera_model[slot], st.params[slot], Xc)[0]
        seen[k] = (Xc[:, 2] > 0) & np.all((uv >= 0) & (uv <= [W, Hh]), axis=1)
        head[k] = S.camera_ids[slot]
    for k in S.active_images:
        # observed where another image (of its head unless cross) sees it too
        others = [j for j in seen if j != k and (cross or head[j] == head[k])]
        if not others:
            continue
        obs = seen[k] & np.any([seen[j] for j in others], axis=0)
        if not obs.any():
            continue
        slot = int(S.img_cam[k])
        cols = _columns(S, k)
        Xc = (X[obs] - st.c[k]) @ st.R[k].T
        _, d_pt, d_par = res.project_with_jacobian(
            S.camera_model[slot], st.params[slot], Xc
        )
        pose = [-d_pt @ skew(Xc), -d_pt @ st.R[k], d_par @ S.refined[slot]]
        Jc = np.concatenate(pose, axis=2) / sigma  # as covariance.image_jacobians
        Jx = (d_pt @ st.R[k]) / sigma
        H[np.ix_(cols, cols)] += np.einsum("npi,npj->ij", Jc, Jc)
        B[np.ix_(np.flatnonzero(obs), cols)] += np.einsum("npi,npj->nij", Jc, Jx)
        U[obs] += np.einsum("npi,npj->nij", Jx, Jx)
    used = np.linalg.det(U) > 1e-12
    Uinv = np.linalg.inv(U[used])
    L = np.linalg.cholesky(Uinv)  # (m, 3, 3)
    G = np.einsum("mij,mjk->mik", B[used], L)  # (m, n, 3)
    G = G.transpose(1, 0, 2).reshape(n, -1)
    _CTX["n_points"] = int(used.sum())
    return H - sp.csr_matrix(G) @ sp.csr_matrix(G).T


def _recording(S, st, cov):
    """``covariance.image_precision`` that also records the sd with the tie
    points of each density added (their information ``L L^T`` observed as
    ``L^T`` with unit sigma)."""
    out = _ORIGINAL(S, st, cov)
    record = {S.image_ids[k]: {"none": v**2} for k, v in out.items()}
    rng = np.random.default_rng(0)
    for n_pts in _CTX["densities"]:
        X = _points(S, st, n_pts, _CTX["max_height"], rng)
        info = _tie_information(S, st, X, _CTX["sigma"], _CTX["cross"])
        info = 0.5 * (np.asarray(info) + np.asarray(info).T)
        lam, V = np.linalg.eigh(info)
        L = V * np.sqrt(np.clip(lam, 0.0, None))
        new = _ORIGINAL(S, st, observed(cov, L.T, 1.0))
        label = f"{n_pts} points per image ({_CTX['n_points']} tied)"
        for k, v in new.items():
            record[S.image_ids[k]][label] = v**2
    _SOLVES.append(record)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--bundle_only", action="store_true")
    parser.add_argument("--points_per_image", type=int, nargs="+", default=[50, 300])
    parser.add_argument("--tie_sigma_px", type=float, default=0.5)
    parser.add_argument("--max_height_m", type=float, default=15.0)
    parser.add_argument("--cross_head", action="store_true")
    args = parser.parse_args(argv)
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    args.base_set = list(args.set or [])
    _CTX.update(
        densities=args.points_per_image,
        sigma=args.tie_sigma_px,
        max_height=args.max_height_m,
        cross=args.cross_head,
    )
    covariance.image_precision = _recording
    run_all(scenes, args, _SOLVES)
    return 0


if __name__ == "__main__":
    sys.exit(main())
