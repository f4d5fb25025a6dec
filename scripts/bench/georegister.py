"""The georegister benchmark on synthetic scenes (issue 27, item 7c and the targets).

What it measures: for each scene kind (``paper``: the oblique block as an
SfM-like model; ``street``: a phone walking a street) a synthetic scene is
generated (kept under ``--work_path``, reused when present) and its SfM-like
model written (true cameras and tracks with 0.5 px noise, moved by a random
similarity; control points with 0.05 m and 0.5 px noise). Then, per mode:

- ``gcp2``, ``gcp3``: ``obliq-colmap georegister`` with the 2 (3) control
  points farthest apart;
- ``auto``: ``georegister`` with the cadastre and the scene's rough priors
  (``--priors_path``), no control point;
- ``oracle``: NOT the command: the similarity that fits the model's camera
  centres to the true ones (least squares); the best any georegistration of
  this model can do (zero for the SfM-like model, the SfM's own shape error
  for pycolmap's);
- ``reference3``: NOT the command: the control points triangulated in the
  SfM-like model and a least-squares similarity (Umeyama) on 3 of them, no
  vertical and no bundle; the floor the noise of the data allows, and the
  check that the scoring runs end to end.

Every result is scored against the truth (``georef_score.score_block``):
the block's vertical and heading errors (deg), median rotation (deg) and
centre (m) errors per image, median of the per-image mean corner deviations
(px, issue 25's measure) and the fraction of images below 2 px. A mode whose
command is not available (``georegister`` not in the CLI yet) is reported
as such.

The block's covariance (report.json's ``uncertainty``) against the truth
(:func:`uncertainty_check`): per image the centre's and rotation's errors
over their predicted sd (``|e| / sqrt(trace C)``: 1 in RMS where the
covariance is right), median and RMS over the images; the centre in 3D
after the one vertical offset the scoring removes, and horizontally.

``--compare_solvers N`` also runs each georegister mode's block adjustment
with both solvers on the same captured block in this process
(``georegister_solvers.compare_solvers``, N alternating repeats each; both
to ``--compare_tolerance``): the time ratio and the optima's differences.

The exact command (from the repository root; ~1 min per street scene, a few
for paper, on 2 shared cores)::

    python scripts/bench/georegister.py --work_path W [--scene paper street]
        [--mode gcp2 gcp3 auto reference3 oracle] [--sfm sfm_like pycolmap]
        [--camera_kind scene|auto] [--block_adjustment 0|1]
        [--block_adjustment_solver obliq|ceres] [--block_adjustment_map_rows 0|1]
        [--sfm_lens_error PP_PX FOCAL] [--gcp_with_map 0|1]
        [--georegister_arg=ARG ...] [--seed 1]
        [--paper_width 1002] [--compare_solvers N] [--compare_tolerance TOL]
        [--output_path bench_georegister.json]

Figures go to docs/STATUS.md (issue 27) and docs/journal/georegister-bench.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from obliq_colmap.cli import SUBCOMMANDS
from obliq_colmap.colmap_io import Block, read_model
from obliq_colmap.control.model import ControlPoints
from obliq_colmap.evaluate import read_absolute_block
from obliq_colmap.synthetic import generate_scene, load_scene, preset
from obliq_colmap.synthetic.georef_score import score_block
from obliq_colmap.synthetic.sfm_like import (
    SfmLikeOptions,
    Similarity,
    noisy_control_points,
    scene_control_points,
    write_pycolmap_sfm,
    write_sfm_like,
)
from obliq_colmap.synthetic.street import write_gcp_list

sys.path.insert(0, str(Path(__file__).resolve().parent))
from georegister_solvers import compare_solvers  # noqa: E402 - beside this script

MODES = ("gcp2", "gcp3", "auto", "reference3", "oracle")


def farthest_subset(control: ControlPoints, k: int) -> ControlPoints:
    """The ``k`` points spread farthest: the farthest pair, then max-min distance."""
    xyz = control.xyz()
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    chosen = [int(i), int(j)]
    while len(chosen) < min(k, len(xyz)):
        chosen.append(int(np.argmax(d[:, chosen].min(1))))
    return ControlPoints([control.points[c] for c in chosen], control.crs)


def triangulate(block: Block, control: ControlPoints) -> np.ndarray:
    """(N, 3) linear (DLT) triangulation of each point in ``block``'s frame.

    Observations in images the block lacks are skipped; NaN for a point seen
    in fewer than 2 of its images.
    """
    by_name = {im.name: im for im in block.images.values()}
    out = []
    for p in control.points:
        rows = []
        seen = [ob for ob in p.observations if ob.image_name in by_name]
        if len(seen) < 2:
            out.append(np.full(3, np.nan))
            continue
        for ob in seen:
            im = by_name[ob.image_name]
            uv = block.cameras[im.camera_id].cam_from_img(ob.xy[None])[0]
            P = im.cam_from_world.matrix()
            rows += [uv[0] * P[2] - P[0], uv[1] * P[2] - P[1]]
        X = np.linalg.svd(np.asarray(rows))[2][-1]
        out.append(X[:3] / X[3])
    return np.asarray(out)


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` of (N, 3) points, N >= 3."""
    ms, md = src.mean(0), dst.mean(0)
    A, B = src - ms, dst - md
    U, S, Vt = np.linalg.svd(B.T @ A)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (A**2).sum())
    return s, R, md - s * R @ ms


