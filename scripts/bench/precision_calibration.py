#!/usr/bin/env python
"""Is the predicted precision honest? Measured deviation against the bundle's
predicted sd, per image, over written models of scenes with the truth
(issue 26: the RMS of deviation / sd within [0.5, 2] over >= 5 scenes x seeds).

Per run (a model ``register`` wrote, and its scene): the judging measure
(``evaluate --vertical_offset search``, in this process: each image's mean
deviation of the true corners it sees, px) against ``report.json``'s
``uncertainty.images[name].predicted_sd_px`` (the last bundle's per-image sd
of its constrained points, scaled by its variance factor). An image's mean
deviation is a mean of absolute errors, so for an honest sd the ratio's RMS
is about 0.8-0.9 (the RMS of a 2D error's magnitude over its per-axis sd is
sqrt 2; a mean over the image's corners of correlated errors lies between).
Written images only; a run without predicted sds (the bundle skipped) is
reported and left out. Prints one line per run and the pooled figures; with
``--output_path`` the per-image rows as JSON.

Run (from the repository root)::

    python scripts/bench/precision_calibration.py \\
        --run ../shared/data/external_oblique/urban-101 OUT/urban-101_bundle \\
        --run /work/scenes/paper_s1 OUT2 ... [--output_path rows.json]

``--runs_glob SCENES_ROOT/*:MODELS_ROOT/{scene}_bundle`` pairs every scene
folder with the model named after it (the layout of ``external.py`` and
``classes.py`` work folders); ``--seeds_json R.json`` adds the runs of
``seeds.py --output_path R.json`` (their ``precision_vs_deviation``, measured
the same way in that process).
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np

from obliq_colmap.evaluate import EvaluateOptions, evaluate_model


def deviations(scene: Path, model: Path) -> dict[str, float]:
    """Image name -> mean deviation (px, the judging measure) of a model."""
    ev = evaluate_model(model, scene, EvaluateOptions(vertical_offset="search"))
    return {
        im.name: float(im.mean_deviation_px)
        for im in ev.images
        if np.isfinite(im.mean_deviation_px)
    }


def predicted(model: Path) -> dict[str, float]:
    """Image name -> predicted sd (px) from the model's report.json."""
    rep = json.loads((model / "report.json").read_text())
    images = (rep.get("uncertainty") or {}).get("images") or {}
    return {
        name: float(v["predicted_sd_px"])
        for name, v in images.items()
        if v.get("predicted_sd_px") is not None and v["predicted_sd_px"] > 0
    }


def summary(r: np.ndarray) -> str:
    if not len(r):
        return "no images"
    return (
        f"{len(r)} images: RMS {np.sqrt(np.mean(r * r)):.2f},"
        f" median {np.median(r):.2f},"
        f" p95 {np.quantile(r, 0.95):.2f}, share within [0.5, 2] x"
        f" {np.mean((r >= 0.5) & (r <= 2)):.0%}"
    )


class Rows:
    """Per-image rows and per-run RMS of the ratio, over every run added."""

    def __init__(self) -> None:
        self.rows: list[dict] = []
        self.per_run: list[float] = []

    def add(self, scene: str, label: str, dev: dict, sd: dict) -> None:
        """One run: image name -> deviation (px) and -> predicted sd (px)."""
        names = sorted(set(sd) & set(dev))
        r = np.array([dev[n] / sd[n] for n in names])
        self.per_run.append(np.sqrt(np.mean(r * r)) if len(r) else np.nan)
        self.rows += [
            dict(scene=scene, model=label, name=n, deviation_px=dev[n],
                 predicted_sd_px=sd[n])
            for n in names
        ]  # fmt: skip
        print(f"{Path(scene).name:16s} {label}: {summary(r)}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--run", nargs=2, action="append", default=[], metavar=("SCENE", "MODEL")
    )
    ap.add_argument("--runs_glob", action="append", default=[])
    ap.add_argument("--seeds_json", type=Path, action="append", default=[])
    ap.add_argument("--output_path", type=Path)
    args = ap.parse_args()
    runs = [(Path(s), Path(m)) for s, m in args.run]
    for spec in args.runs_glob:
        scenes, models = spec.split(":", 1)
        for s in sorted(glob.glob(scenes)):
            m = Path(models.format(scene=Path(s).name))
            if (m / "report.json").is_file():
                runs.append((Path(s), m))
    out = Rows()
    for scene, model in runs:
        sd = predicted(model)
        if not sd:
            print(f"{model}: no predicted sds (bundle skipped?); left out")
            continue
        out.add(str(scene), str(model), deviations(scene, model), sd)
    for path in args.seeds_json:
        for run in json.loads(path.read_text()):
            pv = run.get("precision_vs_deviation") or {}
            pv = {n: v for n, v in pv.items() if v[0] and v[0] > 0}
            out.add(
                run["scene"],
                f"seed {run['seed']}",
                {n: v[1] for n, v in pv.items()},
                {n: v[0] for n, v in pv.items()},
            )
    rows, per_run = out.rows, out.per_run
    r = np.array([x["deviation_px"] / x["predicted_sd_px"] for x in rows])
    print(f"pooled over {len(per_run)} runs, {summary(r)}")
    if per_run:
        print(
            f"per-run RMS: median {np.nanmedian(per_run):.2f},"
            f" range {np.nanmin(per_run):.2f}-{np.nanmax(per_run):.2f}"
        )
    if args.output_path:
        args.output_path.write_text(json.dumps(rows, indent=0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
