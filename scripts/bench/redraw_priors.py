#!/usr/bin/env python
"""An external scene with its priors drawn again from the truth (issue 25:
does a result hold on other draws of the same flight's errors?).

The shipped ``priors/`` of an external scene are ONE draw of its noise
model; the scenes that judge the project have their own. This writes a copy
of SCENE (every file but ``priors/`` linked, not copied) whose ``priors/``
is a new draw from ``gt/`` with the noise model in ``scene.json``'s
``params``:

* camera centre: the true one plus N(0, ``prior_sigma_h``) east and north,
  N(0, ``prior_sigma_v``) up, plus the priors' vertical datum
  (``datum_offset``);
* rotation: the true one turned by N(0, ``prior_sigma_rot_deg``) about each
  axis;
* per head (camera): PINHOLE, the true focal length times 1 + U(-e, e)
  with e = ``prior_focal_err`` (the shipped draws all lie within +-e),
  the principal point at the image centre, no distortion (as shipped).

Run (from the repository root)::

    python scripts/bench/redraw_priors.py --scene_path SCENE \\
        --output_path DIR/NAME --seed N

then ``scripts/bench/external.py --data_path DIR --scene NAME ...`` on it.
It prints the shipped draw's errors and the new one's, per head.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

NOISE_KEYS = (
    "prior_sigma_h",
    "prior_sigma_v",
    "prior_sigma_rot_deg",
    "prior_focal_err",
    "datum_offset",
)


def draw_priors(
    gt: pycolmap.Reconstruction,
    shipped: pycolmap.Reconstruction,
    noise: dict,
    rng: np.random.Generator,
) -> pycolmap.Reconstruction:
    """A copy of ``shipped`` (its ids, names and cameras) with every pose and
    focal length drawn from ``gt`` with ``noise`` (scene.json's params)."""
    out = pycolmap.Reconstruction(shipped)
    for cid, cam in out.cameras.items():
        true = gt.cameras[cid]
        f = true.params[0] * (1.0 + rng.uniform(-1.0, 1.0) * noise["prior_focal_err"])
        out.cameras[cid] = pycolmap.Camera(
            model="PINHOLE",
            width=cam.width,
            height=cam.height,
            params=[f, f, cam.width / 2, cam.height / 2],
            camera_id=cid,
        )
    by_name = {im.name: im for im in gt.images.values()}
    sigma = np.array(
        [noise["prior_sigma_h"], noise["prior_sigma_h"], noise["prior_sigma_v"]]
    )
    for im in out.images.values():
        true = by_name[im.name]
        centre = true.projection_center() + rng.normal(0.0, sigma)
        centre[2] += noise["datum_offset"]
        turn = Rotation.from_rotvec(
            rng.normal(0.0, np.radians(noise["prior_sigma_rot_deg"]), 3)
        ).as_matrix()
        R = true.cam_from_world().rotation.matrix() @ turn
        im.frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre)
    return out


def errors(priors: pycolmap.Reconstruction, gt: pycolmap.Reconstruction) -> str:
    """One line per head: focal error, median horizontal centre error, mean
    height error (the priors' datum included) and median rotation error."""
    by_name = {im.name: im for im in gt.images.values()}
    lines = []
    for cid in sorted(priors.cameras):
        ims = [im for im in priors.images.values() if im.camera_id == cid]
        dc = [
            np.linalg.norm(
                im.projection_center()[:2] - by_name[im.name].projection_center()[:2]
            )
            for im in ims
        ]
        dz = [
            im.projection_center()[2] - by_name[im.name].projection_center()[2]
            for im in ims
        ]
        dr = [
            np.degrees(
                (
                    im.cam_from_world().rotation
                    * by_name[im.name].cam_from_world().rotation.inverse()
                ).angle()
            )
            for im in ims
        ]
        f = priors.cameras[cid].params[0] / gt.cameras[cid].params[0] - 1.0
        head = ims[0].name.split("_")[0] if ims else "?"
        lines.append(
            f"  head {head} (camera {cid}): focal {100 * f:+.1f} %, centre"
            f" {np.median(dc):.1f} m horizontally, height {np.mean(dz):+.1f} m (mean),"
            f" rotation {np.median(dr):.2f} deg (medians over {len(ims)} images)"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene_path", type=Path, required=True)
    parser.add_argument("--output_path", type=Path, required=True)
    parser.add_argument("--seed", type=int, required=True)
    args = parser.parse_args(argv)
    scene = args.scene_path.resolve()
    try:
        params = json.loads((scene / "scene.json").read_text())["params"]
        noise = {k: float(params[k]) for k in NOISE_KEYS}
        gt = pycolmap.Reconstruction(str(scene / "gt"))
        shipped = pycolmap.Reconstruction(str(scene / "priors"))
    except (OSError, KeyError, ValueError, RuntimeError) as exc:
        print(
            f"{scene}: not an external scene with its noise model ({exc})",
            file=sys.stderr,
        )
        return 2
    out = args.output_path
    if out.exists():
        print(f"{out}: exists; give a new folder", file=sys.stderr)
        return 2
    out.mkdir(parents=True)
    for item in scene.iterdir():
        if item.name != "priors":
            (out / item.name).symlink_to(item)
    priors = draw_priors(gt, shipped, noise, np.random.default_rng(args.seed))
    (out / "priors").mkdir()
    priors.write(str(out / "priors"))
    print(f"{scene.name}, shipped priors:\n{errors(shipped, gt)}")
    print(f"{out.name}, drawn with seed {args.seed}:\n{errors(priors, gt)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