def reference_block(model: Path, control: ControlPoints, origin: np.ndarray) -> Block:
    """The SfM-like model placed by a similarity on its triangulated control points."""
    block = read_model(model)
    src = triangulate(block, control)
    ok = np.isfinite(src).all(1)
    if ok.sum() < 3:
        raise ValueError(f"{ok.sum()} control points triangulated in {model}")
    s, R, t = umeyama(src[ok], control.xyz()[ok] - origin)
    # X_local = s R X_sfm + t  <=>  X_sfm = (1/s) R^T (X_local - t)
    inverse = Similarity(1.0 / s, R.T, -R.T @ t / s, origin)
    return inverse.inverse_block(block)


def oracle_block(model: Path, scene) -> Block:
    """The model placed by the similarity fitting its camera centres to the truth."""
    block = read_model(model)
    gt = {im.name: im.cam_from_world.center for im in scene.gt_local.images.values()}
    names = [im.name for im in block.images.values()]
    src = np.array([im.cam_from_world.center for im in block.images.values()])
    s, R, t = umeyama(src, np.array([gt[n] for n in names]))
    return Similarity(1.0 / s, R.T, -R.T @ t / s, scene.origin).inverse_block(block)


def ensure_scene(work: Path, kind: str, seed: int, paper_width: int) -> Path:
    path = work / f"{kind}_seed{seed}"
    if not (path / "scene.json").is_file():
        overrides = {"image_width_px": paper_width} if kind == "paper" else {}
        generate_scene(
            path, preset(kind, **overrides), seed=seed, preset=kind, num_workers=2
        )
    return path


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if len(a) else float("nan")


def uncertainty_check(report: dict, est: Block, scene) -> dict:
    """The covariance in ``report["uncertainty"]`` against the truth: per
    image ``|e| / sqrt(trace C)`` of the centre (3D, after the median
    vertical offset of the centres; and horizontally) and of the rotation
    (the angle of ``R_est R_true^T``); median and RMS over the images, the
    medians of the errors and of the predicted sds beside them."""
    unc = report.get("uncertainty") or {}
    if not unc.get("available"):
        return {"available": False, "reason": unc.get("reason", "no section")}
    truth = {im.name: im.cam_from_world for im in scene.gt.images.values()}
    names, e, rot, sd_c, sd_h, sd_r = [], [], [], [], [], []
    for im in est.images.values():
        u = unc["images"].get(im.name)
        if u is None or im.name not in truth or u["position_sd_m"][0] is None:
            continue
        t = truth[im.name]
        names.append(im.name)
        e.append(im.cam_from_world.center - t.center)
        dR = im.cam_from_world.rotation @ t.rotation.T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        p = np.asarray(u["position_sd_m"], float)
        sd_c.append(np.linalg.norm(p))
        sd_h.append(np.linalg.norm(p[:2]))
        sd_r.append(np.linalg.norm(np.asarray(u["rotation_sd_deg"], float)))
    e = np.array(e).reshape(-1, 3)
    e[:, 2] -= np.median(e[:, 2])  # the scoring's one vertical offset
    c_ratio = np.linalg.norm(e, axis=1) / np.array(sd_c)
    h_ratio = np.linalg.norm(e[:, :2], axis=1) / np.array(sd_h)
    r_ratio = np.array(rot) / np.array(sd_r)
    return {
        "available": True,
        "num_images": len(names),
        "variance_factor": unc.get("variance_factor"),
        "centre_ratio_median": float(np.median(c_ratio)),
        "centre_ratio_rms": _rms(c_ratio),
        "horizontal_ratio_median": float(np.median(h_ratio)),
        "horizontal_ratio_rms": _rms(h_ratio),
        "rotation_ratio_median": float(np.median(r_ratio)),
        "rotation_ratio_rms": _rms(r_ratio),
        "centre_error_median_m": float(np.median(np.linalg.norm(e, axis=1))),
        "centre_sd_median_m": float(np.median(sd_c)),
        "horizontal_error_median_m": float(np.median(np.linalg.norm(e[:, :2], axis=1))),
        "horizontal_sd_median_m": float(np.median(sd_h)),
        "rotation_error_median_deg": float(np.median(rot)),
        "rotation_sd_median_deg": float(np.median(sd_r)),
    }


