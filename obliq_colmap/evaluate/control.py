"""Check points for real data: control points triangulated in ANY model and
scored against their given coordinates (``evaluate --control_points_path``).

The model is ours (a local frame with ``georef.json``: the points are
brought into it with its origin and CRS) or another tool's (taken as being
in the points' CRS already, absolute coordinates). Per point: the
triangulated-minus-given offset in metres (horizontal, vertical) and the
reprojection of the GIVEN position into the images that observe it, minus
the measurement (px), the way real projects are checked.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from obliq_colmap.colmap_io import GEOREF_FILE, read_georef
from obliq_colmap.control.read import read_control_points
from obliq_colmap.control.residuals import point_residuals, summarise
from obliq_colmap.control.triangulate import require_usable, triangulate_control_points
from obliq_colmap.errors import InputError

logger = logging.getLogger(__name__)


def evaluate_control_points(
    model_path: str | Path,
    control_points_path: str | Path,
    check_points: tuple[str, ...] = (),
) -> dict:
    """The report (dict) of the control points' residuals in a model.

    ``check_points``: the names reported as check points (default: all of
    them; the others are reported as control points, i.e. used to make the
    model).
    """
    model_path = Path(model_path)
    try:
        rec = pycolmap.Reconstruction(str(model_path))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises bare errors
        raise InputError(model_path, f"not a readable COLMAP model: {exc}") from None
    origin, crs = np.zeros(3), None
    if (model_path / GEOREF_FILE).is_file():
        georef = read_georef(model_path)
        origin, crs = np.asarray(georef.origin, float), georef.crs
    sizes = {
        rec.images[i].name: (rec.images[i].camera.width, rec.images[i].camera.height)
        for i in rec.reg_image_ids()
    }
    control = read_control_points(control_points_path, sizes, crs)
    unknown = sorted(set(check_points) - set(control.names()))
    if unknown:
        raise InputError(
            control_points_path, f"--check_points names {', '.join(unknown)}: not in it"
        )
    tri = triangulate_control_points(rec, control)
    require_usable(tri, 1, control_points_path)
    given = control.xyz() - origin
    roles = {
        n: "check" if not check_points or n in check_points else "control"
        for n in control.names()
    }
    rows = point_residuals(rec, control, tri, given, tri.xyz, roles)
    return {
        "model": str(model_path),
        "control_points_path": str(control_points_path),
        "crs": control.crs,
        "check_points": summarise(rows, "check"),
        "control_points": summarise(rows, "control"),
        "points": rows,
    }


def format_control_table(report: dict) -> str:
    """The per-point table and the summary, as Markdown."""
    lines = [
        "| point | role | obs | horizontal m | vertical m | mean px |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["points"]:
        v = "-" if r["vertical_m"] is None else f"{r['vertical_m']:+.3f}"
        px = r["mean_reprojection_px"]
        lines.append(
            f"| {r['name']} | {r['role']} | {r['num_observations']} | "
            f"{r['horizontal_m']:.3f} | {v} | {'-' if px is None else f'{px:.2f}'} |"
        )
    for role in ("check_points", "control_points"):
        s = report[role]
        if s.get("num_points"):
            v, px = s["vertical_m_median"], s["reprojection_px_median"]
            lines.append(
                f"\n{role.replace('_', ' ')}: {s['num_points']}, horizontal median "
                f"{s['horizontal_m_median']:.3f} m (RMS {s['horizontal_m_rms']:.3f}), "
                f"vertical median {'-' if v is None else f'{v:.3f}'} m, "
                f"{'-' if px is None else f'{px:.2f}'} px median"
            )
    return "\n".join(lines)
