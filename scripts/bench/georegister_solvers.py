"""Both solvers of georegister's block adjustment on the same block, in one
process (issue 27 item 4: the project's bundle checked against Ceres).

:func:`compare_solvers` runs ``georegister`` once with the adjustment's
inputs captured (the model just before it, the control points' priors, the
verticals, the map rows and the priors' centres: whatever the run passes),
then adjusts copies of that model with each solver in turn, alternating,
``repeats`` times each: the wall times (medians, and their ratio) and how
far apart the two optima are (cost, camera centres, rotations, intrinsics,
points). The covariance is left out of the timed runs (Ceres computes
none); ``function_tolerance`` tightens both solvers' stop alike.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pycolmap

import obliq_colmap.georegister.run as georegister_run
import obliq_colmap.georegister.run_automatic as georegister_automatic
from obliq_colmap.georegister.block import BlockAdjustmentOptions, adjust_block
from obliq_colmap.georegister.options import GeoregisterOptions

#: the modules whose ``adjust_block`` the capture replaces (control points;
#: the automatic mode)
_RUNS = (georegister_run, georegister_automatic)


@dataclasses.dataclass
class BlockInputs:
    """Everything ``adjust_block`` got in one georegister run."""

    rec: pycolmap.Reconstruction  # a copy from before the adjustment
    control: dict
    verticals: dict
    #: the options the run passed (the automatic mode's block placement
    #: sets the map rows' sd from their range: not the command's options)
    block: BlockAdjustmentOptions
    kwargs: dict  # map_rows, prior_centers as the run passed them


def capture_block_inputs(
    input_path: Path, image_path: Path, options: GeoregisterOptions
) -> BlockInputs:
    """georegister's block adjustment inputs on this block."""
    captured: list[BlockInputs] = []
    original = adjust_block

    def capture(rec, control, verticals, block_options, *args, **kwargs):
        # a copy before the solve changes it; the run itself goes on as usual
        names = ("map_rows", "prior_centers")
        kw = dict(zip(names, args, strict=False)) | kwargs
        captured.append(
            BlockInputs(
                pycolmap.Reconstruction(rec), control, verticals, block_options, kw
            )
        )
        return original(rec, control, verticals, block_options, **kw)

    # the bench patches the runs' references only: no hook in the product
    for module in _RUNS:
        module.adjust_block = capture
    try:
        run = georegister_run.georegister
        run(input_path, image_path, dataclasses.replace(options, progress=False))
    finally:
        for module in _RUNS:
            module.adjust_block = original
    if not captured:
        raise RuntimeError("georegister ran no block adjustment")
    return captured[-1]


def _state(rec: pycolmap.Reconstruction) -> dict:
    ids = sorted(rec.reg_image_ids())
    pids = sorted(rec.point3D_ids())
    return {
        "centres": np.array([rec.images[i].projection_center() for i in ids]),
        "rotations": np.array(
            [rec.images[i].cam_from_world().rotation.matrix() for i in ids]
        ),
        "params": {c: np.array(cam.params) for c, cam in rec.cameras.items()},
        "points": np.array([rec.points3D[p].xyz for p in pids]).reshape(-1, 3),
    }


def compare_solvers(
    input_path: Path,
    image_path: Path,
    options: GeoregisterOptions,
    repeats: int = 3,
    function_tolerance: float | None = None,
) -> dict:
    """Both solvers on the same captured block; times and the optima's
    differences (see the module docstring). ``function_tolerance``: both
    solvers' stop (None: the options')."""
    inputs = capture_block_inputs(input_path, image_path, options)
    block = dataclasses.replace(inputs.block, covariance=False)
    if function_tolerance is not None:
        block = dataclasses.replace(block, function_tolerance=function_tolerance)
    kwargs = dict(inputs.kwargs)  # the map rows with their facade rows
    times = {"obliq": [], "ceres": []}
    summaries, states = {}, {}
    for _ in range(repeats):
        for solver in ("obliq", "ceres"):
            rec = pycolmap.Reconstruction(inputs.rec)
            t0 = time.perf_counter()
            summaries[solver] = adjust_block(
                rec,
                inputs.control,
                inputs.verticals,
                dataclasses.replace(block, solver=solver),
                **kwargs,
            )
            times[solver].append(time.perf_counter() - t0)
            states[solver] = _state(rec)
    a, b = states["obliq"], states["ceres"]
    dR = [
        np.degrees(abs(pycolmap.Rotation3d(ra @ rb.T).angle()))
        for ra, rb in zip(a["rotations"], b["rotations"], strict=True)
    ]
    start = _state(inputs.rec)
    moved = np.linalg.norm(a["centres"] - start["centres"], axis=1)
    med = {s: float(np.median(t)) for s, t in times.items()}
    rows = inputs.kwargs.get("map_rows")
    return {
        "num_images": inputs.rec.num_reg_images(),
        "num_points": inputs.rec.num_points3D(),
        "num_observations": int(
            sum(p.track.length() for p in inputs.rec.points3D.values())
        ),
        "num_map_rows": 0 if rows is None else len(rows),
        "num_facade_rows": {s: v.num_facade_rows for s, v in summaries.items()},
        "num_facade_tracks": {s: v.num_facade_tracks for s, v in summaries.items()},
        "function_tolerance": block.function_tolerance,
        "time_s": med,
        "time_s_all": times,
        "time_ratio_obliq_over_ceres": med["obliq"] / med["ceres"],
        "summaries": {s: v.report() for s, v in summaries.items()},
        "initial_cost_relative_difference": (
            summaries["obliq"].initial_cost / summaries["ceres"].initial_cost - 1.0
        ),
        "final_cost_relative_difference": (
            summaries["obliq"].final_cost / summaries["ceres"].final_cost - 1.0
        ),
        "centre_moved_by_adjustment_m_median": float(np.median(moved)),
        "centre_difference_m_max": float(
            np.max(np.linalg.norm(a["centres"] - b["centres"], axis=1))
        ),
        "mean_camera_height_difference_m": float(
            np.mean(a["centres"][:, 2]) - np.mean(b["centres"][:, 2])
        ),
        "rotation_difference_deg_max": float(np.max(dR)),
        "point_difference_m_max": float(
            np.max(np.linalg.norm(a["points"] - b["points"], axis=1), initial=0.0)
        ),
        "params_difference_max": {
            int(c): float(np.max(np.abs(a["params"][c] - b["params"][c])))
            for c in a["params"]
        },
    }