def solver_comparison(cmd: list[str], repeats: int, tolerance: float | None) -> dict:
    """Both solvers on the block of this georegister command, in-process."""
    import argparse

    from obliq_colmap.cli.georegister import add_arguments, options_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(cmd[cmd.index("georegister") + 1 :] + ["--no_progress"])
    return compare_solvers(
        Path(args.input_path),
        Path(args.image_path),
        options_from_args(args),
        repeats,
        tolerance,
    )


def run_mode(
    mode: str,
    scene_path: Path,
    model: Path,
    work: Path,
    control: ControlPoints,
    camera_kind: str = "auto",
    block_adjustment: int | None = None,
    block_solver: str | None = None,
    map_rows: int | None = None,
    gcp_with_map: bool = False,
    extra: list[str] | None = None,
    compare: int = 0,
    compare_tolerance: float | None = None,
) -> dict:
    """Run one mode; returns the score or the reason it did not run."""
    out = work / f"out_{mode}"
    if mode == "reference3":
        scene = load_scene(scene_path)
        sub = farthest_subset(control, 3)
        est = reference_block(model, sub, scene.origin)
        return {"status": "ok", **score_block(est, scene)}
    if mode == "oracle":
        scene = load_scene(scene_path)
        return {"status": "ok", **score_block(oracle_block(model, scene), scene)}
    if "georegister" not in SUBCOMMANDS:
        return {"status": "georegister not in the CLI yet"}
    if out.exists():  # a rerun: the command writes only into an empty folder
        shutil.rmtree(out)
    cmd = [
        sys.executable,
        "-m",
        "obliq_colmap",
        "georegister",
        "--input_path",
        str(model),
        "--image_path",
        str(scene_path / "images"),
        "--output_path",
        str(out),
    ]
    if block_adjustment is not None:
        cmd += ["--block_adjustment", str(block_adjustment)]
    if block_solver is not None:
        cmd += ["--block_adjustment_solver", block_solver]
    if map_rows is not None:
        cmd += ["--block_adjustment_map_rows", str(map_rows)]
    cmd += extra or []
    if camera_kind != "auto":
        cmd += ["--camera_kind", camera_kind]
    if mode == "auto":
        cmd += ["--cadastre_path", str(scene_path / "cadastre.geojson")]
        cmd += ["--priors_path", str(scene_path / "priors")]
    else:
        gcp = work / f"{mode}.txt"
        write_gcp_list(gcp, farthest_subset(control, int(mode[-1])))
        cmd += ["--control_points_path", str(gcp)]
        if gcp_with_map:
            cmd += ["--cadastre_path", str(scene_path / "cadastre.geojson")]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"status": f"exit {proc.returncode}", "stderr": proc.stderr[-2000:]}
    wall = time.perf_counter() - t0
    est, _ = read_absolute_block(out)
    scene = load_scene(scene_path)
    score = score_block(est, scene)
    report = json.loads((out / "report.json").read_text())
    block = report.get("block_adjustment")
    res = {"status": "ok", "time_s": wall, "block_adjustment": block, **score}
    res["uncertainty_check"] = uncertainty_check(report, est, scene)
    if compare:
        res["solvers"] = solver_comparison(cmd, compare, compare_tolerance)
    return res


