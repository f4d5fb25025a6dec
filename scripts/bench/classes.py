"""The scene-class matrix of issue 25: every district x seeds, all four heads.

What it measures: for each scene class (``SCENE_CLASSES``: the paper's mixed
city, dense blocks, detached houses on the harder flight, industrial halls,
high-rise) and each seed, a synthetic scene is generated (kept under
``--work_path``, reused when present) with the sun's azimuth and elevation
drawn from the seed (so one head looks against the light in some flight of
every class), then ``register`` runs on it as a user runs it and is scored
with the measure that judges (``evaluate --vertical_offset search``), exactly
as ``external.py`` scores the external scenes: images written, below 2 px,
median and p95, per head (N, E, S, W). A class whose lens has distortion is
run with ``--camera_model SIMPLE_RADIAL`` and nothing else.

The exact command (from the repository root; ~1-2 min per scene and run on 2
shared cores)::

    python scripts/bench/classes.py --work_path W [--scene_class houses ...]
        [--seeds 1 2] [--run bundle] [--image_width 2004] [--horizontal_fov_deg 25.4]
        [--output_path bench_classes.json]

Figures go to docs/STATUS.md (the table per scene class) and to
docs/journal/independent-scenes.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import external  # noqa: E402

from obliq_colmap.synthetic import generate_scene  # noqa: E402
from obliq_colmap.synthetic.options import SCENE_CLASSES, preset  # noqa: E402


def sun_of(seed: int) -> tuple[float, float]:
    """The sun (azimuth, elevation) in degrees of a flight, drawn from its seed."""
    rng = np.random.default_rng([seed, 25])
    return float(rng.uniform(0.0, 360.0)), float(rng.uniform(30.0, 60.0))


def scene_for(
    work: Path, name: str, seed: int, image_width: int, fov_deg: float | None
) -> Path:
    """Generate (or reuse) the scene of one class and seed."""
    lens = "" if fov_deg is None else f"_fov{fov_deg:g}"
    path = work / "scenes" / f"{name}_s{seed}_w{image_width}{lens}"
    if (path / "scene.json").is_file():
        return path
    azimuth, elevation = sun_of(seed)
    options = preset(
        name,
        image_width_px=image_width,
        sun_azimuth_deg=azimuth,
        sun_elevation_deg=elevation,
        **({} if fov_deg is None else {"horizontal_fov_deg": fov_deg}),
    )
    print(f"# synth {name} seed {seed}: sun {azimuth:.0f} / {elevation:.0f} deg")
    path.parent.mkdir(parents=True, exist_ok=True)
    generate_scene(path, options, seed=seed, show_progress=False, preset=name)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work_path", type=Path, required=True)
    parser.add_argument("--scene_class", action="append", choices=SCENE_CLASSES)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--run", action="append", choices=external.RUNS)
    parser.add_argument("--image_width", type=int, default=2004)
    parser.add_argument(
        "--horizontal_fov_deg",
        type=float,
        help="the lens of every scene (default the preset's, 45 deg; the GSD is "
        "kept, so a longer lens flies higher)",
    )
    parser.add_argument("--register_args", default="")
    parser.add_argument("--output_path", type=Path)
    args = parser.parse_args(argv)
    classes = args.scene_class or list(SCENE_CLASSES)
    runs = args.run or ["bundle"]
    args.work_path.mkdir(parents=True, exist_ok=True)
    print(f"# bench classes: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}")
    everything: dict = {}
    for name in classes:
        for seed in args.seeds:
            scene = scene_for(
                args.work_path, name, seed, args.image_width, args.horizontal_fov_deg
            )
            model = external.camera_model_of(scene)
            results = {}
            for run in runs:
                out = args.work_path / "runs" / f"{scene.name}_{run}"
                if out.exists():
                    shutil.rmtree(out)
                out.parent.mkdir(parents=True, exist_ok=True)
                extra = args.register_args.split()
                r = external.run_register(scene, out, run, model, extra)
                try:
                    results[run] = {
                        "run": r,
                        "eval": external.evaluate_run(scene, out, run),
                    }
                except Exception as exc:  # noqa: BLE001 - the table says it
                    results[run] = {"run": r, "error": f"{type(exc).__name__}: {exc}"}
            label = f"{name} seed {seed}" + (
                f" (--camera_model {model})" if model else ""
            )
            external.print_scene(label, results)
            everything[scene.name] = {"class": name, "seed": seed, "runs": results}
    if args.output_path:
        args.output_path.write_text(
            json.dumps(external.json_ready(everything), indent=1)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
