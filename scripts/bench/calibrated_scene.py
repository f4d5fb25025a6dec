"""A synthetic scene as a calibrated camera system would deliver it.

Not a measurement itself: it makes the scene copies that the calibrated and
PPK runs of ``bench/seeds.py`` (and ``register``) measure. Copies
``--scene_path`` (``obliq-colmap synth`` output) to ``--output_path`` with
the priors' cameras replaced by the truth's (focal length, principal point
and distortion of each head: a calibration report) and the focal-error
option of ``scene.json`` set to 0; with ``--rotation_sigma_deg S`` also each
prior rotation replaced by the true one turned by a random rotation vector
of S degrees per axis (a calibrated INS; the prior centres stay as they are,
and so does ``scene.json``'s rotation noise, which sets stage 2's search);
with ``--position_sigma_m S`` each prior centre replaced by the true one plus
the scene's vertical datum offset plus normal noise of S metres per axis
(survey-grade GNSS, PPK; ``scene.json``'s position noise, which sets stage
2's search, stays), shifted by ``--position_offset_m DX DY DZ`` (a GNSS frame
off the map's, a lever arm left out). Everything else (images, map, truth)
is linked, not copied.

Run (from the repository root)::

    python scripts/bench/calibrated_scene.py --scene_path /work/scenes/paper_s1 \\
        --output_path /work/scenes/paper_s1_cal [--rotation_sigma_deg 0.01]
    python scripts/bench/seeds.py --scene_path /work/scenes/paper_s1_cal \\
        --set registration.refine_focal=False \\
        --set adjustment.bundle.refine_focal_length=False \\
        --set adjustment.bundle.refine_principal_point=False \\
        [--set adjustment.bundle.rotation_prior_sigma_deg=0.01] \\
        [--set adjustment.bundle.position_prior_sigma_m=0.1]

(``register``: the same priors with ``--refine_focal_length 0
--refine_principal_point 0 [--bundle_rotation_sigma 0.01]
[--bundle_position_sigma 0.1]``.)

Figures (of the runs on its copies): docs/journal/stage3-bundle.md (issue 5,
the calibrated and GNSS runs).

Data: a synthetic scene (``obliq-colmap synth``) or an external scene
(``../shared/data/external_oblique/S``: its ``scene.json`` has ``params``
with the priors' ``datum_offset`` instead of ``options``); writes the copy
to ``--output_path``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from obliq_colmap.colmap_io import read_model, write_absolute_model
from obliq_colmap.geometry import Pose


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene_path", required=True, type=Path)
    parser.add_argument("--output_path", required=True, type=Path)
    parser.add_argument("--rotation_sigma_deg", type=float)
    parser.add_argument("--position_sigma_m", type=float)
    parser.add_argument(
        "--position_offset_m", type=float, nargs=3, default=(0.0, 0.0, 0.0)
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--keep_cameras",
        action="store_true",
        help="keep the priors' (uncalibrated) cameras: an INS-grade attitude alone",
    )
    args = parser.parse_args(argv)
    src, dst = args.scene_path.resolve(), args.output_path
    if not (src / "scene.json").is_file():
        print(f"error: {src}: not a synthetic scene (no scene.json)", file=sys.stderr)
        return 2
    if (dst / "priors").exists():
        print(f"error: {dst / 'priors'} exists", file=sys.stderr)
        return 2
    meta = json.loads((src / "scene.json").read_text())
    datum_offset = _datum_offset(meta)
    if datum_offset is None:
        print(
            f"error: {src / 'scene.json'}: no priors' datum offset (neither"
            " options.prior_vertical_datum_offset_m nor params.datum_offset)",
            file=sys.stderr,
        )
        return 2
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("images", "gt", "cadastre.geojson", "gt_buildings.json"):
        if (src / name).exists() and not (dst / name).exists():
            (dst / name).symlink_to(src / name)
    priors, truth = read_model(src / "priors"), read_model(src / "gt")
    cameras = {
        i: dataclasses.replace(truth.cameras[i], camera_id=i) for i in priors.cameras
    }
    images = dict(priors.images)
    if args.keep_cameras:
        cameras = priors.cameras
    elif "options" in meta:
        meta["options"]["prior_focal_percent"] = 0.0
    else:
        meta["params"]["prior_focal_err"] = 0.0
    if args.rotation_sigma_deg is not None:
        rng = np.random.default_rng(args.seed)
        for i, image in images.items():
            true = truth.image_by_name(image.name).cam_from_world.rotation
            turn = Rotation.from_rotvec(
                np.radians(rng.normal(0.0, args.rotation_sigma_deg, 3))
            ).as_matrix()
            pose = Pose.from_center(turn @ true, image.cam_from_world.center)
            images[i] = dataclasses.replace(image, cam_from_world=pose)
    if args.position_sigma_m is not None:
        rng = np.random.default_rng([args.seed, 1])
        datum = np.array([0.0, 0.0, datum_offset])
        datum = datum + np.asarray(args.position_offset_m)
        for i, image in images.items():
            true = truth.image_by_name(image.name).cam_from_world.center
            centre = true + datum + rng.normal(0.0, args.position_sigma_m, 3)
            pose = Pose.from_center(image.cam_from_world.rotation, centre)
            images[i] = dataclasses.replace(image, cam_from_world=pose)
    write_absolute_model(
        dst / "priors", dataclasses.replace(priors, cameras=cameras, images=images)
    )
    (dst / "scene.json").write_text(json.dumps(meta, indent=1))
    kind = "prior" if args.keep_cameras else "calibrated"
    print(f"wrote {dst}: {len(cameras)} {kind} cameras")
    return 0


def _datum_offset(meta: dict) -> float | None:
    """The priors' vertical datum offset (m) of a scene.json: ours or the
    external scenes' format; None where it has neither."""
    if "options" in meta:
        return meta["options"].get("prior_vertical_datum_offset_m")
    return (meta.get("params") or {}).get("datum_offset")


if __name__ == "__main__":
    sys.exit(main())
