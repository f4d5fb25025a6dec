"""Benchmark of ``obliq-colmap register`` end to end on synthetic scenes.

For each scene: the run's time per stage and in total, peak memory (this
process and its workers), the counts of constraints, and the accuracy of the
result against the ground truth (``evaluate``: full deviation and across the
projected vertical), beside the priors' (baseline). The run is
``register_runs.bench_scene``: the scene's prior noise as the prior sigmas
(a user knows their GPS/INS), every other option as ``register``'s.

Run (from the repository root)::

    python scripts/bench/register.py --scene_path /work/scenes/paper_s1 \\
        --scene_path /work/scenes/hard_s1 [--stop_after bundle] [--num_workers 2] \\
        [--output_path bench_register.json]

Figures: docs/STATUS.md (end to end: registered images, deviation, time and
memory per scene) and docs/journal/end-to-end.md.

Data: synthetic scenes, made with ``obliq-colmap synth --preset paper --seed N
--output_path DIR`` (``--preset hard`` for the harder one).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from register_runs import add_run_arguments, bench_scene, print_row  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scene_path", action="append", required=True, help="synthetic scene folder"
    )
    parser.add_argument("--output_path", help="write all rows as JSON here")
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    rows = []
    for scene in args.scene_path:
        scene = Path(scene)
        if not (scene / "gt").is_dir():
            print(f"error: {scene} is not a synthetic scene (no gt/)", file=sys.stderr)
            return 2
        row = bench_scene(scene, args)
        print_row(row)
        rows.append(row)
    meta = {
        "date": time.strftime("%Y-%m-%d"),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
        "python": platform.python_version(),
    }
    print(f"machine: {meta}")
    if args.output_path:
        Path(args.output_path).write_text(
            json.dumps({"meta": meta, "rows": rows}, indent=2, default=float) + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
