"""ESRI ASCII grid (``.asc``) and its projection file (``.prj``).

The ``.prj`` holds ESRI WKT of the horizontal CRS: written here for the
UTM zones of ETRS89 (EPSG:258NN) and WGS 84 (EPSG:326NN / 327NN), the CRSs of
the maps in use; any other CRS needs pyproj (``pip install pyproj``).
"""

from __future__ import annotations

import re

import numpy as np

from obliq_colmap.errors import InputError

__all__ = ["NODATA", "ascii_grid_text", "esri_wkt"]

#: the grid's NODATA value (heights are never this low).
NODATA = -9999.0

_UTM = {
    "258": ("ETRS_1989", "ETRS_1989", "GRS_1980", "298.257222101", False),
    "326": ("WGS_1984", "WGS_1984", "WGS_1984", "298.257223563", False),
    "327": ("WGS_1984", "WGS_1984", "WGS_1984", "298.257223563", True),
}


def esri_wkt(crs: str | None) -> str:
    """ESRI WKT (one line) of a projected CRS named ``EPSG:NNNNN``.

    Raises
    ------
    InputError
        No CRS, or one that needs pyproj and pyproj is not installed.
    """
    if not crs:
        raise InputError("georef.json", "no CRS: cannot write a .prj")
    m = re.fullmatch(r"EPSG:(258|326|327)(\d\d)", crs)
    if m and 1 <= int(m.group(2)) <= 60:
        gcs, datum, sph, inv_f, south = _UTM[m.group(1)]
        zone = int(m.group(2))
        name = f"{gcs}_UTM_Zone_{zone}{'S' if south else 'N'}"
        return (
            f'PROJCS["{name}",GEOGCS["GCS_{gcs}",DATUM["D_{datum}",'
            f'SPHEROID["{sph}",6378137.0,{inv_f}]],PRIMEM["Greenwich",0.0],'
            'UNIT["Degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
            'PARAMETER["False_Easting",500000.0],'
            f'PARAMETER["False_Northing",{10000000.0 if south else 0.0}],'
            f'PARAMETER["Central_Meridian",{6 * zone - 183:.1f}],'
            'PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],'
            'UNIT["Meter",1.0]]'
        )
    try:
        import pyproj
    except ModuleNotFoundError:
        raise InputError(
            "georef.json",
            f"the CRS {crs} needs pyproj for the .prj: pip install pyproj",
        ) from None
    return pyproj.CRS.from_user_input(crs).to_wkt(pyproj.enums.WKTVersion.WKT1_ESRI)


def ascii_grid_text(
    Z: np.ndarray, xll: float, yll: float, cell: float, decimals: int = 3
) -> str:
    """An ESRI ASCII grid of ``Z`` (ny, nx), row 0 north, NaN as NODATA;
    ``(xll, yll)``: the lower-left corner of the lower-left cell."""
    ny, nx = Z.shape
    head = (
        f"ncols {nx}\nnrows {ny}\nxllcorner {xll:.3f}\nyllcorner {yll:.3f}\n"
        f"cellsize {cell:g}\nNODATA_value {NODATA:g}\n"
    )
    vals = np.where(np.isfinite(Z), np.round(Z, decimals), NODATA)
    rows = [" ".join(f"{v:g}" for v in row) for row in vals]
    return head + "\n".join(rows) + "\n"
