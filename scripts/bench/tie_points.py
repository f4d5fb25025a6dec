"""Tie points on a scene with known poses: counts per image, time, and the
triangulated points' reprojection error (the truth's poses, so the error is
the features' own noise). Our generator's scenes and the external ones
(``../shared/data/external_oblique/S``: the ground is their true ground
corners' median height).

    python scripts/bench/tie_points.py --scene_path data_samples/oblique_small
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from obliq_colmap.adjustment.ties import TiePointOptions, tie_points


def _ground_height(scene_path: Path) -> float:
    """The scene's ground height in the frame of its ``gt`` model."""
    scene = json.loads((scene_path / "scene.json").read_text())
    if "origin" in scene:  # our generator's
        return float(scene["origin"][2])
    gt = json.loads((scene_path / "gt_buildings.json").read_text())
    xyz = np.asarray(gt["corners"], float)
    ground = np.asarray(gt["corner_info"])[:, 1] == 0
    return float(np.median(xyz[ground, 2]))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene_path", type=Path, required=True)
    ap.add_argument("--max_image_size", type=int, default=1000)
    args = ap.parse_args()
    rec = pycolmap.Reconstruction(args.scene_path / "gt")
    ground_z = _ground_height(args.scene_path)
    images = sorted(rec.images.values(), key=lambda im: im.name)
    gray = [
        cv2.imread(str(args.scene_path / "images" / im.name), cv2.IMREAD_GRAYSCALE)
        for im in images
    ]
    cams = [rec.cameras[im.camera_id] for im in images]
    poses = [im.cam_from_world() for im in images]
    t0 = time.perf_counter()
    ties = tie_points(
        gray, cams, poses, ground_z, TiePointOptions(max_image_size=args.max_image_size)
    )
    dt = time.perf_counter() - t0
    per = ties.per_image(len(images))
    err = []
    for i in range(len(images)):
        m = ties.obs_image == i
        uv = cams[i].img_from_cam(poses[i] * ties.xyz[ties.obs_point[m]])
        err.append(np.linalg.norm(uv - ties.obs_xy[m], axis=1))
    err = np.concatenate(err)
    print(
        f"images {len(images)}  points {len(ties.xyz)}  observations {len(ties.obs_xy)}"
    )
    print(f"per image: min {per.min()}  median {np.median(per):.0f}  max {per.max()}")
    print(
        "reprojection at true poses: "
        f"median {np.median(err):.3f} px  p95 {np.percentile(err, 95):.3f} px"
    )
    print(f"time {dt:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
