"""Benchmark of ``obliq-colmap export_dense`` against ground truth (issue 28).

    PYTHONPATH=. .venv/bin/python scripts/bench/dense_export.py \\
        [--input_path OUT_MODEL] [--scene data_samples/oblique_small] \\
        [--output_path R.json] [--strip IMAGE ...]

OUT_MODEL is ``register``'s result on SCENE (a synthetic scene: its true
cameras and city give each image's true depth map; an external scene: the
true depths of the building corners visible in each image); without it ``register``
is run on SCENE into a temporary folder. Measured per image, on the written
workspace (``dense.json`` and :func:`check_workspace`):

* its own points (in front of it) and the support points added;
* coverage: the share of its pixels that see the scene whose TRUE depth lies
  inside the depth range COLMAP will search (from the workspace's points);
  a pixel outside cannot get a correct depth from patch_match_stereo;
* slack: the range's width over the true depths' 1-99 % span (1 = tight;
  COLMAP widens its own range by 25 % on each side);
* the number of source images; and the export's wall time.

``--strip`` removes the named images' observations first, to measure the
depth-range support (:mod:`obliq_colmap.dense.support`) against the truth.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from obliq_colmap.cli import main as cli_main
from obliq_colmap.colmap_io import read_georef, read_model, write_result
from obliq_colmap.dense import DenseOptions, export_dense
from obliq_colmap.dense.check import check_workspace
from obliq_colmap.dense.support import read_points
from obliq_colmap.synthetic import load_scene


def true_depths(scene_path: Path):
    """name -> (K,) true depths of what the image sees: the depth map of a
    scene of ours, else (external scenes) the true depths of the building
    corners ``gt_visibility.json`` lists as visible in the true image."""
    vis_file = scene_path / "gt_visibility.json"
    if not vis_file.is_file():
        scene = load_scene(scene_path)

        def of_scene(name: str) -> np.ndarray:
            depth = scene.depth(name)
            return depth[np.isfinite(depth)]

        return of_scene
    visible = json.loads(vis_file.read_text())["images"]
    corners = np.array(
        json.loads((scene_path / "gt_buildings.json").read_text())["corners"]
    )
    gt = read_model(scene_path / "gt")

    def of_corners(name: str) -> np.ndarray:
        pose = gt.image_by_name(name).cam_from_world
        return pose.transform(corners[np.asarray(visible[name], int)])[:, 2]

    return of_corners


def measure(workspace: Path, scene_path: Path) -> dict:
    """Per image and overall figures (see the module docstring)."""
    depths = true_depths(scene_path)
    check = check_workspace(workspace)
    table = json.loads((workspace / "dense.json").read_text())["images"]
    rows = {}
    for name, row in table.items():
        d = depths(name)
        r = {
            "status": row["status"],
            "own": row["num_points_own"],
            "support": row["num_points_support"],
            "sources": len(row["source_images"]),
        }
        if name in check.depth_range:
            lo, hi = check.depth_range[name]
            p1, p99 = np.percentile(d, [1, 99])
            r.update(
                depth_range_m=[round(lo, 1), round(hi, 1)],
                true_depth_p1_p99_m=[round(float(p1), 1), round(float(p99), 1)],
                coverage=round(float(np.mean((d >= lo) & (d <= hi))), 5),
                # the same without COLMAP's 25 % widening: what the points span
                coverage_points=round(
                    float(np.mean((d >= lo / 0.75) & (d <= hi / 1.25))), 5
                ),
                slack=round(float((hi - lo) / (p99 - p1)), 2),
            )
        rows[name] = r
    kept = [r for r in rows.values() if r["status"] == "kept"]
    cov = np.array([r["coverage"] for r in kept])
    return {
        "num_images": len(rows),
        "num_kept": len(kept),
        "workspace_ok": check.ok,
        "problems": check.problems,
        "own_points_min_median": [
            int(min(r["own"] for r in rows.values())),
            float(np.median([r["own"] for r in rows.values()])),
        ],
        "coverage_min_median": [float(cov.min()), float(np.median(cov))],
        "coverage_points_min_median": [
            float(min(r["coverage_points"] for r in kept)),
            float(np.median([r["coverage_points"] for r in kept])),
        ],
        "slack_median": float(np.median([r["slack"] for r in kept])),
        "images": rows,
    }


def strip_images(model: Path, names: list[str], out: Path) -> Path:
    """The model with every observation in the images ``names`` removed
    (as if register had left them without points), written to ``out``."""
    import pycolmap

    block = read_model(model)
    ids = {block.image_by_name(n).image_id for n in names}
    points = []
    for p in read_points(pycolmap.Reconstruction(str(model))):
        p.observations = [(i, xy) for i, xy in p.observations if i not in ids]
        if p.observations:
            points.append(p)
    return write_result(out, block, read_georef(model), points)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input_path", type=Path)
    parser.add_argument(
        "--scene", type=Path, default=Path("data_samples/oblique_small")
    )
    parser.add_argument("--output_path", type=Path)
    parser.add_argument("--image_path", type=Path, help="default SCENE/images")
    parser.add_argument(
        "--min_track_length", type=int, default=DenseOptions.min_track_length
    )
    parser.add_argument(
        "--strip", nargs="*", default=[], help="images to strip of their points"
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        model = args.input_path
        if model is None:
            model = Path(tmp) / "model"
            cli_main(
                [
                    "register",
                    "--image_path", str(args.scene / "images"),
                    "--cadastre_path", str(args.scene / "cadastre.geojson"),
                    "--input_path", str(args.scene / "priors"),
                    "--output_path", str(model),
                ]
            )  # fmt: skip
        if args.strip:
            model = strip_images(model, args.strip, Path(tmp) / "stripped")
        t0 = time.perf_counter()
        export_dense(
            model,
            args.image_path or args.scene / "images",
            Path(tmp) / "dense",
            DenseOptions(min_track_length=args.min_track_length),
        )
        seconds = time.perf_counter() - t0
        result = {
            "export_s": round(seconds, 2),
            **measure(Path(tmp) / "dense", args.scene),
        }
    text = json.dumps(result, indent=2)
    if args.output_path:
        args.output_path.write_text(text + "\n")
    brief = {k: v for k, v in result.items() if k != "images"}
    print(json.dumps(brief, indent=2))
    return 0 if result["workspace_ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
