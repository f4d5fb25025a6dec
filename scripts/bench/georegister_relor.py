"""Benchmark of the relative orientation from VPs (issue 27, item 5) on Herz-Jesu-P8.

For each case (one to three images left out):

1. SfM by pycolmap (as ``georegister_real.sfm``: SIFT, exhaustive matching,
   incremental mapping, one SIMPLE_RADIAL camera) of the sequence WITHOUT the
   left-out images, so that the model's points owe nothing to them;
2. the model's down from its images' VPs (``georegister.vertical``,
   terrestrial prior), as ``georegister`` uses it;
3. each left-out image placed by ``relative_vp`` (VP rotation against a
   neighbour, 2-point position from the SIFT matches to the model's tracks)
   and, on the SAME 2D-3D correspondences, by pycolmap's
   ``estimate_and_refine_absolute_pose`` (P3P LO-RANSAC and refinement, 4 px:
   what a COLMAP user has);
4. both scored against the ground truth after ONE similarity from the model
   to the truth (rotation: the chordal mean of the registered cameras'
   rotation differences; scale and translation: least squares on their
   centres): rotation error (deg) and centre error (m);
5. the few-matches regime: random subsets of k correspondences (k = 3 ..
   50, ``--draws`` each), clean and with 30 % of them made wrong; both
   methods again (the VP method with ``min_inliers`` = 3: two to solve, one
   to confirm);
   median errors of the poses returned and the share within 1 deg and
   0.25 m ("good").

Run (from the repository root; 1-3 min per case on 2 cores, SfM included)::

    OMP_NUM_THREADS=1 python scripts/bench/georegister_relor.py --work_path W

Figures: docs/STATUS.md (issue 27) and docs/journal/georegister.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap.geometry import rotation_angle_deg
from obliq_colmap.georegister.options import VerticalOptions
from obliq_colmap.georegister.relative_vp import (
    PlacedImage,
    RegisteredImages,
    RelativeVPOptions,
    place_prepared,
    prepare_image,
)
from obliq_colmap.georegister.vertical import model_vertical

sys.path.insert(0, str(Path(__file__).resolve().parent))
from georegister_real import (  # noqa: E402
    HJ,
    UTM_OFFSET,
    checks_of,
    gcp_from_tracks,
    relevelled_truth,
    run_georegister,
    sfm,
    write_gcp_list,
)

#: one case per entry: an inner image, each end, two adjacent, a gap of three
CASES = (
    "0003.jpg",
    "0007.jpg",
    "0000.jpg",
    "0003.jpg,0004.jpg",
    "0002.jpg,0003.jpg,0004.jpg",
)
SUBSETS = (3, 4, 5, 6, 8, 10, 15, 20, 30, 50)


def subset_sfm(work: Path, left_out: list[str]) -> Path:
    """SfM of the images without ``left_out`` (symlinks in a folder)."""
    folder = work / "images"
    folder.mkdir(parents=True, exist_ok=True)
    for p in sorted((HJ / "images").glob("*.jpg")):
        link = folder / p.name
        if p.name not in left_out and not link.exists():
            link.symlink_to(p)
    return sfm(folder, work)


def truth_alignment(rec, truth) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R, t) taking the model frame to the truth's: R the chordal
    mean of the cameras' ``R_truth^T R_model`` (the centres of a sequence
    along a facade are nearly collinear and leave the roll about that line
    to their noise), then scale and translation by least squares on the
    centres."""
    by_name = {truth.images[i].name: truth.images[i] for i in truth.reg_image_ids()}
    ims = [rec.images[i] for i in rec.reg_image_ids()]
    M = sum(
        by_name[im.name].cam_from_world().rotation.matrix().T
        @ im.cam_from_world().rotation.matrix()
        for im in ims
    )
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    a = np.array([R @ im.projection_center() for im in ims])
    b = np.array([by_name[im.name].projection_center() for im in ims])
    a0, b0 = a - a.mean(0), b - b.mean(0)
    s = float(np.sum(a0 * b0) / np.sum(a0 * a0))
    return s, R, b.mean(0) - s * a.mean(0)


def errors(cam_from_world: np.ndarray, align, truth_image) -> tuple[float, float]:
    """Rotation (deg) and centre (m) errors of a (3, 4) model-frame pose."""
    s, Ra, ta = align
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    centre = s * Ra @ (-R.T @ t) + ta
    Rt = truth_image.cam_from_world().rotation.matrix()
    rot = float(rotation_angle_deg(R @ Ra.T, Rt))
    return rot, float(np.linalg.norm(centre - truth_image.projection_center()))


