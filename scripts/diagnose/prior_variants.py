"""Which prior error blocks a scene? ``register`` on variants of its priors.

Each variant is a copy of a synthetic scene (images, map and truth linked,
not copied) whose priors model is changed in ONE respect, so that the run
tells which error of the priors the pipeline fails on; each runs ``register``
end to end and is scored as in ``bench/register.py``
(``register_runs.bench_scene``), one row per variant.

Run (from the repository root)::

    python scripts/diagnose/prior_variants.py --scene_path /work/scenes/hard_s1 \\
        --variant scene --variant true_camera [--stop_after initial] \\
        [--camera_model RADIAL --refine_extra_params 1] [--output_path R.json]

Figures: docs/journal/stage2-registration.md (issue 4, the ``hard`` scene's
priors, 2026-12-01); the live question is issue 25 (scenes we did not make:
which error of theirs the chain fails on).

Data: a synthetic scene (``obliq-colmap synth``; variants are written to a
temporary folder and removed).

The variants:

* ``scene``: the scene as generated;
* ``true_camera``: the priors' cameras replaced by the true ones (focal
  length, principal point and lens distortion);
* ``true_distortion``: the priors' focal length and principal point, the true
  distortion parameters;
* ``true_focal``: the true focal length, the priors' principal point and (no)
  distortion;
* ``paper_noise``: the poses drawn again from the true ones with the ``paper``
  preset's prior noise (8 m / 5 m / 1.5 deg, focal 3 %) by the same random
  stream as the generator, cameras as the priors (no distortion).

The scene's ``scene.json`` goes with each variant with the prior noise it
has, so that the run sets the ``--prior_*_sigma`` options as a user who
knows their GPS/INS would.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from obliq_colmap.bundle.residuals import focal_principal_extra_indices
from obliq_colmap.colmap_io import Block, read_model, write_absolute_model
from obliq_colmap.geometry import Camera
from obliq_colmap.synthetic.cameras import prior_block
from obliq_colmap.synthetic.options import PRESETS, SceneOptions

# The helpers shared by the scripts live in scripts/bench/, which is not a
# package: put it first on the path (scripts/README.md).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from register_runs import add_run_arguments, bench_scene, print_row  # noqa: E402

VARIANTS = ("scene", "true_camera", "true_distortion", "true_focal", "paper_noise")
#: The scene files a variant shares with its scene (linked).
_SHARED = ("images", "cadastre.geojson", "gt", "gt_buildings.json")


def _with_cameras(priors: Block, cameras: dict[int, Camera]) -> Block:
    return Block(cameras=cameras, images=dict(priors.images))


def variant_priors(
    variant: str, priors: Block, gt: Block, options: SceneOptions, seed: int
) -> tuple[Block, SceneOptions]:
    """The priors of a variant (absolute frame) and the scene options they have."""
    if variant == "scene":
        return priors, options
    if variant == "true_camera":
        return _with_cameras(priors, dict(gt.cameras)), options
    if variant in ("true_distortion", "true_focal"):
        cams = {}
        for cid, cam in priors.cameras.items():
            true = gt.cameras[cid]
            focal, _, extra = focal_principal_extra_indices(cam.model)
            keep = extra if variant == "true_distortion" else focal
            p = cam.params.copy()
            p[keep] = true.params[keep]
            cams[cid] = Camera(cam.model, cam.width, cam.height, p, cid)
        return _with_cameras(priors, cams), options
    if variant == "paper_noise":
        paper = PRESETS["paper"]
        noise = {
            f.name: getattr(paper, f.name)
            for f in dataclasses.fields(SceneOptions)
            if f.name.startswith("prior_")
        }
        new_options = dataclasses.replace(options, **noise)
        # prior_block works in any frame: its noise does not depend on it.
        return prior_block(new_options, seed, gt), new_options
    raise ValueError(f"unknown variant {variant!r}; allowed: {', '.join(VARIANTS)}")


def make_variant(scene: Path, variant: str, folder: Path) -> Path:
    """A scene folder for ``variant`` under ``folder`` (linked files, new priors)."""
    doc = json.loads((scene / "scene.json").read_text())
    options = SceneOptions.from_json(doc["options"])
    priors, new_options = variant_priors(
        variant,
        read_model(scene / "priors"),
        read_model(scene / "gt"),
        options,
        int(doc["seed"]),
    )
    out = folder / f"{scene.name}_{variant}"
    out.mkdir(parents=True)
    for name in _SHARED:
        os.symlink((scene / name).resolve(), out / name)
    write_absolute_model(out / "priors", priors)
    doc["options"] = new_options.to_json()
    doc["variant"] = variant
    (out / "scene.json").write_text(json.dumps(doc, indent=2) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene_path", required=True, help="synthetic scene folder")
    parser.add_argument("--variant", action="append", choices=VARIANTS, required=True)
    parser.add_argument("--output_path", help="write all rows as JSON here")
    add_run_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    tmp = Path(tempfile.mkdtemp(prefix="bench_variants_"))
    rows = []
    try:
        for variant in args.variant:
            path = make_variant(Path(args.scene_path), variant, tmp)
            row = bench_scene(path, args)
            row["variant"] = variant
            print(f"variant {variant}:")
            print_row(row)
            rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    meta = {"load_average": os.getloadavg(), "args": vars(args)}
    print(f"machine: {meta}")
    if args.output_path:
        Path(args.output_path).write_text(
            json.dumps({"meta": meta, "rows": rows}, indent=2, default=float) + "\n"
        )
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    sys.exit(main())
