"""Time :func:`obliq_colmap.evaluate.evaluate_block` on a city-sized block.

Random oblique cameras over a square of corners; each image sees the corners
that project inside it. Prints the wall time of the evaluation (full and
across verticals); no files are written.

Run (from the repository root)::

    python scripts/bench/evaluate.py [--num_images 500] [--num_corners 20000]

Figures: docs/STATUS.md (foundation: the evaluation's time) and
docs/journal/render.md (the foundation's journal, beside the renderer).

Data: none (the block is generated in memory).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from obliq_colmap.colmap_io import Block, ImageRecord
from obliq_colmap.evaluate import EvaluateOptions, evaluate_block
from obliq_colmap.geometry import Camera, Pose, project, rotation_from_axis_angle

ORIGIN = np.array([512300.0, 5612400.0, 130.0])


def make_block(num_images: int, num_corners: int, rng) -> tuple:
    side = 1500.0
    corners = np.column_stack(
        [
            rng.uniform(-side / 2, side / 2, (num_corners, 2)),
            rng.choice([0.0, 12.0, 18.0], num_corners),
        ]
    )
    cam = Camera("OPENCV", 4008, 2672, [4000, 4000, 2004, 1336, -0.05, 0.01, 0, 0])
    images, visible = {}, {}
    for i in range(num_images):
        heading = rng.uniform(0, 2 * np.pi)
        target = np.r_[rng.uniform(-side / 2, side / 2, 2), 0.0]
        c = target + [-400 * np.sin(heading), -400 * np.cos(heading), 400.0]
        z = (target - c) / np.linalg.norm(target - c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        pose = Pose.from_center(np.stack([x, np.cross(z, x), z]), c)
        name = f"img_{i:05d}.jpg"
        images[i + 1] = ImageRecord(i + 1, name, 1, pose)
        xy, d = project(cam, pose, corners)
        inside = (d > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < cam.width)
        inside &= (xy[:, 1] >= 0) & (xy[:, 1] < cam.height)
        visible[name] = np.nonzero(inside)[0]
    gt = Block({1: cam}, images).shifted(-ORIGIN)
    est = Block({1: cam}, {})
    for i, im in gt.images.items():
        R = (
            rotation_from_axis_angle(rng.normal(0, 1e-4, 3))
            @ im.cam_from_world.rotation
        )
        c = im.cam_from_world.center + rng.normal(0, 0.1, 3)
        est.images[i] = ImageRecord(i, im.name, 1, Pose.from_center(R, c))
    return est, gt, corners + ORIGIN, visible


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num_images", type=int, default=500)
    parser.add_argument("--num_corners", type=int, default=20000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    est, gt, corners, visible = make_block(args.num_images, args.num_corners, rng)
    per_image = np.mean([len(v) for v in visible.values()])
    print(f"{args.num_images} images, {per_image:.0f} visible corners per image")
    for across in (False, True):
        t0 = time.perf_counter()
        ev = evaluate_block(
            est, gt, corners, visible, EvaluateOptions(across_vertical=across)
        )
        dt = time.perf_counter() - t0
        s = ev.summary
        print(
            f"across_vertical={across}: {dt:.2f} s, registered {s.num_registered} / "
            f"{s.num_total}, median deviation {s.deviation_median_px:.3f} px"
        )


if __name__ == "__main__":
    main()