def _alignment(rec, align, truth) -> dict:
    """How well the registered cameras themselves fit the truth (the floor
    of both methods' errors)."""
    by_name = {truth.images[i].name: truth.images[i] for i in truth.reg_image_ids()}
    e = np.array(
        [
            errors(
                rec.images[i].cam_from_world().matrix(),
                align,
                by_name[rec.images[i].name],
            )
            for i in rec.reg_image_ids()
        ]
    )
    return {
        "rotation_deg_median": float(np.median(e[:, 0])),
        "centre_m_median": float(np.median(e[:, 1])),
    }


def absolute_pose(xy, X, camera) -> np.ndarray | None:
    """pycolmap's P3P LO-RANSAC + refinement: (3, 4) cam_from_world or None."""
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = 4.0
    est.ransac.random_seed = 0
    out = pycolmap.estimate_and_refine_absolute_pose(xy, X, camera, est)
    if out is None:
        return None
    return np.asarray(out["cam_from_world"].matrix())


def _scored(pose, align, truth_image) -> dict | None:
    if pose is None:
        return None
    rot, centre = errors(pose, align, truth_image)
    return {"rotation_deg": rot, "centre_m": centre}


def run_case(work: Path, left_out: list[str], truth, draws: int) -> dict:
    t0 = time.perf_counter()
    model_path = subset_sfm(work, left_out)
    rec = pycolmap.Reconstruction(str(model_path))
    t_sfm = time.perf_counter() - t0
    align = truth_alignment(rec, truth)
    vertical = model_vertical(
        rec, HJ / "images", VerticalOptions(camera_kind="terrestrial"), False
    )
    options = RelativeVPOptions()
    cache = RegisteredImages(rec, HJ / "images", options)
    by_name = {truth.images[i].name: truth.images[i] for i in truth.reg_image_ids()}
    out = {
        "sfm_registered": rec.num_reg_images(),
        "sfm_points": rec.num_points3D(),
        "sfm_s": t_sfm,
        "registered_cameras_against_truth": _alignment(rec, align, truth),
        "images": {},
    }
    for name in left_out:
        t0 = time.perf_counter()
        prepared = prepare_image(rec, HJ / "images", name, options, left_out, cache)
        placed = (
            prepared
            if isinstance(prepared, PlacedImage)
            else place_prepared(rec, prepared, vertical.down, options, cache)
        )
        row = {"vp": placed.report(), "vp_s": time.perf_counter() - t0}
        if placed.cam_from_world is not None:
            row["vp"]["rotation_deg"], row["vp"]["centre_m"] = errors(
                placed.cam_from_world, align, by_name[name]
            )
        out["images"][name] = row
        if isinstance(prepared, PlacedImage):
            continue
        # the neighbour's VP directions alone, not refined by the others'
        alone = place_prepared(
            rec, dataclasses.replace(prepared, pool_ids=[]), vertical.down,
            options, cache,
        )  # fmt: skip
        row["vp_neighbour_only"] = _scored(alone.cam_from_world, align, by_name[name])
        corr = prepared.correspondences
        row["num_correspondences"] = len(corr.X)
        t0 = time.perf_counter()
        pose = absolute_pose(corr.xy, corr.X, prepared.camera)
        row["absolute_pose_s"] = time.perf_counter() - t0
        row["absolute_pose"] = _scored(pose, align, by_name[name])
        for outliers in (0.0, 0.3):
            row[f"few_matches_outliers_{outliers:g}"] = few_matches(
                rec, prepared, vertical.down, options, cache, align,
                by_name[name], draws, outliers,
            )  # fmt: skip
    out["command"] = through_the_command(work, model_path, left_out)
    return out


def through_the_command(work: Path, model_path: Path, left_out: list[str]) -> dict:
    """``obliq-colmap georegister --add_missing_images 1`` with 2 control
    points (as ``georegister_real``: SfM tracks triangulated with the
    re-levelled truth), with and without the block adjustment: each
    camera's tilt, heading (deg) and centre (m) errors, the left-out ones
    apart."""
    truth, _ = relevelled_truth(HJ / "images")
    rec = pycolmap.Reconstruction(str(model_path))
    points = gcp_from_tracks(rec, truth)
    gcp = work / "gcp_2.txt"
    write_gcp_list(gcp, points, "EPSG:32632")
    out = {}
    for block in (0, 1):
        result = work / f"georegistered_added_{block}"
        r = run_georegister(
            model_path, HJ / "images", gcp, result, checks_of(points, 2),
            ("--add_missing_images", "1", "--block_adjustment", str(block)),
        )  # fmt: skip
        errs = _camera_errors(result, truth)
        out[f"block_adjustment_{block}"] = {
            "missing_images": r["report"].get("missing_images"),
            "left_out": {n: errs[n] for n in left_out if n in errs},
            "registered_median": {
                k: float(
                    np.median([e[k] for n, e in errs.items() if n not in left_out])
                )
                for k in ("tilt_deg", "heading_deg", "centre_m")
            },
            "wall_s": r["wall_s"],
        }
    return out