def print_result(mode: str, res: dict) -> None:
    if res["status"] != "ok":
        print(f"  {mode:11s} {res['status']}")
        return
    print(
        f"  {mode:11s} vertical {res['vertical_error_deg']:.4f} deg, heading "
        f"{res['heading_error_deg']:+.4f} deg, rotation median "
        f"{res['rotation_error_median_deg']:.4f} deg, centre median "
        f"{res['center_error_median_m']:.3f} m (max "
        f"{res['center_error_max_m']:.3f}), deviation median "
        f"{res['deviation_median_px']:.2f} px, below 2 px "
        f"{100 * res['below_2px']:.0f} % of {res['num_images']}"
    )
    block = res.get("block_adjustment")
    if block:
        print(
            f"  {'':11s} block adjustment ({block['solver']}): cost "
            f"{block['initial_cost']:.6g} -> {block['final_cost']:.6g}, "
            f"{block['iterations']} iterations, {block['time_s']:.2f} s, "
            f"{block.get('num_map_rows', 0)} map rows"
        )
    u = res.get("uncertainty_check")
    if u and u.get("available"):
        print(
            f"  {'':11s} measured / predicted sd (median, RMS): centre "
            f"{u['centre_ratio_median']:.2f}, {u['centre_ratio_rms']:.2f} "
            f"(horizontal {u['horizontal_ratio_median']:.2f}, "
            f"{u['horizontal_ratio_rms']:.2f}), rotation "
            f"{u['rotation_ratio_median']:.2f}, {u['rotation_ratio_rms']:.2f}; "
            f"centre error {u['centre_error_median_m']:.3f} m, sd "
            f"{u['centre_sd_median_m']:.3f} m; rotation error "
            f"{u['rotation_error_median_deg']:.4f} deg, sd "
            f"{u['rotation_sd_median_deg']:.4f} deg; variance factor "
            f"{u['variance_factor']}"
        )
    elif u:
        print(f"  {'':11s} no covariance: {u['reason']}")
    c = res.get("solvers")
    if c:
        print(
            f"  {'':11s} solvers (tolerance {c['function_tolerance']:g}): obliq "
            f"{c['time_s']['obliq']:.2f} s, ceres {c['time_s']['ceres']:.2f} s, "
            f"ratio {c['time_ratio_obliq_over_ceres']:.2f}; cost "
            f"{c['summaries']['obliq']['final_cost']:.9g} / "
            f"{c['summaries']['ceres']['final_cost']:.9g} (rel. "
            f"{c['final_cost_relative_difference']:.2e}, start "
            f"{c['initial_cost_relative_difference']:.1e}); centres apart "
            f"{c['centre_difference_m_max']:.2e} m (moved "
            f"{c['centre_moved_by_adjustment_m_median']:.3f} m), rotations "
            f"{c['rotation_difference_deg_max']:.1e} deg, points "
            f"{c['point_difference_m_max']:.1e} m, intrinsics "
            f"{max(c['params_difference_max'].values()):.1e}; iterations "
            f"{c['summaries']['obliq']['iterations']} / "
            f"{c['summaries']['ceres']['iterations']}; {c['num_map_rows']} map rows, "
            f"facade rows {c['num_facade_rows']['obliq']} / "
            f"{c['num_facade_rows']['ceres']} of {c['num_facade_tracks']['obliq']} / "
            f"{c['num_facade_tracks']['ceres']} tracks"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work_path", required=True, type=Path)
    ap.add_argument("--scene", nargs="+", default=["paper", "street"])
    ap.add_argument("--mode", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument(
        "--sfm",
        nargs="+",
        default=["sfm_like"],
        choices=("sfm_like", "pycolmap"),
        help="input models: the SfM-like model and/or pycolmap's SfM of the images",
    )
    ap.add_argument(
        "--camera_kind",
        default="scene",
        choices=("scene", "auto", "terrestrial", "oblique"),
        help="georegister --camera_kind; scene: terrestrial for a street, "
        "oblique for a flight (what the user knows)",
    )
    ap.add_argument(
        "--block_adjustment",
        type=int,
        choices=(0, 1),
        default=None,
        help="georegister --block_adjustment (default: the command's)",
    )
    ap.add_argument(
        "--block_adjustment_solver",
        choices=("obliq", "ceres"),
        default=None,
        help="georegister --block_adjustment_solver (default: the command's)",
    )
    ap.add_argument(
        "--block_adjustment_map_rows",
        type=int,
        choices=(0, 1),
        default=None,
        help="georegister --block_adjustment_map_rows (default: the command's)",
    )
    ap.add_argument(
        "--sfm_lens_error",
        nargs=2,
        type=float,
        default=(0.0, 0.0),
        metavar=("PP_PX", "FOCAL"),
        help="sfm_like: the model's lens made wrong (principal point moved PP_PX "
        "px, focal scaled by 1 +- FOCAL) and its poses and points re-fitted "
        "with it held, as a real SfM's (SfmLikeOptions); default 0 0",
    )
    ap.add_argument(
        "--gcp_with_map",
        type=int,
        choices=(0, 1),
        default=0,
        help="gcp2, gcp3: pass the scene's cadastre too (its corner lines "
        "then enter the block adjustment); default 0",
    )
    ap.add_argument(
        "--georegister_arg",
        action="append",
        default=[],
        help="one more argument for every georegister command (repeat; "
        "use --georegister_arg=--flag for a leading dash)",
    )
    ap.add_argument(
        "--compare_solvers",
        type=int,
        default=0,
        metavar="N",
        help="also run each mode's block adjustment with both solvers on the "
        "same block in this process, N alternating repeats (default 0: off)",
    )
    ap.add_argument(
        "--compare_tolerance",
        type=float,
        default=None,
        help="both solvers' function tolerance in --compare_solvers "
        "(default: the command's, 1e-6)",
    )
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--paper_width", type=int, default=1002)
    ap.add_argument("--output_path", type=Path, default=None)
    args = ap.parse_args(argv)
    args.work_path.mkdir(parents=True, exist_ok=True)
    pp_err, f_err = args.sfm_lens_error
    options = SfmLikeOptions(principal_point_error_px=pp_err, focal_error=f_err)
    results = {}
    for kind in args.scene:
        scene_path = ensure_scene(args.work_path, kind, args.seed, args.paper_width)
        scene = load_scene(scene_path)
        work_root = args.work_path / f"{kind}_seed{args.seed}_runs"
        for sfm in args.sfm:
            work = work_root / sfm
            if sfm == "sfm_like" and (pp_err or f_err):
                work = work_root / f"{sfm}_lens_pp{pp_err:g}_f{f_err:g}"
            work.mkdir(parents=True, exist_ok=True)
            model = work / "model"
            t0 = time.perf_counter()
            if not (model / "gcp_list.txt").is_file():
                write = write_sfm_like if sfm == "sfm_like" else write_pycolmap_sfm
                try:
                    write(model, scene, options, seed=args.seed)
                except RuntimeError as exc:
                    print(f"{kind} / {sfm}: {exc}")
                    results[f"{kind}/{sfm}"] = {"status": str(exc)}
                    continue
            n_reg = len(read_model(model).images)
            control = noisy_control_points(
                scene_control_points(scene, options), options, args.seed
            )
            print(
                f"{kind} / {sfm}: {n_reg} of {len(scene.gt.images)} images in the "
                f"model ({time.perf_counter() - t0:.0f} s), {len(control)} control "
                "points"
            )
            for mode in args.mode:
                kind_arg = args.camera_kind
                if kind_arg == "scene":
                    kind_arg = "terrestrial" if kind == "street" else "oblique"
                res = run_mode(
                    mode,
                    scene_path,
                    model,
                    work,
                    control,
                    kind_arg,
                    args.block_adjustment,
                    args.block_adjustment_solver,
                    args.block_adjustment_map_rows,
                    bool(args.gcp_with_map),
                    args.georegister_arg,
                    args.compare_solvers,
                    args.compare_tolerance,
                )
                res["camera_kind"] = kind_arg
                res["num_images_in_model"] = n_reg
                results[f"{kind}/{sfm}/{mode}"] = res
                print_result(mode, res)
    if args.output_path:
        args.output_path.write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
