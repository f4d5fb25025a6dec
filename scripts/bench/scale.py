"""Scale benchmarks (issue 29): the global adjustment's cost against the
number of images, the peak memory of a whole run, and the map's size.

Run (from the repository root)::

    python scripts/bench/scale.py bundle [--images 36 100 200 1000]
    python scripts/bench/scale.py memory --scene DIR --num_workers 2
    python scripts/bench/scale.py cadastre [--copies 100]

* ``bundle``: :func:`~obliq_colmap.bundle.solve_bundle` on synthetic blocks
  of the paper's camera (4 oblique heads, 4008 x 2672 px, 500 m altitude,
  stations 300 m apart, 0.5 px noise; ``make_synthetic_problem``) with
  N / 4 stations, each size in a fresh process (BLAS on one thread): the
  build time, the solve's time, iterations, time per iteration, and the
  peak RSS before and after the solve.
* ``memory``: ``obliq-colmap register`` on a scene folder (``synth``'s
  layout) while sampling the RSS of the whole process tree (parent and all
  workers) every 0.2 s; prints the peak sum.
* ``cadastre``: stage 2 of the 16-image sample with its map, and with the
  map plus ``--copies`` copies of it tiled far away (a city-wide map):
  time per image, which the spatial index should keep equal.

Figures: docs/STATUS.md ("Formats, bad input, scale (issue 29)") and
docs/journal/scale.md. Needs ``psutil`` for ``memory``.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from obliq_colmap.synthetic.bundle_problem import PAPER_FLIGHT, make_synthetic_problem

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data_samples" / "oblique_small"

#: The paper's camera and flight; the block's size follows the number of
#: stations.
PAPER = dict(**PAPER_FLIGHT, view_cone_margin_deg=10.0)

#: Stations (x, y) per block size: 4 images (heads) per station.
STATIONS = {36: (3, 3), 100: (5, 5), 200: (10, 5), 400: (10, 10), 1000: (25, 10)}


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bundle_one(num_images: int) -> dict:
    """Build and solve one block of ``num_images`` images (this process)."""
    from threadpoolctl import threadpool_limits

    from obliq_colmap.bundle import BundleOptions, solve_bundle

    nx, ny = STATIONS[num_images]
    # The buildings cover the stations' grid and 220 m beyond, as the
    # paper's 3 x 3 stations and 26 x 26 buildings do.
    span = [PAPER["station_spacing_m"] * (n - 1) + 440.0 for n in (nx, ny)]
    buildings = tuple(round(s / PAPER["spacing_m"]) for s in span)
    t0 = time.perf_counter()
    syn = make_synthetic_problem(
        seed=1, stations=(nx, ny), buildings=buildings, **PAPER
    )
    build_s = time.perf_counter() - t0
    rss_build = _peak_rss_mib()
    P = syn.problem
    with threadpool_limits(1):
        t0 = time.perf_counter()
        result = solve_bundle(P, BundleOptions())
        solve_s = time.perf_counter() - t0
    s = result.summary
    return {
        "images": len(P.image_ids),
        "buildings": buildings,
        "vertical": s.num_vertical,
        "horizontal": s.num_horizontal,
        "heights": s.num_heights,
        "camera_params": s.num_camera_params,
        "build_s": round(build_s, 2),
        "solve_s": round(solve_s, 2),
        "iterations": s.num_iterations,
        "s_per_iteration": round(solve_s / max(1, s.num_iterations), 3),
        "peak_rss_after_build_mib": round(rss_build),
        "peak_rss_mib": round(_peak_rss_mib()),
        "final_rmse_px": [
            round(s.final_rmse_vertical_px, 3),
            round(s.final_rmse_horizontal_px, 3),
        ],
        "termination": s.termination,
    }


def bundle(sizes: list[int]) -> None:
    """Each size in a fresh process (its own peak RSS)."""
    rows = []
    for n in sizes:
        out = subprocess.run(
            [sys.executable, __file__, "_bundle_one", str(n)],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    base = next((r for r in rows if r["images"] == 100), None)
    if base:
        for r in rows:
            print(f"{r['images']} images: {r['solve_s'] / base['solve_s']:.2f}x 100's")


def memory(scene: Path, num_workers: int, extra: list[str]) -> None:
    """Peak RSS of the process tree of one ``register`` run on ``scene``."""
    import psutil

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "obliq_colmap",
            "register",
            "--image_path",
            str(scene / "images"),
            "--cadastre_path",
            str(scene / "cadastre.geojson"),
            "--input_path",
            str(scene / "priors"),
            "--output_path",
            str(Path(tmp) / "out"),
            "--num_workers",
            str(num_workers),
            "--no_progress",
            *extra,
        ]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
        parent = psutil.Process(proc.pid)
        peak, peak_n = 0, 0
        while proc.poll() is None:
            try:
                tree = [parent, *parent.children(recursive=True)]
                rss = sum(p.memory_info().rss for p in tree if p.is_running())
            except psutil.Error:  # a worker ended while sampled
                continue
            if rss > peak:
                peak, peak_n = rss, len(tree)
            time.sleep(0.2)
        wall = time.perf_counter() - t0
    print(
        json.dumps(
            {
                "scene": str(scene),
                "num_workers": num_workers,
                "returncode": proc.returncode,
                "wall_s": round(wall, 1),
                "peak_tree_rss_gib": round(peak / 2**30, 3),
                "processes_at_peak": peak_n,
            }
        )
    )


def _tiled_map(path: Path, copies: int, out: Path) -> int:
    """Write the map plus ``copies`` shifted copies 5 km and more away;
    returns the number of features."""
    data = json.loads(path.read_text())
    features = list(data["features"])
    side = math.ceil(math.sqrt(copies))
    for c in range(copies):
        dx, dy = 5000.0 * (1 + c % side), 5000.0 * (1 + c // side)
        for f in data["features"]:
            g = json.loads(json.dumps(f["geometry"]))
            g["coordinates"] = _shift(g["coordinates"], dx, dy)
            features.append({**f, "geometry": g})
    out.write_text(json.dumps({**data, "features": features}))
    return len(features)


def _shift(coords, dx: float, dy: float):
    if isinstance(coords[0], (int, float)):
        return [coords[0] + dx, coords[1] + dy, *coords[2:]]
    return [_shift(c, dx, dy) for c in coords]


def cadastre(copies: int) -> None:
    """Stage 2 of the sample with its own map and with a tiled city map."""
    from obliq_colmap.pipeline import PipelineOptions, run_register

    with tempfile.TemporaryDirectory() as tmp:
        big = Path(tmp) / "city.geojson"
        _tiled_map(SAMPLE / "cadastre.geojson", copies, big)
        for label, path in (("sample map", SAMPLE / "cadastre.geojson"), ("city", big)):
            options = PipelineOptions(
                stop_after="initial", num_workers=1, progress=False
            )
            t0 = time.perf_counter()
            run = run_register(SAMPLE / "images", path, SAMPLE / "priors", options)
            wall = time.perf_counter() - t0
            per = [o.time_s.get("total", math.nan) for o in run.outcomes.values()]
            print(
                json.dumps(
                    {
                        "map": label,
                        "features": len(json.loads(path.read_text())["features"]),
                        "registered": sum(o.registered for o in run.outcomes.values()),
                        "wall_s": round(wall, 2),
                        "median_image_s": round(sorted(per)[len(per) // 2], 3),
                    }
                )
            )


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "_bundle_one":
        print(json.dumps(bundle_one(int(sys.argv[2]))))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    b = sub.add_parser("bundle")
    b.add_argument("--images", type=int, nargs="+", default=[36, 100, 200, 1000])
    m = sub.add_parser("memory")
    m.add_argument("--scene", type=Path, required=True)
    m.add_argument("--num_workers", type=int, default=2)
    c = sub.add_parser("cadastre")
    c.add_argument("--copies", type=int, default=100)
    args, extra = parser.parse_known_args()
    if args.what == "bundle":
        bundle(args.images)
    elif args.what == "memory":
        memory(args.scene, args.num_workers, extra)
    else:
        cadastre(args.copies)


if __name__ == "__main__":
    main()
