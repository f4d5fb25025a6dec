"""Positions and attitude from the XMP packet that drones write into images.

DJI (and survey cameras following its tags) write ``drone-dji:GpsLatitude``,
``GpsLongitude``, ``AbsoluteAltitude`` and the gimbal's ``GimbalYawDegree``
(clockwise from north), ``GimbalPitchDegree`` (0 horizontal, -90 nadir) and
``GimbalRollDegree`` into an XMP packet near the start of the JPEG. The map
grid is taken as east, north, up: the grid's meridian convergence (under a
degree within a UTM zone) stays in the rotation prior's error.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from obliq_colmap.errors import InputError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".tif", ".tiff")
#: XMP packets sit in the first APP1 segments; 256 KiB covers DJI's.
_HEAD_BYTES = 1 << 18
_TAG = re.compile(rb'drone-dji:(\w+)(?:="([^"]*)"|>([^<]*)<)')
_POSITION = ("GpsLatitude", "GpsLongitude", "AbsoluteAltitude")
_ATTITUDE = ("GimbalYawDegree", "GimbalPitchDegree", "GimbalRollDegree")


@dataclass
class ExifPriors:
    """Priors of a folder of images.

    Attributes
    ----------
    names : N image names; xyz : (N, 3) longitude, latitude, altitude.
    rotations : (N, 3, 3) cam_from_world in east, north, up.
    """

    names: list[str]
    xyz: np.ndarray
    rotations: np.ndarray


def xmp_tags(path: Path) -> dict[str, str]:
    """The ``drone-dji:`` tags of an image (empty when it has none)."""
    with path.open("rb") as f:
        head = f.read(_HEAD_BYTES)
    tags = {}
    for m in _TAG.finditer(head):
        value = m.group(2) if m.group(2) is not None else m.group(3)
        tags[m.group(1).decode()] = value.decode(errors="replace").strip()
    # Early DJI firmware spelled it "GpsLongtitude".
    if "GpsLongitude" not in tags and "GpsLongtitude" in tags:
        tags["GpsLongitude"] = tags["GpsLongtitude"]
    return tags


def cam_from_world_from_gimbal(ypr_deg: np.ndarray) -> np.ndarray:
    """(N, 3) gimbal yaw, pitch, roll (deg) -> (N, 3, 3) cam_from_world (E, N, U).

    The rows are the camera axes: z (view) = (sin y cos p, cos y cos p, sin p),
    x (right) = (cos y, -sin y, 0) before roll, y = z x x; a positive roll
    turns x towards y (the right side goes down).
    """
    a = np.radians(np.asarray(ypr_deg, float).reshape(-1, 3))
    yaw, pitch, roll = a[:, 0], a[:, 1], a[:, 2]
    z = np.column_stack(
        [np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)]
    )
    x = np.column_stack([np.cos(yaw), -np.sin(yaw), np.zeros_like(yaw)])
    y = np.cross(z, x)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    x, y = c * x + s * y, c * y - s * x
    return np.stack([x, y, z], axis=1)


def _numbers(tags: dict[str, str], keys: tuple[str, ...]) -> list[float] | None:
    try:
        return [float(tags[k]) for k in keys]
    except (KeyError, ValueError):
        return None


def has_xmp_priors(folder: Path) -> bool:
    """True when the first image of ``folder`` carries a drone position."""
    first = next(iter(_images(folder)), None)
    return first is not None and _numbers(xmp_tags(first), _POSITION) is not None


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)


def read_xmp_folder(folder: Path) -> ExifPriors:
    """Read every image's position and gimbal attitude; images lacking them
    are named in one InputError (a block half without priors is a mistake)."""
    names, xyz, ypr, missing = [], [], [], []
    for path in _images(folder):
        tags = xmp_tags(path)
        position, attitude = _numbers(tags, _POSITION), _numbers(tags, _ATTITUDE)
        if position is None or attitude is None:
            missing.append(path.name)
            continue
        names.append(path.name)
        xyz.append([position[1], position[0], position[2]])  # lon, lat, alt
        ypr.append(attitude)
    if missing:
        raise InputError(
            folder,
            f"{len(missing)} image(s) without drone-dji GPS and gimbal tags: "
            f"{', '.join(missing[:5])}",
        )
    if not names:
        raise InputError(folder, "no images")
    return ExifPriors(
        names, np.asarray(xyz, float), cam_from_world_from_gimbal(np.asarray(ypr))
    )