def _camera_errors(result: Path, truth) -> dict:
    """Per camera of the output model: tilt, heading (deg), centre (m)
    against the re-levelled truth (as ``georegister_real.camera_errors``)."""
    rec = pycolmap.Reconstruction(str(result))
    origin = np.array(json.loads((result / "georef.json").read_text())["origin"])
    by_name = {truth.images[i].name: truth.images[i] for i in truth.reg_image_ids()}
    out = {}
    for i in rec.reg_image_ids():
        im = rec.images[i]
        t = by_name[im.name]
        Re = im.cam_from_world().rotation.matrix()
        Rt = t.cam_from_world().rotation.matrix()
        up = np.array([0.0, 0.0, 1.0])
        tilt = np.degrees(np.arccos(np.clip((Re @ up) @ (Rt @ up), -1, 1)))
        dh = np.arctan2(Re[2, 1], Re[2, 0]) - np.arctan2(Rt[2, 1], Rt[2, 0])
        heading = abs(np.degrees((dh + np.pi) % (2 * np.pi) - np.pi))
        ce = im.projection_center() + origin - UTM_OFFSET
        out[im.name] = {
            "tilt_deg": float(tilt),
            "heading_deg": float(heading),
            "centre_m": float(np.linalg.norm(ce - t.projection_center())),
        }
    return out


def few_matches(
    rec, prepared, down, options, cache, align, truth_image, draws, outliers
) -> dict:
    """Both methods on random subsets of k of the correspondences, a share
    ``outliers`` of them made wrong (their 3D points shuffled among them, or
    a random model point for a single one)."""
    corr = prepared.correspondences
    rng = np.random.default_rng(0)
    n = len(corr.X)
    rows = {}
    for k in SUBSETS:
        if k > n:
            break
        # 2 to solve and 1 to confirm: the fewest the VP method can vouch for
        opt_k = dataclasses.replace(options, min_inliers=3)
        res = {"vp": [], "absolute_pose": []}
        n_bad = int(round(outliers * k))
        for _ in range(draws):
            pick = rng.choice(n, k, replace=False)
            X = corr.X[pick].copy()
            if n_bad == 1:
                X[0] = corr.X[rng.integers(n)]
            elif n_bad > 1:
                X[:n_bad] = np.roll(X[:n_bad], 1, axis=0)
            sub = dataclasses.replace(
                corr, xy=corr.xy[pick], rays=corr.rays[pick], X=X,
                point3D_ids=corr.point3D_ids[pick],
            )  # fmt: skip
            placed = place_prepared(
                rec, dataclasses.replace(prepared, correspondences=sub), down,
                opt_k, cache,
            )  # fmt: skip
            res["vp"].append(
                None
                if placed.cam_from_world is None
                else errors(placed.cam_from_world, align, truth_image)
            )
            pose = absolute_pose(sub.xy, sub.X, prepared.camera)
            res["absolute_pose"].append(
                None if pose is None else errors(pose, align, truth_image)
            )
        rows[k] = {m: _summary(v) for m, v in res.items()}
    return rows


def _summary(results: list) -> dict:
    ok = [r for r in results if r is not None]
    good = [r for r in ok if r[0] < 1.0 and r[1] < 0.25]
    out = {"draws": len(results), "returned": len(ok), "good": len(good)}
    if ok:
        a = np.array(ok)
        out["rotation_deg_median"] = float(np.median(a[:, 0]))
        out["centre_m_median"] = float(np.median(a[:, 1]))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work_path", type=Path, required=True)
    parser.add_argument(
        "--cases",
        nargs="*",
        default=list(CASES),
        help="comma-separated names left out, one case each",
    )
    parser.add_argument("--draws", type=int, default=30)
    parser.add_argument("--output_path", type=Path)
    args = parser.parse_args(argv)
    print(f"# bench georegister_relor: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}")
    truth = pycolmap.Reconstruction(str(HJ / "gt_colmap_halfres_text"))
    results = {}
    for case in args.cases:
        left = case.split(",")
        work = args.work_path / ("without_" + "_".join(n.split(".")[0] for n in left))
        results[case] = run_case(work, left, truth, args.draws)
        print(json.dumps({case: results[case]}, indent=1, default=float), flush=True)
    if args.output_path:
        text = json.dumps(results, indent=1, default=float)
        args.output_path.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
