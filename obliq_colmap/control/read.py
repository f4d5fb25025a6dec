"""One entry for every control-point format: :func:`read_control_points`."""

from __future__ import annotations

from pathlib import Path

from obliq_colmap.errors import InputError

from .gcp_list import read_gcp_list
from .model import DEFAULT_SIGMA_HORIZONTAL_M, DEFAULT_SIGMA_VERTICAL_M, ControlPoints
from .opensfm_json import read_opensfm_json


def read_control_points(
    path: str | Path,
    image_sizes: dict[str, tuple[int, int]] | None = None,
    crs: str | None = None,
    sigma_horizontal_m: float = DEFAULT_SIGMA_HORIZONTAL_M,
    sigma_vertical_m: float = DEFAULT_SIGMA_VERTICAL_M,
) -> ControlPoints:
    """Read control points, the format recognised by content.

    A file whose first non-blank character is ``{`` is OpenSfM's
    ``ground_control_points.json`` (it needs ``image_sizes``: name -> (w, h),
    from the model); anything else is a ``gcp_list.txt``. Coordinates end in
    ``crs`` (the map's), else the file's projected CRS, else the UTM zone of
    geographic coordinates.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "control point file not found")
    try:
        head = path.read_bytes()[:4096].decode("utf-8-sig", errors="replace").lstrip()
    except OSError as exc:
        raise InputError(path, f"cannot read the control points: {exc}") from None
    if head.startswith("{"):
        return read_opensfm_json(
            path, image_sizes or {}, crs, sigma_horizontal_m, sigma_vertical_m
        )
    return read_gcp_list(path, crs, sigma_horizontal_m, sigma_vertical_m)
