"""Benchmark of ``obliq-colmap georegister`` on real data (issue 27, item 7a/7b).

(a) Herz-Jesu-P8 (``../shared/data/strecha_herzjesu_p8_halfres``: 8 photos of
a church facade with metric ground-truth cameras, 1536 x 1024). Its truth
frame is z-down and about 0.3 deg off the vertical its images' VPs show, and
it has no points and no map, so:

1. SfM by pycolmap (SIFT, exhaustive matching, incremental mapping), in its
   own arbitrary frame;
2. the truth RE-LEVELLED: rotated by the smallest rotation that takes the
   images' VP vertical (``georegister.vertical`` on the truth cameras) to its
   down axis, turned z-up and shifted into UTM-sized coordinates (EPSG:32632),
   as a survey would give it;
3. control points: SfM tracks seen in >= 3 images, triangulated with the
   TRUTH cameras from their SfM observations; the points spread farthest
   apart are used (2, then 3), the others are check points;
4. ``obliq-colmap georegister`` with 2 and with 3 control points; every
   camera's tilt error (angle between its true and estimated vertical),
   heading error (the rest, about the vertical) and centre error against
   the re-levelled truth; check point residuals from the report; the
   block adjustment with each solver (``--block_adjustment_solver obliq``,
   the project's bundle, and ``ceres``), and both on the same captured
   block in this process (``georegister_solvers.compare_solvers``): their
   times as a ratio and how far apart their optima are.

Also COLMAP's own ``model_orientation_aligner`` (MANHATTAN-WORLD) on the same
SfM model, where the ``colmap`` command is installed: its vertical against
the truth's.

(b) Berlin (``../shared/data/opensfm_berlin_facade``: 3 photos, the real
``gcp_list.txt`` in WGS84, 10 points, heights in a local datum): SfM by
pycolmap, georegister with all points; control point residuals in m and px,
and leave-one-out check point residuals.

Run (from the repository root; ~1-3 min on 2 cores)::

    python scripts/bench/georegister_real.py --work_path W [--only herzjesu|berlin]

Figures: docs/STATUS.md (issue 27) and docs/journal/georegister.md.
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
import pycolmap

from obliq_colmap.geometry import rotation_aligning
from obliq_colmap.georegister.options import GeoregisterOptions, VerticalOptions
from obliq_colmap.georegister.vertical import model_vertical

sys.path.insert(0, str(Path(__file__).resolve().parent))
from georegister_solvers import compare_solvers  # noqa: E402 - beside this script

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"
HJ = DATA / "strecha_herzjesu_p8_halfres"
BERLIN = DATA / "opensfm_berlin_facade"
UTM_OFFSET = np.array([500_000.0, 5_400_000.0, 200.0])
#: the truth's half-resolution intrinsics (README: fx, fy, cx, cy)
HJ_PINHOLE = (1379.74, 1382.08, 760.345, 503.405)


def sfm(images: Path, work: Path, pinhole: str | None = None) -> Path:
    """pycolmap SfM with a user's defaults (one camera for all images); the
    largest model's folder. ``pinhole``: "fx,fy,cx,cy" of a known lens, held
    fixed (the oracle of the lens)."""
    out = work / ("sfm" if pinhole is None else "sfm_known_lens")
    if (out / "0" / "images.bin").is_file():
        return out / "0"
    shutil.rmtree(out, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    db = work / f"{out.name}.db"
    db.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    mapper = pycolmap.IncrementalPipelineOptions()
    if pinhole is not None:
        reader.camera_model = "PINHOLE"
        reader.camera_params = pinhole
        mapper.ba_refine_focal_length = False
        mapper.ba_refine_extra_params = False
    pycolmap.extract_features(
        db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader
    )
    pycolmap.match_exhaustive(db)
    models = pycolmap.incremental_mapping(db, images, out, mapper)
    best = max(models, key=lambda k: models[k].num_reg_images())
    if best != 0:
        shutil.move(str(out / str(best)), str(out / "best"))
        return out / "best"
    return out / "0"


def relevelled_truth(images: Path) -> tuple[pycolmap.Reconstruction, float]:
    """The truth, levelled by its images' VPs, z up (a local frame: the UTM-sized
    offset is added only in the control point file, since pycolmap's
    transform with a 5e6 m translation moved the cameras by ~0.1 m); and the
    angle (deg) it was tilted by."""
    gt = pycolmap.Reconstruction(str(HJ / "gt_colmap_halfres_text"))
    v = model_vertical(gt, images, VerticalOptions(camera_kind="terrestrial"), False)
    R = rotation_aligning(v.down, np.array([0.0, 0.0, -1.0]))
    tilt = float(np.degrees(np.arccos(np.clip(v.down @ [0, 0, 1.0], -1, 1))))
    gt.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), np.zeros(3)))
    return gt, tilt


def gcp_from_tracks(sfm_rec, truth, n_points: int = 12) -> list[tuple]:
    """Tracks seen >= 3 times, triangulated with the truth cameras: a spread
    of ``n_points`` (farthest-point order). (name, xyz, [(image, xy)])."""
    by_name = {truth.images[i].name: i for i in truth.reg_image_ids()}
    cands = []
    for pid, p in sfm_rec.points3D.items():
        els = [(sfm_rec.images[e.image_id], e.point2D_idx) for e in p.track.elements]
        if len(els) < 3 or p.error > 1.0:
            continue
        obs = [(im.name, np.asarray(im.points2D[k].xy)) for im, k in els]
        A, b = np.zeros((3, 3)), np.zeros(3)
        for name, xy in obs:
            t = truth.images[by_name[name]]
            pose = t.cam_from_world()
            Rm = pose.rotation.matrix()
            d = np.r_[t.camera.cam_from_img(xy[None])[0], 1.0] @ Rm
            d /= np.linalg.norm(d)
            c = -Rm.T @ pose.translation
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ c
        X = np.linalg.solve(A, b)
        if _truth_reprojection(truth, by_name, X, obs) < 1.0:
            cands.append((pid, X, obs))
    xyz = np.array([c[1] for c in cands])
    chosen = [int(np.argmax(np.linalg.norm(xyz - xyz.mean(0), axis=1)))]
    while len(chosen) < n_points:
        d = np.min(np.linalg.norm(xyz[:, None] - xyz[chosen][None], axis=2), axis=1)
        chosen.append(int(np.argmax(d)))
    return [(f"p{k}", cands[i][1], cands[i][2]) for k, i in enumerate(chosen)]


def _truth_reprojection(truth, by_name, X, obs) -> float:
    """Largest reprojection error (px) of X in the truth cameras: a track
    whose rays do not meet in the truth (a wrong match) is no control point."""
    worst = 0.0
    for name, xy in obs:
        t = truth.images[by_name[name]]
        Xc = t.cam_from_world() * X
        if Xc[2] <= 0:
            return np.inf
        worst = max(
            worst, float(np.linalg.norm(t.camera.img_from_cam(Xc[None])[0] - xy))
        )
    return worst


def write_gcp_list(path: Path, points: list[tuple], crs: str) -> None:
    """OpenSfM's gcp_list.txt (pixels: COLMAP's minus 0.5)."""
    lines = [crs]
    for name, xyz, obs in points:
        for image, xy in obs:
            u, v = xy - 0.5
            x, y, z = xyz + UTM_OFFSET
            lines.append(f"{x:.4f} {y:.4f} {z:.4f} {u:.3f} {v:.3f} {image} {name}")
    path.write_text("\n".join(lines) + "\n")


def run_georegister(sfm_path, images, gcp, out, check_points=(), extra=()) -> dict:
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "obliq_colmap", "georegister",
           "--input_path", str(sfm_path), "--image_path", str(images),
           "--control_points_path", str(gcp), "--output_path", str(out),
           "--no_progress"]  # fmt: skip
    if check_points:
        cmd += ["--check_points", ",".join(check_points)]
    cmd += list(extra)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-2000:])
    report = json.loads((out / "report.json").read_text())
    return {"wall_s": wall, "report": report}


def camera_errors(result: Path, truth: pycolmap.Reconstruction) -> dict:
    """Per camera: tilt (deg), heading (deg) and centre (m) errors, medians."""
    rec = pycolmap.Reconstruction(str(result))
    origin = np.array(json.loads((result / "georef.json").read_text())["origin"])
    by_name = {truth.images[i].name: truth.images[i] for i in truth.reg_image_ids()}
    tilt, heading, centre = [], [], []
    for i in rec.reg_image_ids():
        im = rec.images[i]
        if im.name not in by_name:
            continue
        t = by_name[im.name]
        Re = im.cam_from_world().rotation.matrix()
        Rt = t.cam_from_world().rotation.matrix()
        up = np.array([0.0, 0.0, 1.0])
        # tilt: the angle between the world's vertical as each camera sees it
        ve, vt = Re @ up, Rt @ up
        tilt.append(np.degrees(np.arccos(np.clip(ve @ vt, -1, 1))))
        # heading: the optical axes' azimuths in the map
        ae, at = Re[2], Rt[2]
        dh = np.arctan2(ae[1], ae[0]) - np.arctan2(at[1], at[0])
        heading.append(abs(np.degrees((dh + np.pi) % (2 * np.pi) - np.pi)))
        ce = im.projection_center() + origin - UTM_OFFSET
        centre.append(np.linalg.norm(ce - t.projection_center()))
    return {
        "num_cameras": len(tilt),
        "tilt_deg_median": float(np.median(tilt)),
        "tilt_deg_max": float(np.max(tilt)),
        "heading_deg_median": float(np.median(heading)),
        "heading_deg_max": float(np.max(heading)),
        "centre_m_median": float(np.median(centre)),
        "centre_m_max": float(np.max(centre)),
    }


def colmap_aligner_tilt(sfm_path: Path, images: Path, work: Path, truth) -> dict:
    """COLMAP's model_orientation_aligner on the SfM model: its vertical's
    angle from the truth's (both expressed in the SfM model's frame)."""
    exe = shutil.which("colmap")
    if exe is None:
        return {"status": "colmap not installed"}
    out = work / "colmap_aligned"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    proc = subprocess.run(
        [exe, "model_orientation_aligner", "--input_path", str(sfm_path),
         "--output_path", str(out), "--image_path", str(images),
         "--method", "MANHATTAN-WORLD"],
        capture_output=True, text=True,
    )  # fmt: skip
    if proc.returncode != 0:
        return {"status": f"failed: {proc.stderr[-300:]}"}
    a = pycolmap.Reconstruction(str(sfm_path))
    b = pycolmap.Reconstruction(str(out))
    # rotation from the SfM frame to the aligned frame, from any one camera
    i = next(iter(a.reg_image_ids()))
    Ra = a.images[i].cam_from_world().rotation.matrix()
    Rb = b.images[i].cam_from_world().rotation.matrix()
    R_ab = Rb.T @ Ra  # aligned_from_sfm
    # truth down in the SfM frame: through each camera, averaged
    downs = []
    by_name = {truth.images[k].name: truth.images[k] for k in truth.reg_image_ids()}
    for k in a.reg_image_ids():
        im = a.images[k]
        t = by_name[im.name]
        d_cam = t.cam_from_world().rotation.matrix() @ np.array([0, 0, -1.0])
        downs.append(im.cam_from_world().rotation.matrix().T @ d_cam)
    down = np.mean(downs, axis=0)
    down /= np.linalg.norm(down)
    down_aligned = R_ab @ down
    axis = int(np.argmax(np.abs(down_aligned)))
    angle = np.degrees(np.arccos(abs(down_aligned[axis])))
    return {"status": "ok", "gravity_axis": "xyz"[axis], "tilt_deg": float(angle)}


def herzjesu(work: Path) -> dict:
    images = HJ / "images"
    work = work / "herzjesu"
    sfm_path = sfm(images, work)
    sfm_rec = pycolmap.Reconstruction(str(sfm_path))
    truth, levelled_by = relevelled_truth(images)
    points = gcp_from_tracks(sfm_rec, truth)
    out = {
        "sfm_images": sfm_rec.num_reg_images(),
        "sfm_points": sfm_rec.num_points3D(),
        "truth_relevelled_by_deg": levelled_by,
    }
    runs = [(2, 0, ""), (3, 0, "")]
    runs += [(n, 1, s) for s in ("obliq", "ceres") for n in (2, 3)]
    for n_ctrl, block, solver in runs:
        gcp = work / f"gcp_{n_ctrl}.txt"
        write_gcp_list(gcp, points, "EPSG:32632")
        checks = checks_of(points, n_ctrl)
        label = f"{n_ctrl}_control_points" + (f"_block_adjustment_{solver}" * block)
        result = work / f"georegistered_{label}"
        extra = ("--block_adjustment", str(block))
        if block:
            extra += ("--block_adjustment_solver", solver)
        r = run_georegister(sfm_path, images, gcp, result, checks, extra)
        out[label] = {
            "cameras": camera_errors(result, truth),
            "check_points": r["report"]["check_points"],
            "control_points": r["report"]["control_points"],
            "vertical_sd_deg": r["report"]["vertical"].get("sd_deg"),
            "block_adjustment": r["report"]["block_adjustment"],
            "wall_s": r["wall_s"],
        }
    # both solvers on the same block in this process: times as a ratio
    for n_ctrl in (2, 3):
        options = GeoregisterOptions(
            control_points_path=work / f"gcp_{n_ctrl}.txt",
            check_points=tuple(checks_of(points, n_ctrl)),
            progress=False,
        )
        out[f"{n_ctrl}_control_points_solvers"] = compare_solvers(
            sfm_path, images, options
        )
    out["colmap_model_orientation_aligner"] = colmap_aligner_tilt(
        sfm_path, images, work, truth
    )
    # the oracle of the lens: SfM with the truth's intrinsics held fixed
    known = sfm(images, work, pinhole=",".join(f"{v:g}" for v in HJ_PINHOLE))
    result = work / "georegistered_known_lens_2"
    r = run_georegister(known, images, work / "gcp_2.txt", result, checks_of(points, 2))
    out["known_lens_2_control_points"] = {
        "cameras": camera_errors(result, truth),
        "check_points": r["report"]["check_points"],
    }
    return out


def checks_of(points: list[tuple], n_control: int) -> list[str]:
    return [p[0] for p in points[n_control:]]


def berlin(work: Path) -> dict:
    images = BERLIN / "images"
    work = work / "berlin"
    sfm_path = sfm(images, work)
    gcp = BERLIN / "gcp_list.txt"
    r = run_georegister(sfm_path, images, gcp, work / "georegistered")
    rows = r["report"]["points"]
    loo = []
    for row in rows:
        try:
            rr = run_georegister(
                sfm_path, images, gcp, work / "loo", check_points=[row["name"]]
            )
        except RuntimeError as exc:
            loo.append({"name": row["name"], "error": str(exc)[-200:]})
            continue
        cp = [x for x in rr["report"]["points"] if x["role"] == "check"]
        loo.append(cp[0] if cp else {"name": row["name"], "error": "not usable"})
    return {
        "sfm_images": pycolmap.Reconstruction(str(sfm_path)).num_reg_images(),
        "control_points": r["report"]["control_points"],
        "points": rows,
        "leave_one_out": loo,
        "similarity": r["report"]["similarity"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work_path", type=Path, required=True)
    parser.add_argument("--only", choices=("herzjesu", "berlin"))
    parser.add_argument("--output_path", type=Path)
    args = parser.parse_args(argv)
    print(f"# bench georegister_real: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}")
    results = {}
    if args.only in (None, "herzjesu"):
        results["herzjesu"] = herzjesu(args.work_path)
    if args.only in (None, "berlin"):
        results["berlin"] = berlin(args.work_path)
    text = json.dumps(results, indent=1, default=float)
    print(text)
    if args.output_path:
        args.output_path.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
