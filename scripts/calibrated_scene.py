"""A synthetic scene as a calibrated camera system would deliver it.

Copies ``--scene_path`` (``obliq-colmap synth`` output) to ``--output_path``
with the priors' cameras replaced by the truth's (focal length, principal
point and distortion of each head: a calibration report), the focal-error
option of ``scene.json`` set to 0, and everything else (images, map, the
priors' poses, the truth) linked, not copied. Used for the calibrated-heads
runs in docs/BENCHMARKS.md (issue 5):

    python scripts/calibrated_scene.py --scene_path /work/scenes/paper_s1 \\
        --output_path /work/scenes/paper_s1_cal
    python scripts/bench_seeds.py --scene_path /work/scenes/paper_s1_cal \\
        --set registration.refine_focal=False \\
        --set adjustment.bundle.refine_focal_length=False \\
        --set adjustment.bundle.refine_principal_point=False

(``register``: the same priors with ``--refine_focal_length 0
--refine_principal_point 0``.)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pycolmap


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene_path", required=True, type=Path)
    parser.add_argument("--output_path", required=True, type=Path)
    args = parser.parse_args(argv)
    src, dst = args.scene_path.resolve(), args.output_path
    if not (src / "scene.json").is_file():
        print(f"error: {src}: not a synthetic scene (no scene.json)", file=sys.stderr)
        return 2
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("images", "gt", "cadastre.geojson", "gt_buildings.json"):
        if (src / name).exists() and not (dst / name).exists():
            (dst / name).symlink_to(src / name)
    priors = pycolmap.Reconstruction(str(src / "priors"))
    truth = pycolmap.Reconstruction(str(src / "gt"))
    for camera_id, camera in priors.cameras.items():
        camera.params = truth.cameras[camera_id].params
    (dst / "priors").mkdir(exist_ok=True)
    priors.write(str(dst / "priors"))
    meta = json.loads((src / "scene.json").read_text())
    meta["options"]["prior_focal_percent"] = 0.0
    (dst / "scene.json").write_text(json.dumps(meta, indent=1))
    print(f"wrote {dst}: {len(priors.cameras)} calibrated cameras")
    return 0


if __name__ == "__main__":
    sys.exit(main())
