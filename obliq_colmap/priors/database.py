"""Position priors from a COLMAP database, read with sqlite3.

The ``pose_priors`` table changed between COLMAP versions:

- 3.9 to 3.11: ``(image_id, position, coordinate_system, position_covariance)``;
- 4.x: ``(pose_prior_id, corr_data_id, corr_sensor_id, corr_sensor_type,
  position, position_covariance, gravity, coordinate_system)``, where a
  camera sensor's data id is the image id.

``position`` is three float64; ``coordinate_system`` is -1 undefined,
0 WGS84 (latitude, longitude, altitude: note latitude FIRST) or 1 Cartesian.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from obliq_colmap.errors import InputError
from obliq_colmap.geometry import SUPPORTED_MODELS, Camera

WGS84, CARTESIAN = 0, 1
SENSOR_CAMERA = 0
SQLITE_MAGIC = b"SQLite format 3\x00"


@dataclass
class DatabasePriors:
    """Position priors of a database.

    Attributes
    ----------
    names : N image names; camera_ids : N camera ids.
    xyz : (N, 3) positions, x = easting/longitude first.
    crs : "EPSG:4326" for WGS84 priors, None for Cartesian/undefined.
    cameras : camera_id -> Camera (perspective models only).
    """

    names: list[str]
    camera_ids: list[int]
    xyz: np.ndarray
    crs: str | None
    cameras: dict[int, Camera]


def _columns(con: sqlite3.Connection, table: str) -> set[str]:
    return {row[1] for row in con.execute(f"PRAGMA table_info({table})")}


def _prior_rows(con: sqlite3.Connection, path: Path) -> list[tuple]:
    """(image_id, position blob, coordinate_system) of every image's prior."""
    columns = _columns(con, "pose_priors")
    if "corr_data_id" in columns:  # COLMAP 4.x
        return con.execute(
            "SELECT corr_data_id, position, coordinate_system FROM pose_priors "
            "WHERE corr_sensor_type = ?",
            (SENSOR_CAMERA,),
        ).fetchall()
    if "image_id" in columns:  # COLMAP 3.9-3.11
        return con.execute(
            "SELECT image_id, position, coordinate_system FROM pose_priors"
        ).fetchall()
    raise InputError(path, "COLMAP database without a pose_priors table")


def read_cameras_table(con: sqlite3.Connection, path: Path) -> dict[int, Camera]:
    """The perspective cameras of a database's ``cameras`` table."""
    import pycolmap

    names = {int(v): k for k, v in pycolmap.CameraModelId.__members__.items()}
    cameras = {}
    for cid, model_id, width, height, blob in con.execute(
        "SELECT camera_id, model, width, height, params FROM cameras"
    ):
        model = names.get(int(model_id), str(model_id))
        if model not in SUPPORTED_MODELS:
            raise InputError(
                path,
                f"camera {cid} has model {model}; supported perspective models: "
                f"{', '.join(SUPPORTED_MODELS)}",
            )
        params = np.frombuffer(blob, dtype="<f8")
        cameras[int(cid)] = Camera(model, int(width), int(height), params, int(cid))
    return cameras


def read_database(path: Path) -> DatabasePriors:
    """Read the images with a position prior from a COLMAP database."""
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master")}
            if "pose_priors" not in tables or "images" not in tables:
                raise InputError(path, "COLMAP database without pose_priors/images")
            rows = _prior_rows(con, path)
            images = {
                int(i): (n, int(c))
                for i, n, c in con.execute(
                    "SELECT image_id, name, camera_id FROM images"
                )
            }
            cameras = read_cameras_table(con, path)
        finally:
            con.close()
    except sqlite3.DatabaseError as exc:
        raise InputError(path, f"cannot read the COLMAP database: {exc}") from None
    rows = [r for r in rows if r[1] is not None and int(r[0]) in images]
    if not rows:
        raise InputError(path, "the database holds no position priors of its images")
    systems = {int(r[2]) for r in rows}
    if len(systems) > 1:
        raise InputError(path, f"priors in mixed coordinate systems {sorted(systems)}")
    xyz = np.array([np.frombuffer(r[1], dtype="<f8")[:3] for r in rows], float)
    # COLMAP 4 writes NaN positions for priors that carry only gravity.
    keep = np.all(np.isfinite(xyz), axis=1)
    rows, xyz = [r for r, k in zip(rows, keep, strict=True) if k], xyz[keep]
    if not rows:
        raise InputError(path, "the database's pose priors hold no positions")
    crs = None
    if systems == {WGS84}:
        xyz = xyz[:, [1, 0, 2]]  # lat, lon, alt -> lon, lat, alt
        crs = "EPSG:4326"
    ids = [int(r[0]) for r in rows]
    return DatabasePriors(
        [images[i][0] for i in ids], [images[i][1] for i in ids], xyz, crs, cameras
    )
