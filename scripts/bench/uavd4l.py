"""Stage 1 + stage 2 on the real UAVD4L-LoD drone image (near-nadir, thermal).

Measures stages 1 and 2 on one real image: the VP status and its error, the
segments, the registration's result, and the rotation / centre error of the
prior and of the result against the ground-truth pose (the centre error also
without its vertical part: one image cannot observe the camera height, which
stage 2 holds at the prior).

Run (from the repository root)::

    OMP_NUM_THREADS=1 python scripts/bench/uavd4l.py \\
        --data /work/shared/data/uavd4l_lodloc_demo --overlay /tmp/uavd4l.png

Figures: docs/journal/stage2-registration.md ("The real UAVD4L-LoD drone
image", 2026-12-01).

Data: ``/work/shared/data/uavd4l_lodloc_demo`` (see its README and licence:
the LoD1 model is research use only; nothing of it is written outside a
temporary folder).

The LoD1 model is turned into a cadastre: its up-facing faces (flat roofs)
projected to the ground plane and merged per connected building (shapely
``unary_union``), written as a temporary GeoJSON in the data's LOCAL metric
frame (``"crs": null``, z up; the frame of the poses), loaded with origin (0,
0, 0) so that local = the data's frame. The GPS/IMU prior (4.3 m, 20.7 m
vertical, 4.0 deg off) is the registration's prior; the VP prior is the INS
cone around the prior rotation's vertical (the image is 0.9 deg off nadir:
the vertical VP, the nadir point, lies inside the frame).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from shapely.geometry import Polygon, mapping  # noqa: E402
from shapely.ops import unary_union  # noqa: E402

from obliq_colmap.cadastre import load_cadastre  # noqa: E402
from obliq_colmap.geometry import Camera, Pose, rotation_angle_deg  # noqa: E402
from obliq_colmap.registration import (  # noqa: E402
    RegistrationOptions,
    draw_registration_overlay,
    register_image,
)
from obliq_colmap.vanishing import (  # noqa: E402
    VanishingOptions,
    VPPrior,
    detect_vertical_vp,
    vertical_segments,
)

NAME = "DJI_20230513163714_0033_T"
cv2.setNumThreads(1)


def read_obj(path: Path) -> tuple[np.ndarray, list[list[int]]]:
    """Vertices (V, 3) and faces (0-based vertex indices) of an OBJ mesh."""
    verts, faces = [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(v) for v in line.split()[1:4]])
        elif line.startswith("f "):
            faces.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return np.asarray(verts), faces


def footprints(verts: np.ndarray, faces: list[list[int]]) -> tuple[list, list]:
    """Footprint polygons (the union of the flat roofs' projections) and the
    mean roof height above the lowest vertex of each (for information)."""
    roofs, heights = [], []
    for f in faces:
        P = verts[f]
        if len(P) < 3:
            continue
        nrm = np.cross(P[1] - P[0], P[2] - P[0])
        if np.linalg.norm(nrm) == 0 or nrm[2] / np.linalg.norm(nrm) < 0.9:
            continue  # walls, bottoms
        poly = Polygon(P[:, :2])
        if poly.is_valid and poly.area > 1.0:
            roofs.append(poly)
            heights.append(P[:, 2].mean())
    merged = unary_union(roofs)
    polys = list(merged.geoms) if hasattr(merged, "geoms") else [merged]
    return [p for p in polys if p.area > 4.0], heights


def pose_from_c2w(path: Path) -> Pose:
    T = np.loadtxt(path)
    R_c2w, c = T[:3, :3], T[:3, 3]
    return Pose.from_center(R_c2w.T, c)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="/work/shared/data/uavd4l_lodloc_demo")
    ap.add_argument("--rotation_sigma_deg", type=float, default=4.0)
    ap.add_argument("--position_sigma_m", type=float, default=5.0)
    ap.add_argument(
        "--vp",
        choices=["detect", "prior", "true"],
        default="detect",
        help="detect: stage 1 (falls back to the prior's vertical); prior / "
        "true: the second pass through the prior's / the TRUE vertical VP "
        "(diagnostics: what stage 2 does with a given vertical)",
    )
    ap.add_argument(
        "--ground_height",
        type=float,
        help="ground height (m) in the PRIOR's vertical datum (stage 2's "
        "--ground_height); default: searched",
    )
    ap.add_argument(
        "--allow_vp_in_frame",
        type=int,
        choices=(0, 1),
        default=0,
        help="1: register although the vertical VP lies inside the frame "
        "(RegistrationOptions.allow_vp_in_frame; the default refuses near-nadir views)",
    )
    ap.add_argument("--overlay", help="write the registration overlay PNG here")
    ap.add_argument("--output", help="JSON file for the figures")
    args = ap.parse_args(argv)
    data = Path(args.data)
    t0 = time.perf_counter()
    verts, faces = read_obj(data / "UAVD4L-LoD1.obj")
    polys, _ = footprints(verts, faces)
    ground_z = float(verts[:, 2].min())
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "footprints.geojson"
        fc = {
            "type": "FeatureCollection",
            "crs": None,
            "features": [
                {"type": "Feature", "properties": {"id": i}, "geometry": mapping(p)}
                for i, p in enumerate(polys)
            ],
        }
        path.write_text(json.dumps(fc))
        cad = load_cadastre(path, origin=np.zeros(3))
    t_map = time.perf_counter() - t0
    K = np.loadtxt(data / "intrinsic" / f"{NAME}_intrinsic.txt")[:3, :3]
    img = cv2.imread(str(data / "Query_image" / f"{NAME}.JPG"), cv2.IMREAD_GRAYSCALE)
    H, W = img.shape
    cam = Camera("PINHOLE", W, H, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    gt = pose_from_c2w(data / "GT_pose" / f"{NAME}_pose.txt")
    prior = pose_from_c2w(data / "GPS_pose" / f"{NAME}_pose.txt")
    down = np.array([0.0, 0.0, -1.0])
    off_nadir = math.degrees(math.acos(gt.rotation[2] @ down))

    # Stage 1: the vertical VP within the INS cone around the prior's vertical.
    cone = 3.0 * args.rotation_sigma_deg + 1.0
    t0 = time.perf_counter()
    vp = detect_vertical_vp(
        img, VanishingOptions(), cam, VPPrior.from_rotation(prior.rotation, cone), 0
    )
    t_vp = time.perf_counter() - t0
    n_true = gt.rotation @ down
    vp_err = math.nan
    if vp.vertical_direction is not None:
        vp_err = math.degrees(math.acos(min(1.0, abs(vp.vertical_direction @ n_true))))
    prior_vert_err = math.degrees(math.acos(min(1.0, (prior.rotation @ down) @ n_true)))
    if args.vp != "detect":
        n = n_true if args.vp == "true" else prior.rotation @ down
        seg = vertical_segments(img, cam.K @ n, camera=cam).endpoints
        vtol = RegistrationOptions().vp_tolerance_deg
    elif vp.status == "ok" and vp.vertical_segments is not None:
        seg, n = vp.vertical_segments.endpoints, vp.vertical_direction
        vtol = RegistrationOptions().vp_tolerance_deg
    else:  # fall back to the prior's vertical and the first-pass segments
        seg, n = vp.segments.endpoints, None
        vtol = 2.0 * args.rotation_sigma_deg

    # Stage 2.
    opts = RegistrationOptions(
        prior_position_sigma_m=args.position_sigma_m,
        prior_rotation_sigma_deg=args.rotation_sigma_deg,
        prior_focal_sigma=0.01,
        height_range_m=(0.0, float(verts[:, 2].max() - ground_z)),
        vp_tolerance_deg=vtol,
        ground_height=args.ground_height,
        allow_vp_in_frame=bool(args.allow_vp_in_frame),
    )
    t0 = time.perf_counter()
    r = register_image(seg, n, cam, prior, cad, opts, segments_undistorted=True)
    t_reg = time.perf_counter() - t0

    def errors(pose: Pose) -> dict:
        dc = pose.center - gt.center
        return dict(
            rotation_deg=rotation_angle_deg(pose.rotation, gt.rotation),
            center_m=float(np.linalg.norm(dc)),
            horizontal_m=float(np.linalg.norm(dc[:2])),
            vertical_m=float(dc[2]),
        )

    out = dict(
        image=f"{NAME} ({W}x{H}, thermal), {off_nadir:.2f} deg off nadir",
        map=dict(
            footprints=len(polys),
            corners=int(len(cad.corner_xy)),
            crs=None,
            frame="the data's local metric frame (z up), origin (0, 0, 0)",
            seconds=t_map,
        ),
        vp=dict(
            used=args.vp,
            status=vp.status,
            error_deg=vp_err,
            prior_vertical_error_deg=prior_vert_err,
            segments=len(seg),
            cone_deg=cone,
            seconds=t_vp,
        ),
        registration=dict(
            success=r.success,
            message=r.message,
            inliers=r.num_inliers,
            candidates=r.num_candidates,
            segments_used=r.num_segments,
            ground_height_m=r.ground_height,
            true_ground_min_z_m=ground_z,
            seconds=t_reg,
            focal=None if r.camera is None else float(r.camera.params[0]),
        ),
        prior=errors(prior),
        result=errors(r.cam_from_world),
    )
    print(json.dumps(out, indent=1))
    if args.overlay:
        bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        cv2.imwrite(args.overlay, draw_registration_overlay(bgr, cad, cam, prior, r))
    if args.output:
        Path(args.output).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
