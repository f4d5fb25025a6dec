"""Benchmark the synthetic renderer: seconds per image, split raster / shade / post.

Renders ``--num_images`` images of a preset's flight on ONE core (OpenCV and
BLAS limited to one thread; numpy's element-wise kernels are single-threaded) and
prints the median per stage and in total, plus the city build time.

Run (from the repository root)::

    python scripts/bench/render.py --preset paper --image_width 2004 --num_images 7
    python scripts/bench/render.py --preset paper --image_width 4008 --num_images 3

Figures: docs/STATUS.md (foundation: seconds per rendered image) and
docs/journal/render.md.

Data: none (the city and the images are generated in memory).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from obliq_colmap.synthetic import build_city, preset, render_image
from obliq_colmap.synthetic.cameras import STREAM_RENDER, stream, true_block


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--image_width", type=int, default=2004)
    parser.add_argument("--num_images", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=1, help="untimed renders first")
    parser.add_argument("--json", default=None, help="also write the figures here")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    threadpool_limits(1)  # BLAS (the vertex transform) on one thread too
    options = preset(args.preset, image_width_px=args.image_width)
    t0 = time.perf_counter()
    city = build_city(options, args.seed)
    build_s = time.perf_counter() - t0
    block = true_block(options, args.seed)
    ids = sorted(block.images)
    # Spread the timed images over the four directions.
    picks = [
        ids[int(k)] for k in np.linspace(0, len(ids) - 1, args.num_images + args.warmup)
    ]
    rows, stages = [], []
    for n, image_id in enumerate(picks):
        im = block.images[image_id]
        t, c = time.perf_counter(), time.process_time()
        _, _, buffers = render_image(
            city,
            block.cameras[im.camera_id],
            im.cam_from_world,
            options,
            stream(args.seed, STREAM_RENDER, image_id),
        )
        total, cpu = time.perf_counter() - t, time.process_time() - c
        if n >= args.warmup:
            rows.append((im.name, total, cpu))
            stages.append([buffers["timing_s"][k] for k in ("raster", "shade", "post")])
    stages = np.asarray(stages)
    totals = np.array([r[1] for r in rows])
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}, numpy {np.__version__}",
        "preset": args.preset,
        "image_size": [options.image_width_px, options.image_height_px],
        "supersample": options.supersample,
        "triangles": int(len(city.faces)),
        "city_build_s": round(build_s, 2),
        "images": [r[0] for r in rows],
        "total_s": totals.round(2).tolist(),
        "median_total_s": round(float(np.median(totals)), 2),
        "median_cpu_s": round(float(np.median([r[2] for r in rows])), 2),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "median_raster_s": round(float(np.median(stages[:, 0])), 2),
        "median_shade_s": round(float(np.median(stages[:, 1])), 2),
        "median_post_s": round(float(np.median(stages[:, 2])), 2),
    }
    print(json.dumps(result, indent=2))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)


if __name__ == "__main__":
    main()
