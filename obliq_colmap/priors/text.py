"""Plain-text prior files: recognising them, reading and writing them.

Two layouts are read, both one image per line, fields split by white space
or commas (image names therefore hold neither):

- exterior orientation, ``image_name X Y Z omega phi kappa [more columns]``
  with an optional header line naming the columns (Pix4D writes
  ``imageName X Y Z Omega Phi Kappa``); angles in degrees;
- ODM's ``geo.txt``: a first line giving the projection (``EPSG:n``, a
  ``+proj`` string or ``WGS84``), then ``image_name x y z [yaw pitch roll
  ...]``; ODM documents no convention for the angles, so only x, y, z are
  used (for WGS84, x = longitude and y = latitude).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from obliq_colmap.errors import InputError

_SPLIT = re.compile(r"[,\s]+")
OPK_HEADER = "imageName X Y Z Omega Phi Kappa"


@dataclass
class TextPriors:
    """Priors read from a text file.

    Attributes
    ----------
    names : list of N image names.
    xyz : (N, 3) camera centres in ``crs`` (x = easting or longitude).
    opk_deg : (N, 3) omega, phi, kappa in degrees, or None (positions only).
    crs : the file's declared CRS, or None (the map's).
    """

    names: list[str]
    xyz: np.ndarray
    opk_deg: np.ndarray | None
    crs: str | None


def _fields(line: str) -> list[str]:
    return [f for f in _SPLIT.split(line.strip()) if f]


def _is_projection(line: str) -> bool:
    text = line.strip()
    return bool(
        re.fullmatch(r"EPSG:\d+", text, re.IGNORECASE)
        or text.startswith("+proj")
        or text.upper() == "WGS84"
    )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def sniff_text(path: Path, first_line: str) -> str | None:
    """``"opk"``, ``"geo"`` or None for the first non-empty line of ``path``."""
    if _is_projection(first_line):
        return "geo"
    fields = [f.lower() for f in _fields(first_line)]
    if {"omega", "phi", "kappa"} <= set(fields):
        return "opk"
    if len(fields) >= 7 and all(_is_number(f) for f in fields[1:7]):
        return "opk"
    return None


def _rows(path: Path, lines: list[str], ncols: int) -> tuple[list[str], np.ndarray]:
    """Names and the (N, ncols) numbers after each name; InputError names the line."""
    names, values = [], []
    for lineno, line in lines:
        fields = _fields(line)
        if not fields or fields[0].startswith("#"):
            continue
        try:
            if len(fields) < ncols + 1:
                raise ValueError(f"expected {ncols + 1} fields, got {len(fields)}")
            numbers = [float(f) for f in fields[1 : ncols + 1]]
            if not np.all(np.isfinite(numbers)):
                raise ValueError("not a finite number")
        except ValueError as exc:
            raise InputError(path, f"line {lineno}: {exc}: {line.strip()!r}") from None
        names.append(fields[0])
        values.append(numbers)
    if not names:
        raise InputError(path, "no image lines")
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise InputError(path, f"image(s) listed twice: {', '.join(duplicates[:5])}")
    return names, np.asarray(values, float).reshape(-1, ncols)


def _numbered(text: str) -> list[tuple[int, str]]:
    return [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip()]


def read_opk(path: Path, text: str) -> TextPriors:
    """Read an ``image_name X Y Z omega phi kappa`` file (header optional)."""
    lines = _numbered(text)
    if lines and not all(_is_number(f) for f in _fields(lines[0][1])[1:7]):
        lines = lines[1:]  # the header
    names, values = _rows(path, lines, 6)
    return TextPriors(names, values[:, :3], values[:, 3:], None)


def read_geo(path: Path, text: str) -> TextPriors:
    """Read ODM's ``geo.txt`` (projection line, then ``image_name x y z ...``)."""
    lines = _numbered(text)
    crs = lines[0][1].strip()
    names, values = _rows(path, lines[1:], 3)
    return TextPriors(
        names, values, None, "EPSG:4326" if crs.upper() == "WGS84" else crs
    )


def format_opk(names: list[str], xyz: np.ndarray, opk_deg: np.ndarray) -> str:
    """The OPK text file: header, then one line per image (mm and 1e-6 deg).

    ``xyz`` (N, 3) and ``opk_deg`` (N, 3); read back by :func:`read_opk`.
    """
    lines = [OPK_HEADER]
    for name, p, a in zip(names, np.asarray(xyz), np.asarray(opk_deg), strict=True):
        lines.append(
            f"{name} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {a[0]:.8f} {a[1]:.8f} {a[2]:.8f}"
        )
    return "\n".join(lines) + "\n"
