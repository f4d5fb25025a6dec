"""Where each image's predicted precision comes from (the bundle's weak direction).

For the last bundle of split runs (stages 1-2 cached, ``split_runs.py``),
the predicted sd (px) of each image's constrained points (as
``BundleResult.image_precision_px``) and the same with one block of the
image's parameters known, i.e. from the conditional covariance given its
rotation, its camera height, or its head's intrinsics; the rotation split
into the image's vertical direction (tilt and roll: what a vanishing point
measures) and its heading; and the sd with the vertical direction OBSERVED
with a standard deviation of ``--vp_sigma_deg`` (each value; e.g. stage 1's
vanishing point as one more observation). Block-wide: the sd given the whole
block's tilt (all cameras turned together about the horizontal axes through
their mean centre, the centres turning with them), and with every camera
centre observed at ``--centre_sigma_m`` (each value: GNSS). Where the sd
drops most, that block is the weak direction. Prints the medians over the
images of each run.

Run (from the repository root)::

    python scripts/diagnose/precision.py --scene_path /work/scenes/paper_s1 \\
        --seeds 0 [--set PATH=VALUE ...]

Figures: docs/journal/stage3-bundle.md (issue 5, "The bundle's a-posteriori
precision per image" and "What more information would give", 2026-12-03);
issue 25 / 26.

Data: synthetic scenes (``obliq-colmap synth``); the stage 1-2 cache under
``--cache_path`` (shared with ``bench/seeds.py``).

It replaces ``obliq_colmap.bundle.covariance.image_precision`` by a recording
wrapper (on the same Jacobians, ``covariance.image_jacobians``): it follows
the solver's layout and must move with it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from obliq_colmap.bundle import covariance

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from split_runs import observed, run_all, scene_parser, synthetic_scenes  # noqa: E402

_ORIGINAL = covariance.image_precision
#: One dict per bundle solved: image id -> {condition: variance (px^2)}.
_SOLVES: list[dict[int, dict[str, float]]] = []


#: Standard deviations (deg) of the vertical direction as an observation.
_VP_SIGMAS: list[float] = []
#: Standard deviations (m) of every camera centre as an observation.
_CENTRE_SIGMAS: list[float] = []


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


def _observed(J: np.ndarray, C: np.ndarray, A: np.ndarray, sigma: float) -> float:
    """As :func:`_conditional`, with the combinations ``A`` (m, p) of the
    parameters observed with standard deviation ``sigma`` (0: known)."""
    C = observed(C, A, sigma)
    return float(np.mean(np.einsum("npi,ij,npj->n", J, C, J)))


def _rotation_rows(R: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the (left, camera-frame) rotation increment that tilt the
    image's vertical direction (2, p) and that turn about it (1, p)."""
    down = R @ np.array([0.0, 0.0, -1.0])  # world down in the camera frame
    t1 = np.cross(down, [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    tilt, heading = np.zeros((2, p)), np.zeros((1, p))
    tilt[0, :3], tilt[1, :3], heading[0, :3] = t1, np.cross(down, t1), down
    return tilt, heading


def _block_rows(S, st) -> dict[str, tuple[np.ndarray, list[float]]]:
    """Block-wide combinations of the camera block (rows, n_red) with the
    sigmas they are observed at: the block's tilt (2 rows: a rotation w
    about a horizontal world axis through the mean centre turns each
    camera's R by R w and moves its centre by w x (c - c_mean)), known; and
    every centre (3 rows per image) at each of ``_CENTRE_SIGMAS``."""
    ks = S.active_images
    mean = st.c[ks].mean(axis=0)
    tilt = np.zeros((2, S.n_red))
    for row, w in enumerate(np.eye(3)[:2]):
        for k in ks:
            col = S.pose_col[k]
            tilt[row, col : col + 3] = st.R[k] @ w
            tilt[row, col + 3 : col + 6] = np.cross(w, st.c[k] - mean)
    centres = np.zeros((3 * len(ks), S.n_red))
    for i, k in enumerate(ks):
        centres[3 * i : 3 * i + 3, S.pose_col[k] + 3 : S.pose_col[k] + 6] = np.eye(3)
    return {
        "given the block's tilt": (tilt, [0.0]),
        "all centres observed": (centres, _CENTRE_SIGMAS),
    }


def _recording(S, st, cov):
    """``covariance.image_precision`` that also records the conditional sds
    (on the same Jacobians, :func:`covariance.image_jacobians`)."""
    out = _ORIGINAL(S, st, cov)
    record = {}
    for k, J, cols in covariance.image_jacobians(S, st):
        C = cov[np.ix_(cols, cols)]
        intrinsics = list(range(6, len(cols)))
        tilt, heading = _rotation_rows(st.R[k], len(cols))
        record[S.image_ids[k]] = {
            "all": _conditional(J, C, []),
            "given intrinsics": _conditional(J, C, intrinsics),
            "given camera height": _conditional(J, C, [5]),
            "given rotation": _conditional(J, C, [0, 1, 2]),
            "given vertical direction": _observed(J, C, tilt, 0.0),
            "given heading": _observed(J, C, heading, 0.0),
            "given height + intrinsics": _conditional(J, C, [5, *intrinsics]),
            **{
                f"vertical observed {s:g} deg": _observed(J, C, tilt, np.radians(s))
                for s in _VP_SIGMAS
            },
            # the vertical direction's own sd (deg, RMS of its two angles),
            # squared like the rest (the printout takes the root)
            "vertical direction sd (deg)": np.degrees(1.0) ** 2
            * float(np.trace(tilt @ C @ tilt.T) / 2),
        }
    for name, (A, sigmas) in _block_rows(S, st).items():
        for sigma in sigmas:
            C_new = observed(cov, A, sigma)
            label = (
                name if len(sigmas) == 1 and sigma == 0 else f"{name} at {sigma:g} m"
            )
            for k, v in _ORIGINAL(S, st, C_new).items():
                record[S.image_ids[k]][label] = v**2
    _SOLVES.append(record)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = scene_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--bundle_only", action="store_true")
    parser.add_argument(
        "--vp_sigma_deg", type=float, nargs="*", default=[0.03, 0.06, 0.1]
    )
    parser.add_argument(
        "--centre_sigma_m", type=float, nargs="*", default=[0.05, 0.1, 0.5, 2.0]
    )
    args = parser.parse_args(argv)
    _VP_SIGMAS[:] = args.vp_sigma_deg
    _CENTRE_SIGMAS[:] = args.centre_sigma_m
    scenes = synthetic_scenes(args)
    if scenes is None:
        return 2
    args.base_set = list(args.set or [])
    covariance.image_precision = _recording
    run_all(scenes, args, _SOLVES)
    return 0


if __name__ == "__main__":
    sys.exit(main())
